//! Export of a denoiser for implementations outside candle (the PyTorch yardstick,
//! `xtask/scripts/torch_yardstick.py`, driven by `cargo xtask bench-model --export`): the network's
//! configuration, its weights, a fixed seeded input and candle's output on it, so another
//! implementation can load the same weights, run the same input and compare.
//!
//! A folder holds `config.json` (the [`DenoiserConfig`]), `weights.safetensors` (every parameter
//! by name), `reference.safetensors` (`x`, `t`, `y`, and where they exist `ray_features`, `keep`,
//! the encoder pyramids `semantic.I` / `depth.I`, the fused conditions `fused.I` and the GCMA
//! geometry `gcma.LEVEL.NAME`) and, for a conditioned network, `export.json` ([`ExportInfo`]).
//! Everything is written into a staging folder beside the target first and then moved in, so a
//! failed export leaves no half-written folder.
//!
//! [`export_conditioned`] runs the network as training does: condition fusion through
//! [`Denoiser::prepare_condition`], the per-sample `keep` factor of condition dropout (alternating
//! 1 and 0 over the batch), the GCMA geometry of the given camera through [`Denoiser::geometry`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use veila_geom::{EpipolarConfig, PinholeCamera};

use crate::checkpoint::{compare_tensors, expected_tensors};
use crate::config::{Cues, DenoiserConfig};
use crate::error::{Error, Result};
use crate::init::seeded_var_builder;
use crate::unet::{ConditionInput, Denoiser};

/// A seeded `[B, C, H, W]` standard-normal input of `cfg`'s network and `[B]` times in `(0.02,
/// 0.98)` (ChaCha8 from `seed`; Box-Muller, so the values are the same on every platform).
pub fn seeded_inputs(
    cfg: &DenoiserConfig,
    b: usize,
    seed: u64,
    dev: &Device,
) -> Result<(Tensor, Tensor)> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let shape = [b, cfg.in_channels, cfg.height(), cfg.width()];
    let x = normal_tensor(&mut rng, &shape, 1.0, dev)?;
    let t: Vec<f32> = (0..b).map(|_| rng.random_range(0.02f32..0.98)).collect();
    Ok((x, Tensor::from_vec(t, b, dev)?))
}

/// Seeded normal values of `shape` with standard deviation `std` (Box-Muller).
fn normal_tensor(rng: &mut ChaCha8Rng, shape: &[usize], std: f64, dev: &Device) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|_| {
            let (u1, u2): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
            (std * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
        })
        .collect();
    Ok(Tensor::from_vec(v, shape, dev)?)
}

fn poisoned() -> Error {
    Error::Input("the weight map's lock is poisoned".into())
}

/// Adds seeded noise to every parameter whose initial value is one constant (GroupNorm affines,
/// the zero convolutions that close GCMA's residual branch), so that a comparison on the exported
/// network sees every branch: with the zero convolutions at zero, GCMA adds exactly nothing.
/// Returns how many parameters changed.
pub fn perturb_constant_parameters(varmap: &VarMap, seed: u64) -> Result<usize> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_c0de);
    let vars = varmap.data().lock().map_err(|_| poisoned())?;
    let mut names: Vec<&String> = vars.keys().collect();
    names.sort();
    let mut changed = 0;
    for name in names {
        let var = &vars[name];
        let t = var.as_tensor();
        let (lo, hi) = (
            t.min_all()?.to_scalar::<f32>()?,
            t.max_all()?.to_scalar::<f32>()?,
        );
        if lo != hi {
            continue;
        }
        // a zero convolution's weight gets the scale of a fan-in init, everything else 0.1
        let dims = t.dims();
        let std = if name.ends_with(".weight") && dims.len() == 4 {
            1.0 / ((dims[1] * dims[2] * dims[3]) as f64).sqrt()
        } else {
            0.1
        };
        var.set(&(t + normal_tensor(&mut rng, dims, std, t.device())?)?)?;
        changed += 1;
    }
    Ok(changed)
}

/// The weights of an exported network.
#[derive(Debug, Clone, Copy)]
pub enum ExportWeights<'a> {
    /// Seeded from [`ConditionedExport::seed`], every constant parameter perturbed
    /// ([`perturb_constant_parameters`]).
    Seeded,
    /// Trained tensors (a bundle's denoiser), every parameter by name; `source` names them in
    /// `export.json` and in errors.
    Trained {
        /// The tensors.
        tensors: &'a HashMap<String, Tensor>,
        /// Where they come from (a bundle folder).
        source: &'a Path,
    },
}

