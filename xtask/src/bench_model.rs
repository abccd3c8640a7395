//! `cargo xtask bench-model`: the CPU engine's speed on the denoiser the project trains and samples,
//! and the export that lets PyTorch run the same networks.
//!
//! Times, for `DenoiserConfig::small()` as of issue 19 (unconditional, 32 x 256, f32, seeded random
//! weights, all cores): the forward pass at batch 1 and batch 8 and one training step at batch 8
//! (forward, MSE loss, backward, AdamW). The configuration is frozen in `bench_model_small.json` so the
//! figures stay comparable when the bundled default changes; `xtask/scripts/torch_yardstick.py` times
//! the same network in PyTorch. Prints the medians as one JSON object on stdout, and the CPU time over
//! wall time of the training steps (2.0 = both cores busy on this machine).
//!
//! `--network paper|bundled --export DIR` writes the whole conditioned network instead (issue 45):
//! `DenoiserConfig::paper()` with seeded weights, or the bundle's denoiser with its trained
//! weights; optionally on another `--grid` or at a reduced `--base-channels` for a quick check.
//! The export runs the network as training does (condition fusion through
//! `Denoiser::prepare_condition`, the per-sample `keep` factor of condition dropout, the GCMA
//! geometry of a KITTI camera through `Denoiser::geometry`) and writes the inputs, the geometry
//! tensors and candle's output; the candle side of these networks is timed by `veila bench`.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use clap::Args;
use serde::Serialize;
use veila_nn::export::{
    ConditionedExport, ExportWeights, reference_tensors, seeded_inputs, write_export,
};
use veila_nn::{Denoiser, DenoiserConfig, seeded_var_builder};

/// `DenoiserConfig::small().unconditional()` as it was when this benchmark was written.
const BENCH_CONFIG: &str = include_str!("bench_model_small.json");

/// Arguments of `cargo xtask bench-model`.
#[derive(Debug, Args)]
pub struct BenchModelArgs {
    /// Print only the JSON object (on stdout), without the human-readable lines on stderr.
    #[arg(long)]
    json: bool,
    /// Timed repetitions of each forward measurement (after 2 warm-up runs).
    #[arg(long, default_value_t = 15)]
    forward_runs: usize,
    /// Timed training steps (after 2 warm-up steps).
    #[arg(long, default_value_t = 11)]
    train_runs: usize,
    /// Seed of the weights and inputs.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the network and a reference output for `xtask/scripts/torch_yardstick.py` here:
    /// `config.json`, `weights.safetensors` and `reference.safetensors` (`x`, `t`, `y`, `ray_features`).
    #[arg(long)]
    export: Option<std::path::PathBuf>,
    /// Where the network runs: `cpu` (the benchmark's machine of record), `cuda` or `cuda:N`
    /// (needs `cargo xtask build-cuda --xtask`); the clock waits for the device at every reading.
    #[arg(long, default_value = "cpu", value_parser = crate::device::parse_device)]
    device: crate::device::DeviceArg,
    /// The network: `small` (the frozen benchmark network, timed), or the conditioned `paper`
    /// (`DenoiserConfig::paper()`, seeded weights) or `bundled` (the bundle's denoiser and trained
    /// weights, --model), which are only exported (needs --export).
    #[arg(long, value_enum, default_value_t = Network::Small)]
    network: Network,
    /// Range-image grid `HxW` of an exported `paper` or `bundled` network instead of its sensor's
    /// (both divisible by 2^(levels-1); e.g. `16x256` for a quick check).
    #[arg(long, value_name = "HxW", value_parser = parse_grid)]
    grid: Option<(u32, u32)>,
    /// Base channel count of an exported `paper` network instead of 64 (a reduced-width variant
    /// for a quick check).
    #[arg(long, value_name = "C")]
    base_channels: Option<usize>,
    /// Batch of the exported fixed input (the samples alternate keep = 1, 0: conditioned, dropped).
    #[arg(long, value_name = "B", default_value_t = 2)]
    export_batch: usize,
    /// Bundle folder of `--network bundled` (`--checkpoint` is an alias).
    #[arg(
        long,
        value_name = "DIR",
        default_value = "models/default",
        alias = "checkpoint"
    )]
    model: std::path::PathBuf,
}

