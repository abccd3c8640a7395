//! The cross-modal metrics of `veila eval` (the paper's CM-DC and CM-SC): each generated scan
//! projected into its camera against a depth or class map, from files or predicted by a pretrained
//! network (Depth-Anything-V2, SegFormer) on the camera image. The metrics themselves are
//! `veila_metrics::crossmodal`; this module finds each scan's calibration, maps and image, runs the
//! networks and averages over the scans.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use veila_metrics::crossmodal::{
    DepthAlignment, Map2d, ProjectionFilter, cm_depth_consistency, cm_semantic_consistency,
};
use veila_metrics::{MetricReport, MetricValue, Protocol, Region};
use veila_nn::encoders::depth_anything::{DepthAnythingV2, DepthKind};
use veila_nn::encoders::kind::EncoderKind;
use veila_nn::encoders::mit::SegFormer;
use veila_nn::encoders::preprocess::ImageProcessor;

use crate::eval_features;

/// How CM-DC aligns a depth map to the scan's depths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum AlignmentArg {
    /// Scale by median(scan depth) / median(map): relative monocular depth (the paper's protocol).
    Median,
    /// Scale and shift by least squares (MiDaS-style).
    LeastSquares,
    /// None: metric depth maps.
    None,
    /// Scale and shift of the map to inverse depth by least squares: relative disparity maps
    /// (Depth-Anything-V2's relative checkpoints, MiDaS).
    Disparity,
}

impl From<AlignmentArg> for DepthAlignment {
    fn from(a: AlignmentArg) -> Self {
        match a {
            AlignmentArg::Median => DepthAlignment::Median,
            AlignmentArg::LeastSquares => DepthAlignment::LeastSquares,
            AlignmentArg::None => DepthAlignment::None,
            AlignmentArg::Disparity => DepthAlignment::Disparity,
        }
    }
}

/// The id space of --semantic-maps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(crate) enum SemanticIdsArg {
    /// SemanticKITTI train ids (0 = ignored, 1..=19).
    Train,
    /// SemanticKITTI raw ids (10 car, 40 road, ...), mapped to train ids by its learning map (what
    /// `veila simulate` writes to `semantic_2/`).
    Raw,
}

/// The arguments of the cross-modal metrics (flattened into `veila eval`'s).
#[derive(Debug, Args)]
pub(crate) struct CrossModalArgs {
    /// cm-dc / cm-sc: the generated scans' KITTI calibration (camera image_2): one file for every
    /// scan, or a folder with `<scan stem>.txt` per scan (e.g. `veila simulate`'s `calib/`).
    #[arg(long)]
    pub(crate) calib: Option<PathBuf>,
    /// cm-dc: a folder with a depth map per generated scan, `<scan stem>.png` (16-bit, metres x 256,
    /// 0 = none: the KITTI convention, `veila simulate`'s `depth_2/`) or `<scan stem>.npy` (float
    /// H x W, e.g. a monocular network's depth; not disparity).
    #[arg(long)]
    depth_maps: Option<PathBuf>,
    /// cm-dc: how each depth map is aligned to the scan's depths before AbsRel.
    #[arg(long, value_enum, default_value = "median")]
    depth_alignment: AlignmentArg,
    /// cm-sc: a folder with a class map per generated scan, `<scan stem>.png` (8- or 16-bit
    /// greyscale class ids; e.g. a SegFormer's classes mapped to SemanticKITTI ids).
    #[arg(long)]
    semantic_maps: Option<PathBuf>,
    /// cm-sc: the id space of --semantic-maps.
    #[arg(long, value_enum, default_value = "train")]
    semantic_ids: SemanticIdsArg,
    /// cm-dc / cm-sc with networks instead of map files: a folder with the camera image of each
    /// generated scan, `<scan stem>.png` (e.g. `veila simulate`'s `image_2/`).
    #[arg(long)]
    images: Option<PathBuf>,
    /// cm-dc: predict each image's depth with Depth-Anything-V2 as the paper does, `KIND=PATH`
    /// (`depth-anything-v2-small|base|large`, PATH its Hugging Face `model.safetensors`; the
    /// reference processor and post-processing). A relative checkpoint's inverse depth is aligned to
    /// the points' in disparity space; for a metric one pass --depth-model-max-m.
    #[arg(long, value_name = "KIND=PATH")]
    depth_model: Option<String>,
    /// cm-dc: --depth-model is a metric checkpoint (`Metric-*-hf`) with this max depth in metres
    /// (80 for the outdoor ones); its depth is compared as --depth-alignment says.
    #[arg(long, value_name = "M")]
    depth_model_max_m: Option<f32>,
    /// cm-sc: segment each image with SegFormer, `KIND=PATH` (`segformer-b0` .. `-b5`, PATH a
    /// Cityscapes checkpoint's `model.safetensors`, 1024 x 1024 processor); its 19 classes are
    /// mapped to SemanticKITTI's (sky ignored).
    #[arg(long, value_name = "KIND=PATH")]
    semantic_model: Option<String>,
    /// cm-dc / cm-sc: the camera image's size, WIDTHxHEIGHT, when the maps have another resolution
    /// (default: each map's own size).
    #[arg(long, value_parser = parse_size)]
    image_size: Option<(u32, u32)>,
}

fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WIDTHxHEIGHT, e.g. 1242x375"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|&n| (1..=65_536).contains(&n))
            .ok_or_else(|| format!("`{s}`: sizes are whole numbers from 1 to 65536"))
    };
    Ok((parse(w)?, parse(h)?))
}

/// What the cross-modal metrics need, checked before any work: a calibration and the maps, and
/// scans (not peer sample sets) to project.
pub(crate) fn check_args(
    a: &CrossModalArgs,
    (dc, sc): (bool, bool),
    gen_files: &[PathBuf],
) -> Result<()> {
    if !dc && !sc {
        return Ok(());
    }
    if a.calib.is_none() {
        bail!("cm-dc / cm-sc project the generated points into the camera: pass --calib FILE|DIR");
    }
    match (dc, a.depth_maps.is_some(), a.depth_model.is_some()) {
        (true, false, false) => bail!(
            "cm-dc compares with depth maps: pass --depth-maps DIR (<scan stem>.png or .npy), or \
             --depth-model depth-anything-v2-small=PATH with --images DIR"
        ),
        (_, true, true) => bail!("pass either --depth-maps or --depth-model, not both"),
        _ => {}
    }
    match (sc, a.semantic_maps.is_some(), a.semantic_model.is_some()) {
        (true, false, false) => bail!(
            "cm-sc compares with class maps: pass --semantic-maps DIR (<scan stem>.png), or \
             --semantic-model segformer-b0=PATH with --images DIR"
        ),
        (_, true, true) => bail!("pass either --semantic-maps or --semantic-model, not both"),
        _ => {}
    }
    if (a.depth_model.is_some() || a.semantic_model.is_some()) && a.images.is_none() {
        bail!(
            "--depth-model / --semantic-model run on the camera images: pass --images DIR (<scan stem>.png)"
        );
    }
    if let Some(m) = a.depth_model_max_m
        && !(m.is_finite() && m > 0.0)
    {
        bail!("--depth-model-max-m must be a positive number of metres, got {m}");
    }
    if let Some(f) = gen_files
        .iter()
        .find(|f| veila_data::peer_samples::is_sample_file(f))
    {
        bail!(
            "{}: cm-dc / cm-sc project scans into the camera; peer sample sets have no camera",
            f.display()
        );
    }
    Ok(())
}

/// A scan file's name without its point-format extension (`000001.bin`, `x.pcd.bin` -> `000001`, `x`).
fn scan_stem(path: &Path) -> String {
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
    bail!(
        "{}: no {what} for it: expected {} in {}",
        scan.display(),
        exts.iter()
            .map(|e| format!("{stem}.{e}"))
            .collect::<Vec<_>>()
            .join(" or "),
        dir.display()
    )
}

/// `KIND=PATH` of --depth-model / --semantic-model.
fn split_model_arg<'s>(flag: &str, spec: &'s str) -> Result<(EncoderKind, &'s Path)> {
    let (kind, path) = spec
        .split_once('=')
        .with_context(|| format!("{flag} `{spec}`: expected KIND=PATH"))?;
    let kind: EncoderKind = kind
        .parse()
        .map_err(|e: String| anyhow::anyhow!("{flag}: {e}"))?;
    Ok((kind, Path::new(path)))
}

