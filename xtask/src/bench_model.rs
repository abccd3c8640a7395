//! `cargo xtask bench-model`: the CPU engine's speed on the denoiser the project trains and samples,
//! and the export that lets PyTorch run the same networks.
//!
//! Times, for `DenoiserConfig::small()` as of issue 19 (unconditional, 32 x 256, f32, seeded random
//! weights, all cores): the forward pass at batch 1 and batch 8 and one training step at batch 8
//! (forward, MSE loss, backward, AdamW). The configuration is frozen in `bench_model_small.json` so the
//! figures stay comparable when the bundled default changes; `xtask/scripts/torch_yardstick.py` times
//! the same network in PyTorch. Prints the medians as one JSON object on stdout, and the CPU time over
//! wall time of the training steps (2.0 = both cores busy on this machine). The measuring is
//! `veila_nn::speed`; this driver parses the flags and prints.
//!
//! `--network paper|bundled --export DIR` writes the whole conditioned network instead (issue 45):
//! `DenoiserConfig::paper()` with seeded weights, or the bundle's denoiser with its trained
//! weights; optionally on another `--grid` or at a reduced `--base-channels` for a quick check.
//! The export runs the network as training does (condition fusion through
//! `Denoiser::prepare_condition`, the per-sample `keep` factor of condition dropout, the GCMA
//! geometry of a KITTI camera through `Denoiser::geometry`) and writes the inputs, the geometry
//! tensors and candle's output; the candle side of these networks is timed by `veila bench`.

use anyhow::{Context, Result, bail};
use candle_core::Device;
use clap::Args;
use veila_nn::DenoiserConfig;
use veila_nn::export::{ConditionedExport, ExportWeights};
use veila_nn::speed::{SpeedOptions, measure};

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

/// The frozen benchmark configuration.
pub fn bench_config() -> Result<DenoiserConfig> {
    serde_json::from_str(BENCH_CONFIG).context("parsing bench_model_small.json")
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
    let report = measure(
        &cfg,
        &SpeedOptions {
            forward_runs: args.forward_runs,
            train_runs: args.train_runs,
            seed: args.seed,
            device: (&dev, &args.device.name()),
            export: args.export.as_deref(),
        },
    )
    .with_context(|| match &args.export {
        Some(dir) => format!("timing the network (exported into {})", dir.display()),
        None => "timing the network".into(),
    })?;
    if let Some(dir) = &args.export {
        eprintln!("wrote the yardstick inputs to {}", dir.display());
    }
    let (runs, train_runs) = (args.forward_runs.max(1), args.train_runs.max(1));
    if !args.json {
        let r = &report;
        eprintln!(
            "DenoiserConfig::small() unconditional {}x{}, f32, {} params, {} threads, on {}",
            cfg.height(),
            cfg.width(),
            r.params,
            r.threads,
            r.device
        );
        eprintln!("forward b1   {:8.1} ms (median of {runs})", r.forward_b1_ms);
        eprintln!(
            "forward b8   {:8.1} ms (median of {runs}; {:.2}x batch 1 per sample)",
            r.forward_b8_ms, r.forward_b8_per_sample_over_b1
        );
        eprintln!(
            "train b8     {:8.1} ms (median of {train_runs}; forward + backward + AdamW)",
            r.train_b8_ms
        );
        eprintln!(
            "  phases     {:.1} ms forward + loss, {:.1} ms backward, {:.1} ms AdamW (medians)",
            r.train_b8_forward_ms, r.train_b8_backward_ms, r.train_b8_optimizer_ms
        );
        if let Some(x) = r.train_cpu_over_wall {
            eprintln!("train CPU time / wall time {x:.2}");
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
