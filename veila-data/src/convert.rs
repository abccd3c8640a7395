//! Dataset -> training shards: project every frame, write fixed-size shards atomically, skip shards
//! that are already complete (verified by checksum), split the work across independent workers.
//!
//! # Guarantees
//!
//! - **Bounded memory**: frames are read, projected and written one shard (`frames_per_shard`
//!   frames) at a time; nothing is kept across shards but small manifest entries.
//! - **Atomic**: every shard and its sidecar (`shard-NNNNN-TAG.safetensors.json`) are written to a
//!   temporary file and renamed; killing the process at any moment leaves complete files only.
//! - **Wholly old or wholly new**: a shard's name carries a tag of its settings and sources
//!   (`shard-00003-9f2c41d07a1b.safetensors`), so a conversion that changes a published dataset
//!   writes its shards beside the old ones and never touches a file `manifest.json` lists. The new
//!   manifest replaces the old one in one rename; only then are the shards no manifest lists
//!   removed (by the last worker still running). Until then the folder needs room for both.
//! - **Its own folder only**: a folder holding files no conversion wrote, or another dataset's
//!   manifest, is refused before anything is written.
//! - **Resumable**: a shard whose sidecar exists, was made with the same settings, from source files
//!   with the same contents (SHA-256 of every file of every frame, [`Dataset::source_files`]: a frame
//!   changed under the same id is noticed) and matches the shard file's size and SHA-256 is skipped;
//!   anything else is rebuilt. Temporary files of a killed run (`.veila-*.tmp`, which nobody holds locked any more) are removed
//!   when the next run starts.
//! - **Shardable**: worker `i` of `n` converts the shards `k` with `k % n == i`, so the same command
//!   runs as a Slurm array or a Kubernetes Indexed Job. Whichever worker finds every shard complete
//!   writes `manifest.json`.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use veila_geom::{
    BeamLayout, LidarSensor, ProjectionOptions, ProjectionStats, Projector, RowSource,
};

use crate::dataset::{Dataset, DatasetName, Frame};
use crate::semantic_kitti::LabelMap;
use crate::shard::{
    CameraMatrices, MANIFEST_FORMAT, Manifest, ShardEntry, ShardSample, ShardView, sha256_file,
    sha256_hex, write_shard,
};
use crate::{Error, Result};

/// Conversion settings.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// Output folder (created if missing).
    pub out_dir: PathBuf,
    /// The sensor to project with.
    pub sensor: LidarSensor,
    /// Frames per shard (memory use is about this many frames).
    pub frames_per_shard: usize,
    /// This worker's index, `0..worker_count`.
    pub worker_index: usize,
    /// Number of workers.
    pub worker_count: usize,
    /// Store the camera image in every sample.
    pub include_images: bool,
    /// Projection options.
    pub projection: ProjectionOptions,
}

impl ConvertOptions {
    /// Defaults: 32 frames per shard (about 130 MiB peak with KITTI images), one worker, images included.
    pub fn new(out_dir: impl Into<PathBuf>, sensor: LidarSensor) -> Self {
        ConvertOptions {
            out_dir: out_dir.into(),
            sensor,
            frames_per_shard: 32,
            worker_index: 0,
            worker_count: 1,
            include_images: true,
            projection: ProjectionOptions::default(),
        }
    }
}

/// What one conversion run did.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ConvertSummary {
    /// Shards in the whole dataset.
    pub total_shards: usize,
    /// Shards this worker is responsible for.
    pub assigned_shards: usize,
    /// Shards written in this run.
    pub written_shards: usize,
    /// Shards found complete and skipped.
    pub skipped_shards: usize,
    /// Frames converted in this run.
    pub frames: usize,
    /// Points dropped for non-finite values.
    pub dropped_non_finite: usize,
    /// Points read.
    pub points_in: usize,
    /// Pixels written.
    pub pixels_written: usize,
    /// Points that lost their pixel to a nearer point.
    pub occluded: usize,
    /// Points rejected by the projection (range or field of view).
    pub rejected: usize,
    /// True when this run wrote `manifest.json` (every shard was complete).
    pub manifest_written: bool,
}

/// Progress events, for a progress bar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Progress {
    /// The run starts: this many frames are assigned to this worker.
    Start {
        /// Frames assigned to this worker.
        frames: usize,
    },
    /// Frames finished (converted or found complete).
    Frames(usize),
}

