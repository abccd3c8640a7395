//! `veila convert`: a dataset (KITTI, SemanticKITTI, nuScenes) into the training shards `veila train`
//! reads (see `veila_data::convert` for the guarantees: bounded memory, atomic, resumable,
//! shardable).
//!
//! Its output publishes its own way rather than through `staging`: a conversion runs for hours over
//! many workers, so every shard and its sidecar are written atomically on their own, under names
//! that never collide with a published shard, and `manifest.json` last (one rename), by whichever
//! worker finds every shard complete; a rerun skips the complete shards and rebuilds the rest.
//!
//! The worker's shard comes from `--shard-index/--shard-count`, else from the environment:
//! `SLURM_ARRAY_TASK_ID` (minus `SLURM_ARRAY_TASK_MIN`) of `SLURM_ARRAY_TASK_COUNT` (a Slurm array
//! job), or `JOB_COMPLETION_INDEX` (a Kubernetes Indexed Job) with `--shard-count` or
//! `VEILA_SHARD_COUNT` giving the number of workers.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use veila_data::convert::{ConvertOptions, Progress, SourceSpec, convert, open_source};
use veila_data::dataset::DatasetName;
use veila_data::semantic_kitti::{Sequences, SplitPart};

use crate::progress;
use crate::workers::WorkerArgs;

/// Arguments of `veila convert`.
#[derive(Debug, Args)]
pub(crate) struct ConvertArgs {
    /// Dataset kind.
    #[arg(long, value_parser = crate::choices::dataset_parser())]
    dataset: DatasetName,
    /// Dataset root (KITTI: the folder with training/; SemanticKITTI: the folder with sequences/;
    /// nuScenes: the data root with v1.0-*/ tables or calib/*.json).
    #[arg(long, value_name = "DIR")]
    root: PathBuf,
    /// Output folder for shards and manifest.json (created; a rerun resumes it).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    #[arg(long, help = crate::choices::sensor_spec_help("Default: the dataset's sensor."))]
    sensor: Option<String>,
    #[command(flatten)]
    workers: WorkerArgs,
    /// Frames per shard file, 1 to 1024; peak memory is about this many frames (~4 MiB each for
    /// KITTI with images).
    #[arg(long, default_value_t = 32, value_parser = crate::bounds::int::<usize>(1, 1024))]
    frames_per_shard: usize,
    /// SemanticKITTI label map (default: ROOT/semantic-kitti.yaml or ROOT/../semantic-kitti.yaml).
    #[arg(long, value_name = "FILE")]
    label_map: Option<PathBuf>,
    /// SemanticKITTI: convert one part of the official split only (needs the label map).
    #[arg(long, value_parser = ["train", "valid", "test"], conflicts_with = "sequences")]
    split: Option<String>,
    /// SemanticKITTI: convert these sequences only, 0 to 99 each (comma separated, e.g. 0,1,8).
    #[arg(long, value_delimiter = ',', value_parser = crate::bounds::int::<u32>(0, 99))]
    sequences: Option<Vec<u32>>,
    /// nuScenes: the camera channels paired with each sweep, comma-separated; the first is each
    /// sample's camera, the others its further views (the paper's three:
    /// `CAM_FRONT,CAM_FRONT_LEFT,CAM_FRONT_RIGHT`).
    #[arg(long, value_delimiter = ',', default_value = "CAM_FRONT")]
    camera: Vec<String>,
    /// Leave camera images out of the shards (matrices are still stored).
    #[arg(long)]
    no_images: bool,
}

pub(crate) fn run(args: ConvertArgs) -> Result<()> {
    let (index, count) = args.workers.resolve()?;
    let spec = SourceSpec {
        images: !args.no_images,
        label_map: args.label_map.clone(),
        sequences: match (&args.split, &args.sequences) {
            (Some(part), _) => Sequences::Split(match part.as_str() {
                "train" => SplitPart::Train,
                "valid" => SplitPart::Valid,
                _ => SplitPart::Test,
            }),
            (None, Some(list)) => Sequences::List(list.clone()),
            (None, None) => Sequences::All,
        },
        cameras: args.camera.clone(),
        ..SourceSpec::new(args.dataset, args.root.clone())
    };
    let (dataset, label_map) = open_source(&spec).with_context(|| {
        format!(
            "cannot open {} dataset at {}",
            args.dataset,
            args.root.display()
        )
    })?;
    if args.dataset == DatasetName::SemanticKitti && label_map.is_none() {
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
    let bar = progress::bar(0, "convert");
    let on_progress = |p: Progress| match p {
        Progress::Start { frames } => bar.set_length(frames as u64),
        Progress::Frames(k) => bar.inc(k as u64),
    };
    let summary = convert(dataset.as_ref(), label_map.as_ref(), &opts, &on_progress)
        .with_context(|| format!("converting into {}", args.out.display()))?;
    bar.finish_and_clear();
    println!("{}", serde_json::to_string_pretty(&summary)?);
    if !summary.manifest_written {
        eprintln!("manifest.json not written yet: other workers' shards are still missing");
    }
    Ok(())
}
