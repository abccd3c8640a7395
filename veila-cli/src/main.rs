//! `veila`: the command-line front end of the Veila workspace.
//!
//! Each command family lives in its own module and contributes a clap `Subcommand` enum that is flattened
//! into [`Command`]. Errors are reported through `anyhow` with the file and the problem named; the process
//! exits non-zero and never leaves partial output behind.

use anyhow::Result;
use clap::{Parser, Subcommand};

/// mimalloc keeps freed blocks for reuse; with glibc's allocator every large tensor of a
/// sampling step is a fresh `mmap` and page-faults in again (measured: ~30% of a training step).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

mod model;
mod progress;
mod report; // self-contained HTML reports (veila eval --report)
mod staging; // the output discipline of every command
// command modules (one per family):
mod data_cmd; // project, unproject, render           (veila-data)
mod demo_cmd; // demo (the README's main job)
mod edit_cmd; // edit (RePaint scene editing)         (veila-diffusion::pipeline)
mod eval_cmd; // eval, fd                               (veila-metrics)
mod eval_features; // FRD / FPD features for eval          (veila-nn::feature_nets)
mod generate_cmd; // generate                           (veila-diffusion::pipeline)
mod sim_cmd; // simulate                               (veila-data::sim)
mod train_cmd; // train (bundles from converted shards) (veila-diffusion::trainer)
mod weather_cmd; // weather                                (veila-data::weather)

/// Panoramic LiDAR generation from a monocular RGB image, and the tools around it.
#[derive(Debug, Parser)]
#[command(name = "veila", version, about, long_about = None)]
struct Cli {
    /// Suppress progress bars (they are also hidden when stderr is not a terminal).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    #[command(flatten)]
    Data(data_cmd::DataCmd),
    #[command(flatten)]
    Eval(eval_cmd::EvalCmd),
    #[command(flatten)]
    Sim(sim_cmd::SimCmd),
    #[command(flatten)]
    Weather(weather_cmd::WeatherCmd),
    /// The main job on the bundled default model: simulate a test-split scene, generate its 360°
    /// scan from the camera image alone, and write the generated and true scans, side-by-side
    /// views and the metrics to one folder.
    Demo(demo_cmd::DemoArgs),
    /// Generate panoramic LiDAR scans (KITTI .bin, range EXR, previews) from camera images and
    /// their calibration with a model bundle.
    Generate(generate_cmd::GenerateArgs),
    /// Edit a scan by inpainting: regenerate the pixels a mask image or a 3D box selects, consistent
    /// with the rest of the scan and the camera views (RePaint), and keep every other pixel.
    Edit(edit_cmd::EditArgs),
    /// Train a model bundle (encoders and denoiser) on converted shards from a TOML config;
    /// resumable: rerunning the same config continues from the newest checkpoint.
    Train(train_cmd::TrainArgs),
    /// Print the built-in sensor presets as TOML (a starting point for `--sensor FILE.toml`).
    Sensors,
}

fn main() {
    restore_default_sigpipe();
    staging::install_signal_cleanup();
    let cli = Cli::parse();
    progress::set_quiet(cli.quiet);
    if let Err(err) = run(cli.command) {
        let err = staging::explain(err);
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}

/// Rust ignores SIGPIPE, so `println!` panics when stdout is a closed pipe (`veila eval ... | head`).
/// Restore the default disposition, as command-line tools are expected to behave: the process ends
/// quietly when its reader goes away. Output files are unaffected (they are written atomically).
#[cfg(unix)]
fn restore_default_sigpipe() {
    // SAFETY: first statement of `main`, before any other thread exists; `SIG_DFL` is a valid
    // disposition for SIGPIPE.
    #[allow(unsafe_code)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(not(unix))]
fn restore_default_sigpipe() {}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Data(c) => data_cmd::run(c),
        Command::Eval(c) => eval_cmd::run(c),
        Command::Sim(c) => sim_cmd::run(c),
        Command::Weather(c) => weather_cmd::run(c),
        Command::Demo(a) => demo_cmd::run(a),
        Command::Generate(a) => generate_cmd::run(a),
        Command::Edit(a) => edit_cmd::run(a),
        Command::Train(a) => train_cmd::run(a),
        Command::Sensors => {
            for (name, sensor) in [
                ("hdl64e", veila_geom::LidarSensor::hdl64e()),
                ("hdl32e", veila_geom::LidarSensor::hdl32e()),
            ] {
                println!("# preset {name}\n{}", toml::to_string_pretty(&sensor)?);
            }
            Ok(())
        }
    }
}
