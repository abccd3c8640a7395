//! `veila generate`: panoramic LiDAR scans from camera images with a model bundle.
//!
//! The images and their calibration give a camera rig (one view per `--image`); the bundle's frozen
//! encoders see each image resized to the bundle's input size, the denoiser samples range images on
//! the bundle's grid, and every scan is written as a KITTI `.bin`, a range-image EXR and three
//! previews. Everything goes to a staging folder first: a failure leaves no output behind.
//!
//! Calibration files carry no image size, so each camera takes the size of its image
//! (`veila_diffusion::app::rig` reads and checks them). From the rig to the scans it is the
//! library's `ScanPipeline`, the path every door takes: a LiDAR frame whose forward axis is not
//! the first camera's (nuScenes: `y` forward) is sampled in the model's frame and every scan comes
//! back in the calibration's LiDAR frame, as the files are.
//!
//! With `--frames DIR` it generates a dataset instead: a scan for every frame of a KITTI-layout
//! folder or of converted shards, into a KITTI-layout folder, resumable and split across workers
//! ([`frames`]; the job is the library's `veila_diffusion::app::dataset_gen`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{ArgGroup, Args};
use serde::Serialize;
use veila_diffusion::app::{GenerateOptions, SamplerChoice, ScanPipeline};
use veila_diffusion::{SamplerConfig, SamplerName};

use crate::generation::{
    InputInfo, MAX_SAMPLES, ModelInfo, RigArgs, SAMPLE_BATCH, ScanRecord, Seconds, check_options,
    input_info, load_rig, model_info, resolve_sampler, round3, sampler_help, sampler_parser,
    write_scan,
};
use crate::workers::WorkerArgs;
use crate::{model, progress, staging};

mod frames;

/// Arguments of `veila generate`.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("input").required(true).args(["images", "frames"])))]
pub(crate) struct GenerateArgs {
    #[command(flatten)]
    pub(crate) rig: RigArgs,
    /// Generate a dataset: a scan for every frame of DIR, a KITTI-layout folder (image_2/NAME.png
    /// and calib/NAME.txt) or converted shards (manifest.json), into --out as velodyne/NAME.bin
    /// with dataset.json. Each frame's seed follows from --seed and its name; a rerun resumes,
    /// and workers (--shard-index/--shard-count, Slurm arrays, Kubernetes Indexed Jobs) share
    /// one --out.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["samples", "force", "cameras"])]
    pub(crate) frames: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) workers: WorkerArgs,
    /// With --frames: pseudo-label every generated scan's points with a segmenter, written as
    /// labels/NAME.label (SemanticKITTI raw ids); DIR is a segmenter folder, default the bundled
    /// one (models/segmenter).
    #[arg(long, value_name = "DIR", num_args = 0..=1)]
    pub(crate) segmenter: Option<Option<PathBuf>>,
    /// Model bundle folder (default: $VEILA_MODEL, else the bundled models/default;
    /// `--checkpoint` is an alias).
    #[arg(long, value_name = "DIR", env = "VEILA_MODEL", alias = "checkpoint")]
    pub(crate) model: Option<PathBuf>,
    // the help names the bundled model's sampler as its bundle.json does
    #[arg(long, value_parser = sampler_parser(), help = sampler_help())]
    pub(crate) sampler: Option<SamplerName>,
    /// Where the sampler's steps lie on the noise schedule (default: the bundle's).
    #[arg(long, value_parser = crate::generation::spacing_parser())]
    pub(crate) spacing: Option<veila_diffusion::Spacing>,
    /// Sampler steps (network evaluations per conditioning branch, 1 to 1000; default: the
    /// bundle's).
    #[arg(long, value_name = "N", value_parser = crate::bounds::steps())]
    pub(crate) steps: Option<usize>,
    /// Classifier-free guidance scale, 0 to 20 (1 = none; default: the bundle's).
    #[arg(long, value_name = "S", allow_negative_numbers = true, value_parser = crate::bounds::guidance())]
    pub(crate) guidance: Option<f64>,
    /// Bundles with a prior mean network: the level the draw starts from, 0.001 to 1, from the
    /// mean network's scan with that much noise (1 = pure noise; default: the bundle's).
    /// Lower follows the image more closely and takes fewer steps; higher keeps more texture.
    #[arg(long, value_name = "T", value_parser = crate::bounds::start_level())]
    pub(crate) start_t: Option<f64>,
    /// Residual-diffusion bundles: how much of the sampled residual goes on top of the mean
    /// network's scan, 0 to 1. 1 is a full sample (the data's texture); 0 is the smooth
    /// conditional mean, the smallest pixel error.
    #[arg(
        long,
        value_name = "W",
        default_value_t = 1.0,
        allow_negative_numbers = true,
        value_parser = crate::bounds::unit()
    )]
    pub(crate) residual_weight: f64,
    /// Seed of the initial noise, 0 to 18446744073709551615 (same inputs, model and seed give identical files;
    /// scan `i` is the same whatever --samples).
    #[arg(long, value_name = "S", default_value_t = 0)]
    pub(crate) seed: u64,
    /// Number of scans to draw for the rig, 1 to 100000 (drawn in batches of at most 8: memory
    /// does not grow with N).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = crate::bounds::int::<usize>(1, MAX_SAMPLES as u64))]
    pub(crate) samples: usize,
    /// Output folder (created; must be absent or empty unless --force; with --frames, absent,
    /// empty or this job's dataset, which is resumed).
    #[arg(long, value_name = "DIR")]
    pub(crate) out: PathBuf,
    /// Write into an existing, non-empty output folder (same-named files are replaced).
    #[arg(long)]
    pub(crate) force: bool,
}