/// Depth-Anything-V2 with its head (relative, or metric with `max_m`); the flag says metric.
fn load_depth_model(
    spec: &str,
    max_m: Option<f32>,
    device: &candle_core::Device,
) -> Result<(DepthAnythingV2, bool)> {
    let (kind, path) = split_model_arg("--depth-model", spec)?;
    let mut cfg = kind.depth_anything_config().with_context(|| {
        format!("--depth-model: `{kind}` is not a Depth-Anything-V2 kind (depth-anything-v2-small|base|large)")
    })?;
    if let Some(m) = max_m {
        cfg.depth_estimation_type = DepthKind::Metric;
        cfg.max_depth = m;
    }
    let model =
        DepthAnythingV2::load(&cfg, path, candle_core::DType::F32, device).with_context(|| {
            format!(
                "--depth-model {kind}: {} (the `model.safetensors` of {})",
                path.display(),
                kind.hub_repo().unwrap_or("-")
            )
        })?;
    Ok((model, max_m.is_some()))
}

/// SegFormer with its Cityscapes head.
fn load_semantic_model(spec: &str, device: &candle_core::Device) -> Result<SegFormer> {
    let (kind, path) = split_model_arg("--semantic-model", spec)?;
    let cfg = kind.segformer_cityscapes_config().with_context(|| {
        format!("--semantic-model: `{kind}` is not a SegFormer kind (segformer-b0 .. segformer-b5)")
    })?;
    SegFormer::load(&cfg, path, candle_core::DType::F32, device).with_context(|| {
        format!(
            "--semantic-model {kind}: {} (the `model.safetensors` of {})",
            path.display(),
            kind.hub_repo().unwrap_or("-")
        )
    })
}

