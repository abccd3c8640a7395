//! Veila's data layer: the only library crate of the workspace that touches files.
//!
//! # Reading
//!
//! - Point files with format detection: [`scan::read_points`] (KITTI `.bin`, nuScenes `.pcd.bin`,
//!   PLY, range `.exr`; rules in [`scan`]), or one format directly: [`scan::read_kitti_bin`],
//!   [`scan::read_nuscenes_pcd_bin`], [`ply::read_ply`], [`range_exr::read_range_exr`]. NaN and
//!   infinite points are dropped and counted, never passed on.
//! - Datasets, read lazily through the [`dataset::Dataset`] trait (frame ids up front, frames on
//!   demand, [`dataset::frames`] iterates): [`kitti::KittiObjectDataset`] (velodyne, image_2, calib,
//!   label_2), [`semantic_kitti::SemanticKittiDataset`] (sequences, `calib.txt`, `.label`, the label
//!   map and split of `semantic-kitti.yaml`), [`nuscenes::NuScenesDataset`] (release JSON tables with
//!   the devkit's LiDAR -> ego -> global -> ego -> camera chain, or per-sample JSON).
//! - Calibration: [`kitti::KittiCalib`], [`semantic_kitti::OdometryCalib`],
//!   [`nuscenes::NuScenesSample`], each giving a [`veila_geom::PinholeCamera`]; any of them by content
//!   with [`spec::read_calib_camera`], the one reader every door uses. Sensors by preset or file:
//!   [`spec::sensor_from_spec`].
//! - Images: [`image_io::read_rgb_image`] (PNG / JPEG).
//! - Metadata read whole (manifests, configs, calibrations, label maps, `.label` files):
//!   [`read_capped::read_metadata`], which refuses anything but a regular file, and a file over the
//!   cap for its kind, before reading it.
//! - Paths named inside artifacts (a calibration's image and sweep, a manifest's shards, a bundle's
//!   weights): [`contained::contained`], which refuses one that is absolute, climbs out with `..`
//!   or leads out of its folder through a link, before anything at it is opened.
//!
//! # Writing
//!
//! Every writer is atomic (temporary file in the destination folder, then rename; see [`atomic`]).
//! - Points: [`scan::write_points`] (`.ply` or `.bin` by name), [`ply::write_ply`],
//!   [`scan::write_kitti_bin`], [`semantic_kitti::write_labels`].
//! - Range images as self-describing OpenEXR: [`range_exr::write_range_exr`] (bit-exact round trip).
//! - Images: [`image_io::write_png`]; report time stamps in [`stamp`].
//! - Training shards: [`shard::write_shard`] / [`shard::read_shard`] and [`shard::Manifest`]; whole
//!   datasets with [`convert::convert`] (bounded memory, resumable, shardable across workers).
//!
//! # Features
//!
//! The readers and writers above are the core and always built. Four rooms build on them, each
//! behind a cargo feature (all off by default, so a reader alone compiles no ray tracer, random
//! number stack or plotting):
//!
//! - `augment`: camera image augmentation and degradation (module `augment`: exposure, white
//!   balance, vignetting, blur, sensor noise, colour jitter, JPEG, crop-and-zoom with the camera
//!   updated; seeded); also turned on by `sim`;
//! - `sim`: the procedural scene simulator (module `sim`: scenes from TOML + seed, ray cast through
//!   an `obvhs` BVH into LiDAR scans and camera images with ground truth);
//! - `weather`: the weather simulator (module `weather`: fog, rain, snow, wet ground, night);
//! - `vis`: visualisation (module `vis`: previews, plots, and the HTML reports' building blocks).
//!
//! # Example
//!
//! ```
//! use glam::Vec3;
//! use veila_data::{PointCloud, range_exr, scan};
//! use veila_geom::{LidarSensor, ProjectionOptions, Projector};
//!
//! let dir = tempfile::tempdir()?;
//! let cloud = PointCloud {
//!     xyz: vec![Vec3::new(10.0, 0.0, -1.0), Vec3::new(f32::NAN, 0.0, 0.0), Vec3::new(-5.0, 2.0, 0.0)],
//!     intensity: vec![0.3, 0.1, 0.8],
//!     ring: None,
//!     label: None,
//! };
//! let bin = dir.path().join("000000.bin");
//! scan::write_points(&bin, &cloud)?;
//!
//! // the format is detected; the NaN point is dropped and counted
//! let loaded = scan::read_points(&bin)?;
//! assert_eq!((loaded.format, loaded.cloud.len(), loaded.dropped_non_finite), (scan::PointFormat::KittiBin, 2, 1));
//!
//! // project, store as EXR with the sensor in the header, read back bit-exactly
//! let sensor = LidarSensor::hdl64e();
//! let (image, _stats) = Projector::new(&sensor, ProjectionOptions::default())?
//!     .project(&loaded.cloud.xyz, Some(&loaded.cloud.intensity), None)?;
//! let exr = dir.path().join("000000.exr");
//! range_exr::write_range_exr(&exr, &sensor, &image)?;
//! let back = range_exr::read_range_exr(&exr)?;
//! assert_eq!((back.sensor, back.image), (sensor, image));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod atomic;
#[cfg(feature = "augment")]
pub mod augment;
mod calib;
pub mod contained;
pub mod convert;
pub mod dataset;
pub mod error;
pub mod image_io;
pub mod kitti;
pub mod npy;
pub mod nuscenes;
pub mod peer_samples;
pub mod ply;
pub mod points;
pub mod range_exr;
pub mod read_capped;
pub mod scan;
pub mod semantic_kitti;
pub mod shard;
#[cfg(feature = "sim")]
pub mod sim;
pub mod spec;
#[cfg(any(feature = "augment", feature = "weather"))]
mod srgb;
pub mod stamp;
#[cfg(feature = "vis")]
pub mod vis;
#[cfg(feature = "weather")]
pub mod weather;
mod yaml;

// the main types at the root; the modules stay public for their functions and the rest
pub use dataset::{Dataset, DatasetName, Frame};
pub use error::{Error, Result};
/// The `image` crate, whose `RgbImage` appears in this crate's API.
pub use image;
pub use kitti::KittiObjectDataset;
pub use nuscenes::NuScenesDataset;
pub use points::PointCloud;
pub use range_exr::RangeExr;
pub use scan::{LoadedPoints, PointFormat};
pub use shard::{Shard, ShardReader};
pub use spec::CalibCamera;
