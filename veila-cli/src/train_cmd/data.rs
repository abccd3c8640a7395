//! A run's training data: the shards' manifest and their examples, loaded or streamed.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Result, bail};
use veila_data::shard::Manifest;
use veila_diffusion::app::BundleConfig;
use veila_diffusion::app::ExampleSource;
use veila_diffusion::app::train_config::TrainFile;
use veila_diffusion::app::train_data::{Prepared, ShardSource, load_prepared};

use crate::progress;

/// The training data: the shards' manifest and the examples, in memory or streamed.
pub(super) struct TrainData {
    pub(super) manifest: Manifest,
    pub(super) manifest_path: PathBuf,
    /// In memory (empty when streamed).
    pub(super) prepared: Vec<Prepared>,
    pub(super) stream: Option<Arc<dyn ExampleSource>>,
    /// Streamed: whether the first sample has semantic train ids.
    pub(super) first_has_labels: bool,
    pub(super) samples: usize,
}

/// Step 1 of a run: the shards' manifest, checked, and their examples loaded (or a stream of them).
pub(super) fn load_data(file: &TrainFile, cfg: &BundleConfig) -> Result<TrainData> {
    let data = &file.data;
    let shards = &data.shards;
    let manifest_path = shards.join("manifest.json");
    if !manifest_path.exists() {
        bail!(
            "{}: no manifest.json: [data] shards must be a folder written by `veila convert`",
            shards.display()
        );
    }
    let manifest = Manifest::read(&manifest_path)?;
    if manifest.count == 0 {
        bail!("{}: the manifest lists no samples", manifest_path.display());
    }
    if data.verify {
        manifest.verify(shards)?;
    }
    let want = data
        .max_frames
        .unwrap_or(manifest.count)
        .min(manifest.count);
    let needs_camera = cfg.needs_camera(file.model.encoders_from.is_some());
    let conditional = cfg.denoiser.conditioning.is_some();
    let mut prepared: Vec<Prepared> = Vec::new();
    let mut stream: Option<Arc<dyn ExampleSource>> = None;
    let mut first_has_labels = false;
    if data.stream {
        let source = ShardSource::new(
            shards,
            &manifest,
            want,
            cfg,
            needs_camera,
            conditional,
            data.unify_cameras,
        )?;
        first_has_labels = source.first_sample()?.train_ids.is_some();
        stream = Some(Arc::new(source));
    } else {
        let bar = progress::bar(want as u64, "loading");
        prepared = load_prepared(
            shards,
            &manifest,
            want,
            cfg,
            needs_camera,
            data.unify_cameras,
            || bar.inc(1),
        )?;
        bar.finish_and_clear();
    }
    let samples = stream.as_ref().map_or(prepared.len(), |s| s.len());
    println!(
        "train: {} samples from {}{} ({} sensor {}x{} -> model grid {}x{}), model `{}`",
        samples,
        shards.display(),
        if stream.is_some() {
            format!(", streamed (prefetch {})", data.prefetch)
        } else {
            String::new()
        },
        crate::out::untrusted(&manifest.dataset),
        manifest.sensor.rows,
        manifest.sensor.cols,
        cfg.denoiser.sensor.rows,
        cfg.denoiser.sensor.cols,
        crate::out::untrusted(&cfg.name)
    );
    Ok(TrainData {
        manifest,
        manifest_path,
        prepared,
        stream,
        first_has_labels,
        samples,
    })
}

/// The in-memory examples as the encoders' training takes them.
pub(super) struct EncoderMemory {
    pub(super) images: Vec<Vec<u8>>,
    pub(super) depths: Vec<Vec<f32>>,
    pub(super) cameras: Vec<veila_geom::PinholeCamera>,
    /// `None` unless every example has semantic train ids.
    pub(super) labels: Option<Vec<Vec<u32>>>,
}

impl EncoderMemory {
    pub(super) fn of(prepared: &[Prepared]) -> Self {
        Self {
            images: prepared.iter().map(|p| p.rgb.clone()).collect(),
            depths: prepared.iter().map(|p| p.depth_m.clone()).collect(),
            cameras: prepared.iter().map(|p| p.camera).collect(),
            labels: prepared.iter().map(|p| p.labels.clone()).collect(),
        }
    }
}
