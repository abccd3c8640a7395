//! The training config of `veila segment train` (`[data]`, `[model]`, `[train]`, `[output]`), as
//! serde structs any format can fill (the binary reads TOML).
//!
//! ```toml
//! [data]
//! # simulator frames with their ground truth (the `sim` feature) ...
//! scenes = "../scenes/train-v5.txt"   # a scene list (relative to this file)
//! scene_count = 200                   # (scene file, seed) pairs drawn from it, files interleaved
//! frames_per_scene = 4                # frames of each scene, spread over its frames
//! held_out_scenes = "../scenes/test-v5.txt"   # scored during training (optional)
//! held_out_count = 20
//! # ... or converted shards (`veila convert --label-map`):
//! # shards = "shards/train"           # folder with manifest.json
//! # label_map = "semantic-kitti.yaml" # the shards' label map (default: SemanticKITTI's built in)
//! # max_frames = 2000                 # the first N samples only
//!
//! [model]
//! preset = "bundled"                  # bundled (32 x 256), hdl64 (64 x 1024) or tiny (16 x 64)
//! sensor = "hdl64e"                   # the field of view of the grid (rows and columns: the preset's)
//!
//! [train]
//! steps = 2000
//! batch = 8
//! lr = 2e-3                           # peak; cosine decay to min_lr (default lr / 20)
//! warmup_steps = 100
//! weight_decay = 1e-4
//! seed = 0
//! class_weights = "inverse-frequency" # RangeNet++ / CENet: 1 / (f + 0.001); inverse-sqrt-frequency; uniform
//! augment = true                      # random turn about the vertical axis, left / right mirror
//! checkpoint_every = 250
//! eval_every = 500                    # held-out scores (with held_out_scenes)
//!
//! [output]
//! dir = "runs/segmenter"              # OUTPUT/checkpoints, OUTPUT/segmenter
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use veila_geom::SensorPreset;
use veila_nn::segmenter::SegmenterConfig;
use veila_nn::segmenter::knn::KnnConfig;

use super::frames::ClassWeighting;
use super::labels::LabelSpace;
use super::model::SegmenterModelConfig;
use super::train::SegTrainSettings;
use crate::error::{Error, Result};

/// The most scenes of `[data] scene_count` and `held_out_count`.
pub const MAX_SCENES: usize = 100_000;
/// The most frames of one scene, `[data] frames_per_scene`.
pub const MAX_FRAMES_PER_SCENE: u32 = 1000;
/// The most pixels of every training frame together (frames x rows x cols): the frames are held in
/// memory, 30 bytes a pixel, so about 64 GB.
pub const MAX_TRAINING_PIXELS: u64 = 1 << 31;

/// The config file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegTrainFile {
    /// `[data]`: simulator frames or shards.
    pub data: SegDataSection,
    /// `[model]`: the network and its sensor.
    #[serde(default)]
    pub model: SegModelSection,
    /// `[train]`: steps, batch, rates.
    #[serde(default)]
    pub train: SegTrainSection,
    /// `[output]`: where checkpoints and the model go.
    pub output: SegOutputSection,
}

/// `[data]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegDataSection {
    /// A simulator scene list.
    #[serde(default)]
    pub scenes: Option<PathBuf>,
    /// (scene file, seed) pairs drawn from `scenes`.
    #[serde(default = "d_scene_count")]
    pub scene_count: usize,
    /// Frames of each scene.
    #[serde(default = "d_frames_per_scene")]
    pub frames_per_scene: u32,
    /// A scene list of held-out frames, scored during training.
    #[serde(default)]
    pub held_out_scenes: Option<PathBuf>,
    /// (scene file, seed) pairs drawn from `held_out_scenes`, one frame each.
    #[serde(default = "d_held_out_count")]
    pub held_out_count: usize,
    /// A folder of converted shards (with `manifest.json`).
    #[serde(default)]
    pub shards: Option<PathBuf>,
    /// The shards' label map (`semantic-kitti.yaml`); default SemanticKITTI's, built in.
    #[serde(default)]
    pub label_map: Option<PathBuf>,
    /// Use only the first this many shard samples.
    #[serde(default)]
    pub max_frames: Option<usize>,
}

fn d_scene_count() -> usize {
    200
}
fn d_frames_per_scene() -> u32 {
    4
}
fn d_held_out_count() -> usize {
    20
}

/// A segmenter size.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SegPreset {
    /// [`SegmenterConfig::bundled`]: the bundled model's 32 x 256 grid.
    #[default]
    Bundled,
    /// [`SegmenterConfig::hdl64`]: SemanticKITTI's 64 x 1024.
    Hdl64,
    /// [`SegmenterConfig::tiny`]: 16 x 64, for tests.
    Tiny,
}

