//! `veila simulate`: procedural driving scenes rendered to a KITTI-layout dataset.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use veila_data::sim::{SceneConfig, simulate_to_dir};

use crate::progress;

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
    /// Number of frames (default: the scene file's frames.count).
    #[arg(long, value_name = "N")]
    frames: Option<u32>,
    /// Random seed of the scene layout and the sensor noise.
    #[arg(long, value_name = "S", default_value_t = 0)]
    seed: u64,
    /// Write into an existing, non-empty output directory (same-named files are replaced).
    #[arg(long)]
    force: bool,
}

pub(crate) fn run(cmd: SimCmd) -> Result<()> {
    match cmd {
        SimCmd::Simulate(args) => simulate(args),
    }
}

fn is_empty_dir(p: &Path) -> Result<bool> {
    Ok(std::fs::read_dir(p)
        .with_context(|| format!("{}: cannot read directory", p.display()))?
        .next()
        .is_none())
}

/// Move every file under `from` to the same relative path under `to` (renames within one file system).
fn merge_into(from: &Path, to: &Path) -> Result<()> {
    for entry in
        std::fs::read_dir(from).with_context(|| format!("{}: cannot read", from.display()))?
    {
        let entry = entry?;
        let src = entry.path();
        let dst = to.join(entry.file_name());
        if src.is_dir() {
            std::fs::create_dir_all(&dst)
                .with_context(|| format!("{}: cannot create", dst.display()))?;
            merge_into(&src, &dst)?;
        } else {
            std::fs::rename(&src, &dst)
                .with_context(|| format!("{}: cannot move into place", dst.display()))?;
        }
    }
    Ok(())
}

fn simulate(args: SimulateArgs) -> Result<()> {
    let config = SceneConfig::from_file(&args.scene)?;
    let frames = args.frames.unwrap_or(config.frames.count);
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    let out = &args.out;
    let exists = out.exists();
    if exists && !out.is_dir() {
        bail!("{}: exists and is not a directory", out.display());
    }
    if exists && !args.force && !is_empty_dir(out)? {
        bail!(
            "{}: exists and is not empty (choose another --out or pass --force)",
            out.display()
        );
    }
    // Render into a staging directory beside OUT, then move it into place: a failure leaves nothing.
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent)
        .with_context(|| format!("{}: cannot create", parent.display()))?;
    let staging = tempfile::Builder::new()
        .prefix(".veila-simulate-")
        .tempdir_in(&parent)
        .with_context(|| format!("{}: cannot create a staging directory", parent.display()))?;

    let pb = progress::bar(u64::from(frames), "simulate");
    let summary = simulate_to_dir(&config, args.seed, frames, staging.path(), |done| {
        pb.set_position(u64::from(done))
    })
    .with_context(|| format!("simulating {}", args.scene.display()))?;
    pb.finish_and_clear();

    if exists {
        merge_into(staging.path(), out)?;
    } else {
        let staged = staging.keep();
        std::fs::rename(&staged, out)
            .with_context(|| format!("{}: cannot move the output into place", out.display()))?;
    }
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
