use candle_core::Device;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_diffusion::noise::randn;
use veila_diffusion::oracle::GaussianOracle;
use veila_diffusion::*;

fn ode_error(d: &Diffusion, cfg: SamplerConfig) -> f64 {
    let oracle = GaussianOracle::new(0.2, 0.5, d.clone()).unwrap();
    let sampler = Sampler::new(d, cfg).unwrap();
    let x_t = randn(&mut ChaCha8Rng::seed_from_u64(3), &[1, 1, 16, 16], &Device::Cpu).unwrap();
    let start = sampler.levels()[0];
    let xs = x_t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let out = sampler.sample_from(&oracle, x_t, None, &mut ChaCha8Rng::seed_from_u64(0), |_| {}).unwrap();
    let ys = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    xs.iter().zip(&ys).map(|(&x, &y)| (oracle.pf_ode_solution(x as f64, &start) - y as f64).abs()).fold(0.0, f64::max)
}

#[test]
fn scratch() {
    for sc in [ScheduleConfig::cosine_logsnr(), ScheduleConfig::cosine(), ScheduleConfig::ddpm_linear()] {
    for pred in [Prediction::Epsilon] {
        let d = Diffusion::new(DiffusionConfig { schedule: sc.clone(), prediction: pred, loss_weighting: LossWeighting::Uniform, ..DiffusionConfig::default() }).unwrap();
        for sp in [Spacing::Trailing, Spacing::LogSnr] {
            let mut line = format!("{sc:?} {sp:?}:");
            for n in [5, 10, 20, 40, 80] {
                let e1 = ode_error(&d, SamplerConfig { clip_x0: None, spacing: sp, ..SamplerConfig::ddim(n, 0.0) });
                let e2 = ode_error(&d, SamplerConfig { clip_x0: None, spacing: sp, ..SamplerConfig::dpm_solver_pp_2m(n) });
                line += &format!(" n={n} ddim {e1:.2e} dpm {e2:.2e} |");
            }
            eprintln!("{line}");
        }
    }}
}
