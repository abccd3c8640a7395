//! The cross-modal metrics of a set of generated scans (the paper's CM-DC and CM-SC, `veila eval
//! --metrics cm-dc,cm-sc`): each scan projected into its camera against a depth or class map, read
//! from files or predicted by a pretrained network (Depth-Anything-V2, SegFormer) on the camera
//! image. The metric math is `veila_metrics::crossmodal`; this module finds each scan's
//! calibration, maps and image ([`CrossModalEval::score`]), runs the networks and averages over
//! the scans ([`CrossModalScores::metrics`]). The binary parses its flags into a
//! [`CrossModalEval`], loads the networks and draws the progress.

use std::path::{Path, PathBuf};

use candle_core::Device;
use veila_data::image::RgbImage;
use veila_data::image_io::ImageMap;
use veila_metrics::crossmodal::{
    DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
};
use veila_metrics::{MetricValue, Protocol, Region};
use veila_nn::encoders::depth_anything::DepthAnythingV2;
use veila_nn::encoders::mit::SegFormer;
use veila_nn::encoders::preprocess::ImageProcessor;
use veila_nn::feature_nets::FeatureNets;

use crate::error::{Error, Result, invalid};

/// Where CM-DC's depth maps come from.
#[derive(Debug, Clone, Copy)]
pub enum DepthReference<'a> {
    /// A folder with `<scan stem>.png` (16-bit, metres x 256, 0 = none) or `<scan stem>.npy`
    /// (float H x W) per scan, aligned as `alignment` says.
    Maps {
        /// The folder.
        dir: &'a Path,
        /// How each map is aligned to the scan's depths.
        alignment: DepthAlignment,
    },
    /// Depth-Anything-V2 on each scan's camera image: a relative checkpoint's inverse depth is
    /// aligned in disparity space; a metric one's depth as `metric` says (`None`: relative).
    Model {
        /// The network.
        model: &'a DepthAnythingV2,
        /// The alignment of a metric checkpoint (`None`: the checkpoint is relative).
        metric: Option<DepthAlignment>,
    },
}

/// The id space of class maps read from files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClassIds {
    /// SemanticKITTI train ids (0 = ignored, 1..=19); maps holding raw ids are refused
    /// ([`Error::InvalidConfig`] of field `semantic_ids`).
    Train,
    /// SemanticKITTI raw ids (10 car, 40 road, ...), mapped to train ids by its learning map.
    Raw,
}

/// Where CM-SC's class maps come from.
#[derive(Debug, Clone, Copy)]
pub enum SemanticReference<'a> {
    /// A folder with a class map per scan, `<scan stem>.png` (8- or 16-bit greyscale).
    Maps {
        /// The folder.
        dir: &'a Path,
        /// The maps' id space.
        ids: ClassIds,
    },
    /// SegFormer (Cityscapes head) on each scan's camera image, its classes mapped to
    /// SemanticKITTI's.
    Model(&'a SegFormer),
}

/// What the cross-modal metrics of a set of scans compare with.
#[derive(Debug, Clone, Copy)]
pub struct CrossModalEval<'a> {
    /// The KITTI calibration (camera `image_2`): one file for every scan, or a folder with
    /// `<scan stem>.txt` per scan.
    pub calib: &'a Path,
    /// The camera image's size `(width, height)` when the maps have another resolution (`None`:
    /// each map's own size).
    pub image_size: Option<(u32, u32)>,
    /// A folder with the camera image of each scan, `<scan stem>.png` or `.jpg` (needed by the
    /// networks).
    pub images: Option<&'a Path>,
    /// CM-DC's reference (`None`: no CM-DC).
    pub depth: Option<DepthReference<'a>>,
    /// CM-SC's reference and the range segmentation net that labels the scan's points (`None`:
    /// no CM-SC).
    pub semantic: Option<(SemanticReference<'a>, &'a FeatureNets)>,
}

/// One scan's scores (`None`: not asked for, or no point projects onto a map value).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ScanScores {
    /// CM-DC (AbsRel).
    pub cm_dc: Option<f64>,
    /// CM-SC (percent).
    pub cm_sc: Option<f64>,
}

/// A scan file's name without its point-format extension (`000001.bin`, `x.pcd.bin` -> `000001`, `x`).
pub fn scan_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lower = name.to_lowercase();
    for ext in [".pcd.bin", ".bin", ".ply", ".exr"] {
        if lower.ends_with(ext) {
            return name[..name.len() - ext.len()].to_string();
        }
    }
    name
}

