//! `cargo xtask train-default`: trains the bundled model (`models/default`) from a fixed seed on
//! the simulator's train split with the recipe `veila train` runs too
//! (`veila_diffusion::app::recipe`): the two small CNN encoders first (semantics, depth), then the
//! mean network and the denoiser on their frozen features. Resumable: checkpoints and the trained
//! encoders go to `--work` and a rerun picks up the newest ones.

use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use veila_diffusion::app::bundle::{Bundle, BundleConfig, Method, Variant};
use veila_diffusion::app::sim_recipe::SimRecipe;
use veila_diffusion::app::{
    EncoderData, EncoderEvent, EncoderSource, RecipeInput, TrainExample, run_recipe,
};
use veila_diffusion::{LossAverage, StepStats, TrainObserver};

use crate::device::DeviceArg;
use crate::progress::workspace_root;
use veila_diffusion::app::sim_examples::{self, SimExample, TrainImages};

/// Arguments of `cargo xtask train-default`.
#[derive(Debug, Args, Clone)]
pub struct TrainDefaultArgs {
    /// Output bundle folder.
    #[arg(long, default_value = "models/default")]
    pub out: PathBuf,
    /// Model variant (the ablations of the paper; `full` is the bundled model).
    #[arg(long, default_value = "full")]
    pub variant: Variant,
    /// Generative method: eps, v, residual, flow or regression.
    #[arg(long, default_value = "residual")]
    pub method: Method,
    /// Training steps of the mean network (residual method; default: --steps).
    #[arg(long)]
    pub mean_steps: Option<u64>,
    /// Simulated training frames (from --scenes). The defaults are the recipe of the shipped
    /// `models/default`.
    #[arg(long, default_value_t = 960)]
    pub frames: usize,
    /// Scene list the mean network's and the denoiser's training frames are drawn from (relative to
    /// the workspace): `scenes/train-v5.txt` (the shipped recipe: the streets plus T junctions,
    /// whose view ahead ends at a row of facades), `scenes/train.txt` (streets and a junction, the
    /// recipe until 2026-11-26), `scenes/train-v3.txt` (also open roads, suburbs, curved roads and
    /// a rig drawn per seed), `scenes/train-v4.txt` (the streets and a road between woodland
    /// edges: tree lines, a rig drawn per seed).
    #[arg(long, default_value = sim_examples::RECIPE_SCENES)]
    pub scenes: PathBuf,
    /// Scene list the encoders' training frames are drawn from (as many frames as --frames)
    /// [default: `scenes/train.txt`, the shipped recipe's: its encoders were trained on the
    /// streets and its networks on the streets plus T junctions]. Pass the --scenes list to train
    /// everything on one list.
    #[arg(long)]
    pub encoder_scenes: Option<PathBuf>,
    /// Training steps of each encoder (4,000 since 2026-11-25: on 120 test frames 150 gave a
    /// front range MAE of 1.41 m, 1,500 gave 1.30 m, 4,000 gives 1.26 m).
    #[arg(long, default_value_t = 4000)]
    pub encoder_steps: usize,
    /// Denoiser training steps (the mean network takes as many unless --mean-steps: 2 x 12,500
    /// updates of batch 8 are the 200,000 training samples of the shipped model; 6,250 gave a
    /// front range MAE of 1.26 m on 120 test frames, 12,500 gives 1.19 m).
    #[arg(long, default_value_t = 12500)]
    pub steps: u64,
    /// Batch size of both networks.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Peak learning rate of the denoiser.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Seed of everything.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Updates between checkpoints (both networks).
    #[arg(long, default_value_t = 50)]
    pub checkpoint_every: u64,
    /// Folder for resumable checkpoints (default: target/train-default/VARIANT-METHOD).
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Reuse the encoders of this bundle instead of training them (bench-report uses the default
    /// model's encoders for every ablation).
    #[arg(long)]
    pub encoders_from: Option<PathBuf>,
    /// Start the denoiser from this bundle's denoiser weights wherever names and shapes match
    /// (bench-report's fine-tuned ablations); the rest keeps its seeded initialisation.
    #[arg(long)]
    pub init_from: Option<PathBuf>,
    /// How the training frames' camera images are rendered (issue 18): `stock`, `lighting` (sun
    /// and sky drawn per scene), `materials` (palettes and textures drawn per scene; the shipped
    /// recipe: on the real KITTI frames it beats the image-blind baselines where the stock images
    /// did not), `appearance` (both) or `randomized` (both and the sensor model). Scans, depth and
    /// labels are the same in every style.
    #[arg(long, default_value = "materials", value_parser = parse_images)]
    pub images: TrainImages,
    /// The share of the training frames, within (0, 1], whose images are drawn in the `--images`
    /// style (chosen per frame from its seed); the rest keep the stock images [default: 1, all].
    #[arg(long)]
    pub randomize_share: Option<f32>,
    /// The share of each drawn scene's facade looks, within (0, 1], drawn from the whole colour
    /// wheel (saturated paint and glazed mosaic tiles) instead of the plaster, brick and cladding
    /// palettes; needs an `--images` style that draws materials [default: none].
    #[arg(long)]
    pub wide_facades: Option<f32>,
    /// Augment the encoders' training images (crop-and-zoom, colour, blur, noise, JPEG).
    #[arg(long)]
    pub augment_encoders: bool,
    /// Give the small-CNN encoders the flat-ground prior as a fourth input channel (issue 18:
    /// the flat ground's depth from each image's calibration; stored in `bundle.json`).
    #[arg(long)]
    pub ground_prior: bool,
    /// Append the depth encoder's own depth reading to its feature maps as one more channel, so
    /// the networks see the head's metric depth directly (issue 18; the encoder's weights are the
    /// same either way; stored in `bundle.json`).
    #[arg(long)]
    pub depth_features: bool,
    /// Train the depth encoder to read the sky as far: the simulator's sky pixels (no surface,
    /// depth 0) get the encoder's far limit (`max_depth_m`, 80 m) as their target instead of
    /// none, so its features tell open sky from a facade (issue 18; stored in the provenance).
    #[arg(long)]
    pub sky_depth: bool,
    /// Where the networks train: `cpu` (the shipped recipe's), `cuda` (GPU 0) or `cuda:N`; a GPU
    /// needs the `cuda` feature (`cargo xtask build-cuda --xtask`). A run may resume on another
    /// device; the bundle records the device of the run that finished it.
    #[arg(long, default_value = "cpu", value_parser = crate::device::parse_device)]
    pub device: DeviceArg,
    /// Width of the networks' first U-Net level [default: the shipped recipe's 16].
    #[arg(long, value_parser = clap::value_parser!(u64).range(4..=512))]
    pub base_channels: Option<u64>,
    /// Residual blocks per U-Net level [default: the shipped recipe's 1].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=8))]
    pub res_blocks: Option<u64>,
    /// Width multipliers of the U-Net levels, comma-separated [default: the shipped recipe's
    /// 1,2,2,4]; as many levels as given.
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u64).range(1..=64))]
    pub channel_mults: Option<Vec<u64>>,
    /// Loss weighting over noise levels of the diffusion methods: `min-snr` (min-SNR-5, the
    /// shipped recipe's) or `uniform` (every level alike in the prediction's MSE: for
    /// v-prediction the x₀-space weight SNR + 1).
    #[arg(long, default_value = "min-snr", value_parser = ["min-snr", "uniform"])]
    pub loss_weighting: String,
    /// EMA decay of the shipped weights, in [0, 1).
    #[arg(long, default_value_t = veila_diffusion::app::sim_recipe::RECIPE_EMA_DECAY)]
    pub ema_decay: f64,
    /// Every this many denoiser updates (a multiple of --checkpoint-every), also write a model
    /// bundle of the EMA weights to WORK/snapshots/step-NNNNNNNNNN, for learning curves
    /// (`cargo xtask bench-realism --model`). Not for the residual method, whose mean network
    /// trains first.
    #[arg(long)]
    pub snapshot_every: Option<u64>,
}

