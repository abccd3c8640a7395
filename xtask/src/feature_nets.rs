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
//! Everything is seeded (`--seed`); the default run takes a few minutes on a 2-core CPU.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{D, DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use clap::Args;
use glam::{Quat, Vec3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use veila_data::sim::{Scene, SceneConfig, SceneList, class};
use veila_nn::feature_nets::{
    self, PointNet, PointNetConfig, RangeNet, RangeNetConfig, RangeNetInput,
};
use veila_nn::seeded_var_builder;

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

const NUM_CLASSES: usize = class::NUM_LEARNING_CLASSES;
const LAYOUTS: usize = 3;
const RANGE_BATCH: usize = 4;
const POINT_BATCH: usize = 8;

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// One augmented scan.
struct Sample {
    scene: usize,
    layout: usize,
    input: RangeNetInput,
    /// Learning class per pixel (0 = ignore).
    pixel_class: Vec<u8>,
    points: Vec<Vec3>,
    /// Fraction of the scan's points per learning class.
    composition: [f32; NUM_CLASSES],
}

fn layout_index(scene_file: &Path, files: &[PathBuf]) -> usize {
    files.iter().position(|f| f == scene_file).unwrap_or(0)
}

fn simulate(
    pairs: &[(PathBuf, u64)],
    files: &[PathBuf],
    frames: u32,
    sensor: &veila_geom::LidarSensor,
    seed: u64,
) -> Result<Vec<Sample>> {
    let jobs: Vec<(usize, u32)> = (0..pairs.len())
        .flat_map(|s| (0..frames).map(move |f| (s, f)))
        .collect();
    let configs: Vec<SceneConfig> = files
        .iter()
        .map(|f| SceneConfig::from_file(f).with_context(|| format!("reading {}", f.display())))
        .collect::<Result<_>>()?;
    let scenes: Vec<Scene> = pairs
        .par_iter()
        .map(|(file, s)| {
            let cfg = &configs[layout_index(file, files)];
            Scene::generate(cfg, *s).with_context(|| format!("{} seed {s}", file.display()))
        })
        .collect::<Result<_>>()?;
    jobs.par_iter()
        .map(|&(si, fi)| {
            let scene = &scenes[si];
            let count = scene.config().frames.count.max(1);
            let frame = (fi * count / frames.max(1)).min(count - 1);
            let lidar = scene.config().lidar.sensor()?;
            let scan = scene
                .snapshot(frame)
                .render_lidar(&lidar, &scene.config().lidar.returns)?;
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ ((si as u64) << 20) ^ u64::from(fi));
            let yaw = rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
            let mirror = rng.random_bool(0.5);
            let rot = Quat::from_rotation_z(yaw);
            let points: Vec<Vec3> = scan
                .points
                .xyz
                .iter()
                .map(|p| {
                    let q = rot * *p;
                    if mirror { Vec3::new(q.x, -q.y, q.z) } else { q }
                })
                .collect();
            let labels: Vec<u8> = match &scan.points.label {
                Some(l) => l
                    .iter()
                    .map(|v| class::learning_id((v & 0xffff) as u16))
                    .collect(),
                None => bail!("simulated scan without labels"),
            };
            let input = RangeNetInput::from_points(&points, Some(&scan.points.intensity), sensor)?;
            let pixel_class = input
                .point_index
                .iter()
                .map(|&i| if i == u32::MAX { 0 } else { labels[i as usize] })
                .collect();
            let mut composition = [0f32; NUM_CLASSES];
            for &l in &labels {
                composition[l as usize] += 1.0;
            }
            let total = labels.len().max(1) as f32;
            composition.iter_mut().for_each(|c| *c /= total);
            Ok(Sample {
                scene: si,
                layout: layout_index(&pairs[si].0, files),
                input,
                pixel_class,
                points,
                composition,
            })
        })
        .collect()
}

/// Masked mean cross-entropy of `logits: [N, K]` against `labels: [N]` (u32) with `weight: [N]`.
fn masked_ce(logits: &Tensor, labels: &Tensor, weight: &Tensor) -> Result<Tensor> {
    let logp = candle_nn::ops::log_softmax(logits, D::Minus1)?;
    let picked = logp.gather(&labels.unsqueeze(1)?, 1)?.squeeze(1)?;
    let denom = weight.sum_all()?.maximum(1.0)?;
    Ok((picked.mul(weight)?.sum_all()?.neg()? / denom)?)
}

