//! Dataset-scale generation (`veila generate --frames DIR --out DIR`): a scan for every frame of a
//! KITTI-layout folder or of converted shards ([`FrameSource`]), written as a KITTI-layout folder
//! of generated scans:
//!
//! ```text
//! OUT/dataset.json        the job: bundle, sampler, seed and seed rule, source, labeller, frames
//! OUT/velodyne/NAME.bin   KITTI float32 x, y, z, intensity, in the frame's LiDAR frame
//! OUT/labels/NAME.label   SemanticKITTI raw labels, one u32 per point (with a ScanLabeller)
//! ```
//!
//! # Guarantees
//!
//! - **One path.** Each frame goes through [`ScanPipeline`] with one sample drawn from the seed
//!   [`frame_seed`] gives it, so a frame's scan is the one `veila generate --image --calib --seed`
//!   gives for that seed.
//! - **Seeded per frame.** A frame's seed is a function of the base seed and its name alone: the
//!   dataset does not depend on the order of the frames, the number of workers, or a resume.
//! - **Atomic, resumable.** Each frame's files are written to temporary files and renamed, the
//!   scan last, so a frame whose `velodyne/NAME.bin` is there is complete and a killed run leaves
//!   only hidden `.veila-*.tmp` files (removed by the next run). A rerun skips the complete frames.
//! - **Shardable.** Worker `i` of `n` generates the frames `k` with `k % n == i` (the split of
//!   `veila convert`, the workers numbered by [`veila_data::convert::worker_shard`]); workers share
//!   the output folder, and together write what one worker would, byte for byte.
//! - **One job per folder.** `dataset.json` records the job; a run of another job (another model,
//!   sampler, seed, labeller or list of frames) into the folder is refused, and so is a folder
//!   holding anything else, or one inside the frames' folder (the inputs are never written).
//!
//! # Pseudo-labels
//!
//! A [`ScanLabeller`] in [`DatasetJob::labeller`] labels every generated scan's points; its
//! [`ScanLabeller::identity`] goes into the manifest, and the labels are written beside the scan
//! in the same all-or-nothing step ([`generate_frame`]).

mod manifest;
mod source;

use std::path::{Component, Path, PathBuf};
use std::time::Instant;

use veila_data::atomic::{sweep_stale, write_atomic_all};
use veila_data::scan::encode_kitti_bin;
use veila_data::semantic_kitti::encode_labels;

pub use manifest::{
    BundleId, DATASET_FORMAT, DATASET_MANIFEST, DatasetManifest, LABELS_DIR, SCANS_DIR, SEED_RULE,
    frame_seed,
};
pub use source::{FrameSource, LoadedFrame, MAX_FRAMES, MAX_NAME_BYTES, SourceKind, frame_name};

use super::bundle::Bundle;
use super::generate::GenerateOptions;
use super::pipeline::{Scan, ScanPipeline};
use super::rig::RigImage;
use crate::error::{Error, Result};
use crate::sampler::SamplerConfig;

/// Point labels for generated scans: the pseudo-labelling step of a dataset generation (a
/// segmenter behind this trait gives `labels/NAME.label` beside every scan).
pub trait ScanLabeller {
    /// What identifies this labeller (its weights' SHA-256, say): recorded in `dataset.json`, so
    /// a run with another labeller is another job.
    fn identity(&self) -> String;

    /// One SemanticKITTI raw label per point of `scan.points`, in their order.
    fn label(&self, scan: &Scan) -> Result<Vec<u32>>;
}

/// What a dataset generation does: where, with which sampler and seed, as which worker.
pub struct DatasetJob<'a> {
    /// The output folder (created; see the module docs for what it may already hold).
    pub out_dir: PathBuf,
    /// Sampler, steps and guidance.
    pub sampler: SamplerConfig,
    /// Residual bundles: the weight of the sampled residual (see [`GenerateOptions`]).
    pub residual_weight: f64,
    /// The base seed; each frame's is [`frame_seed`] of it and the frame's name.
    pub seed: u64,
    /// This worker's index, `0..worker_count`.
    pub worker_index: usize,
    /// Number of workers sharing the job.
    pub worker_count: usize,
    /// Labels every scan's points (`labels/NAME.label`), when given.
    pub labeller: Option<&'a dyn ScanLabeller>,
}

impl std::fmt::Debug for DatasetJob<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DatasetJob")
            .field("out_dir", &self.out_dir)
            .field("sampler", &self.sampler)
            .field("residual_weight", &self.residual_weight)
            .field("seed", &self.seed)
            .field("worker_index", &self.worker_index)
            .field("worker_count", &self.worker_count)
            .field("labeller", &self.labeller.map(|l| l.identity()))
            .finish()
    }
}

