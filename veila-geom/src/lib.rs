//! # veila-geom
//!
//! The geometry under Veila, with no IO and no neural-network dependency (only `glam`, `serde` and
//! `thiserror`):
//!
//! - [`LidarSensor`]: spinning-LiDAR models, uniform or with a per-beam elevation table, with the
//!   presets [`LidarSensor::hdl64e`] (KITTI / SemanticKITTI) and [`LidarSensor::hdl32e`] (nuScenes),
//!   named by [`SensorPreset`] (the one list of presets every door offers).
//! - [`Projector`]: spherical projection of point clouds into [`RangeImage`]s (equation 1 of the
//!   paper), nearest point wins, rejected points counted by reason.
//! - [`RayTable`]: the unit ray of every range pixel (the inverse of equation 1) and unprojection.
//! - [`PinholeCamera`]: `K` (3x4) and `T` (camera from LiDAR) from KITTI or nuScenes calibration,
//!   with [`PinholeCamera::try_project`] that never returns a mirrored pixel.
//! - [`EpipolarTable`]: the image positions of `K` samples along every LiDAR ray, for GCMA.
//! - [`flat_ground_depth_map_m`] / [`try_flat_ground_depth_m`]: the flat-ground prior, the camera
//!   depth at which each pixel's ray meets a level ground plane of the LiDAR frame (0 / `None` at
//!   and above the horizon), and [`flat_ground_range_image`], the same plane on a LiDAR grid.
//! - [`FourierEncoding`] and the paper's front/rear [`Region`] split.
//!
//! Frames: LiDAR x forward, y left, z up; camera x right, y down, z forward; metres and radians unless a
//! name says `_deg`.
//!
//! ```
//! use glam::Vec3;
//! use veila_geom::{LidarSensor, ProjectionOptions, Projector, RayTable};
//!
//! let sensor = LidarSensor::hdl64e();
//! let projector = Projector::new(&sensor, ProjectionOptions::default())?;
//! let points = [Vec3::new(10.0, 0.5, -1.0), Vec3::new(-5.0, 3.0, 0.0), Vec3::new(f32::NAN, 0.0, 0.0)];
//! let (image, stats) = projector.project(&points, None, None)?;
//! assert_eq!(stats.written, 2);
//! assert_eq!(stats.rejected.non_finite, 1);
//!
//! // back to points: each lies on its pixel's centre ray at the measured range
//! let rays = RayTable::new(&sensor)?;
//! let back = rays.unproject(&image)?;
//! assert_eq!(back.points.len(), 2);
//! for (q, (row, col)) in back.points.iter().zip(&back.pixels) {
//!     let src = points[image.point_index[image.idx(*row, *col)] as usize];
//!     assert!((q.length() - src.length()).abs() < 1e-4); // same range
//!     assert!(q.angle_between(src) < 0.01); // within one pixel's angular size
//! }
//! # Ok::<(), veila_geom::GeomError>(())
//! ```

mod camera;
mod epipolar;
mod error;
pub mod fastmath;
mod fourier;
mod ground;
mod projection;
mod rays;
mod region;
mod sensor;

pub use camera::{ImagePoint, MAX_CAMERA_OFFSET_M, PinholeCamera};
pub use epipolar::{BilinearGather, DepthSpacing, EpipolarConfig, EpipolarTable};
pub use error::GeomError;
pub use fourier::FourierEncoding;
pub use ground::{flat_ground_depth_map_m, flat_ground_range_image, try_flat_ground_depth_m};
pub use projection::{
    AngleMethod, NO_POINT, OutOfFov, PixelOutcome, ProjectionOptions, ProjectionStats, Projector,
    RangeImage, Rejections, project,
};
pub use rays::{RayTable, Unprojected};
pub use region::Region;
pub use sensor::{BeamLayout, LidarSensor, MAX_SENSOR_PIXELS, RowSource, SensorPreset};
