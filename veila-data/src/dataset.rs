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

/// A dataset, as a command line names it. [`DatasetName::ALL`] is the one list of datasets:
/// `veila convert --dataset`'s choices are built from it (and a test of that door checks that
/// they are), and every reader's [`Dataset::name`] is its entry's name. A new dataset is a reader
/// implementing [`Dataset`], a variant here with its arms, and its arm in
/// [`crate::convert::open_source`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DatasetName {
    /// SemanticKITTI (KITTI odometry sequences with point labels): [`crate::semantic_kitti`].
    SemanticKitti,
    /// KITTI object detection (`training/`): [`crate::kitti`].
    Kitti,
    /// nuScenes (tables or per-sample calibration JSON): [`crate::nuscenes`].
    NuScenes,
}

impl DatasetName {
    /// Every dataset, in the order help texts list them.
    pub const ALL: [DatasetName; 3] = [
        DatasetName::SemanticKitti,
        DatasetName::Kitti,
        DatasetName::NuScenes,
    ];

    /// The name: `semantickitti`, `kitti`, `nuscenes`.
    pub fn as_str(self) -> &'static str {
        match self {
            DatasetName::SemanticKitti => "semantickitti",
            DatasetName::Kitti => "kitti",
            DatasetName::NuScenes => "nuscenes",
        }
    }

    /// One line for a `--help` text.
    pub fn help(self) -> &'static str {
        match self {
            DatasetName::SemanticKitti => {
                "SemanticKITTI: the folder with sequences/ (HDL-64E, point labels)"
            }
            DatasetName::Kitti => "KITTI object detection: the folder with training/ (HDL-64E)",
            DatasetName::NuScenes => {
                "nuScenes: the data root with v1.0-*/ tables or calib/*.json (HDL-32E)"
            }
        }
    }
}

impl std::fmt::Display for DatasetName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for DatasetName {
    type Err = crate::Error;

    fn from_str(name: &str) -> Result<Self> {
        DatasetName::ALL
            .into_iter()
            .find(|d| d.as_str() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = DatasetName::ALL.map(DatasetName::as_str).into();
                crate::Error::Invalid {
                    what: "dataset".into(),
                    message: format!("`{name}` is not one of {}", names.join(", ")),
                }
            })
    }
}

/// A dataset of frames read lazily.
pub trait Dataset: Send + Sync + std::fmt::Debug {
    /// Short name: its [`DatasetName`]'s.
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_dataset_has_one_name_that_parses_back() {
        for d in DatasetName::ALL {
            assert_eq!(d.as_str().parse::<DatasetName>().unwrap(), d);
            assert_eq!(d.to_string(), d.as_str());
            assert!(!d.help().is_empty());
            let same = DatasetName::ALL.iter().filter(|e| e.as_str() == d.as_str());
            assert_eq!(same.count(), 1, "{d}");
        }
        let e = "waymo".parse::<DatasetName>().unwrap_err().to_string();
        assert!(
            e.contains("waymo") && e.contains("semantickitti, kitti, nuscenes"),
            "{e}"
        );
    }
}
