//! `cargo xtask train-feature-nets`: trains the FRD / FPD feature networks shipped in
//! `models/feature-nets` ([`veila_nn::feature_nets`]) on simulated train-split scenes.
//!
//! Data: `--scenes` (scene file, seed) pairs drawn (seeded) from `scenes/train.txt`, `--frames` frames
//! each, rendered with the scene's own HDL-64E (64 x 1024) and projected to the small RangeNet's
//! 32 x 512 input exactly as `veila eval` projects scans. Every scan is augmented once by a random yaw
//! rotation and a random left / right mirror. The last `--holdout` fraction of the scenes (whole scenes,
//! never frames of a training scene) is held out for the accuracies printed at the end.
//!
//! * RangeNet (`rangenet-small`): per-pixel cross-entropy over the SemanticKITTI 20-class learning map
//!   (class 0, unlabelled, and empty pixels ignored). Held out: pixel accuracy and mIoU.
//! * PointNet (`pointnet-small`): a whole-scan task, because FPD feeds whole scans (not objects) to the
//!   net. The 23 logits are two heads: the first 20 predict the scan's **class composition** (the
//!   fraction of its points in each learning class; soft-target cross-entropy) and the last 3 the
//!   **scene layout** (straight road, junction, narrow street; cross-entropy). Both need the global
//!   feature to summarise what is in the scan and how it is laid out, which is what a distribution
//!   distance over scans should be sensitive to; an object-crop classifier would instead be fed whole
//!   scans at test time that it never saw in training. Held out: layout accuracy and the total-variation
//!   distance between predicted and true composition (next to the distance of the training-set mean
//!   composition, the trivial baseline).
//!
//! The scans come from `veila_diffusion::app::feature_net_data`, the training loops from
//! `veila_nn::feature_nets::train`. Everything is seeded (`--seed`); the default run takes a few
//! minutes on a 2-core CPU.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::Args;
use veila_diffusion::app::feature_net_data::{draw_scene_pairs, simulate_feature_samples};
use veila_nn::feature_nets::train::{FeatureSample, LAYOUTS, train_pointnet, train_rangenet};
use veila_nn::feature_nets::{self, PointNet, PointNetConfig, RangeNet, RangeNetConfig};