struct Progress {
    bar: indicatif::ProgressBar,
    loss: LossAverage,
    /// Bundles of the EMA weights written along the run (the denoiser's stage only).
    snapshots: Option<Snapshots>,
}

/// What a learning-curve snapshot needs besides the checkpoint's EMA weights.
#[derive(Clone)]
struct Snapshots {
    every: u64,
    dir: PathBuf,
    config: BundleConfig,
    /// The encoders' weights by bundle file (none for an unconditional model).
    encoders: Vec<(
        &'static str,
        std::collections::HashMap<String, candle_core::Tensor>,
    )>,
}

impl Snapshots {
    fn write(&self, step: u64, checkpoint: &std::path::Path) -> Result<PathBuf> {
        let ema = candle_core::safetensors::load(
            checkpoint.join("ema.safetensors"),
            &candle_core::Device::Cpu,
        )
        .with_context(|| format!("reading {}", checkpoint.display()))?;
        let mut weights: std::collections::HashMap<&str, _> =
            self.encoders.iter().map(|(f, w)| (*f, w.clone())).collect();
        weights.insert(veila_diffusion::app::bundle::DENOISER_FILE, ema);
        let mut config = self.config.clone();
        config.provenance = serde_json::json!({ "snapshot_of_step": step, "trained_by": "cargo xtask train-default" });
        let out = self.dir.join(format!("step-{step:010}"));
        Bundle::save(&out, &config, &weights)?;
        Ok(out)
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

impl<M: veila_diffusion::Denoiser> TrainObserver<M> for Progress {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        let line = self.loss.line(s);
        self.bar.set_position(s.step);
        if self.bar.is_hidden() && (s.step.is_multiple_of(50) || s.step == 1) {
            eprintln!("  step {} {line}", s.step);
        }
        self.bar.set_message(line);
        ControlFlow::Continue(())
    }

    fn on_checkpoint(&mut self, step: u64, path: &std::path::Path) {
        if let Some(s) = &self.snapshots
            && step.is_multiple_of(s.every)
        {
            match s.write(step, path) {
                Ok(out) => self.bar.println(format!("  snapshot {}", out.display())),
                Err(e) => self
                    .bar
                    .println(format!("  snapshot of step {step} failed: {e:#}")),
            }
        }
    }
}

impl TrainDefaultArgs {
    /// The recipe these flags ask for.
    pub fn recipe(&self) -> SimRecipe {
        SimRecipe {
            variant: self.variant,
            method: self.method,
            frames: self.frames,
            scenes: self.scenes.clone(),
            encoder_scenes: self.encoder_scenes.clone(),
            encoder_steps: self.encoder_steps,
            steps: self.steps,
            mean_steps: self.mean_steps,
            batch: self.batch,
            lr: self.lr,
            seed: self.seed,
            checkpoint_every: self.checkpoint_every,
            encoders_from: self.encoders_from.clone(),
            init_from: self.init_from.clone(),
            images: self.images,
            randomize_share: self.randomize_share,
            wide_facades: self.wide_facades,
            augment_encoders: self.augment_encoders,
            ground_prior: self.ground_prior,
            depth_features: self.depth_features,
            sky_depth: self.sky_depth,
            base_channels: self.base_channels.map(|c| c as usize),
            res_blocks: self.res_blocks.map(|n| n as usize),
            channel_mults: self
                .channel_mults
                .as_ref()
                .map(|m| m.iter().map(|&x| x as usize).collect()),
            ema_decay: self.ema_decay,
            uniform_loss_weighting: self.loss_weighting == "uniform",
        }
    }
}

/// Trains and writes a bundle; returns the bundle config written.
pub fn run(args: TrainDefaultArgs) -> Result<BundleConfig> {
    run_with(args, None)
}

/// [`run`] on already simulated training frames (`None`: simulate `args.frames` of them).
pub fn run_with(args: TrainDefaultArgs, frames: Option<&[SimExample]>) -> Result<BundleConfig> {
    let t_all = Instant::now();
    let recipe = args.recipe();
    let render_style = args
        .images
        .checked_style(args.randomize_share, args.wide_facades)?;
    let device = args.device.open()?;
    let root = workspace_root();
    let mut cfg = recipe.bundle_config()?;
    if args.sky_depth && args.encoders_from.is_some() {
        anyhow::bail!(
            "--sky-depth changes how the depth encoder trains, and --encoders-from reuses trained ones: pass one of them"
        );
    }
    if args.encoder_scenes.is_some() && args.encoders_from.is_some() {
        anyhow::bail!(
            "--encoder-scenes chooses the frames the encoders train on, and --encoders-from reuses trained ones: pass one of them"
        );
    }
    let encoder_list = recipe.encoder_list();
    if encoder_list.is_some() && frames.is_some() {
        anyhow::bail!(
            "training on given frames trains the encoders on them too: pass --encoders-from, or --encoder-scenes equal to --scenes"
        );
    }
    let method = cfg.method();
    println!(
        "train-default: variant {} ({}), method {} ({}), {} frames, encoders {} steps, denoiser {} steps x batch {}, seed {}",
        args.variant.name(),
        args.variant.label(),
        method.name(),
        method.label(),
        args.frames,
        args.encoder_steps,
        args.steps,
        args.batch,
        args.seed
    );
    let t = Instant::now();
    let rendered;
    let examples: &[SimExample] = match frames {
        Some(f) => f,
        None => {
            rendered = crate::progress::render_split(
                &args.scenes,
                args.frames,
                &cfg,
                &render_style,
                "simulating train frames",
            )?;
            &rendered
        }
    };
    // the encoders' own frames when they train on another list (same count, style and seeds;
    // never with given frames, refused above)
    let encoder_rendered;
    let encoder_examples: &[SimExample] = match &encoder_list {
        Some(list) => {
            encoder_rendered = crate::progress::render_split(
                list,
                args.frames,
                &cfg,
                &render_style,
                "simulating the encoders' train frames",
            )?;
            &encoder_rendered
        }
        None => examples,
    };
    let sim_secs = t.elapsed().as_secs_f64();
    match &encoder_list {
        Some(l) => println!(
            "  simulated {} frames in {sim_secs:.1} s (networks: {}; encoders: {})",
            examples.len() + encoder_examples.len(),
            args.scenes.display(),
            l.display()
        ),
        None => println!("  simulated {} frames in {sim_secs:.1} s", examples.len()),
    }

    let work = args.work.clone().unwrap_or_else(|| {
        root.join("target/train-default")
            .join(format!("{}-{}", args.variant.name(), method.name()))
    });
    let settings = recipe.settings();
    let run_key = recipe.run_key(&cfg, &settings, examples.len());
    veila_diffusion::claim_checkpoint_dir(&work, &run_key)
        .with_context(|| "pass another --work to start a separate run")?;

    let images: Vec<Vec<u8>> = encoder_examples.iter().map(|e| e.rgb.clone()).collect();
    let labels: Vec<Vec<u32>> = encoder_examples.iter().map(|e| e.labels.clone()).collect();
    let sky_m = recipe.sky_target_m(&cfg).context("--sky-depth")?;
    let depths: Vec<Vec<f32>> = encoder_examples
        .iter()
        .map(|e| match sky_m {
            Some(far) => sim_examples::depth_with_sky_at(&e.depth_m, far),
            None => e.depth_m.clone(),
        })
        .collect();
    let cameras: Vec<veila_geom::PinholeCamera> =
        encoder_examples.iter().map(|e| e.camera).collect();
    let enc_dir = work.join(recipe.encoder_dir_name(examples.len()));
    let encoders = match &args.encoders_from {
        Some(dir) => EncoderSource::Bundle(dir),
        None => EncoderSource::Train {
            data: EncoderData::Memory {
                images: &images,
                labels: Some(&labels),
                depth_m: &depths,
                cameras: Some(&cameras),
            },
            dir: &enc_dir,
        },
    };
    let init = args
        .init_from
        .as_ref()
        .map(|dir| {
            Bundle::from_dir(dir, &device)
                .with_context(|| format!("loading initial weights from {}", dir.display()))
        })
        .transpose()?;
    let mean_init = init.as_ref().and_then(|b| b.mean.as_ref().map(|(_, w)| w));
    let train_examples: Vec<TrainExample> = examples
        .iter()
        .map(|e| e.train_example(&cfg))
        .collect::<veila_diffusion::Result<_>>()?;
    let snapshots = match args.snapshot_every {
        None => None,
        Some(every) => Some(snapshot_plan(&args, &cfg, &work, every)?),
    };
    let t = Instant::now();
    let mut bar: Option<indicatif::ProgressBar> = None;
    let outcome = run_recipe(
        &mut cfg,
        RecipeInput {
            encoders,
            examples: (&train_examples).into(),
            work_dir: &work,
            init: init.as_ref().map(|b| &b.weights),
            mean_init,
            parallel: None,
        },
        &settings,
        &device,
        |event| match event {
            EncoderEvent::Reused(which, path) => {
                println!("  {} encoder: reusing {}", which.name(), path.display())
            }
            EncoderEvent::Step(which, s, total) => {
                let b = bar.get_or_insert_with(|| {
                    let label = format!("{} encoder", which.name());
                    crate::progress::progress_bar(total as u64, &label)
                });
                b.set_position(s.step as u64);
                b.set_message(format!("loss {:.4}", s.loss));
            }
            EncoderEvent::Trained(which, last) => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
                println!("  {} encoder: final batch loss {last:.4}", which.name());
            }
        },
        |stage, p, step| {
            println!(
                "  {}: resumed from {} (step {step})",
                stage.name(),
                p.display()
            )
        },
        |stage, total| Progress {
            bar: crate::progress::progress_bar(total, stage.name()),
            loss: LossAverage::default(),
            snapshots: snapshots
                .clone()
                .filter(|_| stage == veila_diffusion::app::Stage::Denoiser),
        },
    )
    .with_context(|| match &args.encoders_from {
        Some(dir) => format!("training (encoders from {})", dir.display()),
        None => format!("training in {}", work.display()),
    })?;
    let den_secs = t.elapsed().as_secs_f64() - outcome.encoder_seconds;
    let den = outcome
        .fit
        .denoiser
        .as_ref()
        .context("the mean network's run stopped early")?;
    if let Some(dir) = &args.init_from {
        println!(
            "  initialised {} of {} denoiser tensors from {}",
            den.initialised,
            den.ema_weights.len(),
            dir.display()
        );
        if let Some(m) = &outcome.fit.mean {
            println!(
                "  initialised {} of {} mean-network tensors from {}",
                m.initialised,
                m.ema_weights.len(),
                dir.display()
            );
        }
    }
    if let Some(m) = &outcome.fit.mean {
        println!(
            "  mean network: {} steps this run, mean loss {}, {:.0} s; residual scale {:?}",
            m.summary.steps_run,
            m.summary.mean_loss_text(),
            outcome.fit.seconds[0],
            cfg.residual.as_ref().map(|r| &r.scale)
        );
    }
    println!(
        "  denoiser: {} steps this run, mean loss {}, {} skipped, {:.0} s",
        den.summary.steps_run,
        den.summary.mean_loss_text(),
        den.summary.skipped,
        outcome.fit.seconds[1]
    );
    cfg.provenance = recipe.provenance(
        &cfg,
        &outcome,
        &args.device.name(),
        examples.len(),
        sim_secs,
        den_secs,
    )?;
    Bundle::save(&args.out, &cfg, &outcome.into_weights())?;
    // read back through the verifying loader
    Bundle::from_dir(&args.out, &device)
        .with_context(|| format!("re-reading {}", args.out.display()))?;
    println!(
        "wrote {} in {:.0} s ({} parameters in the denoiser)",
        args.out.display(),
        t_all.elapsed().as_secs_f64(),
        veila_nn::checkpoint::parameter_count(&cfg.denoiser)?
    );
    Ok(cfg)
}

