//! The recipe of the bundled model (`models/default`) on simulator frames, as
//! `cargo xtask train-default` runs it: its options ([`SimRecipe`]) and what they give besides the
//! frames themselves — the bundle config, the [`RecipeSettings`], the key that ties a resumable
//! work folder to its run ([`SimRecipe::run_key`]), the folder name of its trained encoders
//! ([`SimRecipe::encoder_dir_name`]) and the provenance written into the bundle
//! ([`SimRecipe::provenance`]). The run itself, [`SimRecipe::train`] (`run.rs`), renders the
//! frames, trains through [`super::recipe::run_recipe`] and writes the bundle, with learning-curve
//! snapshots on request (`snapshots.rs`); the binary parses the flags and draws the progress.
//! `veila train`'s counterparts on converted shards are in [`super::train_config`].

use std::path::{Path, PathBuf};

use super::bundle::{BundleConfig, Method, NetworkKnobs, Variant};
use super::encoder_train::EncoderAugment;
use super::recipe::{RecipeOutcome, RecipeSettings};
use super::sim_examples::{DEFAULT_SCENES, RECIPE_SCENES, TrainImages};
use crate::error::{Error, Result, invalid};
use crate::trainer::{ActivationCheckpointing, Clock, Precision};

mod run;
mod snapshots;

pub use run::SimRun;

/// The options of one run of the recipe on simulator frames (`cargo xtask train-default`'s flags;
/// its defaults are the shipped model's recipe).
#[derive(Debug, Clone, PartialEq)]
pub struct SimRecipe {
    /// Model variant.
    pub variant: Variant,
    /// Generative method.
    pub method: Method,
    /// Simulated training frames.
    pub frames: usize,
    /// Scene list of the networks' training frames (relative to the workspace).
    pub scenes: PathBuf,
    /// Scene list of the encoders' training frames (`None`: [`DEFAULT_SCENES`]).
    pub encoder_scenes: Option<PathBuf>,
    /// Updates of each encoder.
    pub encoder_steps: usize,
    /// Denoiser updates.
    pub steps: u64,
    /// Mean-network updates (`None`: `steps`).
    pub mean_steps: Option<u64>,
    /// Batch of both networks.
    pub batch: usize,
    /// Peak learning rate of the networks.
    pub lr: f64,
    /// Seed of everything.
    pub seed: u64,
    /// Updates between checkpoints.
    pub checkpoint_every: u64,
    /// Reuse this bundle's encoders instead of training them.
    pub encoders_from: Option<PathBuf>,
    /// Start the networks from this bundle's weights where names and shapes match.
    pub init_from: Option<PathBuf>,
    /// How the training images are rendered.
    pub images: TrainImages,
    /// The share of the frames drawn in the `images` style (`None`: all).
    pub randomize_share: Option<f32>,
    /// The share of drawn facades from the whole colour wheel (`None`: none).
    pub wide_facades: Option<f32>,
    /// Augment the encoders' training images.
    pub augment_encoders: bool,
    /// The flat-ground prior as an input channel of the small-CNN encoders.
    pub ground_prior: bool,
    /// The depth encoder's depth reading as one more feature channel.
    pub depth_features: bool,
    /// Train the depth encoder to read the sky as its far limit.
    pub sky_depth: bool,
    /// Width of the networks' first level (`None`: the CPU default's 16 channels).
    pub base_channels: Option<usize>,
    /// Residual blocks per U-Net level (`None`: the CPU default's 1).
    pub res_blocks: Option<usize>,
    /// Width multipliers of the U-Net levels (`None`: the CPU default's 1, 2, 2, 4).
    pub channel_mults: Option<Vec<usize>>,
    /// Octaves of the ray-direction Fourier features (`None`: the CPU default's 4).
    pub ray_freqs: Option<usize>,
    /// EMA decay of the shipped weights (the shipped recipe's: 0.995).
    pub ema_decay: f64,
    /// How the noise levels weigh in the loss (`None`: the CPU default's min-SNR-5).
    pub loss_weighting: Option<crate::prediction::LossWeighting>,
    /// The share of training draws at the clean levels
    /// ([`TrainLevels::clean_share`](crate::TrainLevels::clean_share); `None`: uniform time).
    pub clean_share: Option<f64>,
    /// The power of the range weight in the denoiser's loss
    /// ([`BundleConfig::range_weight`]; `None`: every pixel alike).
    pub range_weight: Option<f64>,
}

