//! `cargo xtask convert`: a dataset into training shards (see `veila_data::convert` for the
//! guarantees: bounded memory, atomic, resumable, shardable).
//!
//! The worker's shard comes from `--shard-index/--shard-count`, else from the environment:
//! `SLURM_ARRAY_TASK_ID` (minus `SLURM_ARRAY_TASK_MIN`) of `SLURM_ARRAY_TASK_COUNT` (a Slurm array
//! job), or `JOB_COMPLETION_INDEX` (a Kubernetes Indexed Job) with `--shard-count` or
//! `VEILA_SHARD_COUNT` giving the number of workers.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use veila_data::convert::{ConvertOptions, Progress, convert, open_dataset};
use veila_data::dataset::Dataset;
use veila_data::nuscenes::NuScenesDataset;
use veila_data::semantic_kitti::{LabelMap, SemanticKittiDataset, Sequences, SplitPart};

/// Convert a dataset into training shards (safetensors + manifest.json).
#[derive(Debug, Args)]
pub struct ConvertArgs {
    /// Dataset kind.
    #[arg(long, value_parser = ["semantickitti", "kitti", "nuscenes"])]
    dataset: String,
    /// Dataset root (KITTI: the folder with training/; SemanticKITTI: the folder with sequences/;
    /// nuScenes: the data root with v1.0-*/ tables or calib/*.json).
    #[arg(long)]
    root: PathBuf,
    /// Output folder for shards and manifest.json.
    #[arg(long)]
    out: PathBuf,
    /// Sensor: hdl64e, hdl32e, hdl32e-per-beam or a .toml/.json file (default: the dataset's sensor).
    #[arg(long)]
    sensor: Option<String>,
    /// This worker's index (default: from Slurm / Kubernetes environment variables, else 0).
    #[arg(long)]
    shard_index: Option<usize>,
    /// Number of workers (default: from the environment, else 1).
    #[arg(long)]
    shard_count: Option<usize>,
    /// Frames per shard file; peak memory is about this many frames (~4 MiB each for KITTI with images).
    #[arg(long, default_value_t = 32)]
    frames_per_shard: usize,
    /// SemanticKITTI label map (default: ROOT/semantic-kitti.yaml or ROOT/../semantic-kitti.yaml).
    #[arg(long)]
    label_map: Option<PathBuf>,
    /// SemanticKITTI: convert one part of the official split only (needs the label map).
    #[arg(long, value_parser = ["train", "valid", "test"], conflicts_with = "sequences")]
    split: Option<String>,
    /// SemanticKITTI: convert these sequences only (comma separated, e.g. 0,1,8).
    #[arg(long, value_delimiter = ',')]
    sequences: Option<Vec<u32>>,
    /// nuScenes: the camera channels paired with each sweep, comma-separated; the first is each
    /// sample's camera, the others its further views (the paper's three:
    /// `CAM_FRONT,CAM_FRONT_LEFT,CAM_FRONT_RIGHT`).
    #[arg(long, value_delimiter = ',', default_value = "CAM_FRONT")]
    camera: Vec<String>,
    /// Leave camera images out of the shards (matrices are still stored).
    #[arg(long)]
    no_images: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn env_usize(env: &dyn Fn(&str) -> Option<String>, name: &str) -> Result<Option<usize>> {
    match env(name) {
        Some(v) => v.trim().parse::<usize>().map(Some).with_context(|| {
            format!("environment variable {name}={v:?} is not a non-negative integer")
        }),
        None => Ok(None),
    }
}

/// Resolve (index, count) from the flags and the environment (`env` looks a variable up).
fn worker(
    shard_index: Option<usize>,
    shard_count: Option<usize>,
    env: &dyn Fn(&str) -> Option<String>,
) -> Result<(usize, usize)> {
    if let Some(i) = shard_index {
        return check(i, shard_count.unwrap_or(1), "--shard-index/--shard-count");
    }
    if let Some(id) = env_usize(env, "SLURM_ARRAY_TASK_ID")? {
        let min = env_usize(env, "SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
        let n = match shard_count {
            Some(n) => n,
            None => env_usize(env, "SLURM_ARRAY_TASK_COUNT")?.context(
                "SLURM_ARRAY_TASK_ID is set but SLURM_ARRAY_TASK_COUNT is not; pass --shard-count",
            )?,
        };
        let i = id
            .checked_sub(min)
            .context("SLURM_ARRAY_TASK_ID is below SLURM_ARRAY_TASK_MIN")?;
        return check(i, n, "SLURM_ARRAY_TASK_ID/SLURM_ARRAY_TASK_COUNT");
    }
    if let Some(i) = env_usize(env, "JOB_COMPLETION_INDEX")? {
        let n = match shard_count {
            Some(n) => n,
            None => env_usize(env, "VEILA_SHARD_COUNT")?.context(
                "JOB_COMPLETION_INDEX is set: pass --shard-count (or VEILA_SHARD_COUNT) with the job's completions",
            )?,
        };
        return check(i, n, "JOB_COMPLETION_INDEX");
    }
    check(0, shard_count.unwrap_or(1), "--shard-count")
}

fn check(i: usize, n: usize, from: &str) -> Result<(usize, usize)> {
    if n == 0 || i >= n {
        bail!("shard index {i} is not in 0..{n} (from {from})");
    }
    Ok((i, n))
}

type Opened = (Box<dyn Dataset>, Option<LabelMap>);

fn open(args: &ConvertArgs) -> Result<Opened> {
    let images = !args.no_images;
    match args.dataset.as_str() {
        "semantickitti" => {
            let map = args.label_map.as_deref().map(LabelMap::read).transpose()?;
            let sequences = match (&args.split, &args.sequences) {
                (Some(part), _) => Sequences::Split(match part.as_str() {
                    "train" => SplitPart::Train,
                    "valid" => SplitPart::Valid,
                    _ => SplitPart::Test,
                }),
                (None, Some(list)) => Sequences::List(list.clone()),
                (None, None) => Sequences::All,
            };
            let ds = match map {
                Some(m) => {
                    SemanticKittiDataset::open_with_label_map(&args.root, sequences, Some(m))?
                }
                None => SemanticKittiDataset::open(&args.root, sequences)?,
            }
            .with_images(images);
            let map = ds.label_map().cloned();
            Ok((Box::new(ds), map))
        }
        "nuscenes" => Ok((
            Box::new({
                let cams: Vec<&str> = args.camera.iter().map(String::as_str).collect();
                NuScenesDataset::open_cameras(&args.root, &cams)?.with_images(images)
            }),
            None,
        )),
        other => Ok(open_dataset(other, &args.root, images)?),
    }
}

pub fn run(args: ConvertArgs) -> Result<()> {
    let (index, count) = worker(args.shard_index, args.shard_count, &|k| {
        std::env::var(k).ok()
    })?;
    let (dataset, label_map) = open(&args).with_context(|| {
        format!(
            "cannot open {} dataset at {}",
            args.dataset,
            args.root.display()
        )
    })?;
    if args.dataset == "semantickitti" && label_map.is_none() {
        eprintln!(
            "warning: no semantic-kitti.yaml found (pass --label-map): shards get raw labels only"
        );
    }
    let sensor = match &args.sensor {
        Some(s) => veila_data::spec::sensor_from_spec(s)?,
        None => dataset.default_sensor(),
    };
    let mut opts = ConvertOptions::new(&args.out, sensor);
    opts.frames_per_shard = args.frames_per_shard;
    opts.worker_index = index;
    opts.worker_count = count;
    opts.include_images = !args.no_images;
    eprintln!(
        "converting {} frames of {} ({}) as worker {index} of {count} into {}",
        dataset.len(),
        args.dataset,
        args.root.display(),
        args.out.display()
    );
    let bar = ProgressBar::new(0);
    if args.quiet {
        bar.set_draw_target(ProgressDrawTarget::hidden());
    }
    bar.set_style(
        ProgressStyle::with_template(
            "{prefix:>10.bold} [{bar:30}] {pos}/{len} {per_sec} eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar.set_prefix("convert");
    let on_progress = |p: Progress| match p {
        Progress::Start { frames } => bar.set_length(frames as u64),
        Progress::Frames(k) => bar.inc(k as u64),
    };
    let summary = convert(dataset.as_ref(), label_map.as_ref(), &opts, &on_progress)?;
    bar.finish_and_clear();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    if !summary.manifest_written {
        eprintln!("manifest.json not written yet: other workers' shards are still missing");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(vars: &'static [(&'static str, &'static str)]) -> impl Fn(&str) -> Option<String> {
        move |k| {
            vars.iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn worker_from_flags_slurm_and_kubernetes() {
        assert_eq!(worker(None, None, &env(&[])).unwrap(), (0, 1));
        assert_eq!(
            worker(Some(2), Some(4), &env(&[("SLURM_ARRAY_TASK_ID", "0")])).unwrap(),
            (2, 4)
        );
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(worker(None, None, &slurm).unwrap(), (3, 4));
        // arrays numbered 1..=4
        let slurm1 = env(&[
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(worker(None, None, &slurm1).unwrap(), (3, 4));
        assert!(worker(None, None, &env(&[("SLURM_ARRAY_TASK_ID", "3")])).is_err());
        let k8s = env(&[("JOB_COMPLETION_INDEX", "5")]);
        assert!(worker(None, None, &k8s).is_err());
        assert_eq!(worker(None, Some(8), &k8s).unwrap(), (5, 8));
        assert_eq!(
            worker(
                None,
                None,
                &env(&[("JOB_COMPLETION_INDEX", "1"), ("VEILA_SHARD_COUNT", "2")])
            )
            .unwrap(),
            (1, 2)
        );
        assert!(worker(None, Some(5), &k8s).is_err());
        assert!(
            worker(
                None,
                None,
                &env(&[
                    ("SLURM_ARRAY_TASK_ID", "x"),
                    ("SLURM_ARRAY_TASK_COUNT", "4")
                ])
            )
            .is_err()
        );
    }
}