/// What [`export_conditioned`] exports.
#[derive(Debug, Clone)]
pub struct ConditionedExport<'a> {
    /// The network's name in `export.json` (`paper`, `bundled`).
    pub network: &'a str,
    /// The network (must be conditioned).
    pub config: DenoiserConfig,
    /// Its weights.
    pub weights: ExportWeights<'a>,
    /// The camera of every view (the GCMA geometry is built from it).
    pub camera: PinholeCamera,
    /// The encoders' input image `(H, W)` the feature sizes come from (recorded only).
    pub image_hw: (usize, usize),
    /// The epipolar sampling of the GCMA geometry.
    pub epipolar: EpipolarConfig,
    /// Batch of the fixed input, in `1..=64` (the samples alternate keep = 1, 0).
    pub batch: usize,
    /// Seed of the weights, the input and the encoder pyramids.
    pub seed: u64,
}

/// What an export of a conditioned network writes next to the tensors (`export.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ExportInfo {
    /// The network's name.
    pub network: String,
    /// Range-image grid `[H, W]`.
    pub grid: [usize; 2],
    /// The encoders' input image `[H, W]` the feature sizes come from.
    pub image: [usize; 2],
    /// Scalar parameters.
    pub params: usize,
    /// Batch of the fixed input.
    pub batch: usize,
    /// Parameters of the seeded network that started as one constant and were perturbed.
    pub perturbed_parameters: usize,
    /// `seed N` or the trained weights' source.
    pub weights_from: String,
    /// The epipolar sampling of the geometry.
    pub epipolar: EpipolarConfig,
    /// The levels with GCMA (their geometry tensors are in the reference).
    pub gcma_levels: Vec<usize>,
    /// Camera views per sample.
    pub num_views: usize,
    /// Relative L2 of candle's output with the image against the same input with every keep 0
    /// (how much the conditioning changes the output: near 0 would make the check blind to it).
    pub conditioning_effect_rel_l2: f64,
}

/// Exports the conditioned network `spec` into `dir` (created if needed; its four files replaced)
/// and returns what `export.json` holds.
pub fn export_conditioned(
    spec: &ConditionedExport<'_>,
    dir: &Path,
    dev: &Device,
) -> Result<ExportInfo> {
    let (cfg, b) = (&spec.config, spec.batch);
    if b == 0 || b > 64 {
        return Err(Error::Input(format!(
            "export batch must be in 1..=64, got {b}"
        )));
    }
    cfg.validate()?;
    let cc = cfg
        .conditioning
        .clone()
        .ok_or_else(|| Error::Config("the exported network is unconditional".into()))?;
    // the seeded variables of every parameter (what training optimises), by their names
    let varmap = VarMap::new();
    Denoiser::new(cfg, seeded_var_builder(&varmap, spec.seed, DType::F32, dev))?;
    let (perturbed, weights_from) = match spec.weights {
        ExportWeights::Trained { tensors, source } => {
            let found = tensors
                .iter()
                .map(|(k, v)| (k.clone(), v.dims().to_vec()))
                .collect();
            let report = compare_tensors(&expected_tensors(cfg)?, &found);
            if !report.is_clean() {
                return Err(Error::CheckpointMismatch {
                    path: source.to_path_buf(),
                    report,
                });
            }
            let vars = varmap.data().lock().map_err(|_| poisoned())?;
            for (name, var) in vars.iter() {
                var.set(&tensors[name].to_device(dev)?.to_dtype(DType::F32)?)?;
            }
            (0, source.display().to_string())
        }
        ExportWeights::Seeded => (
            perturb_constant_parameters(&varmap, spec.seed)?,
            format!("seed {}", spec.seed),
        ),
    };
    let params: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
    // the same network on the same weights without gradient tracking: a forward pass on the
    // variables keeps every intermediate of the graph (15 GB for the paper's at batch 2)
    let frozen: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .map_err(|_| poisoned())?
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect();
    let net = Denoiser::new(cfg, VarBuilder::from_tensors(frozen, DType::F32, dev))?;
    // the rig as training builds it: one camera per view through Denoiser::geometry
    let geometry = match &cc.gcma {
        Some(_) => {
            let cams = vec![spec.camera; cc.num_views];
            Some(net.geometry(&cams, &spec.epipolar, dev)?)
        }
        None => None,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed + 3);
    let (x, t) = seeded_inputs(cfg, b, spec.seed, dev)?;
    let n = b * cc.num_views;
    // random encoder pyramids of the cues the model takes
    let mut pyramid = |channels: &[usize]| -> Result<Vec<Tensor>> {
        channels
            .iter()
            .zip(&cc.feature_sizes)
            .map(|(&c, &[h, w])| normal_tensor(&mut rng, &[n, c, h, w], 1.0, dev))
            .collect()
    };
    let semantic = match cc.cues {
        Cues::DepthOnly => None,
        _ => Some(pyramid(&cc.semantic_channels)?),
    };
    let depth = match cc.cues {
        Cues::SemanticOnly => None,
        _ => Some(pyramid(&cc.depth_channels)?),
    };
    let keep_v: Vec<f32> = (0..b).map(|i| if i % 2 == 0 { 1.0 } else { 0.0 }).collect();
    let keep = Tensor::from_vec(keep_v, b, dev)?;
    let input = ConditionInput {
        semantic: semantic.clone(),
        depth: depth.clone(),
        keep: Some(keep.clone()),
    };
    // as training runs it: the fusion, then the network with the per-sample keep of condition dropout
    let prepared = net.prepare_condition(&input, geometry.as_ref())?;
    let y = net.forward(&x, &t, Some(&prepared))?;
    let dropped = prepared.clone().with_keep(Some(keep.zeros_like()?));
    let y0 = net.forward(&x, &t, Some(&dropped))?;
    let effect = ((&y - &y0)?.sqr()?.sum_all()?.sqrt()?.to_scalar::<f32>()?
        / y.sqr()?.sum_all()?.sqrt()?.to_scalar::<f32>()?) as f64;

    let mut reference = reference_tensors(&net, x, t, y);
    reference.insert("keep".to_string(), keep);
    for (cue, pyramid) in [("semantic", &semantic), ("depth", &depth)] {
        for (i, f) in pyramid.iter().flatten().enumerate() {
            reference.insert(format!("{cue}.{i}"), f.clone());
        }
    }
    for (i, f) in prepared.fused.iter().enumerate() {
        reference.insert(format!("fused.{i}"), f.clone());
    }
    let mut gcma_levels = Vec::new();
    if let Some(g) = &geometry {
        for lg in g.levels() {
            gcma_levels.push(lg.level());
            for (name, tensor) in lg.named_tensors() {
                reference.insert(format!("gcma.{}.{name}", lg.level()), tensor);
            }
        }
    }
    let info = ExportInfo {
        network: spec.network.to_string(),
        grid: [cfg.height(), cfg.width()],
        image: [spec.image_hw.0, spec.image_hw.1],
        params,
        batch: b,
        perturbed_parameters: perturbed,
        weights_from,
        epipolar: spec.epipolar,
        gcma_levels,
        num_views: cc.num_views,
        conditioning_effect_rel_l2: effect,
    };
    write_export(dir, cfg, &varmap, &reference, Some(&info))?;
    Ok(info)
}

