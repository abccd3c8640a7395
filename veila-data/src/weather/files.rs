//! Weather on files: a scan (KITTI `.bin`, nuScenes `.pcd.bin`, PLY), optionally its camera image and
//! calibration, written back in the input's format. Used by `veila weather` and `cargo xtask kitti-weather`.
//!
//! * An empty pipeline copies the input bytes verbatim (a PNG image too): byte-identical outputs.
//! * The camera's depth map comes from the scan itself, projected into the image with the calibration
//!   ([`crate::spec::read_calib_camera`]: KITTI camera 2 or nuScenes `CAM_FRONT`) and densified with
//!   [`DepthMap::from_sparse`]; the camera record notes it. Camera effects that need depth fail without
//!   a calibration file.
//! * Rings: from the file (nuScenes), else the HDL-64E elevation table (noted in the snow record).
//! * Intensity scale: KITTI 1, nuScenes 255; PLY: 255 when any intensity exceeds 1, else 1.
//! * Nothing is written until every output is computed; each file is written atomically.

use std::path::{Path, PathBuf};

use image::RgbImage;
use veila_geom::PinholeCamera;

use super::camera::{CameraInput, DepthMap, Intrinsics};
use super::lidar::LidarInput;
use super::plan::{EffectRecord, EffectsReport, Input};
use super::points::BeamTable;
use super::{WeatherConfig, WeatherSim};
use crate::atomic::write_atomic;
use crate::scan::{PointFormat, read_points};
use crate::{Error, PointCloud, Result};

/// The input files of one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameFiles {
    /// The scan.
    pub scan: PathBuf,
    /// The camera image (PNG or JPEG), optional.
    pub image: Option<PathBuf>,
    /// KITTI object `calib/NNNNNN.txt`, odometry `calib.txt` or nuScenes per-sample JSON (needed
    /// for camera fog, headlights, particles).
    pub calib: Option<PathBuf>,
    /// SemanticKITTI `.label` file (ground mask for wet ground), optional.
    pub labels: Option<PathBuf>,
}

/// Where the outputs of one frame go.
#[derive(Debug, Clone)]
pub struct FrameOutputs {
    /// Output scan path (same format as the input).
    pub scan: PathBuf,
    /// Output PNG path (used when an image is given).
    pub image: Option<PathBuf>,
}

/// Project the scan into the camera and densify to a per-pixel z-depth map (+inf: no LiDAR evidence
/// in the column, i.e. sky).
pub fn depth_from_scan(cloud: &PointCloud, cam: &PinholeCamera) -> DepthMap {
    let samples: Vec<(f32, f32, f32)> = cloud
        .xyz
        .iter()
        .filter_map(|p| cam.try_project_in_image(*p))
        .map(|ip| (ip.u_px, ip.v_px, ip.depth_m))
        .collect();
    DepthMap::from_sparse(cam.width, cam.height, &samples)
}

