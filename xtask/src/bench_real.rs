//! The real frames the tests can reach (`../shared/data/real`): a bundle's scans of each against
//! the real scan, next to two image-free baselines. Part of `cargo xtask bench-report`, and on
//! its own `cargo xtask bench-real` (seconds; for iterating on the sim-to-real gap).
//!
//! Per frame (with so few frames every frame is its own row, never a mean):
//! - **range MAE in the camera's view** (m): mean |generated - real| over the range-grid pixels
//!   whose rays the camera sees (`PinholeCamera::frustum_mask`) and where both
//!   scans have a return, with its **coverage** (the share of the real returns in the view that
//!   the scan also has: a baseline that returns only easy pixels cannot hide behind the MAE);
//! - **range MAE of the front half** (`x > 0` of the model's LiDAR frame; full scans only);
//! - **Chamfer distance in the camera's view** (m², PyTorch3D's convention, `veila-metrics`)
//!   between the scans' points on the bundle's grid (the real scan projected onto the same grid,
//!   so the two have the same density);
//! - an overlay PNG: the generated points on the real image above the real scan's;
//! - an encoder panel PNG (`real/<frame>_encoders.png`): the image at the encoders' input size,
//!   the semantic head's labels in SemanticKITTI's colours and the depth head's map, so a wrong
//!   depth read can be traced to what the encoders took the scene for.
//!
//! The generated rows are the mean ± standard deviation over `seeds` samples; the mean network
//! alone (residual bundles) is deterministic. Baselines: the **mean simulated scan** (per-pixel
//! median of simulated training scans, what a model ignoring the image would answer) and the
//! **flat-ground prior** (each ray below the horizon meets a flat ground plane at the LiDAR's
//! mounting height; no return elsewhere).
//!
//! The frames: KITTI object 000000 and 000001, mmdet3d's demo frame 000008 and the nuScenes
//! sample seen by each of its six cameras (CAM_FRONT, issue 18's frame, and five more views of the
//! same sweep, one camera at a time).
//!
//! The model's LiDAR frame has `x` forward along the camera, as KITTI's and the simulator's.
//! nuScenes' LIDAR_TOP has `y` forward, so its frame is turned about `z` by the multiple of 90°
//! that brings the camera's optical axis nearest to `+x` (an exact identity for KITTI), or by the
//! axis's own azimuth for a camera more than 10° off every quarter turn (nuScenes' oblique
//! cameras), before the scan is generated and compared.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};
use veila_data::PointCloud;
use veila_data::image;
use veila_data::semantic_kitti::LabelMap;
use veila_data::vis::render::{OverlayOptions, render_overlay};
use veila_diffusion::SamplerConfig;
use veila_diffusion::app::rig::{RigView, camera_views, load_view, prepare_views};
use veila_diffusion::app::{Bundle, GenerateOptions};
use veila_geom::{LidarSensor, PinholeCamera, ProjectionOptions, Projector, RangeImage, RayTable};
use veila_nn::encoders::small_cnn::{DenseMaps, SmallCnn};

/// KITTI's Velodyne HDL-64E sits 1.73 m above the ground (Geiger et al. 2013, fig. 3).
const KITTI_LIDAR_HEIGHT_M: f32 = 1.73;

/// The nuScenes sample's cameras, in report order: CAM_FRONT (issue 18's frame) first, then the
/// other five views of the same sweep.
const NUSCENES_CAMERAS: [&str; 6] = [
    "CAM_FRONT",
    "CAM_FRONT_LEFT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
];

/// One real frame: a camera image with its calibration and the LiDAR scan taken with it.
#[derive(Debug, Clone)]
pub struct RealFrame {
    /// Short name (`kitti-000000`).
    pub name: String,
    /// Camera image.
    pub image: PathBuf,
    /// Calibration file (KITTI object calib or the nuScenes sample JSON).
    pub calib: PathBuf,
    /// The scan (KITTI `.bin`, nuScenes `.pcd.bin`).
    pub scan: PathBuf,
    /// LiDAR height above the ground, metres (the flat-ground prior).
    pub lidar_height_m: f32,
    /// The scan covers the camera's view only (mmdet3d's demo frame).
    pub cropped: bool,
    /// The calibration's camera to use (`None`: the file's default, KITTI's image_2 or
    /// nuScenes' CAM_FRONT).
    pub camera: Option<String>,
}

/// The folder of the shared real samples beside the workspace.
pub fn real_root(workspace: &Path) -> PathBuf {
    workspace.join("../shared/data/real")
}

