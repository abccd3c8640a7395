//! What a bundle's denoiser has learned at each noise level: on simulated held-out frames noised
//! to level `t`, the mean squared error of its `x̂₀` against the clean encoded scan, next to doing
//! nothing (`α·x_t`) and to the frames' own mean (a perfect unconditional mean predictor scores
//! about that). A diffusion model samples well only where its `x̂₀` beats both; the noisiest levels
//! decide the layout of a sample, the cleanest its fine texture.
//!
//! With `--sample N` it also draws `N` scans with the bundle's own sampler and prints each one's
//! distance (mean |Δ log2(1 + r)|) to its nearest probe frame, next to the frames' distances to
//! each other: the overfit check. A model trained on a handful of frames (`train-default --frames
//! 8`) and probed on those frames (`--scenes scenes/train-v5.txt`) must draw near-copies of them;
//! if it cannot, the encoding, loss, sampler or decoding disagree. Each draw's texture figures
//! (`veila demo`'s) sit next to its nearest frame's: a network that draws the layout but not the
//! fine texture of the frames it memorised cannot draw it for new ones either.
//!
//! With `--low` it looks closer at the clean levels, where a sample's fine texture forms: at each
//! level, the RMS of `x̂₀`'s error next to the level's `σ`, the share of the added noise `x̂₀`
//! keeps (its error projected on `σ·ε`: 0 removes the noise, 1 passes it through), and the error
//! when the network is told another time than the true one (`t` times 0.5, 0.7, 1.4, 2; the
//! conversion to `x̂₀` keeps the true level). A network that reads the level well scores best at
//! the true time; one that scores about the same at every told time reads the level from the
//! noise itself.
//!
//! With `--restart` it finds the levels where a draw's fine texture is made: each frame is noised
//! to a start level `t₀` and sampled from there down with the realism benchmark's solver
//! ([`Sampler::sample_from_level`](veila_diffusion::sampler::Sampler::sample_from_level) on the
//! levels below `t₀` of 32 DPM-Solver++ steps uniform in log-SNR, `x̂₀` clipped as there; SDEdit's
//! partial resampling), and the result's texture figures sit next to the frame's. Started low
//! enough, the sampler must hand the frame back with its texture; the lowest `t₀` at which the
//! texture breaks is where the network's `x̂₀` stops being precise enough for it.
//!
//! With `--bands` it splits the range channel's `x̂₀` error by the true range of the pixel (bands
//! of metres, dropped rays apart), in the encoded unit the loss sees and in metres, next to the
//! frames' own mean in that band: where in depth the network errs, and how much of each band's
//! variance it has explained at each level.
//!
//! ```sh
//! cargo run --release -p veila-diffusion --features sim --example denoise_probe -- \
//!     BUNDLE_DIR [FRAMES] [--scenes LIST] [--sample N] [--low] [--restart] [--bands]
//! ```
//! Run from the workspace root (it reads `scenes/test-v5.txt` unless `--scenes`).

use std::path::Path;

use candle_core::Device;
use rand::SeedableRng;
use veila_diffusion::Diffusion;
use veila_diffusion::app::VeilaDenoiser;
use veila_diffusion::app::bundle::Bundle;
use veila_diffusion::app::sim_examples::render_split;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    const USAGE: &str = "usage: denoise_probe BUNDLE_DIR [FRAMES] [--scenes LIST] [--sample N] [--low] [--restart] [--bands]";
    let mut dir = None;
    let mut n = 8usize;
    let mut scenes = String::from("scenes/test-v5.txt");
    let mut draws = 0usize;
    let mut low = false;
    let mut restart = false;
    let mut bands = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--scenes" => scenes = args.next().ok_or(USAGE)?,
            "--sample" => draws = args.next().ok_or(USAGE)?.parse()?,
            "--low" => low = true,
            "--restart" => restart = true,
            "--bands" => bands = true,
            _ if dir.is_none() => dir = Some(a),
            _ => n = a.parse()?,
        }
    }
    let dir = dir.ok_or(USAGE)?;
    let device = Device::Cpu;
    let bundle = Bundle::from_dir(Path::new(&dir), &device)?;
    if bundle.is_conditional() || bundle.config.residual.is_some() {
        return Err("the probe feeds no image: give an unconditional, non-residual bundle".into());
    }
    let frames = render_split(Path::new(&scenes), n, &bundle.config, &|| {})?;
    let scans: Vec<_> = frames.iter().map(|f| &f.range).collect();
    let x0 = bundle.config.encoding.encode_batch(&scans, &device)?;
    let diffusion = Diffusion::new(bundle.config.diffusion.clone())?;
    let model = VeilaDenoiser::new(bundle.denoiser.clone());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mse = |a: &candle_core::Tensor| -> candle_core::Result<f32> {
        (a - &x0)?.sqr()?.mean_all()?.to_scalar::<f32>()
    };
    let mean = x0.mean_keepdim(0)?.broadcast_as(x0.shape())?.contiguous()?;
    println!("{dir}: {n} frames of {scenes}");
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
    if bands {
        band_errors(&bundle, &diffusion, &model, &frames, &x0, &mean, &mut rng)?;
    }
    if low {
        low_levels(&diffusion, &model, &x0, &mut rng)?;
    }
    if restart {
        restart_levels(&bundle, &diffusion, &model, &frames, &x0, &mut rng)?;
    }
    if draws > 0 {
        sample_check(&bundle, &frames, draws)?;
    }
    Ok(())
}