fn encode_nuscenes(cloud: &PointCloud) -> Vec<u8> {
    let mut out = Vec::with_capacity(cloud.len() * 20);
    for k in 0..cloud.len() {
        let p = cloud.xyz[k];
        let ring = cloud.ring.as_ref().map_or(0.0, |r| r[k] as f32);
        for v in [p.x, p.y, p.z, cloud.intensity[k], ring] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

fn is_png(path: &Path) -> bool {
    std::fs::File::open(path)
        .and_then(|mut f| {
            let mut head = [0u8; 8];
            std::io::Read::read_exact(&mut f, &mut head).map(|_| head)
        })
        .map(|h| h == *b"\x89PNG\r\n\x1a\n")
        .unwrap_or(false)
}

/// One frame with its weather applied, in memory: the bytes of every output.
#[derive(Debug)]
pub struct FrameResult {
    /// The scan, in the input's format.
    pub scan: Vec<u8>,
    /// The image as PNG, when an image was given.
    pub image: Option<Vec<u8>>,
    /// What ran.
    pub report: EffectsReport,
}

/// Apply `sim` to one frame and write its outputs. Returns the report of what ran (the caller writes
/// it, e.g. as `effects.json`).
pub fn process_frame(
    sim: &WeatherSim,
    files: &FrameFiles,
    out: &FrameOutputs,
) -> Result<EffectsReport> {
    if files.image.is_some() && out.image.is_none() {
        return Err(Error::Invalid {
            what: "weather outputs".into(),
            message: "no output image path".into(),
        });
    }
    let r = compute_frame(sim, files, &out.scan)?;
    write_atomic(&out.scan, &r.scan)?;
    if let (Some(bytes), Some(p)) = (r.image, &out.image) {
        write_atomic(p, &bytes)?;
    }
    Ok(r.report)
}

/// Apply `sim` to one frame in memory; nothing is written. Every input is read and checked, even
/// when no effect runs and its bytes are passed through unchanged (a truncated scan or an image bomb
/// is an error either way). `out_scan` names the scan output in encoding errors.
pub fn compute_frame(sim: &WeatherSim, files: &FrameFiles, out_scan: &Path) -> Result<FrameResult> {
    let plan = sim.plan();
    // ---- LiDAR
    let scan_bytes: Vec<u8>;
    let mut lidar_records = Vec::new();
    let mut clean_cloud: Option<PointCloud> = None;
    let need_cloud_for_depth = !plan.camera.is_empty()
        && plan
            .camera
            .iter()
            .any(|e| e.required_inputs().contains(&Input::DepthMap))
        && files.image.is_some();
    if plan.lidar.is_empty() {
        // checked like any input (the pass-through must not copy garbage), then copied verbatim
        let loaded = read_points(&files.scan)?;
        scan_bytes = std::fs::read(&files.scan).map_err(|e| Error::io(&files.scan, e))?;
        if need_cloud_for_depth {
            clean_cloud = Some(loaded.cloud);
        }
    } else {
        let loaded = read_points(&files.scan)?;
        let mut cloud = loaded.cloud;
        let imax = match loaded.format {
            PointFormat::KittiBin => 1.0,
            PointFormat::NuScenesPcdBin => 255.0,
            PointFormat::Ply => {
                if cloud.intensity.iter().any(|i| *i > 1.0) {
                    255.0
                } else {
                    1.0
                }
            }
            PointFormat::RangeExr => return Err(exr_unsupported(&files.scan)),
        };
        if let Some(lp) = &files.labels {
            if loaded.dropped_non_finite > 0 {
                return Err(Error::Mismatch {
                    context: format!("{} and {}", files.scan.display(), lp.display()),
                    message: format!(
                        "the scan has {} non-finite points, so its labels cannot be aligned",
                        loaded.dropped_non_finite
                    ),
                });
            }
            cloud.label = Some(crate::semantic_kitti::read_labels(lp, Some(cloud.len()))?);
        }
        let mut cfg: WeatherConfig = sim.config().clone();
        cfg.lidar.intensity_max = imax;
        let local = WeatherSim::new(sim.weather(), &cfg)?;
        let beams = BeamTable::hdl64e();
        let res = local.apply_lidar(LidarInput {
            cloud: &cloud,
            ground_mask: None,
            beams: Some(&beams),
        })?;
        lidar_records = res.records;
        if let (true, Some(first)) = (loaded.dropped_non_finite > 0, lidar_records.first_mut()) {
            first.notes.push(format!(
                "{} non-finite input points dropped",
                loaded.dropped_non_finite
            ));
        }
        scan_bytes = match loaded.format {
            PointFormat::KittiBin => crate::scan::encode_kitti_bin(&res.cloud),
            PointFormat::NuScenesPcdBin => encode_nuscenes(&res.cloud),
            _ => {
                let mut buf = Vec::new();
                crate::ply::encode_ply(&res.cloud, &mut buf).map_err(|e| Error::io(out_scan, e))?;
                buf
            }
        };
        clean_cloud = Some(cloud);
    }
    // ---- camera
    let mut camera_records: Vec<EffectRecord> = Vec::new();
    let mut image_bytes: Option<Vec<u8>> = None;
    if let Some(img_path) = &files.image {
        if plan.camera.is_empty() && is_png(img_path) {
            // decoded once to check it (size limits stop decompression bombs), then copied verbatim
            crate::image_io::read_rgb_image(img_path)?;
            image_bytes = Some(std::fs::read(img_path).map_err(|e| Error::io(img_path, e))?);
        } else {
            let img: RgbImage = crate::image_io::read_rgb_image(img_path)?;
            let needs = |i: Input| plan.camera.iter().any(|e| e.required_inputs().contains(&i));
            let (mut depth, mut intr, mut note) = (None, None, None);
            if needs(Input::DepthMap) || needs(Input::Intrinsics) {
                let calib = files.calib.as_ref().ok_or_else(|| Error::MissingInput {
                    effect: plan
                        .camera
                        .iter()
                        .map(|e| e.name())
                        .collect::<Vec<_>>()
                        .join(", "),
                    input: "a calibration file (for the intrinsics and a depth map from the scan)"
                        .into(),
                })?;
                let cam =
                    crate::spec::read_calib_camera(calib, None, img.width(), img.height())?.camera;
                intr = Some(Intrinsics::from_camera(&cam));
                if needs(Input::DepthMap) {
                    let cloud = match &clean_cloud {
                        Some(c) => c,
                        None => {
                            clean_cloud = Some(read_points(&files.scan)?.cloud);
                            clean_cloud.as_ref().expect("just set")
                        }
                    };
                    depth = Some(depth_from_scan(cloud, &cam));
                    note = Some(format!(
                        "depth map from {} projected with {} and densified per column",
                        files.scan.display(),
                        calib.display()
                    ));
                }
            }
            let res = sim.apply_camera(CameraInput {
                image: &img,
                depth: depth.as_ref(),
                intrinsics: intr,
            })?;
            camera_records = res.records;
            if let (Some(n), Some(first)) = (note, camera_records.first_mut()) {
                first.notes.push(n);
            }
            image_bytes = Some(crate::image_io::encode_png(&res.image)?);
        }
    }
    Ok(FrameResult {
        scan: scan_bytes,
        image: image_bytes,
        report: sim.report(lidar_records, camera_records),
    })
}

fn exr_unsupported(scan: &Path) -> Error {
    Error::Invalid {
        what: "weather input".into(),
        message: format!(
            "{}: range-image EXR input is not supported; unproject it to .ply first",
            scan.display()
        ),
    }
}

/// The output file name of a scan: the input's file name (`000000.bin`, `x.pcd.bin`, `x.ply`).
pub fn output_scan_name(scan: &Path) -> Result<String> {
    scan.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| Error::Invalid {
            what: "scan path".into(),
            message: format!("{} has no file name", scan.display()),
        })
}

/// The output PNG name of an image: `<stem>.png`.
pub fn output_image_name(image: &Path) -> Result<String> {
    image
        .file_stem()
        .map(|n| format!("{}.png", n.to_string_lossy()))
        .ok_or_else(|| Error::Invalid {
            what: "image path".into(),
            message: format!("{} has no file name", image.display()),
        })
}