/// Every real frame present under `root`, and a line for each one that is missing.
pub fn real_frames(root: &Path) -> Result<(Vec<RealFrame>, Vec<String>)> {
    let mut frames = Vec::new();
    let mut missing = Vec::new();
    let mut kitti = |name: &str, base: &Path, id: &str, scan_dir: &str, cropped: bool| {
        let f = RealFrame {
            name: name.to_string(),
            image: base.join(format!("image_2/{id}.png")),
            calib: base.join(format!("calib/{id}.txt")),
            scan: base.join(format!("{scan_dir}/{id}.bin")),
            lidar_height_m: KITTI_LIDAR_HEIGHT_M,
            cropped,
            camera: None,
        };
        if [&f.image, &f.calib, &f.scan].iter().all(|p| p.is_file()) {
            frames.push(f);
        } else {
            missing.push(format!("{name}: not found under {}", base.display()));
        }
    };
    let k = root.join("kitti/training");
    kitti("kitti-000000", &k, "000000", "velodyne", false);
    kitti("kitti-000001", &k, "000001", "velodyne", false);
    kitti(
        "kitti-000008 (mmdet3d demo, scan cropped to the camera)",
        &root.join("kitti_mmdet3d_demo"),
        "000008",
        "velodyne_reduced",
        true,
    );
    // nuScenes: the one sample JSON and its LIDAR_TOP sweep, seen by each of the six cameras
    // (CAM_FRONT first, the frame of issue 18; the other five are more real views of the same sweep)
    let nus = root.join("nuscenes");
    let calib = std::fs::read_dir(nus.join("calib")).ok().and_then(|d| {
        d.filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| p.extension().is_some_and(|e| e == "json"))
    });
    match calib {
        Some(calib) => {
            let sample = veila_data::nuscenes::NuScenesSample::read_json(&calib)?;
            // lidar2ego's translation: the ego frame's origin lies on the ground
            let height = sample.ego_from_lidar.w_axis.z as f32;
            for name in NUSCENES_CAMERAS {
                let Some(cam) = sample.cameras.get(name) else {
                    missing.push(format!("nuscenes-{name}: not in {}", calib.display()));
                    continue;
                };
                let f = RealFrame {
                    name: format!("nuscenes-{name}"),
                    image: nus.join(&cam.file),
                    calib: calib.clone(),
                    scan: nus.join(&sample.lidar_file),
                    lidar_height_m: height,
                    cropped: false,
                    camera: Some(name.to_string()),
                };
                if f.image.is_file() && f.scan.is_file() {
                    frames.push(f);
                } else {
                    missing.push(format!(
                        "nuscenes-{name}: image or sweep not found under {}",
                        nus.display()
                    ));
                }
            }
        }
        None => missing.push(format!("nuscenes: no calib JSON under {}", nus.display())),
    }
    Ok((frames, missing))
}

/// `mean ± std` of one figure over the samples of one frame.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Spread {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (0 for one value).
    pub std: f64,
}

fn spread(v: &[f64]) -> Spread {
    let (mean, std) = crate::simdata::mean_std(v);
    Spread { mean, std }
}

/// One method's figures on one frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RealRow {
    /// `model`, `mean-network`, `mean-scan` or `flat-ground`.
    pub method: String,
    /// Range MAE over the pixels the camera sees, m.
    pub view_mae_m: Spread,
    /// Share of the real returns in the view that the scan also has.
    pub view_coverage: f64,
    /// Range MAE of the front half (`x > 0`), m; `None` for a cropped scan.
    pub front_mae_m: Option<Spread>,
    /// Range MAE of the front half outside the camera's view (what the image does not show), m;
    /// `None` for a cropped scan and in reports from before 2026-11-26.
    #[serde(default)]
    pub front_unseen_mae_m: Option<Spread>,
    /// Chamfer distance in the camera's view, m².
    pub view_chamfer_m2: Spread,
}

/// Camera depth against the real LiDAR points that project into the (resized) image.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct DepthScore {
    /// Mean |predicted - true| / true.
    pub abs_rel: f64,
    /// Mean |predicted - true|, m.
    pub mae_m: f64,
    /// Share of the points with a prediction.
    pub coverage: f64,
}

/// Camera depth in one region of the image: which part of the picture the depth head gets wrong.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RegionDepth {
    /// `left`, `centre` or `right` third, `upper` or `lower` half: e.g. `left upper`.
    pub region: String,
    /// Real points in the region.
    pub points: usize,
    /// Median camera depth of the real points, m.
    pub real_median_m: f64,
    /// Median predicted depth at those points, m.
    pub predicted_median_m: f64,
    /// Mean |predicted - true| / true over them.
    pub abs_rel: f64,
}

/// [`depth_score`] split into the image's thirds across and halves down (six regions, those
/// without a point left out): a frame's AbsRel is mostly the near road, which the depth head gets
/// right, so the far objects it misses show only here.
pub fn depth_by_region(
    depth_m: &[f32],
    camera: &PinholeCamera,
    points: &[Vec3],
) -> Vec<RegionDepth> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut cells: Vec<Vec<(f64, f64)>> = vec![Vec::new(); 6];
    for (u, v, t) in pixels_hit(camera, points) {
        let (col, row) = (3 * u / w, 2 * v / h);
        cells[row * 3 + col].push((t, depth_m[v * w + u] as f64));
    }
    let median = |mut x: Vec<f64>| {
        x.sort_by(f64::total_cmp);
        let n = x.len();
        if n % 2 == 1 {
            x[n / 2]
        } else {
            0.5 * (x[n / 2 - 1] + x[n / 2])
        }
    };
    let mut out = Vec::new();
    for (i, c) in cells.into_iter().enumerate() {
        if c.is_empty() {
            continue;
        }
        let abs_rel = c.iter().map(|(t, d)| (d - t).abs() / t).sum::<f64>() / c.len() as f64;
        out.push(RegionDepth {
            region: format!(
                "{} {}",
                ["left", "centre", "right"][i % 3],
                ["upper", "lower"][i / 3]
            ),
            points: c.len(),
            real_median_m: median(c.iter().map(|x| x.0).collect()),
            predicted_median_m: median(c.iter().map(|x| x.1).collect()),
            abs_rel,
        });
    }
    out
}

/// The nearest pixel `(u, v)` of every point that projects into `camera`'s image at least 1 m in
/// front of it, with the point's camera depth in metres.
fn pixels_hit<'a>(
    camera: &'a PinholeCamera,
    points: &'a [Vec3],
) -> impl Iterator<Item = (usize, usize, f64)> + 'a {
    let (w, h) = (camera.width as i64, camera.height as i64);
    points.iter().filter_map(move |p| {
        let ip = camera.try_project_in_image(*p)?;
        let (u, v) = (
            (ip.u_px + 0.5).floor() as i64,
            (ip.v_px + 0.5).floor() as i64,
        );
        (ip.depth_m >= 1.0 && u >= 0 && v >= 0 && u < w && v < h).then_some((
            u as usize,
            v as usize,
            ip.depth_m as f64,
        ))
    })
}