/// The networks `bench-model` knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Network {
    /// `bench_model_small.json`: unconditional, 32 x 256.
    Small,
    /// `DenoiserConfig::paper()`: 64 x 1024, CACM, GCMA at every level, PFC.
    Paper,
    /// The bundle's denoiser (`--model`).
    Bundled,
}

impl Network {
    fn name(self) -> &'static str {
        match self {
            Network::Small => "small",
            Network::Paper => "paper",
            Network::Bundled => "bundled",
        }
    }
}

fn parse_grid(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("expected HxW with positive sizes (e.g. 16x256), got `{s}`");
    let (h, w) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (h, w): (u32, u32) = (
        h.trim().parse().map_err(|_| bad())?,
        w.trim().parse().map_err(|_| bad())?,
    );
    if h == 0 || w == 0 {
        return Err(bad());
    }
    Ok((h, w))
}

/// What `bench-model --json` prints.
#[derive(Debug, Serialize)]
struct BenchModelReport {
    forward_b1_ms: f64,
    forward_b8_ms: f64,
    train_b8_ms: f64,
    /// The training step's three phases (medians, so they need not add up to `train_b8_ms`):
    /// forward with gradient tracking and the loss, backward, AdamW.
    train_b8_forward_ms: f64,
    train_b8_backward_ms: f64,
    train_b8_optimizer_ms: f64,
    /// Process CPU time over wall time during the timed training steps.
    train_cpu_over_wall: Option<f64>,
    /// Batch-8 forward per sample over batch-1 forward (<= 1: batching helps).
    forward_b8_per_sample_over_b1: f64,
    /// Output of the batch-1 forward at the fixed input: mean and RMS (a check that nothing changed).
    forward_b1_mean: f64,
    forward_b1_rms: f64,
    threads: usize,
    params: usize,
    device: String,
}

/// The frozen benchmark configuration.
pub fn bench_config() -> Result<DenoiserConfig> {
    serde_json::from_str(BENCH_CONFIG).context("parsing bench_model_small.json")
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// User + system CPU time of this process in seconds (Linux `/proc/self/stat`, 100 ticks per second).
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // fields after the parenthesised command name; utime and stime are fields 14 and 15 (1-based)
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ut: f64 = f.get(11)?.parse().ok()?;
    let st: f64 = f.get(12)?.parse().ok()?;
    Some((ut + st) / 100.0)
}