/// Train the FRD / FPD feature networks on simulated scenes and write them as a bundle.
#[derive(Debug, Args)]
pub struct TrainFeatureNetsArgs {
    /// Output folder (default: models/feature-nets in the workspace).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Scene list to draw from (default: scenes/train.txt in the workspace).
    #[arg(long)]
    scene_list: Option<PathBuf>,
    /// Number of (scene file, seed) pairs to simulate.
    #[arg(long, default_value_t = 90)]
    scenes: usize,
    /// Frames per scene (spread over the scene's frames).
    #[arg(long, default_value_t = 4)]
    frames: u32,
    /// RangeNet optimisation steps (batch 4).
    #[arg(long, default_value_t = 400)]
    steps: usize,
    /// PointNet optimisation steps (batch 8).
    #[arg(long, default_value_t = 1000)]
    point_steps: usize,
    /// Fraction of the scenes held out for the accuracies.
    #[arg(long, default_value_t = 0.2)]
    holdout: f64,
    /// Seed of the scene draw, the augmentation, the initialisation and the batches.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

pub fn run(a: TrainFeatureNetsArgs) -> Result<()> {
    let t0 = Instant::now();
    let root = crate::progress::workspace_root();
    let out = a.out.unwrap_or_else(|| root.join("models/feature-nets"));
    let list_path = a
        .scene_list
        .unwrap_or_else(|| root.join("scenes/train.txt"));
    if a.scenes < 2 {
        bail!("--scenes must be at least 2 (training and held-out scenes)");
    }
    if !(a.holdout > 0.0 && a.holdout < 1.0) {
        bail!("--holdout must be in (0, 1), got {}", a.holdout);
    }
    if a.steps == 0 || a.point_steps == 0 || a.frames == 0 {
        bail!("--steps, --point-steps and --frames must be > 0");
    }
    let (pairs, files) = draw_scene_pairs(&list_path, a.scenes, a.seed)
        .with_context(|| format!("reading the scene list {}", list_path.display()))?;
    if files.len() != LAYOUTS {
        bail!(
            "{}: expected {LAYOUTS} scene files (the layout head has {LAYOUTS} classes), found {}",
            list_path.display(),
            files.len()
        );
    }
    let rcfg = RangeNetConfig::small();
    let pcfg = PointNetConfig::small();
    eprintln!(
        "simulating {} scenes x {} frames ({} on {} threads)...",
        a.scenes,
        a.frames,
        rcfg.name,
        rayon::current_num_threads()
    );
    let samples = simulate_feature_samples(&pairs, &files, a.frames, &rcfg.sensor, a.seed)?;
    let n_held_scenes = ((a.scenes as f64 * a.holdout).round() as usize).clamp(1, a.scenes - 1);
    let first_held = a.scenes - n_held_scenes;
    let (train, held): (Vec<&FeatureSample>, Vec<&FeatureSample>) =
        samples.iter().partition(|s| s.scene < first_held);
    eprintln!(
        "{} training scans, {} held-out scans ({:.0} s)",
        train.len(),
        held.len(),
        t0.elapsed().as_secs_f64()
    );
    let dev = Device::Cpu;
    let t_range = Instant::now();
    let (rt, rr) = train_rangenet(&rcfg, &train, &held, a.steps, a.seed, &dev, |s, n, l| {
        if s % 25 == 0 || s == n {
            let t = t_range.elapsed().as_secs_f64();
            eprintln!("rangenet step {s:>4}/{n}  loss {l:.4}  ({t:.0} s)");
        }
    })?;
    let range_s = t_range.elapsed().as_secs_f64();
    let t_point = Instant::now();
    let (pt, pr) = train_pointnet(
        &pcfg,
        &train,
        &held,
        a.point_steps,
        a.seed,
        &dev,
        |s, n, l| {
            if s % 100 == 0 || s == n {
                let t = t_point.elapsed().as_secs_f64();
                eprintln!("pointnet step {s:>4}/{n}  loss {l:.4}  ({t:.0} s)");
            }
        },
    )?;
    let point_s = t_point.elapsed().as_secs_f64();
    let description = format!(
        "trained by `cargo xtask train-feature-nets --scenes {} --frames {} --steps {} --point-steps {} --seed {}` \
         on simulated scenes of {}; held out: rangenet pixel accuracy {:.3}, mIoU {:.3}; pointnet layout \
         accuracy {:.3}, composition TV {:.3} (mean-composition baseline {:.3})",
        a.scenes,
        a.frames,
        a.steps,
        a.point_steps,
        a.seed,
        list_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        rr.pixel_accuracy,
        rr.miou,
        pr.layout_accuracy,
        pr.composition_tv,
        pr.baseline_tv
    );
    feature_nets::save_bundle(&out, "veila-sim", &description, (&rcfg, &rt), (&pcfg, &pt))
        .with_context(|| format!("writing {}", out.display()))?;
    println!("wrote {}", out.display());
    println!(
        "rangenet-small: {} parameters, {range_s:.0} s, final training loss {:.4}, held-out pixel accuracy {:.3}, mIoU {:.3}",
        RangeNet::parameter_count(&rcfg)?,
        rr.final_loss,
        rr.pixel_accuracy,
        rr.miou
    );
    println!(
        "pointnet-small: {} parameters, {point_s:.0} s, final training loss {:.4}, held-out layout accuracy {:.3}, composition TV {:.3} (baseline {:.3})",
        PointNet::parameter_count(&pcfg)?,
        pr.final_loss,
        pr.layout_accuracy,
        pr.composition_tv,
        pr.baseline_tv
    );
    println!("total {:.0} s", t0.elapsed().as_secs_f64());
    Ok(())
}