impl SegPreset {
    /// The network of the preset.
    pub fn network(self) -> SegmenterConfig {
        match self {
            SegPreset::Bundled => SegmenterConfig::bundled(),
            SegPreset::Hdl64 => SegmenterConfig::hdl64(),
            SegPreset::Tiny => SegmenterConfig::tiny(),
        }
    }
}

/// `[model]`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegModelSection {
    /// The network's size.
    #[serde(default)]
    pub preset: SegPreset,
    /// The sensor whose field of view the grid spans (rows and columns: the preset's).
    #[serde(default)]
    pub sensor: SensorPreset,
    /// Name written into the model (default: the preset's).
    #[serde(default)]
    pub name: Option<String>,
    /// The kNN clean-up (default RangeNet++'s).
    #[serde(default)]
    pub knn: KnnConfig,
}

/// `[train]` (every key optional: [`SegTrainSection::default`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegTrainSection {
    /// Updates.
    pub steps: u64,
    /// Frames per update.
    pub batch: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Final learning rate (default `lr / 20`).
    pub min_lr: Option<f64>,
    /// Warm-up updates.
    pub warmup_steps: u64,
    /// AdamW weight decay.
    pub weight_decay: f64,
    /// Seed.
    pub seed: u64,
    /// Class weights of the loss.
    pub class_weights: ClassWeighting,
    /// Random turns and mirrors.
    pub augment: bool,
    /// Checkpoint interval.
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    pub keep_checkpoints: Option<usize>,
    /// Held-out scoring interval.
    pub eval_every: Option<u64>,
}

impl Default for SegTrainSection {
    fn default() -> Self {
        SegTrainSection {
            steps: 2000,
            batch: 8,
            lr: 2e-3,
            min_lr: None,
            warmup_steps: 100,
            weight_decay: 1e-4,
            seed: 0,
            class_weights: ClassWeighting::default(),
            augment: true,
            checkpoint_every: 250,
            keep_checkpoints: Some(3),
            eval_every: None,
        }
    }
}

impl SegTrainSection {
    /// The trainer's settings.
    pub fn settings(&self) -> SegTrainSettings {
        SegTrainSettings {
            steps: self.steps,
            batch: self.batch,
            lr: self.lr,
            min_lr: self.min_lr.unwrap_or(self.lr / 20.0),
            warmup_steps: self.warmup_steps,
            weight_decay: self.weight_decay,
            seed: self.seed,
            augment: self.augment,
            checkpoint_every: self.checkpoint_every,
            keep_checkpoints: self.keep_checkpoints,
            eval_every: self.eval_every,
        }
    }
}

/// `[output]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegOutputSection {
    /// The run folder.
    pub dir: PathBuf,
}

fn bad(config_path: &Path, reason: impl Into<String>) -> Error {
    Error::Input {
        path: config_path.to_path_buf(),
        reason: reason.into(),
    }
}

impl SegTrainFile {
    /// Makes the relative paths relative to the config file `config_path` and checks every value
    /// (errors name the file).
    pub fn resolve_and_check(&mut self, config_path: &Path) -> Result<()> {
        let base = config_path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let resolve = |p: &Option<PathBuf>| {
            p.as_ref().map(|p| {
                if p.is_absolute() {
                    p.clone()
                } else {
                    base.join(p)
                }
            })
        };
        let d = &mut self.data;
        d.scenes = resolve(&d.scenes);
        d.held_out_scenes = resolve(&d.held_out_scenes);
        d.shards = resolve(&d.shards);
        d.label_map = resolve(&d.label_map);
        self.output.dir = resolve(&Some(self.output.dir.clone())).unwrap_or_default();
        let d = &self.data;
        match (&d.scenes, &d.shards) {
            (Some(_), Some(_)) | (None, None) => {
                return Err(bad(
                    config_path,
                    "[data] needs exactly one of `scenes` (simulator frames) and `shards`",
                ));
            }
            (Some(_), None) if d.label_map.is_some() || d.max_frames.is_some() => {
                return Err(bad(
                    config_path,
                    "[data] label_map and max_frames go with `shards`; simulator frames carry SemanticKITTI's classes",
                ));
            }
            (None, Some(_)) if d.held_out_scenes.is_some() => {
                return Err(bad(
                    config_path,
                    "[data] held_out_scenes goes with `scenes` (score shards with `veila segment eval`)",
                ));
            }
            _ => {}
        }
        if d.scene_count == 0 || d.scene_count > MAX_SCENES || d.held_out_count > MAX_SCENES {
            return Err(bad(
                config_path,
                format!("[data] scene_count and held_out_count must be in 1..={MAX_SCENES}"),
            ));
        }
        if d.frames_per_scene == 0 || d.frames_per_scene > MAX_FRAMES_PER_SCENE {
            return Err(bad(
                config_path,
                format!("[data] frames_per_scene must be in 1..={MAX_FRAMES_PER_SCENE}"),
            ));
        }
        if d.max_frames == Some(0) {
            return Err(bad(config_path, "[data] max_frames must be at least 1"));
        }
        let net = self.model.preset.network();
        let frames = match &d.scenes {
            Some(_) => d.scene_count as u64 * u64::from(d.frames_per_scene),
            None => d.max_frames.unwrap_or(0) as u64,
        };
        if frames.saturating_mul((net.rows * net.cols) as u64) > MAX_TRAINING_PIXELS {
            return Err(bad(
                config_path,
                format!(
                    "[data] {frames} frames of {} x {} pixels pass the {MAX_TRAINING_PIXELS} pixels held in memory",
                    net.rows, net.cols
                ),
            ));
        }
        self.train
            .settings()
            .validate()
            .map_err(|e| bad(config_path, format!("[train] {e}")))?;
        self.model
            .knn
            .validate()
            .map_err(|e| bad(config_path, format!("[model] {e}")))?;
        Ok(())
    }

