//! The real frames the tests can reach (`../shared/data/real`): a bundle's scans of each against
//! the real scan, next to two image-free baselines ([`evaluate`], [`RealReport::markdown`]). The
//! real-frame section of `cargo xtask bench-report`, and on its own `cargo xtask bench-real`
//! (seconds; for iterating on the sim-to-real gap), which write the report. The mean-scan
//! baselines are simulated here too ([`mean_scan_of`], [`reference_mean_scan`]).
//!
//! Per frame (with so few frames every frame is its own row, never a mean):
//! - **range MAE in the camera's view** (m): mean |generated - real| over the range-grid pixels
//!   whose rays the camera sees (`PinholeCamera::frustum_mask`) and where both
//!   scans have a return, with its **coverage** (the share of the real returns in the view that
//!   the scan also has: a baseline that returns only easy pixels cannot hide behind the MAE);
//! - **range MAE of the front half** (the half ahead of the camera, to the nearest quarter turn;
//!   full scans only), and of the part of it outside the camera's view;
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
//! Every frame goes from its image and calibration to scans through `ScanPipeline`, as every
//! door does: a LiDAR frame whose forward axis is not the camera's (nuScenes: `y` forward) is
//! turned by quarter turns into the model's frame for sampling and back. The scans are scored in
//! the calibration's LiDAR frame (`veila_metrics::view`), the simulator's mean scans turned into
//! it by the same quarter turns; the front half is the half that the pipeline's quarter turn brings
//! forward. The oblique nuScenes cameras (55-110° off the LiDAR's
//! `y`) are sampled the way `veila generate` samples them, with the camera off the model's axis.

use std::path::{Path, PathBuf};

use candle_core::Device;
use glam::Vec3;
use serde::{Deserialize, Serialize};
use veila_data::image;
use veila_data::semantic_kitti::LabelMap;
use veila_data::vis::render::{OverlayOptions, render_overlay};
use veila_geom::{PinholeCamera, ProjectionOptions, Projector, RangeImage};
use veila_metrics::view::{
    DepthScore, RegionDepth, ViewRegions, ViewScores, depth_by_region, depth_score,
    flat_ground_depth,
};

use super::progress::Progress;
use super::rig::{load_view, prepare_view};
use super::scoring::encoder_maps;
use super::sim_examples::{DEFAULT_SCENES, RenderStyle, render_split_shown, train_split_of};
use super::{Bundle, BundleConfig, GenerateOptions, ScanPipeline};
use crate::SamplerConfig;
use crate::error::{Error, Result};

/// KITTI's Velodyne HDL-64E sits 1.73 m above the ground (Geiger et al. 2013, fig. 3).
const KITTI_LIDAR_HEIGHT_M: f32 = 1.73;