#[derive(Debug, Serialize)]
struct GenerateReport<'a> {
    command: &'static str,
    veila_version: &'static str,
    inputs: Vec<InputInfo>,
    model: ModelInfo,
    sampler: &'a SamplerConfig,
    sampler_name: String,
    /// Quarter turns about z from the calibration's LiDAR frame into the model's (1 for
    /// nuScenes); the scans are written in the calibration's frame.
    model_frame_quarter_turns: i32,
    steps: usize,
    guidance: f64,
    residual_weight: f64,
    seed: u64,
    samples: usize,
    sample_batch: usize,
    scans: Vec<ScanRecord>,
}

pub(crate) fn run(args: GenerateArgs) -> Result<()> {
    // the parsers hold every flag to its range; what depends on the model is checked once it is
    // loaded, before the rig is read
    let t0 = Instant::now();
    let worker = match &args.frames {
        Some(_) => Some(args.workers.resolve()?),
        None if args.workers.given() => {
            bail!("--shard-index and --shard-count split a dataset: give them with --frames")
        }
        None => None,
    };
    if args.segmenter.is_some() && args.frames.is_none() {
        bail!("--segmenter pseudo-labels a dataset's scans: give it with --frames");
    }
    let mut inputs = staging::Inputs::new();
    inputs.extend(&args.rig.images).extend(&args.rig.calibs);
    let device = model::device()?;
    let bundle = model::load_bundle(args.model.as_deref(), &device)?;
    let sampler = resolve_sampler(
        &bundle,
        SamplerChoice {
            name: args.sampler,
            spacing: args.spacing,
            steps: args.steps,
            guidance: args.guidance,
            start_t: args.start_t,
        },
    );
    let options = GenerateOptions {
        sampler: sampler.clone(),
        samples: args.samples,
        seed: args.seed,
        unconditional: false,
        residual_weight: args.residual_weight,
    };
    check_options(&options, &bundle)?;
    if let (Some(dir), Some(worker)) = (&args.frames, worker) {
        let segmenter = match &args.segmenter {
            Some(seg_dir) => Some(model::load_segmenter(seg_dir.as_deref(), &device)?),
            None => None,
        };
        return frames::run(
            &bundle,
            frames::FramesRun {
                frames: dir,
                out: &args.out,
                options: &options,
                worker,
                segmenter: segmenter.as_ref(),
            },
        );
    }
    let views = load_rig(&args.rig)?;
    let pipeline = ScanPipeline::from_views(&bundle, &views)?;
    let turns = pipeline.quarter_turns();
    // inputs are good: only now does the output folder get a staging directory
    let staging = staging::stage_checked(&args.out, args.force, &inputs)?;
    let load_secs = t0.elapsed().as_secs_f64();

    let batches = args.samples.div_ceil(SAMPLE_BATCH);
    let pb = progress::bar((sampler.steps * batches) as u64, "generate"); // <= 1000 * 12500
    pb.set_message(format!("{} scan(s), {}", args.samples, sampler.kind));
    let (mut sampling_secs, mut writing_secs) = (0.0, 0.0);
    let mut records = Vec::new();
    for (b, (first, batch)) in options.batches(SAMPLE_BATCH).enumerate() {
        let t = Instant::now();
        let scans = pipeline
            .generate(&batch, |done, total| {
                pb.set_length((total * batches) as u64);
                pb.set_position((b * total + done) as u64);
            })
            .context("sampling")?;
        sampling_secs += t.elapsed().as_secs_f64();
        // each batch is written and dropped before the next is drawn
        let t = Instant::now();
        for (j, scan) in scans.iter().enumerate() {
            records.push(write_scan(
                staging.path(),
                &format!("scan_{:03}", first + j),
                &bundle,
                scan,
                &views[0],
            )?);
        }
        writing_secs += t.elapsed().as_secs_f64();
    }
    pb.finish_and_clear();
    let report = GenerateReport {
        command: "generate",
        veila_version: env!("CARGO_PKG_VERSION"),
        inputs: input_info(&views),
        model: model_info(&bundle, args.model.as_deref()),
        sampler: &sampler,
        sampler_name: sampler.kind.to_string(),
        model_frame_quarter_turns: turns,
        steps: sampler.steps,
        guidance: sampler.guidance_scale,
        residual_weight: args.residual_weight,
        seed: args.seed,
        samples: args.samples,
        sample_batch: SAMPLE_BATCH,
        scans: records,
    };
    let timings = Seconds {
        load: round3(load_secs),
        sampling: round3(sampling_secs),
        per_scan: round3(sampling_secs / args.samples as f64),
        writing: round3(writing_secs),
    };
    veila_data::atomic::write_atomic(
        &staging.path().join("generate.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    veila_data::atomic::write_atomic(
        &staging.path().join("timings.json"),
        serde_json::to_string_pretty(&timings)?.as_bytes(),
    )?;
    staging.commit()?;

    println!(
        "generated {} scan(s) on the {}x{} grid of model `{}` from {} view(s): {sampler}, seed {}",
        args.samples,
        report.model.grid[0],
        report.model.grid[1],
        crate::out::untrusted(&report.model.name),
        views.len(),
        args.seed
    );
    for r in &report.scans {
        println!(
            "  {}: {} points ({} in the first image)",
            r.file, r.points, r.points_in_first_image
        );
    }
    println!(
        "{:.2} s per scan (sampling {:.2} s, loading {:.2} s, writing {:.2} s); wrote {}",
        sampling_secs / args.samples as f64,
        sampling_secs,
        load_secs,
        writing_secs,
        args.out.display()
    );
    Ok(())
}