/// The EMA decay of the shipped recipe.
pub const RECIPE_EMA_DECAY: f64 = 0.995;

impl SimRecipe {
    /// The shipped model's recipe (`cargo xtask train-default` without flags).
    pub fn shipped() -> SimRecipe {
        SimRecipe {
            variant: Variant::Full,
            method: Method::Residual,
            frames: 960,
            scenes: PathBuf::from(RECIPE_SCENES),
            encoder_scenes: None,
            encoder_steps: 4000,
            steps: 12500,
            mean_steps: None,
            batch: 8,
            lr: 1e-3,
            seed: 0,
            checkpoint_every: 50,
            encoders_from: None,
            init_from: None,
            images: TrainImages::Materials,
            randomize_share: None,
            wide_facades: None,
            augment_encoders: false,
            ground_prior: false,
            depth_features: false,
            sky_depth: false,
            base_channels: None,
            res_blocks: None,
            channel_mults: None,
            ray_freqs: None,
            ema_decay: RECIPE_EMA_DECAY,
            loss_weighting: None,
            clean_share: None,
            range_weight: None,
        }
    }

    /// The network knobs of these options (the CPU default's where they are `None`).
    pub fn network_knobs(&self) -> NetworkKnobs {
        NetworkKnobs {
            base_channels: self.base_channels,
            channel_mults: self.channel_mults.clone(),
            res_blocks: self.res_blocks,
            ray_freqs: self.ray_freqs,
            loss_weighting: self.loss_weighting,
            clean_share: self.clean_share,
            range_weight: self.range_weight,
        }
    }

    /// The bundle config the run trains: the variant's CPU default with the method, the network
    /// knobs, the ground prior and the depth features switched as asked.
    pub fn bundle_config(&self) -> Result<BundleConfig> {
        let mut cfg = BundleConfig::cpu_default(self.variant).with_method(self.method);
        cfg.set_network(&self.network_knobs())?;
        if self.ground_prior {
            cfg.set_ground_prior(Some(veila_nn::encoders::ground::GroundPrior::default()));
        }
        if self.depth_features {
            cfg.set_depth_features(true)?;
        }
        Ok(cfg)
    }

    /// The list the encoders train on when it is not `scenes` (`None`: the same frames as the
    /// networks, or encoders reused from `encoders_from`).
    pub fn encoder_list(&self) -> Option<PathBuf> {
        if self.encoders_from.is_some() {
            return None;
        }
        let list = self
            .encoder_scenes
            .clone()
            .unwrap_or_else(|| PathBuf::from(DEFAULT_SCENES));
        (list != self.scenes).then_some(list)
    }

    /// The recipe's settings: these options, the encoders' batch and learning rate fixed.
    pub fn settings(&self) -> RecipeSettings {
        RecipeSettings {
            seed: self.seed,
            steps: self.steps,
            mean_steps: self.mean_steps,
            batch: self.batch,
            lr: self.lr,
            ema_decay: self.ema_decay,
            cond_drop_prob: 0.1,
            checkpoint_every: self.checkpoint_every,
            keep_checkpoints: 2,
            encoder_steps: self.encoder_steps,
            encoder_batch: 8,
            encoder_lr: 2e-3,
            grad_accum_steps: 1,
            encoder_augment: self.augment_encoders.then(EncoderAugment::default),
            precision: Precision::F32,
            activation_checkpointing: ActivationCheckpointing::None,
        }
    }

    /// The depth target of the sky pixels under `sky_depth`: the far limit of the small-CNN depth
    /// encoder's depth head (`None` without it; an error for a variant without that head).
    pub fn sky_target_m(&self, cfg: &BundleConfig) -> Result<Option<f32>> {
        if !self.sky_depth {
            return Ok(None);
        }
        match cfg
            .depth_encoder
            .as_ref()
            .and_then(|e| e.small_cnn_config())
            .filter(|c| c.depth_head)
        {
            Some(c) => Ok(Some(c.max_depth_m)),
            None => Err(invalid(
                "sky_depth",
                "it trains the small-CNN depth encoder's depth head, and this variant has none",
            )),
        }
    }

