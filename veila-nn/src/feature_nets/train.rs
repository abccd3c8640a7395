//! Training the feature networks of FRD / FPD (`cargo xtask train-feature-nets`, which simulates
//! the scans and writes the bundle with [`super::save_bundle`]).
//!
//! * RangeNet: per-pixel cross-entropy over the 20-class learning map (class 0, unlabelled, and
//!   empty pixels ignored); held out: pixel accuracy and mIoU ([`train_rangenet`]).
//! * PointNet: a whole-scan task, because FPD feeds whole scans to the net: its first
//!   [`COMPOSITION_CLASSES`] logits predict the scan's class composition (soft-target
//!   cross-entropy), the last [`LAYOUTS`] its scene layout (cross-entropy); held out: layout
//!   accuracy and the total-variation distance of the composition, next to that of the training
//!   mean composition ([`train_pointnet`]).
//!
//! AdamW with a warm-up and a cosine decay to 5 % ([`learning_rate`]); every draw is seeded.

use std::collections::HashMap;

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use glam::Vec3;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{PointNet, PointNetConfig, RangeNet, RangeNetConfig, RangeNetInput};
use crate::error::{Error, Result};
use crate::seeded_var_builder;

/// Classes of the learning map (the RangeNet head and the PointNet composition head).
pub const COMPOSITION_CLASSES: usize = 20;
/// Scene layouts the PointNet layout head tells apart (one per scene file of the list).
pub const LAYOUTS: usize = 3;
const RANGE_BATCH: usize = 4;
const POINT_BATCH: usize = 8;

/// One augmented training scan.
#[derive(Debug, Clone)]
pub struct FeatureSample {
    /// The scene it was rendered from (held-out scenes are whole scenes).
    pub scene: usize,
    /// Its layout (the scene file's index in the list).
    pub layout: usize,
    /// The scan on the RangeNet's grid.
    pub input: RangeNetInput,
    /// Learning class per range pixel (0 = ignore).
    pub pixel_class: Vec<u8>,
    /// The scan's points.
    pub points: Vec<Vec3>,
    /// Fraction of the scan's points per learning class.
    pub composition: [f32; COMPOSITION_CLASSES],
}

/// Held-out figures of a trained RangeNet.
#[derive(Debug, Clone, Copy)]
pub struct RangeReport {
    /// Smoothed training loss at the last step.
    pub final_loss: f32,
    /// Held-out pixel accuracy (labelled pixels).
    pub pixel_accuracy: f64,
    /// Held-out mean IoU over the classes present.
    pub miou: f64,
}

/// Held-out figures of a trained PointNet.
#[derive(Debug, Clone, Copy)]
pub struct PointReport {
    /// Smoothed training loss at the last step.
    pub final_loss: f32,
    /// Held-out layout accuracy.
    pub layout_accuracy: f64,
    /// Held-out total-variation distance of the predicted composition.
    pub composition_tv: f64,
    /// The same for the training set's mean composition (the trivial baseline).
    pub baseline_tv: f64,
}

/// Masked mean cross-entropy of `logits: [N, K]` against `labels: [N]` (u32) with `weight: [N]`
/// (0 when every weight is 0).
pub fn masked_cross_entropy(logits: &Tensor, labels: &Tensor, weight: &Tensor) -> Result<Tensor> {
    let logp = candle_nn::ops::log_softmax(logits, D::Minus1)?;
    let picked = logp.gather(&labels.unsqueeze(1)?, 1)?.squeeze(1)?;
    let denom = weight.sum_all()?.maximum(1.0)?;
    Ok((picked.mul(weight)?.sum_all()?.neg()? / denom)?)
}

/// The learning rate at `step` of `steps`: a linear warm-up over the first 5 %, then a cosine
/// decay from `base` to 5 % of it.
pub fn learning_rate(step: usize, steps: usize, base: f64) -> f64 {
    let warm = (steps / 20).max(1);
    if step < warm {
        base * (step + 1) as f64 / warm as f64
    } else {
        let t = (step - warm) as f64 / (steps - warm).max(1) as f64;
        base * (0.05 + 0.95 * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
    }
}

fn range_batch(
    samples: &[&FeatureSample],
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

fn adamw(varmap: &VarMap, lr: f64) -> Result<AdamW> {
    Ok(AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr,
            weight_decay: 1e-4,
            ..Default::default()
        },
    )?)
}