    /// The config of the model this file trains, in the classes of `labels` (its provenance
    /// empty: the run fills it in): the preset's network on `[model] sensor`'s field of view.
    pub fn model_config(&self, labels: &LabelSpace) -> Result<SegmenterModelConfig> {
        let mut network = self.model.preset.network();
        network.num_classes = labels.num_classes();
        if let Some(n) = &self.model.name {
            network.name = n.clone();
        }
        let mut cfg =
            SegmenterModelConfig::new(network, &self.model.sensor.sensor(), labels.classes());
        cfg.knn = self.model.knn;
        Ok(cfg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<SegTrainFile> {
        let mut f: SegTrainFile = toml::from_str(text).map_err(|e| Error::Data(e.to_string()))?;
        f.resolve_and_check(Path::new("cfg/seg.toml"))?;
        Ok(f)
    }

    #[test]
    fn paths_resolve_against_the_file_and_one_data_source_is_required() {
        let f = parse("[data]\nscenes = \"s.txt\"\n[output]\ndir = \"run\"\n").unwrap();
        assert_eq!(f.data.scenes.as_deref(), Some(Path::new("cfg/s.txt")));
        assert_eq!(f.output.dir, Path::new("cfg/run"));
        let cfg = f.model_config(&LabelSpace::semantic_kitti()).unwrap();
        assert_eq!((cfg.sensor.rows, cfg.sensor.cols), (32, 256));
        assert_eq!(cfg.sensor.fov_down_deg, -25.0);
        assert_eq!(cfg.classes.len(), 20);
        for bad in [
            "[data]\n[output]\ndir = \"run\"\n",
            "[data]\nscenes = \"s\"\nshards = \"x\"\n[output]\ndir = \"r\"\n",
            "[data]\nscenes = \"s\"\nlabel_map = \"y\"\n[output]\ndir = \"r\"\n",
            "[data]\nshards = \"x\"\nheld_out_scenes = \"t\"\n[output]\ndir = \"r\"\n",
            "[data]\nscenes = \"s\"\nframes_per_scene = 0\n[output]\ndir = \"r\"\n",
            "[data]\nscenes = \"s\"\nscene_count = 100000\nframes_per_scene = 1000\n[output]\ndir = \"r\"\n",
            "[data]\nscenes = \"s\"\n[train]\nsteps = 0\nbatch = 8\nlr = 1e-3\nwarmup_steps = 1\nweight_decay = 0\nseed = 0\nclass_weights = \"uniform\"\naugment = true\ncheckpoint_every = 5\n[output]\ndir = \"r\"\n",
        ] {
            let e = parse(bad).expect_err(bad).to_string();
            assert!(e.contains("seg.toml"), "{e}");
        }
        assert!(parse("[data]\nscenes = \"s\"\nwhat = 1\n[output]\ndir = \"r\"\n").is_err());
    }

    #[test]
    fn the_example_configs_are_valid() {
        for name in ["segment.toml", "segment-sim.toml"] {
            let p = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../examples")
                .join(name);
            let text = std::fs::read_to_string(&p).unwrap();
            let mut f: SegTrainFile = toml::from_str(&text).unwrap();
            f.resolve_and_check(&p).unwrap();
        }
    }
}