fn range_batch(
    samples: &[&Sample],
    cfg: &RangeNetConfig,
    dev: &Device,
) -> Result<(Tensor, Tensor, Tensor)> {
    let inputs: Vec<&RangeNetInput> = samples.iter().map(|s| &s.input).collect();
    let x = RangeNetInput::batch(&inputs, cfg, dev)?;
    let labels: Vec<u32> = samples
        .iter()
        .flat_map(|s| s.pixel_class.iter().map(|&c| u32::from(c)))
        .collect();
    let weight: Vec<f32> = labels
        .iter()
        .map(|&c| if c == 0 { 0.0 } else { 1.0 })
        .collect();
    let n = labels.len();
    Ok((
        x,
        Tensor::from_vec(labels, n, dev)?,
        Tensor::from_vec(weight, n, dev)?,
    ))
}

fn flat_logits(logits: &Tensor) -> Result<Tensor> {
    let k = logits.dim(1)?;
    Ok(logits.permute((0, 2, 3, 1))?.reshape(((), k))?)
}

fn lr_at(step: usize, steps: usize, base: f64) -> f64 {
    let warm = (steps / 20).max(1);
    if step < warm {
        base * (step + 1) as f64 / warm as f64
    } else {
        let t = (step - warm) as f64 / (steps - warm).max(1) as f64;
        base * (0.05 + 0.95 * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
    }
}

struct RangeReport {
    final_loss: f32,
    pixel_accuracy: f64,
    miou: f64,
}

fn train_rangenet(
    cfg: &RangeNetConfig,
    train: &[&Sample],
    held: &[&Sample],
    steps: usize,
    seed: u64,
    dev: &Device,
) -> Result<(HashMap<String, Tensor>, RangeReport)> {
    let varmap = VarMap::new();
    let net = RangeNet::new(cfg, seeded_var_builder(&varmap, seed, DType::F32, dev))?;
    let base_lr = 3e-3;
    let mut opt = AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: base_lr,
            weight_decay: 1e-4,
            ..Default::default()
        },
    )?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5a5a);
    let mut order: Vec<usize> = (0..train.len()).collect();
    let mut cursor = order.len();
    let start = Instant::now();
    let mut running = 0f32;
    let mut last_loss = f32::NAN;
    for step in 0..steps {
        let mut batch = Vec::with_capacity(RANGE_BATCH);
        while batch.len() < RANGE_BATCH.min(train.len()) {
            if cursor == order.len() {
                order.shuffle(&mut rng);
                cursor = 0;
            }
            batch.push(train[order[cursor]]);
            cursor += 1;
        }
        let (x, y, w) = range_batch(&batch, cfg, dev)?;
        opt.set_learning_rate(lr_at(step, steps, base_lr));
        let loss = masked_ce(&flat_logits(&net.forward_t(&x, true)?)?, &y, &w)?;
        opt.backward_step(&loss)?;
        let l = loss.to_scalar::<f32>()?;
        running = if step == 0 {
            l
        } else {
            0.95 * running + 0.05 * l
        };
        last_loss = running;
        if (step + 1) % 25 == 0 || step + 1 == steps {
            eprintln!(
                "rangenet step {:>4}/{steps}  loss {running:.4}  ({:.0} s)",
                step + 1,
                start.elapsed().as_secs_f64()
            );
        }
    }
    // held-out pixel accuracy and mIoU (inference mode, running statistics)
    let mut conf = vec![0u64; NUM_CLASSES * NUM_CLASSES];
    for chunk in held.chunks(RANGE_BATCH) {
        let (x, y, _) = range_batch(chunk, cfg, dev)?;
        let pred = flat_logits(&net.forward(&x)?)?
            .argmax(D::Minus1)?
            .to_vec1::<u32>()?;
        for (p, t) in pred.iter().zip(y.to_vec1::<u32>()?) {
            if t != 0 {
                conf[t as usize * NUM_CLASSES + *p as usize] += 1;
            }
        }
    }
    let total: u64 = conf.iter().sum();
    let correct: u64 = (0..NUM_CLASSES).map(|c| conf[c * NUM_CLASSES + c]).sum();
    let mut ious = Vec::new();
    for c in 1..NUM_CLASSES {
        let tp = conf[c * NUM_CLASSES + c] as f64;
        let t: u64 = (0..NUM_CLASSES).map(|p| conf[c * NUM_CLASSES + p]).sum();
        let p: u64 = (0..NUM_CLASSES).map(|t| conf[t * NUM_CLASSES + c]).sum();
        if t > 0 {
            ious.push(tp / ((t + p) as f64 - tp));
        }
    }
    let report = RangeReport {
        final_loss: last_loss,
        pixel_accuracy: correct as f64 / total.max(1) as f64,
        miou: ious.iter().sum::<f64>() / ious.len().max(1) as f64,
    };
    Ok((tensors_of(&varmap, net.batch_norm_stats())?, report))
}

/// The trained variables with the BatchNorm running statistics of the modules (which
/// `candle_nn::BatchNorm` keeps in its own copies).
fn tensors_of(varmap: &VarMap, stats: Vec<(String, Tensor)>) -> Result<HashMap<String, Tensor>> {
    let mut out: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("poisoned varmap lock"))?
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    for (k, v) in stats {
        out.insert(k, v);
    }
    Ok(out)
}