fn time_forward(net: &Denoiser, x: &Tensor, t: &Tensor, runs: usize) -> Result<f64> {
    let mut times = Vec::with_capacity(runs);
    for i in 0..runs + 2 {
        x.device().synchronize()?;
        let start = Instant::now();
        let y = net.forward(x, t, None)?;
        // the work is done when the device says so (the CPU backend is synchronous)
        y.device().synchronize()?;
        if i >= 2 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(median(times))
}

/// Runs the benchmark.
pub fn run(args: BenchModelArgs) -> Result<()> {
    let dev: Device = args.device.open()?;
    if args.network != Network::Small {
        let Some(dir) = &args.export else {
            bail!(
                "--network {} is only exported (--export DIR); `veila bench --models` times it in candle",
                args.network.name()
            );
        };
        return export_conditioned(&args, dir, &dev);
    }
    if args.grid.is_some() || args.base_channels.is_some() {
        bail!("--grid and --base-channels apply to --network paper or bundled");
    }
    let cfg = bench_config()?;
    let varmap = VarMap::new();
    let net = Denoiser::new(
        &cfg,
        seeded_var_builder(&varmap, args.seed, DType::F32, &dev),
    )?;
    let params: usize = varmap.all_vars().iter().map(|v| v.elem_count()).sum();
    let runs = args.forward_runs.max(1);
    let (x1, t1) = seeded_inputs(&cfg, 1, args.seed, &dev)?;
    let (x8, t8) = seeded_inputs(&cfg, 8, args.seed + 1, &dev)?;
    let y1 = net.forward(&x1, &t1, None)?;
    let forward_b1_mean = f64::from(y1.mean_all()?.to_scalar::<f32>()?);
    let forward_b1_rms = f64::from(y1.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?);
    if let Some(dir) = &args.export {
        let reference = reference_tensors(&net, x1.clone(), t1.clone(), y1.clone());
        write_export(dir, &cfg, &varmap, &reference, None)
            .with_context(|| format!("writing the export into {}", dir.display()))?;
        eprintln!("wrote the yardstick inputs to {}", dir.display());
    }
    let forward_b1_ms = time_forward(&net, &x1, &t1, runs)?;
    let forward_b8_ms = time_forward(&net, &x8, &t8, runs)?;

    let mut opt = AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: 1e-4,
            ..Default::default()
        },
    )?;
    let noise = seeded_inputs(&cfg, 8, args.seed + 2, &dev)?.0;
    // one step, timed by phase: [forward + loss, backward, optimizer] in ms
    let mut step = || -> Result<[f64; 3]> {
        dev.synchronize()?;
        let t0 = Instant::now();
        let pred = net.forward(&x8, &t8, None)?;
        let loss = (pred - &noise)?.sqr()?.mean_all()?;
        dev.synchronize()?;
        let t1 = Instant::now();
        let grads = loss.backward()?;
        dev.synchronize()?;
        let t2 = Instant::now();
        opt.step(&grads)?;
        dev.synchronize()?;
        let t3 = Instant::now();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        Ok([ms(t0, t1), ms(t1, t2), ms(t2, t3)])
    };
    step()?;
    step()?;
    let train_runs = args.train_runs.max(1);
    let mut times = Vec::with_capacity(train_runs);
    let mut phases: [Vec<f64>; 3] = Default::default();
    let cpu0 = process_cpu_s();
    let wall0 = Instant::now();
    for _ in 0..train_runs {
        let start = Instant::now();
        let p = step()?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
        for (all, t) in phases.iter_mut().zip(p) {
            all.push(t);
        }
    }
    let [
        train_b8_forward_ms,
        train_b8_backward_ms,
        train_b8_optimizer_ms,
    ] = phases.map(median);
    let wall = wall0.elapsed().as_secs_f64();
    let train_cpu_over_wall = match (cpu0, process_cpu_s()) {
        (Some(a), Some(b)) if wall > 0.0 => Some((b - a) / wall),
        _ => None,
    };
    let train_b8_ms = median(times);
    let report = BenchModelReport {
        forward_b1_ms,
        forward_b8_ms,
        train_b8_ms,
        train_b8_forward_ms,
        train_b8_backward_ms,
        train_b8_optimizer_ms,
        train_cpu_over_wall,
        forward_b8_per_sample_over_b1: forward_b8_ms / 8.0 / forward_b1_ms,
        forward_b1_mean,
        forward_b1_rms,
        threads: rayon::current_num_threads(),
        params,
        device: args.device.name(),
    };
    if !args.json {
        eprintln!(
            "DenoiserConfig::small() unconditional {}x{}, f32, {} params, {} threads, on {}",
            cfg.height(),
            cfg.width(),
            params,
            report.threads,
            report.device
        );
        eprintln!("forward b1   {forward_b1_ms:8.1} ms (median of {runs})");
        eprintln!(
            "forward b8   {forward_b8_ms:8.1} ms (median of {runs}; {:.2}x batch 1 per sample)",
            report.forward_b8_per_sample_over_b1
        );
        eprintln!(
            "train b8     {train_b8_ms:8.1} ms (median of {train_runs}; forward + backward + AdamW)"
        );
        eprintln!(
            "  phases     {train_b8_forward_ms:.1} ms forward + loss, {train_b8_backward_ms:.1} ms backward, {train_b8_optimizer_ms:.1} ms AdamW (medians)"
        );
        if let Some(r) = train_cpu_over_wall {
            eprintln!("train CPU time / wall time {r:.2}");
        }
    }
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

