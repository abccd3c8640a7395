//! Procedural scene simulator: paired camera images and LiDAR scans with ground-truth semantics and
//! depth, by ray casting through an `obvhs` BVH.
//!
//! - [`SceneConfig`]: a TOML scene file (layout, road, population, ego, sensors, lighting,
//!   appearance randomisation of the camera image, rig variation, frames).
//! - [`Scene::generate`]: a deterministic world from a config and a seed: road with lanes and
//!   markings, kerbs, sidewalks, parking strips, buildings with windows, open roadsides, fences,
//!   hedges, guardrails, trees, bushes, terrain, street lights, signs, traffic lights, parked and moving cars, vans, trucks,
//!   buses, trailers, pedestrians and cyclists; every surface has a [`Material`] (albedo, LiDAR
//!   reflectivity) and a SemanticKITTI raw class ([`class`](crate::semantic_kitti::class)).
//! - [`Scene::snapshot`]: the world at one frame with its BVH ([`Accel`]) and the ego's LiDAR pose;
//!   [`SceneSnapshot::render_lidar`] gives a [`SimScan`] (points with intensity, ring and label, range
//!   image, per-ray outcome), [`SceneSnapshot::render_camera`] a [`SimImage`] (RGB, depth, semantics);
//!   [`Scene::render_frame`] both with the scene's own sensors ([`SimFrame`]).
//! - [`simulate_to_dir`]: frames in the KITTI layout (see [`output`]); [`SceneList`]: train / test
//!   splits of scene files and seeds (`scenes/train.txt`, `scenes/test.txt`).
//!
//! Everything is deterministic in (config, seed) and independent of the number of threads.
//!
//! ```
//! use veila_data::sim::{CameraRenderOptions, LidarReturnModel, Scene, SceneConfig, SimCalib};
//! use veila_geom::LidarSensor;
//!
//! let config = SceneConfig::default(); // a straight street
//! let scene = Scene::generate(&config, 7)?;
//! let snapshot = scene.snapshot(0);
//! let sensor = LidarSensor { rows: 16, cols: 256, ..LidarSensor::hdl64e() };
//! let scan = snapshot.render_lidar(&sensor, &LidarReturnModel::default())?;
//! assert!(scan.points.len() > 16 * 256 / 2);
//!
//! let mut cam_cfg = config.camera;
//! (cam_cfg.width, cam_cfg.height, cam_cfg.cx, cam_cfg.cy) = (124, 38, 61.0, 17.0);
//! (cam_cfg.fx, cam_cfg.fy) = (72.0, 72.0);
//! let camera = SimCalib::from_config(&cam_cfg).camera()?;
//! let image = snapshot.render_camera(&camera, &CameraRenderOptions::default())?;
//! assert_eq!(image.rgb.len(), 124 * 38 * 3);
//! # Ok::<(), veila_data::Error>(())
//! ```

mod appearance;
pub mod camera;
pub mod config;
pub mod curve;
pub mod frame;
mod hash;
pub mod lidar;
pub mod material;
pub mod mesh;
pub mod objects;
pub mod output;
pub mod raycast;
pub mod scene;
pub mod split;

pub use camera::{CameraRenderOptions, SimCalib, SimImage};
pub use config::{
    AppearanceConfig, CameraConfig, EgoConfig, FramesConfig, Layout, LidarConfig, LidarReturnModel,
    LightingConfig, PopulationConfig, RigConfig, RoadConfig, RoadParams, SceneConfig,
};
pub use curve::RoadCurve;
pub use frame::SceneSnapshot;
pub use lidar::{RayOutcome, SimScan};
pub use material::Material;
pub use mesh::{Mesh, Surface};
pub use output::{FramePaths, SimSummary, simulate_to_dir, write_frame};
pub use raycast::{Accel, Hit};
pub use scene::{Actor, Scene, SimFrame, SimView};
pub use split::{SceneList, SceneListEntry};