/// `--images`: a [`TrainImages`] style by its name.
/// The snapshots `--snapshot-every` asks for: refused for the residual method and for encoders
/// trained in this run (a snapshot takes them from `--encoders-from`).
fn snapshot_plan(
    args: &TrainDefaultArgs,
    cfg: &BundleConfig,
    work: &std::path::Path,
    every: u64,
) -> Result<Snapshots> {
    if every == 0 || !every.is_multiple_of(args.checkpoint_every.max(1)) {
        anyhow::bail!(
            "--snapshot-every {every} must be a positive multiple of --checkpoint-every {}",
            args.checkpoint_every
        );
    }
    if cfg.residual.is_some() {
        anyhow::bail!(
            "--snapshot-every: the residual method's bundle needs its finished mean network"
        );
    }
    let mut encoders = Vec::new();
    if cfg.denoiser.conditioning.is_some() {
        let Some(dir) = &args.encoders_from else {
            anyhow::bail!("--snapshot-every with a conditional model needs --encoders-from");
        };
        for file in [
            veila_diffusion::app::bundle::SEMANTIC_FILE,
            veila_diffusion::app::bundle::DEPTH_FILE,
        ] {
            if cfg.weight_files().contains(&file) {
                let w = candle_core::safetensors::load(dir.join(file), &candle_core::Device::Cpu)
                    .with_context(|| format!("reading {}", dir.join(file).display()))?;
                encoders.push((file, w));
            }
        }
    }
    Ok(Snapshots {
        every,
        dir: work.join("snapshots"),
        config: cfg.clone(),
        encoders,
    })
}