/// Scores per-pixel camera depth (`None` = no prediction) against the points' camera depths,
/// nearest pixel of a `width x height` map.
pub fn depth_score(
    depth_m: &[Option<f32>],
    camera: &PinholeCamera,
    points: &[Vec3],
) -> Option<DepthScore> {
    let w = camera.width as usize;
    let (mut rel, mut abs, mut n, mut total) = (0.0f64, 0.0f64, 0usize, 0usize);
    for (u, v, t) in pixels_hit(camera, points) {
        total += 1;
        if let Some(d) = depth_m[v * w + u] {
            rel += (d as f64 - t).abs() / t;
            abs += (d as f64 - t).abs();
            n += 1;
        }
    }
    (n > 0).then(|| DepthScore {
        abs_rel: rel / n as f64,
        mae_m: abs / n as f64,
        coverage: n as f64 / total as f64,
    })
}

/// The depth head's map (metres, `h x w`) of an `h x w` RGB image seen by `camera` (the camera of
/// that image: an encoder with the ground prior computes its input channel from it); `None`
/// without a depth head.
pub fn predict_depth(
    net: &SmallCnn,
    rgb: &[u8],
    camera: &PinholeCamera,
    h: usize,
    w: usize,
) -> Result<Option<Vec<f32>>> {
    Ok(predict_maps(net, rgb, camera, h, w)?.depth_m)
}

/// Both heads' maps of an `h x w` RGB image seen by `camera` (see [`predict_depth`]).
fn predict_maps(
    net: &SmallCnn,
    rgb: &[u8],
    camera: &PinholeCamera,
    h: usize,
    w: usize,
) -> Result<DenseMaps> {
    let img = net
        .config()
        .input_tensor(rgb, h, w, Some(camera), &candle_core::Device::Cpu)?;
    Ok(net.predict_maps(&img)?.swap_remove(0))
}

/// The flat-ground prior in the image ([`veila_geom::flat_ground_depth_map_m`]): each pixel's ray
/// meets the ground plane `height_m` below the (level) LiDAR; `None` at and above the horizon or
/// beyond `max_m`.
pub fn flat_ground_depth(camera: &PinholeCamera, height_m: f32, max_m: f32) -> Vec<Option<f32>> {
    veila_geom::flat_ground_depth_map_m(camera, -height_m)
        .into_iter()
        .map(|d| (d > 0.0 && d <= max_m).then_some(d))
        .collect()
}

/// All rows of one frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RealFrameResult {
    /// The frame's name.
    pub frame: String,
    /// The bundle's depth encoder on the resized real image (its depth head), against the real
    /// points.
    pub encoder_depth: Option<DepthScore>,
    /// The same by image region ([`depth_by_region`]; empty without a depth head, and in reports
    /// written before 2026-11-25, which lack the field).
    #[serde(default)]
    pub encoder_depth_regions: Vec<RegionDepth>,
    /// The flat-ground prior's camera depth at the same points.
    pub ground_depth: Option<DepthScore>,
    /// Real returns on the bundle's grid inside the camera's view.
    pub real_view_returns: usize,
    /// The rows.
    pub rows: Vec<RealRow>,
    /// The overlay PNG, relative to the report folder.
    pub overlay: String,
}

/// The real-frame section of a report.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RealReport {
    /// Samples per frame behind each generated row.
    pub seeds: usize,
    /// Sampler of the generated rows.
    pub sampler: String,
    /// Frames not found.
    pub missing: Vec<String>,
    /// Per frame.
    pub frames: Vec<RealFrameResult>,
}

/// Largest angle between a camera's optical axis and the nearest quarter turn of the LiDAR's `x`
/// for which the frame turns by that quarter turn exactly (sensor axes stay on the grid).
const QUARTER_TURN_TOLERANCE_DEG: f32 = 10.0;

/// Turn about `z` from the dataset's LiDAR frame into the model's, whose `x` is the camera's
/// optical axis (as in training): the nearest multiple of 90° when the axis lies within
/// [`QUARTER_TURN_TOLERANCE_DEG`] of it (KITTI: the identity; nuScenes CAM_FRONT and CAM_BACK),
/// else the axis's own azimuth (nuScenes' four oblique cameras, 55-110° off the LiDAR's `y`).
fn model_from_lidar(camera: &PinholeCamera) -> Mat4 {
    let axis = optical_axis_lidar(camera);
    let yaw = axis.y.atan2(axis.x);
    let quarter = (yaw / std::f32::consts::FRAC_PI_2).round() * std::f32::consts::FRAC_PI_2;
    let turn = if (yaw - quarter).abs() <= QUARTER_TURN_TOLERANCE_DEG.to_radians() {
        quarter
    } else {
        yaw
    };
    if turn == 0.0 {
        Mat4::IDENTITY
    } else {
        Mat4::from_rotation_z(-turn)
    }
}

/// The camera's optical axis (its `+z`) in the LiDAR frame.
fn optical_axis_lidar(camera: &PinholeCamera) -> Vec3 {
    camera.cam_from_lidar.inverse().transform_vector3(Vec3::Z)
}

/// Masks of the range grid: in the camera's view, in the front half, in the front half outside
/// the view.
struct Regions {
    view: Vec<bool>,
    front: Vec<bool>,
    front_unseen: Vec<bool>,
    dirs: Vec<Vec3>,
}

impl Regions {
    fn new(sensor: &LidarSensor, camera: &PinholeCamera) -> Result<Self> {
        let rays = RayTable::new(sensor)?;
        let dirs = rays.dirs().to_vec();
        let view = camera.frustum_mask(&rays);
        let front: Vec<bool> = dirs.iter().map(|d| d.x > 0.0).collect();
        let front_unseen = front.iter().zip(&view).map(|(&f, &v)| f && !v).collect();
        Ok(Regions {
            view,
            front,
            front_unseen,
            dirs,
        })
    }