/// The reference tensors every export holds: the input `x`, `t`, candle's output `y` and, where
/// the network has them, its `ray_features`.
pub fn reference_tensors(
    net: &Denoiser,
    x: Tensor,
    t: Tensor,
    y: Tensor,
) -> HashMap<String, Tensor> {
    let mut reference = HashMap::from([
        ("x".to_string(), x),
        ("t".to_string(), t),
        ("y".to_string(), y),
    ]);
    if let Some(rf) = net.ray_features() {
        reference.insert("ray_features".to_string(), rf.clone());
    }
    reference
}

/// Writes an export folder: `config.json`, `weights.safetensors` (`varmap`),
/// `reference.safetensors` and, with `info`, `export.json`; staged beside `dir` and moved in.
pub fn write_export(
    dir: &Path,
    cfg: &DenoiserConfig,
    varmap: &VarMap,
    reference: &HashMap<String, Tensor>,
    info: Option<&ExportInfo>,
) -> Result<()> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Io { path, source }
    };
    let json = |value: serde_json::Result<String>, name: &str| {
        value.map_err(|source| Error::Json {
            path: dir.join(name),
            source,
        })
    };
    let mut texts = vec![(
        "config.json",
        json(serde_json::to_string_pretty(cfg), "config.json")?,
    )];
    if let Some(info) = info {
        texts.push((
            "export.json",
            json(serde_json::to_string_pretty(info), "export.json")?,
        ));
    }
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let stage = staging_dir_beside(dir)?;
    let safetensors = |path: PathBuf, e: candle_core::Error| Error::SafeTensors {
        path,
        message: e.to_string(),
    };
    let staged = (|| -> Result<()> {
        for (name, text) in &texts {
            let path = stage.join(name);
            std::fs::write(&path, text).map_err(io(&path))?;
        }
        let w = stage.join("weights.safetensors");
        varmap.save(&w).map_err(|e| safetensors(w.clone(), e))?;
        let r = stage.join("reference.safetensors");
        candle_core::safetensors::save(reference, &r).map_err(|e| safetensors(r.clone(), e))
    })();
    if let Err(e) = staged {
        let _ = std::fs::remove_dir_all(&stage);
        return Err(e);
    }
    let tensors = ["weights.safetensors", "reference.safetensors"];
    for f in texts.iter().map(|(name, _)| *name).chain(tensors) {
        let to = dir.join(f);
        std::fs::rename(stage.join(f), &to).map_err(io(&to))?;
    }
    std::fs::remove_dir(&stage).map_err(io(&stage))
}

