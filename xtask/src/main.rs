//! `cargo xtask`: project automation (dataset conversion, benchmark reports, recipes) and the tidy checks
//! that keep the workspace's layering honest (run by `cargo test`).

use anyhow::Result;
use clap::{Parser, Subcommand};

// the global allocator and the process settings, as `veila` has them
#[path = "../../veila-cli/src/process.rs"]
mod process;

mod bench_encoders; // cargo xtask bench-encoders
mod bench_memory; // cargo xtask bench-memory (peak host memory of veila train)
mod bench_model; // cargo xtask bench-model
mod bench_real; // cargo xtask bench-real (and bench-report's real-frame section)
mod bench_report; // cargo xtask bench-report
mod build_cuda; // cargo xtask build-cuda (CUDA toolkit from PyPI)
mod convert; // cargo xtask convert       (veila-data shards)
mod device; // --device of the commands that run networks
mod encoder_transfer; // cargo xtask encoder-transfer (depth encoder recipes, sim vs real)
mod feature_nets; // cargo xtask train-feature-nets (veila-nn feature_nets)
mod kitti_weather; // cargo xtask kitti-weather (veila-data weather)
mod method_sweep; // cargo xtask method-sweep (generative methods at equal training compute)
mod overfit; // the bundled-size overfit check (an ignored test, run by hand)
mod progress; // progress bars of the long commands
mod sampler_name; // samplers by their command-line name
mod seed_spread; // cargo xtask seed-spread (recipes by the mean over their seeds, real frames)
mod simdata; // simulated examples for training and benchmarks
#[cfg(test)]
mod tidy;
mod train_default; // cargo xtask train-default (the bundled model)
mod train_probe; // cargo xtask train-probe (a run's checkpoints against the baselines)

#[derive(Debug, Parser)]
#[command(name = "xtask", about = "Veila project automation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    Convert(convert::ConvertArgs),
    /// Build KITTI-Weather (clean, night, fog, snow variants) from a KITTI-layout dataset.
    KittiWeather(kitti_weather::KittiWeatherArgs),
    /// Train the bundled model (models/default) from a fixed seed on the simulator's train split.
    TrainDefault(train_default::TrainDefaultArgs),
    /// Score a train-default run's newest checkpoints against the baselines (beside the run).
    TrainProbe(train_probe::TrainProbeArgs),
    /// Train the FRD / FPD feature networks (RangeNet, PointNet) on simulated scenes.
    TrainFeatureNets(feature_nets::TrainFeatureNetsArgs),
    /// Benchmark report: Veila vs the unconditional baseline and the ablations, and sampler speed vs quality.
    BenchReport(bench_report::BenchReportArgs),
    /// A bundle on the real KITTI / nuScenes frames of ../shared/data/real against the real scans
    /// and two image-free baselines (bench-report's real-frame section alone, in seconds).
    BenchReal(bench_real::BenchRealArgs),
    /// Depth-encoder training recipes (augmentation, domain randomisation) scored on simulated
    /// and on real images: the sim-to-real ablation at the encoders.
    EncoderTransfer(encoder_transfer::EncoderTransferArgs),
    /// CPU engine speed: forward b1/b8 and a b8 training step of the small denoiser (medians, JSON).
    BenchModel(bench_model::BenchModelArgs),
    /// Build `veila` with `--features cuda` without a local CUDA install (nvcc and libraries from
    /// PyPI wheels, a libcuda stub for linking), for a GPU machine.
    BuildCuda(build_cuda::BuildCudaArgs),
    /// Pretrained image encoders on the CPU: seconds per KITTI-size image in f32 / bf16 / f16, with
    /// the half-precision error next to the time.
    BenchEncoders(bench_encoders::BenchEncodersArgs),
    /// Peak host memory of `veila train` against the dataset size, examples in memory and streamed.
    BenchMemory(bench_memory::BenchMemoryArgs),
    /// Generative methods (ε / v diffusion, residual diffusion, rectified flow, regression) at
    /// equal training compute: quality against training seconds.
    MethodSweep(method_sweep::MethodSweepArgs),
    /// Recipes ranked by the mean over their seeds on the real frames: `bench-real` reports of each
    /// recipe's seeds aggregated per frame (mean ± std, seeds below the mean scan, difference to the
    /// first recipe with its standard error).
    SeedSpread(seed_spread::SeedSpreadArgs),
    /// Print the workspace's crate layering rules (checked by `cargo test -p xtask`).
    Layers,
}

fn main() {
    process::tune_process();
    if let Err(err) = run(Cli::parse().command) {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Convert(a) => convert::run(a),
        Command::KittiWeather(a) => kitti_weather::run(a),
        Command::TrainFeatureNets(a) => feature_nets::run(a),
        Command::BenchReport(a) => bench_report::run(a),
        Command::BenchReal(a) => bench_real::run(a),
        Command::EncoderTransfer(a) => encoder_transfer::run(a),
        Command::MethodSweep(a) => method_sweep::run(a),
        Command::BenchModel(a) => bench_model::run(a),
        Command::BenchEncoders(a) => bench_encoders::run(a),
        Command::BenchMemory(a) => bench_memory::run(a),
        Command::BuildCuda(a) => build_cuda::run(a),
        Command::TrainDefault(a) => train_default::run(a).map(|_| ()),
        Command::TrainProbe(a) => train_probe::run(a),
        Command::SeedSpread(a) => seed_spread::run(a),
        Command::Layers => {
            println!("see ARCHITECTURE.md, section 'Layering'");
            Ok(())
        }
    }
}