/// The simulator's KITTI-like `image_2` camera (the rig the bundled model trains on), for images of
/// `w x h` pixels.
fn sim_camera(w: usize, h: usize) -> Result<veila_geom::PinholeCamera> {
    use veila_data::sim::{CameraConfig, SimCalib};
    let cam = SimCalib::from_config(&CameraConfig::default()).camera()?;
    cam.resized(w as u32, h as u32)
        .with_context(|| format!("resizing the simulator's camera to {w} x {h}"))
}

/// `--network paper|bundled --export DIR`: the conditioned network, its fixed input and output
/// (`veila_nn::export`).
fn export_conditioned(args: &BenchModelArgs, dir: &std::path::Path, dev: &Device) -> Result<()> {
    let bundle = match args.network {
        Network::Paper => None,
        Network::Bundled if args.base_channels.is_some() => {
            bail!("--base-channels would not fit the bundle's trained weights")
        }
        Network::Bundled => Some(
            veila_diffusion::app::Bundle::from_dir(&args.model, dev)
                .with_context(|| format!("loading the bundle {}", args.model.display()))?,
        ),
        Network::Small => bail!("internal: the small network has no conditioned export"),
    };
    let (mut config, image_hw, epipolar, weights) = match &bundle {
        None => (
            DenoiserConfig::paper(),
            (384, 1248),
            veila_geom::EpipolarConfig::default(),
            ExportWeights::Seeded,
        ),
        Some(b) => (
            b.config.denoiser.clone(),
            (b.config.image_height, b.config.image_width),
            b.config.epipolar,
            ExportWeights::Trained {
                tensors: &b.weights,
                source: &args.model,
            },
        ),
    };
    if let Some((h, w)) = args.grid {
        (config.sensor.rows, config.sensor.cols) = (h, w);
    }
    if let Some(c) = args.base_channels {
        config.base_channels = c;
    }
    let spec = ConditionedExport {
        network: args.network.name(),
        config,
        weights,
        camera: sim_camera(image_hw.1, image_hw.0)?,
        image_hw,
        epipolar,
        batch: args.export_batch,
        seed: args.seed,
    };
    let info = veila_nn::export::export_conditioned(&spec, dir, dev).with_context(|| {
        format!(
            "exporting the {} network into {}",
            spec.network,
            dir.display()
        )
    })?;
    eprintln!(
        "wrote {} ({}x{}, {} parameters, batch {}, keep alternating 1/0; the image changes the \
         output by {:.3} relative L2) to {}",
        info.network,
        info.grid[0],
        info.grid[1],
        info.params,
        info.batch,
        info.conditioning_effect_rel_l2,
        dir.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_parse_and_bad_ones_are_refused() {
        assert_eq!(parse_grid("16x256"), Ok((16, 256)));
        assert_eq!(parse_grid("64X1024"), Ok((64, 1024)));
        for bad in ["16", "0x256", "16x", "axb", "16x-4"] {
            assert!(parse_grid(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_paper_export_is_the_network_the_flags_name() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            args: BenchModelArgs,
        }
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ys");
        let cli = Cli::try_parse_from([
            "bench-model",
            "--network",
            "paper",
            "--grid",
            "8x64",
            "--base-channels",
            "8",
            "--export",
            out.to_str().unwrap(),
        ])
        .unwrap();
        run(cli.args).unwrap();
        // the network of the flags (veila_nn::export's own tests check what the files hold)
        let info: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("export.json")).unwrap())
                .unwrap();
        assert_eq!(info["network"], "paper");
        assert_eq!(info["grid"], serde_json::json!([8, 64]));
        assert_eq!(info["image"], serde_json::json!([384, 1248]));
        assert_eq!(info["batch"], 2);
    }

    #[test]
    fn frozen_config_is_the_small_unconditional_model() {
        let cfg = bench_config().unwrap();
        assert_eq!((cfg.height(), cfg.width()), (32, 256));
        assert!(cfg.conditioning.is_none());
        assert_eq!(cfg.base_channels, 16);
        cfg.validate().unwrap();
    }
}