fn parse_images(s: &str) -> Result<TrainImages> {
    Ok(s.parse()?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn parse(argv: &[&str]) -> TrainDefaultArgs {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: TrainDefaultArgs,
        }
        <Cli as clap::Parser>::try_parse_from(
            std::iter::once("train-default").chain(argv.iter().copied()),
        )
        .unwrap()
        .args
    }

    #[test]
    fn the_flags_default_to_the_shipped_recipe() {
        // the shipped recipe: networks on train-v5, encoders on the street list
        let r = parse(&[]).recipe();
        assert_eq!(r.scenes, Path::new("scenes/train-v5.txt"));
        assert_eq!(r.encoder_list(), Some(PathBuf::from("scenes/train.txt")));
        assert_eq!(
            (r.images, r.frames, r.steps),
            (TrainImages::Materials, 960, 12500)
        );
    }

    #[test]
    fn encoder_scenes_with_reused_encoders_is_refused_before_any_work() {
        let mut a = parse(&[
            "--encoders-from",
            "models/default",
            "--encoder-scenes",
            "scenes/train.txt",
        ]);
        a.out = std::env::temp_dir().join("veila-never-written");
        let e = run(a).unwrap_err().to_string();
        assert!(
            e.contains("--encoder-scenes") && e.contains("--encoders-from"),
            "{e}"
        );
        assert!(!std::env::temp_dir().join("veila-never-written").exists());
    }

    #[test]
    fn the_device_flag_names_the_cpu_or_one_gpu() {
        assert_eq!(parse(&[]).device, DeviceArg::Cpu);
        assert_eq!(parse(&["--device", "cuda"]).device, DeviceArg::Cuda(0));
        assert_eq!(parse(&["--device", "cuda:3"]).device, DeviceArg::Cuda(3));
        for bad in ["gpu", "cuda:", "cuda:x", "cuda:-1", "CPU"] {
            assert!(crate::device::parse_device(bad).is_err(), "{bad}");
        }
        assert_eq!(DeviceArg::Cuda(3).name(), "cuda:3");
        // a build without the feature says how to get one, before any work
        if !cfg!(feature = "cuda") {
            let e = DeviceArg::Cuda(0).open().unwrap_err().to_string();
            assert!(e.contains("build-cuda --xtask"), "{e}");
        }
    }
}