/// The `--bands` table (module docs): the range channel's `x̂₀` error by the pixel's true range.
fn band_errors(
    bundle: &Bundle,
    diffusion: &Diffusion,
    model: &VeilaDenoiser<'_>,
    frames: &[veila_diffusion::app::sim_examples::SimExample],
    x0: &candle_core::Tensor,
    mean: &candle_core::Tensor,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Result<(), Box<dyn std::error::Error>> {
    const EDGES_M: [f32; 5] = [0.0, 10.0, 20.0, 40.0, f32::INFINITY];
    let labels = ["dropped", "< 10 m", "10-20 m", "20-40 m", ">= 40 m"];
    // band of each pixel of the batch (0: dropped ray), in the channel-0 layout of x0
    let band: Vec<usize> = frames
        .iter()
        .flat_map(|f| {
            f.range.range_m.iter().zip(&f.range.mask).map(|(&r, &m)| {
                if !(m && r.is_finite() && r > 0.0) {
                    0
                } else {
                    1 + EDGES_M[1..].iter().position(|&e| r < e).unwrap_or(3)
                }
            })
        })
        .collect();
    let range_channel = |x: &candle_core::Tensor| -> candle_core::Result<Vec<f32>> {
        x.narrow(1, 0, 1)?.flatten_all()?.to_vec1::<f32>()
    };
    let truth = range_channel(x0)?;
    let mean_v = range_channel(mean)?;
    let enc = &bundle.config.encoding;
    let count: Vec<usize> = (0..5)
        .map(|b| band.iter().filter(|&&x| x == b).count())
        .collect();
    println!(
        "\nrange channel, pixels per band: {}",
        labels
            .iter()
            .zip(&count)
            .map(|(l, c)| format!("{l} {c}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    println!(
        "| t | σ | {} |\n|---|---|{}",
        labels
            .iter()
            .map(|l| format!("{l}: RMS enc / mean's / metres MAE"))
            .collect::<Vec<_>>()
            .join(" | "),
        "---|".repeat(5)
    );
    for t in [0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9] {
        let level = diffusion.schedule().level(t);
        let eps = veila_diffusion::noise::randn(rng, x0.dims(), x0.device())?;
        let x_t = ((x0 * level.alpha())? + (&eps * level.sigma())?)?;
        let den = diffusion.denoise(model, &x_t, &level, None, None, None)?;
        let pred = range_channel(&den.x0)?;
        let mut sq = [0.0f64; 5];
        let mut sq_mean = [0.0f64; 5];
        let mut abs_m = [0.0f64; 5];
        for (p, &b) in band.iter().enumerate() {
            let e = (pred[p] - truth[p]) as f64;
            sq[b] += e * e;
            let em = (mean_v[p] - truth[p]) as f64;
            sq_mean[b] += em * em;
            abs_m[b] += (enc.decode_range(pred[p]) - enc.decode_range(truth[p])).abs() as f64;
        }
        let cells: Vec<String> = (0..5)
            .map(|b| {
                let n = count[b].max(1) as f64;
                format!(
                    "{:.4} / {:.4} / {:.2}",
                    (sq[b] / n).sqrt(),
                    (sq_mean[b] / n).sqrt(),
                    abs_m[b] / n
                )
            })
            .collect();
        println!("| {t} | {:.4} | {} |", level.sigma(), cells.join(" | "));
    }
    Ok(())
}

/// A network told `factor` times the time it is run at.
struct ToldTime<D> {
    inner: D,
    factor: f64,
}

impl<D: veila_diffusion::Denoiser> veila_diffusion::Denoiser for ToldTime<D> {
    type Cond = D::Cond;

    fn forward(
        &self,
        x_t: &candle_core::Tensor,
        t: &candle_core::Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<candle_core::Tensor> {
        self.inner.forward(x_t, &(t * self.factor)?, cond)
    }
}

/// The `--low` table (module docs).
fn low_levels(
    diffusion: &Diffusion,
    model: &VeilaDenoiser<'_>,
    x0: &candle_core::Tensor,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Result<(), Box<dyn std::error::Error>> {
    const TOLD: [f64; 4] = [0.5, 0.7, 1.4, 2.0];
    println!(
        "\n| t | σ | x̂₀ error RMS | error / σ | noise kept | RMS told t x {} |\n|---|---|---|---|---|---|",
        TOLD.map(|k| k.to_string()).join(" / ")
    );
    let rms = |a: &candle_core::Tensor| -> candle_core::Result<f64> {
        Ok((a - x0)?.sqr()?.mean_all()?.to_scalar::<f32>()?.sqrt() as f64)
    };
    for t in [0.0003, 0.001, 0.003, 0.01, 0.02, 0.05] {
        let level = diffusion.schedule().level(t);
        let eps = veila_diffusion::noise::randn(rng, x0.dims(), x0.device())?;
        let noise = (&eps * level.sigma())?;
        let x_t = ((x0 * level.alpha())? + &noise)?;
        let den = diffusion.denoise(model, &x_t, &level, None, None, None)?;
        let err = (&den.x0 - x0)?;
        let kept = (&err * &noise)?.sum_all()?.to_scalar::<f32>()? as f64
            / noise.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
        let told = TOLD
            .iter()
            .map(|&factor| {
                let m = ToldTime {
                    inner: model,
                    factor,
                };
                let d = diffusion.denoise(&m, &x_t, &level, None, None, None)?;
                Ok(format!("{:.5}", rms(&d.x0)?))
            })
            .collect::<Result<Vec<_>, Box<dyn std::error::Error>>>()?;
        let e = rms(&den.x0)?;
        println!(
            "| {t} | {:.5} | {e:.5} | {:.3} | {kept:.3} | {} |",
            level.sigma(),
            e / level.sigma(),
            told.join(" / ")
        );
    }
    Ok(())
}

/// The `--restart` table (module docs): the frames noised to `t₀` and sampled down from there.
fn restart_levels(
    bundle: &Bundle,
    diffusion: &Diffusion,
    model: &VeilaDenoiser<'_>,
    frames: &[veila_diffusion::app::sim_examples::SimExample],
    x0: &candle_core::Tensor,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Result<(), Box<dyn std::error::Error>> {
    use veila_diffusion::Spacing;
    use veila_diffusion::sampler::{Sampler, SamplerConfig};
    use veila_metrics::texture::{TextureSummary, scan_distance};
    // the realism benchmark's solver: 32 DPM-Solver++ steps, uniform in log-SNR down to t = 1e-3
    let mut cfg = SamplerConfig::dpm_solver_pp_2m(32);
    cfg.spacing = Spacing::LogSnr;
    let sampler = Sampler::new(diffusion, cfg)?;
    let frame_tex: Vec<TextureSummary> = frames
        .iter()
        .map(|f| TextureSummary::of(&f.range, &f.range))
        .collect::<Result<_, _>>()?;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "\n| t₀ | σ at t₀ | steps | smooth lower (%), result / frame | depth edges upper (%), result / frame | \
         texture along rows (w1, decades) | distance to its frame |\n|---|---|---|---|---|---|---|"
    );
    for t0 in [0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0] {
        let start = diffusion.schedule().level(t0);
        let eps = veila_diffusion::noise::randn(rng, x0.dims(), x0.device())?;
        let x_t = diffusion.q_sample(x0, &eps, &vec![start; x0.dim(0)?])?;
        let mut steps = 0;
        let x = sampler.sample_from_level(model, x_t, start, None, rng, |_| steps += 1)?;
        let scans = bundle.config.encoding.decode_batch(&x)?;
        let (mut smooth, mut edges, mut w1, mut dist) = (vec![], vec![], vec![], vec![]);
        for (scan, f) in scans.iter().zip(frames) {
            let tex = TextureSummary::of(scan, &f.range)?;
            smooth.push(tex.smooth_lower_pct);
            edges.push(tex.depth_edges_upper_pct);
            w1.push(tex.w1_along_decades);
            dist.push(scan_distance(scan, &f.range)?);
        }
        let frame_smooth: Vec<f64> = frame_tex.iter().map(|t| t.smooth_lower_pct).collect();
        let frame_edges: Vec<f64> = frame_tex.iter().map(|t| t.depth_edges_upper_pct).collect();
        println!(
            "| {t0} | {:.5} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.3} | {:.4} |",
            start.sigma(),
            steps,
            mean(&smooth),
            mean(&frame_smooth),
            mean(&edges),
            mean(&frame_edges),
            mean(&w1),
            mean(&dist)
        );
    }
    Ok(())
}

/// Draws `draws` scans and prints each one's distance to its nearest frame, next to how far the
/// frames lie from each other (the nearest other frame, median over frames).
fn sample_check(
    bundle: &Bundle,
    frames: &[veila_diffusion::app::sim_examples::SimExample],
    draws: usize,
) -> Result<(), Box<dyn std::error::Error>> {
    use veila_diffusion::app::generate::GenerateOptions;
    use veila_metrics::texture::{TextureSummary, nearest_scan, scan_distance};
    let pool: Vec<_> = frames.iter().map(|f| f.range.clone()).collect();
    let mut between = Vec::new();
    for (i, a) in pool.iter().enumerate() {
        let mut nearest = f64::INFINITY;
        for (j, b) in pool.iter().enumerate() {
            if j != i {
                nearest = nearest.min(scan_distance(a, b)?);
            }
        }
        if nearest.is_finite() {
            between.push(nearest);
        }
    }
    between.sort_by(f64::total_cmp);
    let valid_share = |scan: &veila_geom::RangeImage| {
        scan.mask.iter().filter(|&&m| m).count() as f64 / scan.mask.len().max(1) as f64
    };
    let frames_valid = pool.iter().map(valid_share).sum::<f64>() / pool.len().max(1) as f64;
    let mut options = GenerateOptions::new(bundle.config.sampler.clone());
    options.samples = draws;
    options.seed = 7;
    let t = std::time::Instant::now();
    let scans = bundle.generate(&[], &options, |_, _| {})?;
    println!(
        "\n{draws} samples ({:?}, {} steps) in {:.1} s; the frames' nearest other frame: median {:.4}; \
         the frames' valid share {frames_valid:.3}",
        bundle.config.sampler.kind,
        bundle.config.sampler.steps,
        t.elapsed().as_secs_f64(),
        between.get(between.len() / 2).copied().unwrap_or(f64::NAN)
    );
    // the texture figures of each draw against its nearest frame, and the frame's own: whether
    // the network can draw the data's fine texture at all, not only its layout
    println!(
        "| sample | nearest frame | distance | valid share | smooth lower (%), draw / frame | \
         depth edges upper (%), draw / frame | texture along rows (w1, decades) |\n|---|---|---|---|---|---|---|"
    );
    for (s, scan) in scans.iter().enumerate() {
        let (i, d) = nearest_scan(scan, &pool)?;
        let draw = TextureSummary::of(scan, &pool[i])?;
        let frame = TextureSummary::of(&pool[i], &pool[i])?;
        println!(
            "| {s} | {i} | {d:.4} | {:.3} | {:.2} / {:.2} | {:.2} / {:.2} | {:.3} |",
            valid_share(scan),
            draw.smooth_lower_pct,
            frame.smooth_lower_pct,
            draw.depth_edges_upper_pct,
            frame.depth_edges_upper_pct,
            draw.w1_along_decades
        );
    }
    Ok(())
}
