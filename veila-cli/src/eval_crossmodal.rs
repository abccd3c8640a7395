//! The cross-modal metrics of `veila eval` (the paper's CM-DC and CM-SC): each generated scan
//! projected into its camera against a depth or class map, from files or predicted by a pretrained
//! network (Depth-Anything-V2, SegFormer) on the camera image. The metrics themselves are
//! `veila_metrics::crossmodal`; finding each scan's calibration, maps and image, running the
//! networks and averaging over the scans is `veila_diffusion::app::crossmodal_eval`. This module
//! holds the flags, checks them, loads the networks and draws the progress.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use veila_diffusion::app::crossmodal_eval::{
    ClassIds, CrossModalEval, CrossModalScores, DepthReference, SemanticReference,
};
use veila_metrics::MetricReport;
use veila_metrics::crossmodal::DepthAlignment;
use veila_nn::encoders::depth_anything::{DepthAnythingV2, DepthKind};
use veila_nn::encoders::kind::EncoderKind;
use veila_nn::encoders::mit::SegFormer;

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
    /// cm-dc / cm-sc: the generated scans' calibration (KITTI camera image_2, or a nuScenes
    /// per-sample JSON's CAM_FRONT): one file for every scan, or a folder with `<scan stem>.txt`
    /// per scan (e.g. `veila simulate`'s `calib/`).
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
    /// cm-dc: --depth-model is a metric checkpoint (`Metric-*-hf`) with this max depth in metres,
    /// 0.1 to 1000 (80 for the outdoor ones); its depth is compared as --depth-alignment says.
    #[arg(long, value_name = "M", value_parser = crate::bounds::float32(0.1, 1000.0))]
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
    let depth = match (&depth_model, a.depth_maps.as_deref()) {
        _ if !want_dc => None,
        (Some((model, metric)), _) => Some(DepthReference::Model {
            model,
            metric: metric.then(|| a.depth_alignment.into()),
        }),
        (None, Some(dir)) => Some(DepthReference::Maps {
            dir,
            alignment: a.depth_alignment.into(),
        }),
        (None, None) => bail!("--depth-maps"),
    };
    let semantic = match (&nets, &semantic_model, a.semantic_maps.as_deref()) {
        (None, ..) => None,
        (Some(nets), Some(model), _) => Some((SemanticReference::Model(model), nets)),
        (Some(nets), None, Some(dir)) => {
            let ids = match a.semantic_ids {
                SemanticIdsArg::Train => ClassIds::Train,
                SemanticIdsArg::Raw => ClassIds::Raw,
            };
            Some((SemanticReference::Maps { dir, ids }, nets))
        }
        (Some(_), None, None) => bail!("--semantic-maps"),
    };
    let eval = CrossModalEval {
        calib,
        image_size: a.image_size,
        images: a.images.as_deref(),
        depth,
        semantic,
    };
    let mut scores = CrossModalScores::default();
    let pb = crate::progress::bar(gen_files.len() as u64, "cross-modal");
    for f in gen_files {
        match eval.score(f, &device) {
            Ok(s) => scores.push(s),
            // the library names the field; the flag is this binary's
            Err(veila_diffusion::Error::InvalidConfig {
                field: "semantic_ids",
                reason,
            }) => bail!("--semantic-ids train (pass --semantic-ids raw for raw ids): {reason}"),
            Err(e) => return Err(e.into()),
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    match scores.metrics((want_dc, want_sc)) {
        Ok(values) => report.metrics.extend(values),
        Err(name) => bail!(
            "{name}: no generated scan has points in the camera's view with a map value there \
             (check --calib and the maps)"
        ),
    }
    Ok(())
}