/// `dir/<stem>.<ext>` for the first extension that exists, or an error naming what was looked for.
fn companion(dir: &Path, stem: &str, exts: &[&str], what: &str, scan: &Path) -> Result<PathBuf> {
    for ext in exts {
        let p = dir.join(format!("{stem}.{ext}"));
        if p.is_file() {
            return Ok(p);
        }
    }
    let expected: Vec<String> = exts.iter().map(|e| format!("{stem}.{e}")).collect();
    Err(Error::Input {
        path: scan.to_path_buf(),
        reason: format!(
            "no {what} for it: expected {} in {}",
            expected.join(" or "),
            dir.display()
        ),
    })
}

/// An error of the file `path`.
fn at(path: &Path, reason: impl std::fmt::Display) -> Error {
    Error::Input {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

impl CrossModalEval<'_> {
    /// The camera image of `scan` (`stem`), and its path.
    fn image(&self, stem: &str, scan: &Path) -> Result<(PathBuf, RgbImage)> {
        let dir = self
            .images
            .ok_or_else(|| invalid("images", "the networks run on the camera images"))?;
        let p = companion(dir, stem, &["png", "jpg"], "camera image", scan)?;
        let img = veila_data::image_io::read_rgb_image(&p)?;
        Ok((p, img))
    }

    /// The scores of the scan file `scan` (networks on `device`). A scan none of whose points
    /// project onto a map value, or whose metric fails, scores `None` with a warning; a missing
    /// or unreadable file is an error naming it.
    pub fn score(&self, scan: &Path, device: &Device) -> Result<ScanScores> {
        let stem = scan_stem(scan);
        let calib_file = if self.calib.is_dir() {
            companion(self.calib, &stem, &["txt"], "calibration", scan)?
        } else {
            self.calib.to_path_buf()
        };
        let loaded = veila_data::scan::read_points(scan)?;
        let cloud = &loaded.cloud;
        let camera_for = |w: u32, h: u32| -> Result<veila_geom::PinholeCamera> {
            let (w, h) = self.image_size.unwrap_or((w, h));
            Ok(veila_data::spec::read_calib_camera(&calib_file, None, w, h)?.camera)
        };
        let mut scores = ScanScores::default();
        if let Some(depth) = &self.depth {
            let (mp, map, alignment) = match *depth {
                DepthReference::Model { model, metric } => {
                    let (p, img) = self.image(&stem, scan)?;
                    let (w, h) = img.dimensions();
                    let (rows, cols) = (h as usize, w as usize);
                    let processor = ImageProcessor::depth_anything_v2();
                    let data = model
                        .predict_depth_map_rgb8(&processor, img.as_raw(), rows, cols, device)
                        .map_err(|e| at(&p, format!("depth prediction: {e}")))?;
                    let map = ImageMap {
                        width: w,
                        height: h,
                        data,
                    };
                    (p, map, metric.unwrap_or(DepthAlignment::Disparity))
                }
                DepthReference::Maps { dir, alignment } => {
                    let mp = companion(dir, &stem, &["png", "npy"], "depth map", scan)?;
                    let map = veila_data::image_io::read_depth_map(&mp)?;
                    (mp, map, alignment)
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let m = Map2d::new(map.width, map.height, &map.data).map_err(|e| at(&mp, e))?;
            let filter = ProjectionFilter::default();
            match cm_depth_consistency(&cloud.xyz, &cam, &m, alignment, &filter) {
                Ok(c) if c.abs_rel.is_finite() => scores.cm_dc = Some(c.abs_rel),
                Ok(_) => tracing::warn!("{}: no point projects onto a depth value", scan.display()),
                Err(e) => tracing::warn!("{}: cm-dc skipped: {e}", scan.display()),
            }
        }
        if let Some((semantic, nets)) = &self.semantic {
            let (mp, map) = match *semantic {
                SemanticReference::Model(model) => {
                    let (p, img) = self.image(&stem, scan)?;
                    let (w, h) = img.dimensions();
                    let (rows, cols) = (h as usize, w as usize);
                    let processor = ImageProcessor::segformer(1024, 1024);
                    let labels = model
                        .predict_label_map_rgb8(&processor, img.as_raw(), rows, cols, device)
                        .map_err(|e| at(&p, format!("segmentation: {e}")))?;
                    let data = labels
                        .into_iter()
                        .map(veila_metrics::crossmodal::cityscapes_to_semantickitti)
                        .collect();
                    let map = ImageMap {
                        width: w,
                        height: h,
                        data,
                    };
                    (p, map)
                }
                SemanticReference::Maps { dir, ids } => {
                    let mp = companion(dir, &stem, &["png"], "class map", scan)?;
                    let mut map = veila_data::image_io::read_label_map(&mp)?;
                    match ids {
                        ClassIds::Train => {
                            let name = mp.display().to_string();
                            veila_metrics::crossmodal::check_train_ids(&map.data, &name)
                                .map_err(|e| invalid("semantic_ids", e.to_string()))?;
                        }
                        ClassIds::Raw => {
                            for v in &mut map.data {
                                let raw = u16::try_from(*v).unwrap_or(0);
                                *v = u32::from(veila_data::semantic_kitti::class::learning_id(raw));
                            }
                        }
                    }
                    (mp, map)
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let (pts, labels) = nets.segment_points(&cloud.xyz, Some(&cloud.intensity))?;
            let m = Map2d::new(map.width, map.height, &map.data).map_err(|e| at(&mp, e))?;
            let filter = ProjectionFilter {
                ignore_label: Some(0),
                ..ProjectionFilter::default()
            };
            match cm_semantic_consistency(&pts, &labels, &cam, &m, &filter) {
                Ok(c) if c.percent.is_finite() => scores.cm_sc = Some(c.percent),
                Ok(_) => {
                    tracing::warn!(
                        "{}: no point projects onto a labelled pixel",
                        scan.display()
                    )
                }
                Err(e) => tracing::warn!("{}: cm-sc skipped: {e}", scan.display()),
            }
        }
        Ok(scores)
    }
}

/// The scores of a set of scans, collected scan by scan.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CrossModalScores {
    /// CM-DC of every scan that has one.
    pub cm_dc: Vec<f64>,
    /// CM-SC of every scan that has one.
    pub cm_sc: Vec<f64>,
}

impl CrossModalScores {
    /// Adds one scan's scores.
    pub fn push(&mut self, s: ScanScores) {
        self.cm_dc.extend(s.cm_dc);
        self.cm_sc.extend(s.cm_sc);
    }

    /// The metrics asked for (`(cm-dc, cm-sc)`), each the mean over the scans that have a score
    /// (region front: the camera's field of view). `Err(name)`: no scan has a score of that
    /// metric.
    pub fn metrics(
        &self,
        (dc, sc): (bool, bool),
    ) -> std::result::Result<Vec<MetricValue>, &'static str> {
        let mut out = Vec::new();
        for (want, name, vals) in [(dc, "cm-dc", &self.cm_dc), (sc, "cm-sc (%)", &self.cm_sc)] {
            if !want {
                continue;
            }
            if vals.is_empty() {
                return Err(name);
            }
            out.push(MetricValue {
                name: name.into(),
                protocol: Protocol::Veila,
                region: Region::Front,
                value: vals.iter().sum::<f64>() / vals.len() as f64,
                generated: vals.len(),
                reference: 0,
                paper_scale: None,
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_stems_drop_the_point_format() {
        assert_eq!(scan_stem(Path::new("a/000001.bin")), "000001");
        assert_eq!(scan_stem(Path::new("x.PCD.bin")), "x");
        assert_eq!(scan_stem(Path::new("s.ply")), "s");
        assert_eq!(scan_stem(Path::new("noext")), "noext");
    }

    #[test]
    fn a_missing_companion_names_the_scan_and_every_file_looked_for() {
        let dir = tempfile::tempdir().unwrap();
        let e = companion(
            dir.path(),
            "7",
            &["png", "npy"],
            "depth map",
            Path::new("g/7.bin"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with("g/7.bin: no depth map for it: expected 7.png or 7.npy in"),
            "{e}"
        );
        std::fs::write(dir.path().join("7.npy"), b"").unwrap();
        let p = companion(
            dir.path(),
            "7",
            &["png", "npy"],
            "depth map",
            Path::new("7.bin"),
        );
        assert_eq!(p.unwrap(), dir.path().join("7.npy"));
    }

    #[test]
    fn the_metrics_are_means_over_the_scans_with_a_score() {
        let mut s = CrossModalScores::default();
        s.push(ScanScores {
            cm_dc: Some(0.1),
            cm_sc: None,
        });
        s.push(ScanScores {
            cm_dc: Some(0.3),
            cm_sc: Some(50.0),
        });
        let m = s.metrics((true, true)).unwrap();
        assert_eq!((m[0].name.as_str(), m[0].generated), ("cm-dc", 2));
        assert!((m[0].value - 0.2).abs() < 1e-12);
        assert_eq!((m[1].name.as_str(), m[1].value), ("cm-sc (%)", 50.0));
        assert!(s.metrics((false, false)).unwrap().is_empty());
        assert_eq!(
            CrossModalScores::default().metrics((true, false)),
            Err("cm-dc")
        );
    }
}
