//! `cargo xtask`: project automation (the model recipes, benchmark reports, the CUDA build) and the
//! tidy checks that keep the workspace's layering honest (run by `cargo test`).

use anyhow::Result;
use clap::{Parser, Subcommand};

/// The allocator and the process settings `veila` runs with (`veila_nn::process`).
#[global_allocator]
static GLOBAL: veila_nn::process::MiMalloc = veila_nn::process::MiMalloc;

mod attach_prior; // cargo xtask attach-prior (veila-diffusion app::bundle::attach_prior)
mod bench_augment; // cargo xtask bench-augment (veila-diffusion app::augment)
mod bench_encoders; // cargo xtask bench-encoders
mod bench_memory; // cargo xtask bench-memory (peak host memory of veila train)
mod bench_model; // cargo xtask bench-model (veila-nn speed)
mod bench_real; // cargo xtask bench-real (veila-diffusion app::real_frames), the list parsers
mod bench_realism; // cargo xtask bench-realism (veila-diffusion app::realism)
mod bench_report; // cargo xtask bench-report (veila-diffusion app::bench_report)
mod build_cuda; // cargo xtask build-cuda (CUDA toolkit from PyPI)
mod check_kernels; // cargo xtask check-kernels (fused ops against their compositions, on a GPU too)
mod device; // --device of the commands that run networks
mod feature_nets; // cargo xtask train-feature-nets (veila-nn feature_nets)
mod kitti_weather; // cargo xtask kitti-weather (veila-data weather)
mod progress; // progress bars of the long commands, the workspace root
#[cfg(test)]
mod tidy;
mod train_default; // cargo xtask train-default (the bundled model; veila-diffusion app::sim_recipe)

#[derive(Debug, Parser)]
#[command(name = "xtask", about = "Veila project automation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// A direct-diffusion bundle with another bundle's mean network as the prior its draws start
    /// from (the same encoders required).
    AttachPrior(attach_prior::AttachPriorArgs),
    /// Build KITTI-Weather (clean, night, fog, snow variants) from a KITTI-layout dataset.
    KittiWeather(kitti_weather::KittiWeatherArgs),
    /// Train the bundled model (models/default) from a fixed seed on the simulator's train split.
    TrainDefault(train_default::TrainDefaultArgs),
    /// Train the FRD / FPD feature networks (RangeNet, PointNet) on simulated scenes.
    TrainFeatureNets(feature_nets::TrainFeatureNetsArgs),
    /// Benchmark report: Veila vs the unconditional baseline and the ablations, and sampler speed vs quality.
    BenchReport(bench_report::BenchReportArgs),
    /// A bundle on the real KITTI / nuScenes frames of ../shared/data/real against the real scans
    /// and two image-free baselines (bench-report's real-frame section alone, in seconds).
    BenchReal(bench_real::BenchRealArgs),
    /// Generators judged as generators: realism, texture, faithfulness, memorisation, diversity
    /// and time of every model row and sampler setting, next to the mean scan, retrieval and the
    /// data floor, on held-out simulated frames.
    BenchRealism(bench_realism::BenchRealismArgs),
    /// Generated scans for LiDAR segmentation: a segmenter trained on 1 %, 10 % and 20 % of the
    /// labels, alone and with generated scans pseudo-labelled by a teacher, against the true-scan,
    /// mean-network and retrieval controls (resumable; the paper's augmentation table).
    BenchAugment(bench_augment::BenchAugmentArgs),
    /// CPU engine speed: forward b1/b8 and a b8 training step of the small denoiser (medians, JSON).
    BenchModel(bench_model::BenchModelArgs),
    /// Build `veila` with `--features cuda` without a local CUDA install (nvcc and libraries from
    /// PyPI wheels, a libcuda stub for linking), for a GPU machine.
    BuildCuda(build_cuda::BuildCudaArgs),
    /// The fused ops (GroupNorm + SiLU, residual sum, AdamW) against their candle compositions on
    /// one device, errors next to milliseconds: the CUDA kernels' check on a GPU.
    CheckKernels(check_kernels::CheckKernelsArgs),
    /// Pretrained image encoders on the CPU: seconds per KITTI-size image in f32 / bf16 / f16, with
    /// the half-precision error next to the time.
    BenchEncoders(bench_encoders::BenchEncodersArgs),
    /// Peak host memory of `veila train` against the dataset size, examples in memory and streamed.
    BenchMemory(bench_memory::BenchMemoryArgs),
    /// Run the tidy checks (crate layering, import cycles, file sizes, no `#[path]` includes, ...):
    /// the `tidy::` tests of this crate, as `cargo test -p xtask --bin xtask -- tidy::` runs them.
    Tidy,
    /// Print the workspace's crate layering rules (checked by `cargo xtask tidy`).
    Layers,
}

fn main() {
    // SAFETY: first thing in `main`, before any other thread exists.
    #[allow(unsafe_code)]
    unsafe {
        veila_nn::process::tune_process();
    }
    if let Err(err) = run(Cli::parse().command) {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::AttachPrior(a) => attach_prior::run(a),
        Command::KittiWeather(a) => kitti_weather::run(a),
        Command::TrainFeatureNets(a) => feature_nets::run(a),
        Command::BenchReport(a) => bench_report::run(a),
        Command::BenchReal(a) => bench_real::run(a),
        Command::BenchRealism(a) => bench_realism::run(a),
        Command::BenchAugment(a) => bench_augment::run(a),
        Command::BenchModel(a) => bench_model::run(a),
        Command::BenchEncoders(a) => bench_encoders::run(a),
        Command::BenchMemory(a) => bench_memory::run(a),
        Command::BuildCuda(a) => build_cuda::run(a),
        Command::CheckKernels(a) => check_kernels::run(a),
        Command::TrainDefault(a) => train_default::run(a).map(|_| ()),
        Command::Tidy => tidy(),
        Command::Layers => {
            println!("see ARCHITECTURE.md, section 'Layering'");
            Ok(())
        }
    }
}

/// `cargo test -p xtask --bin xtask -- tidy::` in the workspace, its output passed through.
fn tidy() -> Result<()> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let root = progress::workspace_root();
    let status = std::process::Command::new(cargo)
        .args(["test", "-p", "xtask", "--bin", "xtask", "--", "tidy::"])
        .current_dir(&root)
        .status()
        .map_err(|e| anyhow::anyhow!("cannot run cargo test in {}: {e}", root.display()))?;
    if !status.success() {
        anyhow::bail!("tidy checks failed ({status})");
    }
    Ok(())
}
