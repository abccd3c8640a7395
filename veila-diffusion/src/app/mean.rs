//! The mean network of residual diffusion, frozen: the residual targets the denoiser trains on
//! ([`residual_target`], [`residual_scale`], with [`regression_weight`] leaving dropped rays out
//! of the regression loss) and the mean network's one-pass prediction of a batch
//! ([`MeanPredictor`], [`predict_means`], [`residual_scale_of`] for a streamed set).

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_geom::PinholeCamera;
use veila_nn::Denoiser as Net;
use veila_nn::encoders::kind::AnyEncoder;

use super::bundle::BundleConfig;
use super::dataset::{ExampleSource, Rigs, TrainExample};
use super::nn::{NetCond, VeilaDenoiser};
use super::stage::{Stage, encode_examples, has_gcma, num_views, rig_condition, stage_config};
use crate::error::{Error, Result};
use crate::objective::Diffusion;
use crate::sampler::{Sampler, SamplerConfig};

/// Per-element loss weights of a regression target: 1 on the ray-drop channel everywhere, and on
/// the range and intensity channels only where the target has a return (a dropped ray has no
/// range to predict).
pub fn regression_weight(enc: &crate::RangeEncoding, x0: &[f32], hw: usize) -> Vec<f32> {
    let c = enc.num_channels();
    let mut w = vec![1.0f32; c * hw];
    if let Some(dc) = enc.raydrop_channel() {
        for p in 0..hw {
            if x0[dc * hw + p] <= enc.raydrop_threshold {
                for ch in 0..c {
                    if ch != dc {
                        w[ch * hw + p] = 0.0;
                    }
                }
            }
        }
    }
    w
}

/// Per-element loss weights of the denoiser under [`BundleConfig::range_weight`] `power`: a
/// return's range and intensity weigh `((r + 1) / 11)^power`, `r` its range in metres decoded from
/// `x0` (1 at 10 m); dropped rays and the ray-drop channel weigh 1.
pub fn range_weight(enc: &crate::RangeEncoding, x0: &[f32], hw: usize, power: f64) -> Vec<f32> {
    let c = enc.num_channels();
    let mut w = vec![1.0f32; c * hw];
    for p in 0..hw.min(x0.len()) {
        let r = enc.decode_range(x0[p]);
        let returned = match enc.raydrop_channel() {
            Some(dc) => x0
                .get(dc * hw + p)
                .is_some_and(|&v| v > enc.raydrop_threshold),
            None => r >= enc.min_range_m,
        };
        if !returned {
            continue;
        }
        let wp = ((r as f64 + 1.0) / 11.0).powf(power) as f32;
        for ch in 0..c {
            if Some(ch) != enc.raydrop_channel() {
                w[ch * hw + p] = wp;
            }
        }
    }
    w
}

/// The loss weights of one encoded example `x0` in `stage`: the mean network's
/// [`regression_weight`]; the denoiser's [`range_weight`] where the config asks for one (on the
/// true scan, so a residual denoiser weighs its residual by the range it corrects); `None`: all 1.
pub fn loss_weight(config: &BundleConfig, stage: Stage, x0: &[f32], hw: usize) -> Option<Vec<f32>> {
    match (stage, config.range_weight) {
        (Stage::Mean, _) => Some(regression_weight(&config.encoding, x0, hw)),
        (Stage::Denoiser, Some(p)) if p > 0.0 => Some(range_weight(&config.encoding, x0, hw, p)),
        _ => None,
    }
}

/// The raw residual `x₀ − μ` of residual diffusion: where the target has no return, its range and
/// intensity are taken to be the mean's (they are not decoded), so only the ray-drop channel
/// carries a residual there.
pub fn raw_residual(enc: &crate::RangeEncoding, x0: &[f32], mean: &[f32], hw: usize) -> Vec<f32> {
    let w = regression_weight(enc, x0, hw);
    x0.iter()
        .zip(mean)
        .zip(&w)
        .map(|((x, m), w)| if *w > 0.0 { x - m } else { 0.0 })
        .collect()
}

/// The training target of a residual denoiser: [`raw_residual`] divided by the per-channel scale.
pub fn residual_target(
    enc: &crate::RangeEncoding,
    x0: &[f32],
    mean: &[f32],
    scale: &[f32],
    hw: usize,
) -> Vec<f32> {
    let mut r = raw_residual(enc, x0, mean, hw);
    for (ch, s) in scale.iter().enumerate() {
        for v in &mut r[ch * hw..(ch + 1) * hw] {
            *v /= s;
        }
    }
    r
}

