//! Writing simulated frames in the KITTI layout.
//!
//! ```text
//! DIR/velodyne/NNNNNN.bin     f32 x, y, z, intensity (KITTI; intensity in [0, 1])
//! DIR/labels/NNNNNN.label     u32 per point: SemanticKITTI raw class | instance << 16
//! DIR/image_2/NNNNNN.png      8-bit sRGB
//! DIR/calib/NNNNNN.txt        P0..P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo (KITTI object format)
//! DIR/depth_2/NNNNNN.png      16-bit, depth (camera z) in metres * 256, 0 = no depth (KITTI depth)
//! DIR/semantic_2/NNNNNN.png   16-bit, SemanticKITTI raw class id per pixel, 0 = sky
//! DIR/scene.json              the scene configuration, seed, frame count and per-frame statistics
//! DIR/lidar_poses.txt         per frame: world_from_lidar as 12 numbers (row-major 3x4)
//! DIR/calib.txt              KITTI odometry calibration (P0..P3, Tr), for the SemanticKITTI reader
//! DIR/poses.txt              KITTI odometry poses: camera 0 of frame i in camera 0 of frame 0 (3x4)
//! DIR/times.txt               per frame: time in seconds
//! ```
//!
//! DIR itself is laid out like a KITTI object split (`KittiObjectDataset::open(DIR)`) and like one
//! SemanticKITTI sequence (place it at `ROOT/sequences/NN` for `SemanticKittiDataset`).
//!
//! Every file is written atomically (temporary file in the same directory, then rename).

use std::path::{Path, PathBuf};

use glam::Affine3A;
use image::{ImageBuffer, ImageFormat, Luma};
use serde::Serialize;

use super::camera::{CameraRenderOptions, SimCalib, SimImage};
use super::config::SceneConfig;
use super::lidar::SimScan;
use super::scene::Scene;
use crate::atomic::write_atomic;
use crate::{Error, Result};

/// Sub-folders of a simulated dataset.
pub const SUBDIRS: [&str; 6] = [
    "velodyne",
    "labels",
    "image_2",
    "calib",
    "depth_2",
    "semantic_2",
];

/// Paths of one frame's files.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FramePaths {
    /// `velodyne/NNNNNN.bin`.
    pub velodyne: PathBuf,
    /// `labels/NNNNNN.label`.
    pub labels: PathBuf,
    /// `image_2/NNNNNN.png`.
    pub image: PathBuf,
    /// `calib/NNNNNN.txt`.
    pub calib: PathBuf,
    /// `depth_2/NNNNNN.png`.
    pub depth: PathBuf,
    /// `semantic_2/NNNNNN.png`.
    pub semantic: PathBuf,
}

impl FramePaths {
    /// The paths of frame `index` under `dir`.
    pub fn new(dir: &Path, index: u32) -> Self {
        let stem = format!("{index:06}");
        FramePaths {
            velodyne: dir.join("velodyne").join(format!("{stem}.bin")),
            labels: dir.join("labels").join(format!("{stem}.label")),
            image: dir.join("image_2").join(format!("{stem}.png")),
            calib: dir.join("calib").join(format!("{stem}.txt")),
            depth: dir.join("depth_2").join(format!("{stem}.png")),
            semantic: dir.join("semantic_2").join(format!("{stem}.png")),
        }
    }
}

/// Create `dir` and its KITTI sub-folders.
pub fn create_output_dirs(dir: &Path) -> Result<()> {
    for sub in SUBDIRS {
        let p = dir.join(sub);
        std::fs::create_dir_all(&p).map_err(|e| Error::io(&p, e))?;
    }
    Ok(())
}

fn encode_png_u16(path: &Path, width: u32, height: u32, data: Vec<u16>) -> Result<Vec<u8>> {
    let img: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(width, height, data)
        .ok_or_else(|| Error::Mismatch {
            context: path.display().to_string(),
            message: "buffer size does not match the image size".into(),
        })?;
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, ImageFormat::Png)
        .map_err(|e| Error::format(path, format!("PNG encoding failed: {e}")))?;
    Ok(buf.into_inner())
}

/// KITTI depth encoding of a depth map: `round(depth_m * 256)` as u16, 0 for no depth (0, negative,
/// non-finite), saturating at 65535 (255.996 m).
pub fn encode_kitti_depth(depth_m: &[f32]) -> Vec<u16> {
    depth_m
        .iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                (d * 256.0).round().clamp(1.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect()
}

/// Write one frame (scan, image and calibration) into `dir` (sub-folders must exist).
pub fn write_frame(
    dir: &Path,
    index: u32,
    scan: &SimScan,
    image: &SimImage,
    calib: &SimCalib,
) -> Result<FramePaths> {
    let paths = FramePaths::new(dir, index);
    crate::scan::write_kitti_bin(&paths.velodyne, &scan.points)?;
    let labels = scan.points.label.as_deref().unwrap_or(&[]);
    if labels.len() != scan.points.len() {
        return Err(Error::Mismatch {
            context: paths.labels.display().to_string(),
            message: format!("{} points but {} labels", scan.points.len(), labels.len()),
        });
    }
    crate::semantic_kitti::write_labels(&paths.labels, labels)?;
    crate::image_io::write_png(&paths.image, &image.to_rgb_image()?)?;
    write_atomic(&paths.calib, calib.to_kitti_text().as_bytes())?;
    let depth = encode_png_u16(
        &paths.depth,
        image.width,
        image.height,
        encode_kitti_depth(&image.depth_m),
    )?;
    write_atomic(&paths.depth, &depth)?;
    let sem = encode_png_u16(
        &paths.semantic,
        image.width,
        image.height,
        image.semantic.clone(),
    )?;
    write_atomic(&paths.semantic, &sem)?;
    Ok(paths)
}

/// Statistics of one simulated frame (written to `scene.json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameStats {
    /// Frame index.
    pub index: u32,
    /// Time, seconds.
    pub time_s: f32,
    /// Triangles in the scene at this instant.
    pub triangles: usize,
    /// LiDAR rays cast.
    pub rays: usize,
    /// Points returned.
    pub points: usize,
    /// Rays per outcome: return, no hit, too near, grazing, weak, random drop.
    pub outcomes: [usize; 6],
    /// Distinct SemanticKITTI classes among the points.
    pub classes: Vec<u16>,
}