    /// The key of a work folder: it resumes only the run it was made for (same model, diffusion
    /// and training settings, same data). `frames`: the networks' training frames.
    pub fn run_key(
        &self,
        cfg: &BundleConfig,
        settings: &RecipeSettings,
        frames: usize,
    ) -> serde_json::Value {
        let (tc, mean_tc) = settings.train_configs(cfg.denoiser.conditioning.is_some());
        let mut run_key = serde_json::json!({
            "denoiser": cfg.denoiser,
            "diffusion": cfg.diffusion,
            "residual": cfg.residual.as_ref().map(|r| &r.mean_net),
            "encoding": cfg.encoding,
            "train": tc,
            "mean_train": cfg.residual.as_ref().map(|_| &mean_tc),
            "frames": frames,
            "batch": self.batch,
            "encoders_from": self.encoders_from,
            "init_from": self.init_from,
            "randomize": self.images == TrainImages::Randomized,
            "encoder_augment": settings.encoder_augment,
        });
        // (only when on: the work folders of earlier runs keep their key)
        let flags = [
            ("ground_prior", self.ground_prior),
            ("depth_features", self.depth_features),
            ("sky_depth", self.sky_depth),
        ];
        for (key, on) in flags {
            if on {
                run_key[key] = serde_json::Value::Bool(true);
            }
        }
        if let Some(p) = self.randomize_share {
            run_key["randomize_share"] = serde_json::json!(p);
        }
        if let Some(p) = self.wide_facades {
            run_key["wide_facade_share"] = serde_json::json!(p);
        }
        let style = self.images.style(None);
        if style.randomize_lighting {
            run_key["randomize_lighting"] = serde_json::Value::Bool(true);
        }
        if style.randomize_materials {
            run_key["randomize_materials"] = serde_json::Value::Bool(true);
        }
        if self.scenes != Path::new(DEFAULT_SCENES) {
            run_key["scenes"] = serde_json::json!(self.scenes);
        }
        if let Some(list) = &self.encoder_list() {
            run_key["encoder_scenes"] = serde_json::json!(list);
        }
        run_key
    }

    /// The folder name, inside the work folder, of the encoders trained for `frames` frames: a
    /// resumed run reuses them (their training is deterministic: the same seed gives the same
    /// weights).
    pub fn encoder_dir_name(&self, frames: usize) -> String {
        let on = |flag: bool, tag: &'static str| if flag { tag } else { "" };
        format!(
            "encoders-seed{}-steps{}-frames{frames}{}{}{}{}{}{}",
            self.seed,
            self.encoder_steps,
            match self.images {
                TrainImages::Stock => "",
                TrainImages::Lighting => "-lit",
                TrainImages::Materials => "-materials",
                TrainImages::Appearance => "-lit-materials",
                TrainImages::Randomized => "-randomized",
            },
            self.randomize_share
                .map(|p| format!("{:.0}", 100.0 * p))
                .unwrap_or_default(),
            self.wide_facades
                .map(|p| format!("-wide{:.0}", 100.0 * p))
                .unwrap_or_default(),
            on(self.augment_encoders, "-augmented"),
            on(self.ground_prior, "-ground"),
            on(self.sky_depth, "-sky"),
        )
    }

