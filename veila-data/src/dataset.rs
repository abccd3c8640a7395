//! The common face of every dataset reader: a list of frame ids known up front and frames read on
//! demand, so a 43k-scan SemanticKITTI never has to fit in memory.

use std::path::PathBuf;

use image::RgbImage;
use veila_geom::{LidarSensor, PinholeCamera};

use crate::{PointCloud, Result};

/// One frame of a dataset: a LiDAR scan and, where the dataset has one, the paired camera.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Stable id, unique within the dataset (`000123`, `08/000123`, a nuScenes sample token).
    pub id: String,
    /// The scan in the LiDAR frame; non-finite points already dropped. Intensity in the dataset's own
    /// scale (see [`Dataset::intensity_max`]). SemanticKITTI raw labels in [`PointCloud::label`].
    pub points: PointCloud,
    /// Points dropped for a NaN or infinite coordinate or intensity.
    pub dropped_non_finite: usize,
    /// The scan file.
    pub scan_path: PathBuf,
    /// The camera image file, when the dataset has a camera.
    pub image_path: Option<PathBuf>,
    /// The decoded camera image (only when the dataset was opened with images enabled).
    pub image: Option<RgbImage>,
    /// The camera model (intrinsics and `cam_from_lidar`), when the dataset has a camera.
    pub camera: Option<PinholeCamera>,
    /// Further cameras of the rig, when the dataset was opened with several (nuScenes' side
    /// cameras); empty otherwise.
    pub extra_views: Vec<FrameView>,
}

/// A further camera of a [`Frame`].
#[derive(Debug, Clone)]
pub struct FrameView {
    /// The dataset's name for the camera (`CAM_FRONT_LEFT`, `image_3`).
    pub channel: String,
    /// The image file.
    pub image_path: PathBuf,
    /// The decoded image (only when the dataset was opened with images enabled).
    pub image: Option<RgbImage>,
    /// The camera model.
    pub camera: PinholeCamera,
}

/// A dataset of frames read lazily.
pub trait Dataset: Send + Sync + std::fmt::Debug {
    /// Short name (`kitti`, `semantickitti`, `nuscenes`).
    fn name(&self) -> &'static str;
    /// Number of frames.
    fn len(&self) -> usize;
    /// True when the dataset has no frames.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Id of frame `index` (no file is read). Panics if `index >= len()`, like slice indexing.
    fn frame_id(&self, index: usize) -> String;
    /// Read frame `index` from disk; any problem with its files is an error naming the file. Panics if
    /// `index >= len()`, like slice indexing.
    fn load(&self, index: usize) -> Result<Frame>;
    /// The sensor that recorded the dataset (the preset used when none is given).
    fn default_sensor(&self) -> LidarSensor;
    /// The largest intensity value of the dataset's scale (1 for KITTI, 255 for nuScenes); divide by it
    /// to get intensities in `[0, 1]`.
    fn intensity_max(&self) -> f32;
    /// The files frame `index` is made of (scan, labels, image, calibration), for change detection:
    /// a resumed conversion compares their contents with those it converted. Default: none known.
    fn source_files(&self, index: usize) -> Result<Vec<PathBuf>> {
        let _ = index;
        Ok(Vec::new())
    }
}

/// Iterator over the frames of a dataset, reading each on demand.
#[derive(Debug)]
pub struct Frames<'a> {
    dataset: &'a dyn Dataset,
    next: usize,
}

impl Iterator for Frames<'_> {
    type Item = Result<Frame>;
    fn next(&mut self) -> Option<Self::Item> {
        if self.next >= self.dataset.len() {
            return None;
        }
        let i = self.next;
        self.next += 1;
        Some(self.dataset.load(i))
    }
    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.dataset.len().saturating_sub(self.next);
        (left, Some(left))
    }
}

impl ExactSizeIterator for Frames<'_> {}

/// Lazy iteration over any dataset.
pub fn frames(dataset: &dyn Dataset) -> Frames<'_> {
    Frames { dataset, next: 0 }
}