    /// (MAE, coverage) of `scan` against `real` over `mask`.
    fn mae(mask: &[bool], scan: &RangeImage, real: &RangeImage) -> (f64, f64) {
        let (mut sum, mut n, mut real_n) = (0.0f64, 0usize, 0usize);
        for i in 0..mask.len() {
            if mask[i] && real.mask[i] {
                real_n += 1;
                if scan.mask[i] {
                    sum += (scan.range_m[i] - real.range_m[i]).abs() as f64;
                    n += 1;
                }
            }
        }
        let mae = if n > 0 { sum / n as f64 } else { f64::NAN };
        (mae, n as f64 / real_n.max(1) as f64)
    }

    fn points(&self, scan: &RangeImage) -> Vec<Vec3> {
        (0..self.view.len())
            .filter(|&i| self.view[i] && scan.mask[i])
            .map(|i| self.dirs[i] * scan.range_m[i])
            .collect()
    }
}

/// How to sample the generated rows.
pub struct RealOptions<'a> {
    /// Sampler of the bundle's scans.
    pub sampler: &'a SamplerConfig,
    /// Its label for the report.
    pub sampler_label: String,
    /// Samples per frame.
    pub seeds: usize,
    /// The mean simulated scan (the image-free baseline) of the bundle's own training list.
    pub mean_scan: &'a RangeImage,
    /// The street list's mean scan (`scenes/train.txt`, which every training list extends) with its
    /// row label, for a bundle trained on another list: the baseline moves with the list, so both
    /// are reported.
    pub reference_mean_scan: Option<&'a (String, RangeImage)>,
}

/// The mean scan of the street list (`scenes/train.txt`, `frames` frames) and its row label, when
/// the bundle trained on another list; `None` when it trained on that one.
pub fn reference_mean_scan(
    cfg: &veila_diffusion::app::bundle::BundleConfig,
    frames: usize,
) -> Result<Option<(String, RangeImage)>> {
    let own = crate::simdata::train_split_of(cfg);
    let streets = PathBuf::from(crate::simdata::DEFAULT_SCENES);
    if own == streets {
        return Ok(None);
    }
    let train = crate::simdata::render_split(
        &crate::simdata::workspace_root().join(&streets),
        frames,
        cfg,
        "simulating the street list's baseline frames",
    )?;
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    Ok(Some((
        format!("mean-scan ({})", streets.display()),
        veila_metrics::baseline::median_scan(&refs)?,
    )))
}

fn read_cloud(path: &Path) -> Result<PointCloud> {
    let loaded = veila_data::scan::read_points(path)?;
    Ok(loaded.cloud)
}

/// Evaluates `bundle` on every real frame present, writing the overlays into `out/real/`.
pub fn evaluate(bundle: &Bundle, opts: &RealOptions<'_>, out: &Path) -> Result<RealReport> {
    let root = real_root(&crate::simdata::workspace_root());
    let (frames, missing) = real_frames(&root)?;
    for m in &missing {
        println!("  real frames: skipped {m}");
    }
    let dir = out.join("real");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let sensor = &bundle.config.denoiser.sensor;
    let projector = Projector::new(sensor, ProjectionOptions::default())?;
    // the label colours of the encoder panels (the panels go without labels where it is absent)
    let label_map = LabelMap::read(&root.join("semantickitti/semantic-kitti.yaml")).ok();
    let mut results = Vec::new();
    for f in &frames {
        let view = load_view(&f.image, &f.calib, f.camera.as_deref())
            .with_context(|| format!("real frame {}", f.name))?;
        let model_from = model_from_lidar(&view.camera);
        let camera = PinholeCamera {
            cam_from_lidar: view.camera.cam_from_lidar * model_from.inverse(),
            ..view.camera
        };
        let view = RigView { camera, ..view };
        let cloud = read_cloud(&f.scan)?;
        let xyz: Vec<Vec3> = cloud
            .xyz
            .iter()
            .map(|p| model_from.transform_point3(*p))
            .collect();
        let (real, _) = projector.project(&xyz, None, None)?;
        let regions = Regions::new(sensor, &view.camera)?;
        let real_pts = regions.points(&real);

        let prepared = prepare_views(&bundle.config, std::slice::from_ref(&view))?;
        let views = camera_views(&prepared);
        let (small_rgb, small_cam) = &prepared[0];
        let encoder_map = match bundle.depth.as_ref().and_then(|d| d.as_small_cnn()) {
            Some(net) => predict_depth(
                net,
                small_rgb,
                small_cam,
                bundle.config.image_height,
                bundle.config.image_width,
            )?,
            None => None,
        };
        let stem: String = f.name.chars().take_while(|c| !c.is_whitespace()).collect();
        if let Some(img) = encoder_maps_png(
            bundle,
            small_rgb,
            small_cam,
            encoder_map.as_deref(),
            label_map.as_ref(),
        )? {
            let file = out.join(format!("real/{stem}_encoders.png"));
            img.save(&file)
                .with_context(|| format!("writing {}", file.display()))?;
        }
        let encoder_depth = encoder_map.as_ref().and_then(|d| {
            let d: Vec<Option<f32>> = d.iter().copied().map(Some).collect();
            depth_score(&d, small_cam, &xyz)
        });
        let encoder_depth_regions = encoder_map
            .as_ref()
            .map_or_else(Vec::new, |d| depth_by_region(d, small_cam, &xyz));
        let ground_depth = depth_score(
            &flat_ground_depth(small_cam, f.lidar_height_m, sensor.max_range_m),
            small_cam,
            &xyz,
        );
        let scored = |method: &str, scans: &[RangeImage]| -> Result<RealRow> {
            let mut view_mae = Vec::new();
            let mut coverage = Vec::new();
            let mut front = Vec::new();
            let mut unseen = Vec::new();
            let mut chamfer = Vec::new();
            for s in scans {
                let (m, c) = Regions::mae(&regions.view, s, &real);
                view_mae.push(m);
                coverage.push(c);
                front.push(Regions::mae(&regions.front, s, &real).0);
                unseen.push(Regions::mae(&regions.front_unseen, s, &real).0);
                let pts = regions.points(s);
                chamfer.push(
                    veila_metrics::chamfer::chamfer_distance(&pts, &real_pts)
                        .map(|c| c.value())
                        .unwrap_or(f64::NAN),
                );
            }
            Ok(RealRow {
                method: method.to_string(),
                view_mae_m: spread(&view_mae),
                view_coverage: spread(&coverage).mean,
                front_mae_m: (!f.cropped).then(|| spread(&front)),
                front_unseen_mae_m: (!f.cropped).then(|| spread(&unseen)),
                view_chamfer_m2: spread(&chamfer),
            })
        };
        let generate = |seed: u64, residual_weight: f64| -> Result<RangeImage> {
            let mut s = bundle.generate(
                &views,
                &GenerateOptions {
                    sampler: opts.sampler.clone(),
                    samples: 1,
                    seed,
                    unconditional: false,
                    residual_weight,
                },
                |_, _| {},
            )?;
            Ok(s.swap_remove(0))
        };
        let samples = (0..opts.seeds.max(1) as u64)
            .map(|s| generate(s, 1.0))
            .collect::<Result<Vec<_>>>()?;
        let mut rows = vec![scored("model", &samples)?];
        if bundle.mean.is_some() {
            rows.push(scored("mean-network", &[generate(0, 0.0)?])?);
        }
        rows.push(scored("mean-scan", std::slice::from_ref(opts.mean_scan))?);
        if let Some((label, scan)) = opts.reference_mean_scan {
            rows.push(scored(label, std::slice::from_ref(scan))?);
        }
        rows.push(scored(
            "flat-ground",
            &[veila_geom::flat_ground_range_image(
                sensor,
                -f.lidar_height_m,
            )?],
        )?);

        // overlay: the first sample's points above the real scan's (both on the model's grid)
        let gen_pts = regions.points(&samples[0]);
        let ov = |pts: &[Vec3]| -> Result<image::RgbImage> {
            let opts = OverlayOptions {
                radius_px: 2,
                ..OverlayOptions::default()
            };
            Ok(render_overlay(&view.image, &view.camera, pts, &opts)?.image)
        };
        let (top, bottom) = (ov(&gen_pts)?, ov(&real_pts)?);
        let mut both = image::RgbImage::new(top.width(), top.height() * 2);
        image::imageops::replace(&mut both, &top, 0, 0);
        image::imageops::replace(&mut both, &bottom, 0, top.height() as i64);
        let file = format!("real/{stem}_overlay.png");
        both.save(out.join(&file))
            .with_context(|| format!("writing {}", out.join(&file).display()))?;
        results.push(RealFrameResult {
            frame: f.name.clone(),
            encoder_depth,
            encoder_depth_regions,
            ground_depth,
            real_view_returns: real_pts.len(),
            rows,
            overlay: file,
        });
    }
    Ok(RealReport {
        seeds: opts.seeds.max(1),
        sampler: opts.sampler_label.clone(),
        missing,
        frames: results,
    })
}