/// What [`simulate_to_dir`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SimSummary {
    /// Scene name.
    pub name: String,
    /// Seed.
    pub seed: u64,
    /// Frames written.
    pub frames: u32,
    /// Per-frame statistics.
    pub frame_stats: Vec<FrameStats>,
}

#[derive(Serialize)]
struct SceneJson<'a> {
    generator: &'static str,
    seed: u64,
    frames: u32,
    config: &'a SceneConfig,
    summary: &'a SimSummary,
}

fn pose_line(p: &Affine3A) -> String {
    let m = p.matrix3;
    let t = p.translation;
    let rows = [
        [m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x],
        [m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y],
        [m.x_axis.z, m.y_axis.z, m.z_axis.z, t.z],
    ];
    rows.iter()
        .flatten()
        .map(|v| format!("{v:.9e}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Generate `config` with `seed` and write `frames` frames into `dir` in the KITTI layout.
/// `progress` is called after every frame with the number of frames done.
pub fn simulate_to_dir(
    config: &SceneConfig,
    seed: u64,
    frames: u32,
    dir: &Path,
    mut progress: impl FnMut(u32),
) -> Result<SimSummary> {
    if !(1..=super::config::MAX_FRAMES).contains(&frames) {
        return Err(Error::Invalid {
            what: "frame count".into(),
            message: format!(
                "{frames}: must be between 1 and {}",
                super::config::MAX_FRAMES
            ),
        });
    }
    let scene = Scene::generate(config, seed)?;
    let sensor = config.lidar.sensor()?;
    // the scene's rig: the config's camera, or the one drawn for this seed ([rig])
    let calib = SimCalib::from_config(scene.camera_config());
    let camera = calib.camera()?;
    let opts = CameraRenderOptions::from(scene.camera_config());
    create_output_dirs(dir)?;
    let mut summary = SimSummary {
        name: config.name.clone(),
        seed,
        frames,
        frame_stats: Vec::new(),
    };
    let mut poses = String::new();
    let mut odo_poses = String::new();
    let mut first_pose: Option<Affine3A> = None;
    let cam_from_lidar = calib.rect_cam0_from_lidar();
    let mut times = String::new();
    for i in 0..frames {
        let snap = scene.snapshot(i);
        let scan = snap.render_lidar(&sensor, &config.lidar.returns)?;
        let image = snap.render_camera(&camera, &opts)?;
        write_frame(dir, i, &scan, &image, &calib)?;
        let mut classes: Vec<u16> = scan
            .points
            .label
            .iter()
            .flatten()
            .map(|l| (l & 0xFFFF) as u16)
            .collect();
        classes.sort_unstable();
        classes.dedup();
        summary.frame_stats.push(FrameStats {
            index: i,
            time_s: snap.time_s,
            triangles: snap.accel.num_triangles(),
            rays: scan.outcome.len(),
            points: scan.points.len(),
            outcomes: scan.outcome_counts(),
            classes,
        });
        poses.push_str(&pose_line(&snap.world_from_lidar));
        poses.push('\n');
        let first = *first_pose.get_or_insert(snap.world_from_lidar);
        let cam0_pose =
            cam_from_lidar * first.inverse() * snap.world_from_lidar * cam_from_lidar.inverse();
        odo_poses.push_str(&pose_line(&cam0_pose));
        odo_poses.push('\n');
        times.push_str(&format!("{:.6e}\n", snap.time_s));
        progress(i + 1);
    }
    write_atomic(&dir.join("lidar_poses.txt"), poses.as_bytes())?;
    write_atomic(&dir.join("poses.txt"), odo_poses.as_bytes())?;
    write_atomic(&dir.join("calib.txt"), calib.to_odometry_text().as_bytes())?;
    write_atomic(&dir.join("times.txt"), times.as_bytes())?;
    let json = SceneJson {
        generator: concat!("veila-data ", env!("CARGO_PKG_VERSION")),
        seed,
        frames,
        config,
        summary: &summary,
    };
    let text = serde_json::to_string_pretty(&json).map_err(|e| Error::Invalid {
        what: "scene.json".into(),
        message: e.to_string(),
    })?;
    write_atomic(&dir.join("scene.json"), text.as_bytes())?;
    Ok(summary)
}
