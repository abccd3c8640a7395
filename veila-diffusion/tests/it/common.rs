//! Test networks: a tiny FiLM-conditioned conv net (trainable, candle style) and a conditional
//! Gaussian oracle.

use std::cell::Cell;

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, Linear, VarBuilder, VarMap, conv2d, linear};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::noise::randn;
use veila_diffusion::{Denoiser, Diffusion, NoiseLevel, Prediction};

/// Tiny denoiser configuration.
#[derive(Debug, Clone, Copy)]
pub struct TinyConfig {
    pub channels: usize,
    pub hidden: usize,
    /// Size of a per-sample conditioning vector (0 = unconditional).
    pub cond_dim: usize,
    /// A learned per-pixel embedding for inputs of this `(H, W)` (lets the net memorise a sample).
    pub pos: Option<(usize, usize)>,
}

/// conv3x3 -> FiLM(time[, cond]) -> SiLU -> conv3x3 -> SiLU -> conv3x3.
#[derive(Debug)]
pub struct TinyNet {
    conv_in: Conv2d,
    conv_mid: Conv2d,
    conv_out: Conv2d,
    film: Linear,
    cond: Option<Linear>,
    pos: Option<Tensor>,
    hidden: usize,
}

pub const TIME_FREQS: usize = 8;

impl TinyNet {
    pub fn new(cfg: TinyConfig, vb: VarBuilder<'_>) -> candle_core::Result<Self> {
        let c = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        Ok(Self {
            conv_in: conv2d(cfg.channels, cfg.hidden, 3, c, vb.pp("conv_in"))?,
            conv_mid: conv2d(cfg.hidden, cfg.hidden, 3, c, vb.pp("conv_mid"))?,
            conv_out: conv2d(cfg.hidden, cfg.channels, 3, c, vb.pp("conv_out"))?,
            film: linear(2 * TIME_FREQS, 2 * cfg.hidden, vb.pp("film"))?,
            cond: if cfg.cond_dim > 0 {
                Some(linear(cfg.cond_dim, 2 * cfg.hidden, vb.pp("cond"))?)
            } else {
                None
            },
            pos: match cfg.pos {
                Some((h, w)) => Some(vb.get_with_hints(
                    (1, cfg.hidden, h, w),
                    "pos",
                    candle_nn::Init::Const(0.0),
                )?),
                None => None,
            },
            hidden: cfg.hidden,
        })
    }

    /// Builds the net in a new VarMap under the prefix `tag`, with weights drawn from a seeded RNG
    /// (candle's own initialisers are not seedable on the CPU): weights ~ N(0, 1/fan_in), biases
    /// and embeddings 0.
    pub fn build_seeded(cfg: TinyConfig, tag: &str, seed: u64) -> (Self, VarMap) {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let net = Self::new(cfg, vb.pp(tag)).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let data = vm.data().lock().unwrap();
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        for n in names {
            let v = &data[n];
            let dims = v.dims().to_vec();
            let new = if n.ends_with("weight") {
                let fan_in: usize = dims[1..].iter().product();
                (randn(&mut rng, &dims, &Device::Cpu).unwrap() / (fan_in as f64).sqrt()).unwrap()
            } else {
                v.zeros_like().unwrap()
            };
            v.set(&new).unwrap();
        }
        drop(data);
        (net, vm)
    }

    /// [`Self::build_seeded`] with seed 0.
    pub fn build(cfg: TinyConfig, tag: &str) -> (Self, VarMap) {
        Self::build_seeded(cfg, tag, 0)
    }

    fn time_features(t: &Tensor) -> candle_core::Result<Tensor> {
        // t in [0, 1] (TimeInput::Unit); sin/cos at octave frequencies
        let t = t.to_dtype(DType::F32)?.unsqueeze(1)?; // [B, 1]
        let freqs: Vec<f32> = (0..TIME_FREQS)
            .map(|k| std::f32::consts::PI * (1 << k) as f32 / 2.0)
            .collect();
        let f = Tensor::from_vec(freqs, (1, TIME_FREQS), t.device())?;
        let a = t.broadcast_mul(&f)?;
        Tensor::cat(&[a.sin()?, a.cos()?], 1)
    }
}

impl Denoiser for TinyNet {
    type Cond = Tensor;

    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Tensor>,
    ) -> candle_core::Result<Tensor> {
        let mut film = self.film.forward(&Self::time_features(t)?)?; // [B, 2h]
        if let (Some(lin), Some(c)) = (&self.cond, cond) {
            film = (film + lin.forward(c)?)?;
        }
        let scale = film.narrow(1, 0, self.hidden)?.unsqueeze(2)?.unsqueeze(3)?;
        let shift = film
            .narrow(1, self.hidden, self.hidden)?
            .unsqueeze(2)?
            .unsqueeze(3)?;
        let mut h = self.conv_in.forward(x_t)?;
        if let Some(p) = &self.pos {
            h = h.broadcast_add(p)?;
        }
        let h = h
            .broadcast_mul(&(scale + 1.0)?)?
            .broadcast_add(&shift)?
            .silu()?;
        let h = self.conv_mid.forward(&h)?.silu()?;
        self.conv_out.forward(&h)
    }
}

/// Gaussian oracle whose data mean comes from the conditioning: `cond` is a `[B, 1, 1, 1]` tensor
/// of per-sample means; the null conditioning (zeros) means mean 0.
#[derive(Debug)]
pub struct CondOracle {
    pub std: f64,
    pub diffusion: Diffusion,
    pub calls: Cell<usize>,
}

impl CondOracle {
    pub fn new(std: f64, diffusion: Diffusion) -> Self {
        Self {
            std,
            diffusion,
            calls: Cell::new(0),
        }
    }

    fn level(&self, t: &Tensor) -> candle_core::Result<NoiseLevel> {
        let v = t.to_dtype(DType::F64)?.to_vec1::<f64>()?;
        Ok(self.diffusion.level_of_model_time(v[0]))
    }
}

impl Denoiser for CondOracle {
    type Cond = Tensor;

    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Tensor>,
    ) -> candle_core::Result<Tensor> {
        self.calls.set(self.calls.get() + 1);
        let l = self.level(t)?;
        let s2 = self.std * self.std;
        let d = l.alpha_bar * s2 + l.sigma2;
        let mu = match cond {
            Some(c) => c.clone(),
            None => x_t
                .zeros_like()?
                .narrow(1, 0, 1)?
                .narrow(2, 0, 1)?
                .narrow(3, 0, 1)?,
        };
        // E[x0 | x_t] = mu·σ²/d + α s²/d · x_t
        let x0 = (x_t * (l.alpha() * s2 / d))?.broadcast_add(&(mu * (l.sigma2 / d))?)?;
        match self.diffusion.prediction() {
            Prediction::Sample => Ok(x0),
            Prediction::Epsilon => (x_t - (x0 * l.alpha())?)? / l.sigma(),
            Prediction::V => {
                let eps = ((x_t - (&x0 * l.alpha())?)? / l.sigma())?;
                (eps * l.alpha())? - (x0 * l.sigma())?
            }
        }
    }
}

pub fn stats(t: &Tensor) -> (f64, f64) {
    let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let n = v.len() as f64;
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
    let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var)
}

pub fn all_finite(t: &Tensor) -> bool {
    t.flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .all(|x| x.is_finite())
}
