//! What a bundle's denoiser has learned at each noise level: on simulated held-out frames noised
//! to level `t`, the mean squared error of its `x̂₀` against the clean encoded scan, next to doing
//! nothing (`α·x_t`) and to the frames' own mean (a perfect unconditional mean predictor scores
//! about that). A diffusion model samples well only where its `x̂₀` beats both; the noisiest levels
//! decide the layout of a sample, the cleanest its fine texture.
//!
//! ```sh
//! cargo run --release -p veila-diffusion --features sim --example denoise_probe -- BUNDLE_DIR [FRAMES]
//! ```
//! Run from the workspace root (it reads `scenes/test-v5.txt`).

use std::path::Path;

use candle_core::Device;
use rand::SeedableRng;
use veila_diffusion::Diffusion;
use veila_diffusion::app::VeilaDenoiser;
use veila_diffusion::app::bundle::Bundle;
use veila_diffusion::app::sim_examples::render_split;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let dir = args
        .next()
        .ok_or("usage: denoise_probe BUNDLE_DIR [FRAMES]")?;
    let n: usize = args.next().map_or(Ok(8), |s| s.parse())?;
    let device = Device::Cpu;
    let bundle = Bundle::from_dir(Path::new(&dir), &device)?;
    if bundle.is_conditional() || bundle.config.residual.is_some() {
        return Err("the probe feeds no image: give an unconditional, non-residual bundle".into());
    }
    let frames = render_split(Path::new("scenes/test-v5.txt"), n, &bundle.config, &|| {})?;
    let scans: Vec<_> = frames.iter().map(|f| &f.range).collect();
    let x0 = bundle.config.encoding.encode_batch(&scans, &device)?;
    let diffusion = Diffusion::new(bundle.config.diffusion.clone())?;
    let model = VeilaDenoiser::new(bundle.denoiser.clone());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mse = |a: &candle_core::Tensor| -> candle_core::Result<f32> {
        (a - &x0)?.sqr()?.mean_all()?.to_scalar::<f32>()
    };
    let mean = x0.mean_keepdim(0)?.broadcast_as(x0.shape())?.contiguous()?;
    println!("{dir}: {n} frames of scenes/test-v5.txt");
    println!("| t | log-SNR | x̂₀ MSE | α·x_t MSE | frames' mean MSE |\n|---|---|---|---|---|");
    for t in [0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 0.98] {
        let level = diffusion.schedule().level(t);
        let eps = veila_diffusion::noise::randn(&mut rng, x0.dims(), &device)?;
        let x_t = ((&x0 * level.alpha())? + (&eps * level.sigma())?)?;
        let den = diffusion.denoise(&model, &x_t, &level, None, None, None)?;
        println!(
            "| {t:.2} | {:.2} | {:.5} | {:.5} | {:.5} |",
            level.log_snr,
            mse(&den.x0)?,
            mse(&(&x_t * level.alpha())?)?,
            mse(&mean)?
        );
    }
    Ok(())
}