/// A fresh, empty folder beside `dir` (same file system, so its files can be renamed into `dir`).
fn staging_dir_beside(dir: &Path) -> Result<PathBuf> {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "export".into());
    let stage = dir.with_file_name(format!(".{name}.partial-{}", std::process::id()));
    let io = |source| Error::Io {
        path: stage.clone(),
        source,
    };
    if stage.exists() {
        std::fs::remove_dir_all(&stage).map_err(io)?;
    }
    std::fs::create_dir(&stage).map_err(io)?;
    Ok(stage)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `DenoiserConfig::paper()` on an 8 x 64 grid at 8 base channels, and a KITTI-like camera of
    /// the paper's 384 x 1248 image (LiDAR x forward).
    fn small_paper() -> (DenoiserConfig, PinholeCamera) {
        let mut cfg = DenoiserConfig::paper();
        (cfg.sensor.rows, cfg.sensor.cols) = (8, 64);
        cfg.base_channels = 8;
        let k = [
            [721.5, 0.0, 609.6, 0.0],
            [0.0, 721.5, 172.9, 0.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        let tr = [
            [0.0, -1.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
        ];
        let cam = PinholeCamera::from_kitti_odometry(k, tr, 1248, 384).expect("camera");
        (cfg, cam)
    }

    #[test]
    fn a_conditioned_export_holds_the_geometry_and_the_condition_moves_the_output() {
        let (config, camera) = small_paper();
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ys");
        let spec = ConditionedExport {
            network: "paper",
            config,
            weights: ExportWeights::Seeded,
            camera,
            image_hw: (384, 1248),
            epipolar: EpipolarConfig::default(),
            batch: 2,
            seed: 0,
        };
        let info = export_conditioned(&spec, &out, &Device::Cpu).unwrap();
        let written: ExportInfo =
            serde_json::from_str(&std::fs::read_to_string(out.join("export.json")).unwrap())
                .unwrap();
        assert_eq!(written.grid, [8, 64]);
        assert_eq!(written.gcma_levels, [0, 1, 2, 3]);
        assert_eq!(written.params, info.params);
        // GroupNorm affines and the four encoder + four decoder zero convolutions at least
        assert!(info.perturbed_parameters > 16);
        let effect = info.conditioning_effect_rel_l2;
        assert!(effect > 1e-3 && effect.is_finite(), "{effect}");
        let reference =
            candle_core::safetensors::load(out.join("reference.safetensors"), &Device::Cpu)
                .unwrap();
        for level in 0..4 {
            let active = &reference[&format!("gcma.{level}.active")];
            let valid = &reference[&format!("gcma.{level}.valid")];
            assert_eq!(active.dtype(), DType::U32);
            assert_eq!(valid.dim(0).unwrap(), active.dim(0).unwrap());
            assert!(active.dim(0).unwrap() > 0, "level {level}: no active pixel");
        }
        assert_eq!(reference["keep"].to_vec1::<f32>().unwrap(), [1.0, 0.0]);
        // the weights reload into the same network, and no staging folder is left behind
        let weights =
            candle_core::safetensors::load(out.join("weights.safetensors"), &Device::Cpu).unwrap();
        assert_eq!(weights.len(), expected_tensors(&spec.config).unwrap().len());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        // trained weights that do not fit the network are refused by name, before anything is written
        let wrong = HashMap::from([(
            "nope".to_string(),
            Tensor::zeros(1, DType::F32, &Device::Cpu).unwrap(),
        )]);
        let bad = ConditionedExport {
            weights: ExportWeights::Trained {
                tensors: &wrong,
                source: Path::new("models/x"),
            },
            ..spec.clone()
        };
        let e = export_conditioned(&bad, &dir.path().join("bad"), &Device::Cpu).unwrap_err();
        assert!(matches!(e, Error::CheckpointMismatch { .. }), "{e}");
        assert!(!dir.path().join("bad").exists());
        // the batch is checked first
        let e = export_conditioned(&ConditionedExport { batch: 0, ..spec }, &out, &Device::Cpu);
        assert!(e.unwrap_err().to_string().contains("1..=64"));
    }
}