struct PointReport {
    final_loss: f32,
    layout_accuracy: f64,
    composition_tv: f64,
    baseline_tv: f64,
}

fn point_batch(
    samples: &[&Sample],
    cfg: &PointNetConfig,
    rng: Option<&mut ChaCha8Rng>,
    dev: &Device,
) -> Result<(Tensor, Tensor, Tensor)> {
    let n = cfg.num_points.unwrap_or(2048);
    let mut data = Vec::with_capacity(samples.len() * 3 * n);
    match rng {
        // training: a fresh random subset of every scan each time
        Some(rng) => {
            for s in samples {
                let mut pts = vec![Vec3::ZERO; n];
                for p in pts.iter_mut() {
                    *p = s.points[rng.random_range(0..s.points.len())];
                }
                let sub = PointNetConfig {
                    num_points: None,
                    ..cfg.clone()
                };
                data.extend(PointNet::prepare(&sub, &pts)?);
            }
        }
        // evaluation: exactly what `veila eval` feeds the net
        None => {
            for s in samples {
                data.extend(PointNet::prepare(cfg, &s.points)?);
            }
        }
    }
    let b = samples.len();
    let x = Tensor::from_vec(data, (b, 3, n), dev)?;
    let comp: Vec<f32> = samples.iter().flat_map(|s| s.composition).collect();
    let layout: Vec<u32> = samples.iter().map(|s| s.layout as u32).collect();
    Ok((
        x,
        Tensor::from_vec(comp, (b, NUM_CLASSES), dev)?,
        Tensor::from_vec(layout, b, dev)?,
    ))
}

fn point_loss(logits: &Tensor, comp: &Tensor, layout: &Tensor) -> Result<Tensor> {
    let comp_logp = candle_nn::ops::log_softmax(&logits.narrow(1, 0, NUM_CLASSES)?, D::Minus1)?;
    let soft_ce = (comp_logp.mul(comp)?.sum(D::Minus1)?.mean_all()?.neg())?;
    let lay = candle_nn::loss::cross_entropy(&logits.narrow(1, NUM_CLASSES, LAYOUTS)?, layout)?;
    Ok((soft_ce + lay)?)
}

fn train_pointnet(
    cfg: &PointNetConfig,
    train: &[&Sample],
    held: &[&Sample],
    steps: usize,
    seed: u64,
    dev: &Device,
) -> Result<(HashMap<String, Tensor>, PointReport)> {
    let varmap = VarMap::new();
    let net = PointNet::new(cfg, seeded_var_builder(&varmap, seed ^ 1, DType::F32, dev))?;
    let base_lr = 2e-3;
    let mut opt = AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: base_lr,
            weight_decay: 1e-4,
            ..Default::default()
        },
    )?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xa5a5);
    let start = Instant::now();
    let mut running = 0f32;
    for step in 0..steps {
        let batch: Vec<&Sample> = (0..POINT_BATCH)
            .map(|_| train[rng.random_range(0..train.len())])
            .collect();
        let (x, comp, layout) = point_batch(&batch, cfg, Some(&mut rng), dev)?;
        opt.set_learning_rate(lr_at(step, steps, base_lr));
        let loss = point_loss(&net.forward_t(&x, true)?.logits, &comp, &layout)?;
        opt.backward_step(&loss)?;
        let l = loss.to_scalar::<f32>()?;
        running = if step == 0 {
            l
        } else {
            0.95 * running + 0.05 * l
        };
        if (step + 1) % 100 == 0 || step + 1 == steps {
            eprintln!(
                "pointnet step {:>4}/{steps}  loss {running:.4}  ({:.0} s)",
                step + 1,
                start.elapsed().as_secs_f64()
            );
        }
    }
    let mut mean = [0f64; NUM_CLASSES];
    for s in train {
        for (m, c) in mean.iter_mut().zip(s.composition) {
            *m += f64::from(c) / train.len() as f64;
        }
    }
    let (mut right, mut tv, mut base_tv) = (0usize, 0f64, 0f64);
    for chunk in held.chunks(POINT_BATCH) {
        let (x, comp, layout) = point_batch(chunk, cfg, None, dev)?;
        let logits = net.forward(&x)?.logits;
        let pred_layout = logits
            .narrow(1, NUM_CLASSES, LAYOUTS)?
            .argmax(D::Minus1)?
            .to_vec1::<u32>()?;
        right += pred_layout
            .iter()
            .zip(layout.to_vec1::<u32>()?)
            .filter(|(p, t)| **p == *t)
            .count();
        let pred = candle_nn::ops::softmax(&logits.narrow(1, 0, NUM_CLASSES)?, D::Minus1)?
            .to_vec2::<f32>()?;
        for (p, t) in pred.iter().zip(comp.to_vec2::<f32>()?) {
            tv += 0.5
                * p.iter()
                    .zip(&t)
                    .map(|(a, b)| f64::from((a - b).abs()))
                    .sum::<f64>();
            base_tv += 0.5
                * mean
                    .iter()
                    .zip(&t)
                    .map(|(a, b)| (a - f64::from(*b)).abs())
                    .sum::<f64>();
        }
    }
    let n = held.len().max(1) as f64;
    let report = PointReport {
        final_loss: running,
        layout_accuracy: right as f64 / n,
        composition_tv: tv / n,
        baseline_tv: base_tv / n,
    };
    Ok((tensors_of(&varmap, net.batch_norm_stats())?, report))
}