    /// The provenance of the finished bundle (`cfg` trained on `frames` frames on `device` by
    /// `outcome`, the run's seconds: simulating the frames and fitting the networks).
    pub fn provenance(
        &self,
        cfg: &BundleConfig,
        outcome: &RecipeOutcome,
        device: &str,
        frames: usize,
        sim_secs: f64,
        den_secs: f64,
    ) -> Result<serde_json::Value> {
        let settings = self.settings();
        let (tc, _) = settings.train_configs(cfg.denoiser.conditioning.is_some());
        let mean_steps = settings.mean_steps();
        let den = outcome.fit.denoiser.as_ref().ok_or_else(|| {
            Error::Data("the mean network's run stopped early: no denoiser to record".into())
        })?;
        let (summary, enc_secs, seconds) =
            (&den.summary, outcome.encoder_seconds, outcome.fit.seconds);
        // the runs' own clocks, summed over every resumed session (this process's seconds below)
        let clock = |c: Clock| serde_json::json!({ "seconds": c.seconds.round(), "from_step": c.from_step });
        let train_clock = serde_json::json!({
            "mean": outcome.fit.mean.as_ref().map(|m| clock(m.summary.clock)),
            "denoiser": clock(summary.clock),
        });
        let encoder_list = self.encoder_list();
        Ok(serde_json::json!({
            "trained_by": "cargo xtask train-default",
            "device": device,
            "variant": self.variant.name(),
            "method": cfg.method().name(),
            "seed": self.seed,
            "train_split": self.scenes.display().to_string(),
            "encoder_split": if self.encoders_from.is_some() {
                None
            } else {
                Some(encoder_list.as_deref().unwrap_or(&self.scenes).display().to_string())
            },
            "frames": frames,
            "train_images": {
                "appearance": self.images.provenance_name(),
                "sensor_randomized": self.images == TrainImages::Randomized,
                "randomized_share": self.randomize_share,
                "wide_facade_share": self.wide_facades,
                "encoder_augment": self.augment_encoders,
                "sky_depth_m": self.sky_target_m(cfg)?,
            },
            "encoder_steps": if self.encoders_from.is_some() { 0 } else { self.encoder_steps },
            "encoders_from": self.encoders_from.as_ref().map(|p| p.display().to_string()),
            "denoiser_steps": self.steps,
            "mean_steps": cfg.residual.as_ref().map(|_| mean_steps),
            "training_samples": (self.steps + cfg.residual.as_ref().map_or(0, |_| mean_steps)) * self.batch as u64,
            "batch": self.batch,
            "lr": self.lr,
            "ema_decay": tc.ema_decay,
            "cond_drop_prob": tc.cond_drop_prob,
            "final_mean_loss": summary.mean_loss,
            "train_wall_seconds": train_clock,
            "seconds": {
                "simulation": sim_secs.round(),
                "encoders": enc_secs.round(),
                "mean": seconds[0].round(),
                "denoiser": seconds[1].round(),
                "total": (sim_secs + enc_secs + den_secs).round(),
            },
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::app::progress::Lines;

    /// A run on the CPU that simulates its own frames and writes no snapshots.
    fn cpu_run<'a>(root: &'a Path, work: &'a Path, out: &'a Path) -> SimRun<'a> {
        SimRun {
            root,
            out,
            work,
            device: &candle_core::Device::Cpu,
            device_name: "cpu",
            snapshot_every: None,
            frames: None,
        }
    }

    #[test]
    fn a_work_folder_of_another_run_is_refused_before_any_frame_is_simulated() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let tmp = tempfile::tempdir().unwrap();
        let work = tmp.path().join("work");
        std::fs::create_dir(&work).unwrap();
        std::fs::write(work.join(crate::trainer::RUN_RECORD_FILE), "{}").unwrap();
        let recipe = SimRecipe {
            variant: Variant::Unconditional,
            frames: 3,
            steps: 2,
            ..SimRecipe::shipped()
        };
        let lines = Lines::default();
        let out = tmp.path().join("bundle");
        let run = cpu_run(&root, &work, &out);
        let e = recipe.train(&run, &lines).unwrap_err().to_string();
        assert!(e.contains("other settings"), "{e}");
        let told = lines.0.into_inner().unwrap();
        assert!(
            told.iter().all(|l| !l.contains("simulated")),
            "frames were simulated first: {told:?}"
        );
        assert!(!out.exists());
        assert_eq!(
            std::fs::read_to_string(work.join(crate::trainer::RUN_RECORD_FILE)).unwrap(),
            "{}",
            "the other run's record is left as it was"
        );
    }

    #[test]
    fn a_model_that_never_looks_at_the_camera_trains_on_the_scans_alone() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let tmp = tempfile::tempdir().unwrap();
        // the encoders' own list differs from the networks' (the shipped recipe's), yet an
        // unconditional model has no encoders: no frames of theirs are simulated
        let recipe = SimRecipe {
            variant: Variant::Unconditional,
            frames: 3,
            steps: 2,
            batch: 2,
            checkpoint_every: 2,
            ..SimRecipe::shipped()
        };
        assert!(recipe.encoder_list().is_some());
        let lines = Lines::default();
        let (work, out) = (tmp.path().join("work"), tmp.path().join("bundle"));
        let run = cpu_run(&root, &work, &out);
        let cfg = recipe.train(&run, &lines).unwrap();
        assert!(!cfg.needs_camera(false));
        let told = lines.0.into_inner().unwrap();
        let simulated: Vec<&String> = told.iter().filter(|l| l.contains("simulated")).collect();
        assert_eq!(simulated.len(), 1, "{told:?}");
        assert!(
            simulated[0].contains("simulated 3 frames") && simulated[0].contains("scans alone"),
            "{told:?}"
        );
        assert!(out.join("bundle.json").exists());
        // a conditional model needs the camera, even with its encoders reused
        let full = BundleConfig::cpu_default(Variant::Full);
        assert!(full.needs_camera(false) && full.needs_camera(true));
    }