/// Sidecar written next to every shard: its manifest entry and the settings fingerprint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Sidecar {
    fingerprint: String,
    /// SHA-256 of the shard's source files (ids, names and contents); empty in old sidecars.
    #[serde(default)]
    sources: String,
    entry: ShardEntry,
}

/// SHA-256 over the ids of `frames` and the names and contents of their source files.
fn sources_digest(dataset: &dyn Dataset, frames: std::ops::Range<usize>) -> Result<String> {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    for i in frames {
        h.update(dataset.frame_id(i).as_bytes());
        h.update([0]);
        for f in dataset.source_files(i)? {
            let name = f
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            h.update(name.as_bytes());
            h.update([0]);
            if f.is_file() {
                let (sha, bytes) = sha256_source(&f)?;
                h.update(sha.as_bytes());
                h.update(bytes.to_le_bytes());
            } else {
                h.update(b"absent");
            }
        }
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// The cap of a dataset's source file, by its name (scans, `.label`, calibrations, images), with
/// what it is in words: the readers' own limits, so a 100 GB sparse scan is refused from its
/// length before it is hashed.
fn source_cap(path: &Path) -> (u64, &'static str) {
    use crate::read_capped::*;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if name.ends_with(".pcd.bin") {
        (MAX_NUSCENES_SCAN_BYTES, "a nuScenes scan")
    } else if name.ends_with(".bin") {
        (MAX_KITTI_SCAN_BYTES, "a KITTI scan")
    } else if name.ends_with(".label") {
        (MAX_LABEL_FILE_BYTES, "a `.label` file")
    } else if name.ends_with(".txt") || name.ends_with(".json") {
        (MAX_CALIBRATION_BYTES, "a calibration file")
    } else {
        (MAX_CAMERA_IMAGE_BYTES, "a camera image")
    }
}

/// SHA-256 and length of the source file `path`, within its [`source_cap`] (checked before
/// anything is read; a FIFO or device is refused unopened).
fn sha256_source(path: &Path) -> Result<(String, u64)> {
    let (cap, kind) = source_cap(path);
    let file = crate::read_capped::open_capped_take(path, cap, kind)?;
    let (sha, total) = crate::shard::sha256_read(file, path)?;
    crate::read_capped::check_len(path, total, cap, kind)?;
    Ok((sha, total))
}

/// Project one frame into a training sample. Intensity is divided by `intensity_max`; labels become
/// train ids through `label_map`, when given.
pub fn frame_to_sample(
    frame: &Frame,
    projector: &Projector,
    intensity_max: f32,
    label_map: Option<&LabelMap>,
    include_image: bool,
) -> Result<(ShardSample, ProjectionStats)> {
    let pts = &frame.points;
    let uses_ring = matches!(
        projector.sensor().beams,
        BeamLayout::PerBeam {
            row_source: RowSource::Ring,
            ..
        }
    );
    let rings = if uses_ring {
        Some(pts.ring.as_deref().ok_or_else(|| Error::Invalid {
            what: "sensor".into(),
            message: format!(
                "frame {}: the sensor takes rows from rings but the scan has none",
                frame.id
            ),
        })?)
    } else {
        None
    };
    let scale = if intensity_max > 0.0 {
        1.0 / intensity_max
    } else {
        1.0
    };
    let intensity: Vec<f32> = pts.intensity.iter().map(|i| i * scale).collect();
    let (mut img, stats) = projector.project(&pts.xyz, Some(&intensity), rings)?;
    if let Some(l) = &pts.label {
        img.gather_labels(l)?;
    }
    let train_ids = match (&img.label, label_map) {
        (Some(raw), Some(map)) => Some(map.train_ids(raw)),
        _ => None,
    };
    // a shard keeps no source points: the sample is what reading the shard back gives
    img.point_index.fill(veila_geom::NO_POINT);
    let sample = ShardSample {
        id: frame.id.clone(),
        scan: img,
        train_ids,
        image: if include_image {
            frame.image.clone()
        } else {
            None
        },
        camera: frame.camera.as_ref().map(CameraMatrices::from_camera),
        extra_views: if include_image {
            frame
                .extra_views
                .iter()
                .filter_map(|v| {
                    v.image.as_ref().map(|image| ShardView {
                        image: image.clone(),
                        camera: CameraMatrices::from_camera(&v.camera),
                    })
                })
                .collect()
        } else {
            Vec::new()
        },
    };
    Ok((sample, stats))
}

fn fingerprint(dataset: &dyn Dataset, opts: &ConvertOptions) -> Result<String> {
    let desc = serde_json::json!({
        "format": MANIFEST_FORMAT,
        "dataset": dataset.name(),
        "frames": dataset.len(),
        "first": if dataset.is_empty() { String::new() } else { dataset.frame_id(0) },
        "last": if dataset.is_empty() { String::new() } else { dataset.frame_id(dataset.len() - 1) },
        "sensor": opts.sensor,
        "frames_per_shard": opts.frames_per_shard,
        "images": opts.include_images,
        "projection": format!("{:?}", opts.projection),
    });
    Ok(sha256_hex(desc.to_string().as_bytes())[..16].to_string())
}

/// File name of shard `k` made with settings fingerprint `fp` from sources with digest `sources`:
/// `shard-NNNNN-TAG.safetensors`, TAG the first 12 hex digits of their SHA-256. A shard that
/// would hold other samples gets another name, so it never overwrites a published one.
pub fn shard_file_name(k: usize, fp: &str, sources: &str) -> String {
    let tag = &sha256_hex(format!("{fp}\n{sources}").as_bytes())[..12];
    format!("shard-{k:05}-{tag}.safetensors")
}

/// The shard index of a shard or sidecar file name (`shard-NNNNN[-TAG].safetensors[.json]`).
fn shard_index(name: &str) -> Option<usize> {
    let stem = name
        .strip_suffix(".safetensors")
        .or_else(|| name.strip_suffix(".safetensors.json"))?;
    let rest = stem.strip_prefix("shard-")?;
    let digits = rest.split_once('-').map_or(rest, |(k, _)| k);
    let well_formed = digits.len() >= 5 && digits.bytes().all(|b| b.is_ascii_digit());
    digits.parse().ok().filter(|_| well_formed)
}

/// The frames of shard `k`: `frames_per_shard` of them, fewer in the last shard of `n`.
fn shard_frames(k: usize, frames_per_shard: usize, n: usize) -> std::ops::Range<usize> {
    k * frames_per_shard..((k + 1) * frames_per_shard).min(n)
}

fn sidecar_path(out: &Path, file: &str) -> PathBuf {
    out.join(format!("{file}.json"))
}

/// The sidecar's entry when shard file `file` is complete and was made with these settings (and
/// from these sources, when `sources` is given).
fn complete_entry(out: &Path, file: &str, fp: &str, sources: Option<&str>) -> Option<ShardEntry> {
    let text = crate::read_capped::read_metadata_string(
        &sidecar_path(out, file),
        crate::read_capped::MAX_JSON_METADATA_BYTES,
        "a shard sidecar",
    )
    .ok()?;
    let sc: Sidecar = serde_json::from_str(&text).ok()?;
    if sc.fingerprint != fp || sources.is_some_and(|s| s != sc.sources) || sc.entry.file != file {
        return None;
    }
    let (sha, bytes) = sha256_file(&out.join(&sc.entry.file)).ok()?;
    (sha == sc.entry.sha256 && bytes == sc.entry.bytes).then_some(sc.entry)
}

/// Refuses an output folder that holds files no conversion wrote, or the manifest of another
/// dataset: a conversion replaces only its own earlier output.
fn check_own_folder(out: &Path, dataset: &str) -> Result<()> {
    let refuse = |path: PathBuf, why: String| {
        Err(Error::io(
            path,
            std::io::Error::new(std::io::ErrorKind::AlreadyExists, why),
        ))
    };
    let rd = std::fs::read_dir(out).map_err(|e| Error::io(out, e))?;
    let mut names: Vec<String> = rd
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    if let Some(n) = names.iter().find(|n| {
        n.as_str() != "manifest.json"
            && !n.starts_with(crate::atomic::HIDDEN_PREFIX)
            && shard_index(n).is_none()
    }) {
        return refuse(
            out.join(n),
            "this file is not part of a converted dataset, and convert writes only into an \
             empty folder or its own earlier output: choose another output folder (nothing was \
             changed)"
                .into(),
        );
    }
    let manifest = out.join("manifest.json");
    if manifest.exists() {
        // the listing names the dataset; the shards are checked where they are reused
        let m = Manifest::read_listing(&manifest)?;
        if m.dataset != dataset {
            return refuse(
                manifest,
                format!(
                    "the folder holds a converted `{}` dataset and this conversion is `{dataset}`: \
                     choose another output folder (nothing was changed)",
                    m.dataset
                ),
            );
        }
    }
    Ok(())
}

/// Convert `dataset` into shards under `opts.out_dir` (see the module docs).
pub fn convert(
    dataset: &dyn Dataset,
    label_map: Option<&LabelMap>,
    opts: &ConvertOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<ConvertSummary> {
    if opts.frames_per_shard == 0 {
        return Err(Error::Invalid {
            what: "frames per shard".into(),
            message: "must be at least 1".into(),
        });
    }
    if opts.worker_count == 0 || opts.worker_index >= opts.worker_count {
        return Err(Error::Invalid {
            what: "shard selection".into(),
            message: format!(
                "index {} is not in 0..{}",
                opts.worker_index, opts.worker_count
            ),
        });
    }
    let projector = Projector::new(&opts.sensor, opts.projection)?;
    let out = &opts.out_dir;
    let created = !out.exists();
    if !created {
        check_own_folder(out, dataset.name())?;
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    // probe writability up front, so a read-only folder fails before any work
    crate::atomic::write_atomic(&out.join(".veila-write-probe"), b"")?;
    let _ = std::fs::remove_file(out.join(".veila-write-probe"));
    // temporary shards of a killed run (up to one shard each)
    crate::atomic::sweep_stale(out);

    let fp = fingerprint(dataset, opts)?;
    // workers of this conversion share the folder; one with other settings is refused
    let run = join_conversion(out, &fp)?;
    let result = convert_joined(dataset, label_map, opts, progress, &projector, &fp, &run);
    if result.is_err() && created {
        // a failed first conversion leaves its folder as empty as it found it
        drop(run);
        remove_if_only_locks(out);
    }
    result
}

/// Files a conversion keeps beside its shards to coordinate its workers ([`join_conversion`]).
const LOCK_FILES: [&str; 2] = [".veila-convert.guard", ".veila-convert.run"];

/// Removes the [`LOCK_FILES`] from `out` if it holds nothing else and no other conversion holds
/// them.
fn remove_if_only_locks(out: &Path) {
    let Ok(entries) = std::fs::read_dir(out) else {
        return;
    };
    let names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    if !names.iter().all(|n| LOCK_FILES.contains(&n.as_str())) {
        return;
    }
    let Ok(guard) = std::fs::File::open(out.join(LOCK_FILES[0])) else {
        return;
    };
    let Ok(run) = std::fs::File::open(out.join(LOCK_FILES[1])) else {
        return;
    };
    if guard.try_lock().is_ok() && run.try_lock().is_ok() {
        for name in LOCK_FILES {
            let _ = std::fs::remove_file(out.join(name));
        }
    }
}

/// [`convert`] once this process has joined the conversion into `opts.out_dir`.
fn convert_joined(
    dataset: &dyn Dataset,
    label_map: Option<&LabelMap>,
    opts: &ConvertOptions,
    progress: &(dyn Fn(Progress) + Sync),
    projector: &Projector,
    fp: &str,
    run: &std::fs::File,
) -> Result<ConvertSummary> {
    let out = &opts.out_dir;
    let n = dataset.len();
    let fps = opts.frames_per_shard;
    let total_shards = n.div_ceil(fps);
    let mine: Vec<usize> = (0..total_shards)
        .filter(|k| k % opts.worker_count == opts.worker_index)
        .collect();
    let my_frames: usize = mine.iter().map(|&k| shard_frames(k, fps, n).len()).sum();
    progress(Progress::Start { frames: my_frames });
    let mut summary = ConvertSummary {
        total_shards,
        assigned_shards: mine.len(),
        ..Default::default()
    };
    let intensity_max = dataset.intensity_max();

    // this worker's shards: their entries once verified or written
    let mut own: std::collections::BTreeMap<usize, ShardEntry> = Default::default();
    for &k in &mine {
        let range = shard_frames(k, fps, n);
        let count = range.len();
        let sources = sources_digest(dataset, range.clone())?;
        let file = shard_file_name(k, fp, &sources);
        if let Some(entry) = complete_entry(out, &file, fp, Some(&sources)) {
            own.insert(k, entry);
            summary.skipped_shards += 1;
            progress(Progress::Frames(count));
            continue;
        }
        let results: Vec<Result<(ShardSample, ProjectionStats, usize)>> = range
            .into_par_iter()
            .map(|i| {
                let frame = dataset.load(i)?;
                let (s, st) = frame_to_sample(
                    &frame,
                    projector,
                    intensity_max,
                    label_map,
                    opts.include_images,
                )?;
                progress(Progress::Frames(1));
                Ok((s, st, frame.dropped_non_finite))
            })
            .collect();
        let mut samples = Vec::with_capacity(count);
        for r in results {
            let (s, st, dropped) = r?;
            summary.frames += 1;
            summary.dropped_non_finite += dropped;
            summary.points_in += st.input;
            summary.pixels_written += st.written;
            summary.occluded += st.occluded;
            summary.rejected += st.rejected.total();
            samples.push(s);
        }
        // a new name: the published shards stay as they are until the new manifest replaces theirs
        let entry = write_shard(&out.join(&file), &opts.sensor, dataset.name(), &samples)?;
        drop(samples);
        let sc = Sidecar {
            fingerprint: fp.to_string(),
            sources,
            entry: entry.clone(),
        };
        let text = serde_json::to_string_pretty(&sc).map_err(|e| Error::Invalid {
            what: "sidecar".into(),
            message: e.to_string(),
        })?;
        crate::atomic::write_atomic(&sidecar_path(out, &file), text.as_bytes())?;
        own.insert(k, entry);
        summary.written_shards += 1;
    }

    // the manifest, once every shard (from any worker) is complete
    let mut files_of: std::collections::BTreeMap<usize, Vec<String>> = Default::default();
    for e in std::fs::read_dir(out)
        .map_err(|e| Error::io(out, e))?
        .flatten()
    {
        let name = e.file_name().to_string_lossy().into_owned();
        if let (Some(k), false) = (shard_index(&name), name.ends_with(".json")) {
            files_of.entry(k).or_default().push(name);
        }
    }
    let mut entries = Vec::with_capacity(total_shards);
    for k in 0..total_shards {
        // our own shards were verified or written above; re-hashing them would double the IO
        let entry = match own.remove(&k) {
            Some(e) => Some(e),
            None => other_workers_shard(dataset, out, k, fps, fp, files_of.get(&k))?,
        };
        match entry {
            Some(e) => entries.push(e),
            None => return Ok(summary),
        }
    }
    let manifest = Manifest {
        format: MANIFEST_FORMAT.into(),
        dataset: dataset.name().into(),
        sensor: opts.sensor.clone(),
        frames_per_shard: fps,
        count: n,
        shards: entries,
    };
    // one rename publishes the new dataset whole
    manifest.write(&out.join("manifest.json"))?;
    summary.manifest_written = true;
    // then the shards it does not list (an earlier conversion's, or a killed one's) go, by the
    // last worker of this conversion still running (one still writing holds the run lock shared)
    if run.try_lock().is_ok() {
        let listed: std::collections::BTreeSet<&str> =
            manifest.shards.iter().map(|e| e.file.as_str()).collect();
        let rd = std::fs::read_dir(out).map_err(|e| Error::io(out, e))?;
        for e in rd.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let shard = name.strip_suffix(".json").unwrap_or(&name);
            if shard_index(&name).is_some() && !listed.contains(shard) {
                std::fs::remove_file(e.path()).map_err(|err| Error::io(e.path(), err))?;
            }
        }
    }
    Ok(summary)
}

/// The entry of shard `k` of another worker, when one of its `files` is complete with these
/// settings. Several complete candidates (the sources changed under the same settings) are told
/// apart by hashing the sources.
fn other_workers_shard(
    dataset: &dyn Dataset,
    out: &Path,
    k: usize,
    fps: usize,
    fp: &str,
    files: Option<&Vec<String>>,
) -> Result<Option<ShardEntry>> {
    let Some(files) = files else {
        return Ok(None);
    };
    let mut complete: Vec<ShardEntry> = files
        .iter()
        .filter_map(|f| complete_entry(out, f, fp, None))
        .collect();
    if complete.len() <= 1 {
        return Ok(complete.pop());
    }
    let sources = sources_digest(dataset, shard_frames(k, fps, dataset.len()))?;
    let want = shard_file_name(k, fp, &sources);
    Ok(complete.into_iter().find(|e| e.file == want))
}

/// Join the conversion into `out` with settings fingerprint `fp`: the workers of one conversion
/// share the folder (a shared `flock` on `.veila-convert.run`, which holds their fingerprint);
/// a conversion with other settings while they run is refused. Held until dropped.
fn join_conversion(out: &Path, fp: &str) -> Result<std::fs::File> {
    let open = |name: &str| {
        let p = out.join(name);
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&p)
            .map_err(|e| Error::io(p, e))
    };
    // the guard makes looking at the run file and joining it one step
    let guard = open(".veila-convert.guard")?;
    guard
        .lock()
        .map_err(|e| Error::io(out.join(".veila-convert.guard"), e))?;
    let run_path = out.join(".veila-convert.run");
    let run = open(".veila-convert.run")?;
    if run.try_lock().is_ok() {
        // nobody converts into `out`: the run is ours to describe
        std::fs::write(&run_path, fp).map_err(|e| Error::io(&run_path, e))?;
        run.unlock().map_err(|e| Error::io(&run_path, e))?;
    } else {
        let theirs = crate::read_capped::read_metadata_string(
            &run_path,
            crate::read_capped::MAX_CONFIG_BYTES,
            "a conversion's run file",
        )
        .unwrap_or_default();
        if theirs != fp {
            return Err(Error::io(
                out,
                std::io::Error::new(
                    std::io::ErrorKind::WouldBlock,
                    "another veila process is writing this output (a conversion with other \
                     settings; wait for it to finish or choose another output)",
                ),
            ));
        }
    }
    run.lock_shared().map_err(|e| Error::io(&run_path, e))?;
    Ok(run)
}

/// Open a dataset for conversion with every SemanticKITTI sequence (and its label map, from
/// `semantic-kitti.yaml`) and nuScenes' `CAM_FRONT`: [`open_source`] of [`SourceSpec::new`].
pub fn open_dataset(
    name: DatasetName,
    root: &Path,
    load_images: bool,
) -> Result<(Box<dyn Dataset>, Option<LabelMap>)> {
    open_source(&SourceSpec {
        images: load_images,
        ..SourceSpec::new(name, root)
    })
}

/// Which dataset a conversion reads and how: what [`open_source`] opens.
#[derive(Debug, Clone)]
pub struct SourceSpec {
    /// The dataset.
    pub kind: DatasetName,
    /// Dataset root (KITTI: the folder with `training/`; SemanticKITTI: the folder with
    /// `sequences/`; nuScenes: the data root with `v1.0-*/` tables or `calib/*.json`).
    pub root: PathBuf,
    /// Read the camera images (they are stored in every sample).
    pub images: bool,
    /// SemanticKITTI: the label map file (default: the dataset's own lookup beside the root).
    pub label_map: Option<PathBuf>,
    /// SemanticKITTI: which sequences.
    pub sequences: crate::semantic_kitti::Sequences,
    /// nuScenes: the camera channels paired with each sweep; the first is each sample's camera,
    /// the others its further views.
    pub cameras: Vec<String>,
}

impl SourceSpec {
    /// A dataset of `kind` at `root` with images, every SemanticKITTI sequence and nuScenes'
    /// `CAM_FRONT`.
    pub fn new(kind: DatasetName, root: impl Into<PathBuf>) -> Self {
        SourceSpec {
            kind,
            root: root.into(),
            images: true,
            label_map: None,
            sequences: crate::semantic_kitti::Sequences::All,
            cameras: vec!["CAM_FRONT".into()],
        }
    }
}

/// Opens the dataset `spec` names, with its label map when it has one (SemanticKITTI).
pub fn open_source(spec: &SourceSpec) -> Result<(Box<dyn Dataset>, Option<LabelMap>)> {
    use crate::semantic_kitti::SemanticKittiDataset;
    match spec.kind {
        DatasetName::SemanticKitti => {
            let map = spec.label_map.as_deref().map(LabelMap::read).transpose()?;
            let sequences = spec.sequences.clone();
            let ds = match map {
                Some(m) => {
                    SemanticKittiDataset::open_with_label_map(&spec.root, sequences, Some(m))?
                }
                None => SemanticKittiDataset::open(&spec.root, sequences)?,
            }
            .with_images(spec.images);
            let map = ds.label_map().cloned();
            Ok((Box::new(ds), map))
        }
        DatasetName::Kitti => Ok((
            Box::new(crate::kitti::KittiObjectDataset::open(&spec.root)?.with_images(spec.images)),
            None,
        )),
        DatasetName::NuScenes => {
            let cams: Vec<&str> = spec.cameras.iter().map(String::as_str).collect();
            Ok((
                Box::new(
                    crate::nuscenes::NuScenesDataset::open_cameras(&spec.root, &cams)?
                        .with_images(spec.images),
                ),
                None,
            ))
        }
    }
}

/// This worker's `(index, count)` for [`ConvertOptions`] (and every other job split across workers
/// the same way, such as `veila generate --frames`): from `index` / `count` when given, else
/// from the environment (`env` looks a variable up): `SLURM_ARRAY_TASK_ID` (minus
/// `SLURM_ARRAY_TASK_MIN`) of `SLURM_ARRAY_TASK_COUNT` (a Slurm array job), or
/// `JOB_COMPLETION_INDEX` (a Kubernetes Indexed Job) with `count` or `VEILA_SHARD_COUNT` giving the
/// number of workers; else worker 0 of `count` (default 1).
pub fn worker_shard(
    index: Option<usize>,
    count: Option<usize>,
    env: &dyn Fn(&str) -> Option<String>,
) -> Result<(usize, usize)> {
    let invalid = |message: String| Error::Invalid {
        what: "worker".into(),
        message,
    };
    let env_usize = |name: &str| -> Result<Option<usize>> {
        match env(name) {
            Some(v) => v.trim().parse::<usize>().map(Some).map_err(|_| {
                invalid(format!(
                    "environment variable {name}={v:?} is not a non-negative integer"
                ))
            }),
            None => Ok(None),
        }
    };
    let check = |i: usize, n: usize, from: &str| -> Result<(usize, usize)> {
        if n == 0 || i >= n {
            return Err(invalid(format!(
                "shard index {i} is not in 0..{n} (from {from})"
            )));
        }
        Ok((i, n))
    };
    if let Some(i) = index {
        return check(i, count.unwrap_or(1), "--shard-index/--shard-count");
    }
    if let Some(id) = env_usize("SLURM_ARRAY_TASK_ID")? {
        let min = env_usize("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0);
        let n = match count {
            Some(n) => n,
            None => env_usize("SLURM_ARRAY_TASK_COUNT")?.ok_or_else(|| {
                invalid(
                    "SLURM_ARRAY_TASK_ID is set but SLURM_ARRAY_TASK_COUNT is not; pass --shard-count"
                        .into(),
                )
            })?,
        };
        let i = id
            .checked_sub(min)
            .ok_or_else(|| invalid("SLURM_ARRAY_TASK_ID is below SLURM_ARRAY_TASK_MIN".into()))?;
        return check(i, n, "SLURM_ARRAY_TASK_ID/SLURM_ARRAY_TASK_COUNT");
    }
    if let Some(i) = env_usize("JOB_COMPLETION_INDEX")? {
        let n = match count {
            Some(n) => n,
            None => env_usize("VEILA_SHARD_COUNT")?.ok_or_else(|| {
                invalid(
                    "JOB_COMPLETION_INDEX is set: pass --shard-count (or VEILA_SHARD_COUNT) with the job's completions"
                        .into(),
                )
            })?,
        };
        return check(i, n, "JOB_COMPLETION_INDEX");
    }
    check(0, count.unwrap_or(1), "--shard-count")
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
        assert_eq!(worker_shard(None, None, &env(&[])).unwrap(), (0, 1));
        assert_eq!(
            worker_shard(Some(2), Some(4), &env(&[("SLURM_ARRAY_TASK_ID", "0")])).unwrap(),
            (2, 4)
        );
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(worker_shard(None, None, &slurm).unwrap(), (3, 4));
        // arrays numbered 1..=4
        let slurm1 = env(&[
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]);
        assert_eq!(worker_shard(None, None, &slurm1).unwrap(), (3, 4));
        assert!(worker_shard(None, None, &env(&[("SLURM_ARRAY_TASK_ID", "3")])).is_err());
        let k8s = env(&[("JOB_COMPLETION_INDEX", "5")]);
        assert!(worker_shard(None, None, &k8s).is_err());
        assert_eq!(worker_shard(None, Some(8), &k8s).unwrap(), (5, 8));
        assert_eq!(
            worker_shard(
                None,
                None,
                &env(&[("JOB_COMPLETION_INDEX", "1"), ("VEILA_SHARD_COUNT", "2")])
            )
            .unwrap(),
            (1, 2)
        );
        assert!(worker_shard(None, Some(5), &k8s).is_err());
        assert!(
            worker_shard(
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