pub fn run(a: TrainFeatureNetsArgs) -> Result<()> {
    let t0 = Instant::now();
    let root = workspace_root();
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
    let list = SceneList::read(&list_path)
        .with_context(|| format!("reading the scene list {}", list_path.display()))?;
    let files: Vec<PathBuf> = list.entries.iter().map(|e| e.scene.clone()).collect();
    if files.len() != LAYOUTS {
        bail!(
            "{}: expected {LAYOUTS} scene files (the layout head has {LAYOUTS} classes), found {}",
            list_path.display(),
            files.len()
        );
    }
    // a seeded draw of (scene file, seed) pairs, round-robin over the files so layouts stay balanced
    let mut rng = ChaCha8Rng::seed_from_u64(a.seed);
    let mut per_file: Vec<Vec<u64>> = list
        .entries
        .iter()
        .map(|e| {
            let mut s: Vec<u64> = e.seeds.clone().collect();
            s.shuffle(&mut rng);
            s
        })
        .collect();
    let mut pairs = Vec::with_capacity(a.scenes);
    for i in 0..a.scenes {
        let f = i % files.len();
        let Some(seed) = per_file[f].pop() else {
            bail!(
                "{} has too few seeds for --scenes {}",
                list_path.display(),
                a.scenes
            );
        };
        pairs.push((files[f].clone(), seed));
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
    let samples = simulate(&pairs, &files, a.frames, &rcfg.sensor, a.seed)?;
    let n_held_scenes = ((a.scenes as f64 * a.holdout).round() as usize).clamp(1, a.scenes - 1);
    let first_held = a.scenes - n_held_scenes;
    let (train, held): (Vec<&Sample>, Vec<&Sample>) =
        samples.iter().partition(|s| s.scene < first_held);
    eprintln!(
        "{} training scans, {} held-out scans ({:.0} s)",
        train.len(),
        held.len(),
        t0.elapsed().as_secs_f64()
    );
    let dev = Device::Cpu;
    let t_range = Instant::now();
    let (rt, rr) = train_rangenet(&rcfg, &train, &held, a.steps, a.seed, &dev)?;
    let range_s = t_range.elapsed().as_secs_f64();
    let t_point = Instant::now();
    let (pt, pr) = train_pointnet(&pcfg, &train, &held, a.point_steps, a.seed, &dev)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masked_cross_entropy_matches_a_direct_computation() {
        let dev = Device::Cpu;
        let logits = [[2.0f32, -1.0, 0.5], [0.0, 0.0, 3.0], [1.0, 1.0, 1.0]];
        let labels = [0u32, 2, 1];
        let weight = [1.0f32, 1.0, 0.0];
        let t = Tensor::new(&logits, &dev).unwrap();
        let got = masked_ce(
            &t,
            &Tensor::new(&labels, &dev).unwrap(),
            &Tensor::new(&weight, &dev).unwrap(),
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
        let mut want = 0.0f64;
        for i in 0..2 {
            let z: f64 = logits[i].iter().map(|v| f64::from(*v).exp()).sum();
            want -= f64::from(logits[i][labels[i] as usize]) - z.ln();
        }
        want /= 2.0;
        assert!((f64::from(got) - want).abs() < 1e-5, "{got} vs {want}");
        // all pixels ignored: zero, not NaN
        let zero = masked_ce(
            &t,
            &Tensor::new(&labels, &dev).unwrap(),
            &Tensor::zeros(3, DType::F32, &dev).unwrap(),
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
        assert_eq!(zero, 0.0);
    }

    #[test]
    fn learning_rate_warms_up_then_decays_to_five_percent() {
        let steps = 400;
        assert!(lr_at(0, steps, 1.0) < 0.1);
        assert!((lr_at(steps / 20, steps, 1.0) - 1.0).abs() < 1e-9);
        assert!((lr_at(steps - 1, steps, 1.0) - 0.05).abs() < 1e-3);
        for s in steps / 20..steps - 1 {
            assert!(lr_at(s + 1, steps, 1.0) <= lr_at(s, steps, 1.0));
        }
    }
}
