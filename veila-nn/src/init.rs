//! Deterministic weight initialisation.
//!
//! candle's CPU random generator cannot be seeded, so a freshly built model differs between runs. The
//! [`seeded_var_builder`] draws every parameter from a ChaCha8 stream keyed by `(seed, tensor name)`,
//! honouring candle's init hints (constant, normal, uniform, Kaiming), and stores it as a trainable
//! [`candle_core::Var`] in the given [`VarMap`]. The same seed gives the same weights on every run and
//! every device, independently of the order in which layers are built.

use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::init::{Init, NormalOrUniform};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

struct SeededBackend {
    varmap: VarMap,
    seed: u64,
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Values of `init` for `shape`, drawn from a ChaCha8 stream seeded by `(seed, name)`.
pub fn seeded_values(init: Init, shape: &Shape, seed: u64, name: &str) -> Vec<f32> {
    let n = shape.elem_count();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ fnv1a(name));
    let normal = |rng: &mut ChaCha8Rng, mean: f64, std: f64| -> Vec<f32> {
        (0..n)
            .map(|_| (mean + std * rng.sample::<f64, _>(StandardNormal)) as f32)
            .collect()
    };
    let uniform = |rng: &mut ChaCha8Rng, lo: f64, up: f64| -> Vec<f32> {
        (0..n).map(|_| rng.random_range(lo..up) as f32).collect()
    };
    match init {
        Init::Const(c) => vec![c as f32; n],
        Init::Randn { mean, stdev } => normal(&mut rng, mean, stdev),
        Init::Uniform { lo, up } if up > lo => uniform(&mut rng, lo, up),
        Init::Uniform { lo, .. } => vec![lo as f32; n],
        Init::Kaiming {
            dist,
            fan,
            non_linearity,
        } => {
            let std = non_linearity.gain() / (fan.for_shape(shape).max(1) as f64).sqrt();
            match dist {
                NormalOrUniform::Normal => normal(&mut rng, 0.0, std),
                NormalOrUniform::Uniform => {
                    let bound = 3f64.sqrt() * std;
                    uniform(&mut rng, -bound, bound)
                }
            }
        }
    }
}

impl SimpleBackend for SeededBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut data = self
            .varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("poisoned varmap lock".into()))?;
        if let Some(v) = data.get(name) {
            if v.shape() != &s {
                candle_core::bail!(
                    "shape mismatch for {name}: stored {:?}, requested {s:?}",
                    v.shape()
                );
            }
            return v.as_tensor().to_dtype(dtype);
        }
        let values = seeded_values(h, &s, self.seed, name);
        let var = Var::from_tensor(&Tensor::from_vec(values, s, dev)?.to_dtype(dtype)?)?;
        let t = var.as_tensor().clone();
        data.insert(name.to_string(), var);
        Ok(t)
    }

    fn get_unchecked(
        &self,
        name: &str,
        dtype: DType,
        _dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let data = self
            .varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("poisoned varmap lock".into()))?;
        match data.get(name) {
            Some(v) => v.as_tensor().to_dtype(dtype),
            None => candle_core::bail!(
                "no tensor named {name} (get_unchecked needs a shape to initialise)"
            ),
        }
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.varmap
            .data()
            .lock()
            .map(|d| d.contains_key(name))
            .unwrap_or(false)
    }
}

/// A [`VarBuilder`] that creates trainable variables in `varmap` with seeded, name-keyed random values
/// (tensors already in `varmap` are reused). Use it instead of `VarBuilder::from_varmap` for
/// reproducible training runs and tests.
///
/// ```
/// use candle_core::{DType, Device};
/// use candle_nn::VarMap;
/// let (a, b) = (VarMap::new(), VarMap::new());
/// let wa = veila_nn::seeded_var_builder(&a, 7, DType::F32, &Device::Cpu)
///     .get_with_hints((2, 3), "w", candle_nn::init::DEFAULT_KAIMING_NORMAL)?;
/// let wb = veila_nn::seeded_var_builder(&b, 7, DType::F32, &Device::Cpu)
///     .get_with_hints((2, 3), "w", candle_nn::init::DEFAULT_KAIMING_NORMAL)?;
/// assert_eq!(wa.to_vec2::<f32>()?, wb.to_vec2::<f32>()?);
/// # Ok::<(), candle_core::Error>(())
/// ```
pub fn seeded_var_builder(
    varmap: &VarMap,
    seed: u64,
    dtype: DType,
    device: &Device,
) -> VarBuilder<'static> {
    VarBuilder::from_backend(
        Box::new(SeededBackend {
            varmap: varmap.clone(),
            seed,
        }),
        dtype,
        device.clone(),
    )
}