/// The per-channel residual scale: the root mean square of [`raw_residual`] over the examples,
/// counted on returns for range and intensity and everywhere for ray drop (at least 1e-3).
pub fn residual_scale(
    enc: &crate::RangeEncoding,
    x0: &[Vec<f32>],
    means: &[Vec<f32>],
    hw: usize,
) -> Vec<f32> {
    let mut sums = ResidualSums::new(enc.num_channels());
    for (x, m) in x0.iter().zip(means) {
        sums.add(enc, x, m, hw);
    }
    sums.scale()
}

/// Running sums of squared residuals per channel (see [`residual_scale`]).
struct ResidualSums {
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl ResidualSums {
    fn new(c: usize) -> Self {
        Self {
            sum: vec![0.0; c],
            count: vec![0.0; c],
        }
    }

    fn add(&mut self, enc: &crate::RangeEncoding, x: &[f32], m: &[f32], hw: usize) {
        let w = regression_weight(enc, x, hw);
        let r = raw_residual(enc, x, m, hw);
        for ch in 0..self.sum.len() {
            for p in ch * hw..(ch + 1) * hw {
                if w[p] > 0.0 {
                    self.sum[ch] += f64::from(r[p]) * f64::from(r[p]);
                    self.count[ch] += 1.0;
                }
            }
        }
    }

    fn scale(&self) -> Vec<f32> {
        self.sum
            .iter()
            .zip(&self.count)
            .map(|(s, n)| ((s / n.max(1.0)).sqrt() as f32).max(1e-3))
            .collect()
    }
}

/// The frozen mean network of a residual bundle: its one-pass prediction of a batch of examples
/// (what the residual denoiser's targets subtract and what it is conditioned on).
pub struct MeanPredictor {
    config: BundleConfig,
    net: Net,
    diffusion: Diffusion,
    /// The geometry of each camera, when the mean network has GCMA.
    rigs: Option<Rigs>,
    device: Device,
}

impl std::fmt::Debug for MeanPredictor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeanPredictor").finish_non_exhaustive()
    }
}

impl MeanPredictor {
    /// The mean network of `config` with `weights` (the GCMA geometry of each camera is built
    /// when it first appears).
    pub fn new(
        config: &BundleConfig,
        weights: &HashMap<String, Tensor>,
        device: &Device,
    ) -> Result<Self> {
        let (cfg, diffusion) = stage_config(config, Stage::Mean)?;
        let net = Net::new(
            &cfg,
            VarBuilder::from_tensors(weights.clone(), DType::F32, device),
        )?;
        Ok(Self {
            config: config.clone(),
            rigs: has_gcma(&net).then(Rigs::new),
            net,
            diffusion: Diffusion::new(diffusion)?,
            device: device.clone(),
        })
    }

    /// The prediction (encoded, `channels * rows * cols` values) of each of `examples`, in one
    /// batch.
    pub fn predict(
        &self,
        semantic: Option<&AnyEncoder>,
        depth: Option<&AnyEncoder>,
        examples: &[TrainExample],
    ) -> Result<Vec<Vec<f32>>> {
        let input = if self.net.is_conditional() && !examples.is_empty() {
            let nv = num_views(&self.net);
            Some(encode_examples(
                &self.config,
                semantic,
                depth,
                examples,
                nv,
                &self.device,
            )?)
        } else {
            None
        };
        self.predict_encoded(input.as_ref(), examples)
    }

