//! The same numbers on every device: written once for a `Device`, run on the CPU and, with the
//! `cuda` feature, on the first CUDA device (noise is drawn on the CPU, so seeds agree).

use candle_core::Device;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::oracle::GaussianOracle;
use veila_diffusion::{Diffusion, DiffusionConfig, Sampler, SamplerConfig};

fn sample_on(dev: &Device) -> Vec<f32> {
    let d = Diffusion::new(DiffusionConfig::default()).unwrap();
    let oracle = GaussianOracle::new(0.1, 0.4, d.clone()).unwrap();
    let mut out = Vec::new();
    for cfg in [
        SamplerConfig::ddpm(20),
        SamplerConfig::ddim(20, 0.5),
        SamplerConfig::dpm_solver_pp_2m(10),
    ] {
        let s = Sampler::new(&d, cfg).unwrap();
        let x = s
            .sample(
                &oracle,
                &[2, 3, 4, 16],
                dev,
                None,
                &mut ChaCha8Rng::seed_from_u64(1),
            )
            .unwrap();
        assert!(x.device().same_device(dev));
        out.extend(x.flatten_all().unwrap().to_vec1::<f32>().unwrap());
    }
    out
}

fn matches_cpu(dev: &Device) {
    let a = sample_on(&Device::Cpu);
    let b = sample_on(dev);
    assert_eq!(a.len(), b.len());
    let m = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(m < 1e-4, "max difference to the CPU: {m}");
    assert!(a.iter().all(|v| v.is_finite()));
}

#[test]
fn samplers_cpu() {
    matches_cpu(&Device::Cpu);
}

#[cfg(feature = "cuda")]
#[test]
fn samplers_cuda() {
    matches_cpu(&Device::new_cuda(0).unwrap());
}
