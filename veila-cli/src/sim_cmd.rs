//! `veila simulate`: procedural driving scenes rendered to a KITTI-layout dataset.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use veila_data::sim::{SceneConfig, simulate_to_dir};

use crate::{progress, staging};

/// Scene simulator commands.
#[derive(Debug, Subcommand)]
pub(crate) enum SimCmd {
    /// Render a procedural scene (TOML scene file + seed) to paired LiDAR scans, camera images,
    /// semantic and depth maps in the KITTI layout: OUT/velodyne/000000.bin, OUT/labels/000000.label,
    /// OUT/image_2/000000.png, OUT/calib/000000.txt, OUT/depth_2/000000.png, OUT/semantic_2/000000.png.
    /// The same scene and seed always give byte-identical files.
    Simulate(SimulateArgs),
}

/// Arguments of `veila simulate`.
#[derive(Debug, Args)]
pub(crate) struct SimulateArgs {
    /// Scene file (TOML; see scenes/ for examples).
    #[arg(long, value_name = "SCENE.toml")]
    scene: PathBuf,
    /// Output directory (created; must not exist or be empty unless --force).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Number of frames, 1 to 100000 (default: the scene file's frames.count).
    #[arg(long, value_name = "N", value_parser = crate::bounds::int::<u32>(1, veila_data::sim::config::MAX_FRAMES.into()))]
    frames: Option<u32>,
    /// Random seed of the scene layout and the sensor noise, 0 to 18446744073709551615.
    #[arg(long, value_name = "S", default_value_t = 0)]
    seed: u64,
    /// Write into an existing, non-empty output directory: the files of an earlier `simulate` there
    /// are replaced (none of its frames stays beside the new ones), every other file is kept.
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(cmd: SimCmd) -> Result<()> {
    match cmd {
        SimCmd::Simulate(args) => simulate(args),
    }
}

fn simulate(args: SimulateArgs) -> Result<()> {
    let config = SceneConfig::from_file(&args.scene)?;
    let frames = args.frames.unwrap_or(config.frames.count);
    let max = veila_data::sim::config::MAX_FRAMES;
    if !(1..=max).contains(&frames) {
        match args.frames {
            Some(n) => bail!("--frames {n}: must be between 1 and {max}"),
            None => bail!(
                "{}: frames.count {frames}: must be between 1 and {max}",
                args.scene.display()
            ),
        }
    }
    let out = &args.out;
    let mut inputs = staging::Inputs::new();
    inputs.add(&args.scene);
    let staging = staging::stage_checked(out, args.force, &inputs)?;

    let pb = progress::bar(u64::from(frames), "simulate");
    let summary = simulate_to_dir(&config, args.seed, frames, staging.path(), |done| {
        pb.set_position(u64::from(done))
    })
    .with_context(|| format!("simulating {}", args.scene.display()))?;
    pb.finish_and_clear();

    staging.commit()?;
    let points: usize = summary.frame_stats.iter().map(|f| f.points).sum();
    let rays: usize = summary.frame_stats.iter().map(|f| f.rays).sum();
    println!(
        "wrote {frames} frame(s) of scene {:?} (seed {}) to {}: {:.0} points per scan ({:.1}% of rays returned)",
        config.name,
        args.seed,
        out.display(),
        points as f64 / f64::from(frames),
        100.0 * points as f64 / rays.max(1) as f64
    );
    Ok(())
}