/// The nuScenes sample's cameras, in report order: CAM_FRONT (issue 18's frame) first, then the
/// other five views of the same sweep.
pub const NUSCENES_CAMERAS: [&str; 6] = [
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

/// The mean-scan baseline of a scene list: the per-pixel median of the simulated scans of its
/// first `frames` frames (`list` relative to the workspace `root`), rendered for `cfg`.
pub fn mean_scan_of(
    root: &Path,
    list: &Path,
    frames: usize,
    cfg: &BundleConfig,
    label: &str,
    progress: &dyn Progress,
) -> Result<RangeImage> {
    let style = RenderStyle::default();
    let train = render_split_shown(root, list, frames, cfg, &style, label, progress)?;
    let refs: Vec<&RangeImage> = train.iter().map(|e| &e.range).collect();
    Ok(veila_metrics::baseline::median_scan(&refs)?)
}

/// The mean scan of the street list ([`DEFAULT_SCENES`], `frames` frames) and its row label, when
/// the bundle of `cfg` trained on another list; `None` when it trained on that one
/// ([`RealOptions::reference_mean_scan`]).
pub fn reference_mean_scan(
    root: &Path,
    cfg: &BundleConfig,
    frames: usize,
    progress: &dyn Progress,
) -> Result<Option<(String, RangeImage)>> {
    let streets = PathBuf::from(DEFAULT_SCENES);
    if train_split_of(cfg) == streets {
        return Ok(None);
    }
    let label = "simulating the street list's baseline frames";
    let median = mean_scan_of(root, &streets, frames, cfg, label, progress)?;
    Ok(Some((format!("mean-scan ({})", streets.display()), median)))
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
                // the files the sample names lie in the data folder
                let inside = |rel: &str, field: &str| {
                    veila_data::contained::contained(&nus, Path::new(rel), field, &calib)
                };
                let f = RealFrame {
                    name: format!("nuscenes-{name}"),
                    image: inside(&cam.file, &format!("cameras.{name}.file"))?,
                    calib: calib.clone(),
                    scan: inside(&sample.lidar_file, "lidar.file")?,
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

/// One method's figures on one frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RealRow {
    /// `model`, `mean-network`, `mean-scan` or `flat-ground`.
    pub method: String,
    /// Its scores in the camera's view against the real scan.
    #[serde(flatten)]
    pub scores: ViewScores,
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

/// How to sample the generated rows.
#[derive(Debug)]
pub struct RealOptions<'a> {
    /// The folder of the real samples ([`real_root`]).
    pub root: &'a Path,
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

/// Evaluates `bundle` on every real frame present, writing the overlays into `out/real/`. Each
/// frame's scans come through [`ScanPipeline`] as every door's do, in the calibration's LiDAR
/// frame, where the real scan is projected onto the bundle's grid and both are scored.
pub fn evaluate(bundle: &Bundle, opts: &RealOptions<'_>, out: &Path) -> Result<RealReport> {
    let root = opts.root;
    let (frames, missing) = real_frames(root)?;
    let dir = out.join("real");
    std::fs::create_dir_all(&dir).map_err(|source| Error::Io {
        action: "creating the overlay folder",
        path: dir.clone(),
        source,
    })?;
    let sensor = &bundle.config.denoiser.sensor;
    let projector = Projector::new(sensor, ProjectionOptions::default())?;
    // the label colours of the encoder panels (the panels go without labels where it is absent)
    let label_map = LabelMap::read(&root.join("semantickitti/semantic-kitti.yaml")).ok();
    let mut results = Vec::new();
    for f in &frames {
        let view = load_view(&f.image, &f.calib, f.camera.as_deref())
            .map_err(|e| Error::Data(format!("real frame {}: {e}", f.name)))?;
        let pipeline = ScanPipeline::from_views(bundle, std::slice::from_ref(&view))?;
        let xyz = veila_data::scan::read_points(&f.scan)?.cloud.xyz;
        let (real, _) = projector.project(&xyz, None, None)?;
        let regions = ViewRegions::new(sensor, &view.camera, pipeline.quarter_turns())?;
        let real_pts = regions.points_in_view(&real);

        // the encoders' input, fitted as the pipeline fits it, with its camera in the LiDAR frame
        let (small_rgb, small_cam) = prepare_view(&bundle.config, &view.image, &view.camera)?;
        let (h, w) = (bundle.config.image_height, bundle.config.image_width);
        let encoder_map = match bundle.depth.as_ref().and_then(|d| d.as_small_cnn()) {
            Some(net) => encoder_maps(net, &small_rgb, &small_cam, h, w, &Device::Cpu)?.depth_m,
            None => None,
        };
        let stem: String = f.name.chars().take_while(|c| !c.is_whitespace()).collect();
        if let Some(img) = encoder_maps_png(
            bundle,
            &small_rgb,
            &small_cam,
            encoder_map.as_deref(),
            label_map.as_ref(),
        )? {
            let file = out.join(format!("real/{stem}_encoders.png"));
            veila_data::image_io::write_png(&file, &img)?;
        }
        let encoder_depth = match &encoder_map {
            Some(d) => {
                let d: Vec<Option<f32>> = d.iter().copied().map(Some).collect();
                depth_score(&d, &small_cam, &xyz)?
            }
            None => None,
        };
        let encoder_depth_regions = match &encoder_map {
            Some(d) => depth_by_region(d, &small_cam, &xyz)?,
            None => Vec::new(),
        };
        let ground_depth = depth_score(
            &flat_ground_depth(&small_cam, f.lidar_height_m, sensor.max_range_m),
            &small_cam,
            &xyz,
        )?;
        let scored = |method: &str, scans: &[RangeImage]| -> Result<RealRow> {
            Ok(RealRow {
                method: method.to_string(),
                scores: ViewScores::of(&regions, &real, scans, f.cropped)?,
            })
        };
        let generate = |seed: u64, residual_weight: f64| -> Result<RangeImage> {
            let options = GenerateOptions {
                sampler: opts.sampler.clone(),
                samples: 1,
                seed,
                unconditional: false,
                residual_weight,
            };
            Ok(pipeline.generate(&options, |_, _| {})?.swap_remove(0).range)
        };
        let samples = (0..opts.seeds.max(1) as u64)
            .map(|s| generate(s, 1.0))
            .collect::<Result<Vec<_>>>()?;
        let mut rows = vec![scored("model", &samples)?];
        if bundle.mean.is_some() {
            rows.push(scored("mean-network", &[generate(0, 0.0)?])?);
        }
        // the mean scans are the simulator's, in the model's frame: turned into the LiDAR's as
        // the pipeline turns its samples, so that every row is scored in one frame
        let to_lidar = |scan: &RangeImage| {
            super::rig::range_to_lidar_frame(&bundle.config, scan, pipeline.quarter_turns())
        };
        rows.push(scored("mean-scan", &[to_lidar(opts.mean_scan)?])?);
        if let Some((label, scan)) = opts.reference_mean_scan {
            rows.push(scored(label, &[to_lidar(scan)?])?);
        }
        rows.push(scored(
            "flat-ground",
            &[veila_geom::flat_ground_range_image(
                sensor,
                -f.lidar_height_m,
            )?],
        )?);

        // overlay: the first sample's points above the real scan's (both on the bundle's grid)
        let gen_pts = regions.points_in_view(&samples[0]);
        let ov = |pts: &[Vec3]| -> Result<image::RgbImage> {
            let opts = OverlayOptions {
                radius_px: 2,
                ..OverlayOptions::default()
            };
            Ok(render_overlay(&view.image, &view.camera, pts, &opts)?.image)
        };
        let (top, bottom) = (ov(&gen_pts)?, ov(&real_pts)?);
        let file = format!("real/{stem}_overlay.png");
        let stacked = veila_data::vis::render::stack_vertical(&[top, bottom]);
        veila_data::image_io::write_png(&out.join(&file), &stacked)?;
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
    let maps = encoder_maps(net, rgb, camera, h, w, &Device::Cpu)?;
    if let (Some(map), Some(ids)) = (labels, maps.labels) {
        parts.push(panel(&|k| map.train_color_rgb(ids[k].min(255) as u8)));
    }
    parts.push(panel(&|k| {
        let t = (depth_m[k].max(2.0) / 2.0).ln() / (80.0f32 / 2.0).ln();
        veila_data::vis::render::Colormap::Viridis.rgb(1.0 - t)
    }));
    Ok(Some(veila_data::vis::render::stack_vertical(&parts)))
}

impl RealReport {
    /// The section's Markdown.
    pub fn markdown(&self) -> String {
        let r = self;
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
                let pm = |x: &veila_metrics::view::Spread| {
                    if x.std > 0.0 {
                        format!("{:.2} ± {:.2}", x.mean, x.std)
                    } else {
                        format!("{:.2}", x.mean)
                    }
                };
                let r = &row.scores;
                let _ = writeln!(
                    s,
                    "| {} | {} | {:.0} % | {} | {} | {} |",
                    row.method,
                    pm(&r.view_mae_m),
                    100.0 * r.view_coverage,
                    r.front_mae_m.as_ref().map_or("-".to_string(), pm),
                    r.front_unseen_mae_m.as_ref().map_or("-".to_string(), pm),
                    pm(&r.view_chamfer_m2)
                );
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_street_mean_scan_joins_only_for_a_bundle_trained_on_another_list() {
        use crate::app::bundle::Variant;
        let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut cfg = BundleConfig::cpu_default(Variant::Full);
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train.txt" });
        assert!(
            reference_mean_scan(&workspace, &cfg, 3, &())
                .unwrap()
                .is_none()
        );
        // a bundle without a recorded list was trained on the street list
        cfg.provenance = serde_json::Value::Null;
        assert!(
            reference_mean_scan(&workspace, &cfg, 3, &())
                .unwrap()
                .is_none()
        );
        cfg.provenance = serde_json::json!({ "train_split": "scenes/train-v5.txt" });
        let (label, scan) = reference_mean_scan(&workspace, &cfg, 4, &())
            .unwrap()
            .unwrap();
        assert_eq!(label, "mean-scan (scenes/train.txt)");
        // the per-pixel median of the street list's first frames, not of the bundle's own list
        // (whose fourth frame is a T junction)
        let median =
            |list: &str| mean_scan_of(&workspace, Path::new(list), 4, &cfg, "", &()).unwrap();
        assert_eq!(scan.range_m, median("scenes/train.txt").range_m);
        assert_ne!(scan.range_m, median("scenes/train-v5.txt").range_m);
    }

    #[test]
    fn every_nuscenes_camera_is_a_frame_of_its_own_image() {
        let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let root = real_root(&workspace);
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
            load_view(&f.image, &f.calib, f.camera.as_deref()).unwrap();
            assert!(
                images.insert(f.image.clone()),
                "{} repeats an image",
                f.name
            );
        }
    }
}