/// The encoders' view of one real image, at their input size and scaled up 3x: the image, the
/// semantic head's labels (in `labels`' colours, when given) and the depth head's map
/// `depth_m` (viridis, log scale, 2 m bright to 80 m dark), stacked; `None` when the bundle's
/// encoders are not small CNNs.
fn encoder_maps_png(
    bundle: &Bundle,
    rgb: &[u8],
    camera: &PinholeCamera,
    depth_m: Option<&[f32]>,
    labels: Option<&LabelMap>,
) -> Result<Option<image::RgbImage>> {
    let (h, w) = (bundle.config.image_height, bundle.config.image_width);
    let (Some(net), Some(depth_m)) = (
        bundle.semantic.as_ref().and_then(|e| e.as_small_cnn()),
        depth_m,
    ) else {
        return Ok(None);
    };
    let panel = |f: &dyn Fn(usize) -> [u8; 3]| {
        let img = image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
            image::Rgb(f(y as usize * w + x as usize))
        });
        image::imageops::resize(
            &img,
            3 * w as u32,
            3 * h as u32,
            image::imageops::FilterType::Nearest,
        )
    };
    let mut parts = vec![panel(&|k| [rgb[3 * k], rgb[3 * k + 1], rgb[3 * k + 2]])];
    if let (Some(map), Some(ids)) = (labels, predict_maps(net, rgb, camera, h, w)?.labels) {
        parts.push(panel(&|k| map.train_color_rgb(ids[k].min(255) as u8)));
    }
    parts.push(panel(&|k| {
        let t = (depth_m[k].max(2.0) / 2.0).ln() / (80.0f32 / 2.0).ln();
        veila_data::vis::render::Colormap::Viridis.rgb(1.0 - t)
    }));
    Ok(Some(veila_data::vis::render::stack_vertical(&parts)))
}

/// Arguments of `cargo xtask bench-real`.
#[derive(Debug, clap::Args)]
pub struct BenchRealArgs {
    /// Model bundle.
    #[arg(long, default_value = "models/default")]
    model: PathBuf,
    /// Output folder (report.md, report.json, real/*.png).
    #[arg(long, default_value = "target/bench-real")]
    out: PathBuf,
    /// Samples per frame.
    #[arg(long, default_value_t = 4)]
    seeds: usize,
    /// Sampler: ddpm, ddim or dpm.
    #[arg(long, default_value = "ddpm", value_parser = ["ddpm", "ddim", "dpm"])]
    sampler: String,
    /// Sampler steps.
    #[arg(long, default_value_t = 4)]
    steps: usize,
    /// Simulated training frames behind the mean-scan baseline.
    #[arg(long, default_value_t = 96)]
    baseline_frames: usize,
}