/// An error unless there is a training sample.
fn check_samples(train: &[&FeatureSample]) -> Result<()> {
    if train.is_empty() {
        return Err(Error::Input("no training scans".into()));
    }
    Ok(())
}

/// Trains a RangeNet on `train` (batches of 4 in a seeded shuffled order) for `steps` steps and
/// scores it on `held`; `on_step(step, steps, smoothed_loss)` after every step. Returns the
/// weights (BatchNorm running statistics included) and the held-out figures.
pub fn train_rangenet(
    cfg: &RangeNetConfig,
    train: &[&FeatureSample],
    held: &[&FeatureSample],
    steps: usize,
    seed: u64,
    dev: &Device,
    mut on_step: impl FnMut(usize, usize, f32),
) -> Result<(HashMap<String, Tensor>, RangeReport)> {
    check_samples(train)?;
    let varmap = VarMap::new();
    let net = RangeNet::new(cfg, seeded_var_builder(&varmap, seed, DType::F32, dev))?;
    let base_lr = 3e-3;
    let mut opt = adamw(&varmap, base_lr)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5a5a);
    let mut order: Vec<usize> = (0..train.len()).collect();
    let mut cursor = order.len();
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
        opt.set_learning_rate(learning_rate(step, steps, base_lr));
        let loss = masked_cross_entropy(&flat_logits(&net.forward_t(&x, true)?)?, &y, &w)?;
        opt.backward_step(&loss)?;
        let l = loss.to_scalar::<f32>()?;
        running = if step == 0 {
            l
        } else {
            0.95 * running + 0.05 * l
        };
        last_loss = running;
        on_step(step + 1, steps, running);
    }
    // held-out pixel accuracy and mIoU (inference mode, running statistics)
    const K: usize = COMPOSITION_CLASSES;
    let mut conf = vec![0u64; K * K];
    for chunk in held.chunks(RANGE_BATCH) {
        let (x, y, _) = range_batch(chunk, cfg, dev)?;
        let pred = flat_logits(&net.forward(&x)?)?
            .argmax(D::Minus1)?
            .to_vec1::<u32>()?;
        for (p, t) in pred.iter().zip(y.to_vec1::<u32>()?) {
            if t != 0 && (t as usize) < K && (*p as usize) < K {
                conf[t as usize * K + *p as usize] += 1;
            }
        }
    }
    let total: u64 = conf.iter().sum();
    let correct: u64 = (0..K).map(|c| conf[c * K + c]).sum();
    let mut ious = Vec::new();
    for c in 1..K {
        let tp = conf[c * K + c] as f64;
        let t: u64 = (0..K).map(|p| conf[c * K + p]).sum();
        let p: u64 = (0..K).map(|t| conf[t * K + c]).sum();
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
        .map_err(|_| Error::Input("the VarMap lock is poisoned".into()))?
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    out.extend(stats);
    Ok(out)
}

fn point_batch(
    samples: &[&FeatureSample],
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
                if s.points.is_empty() {
                    return Err(Error::Input("a training scan without points".into()));
                }
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
        Tensor::from_vec(comp, (b, COMPOSITION_CLASSES), dev)?,
        Tensor::from_vec(layout, b, dev)?,
    ))
}

fn point_loss(logits: &Tensor, comp: &Tensor, layout: &Tensor) -> Result<Tensor> {
    let k = COMPOSITION_CLASSES;
    let comp_logp = candle_nn::ops::log_softmax(&logits.narrow(1, 0, k)?, D::Minus1)?;
    let soft_ce = (comp_logp.mul(comp)?.sum(D::Minus1)?.mean_all()?.neg())?;
    let lay = candle_nn::loss::cross_entropy(&logits.narrow(1, k, LAYOUTS)?, layout)?;
    Ok((soft_ce + lay)?)
}

