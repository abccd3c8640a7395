//! `cargo xtask bench-memory`: peak host memory of `veila train` against the dataset size, with
//! the examples in memory and streamed from the shards (`[data] stream = true`).
//!
//! For each frame count it renders that many frames of the simulator's train split at full size
//! (KITTI camera, 64-beam LiDAR), writes them as training shards like `veila convert`
//! (cached in `--work`), then runs the release `veila train` on them with the shipped bundle's
//! recipe for a few updates of every stage (encoders, mean network, denoiser), once per mode, and
//! reads the peak resident set it prints (`VmHWM`). What grows with the frames in memory mode is
//! every prepared example (image, sparse depth and labels, range image) and its frozen features;
//! in streaming mode only the shard index does.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use rayon::prelude::*;
use serde::Serialize;
use veila_data::semantic_kitti::class;
use veila_data::shard::{CameraMatrices, MANIFEST_FORMAT, Manifest, ShardSample, write_shard};
use veila_data::sim::{Scene, SceneConfig};
use veila_geom::{ProjectionOptions, Projector};

use crate::progress::workspace_root;
use veila_diffusion::app::sim_examples::split_items;

/// Arguments of `cargo xtask bench-memory`.
#[derive(Debug, Args)]
pub struct BenchMemoryArgs {
    /// Dataset sizes, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "10,1000")]
    frames: Vec<usize>,
    /// Updates of each stage (encoders, mean network, denoiser) per run.
    #[arg(long, default_value_t = 4)]
    steps: usize,
    /// Batch size of the runs.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Frames per shard file.
    #[arg(long, default_value_t = 64)]
    frames_per_shard: usize,
    /// Shards and runs go here (shards are kept and reused).
    #[arg(long, default_value = "target/bench-memory")]
    work: PathBuf,
    /// Write the rows as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Debug, Serialize)]
struct Row {
    frames: usize,
    mode: &'static str,
    peak_host_mib: f64,
    wall_s: f64,
    shard_mib: f64,
}

/// Renders the first `n` frames of the train split and writes them as shards (cached).
fn make_shards(dir: &Path, n: usize, per_shard: usize) -> Result<f64> {
    let manifest_path = dir.join("manifest.json");
    if let Ok(m) = Manifest::read(&manifest_path)
        && m.count == n
    {
        return Ok(m.shards.iter().map(|s| s.bytes as f64).sum::<f64>() / 1048576.0);
    }
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let root = workspace_root();
    let items = split_items(&root.join("scenes/train.txt"), n)?;
    if items.len() < n {
        bail!("the train split has only {} frames", items.len());
    }
    let bar = crate::progress::progress_bar(n as u64, "render");
    let mut entries = Vec::new();
    let mut sensor = None;
    for (k, chunk) in items.chunks(per_shard.max(1)).enumerate() {
        let samples: Vec<(ShardSample, veila_geom::LidarSensor)> = chunk
            .par_iter()
            .map(|(path, seed)| -> Result<_> {
                let cfg = SceneConfig::from_file(path)?;
                let scene = Scene::generate(&cfg, *seed)?;
                let frames = cfg.frames.count.max(1) as u64;
                let f = scene.render_frame((*seed % frames) as u32)?;
                let projector = Projector::new(&f.sensor, ProjectionOptions::default())?;
                let pts = &f.scan.points;
                let (mut img, _) = projector.project(&pts.xyz, Some(&pts.intensity), None)?;
                let labels = pts.label.as_ref().context("the simulator gave no labels")?;
                img.gather_labels(labels)?;
                let raw = img.label.clone().unwrap_or_default();
                bar.inc(1);
                Ok((
                    ShardSample {
                        id: format!("{}-{seed:06}", path.display()),
                        train_ids: Some(
                            raw.iter()
                                .map(|r| class::learning_id((r & 0xFFFF) as u16))
                                .collect(),
                        ),
                        scan: veila_geom::RangeImage {
                            point_index: vec![veila_geom::NO_POINT; img.num_pixels()],
                            label: None,
                            ..img
                        },
                        image: Some(f.image.to_rgb_image()?),
                        camera: Some(CameraMatrices::from_camera(&f.camera)),
                        extra_views: Vec::new(),
                    },
                    f.sensor.clone(),
                ))
            })
            .collect::<Result<_>>()?;
        let s = samples[0].1.clone();
        if samples.iter().any(|(_, x)| *x != s) {
            bail!("the train split's scenes use different LiDAR sensors");
        }
        let shard: Vec<ShardSample> = samples.into_iter().map(|(x, _)| x).collect();
        let p = dir.join(format!("shard-{k:05}.safetensors"));
        entries.push(write_shard(&p, &s, "sim", &shard)?);
        sensor = Some(s);
    }
    bar.finish_and_clear();
    let bytes: f64 = entries.iter().map(|e| e.bytes as f64).sum();
    Manifest {
        format: MANIFEST_FORMAT.into(),
        dataset: "sim".into(),
        sensor: sensor.context("no frames")?,
        frames_per_shard: per_shard,
        count: n,
        shards: entries,
    }
    .write(&manifest_path)?;
    Ok(bytes / 1048576.0)
}

pub fn run(args: BenchMemoryArgs) -> Result<()> {
    let root = workspace_root();
    let work = root.join(&args.work);
    println!("building the release veila ...");
    let status = Command::new(env!("CARGO"))
        .current_dir(&root)
        .args(["build", "--release", "--locked", "-p", "veila-cli"])
        .status()
        .context("cannot run cargo")?;
    if !status.success() {
        bail!("cargo build --release -p veila-cli failed");
    }
    let veila = root.join("target/release/veila");
    let mut rows = Vec::new();
    for &n in &args.frames {
        let shards = work.join(format!("shards-{n}"));
        let shard_mib = make_shards(&shards, n, args.frames_per_shard)?;
        for (mode, data) in [("memory", ""), ("stream", "stream = true\n")] {
            let out = work.join(format!("run-{n}-{mode}"));
            let _ = std::fs::remove_dir_all(&out);
            let config = work.join(format!("train-{n}-{mode}.toml"));
            std::fs::write(
                &config,
                format!(
                    "[data]\nshards = \"{}\"\nverify = false\n{data}\n[model]\nbundle = \"{}\"\n\n\
                     [train]\nsteps = {s}\nbatch = {b}\nencoder_steps = {s}\nencoder_batch = {b}\n\
                     checkpoint_every = {s}\n\n[output]\ndir = \"{}\"\n",
                    shards.display(),
                    root.join("models/default/bundle.json").display(),
                    out.display(),
                    s = args.steps,
                    b = args.batch,
                ),
            )?;
            let t = Instant::now();
            let o = Command::new(&veila)
                .args(["train", "--quiet", "--config"])
                .arg(&config)
                .output()
                .context("cannot run veila")?;
            let wall_s = t.elapsed().as_secs_f64();
            let stdout = String::from_utf8_lossy(&o.stdout);
            if !o.status.success() {
                bail!(
                    "veila train ({n} frames, {mode}) failed:\n{stdout}\n{}",
                    String::from_utf8_lossy(&o.stderr)
                );
            }
            let peak = stdout
                .lines()
                .find_map(|l| l.strip_prefix("peak host memory: "))
                .and_then(|l| l.trim_end_matches(" MiB").parse::<f64>().ok())
                .context("veila train printed no peak memory (Linux only)")?;
            println!("{n:>6} frames  {mode:<6}  peak host {peak:>7.0} MiB  {wall_s:>6.1} s");
            rows.push(Row {
                frames: n,
                mode,
                peak_host_mib: peak,
                wall_s,
                shard_mib,
            });
            let _ = std::fs::remove_dir_all(&out);
        }
    }
    println!();
    println!(
        "| frames | shards (MiB) | in memory: peak host (MiB), wall (s) | streamed: peak host (MiB), wall (s) |"
    );
    println!("|---|---|---|---|");
    for n in &args.frames {
        let get = |m: &str| rows.iter().find(|r| r.frames == *n && r.mode == m);
        if let (Some(a), Some(b)) = (get("memory"), get("stream")) {
            println!(
                "| {n} | {:.0} | {:.0}, {:.1} | {:.0}, {:.1} |",
                a.shard_mib, a.peak_host_mib, a.wall_s, b.peak_host_mib, b.wall_s
            );
        }
    }
    if let Some(p) = &args.json {
        std::fs::write(p, serde_json::to_vec_pretty(&rows)?)
            .with_context(|| format!("{}: cannot write", p.display()))?;
    }
    Ok(())
}