/// CM-DC and CM-SC (when requested) over the generated scans, appended to `report` (region front:
/// the camera's field of view; the value is the mean over the scans that have points in it).
pub(crate) fn metrics(
    a: &CrossModalArgs,
    (want_dc, want_sc): (bool, bool),
    feature_nets: Option<&Path>,
    gen_files: &[PathBuf],
    report: &mut MetricReport,
) -> Result<()> {
    if !want_dc && !want_sc {
        return Ok(());
    }
    let calib = a.calib.as_deref().context("cm-dc / cm-sc need --calib")?;
    let nets = if want_sc {
        Some(eval_features::load_nets(feature_nets)?)
    } else {
        None
    };
    // chosen once: on a CUDA build it opens the GPU
    let device = crate::model::device()?;
    let depth_model = match (&a.depth_model, want_dc) {
        (Some(spec), true) => Some(load_depth_model(spec, a.depth_model_max_m, &device)?),
        _ => None,
    };
    let semantic_model = match (&a.semantic_model, want_sc) {
        (Some(spec), true) => Some(load_semantic_model(spec, &device)?),
        _ => None,
    };
    let image_for = |stem: &str, f: &Path| -> Result<(PathBuf, veila_data::image::RgbImage)> {
        let dir = a.images.as_deref().context("--images")?;
        let p = companion(dir, stem, &["png", "jpg"], "camera image", f)?;
        let img = veila_data::image_io::read_rgb_image(&p)?;
        Ok((p, img))
    };
    let (mut dc, mut sc) = (Vec::new(), Vec::new());
    let pb = crate::progress::bar(gen_files.len() as u64, "cross-modal");
    for f in gen_files {
        let stem = scan_stem(f);
        let calib_file = if calib.is_dir() {
            companion(calib, &stem, &["txt"], "calibration", f)?
        } else {
            calib.to_path_buf()
        };
        let loaded = veila_data::scan::read_points(f)?;
        let cloud = &loaded.cloud;
        let camera_for = |w: u32, h: u32| -> Result<veila_geom::PinholeCamera> {
            let (w, h) = a.image_size.unwrap_or((w, h));
            Ok(veila_data::weather::files::read_camera(&calib_file, w, h)?)
        };
        if want_dc {
            let (mp, map, alignment) = match &depth_model {
                Some((model, metric)) => {
                    let (p, img) = image_for(&stem, f)?;
                    let (w, h) = img.dimensions();
                    let data = model
                        .predict_depth_map_rgb8(
                            &ImageProcessor::depth_anything_v2(),
                            img.as_raw(),
                            h as usize,
                            w as usize,
                            &device,
                        )
                        .with_context(|| format!("{}: depth prediction", p.display()))?;
                    let alignment = if *metric {
                        a.depth_alignment.into()
                    } else {
                        DepthAlignment::Disparity
                    };
                    (
                        p,
                        veila_data::image_io::ImageMap {
                            width: w,
                            height: h,
                            data,
                        },
                        alignment,
                    )
                }
                None => {
                    let dir = a.depth_maps.as_deref().context("--depth-maps")?;
                    let mp = companion(dir, &stem, &["png", "npy"], "depth map", f)?;
                    let map = veila_data::image_io::read_depth_map(&mp)?;
                    (mp, map, a.depth_alignment.into())
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let m = Map2d::new(map.width, map.height, &map.data)
                .with_context(|| mp.display().to_string())?;
            match cm_depth_consistency(
                &cloud.xyz,
                &cam,
                &m,
                alignment,
                &ProjectionFilter::default(),
            ) {
                Ok(c) if c.abs_rel.is_finite() => dc.push(c.abs_rel),
                Ok(_) => tracing::warn!("{}: no point projects onto a depth value", f.display()),
                Err(e) => tracing::warn!("{}: cm-dc skipped: {e}", f.display()),
            }
        }
        if let Some(nets) = &nets {
            let (mp, map) = match &semantic_model {
                Some(model) => {
                    let (p, img) = image_for(&stem, f)?;
                    let (w, h) = img.dimensions();
                    let labels = model
                        .predict_label_map_rgb8(
                            &ImageProcessor::segformer(1024, 1024),
                            img.as_raw(),
                            h as usize,
                            w as usize,
                            &device,
                        )
                        .with_context(|| format!("{}: segmentation", p.display()))?;
                    let data = labels
                        .into_iter()
                        .map(veila_metrics::crossmodal::cityscapes_to_semantickitti)
                        .collect();
                    (
                        p,
                        veila_data::image_io::ImageMap {
                            width: w,
                            height: h,
                            data,
                        },
                    )
                }
                None => {
                    let dir = a.semantic_maps.as_deref().context("--semantic-maps")?;
                    let mp = companion(dir, &stem, &["png"], "class map", f)?;
                    let mut map = veila_data::image_io::read_label_map(&mp)?;
                    if a.semantic_ids == SemanticIdsArg::Train {
                        veila_metrics::crossmodal::check_train_ids(
                            &map.data,
                            &mp.display().to_string(),
                        )
                        .context("--semantic-ids train (pass --semantic-ids raw for raw ids)")?;
                    }
                    if a.semantic_ids == SemanticIdsArg::Raw {
                        for v in &mut map.data {
                            *v = u32::from(veila_data::sim::class::learning_id(
                                u16::try_from(*v).unwrap_or(0),
                            ));
                        }
                    }
                    (mp, map)
                }
            };
            let cam = camera_for(map.width, map.height)?;
            let (pts, labels) = nets.segment_points(&cloud.xyz, Some(&cloud.intensity))?;
            let m = Map2d::new(map.width, map.height, &map.data)
                .with_context(|| mp.display().to_string())?;
            let filter = ProjectionFilter {
                ignore_label: Some(0),
                ..ProjectionFilter::default()
            };
            match cm_semantic_consistency(&pts, &labels, &cam, &m, &filter) {
                Ok(c) if c.percent.is_finite() => sc.push(c.percent),
                Ok(_) => tracing::warn!("{}: no point projects onto a labelled pixel", f.display()),
                Err(e) => tracing::warn!("{}: cm-sc skipped: {e}", f.display()),
            }
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    for (want, name, vals) in [(want_dc, "cm-dc", &dc), (want_sc, "cm-sc (%)", &sc)] {
        if !want {
            continue;
        }
        if vals.is_empty() {
            bail!(
                "{name}: no generated scan has points in the camera's view with a map value there \
                 (check --calib and the maps)"
            );
        }
        report.metrics.push(MetricValue {
            name: name.into(),
            protocol: Protocol::Veila,
            region: Region::Front,
            value: mean(vals),
            generated: vals.len(),
            reference: 0,
            paper_scale: None,
        });
    }
    Ok(())
}