    #[test]
    fn the_sky_target_is_the_depth_encoders_far_limit_where_there_is_one() {
        let full = BundleConfig::cpu_default(Variant::Full);
        let far = full
            .depth_encoder
            .as_ref()
            .and_then(|e| e.small_cnn_config())
            .map(|c| c.max_depth_m)
            .unwrap();
        let sky = SimRecipe {
            sky_depth: true,
            ..SimRecipe::shipped()
        };
        assert_eq!(sky.sky_target_m(&full).unwrap(), Some(far));
        assert_eq!(SimRecipe::shipped().sky_target_m(&full).unwrap(), None);
        // without a depth encoder the flag has nothing to train, and says so
        let blind = BundleConfig::cpu_default(Variant::Unconditional);
        assert_eq!(SimRecipe::shipped().sky_target_m(&blind).unwrap(), None);
        let e = sky.sky_target_m(&blind).unwrap_err().to_string();
        assert!(e.contains("sky_depth"), "{e}");
    }

    #[test]
    fn the_recipe_trains_its_encoders_on_the_streets_and_its_networks_with_t_junctions() {
        let with = |scenes: &str, encoder_scenes: Option<&str>| SimRecipe {
            scenes: scenes.into(),
            encoder_scenes: encoder_scenes.map(PathBuf::from),
            ..SimRecipe::shipped()
        };
        // the shipped recipe: networks on train-v5, encoders on the street list
        assert_eq!(
            SimRecipe::shipped().encoder_list(),
            Some(PathBuf::from("scenes/train.txt"))
        );
        // one list for everything: no second set of frames
        let v5 = "scenes/train-v5.txt";
        assert_eq!(with(v5, Some(v5)).encoder_list(), None);
        assert_eq!(with("scenes/train.txt", None).encoder_list(), None);
        let v3 = with("scenes/train-v4.txt", Some("scenes/train-v3.txt"));
        assert_eq!(
            v3.encoder_list(),
            Some(PathBuf::from("scenes/train-v3.txt"))
        );
        // reused encoders train on nothing
        let reused = SimRecipe {
            encoders_from: Some("models/default".into()),
            ..SimRecipe::shipped()
        };
        assert_eq!(reused.encoder_list(), None);
    }

    #[test]
    fn the_run_key_and_the_encoder_folder_name_only_the_switches_that_are_on() {
        let r = SimRecipe::shipped();
        let cfg = r.bundle_config().unwrap();
        let key = r.run_key(&cfg, &r.settings(), 960);
        assert_eq!(key["frames"], 960);
        assert_eq!(key["randomize_materials"], true);
        assert_eq!(key["scenes"], "scenes/train-v5.txt");
        assert_eq!(key["encoder_scenes"], "scenes/train.txt");
        for off in [
            "ground_prior",
            "sky_depth",
            "randomize_share",
            "randomize_lighting",
        ] {
            assert!(key.get(off).is_none(), "{off}");
        }
        assert_eq!(
            r.encoder_dir_name(960),
            "encoders-seed0-steps4000-frames960-materials"
        );
        let all = SimRecipe {
            images: TrainImages::Randomized,
            randomize_share: Some(0.5),
            wide_facades: Some(0.25),
            augment_encoders: true,
            ground_prior: true,
            sky_depth: true,
            ..SimRecipe::shipped()
        };
        assert_eq!(
            all.encoder_dir_name(96),
            "encoders-seed0-steps4000-frames96-randomized50-wide25-augmented-ground-sky"
        );
        let key = all.run_key(&all.bundle_config().unwrap(), &all.settings(), 96);
        assert_eq!(
            (&key["ground_prior"], &key["sky_depth"]),
            (&true.into(), &true.into())
        );
        assert_eq!(key["randomize"], true);
    }
}
