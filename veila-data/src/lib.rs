//! Veila's data layer: the only library crate of the workspace that touches files.

pub mod atomic;
mod calib;
mod colormap_data;
pub mod convert;
pub mod dataset;
pub mod error;
pub mod image_io;
pub mod kitti;
pub mod nuscenes;
pub mod ply;
pub mod points;
pub mod range_exr;
pub mod render;
pub mod scan;
pub mod semantic_kitti;
pub mod shard;
pub mod spec;
pub mod sim;
pub mod weather;
mod yaml_lite;

pub use error::{Error, Result};
/// The `image` crate, whose `RgbImage` appears in this crate's API.
pub use image;
pub use points::PointCloud;
