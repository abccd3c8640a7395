//! Veila's data layer: the only library crate of the workspace that touches files.
//!
//! (Being filled in.) It holds the dataset readers (KITTI object, KITTI odometry / SemanticKITTI,
//! nuScenes), range images as OpenEXR, PNG previews, points as KITTI `.bin` and PLY, training shards
//! (safetensors + manifest), the procedural scene simulator ([`sim`]) and the weather simulator
//! ([`weather`]).

pub mod atomic;
pub mod error;
pub mod points;
pub mod sim;
pub mod weather;

pub use error::{Error, Result};
pub use points::PointCloud;