/// Progress of a dataset generation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DatasetEvent<'a> {
    /// The folder is claimed: `to_generate` of this worker's `assigned` frames are left to do
    /// (the others were complete) out of `total` in the dataset.
    Start {
        /// Frames in the dataset.
        total: usize,
        /// Frames this worker is responsible for.
        assigned: usize,
        /// Of those, the frames this run generates.
        to_generate: usize,
    },
    /// Frame `name` was generated and written, in `seconds`.
    Frame {
        /// Its name.
        name: &'a str,
        /// Wall-clock time of reading, sampling, labelling and writing it.
        seconds: f64,
    },
}

/// What one run of a dataset generation did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DatasetSummary {
    /// Frames in the dataset.
    pub total: usize,
    /// Frames this worker is responsible for.
    pub assigned: usize,
    /// Of those, frames found complete and skipped.
    pub skipped: usize,
    /// Frames generated by this run.
    pub generated: usize,
    /// Frames of the whole dataset complete in the folder at the end (every worker's).
    pub complete: usize,
}

/// The job's manifest for `bundle` and `source` (what `dataset.json` holds).
pub fn job_manifest(
    bundle: &Bundle,
    source: &FrameSource,
    job: &DatasetJob<'_>,
) -> DatasetManifest {
    DatasetManifest {
        format: DATASET_FORMAT.into(),
        bundle: BundleId {
            name: bundle.config.name.clone(),
            manifest_sha256: bundle.manifest_sha256.clone(),
        },
        sampler: job.sampler.clone(),
        residual_weight: job.residual_weight,
        seed: job.seed,
        seed_rule: SEED_RULE.into(),
        source: source.kind().as_str().into(),
        labeller: job.labeller.map(|l| l.identity()),
        frames: source.names().to_vec(),
    }
}