/// `cargo xtask bench-real`.
pub fn run(args: BenchRealArgs) -> Result<()> {
    let t = std::time::Instant::now();
    let root = crate::simdata::workspace_root();
    let abs = |p: &Path| {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            root.join(p)
        }
    };
    let (model_dir, out) = (abs(&args.model), abs(&args.out));
    let bundle = Bundle::from_dir(&model_dir, &candle_core::Device::Cpu)
        .with_context(|| format!("loading {}", model_dir.display()))?;
    let train = crate::simdata::render_split(
        &root.join(crate::simdata::train_split_of(&bundle.config)),
        args.baseline_frames,
        &bundle.config,
        "simulating baseline train frames",
    )?;
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    let median = veila_metrics::baseline::median_scan(&refs)?;
    let streets = reference_mean_scan(&bundle.config, args.baseline_frames)?;
    let sampler = sampler_for(
        &args.sampler,
        args.steps,
        bundle.config.sampler.guidance_scale,
    )?;
    let report = evaluate(
        &bundle,
        &RealOptions {
            sampler: &sampler,
            sampler_label: format!("{} {} steps", sampler.kind.title(), args.steps),
            seeds: args.seeds,
            mean_scan: &median,
            reference_mean_scan: streets.as_ref(),
        },
        &out,
    )?;
    let md = format!(
        "# Real frames: {}\n\n{}",
        args.model.display(),
        markdown(&report)
    );
    veila_data::atomic::write_atomic(&out.join("report.md"), md.as_bytes())?;
    veila_data::atomic::write_atomic(
        &out.join("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    print!("{}", markdown(&report));
    println!(
        "wrote {} in {:.0} s",
        out.display(),
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The section's Markdown.
pub fn markdown(r: &RealReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "## Real frames\n\nThe bundle on every real frame the tests can reach (`../shared/data/real`), \
         against the real scan projected onto the bundle's grid. `model`: {} samples ({}), mean ± \
         std; `mean-network`: the residual bundle's mean network alone; `mean-scan`: the per-pixel \
         median of simulated scans of the bundle's training list (for a bundle trained on another \
         list than the streets of `scenes/train.txt`, a second row has theirs); `flat-ground`: a \
         flat ground plane at the LiDAR's height. View = the grid pixels the camera sees; coverage = share of the real returns \
         there that the scan also has (MAE counts only pixels where both have one). The overlays \
         (generated points above, real below, coloured by depth) are written under `real/` by the \
         command and are not committed: they contain the real images, which keep their licences.\n",
        r.seeds, r.sampler
    );
    for m in &r.missing {
        let _ = writeln!(s, "- skipped: {m}");
    }
    for f in &r.frames {
        let _ = writeln!(
            s,
            "\n### {}\n\n{} real returns in the camera's view. ![overlay: generated above, real below]({})\n",
            f.frame, f.real_view_returns, f.overlay
        );
        let dep = |d: &Option<DepthScore>| {
            d.map_or("-".to_string(), |d| {
                format!(
                    "AbsRel {:.3}, MAE {:.2} m ({:.0} % of the points)",
                    d.abs_rel,
                    d.mae_m,
                    100.0 * d.coverage
                )
            })
        };
        let _ = writeln!(
            s,
            "Camera depth at the real points: depth encoder {}; flat-ground prior {}.\n",
            dep(&f.encoder_depth),
            dep(&f.ground_depth)
        );
        if !f.encoder_depth_regions.is_empty() {
            let _ = write!(
                s,
                "The depth encoder by image region (thirds across, halves down), real median / \
                 encoder median depth (m), AbsRel:"
            );
            for r in &f.encoder_depth_regions {
                let _ = write!(
                    s,
                    " {} {:.1} / {:.1}, {:.2};",
                    r.region, r.real_median_m, r.predicted_median_m, r.abs_rel
                );
            }
            s.pop();
            s.push_str(".\n\n");
        }
        let _ = writeln!(
            s,
            "| method | range MAE in view (m) | coverage | range MAE front half (m) | front half outside the view (m) | Chamfer in view (m²) |\n|---|---|---|---|---|---|"
        );
        for row in &f.rows {
            let pm = |x: &Spread| {
                if x.std > 0.0 {
                    format!("{:.2} ± {:.2}", x.mean, x.std)
                } else {
                    format!("{:.2}", x.mean)
                }
            };
            let _ = writeln!(
                s,
                "| {} | {} | {:.0} % | {} | {} | {} |",
                row.method,
                pm(&row.view_mae_m),
                100.0 * row.view_coverage,
                row.front_mae_m.as_ref().map_or("-".to_string(), pm),
                row.front_unseen_mae_m.as_ref().map_or("-".to_string(), pm),
                pm(&row.view_chamfer_m2)
            );
        }
    }
    s
}

/// The sampler a benchmark's `--sampler` names ([`SamplerConfig::named`]), with `steps` steps and
/// the guidance scale `guidance`.
pub fn sampler_for(name: &str, steps: usize, guidance: f64) -> Result<SamplerConfig> {
    let mut s = SamplerConfig::named(name, steps)?;
    s.guidance_scale = guidance;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// KITTI-like axes: camera `x` right = LiDAR `-y`, `y` down = LiDAR `-z`, `z` forward = LiDAR `+x`.
    fn kitti_axes() -> Mat4 {
        Mat4::from_cols(
            glam::Vec4::new(0., 0., 1., 0.),
            glam::Vec4::new(-1., 0., 0., 0.),
            glam::Vec4::new(0., -1., 0., 0.),
            glam::Vec4::W,
        )
    }

    #[test]
    fn the_street_mean_scan_joins_only_for_a_bundle_trained_on_another_list() {
        use veila_diffusion::app::bundle::BundleConfig;
        let mut cfg = BundleConfig::cpu_default(veila_diffusion::app::bundle::Variant::Full);
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train.txt" });
        assert!(reference_mean_scan(&cfg, 3).unwrap().is_none());
        // a bundle without a recorded list was trained on the street list
        cfg.provenance = serde_json::Value::Null;
        assert!(reference_mean_scan(&cfg, 3).unwrap().is_none());
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train-v5.txt" });
        let (label, scan) = reference_mean_scan(&cfg, 4).unwrap().unwrap();
        assert_eq!(label, "mean-scan (scenes/train.txt)");
        // the per-pixel median of the street list's first frames, not of the bundle's own list (whose
        // fourth frame is a T junction)
        let render = |list: &str| {
            crate::simdata::render_split(&crate::simdata::workspace_root().join(list), 4, &cfg, "")
                .unwrap()
        };
        let median = |frames: &[crate::simdata::SimExample]| {
            let refs: Vec<&RangeImage> = frames.iter().map(|e| &e.range).collect();
            veila_metrics::baseline::median_scan(&refs).unwrap()
        };
        assert_eq!(scan.range_m, median(&render("scenes/train.txt")).range_m);
        assert_ne!(scan.range_m, median(&render("scenes/train-v5.txt")).range_m);
    }

    /// A 1200 x 360 KITTI-size pinhole camera (focal 700 px).
    fn wide_camera(cam_from_lidar: Mat4) -> PinholeCamera {
        let k = [
            [700.0, 0.0, 600.0, 0.0],
            [0.0, 700.0, 180.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        PinholeCamera::new(k, cam_from_lidar, 1200, 360).unwrap()
    }

    #[test]
    fn the_front_half_splits_into_the_view_and_the_unseen_rest() {
        let sensor = LidarSensor::hdl64e();
        let cam = wide_camera(kitti_axes());
        let r = Regions::new(&sensor, &cam).unwrap();
        let n = r.front.len();
        let count = |m: &[bool]| m.iter().filter(|&&b| b).count();
        // a KITTI camera looks along +x: its view lies inside the front half, and the unseen part
        // is the rest of it; 2 atan(600 / 700) = 81.2 degrees of the front half's 180
        for i in 0..n {
            assert!(!r.view[i] || r.front[i], "pixel {i} seen but behind");
            assert_eq!(r.front_unseen[i], r.front[i] && !r.view[i], "pixel {i}");
        }
        // by columns: the camera's 28-degree height cuts the beams too
        let (rows, cols) = (sensor.rows as usize, sensor.cols as usize);
        let any_row = |m: &[bool], c: usize| (0..rows).any(|row| m[row * cols + c]);
        let seen_cols = (0..cols).filter(|&c| any_row(&r.view, c)).count();
        let front_cols = (0..cols).filter(|&c| any_row(&r.front, c)).count();
        let seen_share = seen_cols as f64 / front_cols as f64;
        let expected = 2.0 * (600.0f64 / 700.0).atan().to_degrees() / 180.0;
        assert!(
            (seen_share - expected).abs() < 0.03,
            "{seen_share} vs {expected}"
        );
        // the front MAE is the returns-weighted mix of the seen and unseen parts' MAEs
        let ranges = |k: usize| (0..n).map(|i| 5.0 + (i % k) as f32).collect::<Vec<f32>>();
        let real = RangeImage::try_from_range_m(sensor.rows, sensor.cols, ranges(7)).unwrap();
        let scan = RangeImage::try_from_range_m(sensor.rows, sensor.cols, ranges(5)).unwrap();
        let seen_front: Vec<bool> = (0..n).map(|i| r.front[i] && r.view[i]).collect();
        let (front, _) = Regions::mae(&r.front, &scan, &real);
        let (seen, _) = Regions::mae(&seen_front, &scan, &real);
        let (unseen, _) = Regions::mae(&r.front_unseen, &scan, &real);
        let (ns, nu) = (count(&seen_front) as f64, count(&r.front_unseen) as f64);
        let mix = (seen * ns + unseen * nu) / (ns + nu);
        assert!((front - mix).abs() < 1e-9, "{front} vs {mix}");
    }

    #[test]
    fn flat_ground_depth_points_lie_on_the_plane() {
        let k = [
            [200.0, 0.0, 160.0, 12.0],
            [0.0, 200.0, 48.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        // KITTI-like axes, the camera pitched down by 5 degrees and 0.1 m above the LiDAR
        let axes = kitti_axes();
        let cam_from_lidar = Mat4::from_rotation_x(5f32.to_radians())
            * axes
            * Mat4::from_translation(Vec3::new(0.0, 0.0, -0.1));
        let cam = PinholeCamera::new(k, cam_from_lidar, 320, 96).unwrap();
        let d = flat_ground_depth(&cam, 1.73, 80.0);
        let mut hits = 0;
        for v in 0..96u32 {
            for u in 0..320u32 {
                if let Some(depth) = d[(v * 320 + u) as usize] {
                    hits += 1;
                    let p = cam.try_back_project(u as f32, v as f32, depth).unwrap();
                    assert!((p.z + 1.73).abs() < 1e-3, "{p}");
                    // and projecting it back lands on the pixel
                    let ip = cam.try_project(p).unwrap();
                    assert!((ip.u_px - u as f32).abs() < 1e-2 && (ip.v_px - v as f32).abs() < 1e-2);
                }
            }
        }
        // the lower rows see the ground, the top row does not (pitched 5 deg down, fov ~27 deg)
        assert!(hits > 320 * 30);
        assert!(d[..320].iter().all(|x| x.is_none()));
        // nothing beyond max_m survives
        let near = flat_ground_depth(&cam, 1.73, 10.0);
        assert!(near.iter().flatten().all(|&x| x <= 10.0));
        assert!(near.iter().flatten().count() < hits);
    }

    #[test]
    fn depth_by_region_splits_the_image_and_scores_each_part_apart() {
        let k = [
            [100.0, 0.0, 150.0, 0.0],
            [0.0, 100.0, 50.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        // camera frame = LiDAR frame: z forward, x right, y down
        let cam = PinholeCamera::new(k, Mat4::IDENTITY, 300, 100).unwrap();
        // a map that is right everywhere but the upper left third, where it reads 10 m
        let truth = |u: usize, v: usize| 5.0 + (u + v) as f32 * 0.1;
        let mut map = vec![0.0f32; 300 * 100];
        for v in 0..100 {
            for u in 0..300 {
                map[v * 300 + u] = if u < 100 && v < 50 { 10.0 } else { truth(u, v) };
            }
        }
        // one point at every fifth pixel centre, at the true depth
        let mut pts = Vec::new();
        for v in (0..100).step_by(5) {
            for u in (0..300).step_by(5) {
                let z = truth(u, v);
                pts.push(Vec3::new(
                    (u as f32 - 150.0) * z / 100.0,
                    (v as f32 - 50.0) * z / 100.0,
                    z,
                ));
            }
        }
        let r = depth_by_region(&map, &cam, &pts);
        let names: Vec<&str> = r.iter().map(|x| x.region.as_str()).collect();
        assert_eq!(
            names,
            [
                "left upper",
                "centre upper",
                "right upper",
                "left lower",
                "centre lower",
                "right lower"
            ]
        );
        assert_eq!(r.iter().map(|x| x.points).sum::<usize>(), pts.len());
        for x in &r[1..] {
            assert!(x.abs_rel < 1e-4, "{x:?}");
            assert!(
                (x.real_median_m - x.predicted_median_m).abs() < 1e-3,
                "{x:?}"
            );
        }
        // brute force for the upper left: truths 5.0 + (u + v) / 10 over u, v in 0, 5, .., 45
        let t: Vec<f64> = (0..100)
            .step_by(5)
            .flat_map(|u| (0..50).step_by(5).map(move |v| 5.0 + (u + v) as f64 * 0.1))
            .collect();
        let want = t.iter().map(|t| (10.0 - t).abs() / t).sum::<f64>() / t.len() as f64;
        assert!(
            (r[0].abs_rel - want).abs() < 1e-4,
            "{} {want}",
            r[0].abs_rel
        );
        assert_eq!(r[0].predicted_median_m, 10.0);
        // a frame with points in one region reports only that one
        let one = depth_by_region(&map, &cam, &pts[..1]);
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].region, "left upper");
    }

    #[test]
    fn nuscenes_frame_turns_a_quarter_and_kitti_not_at_all() {
        let axes = kitti_axes();
        let kitti = wide_camera(axes);
        assert_eq!(model_from_lidar(&kitti), Mat4::IDENTITY);
        // nuScenes-like: the optical axis along the LiDAR's +y; the model's +x must be it
        let nus = wide_camera(axes * Mat4::from_rotation_z(-std::f32::consts::FRAC_PI_2));
        let m = model_from_lidar(&nus);
        let axis_lidar = optical_axis_lidar(&nus);
        let axis_model = m.transform_vector3(axis_lidar);
        assert!((axis_model - Vec3::X).length() < 1e-5, "{axis_model}");
    }

    #[test]
    fn every_nuscenes_camera_is_a_frame_and_faces_the_models_x() {
        let root = real_root(&crate::simdata::workspace_root());
        if !root.join("nuscenes").is_dir() {
            eprintln!("skipped: no real samples under {}", root.display());
            return;
        }
        let (frames, _) = real_frames(&root).unwrap();
        let nus: Vec<&RealFrame> = frames
            .iter()
            .filter(|f| f.name.starts_with("nuscenes-"))
            .collect();
        let names: Vec<&str> = nus.iter().map(|f| f.name.as_str()).collect();
        let want: Vec<String> = NUSCENES_CAMERAS
            .iter()
            .map(|c| format!("nuscenes-{c}"))
            .collect();
        assert_eq!(names, want);
        let mut images = std::collections::HashSet::new();
        for f in nus {
            let view = load_view(&f.image, &f.calib, f.camera.as_deref()).unwrap();
            assert!(
                images.insert(f.image.clone()),
                "{} repeats an image",
                f.name
            );
            // the camera's optical axis, turned into the model's frame, is within 10 deg of +x
            let axis = optical_axis_lidar(&view.camera);
            let a = model_from_lidar(&view.camera).transform_vector3(axis);
            let off = a.y.atan2(a.x).to_degrees().abs();
            assert!(
                off <= QUARTER_TURN_TOLERANCE_DEG + 1e-3,
                "{}: {off} deg",
                f.name
            );
        }
    }

    #[test]
    fn an_oblique_camera_turns_by_its_own_azimuth_and_a_near_axis_one_by_the_quarter() {
        // a camera looking `deg` to the left of the LiDAR's +x
        let looking = |deg: f32| {
            let c = wide_camera(kitti_axes() * Mat4::from_rotation_z(-deg.to_radians()));
            let axis_lidar = optical_axis_lidar(&c);
            (model_from_lidar(&c), axis_lidar)
        };
        for deg in [55.0f32, -55.0, 110.0, -110.0, 135.0, 30.0] {
            let (m, axis) = looking(deg);
            let a = m.transform_vector3(axis);
            assert!((a - Vec3::X).length() < 1e-5, "{deg}: {a}");
        }
        // within 10 degrees of a quarter turn: the quarter turn itself, the axis a little off +x
        for (deg, quarter) in [(4.0f32, 0.0f32), (-8.0, 0.0), (95.0, 90.0), (183.0, 180.0)] {
            let (m, axis) = looking(deg);
            let want = Mat4::from_rotation_z(-quarter.to_radians());
            let got = m.transform_vector3(Vec3::X);
            assert!(
                (got - want.transform_vector3(Vec3::X)).length() < 1e-5,
                "{deg}: {got}"
            );
            let a = m.transform_vector3(axis);
            let off = a.y.atan2(a.x).to_degrees();
            assert!((off - (deg - quarter)).abs() < 1e-3, "{deg}: {off}");
        }
    }
}