/// Trains a PointNet (`cfg.num_classes` = [`COMPOSITION_CLASSES`] + [`LAYOUTS`]) on `train`
/// (batches of 8 drawn with replacement, a fresh random subset of each scan's points) and scores
/// it on `held`; `on_step` as for [`train_rangenet`].
pub fn train_pointnet(
    cfg: &PointNetConfig,
    train: &[&FeatureSample],
    held: &[&FeatureSample],
    steps: usize,
    seed: u64,
    dev: &Device,
    mut on_step: impl FnMut(usize, usize, f32),
) -> Result<(HashMap<String, Tensor>, PointReport)> {
    check_samples(train)?;
    if cfg.num_classes != COMPOSITION_CLASSES + LAYOUTS {
        return Err(Error::Config(format!(
            "the PointNet's {} logits are not {COMPOSITION_CLASSES} composition classes and {LAYOUTS} layouts",
            cfg.num_classes
        )));
    }
    let varmap = VarMap::new();
    let net = PointNet::new(cfg, seeded_var_builder(&varmap, seed ^ 1, DType::F32, dev))?;
    let base_lr = 2e-3;
    let mut opt = adamw(&varmap, base_lr)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xa5a5);
    let mut running = 0f32;
    for step in 0..steps {
        let batch: Vec<&FeatureSample> = (0..POINT_BATCH)
            .map(|_| train[rng.random_range(0..train.len())])
            .collect();
        let (x, comp, layout) = point_batch(&batch, cfg, Some(&mut rng), dev)?;
        opt.set_learning_rate(learning_rate(step, steps, base_lr));
        let loss = point_loss(&net.forward_t(&x, true)?.logits, &comp, &layout)?;
        opt.backward_step(&loss)?;
        let l = loss.to_scalar::<f32>()?;
        running = if step == 0 {
            l
        } else {
            0.95 * running + 0.05 * l
        };
        on_step(step + 1, steps, running);
    }
    let mut mean = [0f64; COMPOSITION_CLASSES];
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
            .narrow(1, COMPOSITION_CLASSES, LAYOUTS)?
            .argmax(D::Minus1)?
            .to_vec1::<u32>()?;
        right += pred_layout
            .iter()
            .zip(layout.to_vec1::<u32>()?)
            .filter(|(p, t)| **p == *t)
            .count();
        let pred = candle_nn::ops::softmax(&logits.narrow(1, 0, COMPOSITION_CLASSES)?, D::Minus1)?
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
        let got = masked_cross_entropy(
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
        let zero = masked_cross_entropy(
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
        assert!(learning_rate(0, steps, 1.0) < 0.1);
        assert!((learning_rate(steps / 20, steps, 1.0) - 1.0).abs() < 1e-9);
        assert!((learning_rate(steps - 1, steps, 1.0) - 0.05).abs() < 1e-3);
        for s in steps / 20..steps - 1 {
            assert!(learning_rate(s + 1, steps, 1.0) <= learning_rate(s, steps, 1.0));
        }
    }

    #[test]
    fn training_without_scans_or_with_a_mismatched_head_is_an_error() {
        let dev = Device::Cpu;
        let r = train_rangenet(&RangeNetConfig::small(), &[], &[], 1, 0, &dev, |_, _, _| {});
        assert!(r.is_err());
        let mut cfg = PointNetConfig::small();
        assert!(train_pointnet(&cfg, &[], &[], 1, 0, &dev, |_, _, _| {}).is_err());
        cfg.num_classes = 16;
        let sample = FeatureSample {
            scene: 0,
            layout: 0,
            input: RangeNetInput::from_points(
                &[Vec3::new(5.0, 0.0, 0.0)],
                None,
                &RangeNetConfig::small().sensor,
            )
            .unwrap(),
            pixel_class: vec![],
            points: vec![Vec3::new(5.0, 0.0, 0.0)],
            composition: [0.05; COMPOSITION_CLASSES],
        };
        let e = train_pointnet(&cfg, &[&sample], &[], 1, 0, &dev, |_, _, _| {});
        assert!(e.unwrap_err().to_string().contains("16 logits"));
    }
}