/// Generates this worker's frames of `source` into `job.out_dir` (see the module docs), skipping
/// the complete ones. Everything is checked before anything is written: the options against the
/// bundle, the frames' cameras against the model, the output folder against the input and
/// against `dataset.json`. `on_event` hears the start and every frame.
pub fn generate_dataset(
    bundle: &Bundle,
    source: &FrameSource,
    job: &DatasetJob<'_>,
    on_event: &mut dyn FnMut(DatasetEvent<'_>),
) -> Result<DatasetSummary> {
    if job.worker_count == 0 || job.worker_index >= job.worker_count {
        return Err(Error::InvalidConfig {
            field: "worker_index",
            reason: format!(
                "worker {} is not in 0..{}",
                job.worker_index, job.worker_count
            ),
        });
    }
    let options = GenerateOptions {
        sampler: job.sampler.clone(),
        samples: 1,
        seed: job.seed,
        unconditional: false,
        residual_weight: job.residual_weight,
    };
    options.check(bundle)?;
    let views = bundle.config.num_views();
    source.check_views(views)?;
    let out = &job.out_dir;
    check_not_inside(source.dir(), out)?;
    manifest::claim(out, &job_manifest(bundle, source, job))?;
    let labels = job.labeller.is_some();
    let mut subdirs = vec![out.join(SCANS_DIR)];
    if labels {
        subdirs.push(out.join(LABELS_DIR));
    }
    for d in &subdirs {
        std::fs::create_dir_all(d).map_err(|source| Error::Io {
            action: "creating the output folder",
            path: d.clone(),
            source,
        })?;
        // temporary files of a killed run (nobody holds them locked any more)
        sweep_stale(d);
    }
    sweep_stale(out);

    let names = source.names();
    let assigned: Vec<usize> = (0..names.len())
        .filter(|k| k % job.worker_count == job.worker_index)
        .collect();
    let pending: Vec<usize> = assigned
        .iter()
        .copied()
        .filter(|&k| !frame_complete(out, &names[k], labels))
        .collect();
    on_event(DatasetEvent::Start {
        total: names.len(),
        assigned: assigned.len(),
        to_generate: pending.len(),
    });
    for &k in &pending {
        let t = Instant::now();
        generate_frame(bundle, source, k, &options, job.labeller, out)?;
        on_event(DatasetEvent::Frame {
            name: &names[k],
            seconds: t.elapsed().as_secs_f64(),
        });
    }
    Ok(DatasetSummary {
        total: names.len(),
        assigned: assigned.len(),
        skipped: assigned.len() - pending.len(),
        generated: pending.len(),
        complete: names
            .iter()
            .filter(|n| frame_complete(out, n, labels))
            .count(),
    })
}

/// The per-frame step: frame `k` of `source` read, its scan sampled with the frame's seed,
/// labelled when a labeller is given, and its files written all or nothing (the label file
/// first, the scan last: a scan's presence means the frame is complete).
pub fn generate_frame(
    bundle: &Bundle,
    source: &FrameSource,
    k: usize,
    options: &GenerateOptions,
    labeller: Option<&dyn ScanLabeller>,
    out: &Path,
) -> Result<()> {
    let name = &source.names()[k];
    let frame = source.load(k, bundle.config.num_views())?;
    let in_frame = |e: Error| Error::Input {
        path: frame.origin.clone(),
        reason: format!("frame `{name}`: {e}"),
    };
    let rig: Vec<RigImage<'_>> = frame
        .views
        .iter()
        .map(|(image, camera)| RigImage { image, camera })
        .collect();
    let pipeline = ScanPipeline::new(bundle, &rig).map_err(in_frame)?;
    let options = GenerateOptions {
        samples: 1,
        seed: frame_seed(options.seed, name),
        ..options.clone()
    };
    let scan = pipeline
        .generate(&options, |_, _| {})?
        .pop()
        .ok_or_else(|| in_frame(Error::Data("the sampler gave no scan".into())))?;
    // the pseudo-labelling hook
    let labels = labeller.map(|l| l.label(&scan)).transpose()?;
    let bin = encode_kitti_bin(&scan.points);
    let bin_path = out.join(SCANS_DIR).join(format!("{name}.bin"));
    match labels {
        Some(labels) => {
            if labels.len() != scan.points.len() {
                return Err(in_frame(Error::Data(format!(
                    "the labeller gave {} labels for {} points",
                    labels.len(),
                    scan.points.len()
                ))));
            }
            let label_path = out.join(LABELS_DIR).join(format!("{name}.label"));
            write_atomic_all(&[(&label_path, &encode_labels(&labels)), (&bin_path, &bin)])?;
        }
        None => write_atomic_all(&[(&bin_path, &bin)])?,
    }
    Ok(())
}

/// Whether frame `name` is complete in `out`: its scan is a regular file of whole KITTI records
/// (and, with labels, its label file has one label per point).
pub fn frame_complete(out: &Path, name: &str, labels: bool) -> bool {
    let len = |p: PathBuf| {
        std::fs::symlink_metadata(p)
            .ok()
            .filter(|m| m.is_file())
            .map(|m| m.len())
    };
    let Some(bin) = len(out.join(SCANS_DIR).join(format!("{name}.bin"))) else {
        return false;
    };
    if bin % 16 != 0 {
        return false;
    }
    !labels || len(out.join(LABELS_DIR).join(format!("{name}.label"))) == Some(bin / 4)
}

/// Refuses an output folder that is the input folder, lies inside it, or holds it (links and `..`
/// resolved): generated scans never go among the inputs.
pub fn check_not_inside(input: &Path, out: &Path) -> Result<()> {
    let input = std::fs::canonicalize(input).map_err(|source| Error::Io {
        action: "resolving the frames' folder",
        path: input.to_path_buf(),
        source,
    })?;
    let resolved = resolve(out)?;
    let refuse = |what: &str| {
        Err(Error::Output {
            path: out.to_path_buf(),
            reason: format!(
                "{what} the frames' folder {}: generated scans never go among the inputs; choose \
                 another --out",
                input.display()
            ),
        })
    };
    if resolved == input {
        return refuse("is");
    }
    if resolved.starts_with(&input) {
        return refuse("is inside");
    }
    if input.starts_with(&resolved) {
        return refuse("holds");
    }
    Ok(())
}

/// `path` made absolute with links resolved, as far as it exists; the rest, which does not exist
/// yet, appended with `.` and `..` applied.
fn resolve(path: &Path) -> Result<PathBuf> {
    let abs = std::path::absolute(path).map_err(|source| Error::Io {
        action: "resolving the output folder",
        path: path.to_path_buf(),
        source,
    })?;
    let mut existing = abs.as_path();
    let mut rest = Vec::new();
    while std::fs::symlink_metadata(existing).is_err() {
        match (existing.parent(), existing.file_name()) {
            (Some(p), Some(n)) => {
                rest.push(n.to_os_string());
                existing = p;
            }
            _ => break,
        }
    }
    let mut resolved = std::fs::canonicalize(existing).map_err(|source| Error::Io {
        action: "resolving the output folder",
        path: existing.to_path_buf(),
        source,
    })?;
    for part in rest.iter().rev() {
        match Path::new(part).components().next() {
            Some(Component::ParentDir) => {
                resolved.pop();
            }
            Some(Component::CurDir) | None => {}
            _ => resolved.push(part),
        }
    }
    Ok(resolved)
}
