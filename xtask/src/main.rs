//! `cargo xtask`: project automation (dataset conversion, benchmark reports, recipes) and the tidy checks
//! that keep the workspace's layering honest (run by `cargo test`).

use anyhow::Result;
use clap::{Parser, Subcommand};

mod convert; // cargo xtask convert       (veila-data shards)
mod kitti_weather; // cargo xtask kitti-weather (veila-data weather)
#[cfg(test)]
mod tidy;

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
    /// Print the workspace's crate layering rules (checked by `cargo test -p xtask`).
    Layers,
}

fn main() {
    if let Err(err) = run(Cli::parse().command) {
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Convert(a) => convert::run(a),
        Command::KittiWeather(a) => kitti_weather::run(a),
        Command::Layers => {
            println!("see ARCHITECTURE.md, section 'Layering'");
            Ok(())
        }
    }
}