    /// [`Self::predict`] from the examples' frozen encoder features already computed
    /// ([`encode_examples`]; `None` for an unconditional network).
    pub(super) fn predict_encoded(
        &self,
        input: Option<&veila_nn::ConditionInput>,
        examples: &[TrainExample],
    ) -> Result<Vec<Vec<f32>>> {
        if examples.is_empty() {
            return Ok(Vec::new());
        }
        let cfg = self.net.config();
        let (h, w) = (cfg.height(), cfg.width());
        let c = self.config.channels();
        let sampler = Sampler::new(
            &self.diffusion,
            SamplerConfig {
                steps: 1,
                guidance_scale: 1.0,
                ..self.config.sampler.clone()
            },
        )?;
        let image = match (self.net.is_conditional(), input) {
            (true, Some(input)) => {
                let nv = num_views(&self.net);
                let rigs: Vec<Vec<PinholeCamera>> = examples.iter().map(|e| e.rig(nv)).collect();
                let cams: Vec<&[PinholeCamera]> = rigs.iter().map(|r| &r[..]).collect();
                Some(rig_condition(
                    &self.net,
                    self.rigs.as_ref(),
                    input,
                    &cams,
                    &self.config.epipolar,
                    &self.device,
                )?)
            }
            (true, None) => {
                return Err(Error::Data(
                    "the mean network is image-conditioned: it needs the examples' features".into(),
                ));
            }
            (false, _) => None,
        };
        let cond = NetCond { image, mean: None };
        let model = VeilaDenoiser::new(self.net.clone());
        let zeros = Tensor::zeros((examples.len(), c, h, w), DType::F32, &self.device)?;
        // the one-pass regression from zeros draws no noise; a fixed stream keeps it so anyway
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mu = sampler.sample_from(&model, zeros, Some(&cond), &mut rng, |_| {})?;
        (0..examples.len())
            .map(|i| Ok(mu.get(i)?.flatten_all()?.to_vec1::<f32>()?))
            .collect()
    }
}

/// The mean network's one-pass prediction (encoded, `channels * rows * cols` values) for every
/// example, in batches of `batch_size`: what a residual denoiser trains on.
pub fn predict_means(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    mean_weights: &HashMap<String, Tensor>,
    examples: &[TrainExample],
    batch_size: usize,
    device: &Device,
) -> Result<Vec<Vec<f32>>> {
    let predictor = MeanPredictor::new(config, mean_weights, device)?;
    let mut out = Vec::with_capacity(examples.len());
    for chunk in examples.chunks(batch_size.max(1)) {
        out.extend(predictor.predict(semantic, depth, chunk)?);
    }
    Ok(out)
}

/// [`residual_scale`] of a streamed set: one pass over `source` in chunks of `batch_size`, the
/// mean network (`mean_weights`) predicting each chunk; memory bounded by the chunk.
pub fn residual_scale_of(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    mean_weights: &HashMap<String, Tensor>,
    source: &dyn ExampleSource,
    batch_size: usize,
    device: &Device,
) -> Result<Vec<f32>> {
    if source.is_empty() {
        return Err(Error::Data(
            "the residual scale needs at least one example".into(),
        ));
    }
    let predictor = MeanPredictor::new(config, mean_weights, device)?;
    let (h, w) = (config.denoiser.height(), config.denoiser.width());
    let c = config.channels();
    let mut sums = ResidualSums::new(c);
    let n = source.len();
    let step = batch_size.max(1);
    for start in (0..n).step_by(step) {
        let chunk = (start..(start + step).min(n))
            .map(|i| source.example(i))
            .collect::<Result<Vec<_>>>()?;
        let means = predictor.predict(semantic, depth, &chunk)?;
        for (ex, m) in chunk.iter().zip(&means) {
            sums.add(&config.encoding, &ex.x0, m, h * w);
        }
    }
    Ok(sums.scale())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A return's weight is `((r + 1) / 11)^p` on range and intensity, worked out by hand for
    /// a few ranges; a dropped ray and the ray-drop channel keep 1.
    #[test]
    fn range_weight_grows_with_the_true_range_and_spares_dropped_rays() {
        let enc = crate::RangeEncoding::kitti();
        let ranges_m = [10.0f32, 32.0, 2.0, -1.0]; // the last: a dropped ray
        let hw = ranges_m.len();
        let mut x0 = vec![-1.0f32; 3 * hw];
        for (p, &r) in ranges_m.iter().enumerate() {
            if r > 0.0 {
                x0[p] = enc.encode_range(r);
                x0[hw + p] = 0.2;
                x0[2 * hw + p] = 1.0;
            }
        }
        for power in [1.0, 2.0, 0.5] {
            let w = range_weight(&enc, &x0, hw, power);
            let want = [1.0, 3f64.powf(power), (3.0f64 / 11.0).powf(power), 1.0];
            for (p, want) in want.iter().enumerate() {
                for ch in 0..2 {
                    let got = w[ch * hw + p] as f64;
                    assert!(
                        (got - want).abs() < 1e-4 * want,
                        "power {power} pixel {p} channel {ch}: {got} vs {want}"
                    );
                }
                assert_eq!(w[2 * hw + p], 1.0, "the ray-drop channel weighs 1");
            }
        }
        // power 0 is every pixel alike
        assert!(range_weight(&enc, &x0, hw, 0.0).iter().all(|&v| v == 1.0));
    }
}
