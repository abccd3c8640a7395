//! `cargo xtask train-default`: trains the bundled model (`models/default`) from a fixed seed on
//! the simulator's train split with the recipe `veila train` runs too
//! (`veila_diffusion::app::recipe`): the two small CNN encoders first (semantics, depth), then the
//! mean network and the denoiser on their frozen features. Resumable: checkpoints and the trained
//! encoders go to `--work` and a rerun picks up the newest ones. The recipe and its run are
//! `veila_diffusion::app::sim_recipe`; this driver parses the flags and shows the run.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use veila_diffusion::LossWeighting;
use veila_diffusion::app::bundle::{BundleConfig, Method, Variant};
use veila_diffusion::app::sim_examples::{self, TrainImages};
use veila_diffusion::app::sim_recipe::{SimRecipe, SimRun};

use crate::device::DeviceArg;
use crate::progress::{Terminal, workspace_root};

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
    /// (bench-report's fine-tuned ablations; a conditional model from an unconditional bundle,
    /// `docs/lab/cond-v16`); the rest keeps its seeded initialisation. Refused when fewer than
    /// half of the bundle's tensors fit.
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
    /// Octaves of the Fourier features of each pixel's ray direction fed to the U-Nets
    /// [default: the shipped recipe's 4; 6 resolve about 2.6 pixels of azimuth, R2DM's scale].
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=32))]
    pub ray_freqs: Option<u64>,
    /// Loss weighting over noise levels of the diffusion methods: `min-snr` (min-SNR-5, the
    /// shipped recipe's) or `uniform` (every level alike in the prediction's MSE: for
    /// v-prediction the x₀-space weight SNR + 1) [default: min-snr].
    #[arg(long, value_parser = str::parse::<LossWeighting>)]
    pub loss_weighting: Option<LossWeighting>,
    /// The share of diffusion training draws at the clean levels, log-SNR 6 to 18, where a
    /// sample's fine texture forms (the rest uniform in time) [default: none, uniform time].
    #[arg(long)]
    pub clean_share: Option<f64>,
    /// Weigh each return's error in the denoiser's loss by ((r + 1) / 11)^P, r its range in
    /// metres: P from 0 (every pixel alike) to 2 (errors as metres) [default: none, alike].
    #[arg(long, value_name = "P")]
    pub range_weight: Option<f64>,
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
            ray_freqs: self.ray_freqs.map(|n| n as usize),
            ema_decay: self.ema_decay,
            loss_weighting: self.loss_weighting,
            clean_share: self.clean_share,
            range_weight: self.range_weight,
        }
    }
}

/// Trains and writes a bundle (`veila_diffusion::app::sim_recipe`); returns the bundle config
/// written.
pub fn run(args: TrainDefaultArgs) -> Result<BundleConfig> {
    let recipe = args.recipe();
    let device = args.device.open()?;
    let root = workspace_root();
    let work = match &args.work {
        Some(w) => w.clone(),
        None => root.join("target/train-default").join(format!(
            "{}-{}",
            args.variant.name(),
            recipe.bundle_config()?.method().name()
        )),
    };
    let run = SimRun {
        root: &root,
        out: &args.out,
        work: &work,
        device: &device,
        device_name: &args.device.name(),
        snapshot_every: args.snapshot_every,
        frames: None,
    };
    Ok(recipe.train(&run, &Terminal::default())?)
}

/// `--images`: a [`TrainImages`] style by its name.
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
        assert_eq!(r, SimRecipe::shipped());
        assert_eq!(r.scenes, Path::new("scenes/train-v5.txt"));
        assert_eq!(r.encoder_list(), Some(PathBuf::from("scenes/train.txt")));
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
            e.contains("encoder_scenes") && e.contains("encoders_from"),
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
