//! What a run of the benchmark report measures ([`BenchReportOptions`]) and how its ablation
//! variants are trained ([`Protocol`]).

use std::path::PathBuf;

use serde::Serialize;

use crate::SamplerName;
use crate::app::bundle::Variant;
use crate::error::{Error, Result, invalid};

/// How ablation variants are trained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Protocol {
    /// From the bundled model's weights.
    Finetune,
    /// From a seeded initialisation.
    Scratch,
}

impl Protocol {
    /// Every protocol, in the order help texts list them.
    pub const ALL: [Protocol; 2] = [Protocol::Finetune, Protocol::Scratch];

    /// The command-line name: `finetune`, `scratch`.
    pub fn as_str(self) -> &'static str {
        match self {
            Protocol::Finetune => "finetune",
            Protocol::Scratch => "scratch",
        }
    }

    /// One line for a `--help` text.
    pub fn help(self) -> &'static str {
        match self {
            Protocol::Finetune => "From the bundled model's weights",
            Protocol::Scratch => "From a seeded initialisation",
        }
    }

    /// The protocol's tag in the variants' folder names.
    pub fn tag(self) -> &'static str {
        match self {
            Protocol::Finetune => "ft",
            Protocol::Scratch => "scratch",
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Protocol {
    type Err = Error;

    fn from_str(name: &str) -> Result<Self> {
        Protocol::ALL
            .into_iter()
            .find(|p| p.as_str() == name)
            .ok_or_else(|| invalid("protocol", format!("{name:?} is not finetune or scratch")))
    }
}

/// The options of one benchmark report (`cargo xtask bench-report`'s flags; paths as the driver
/// resolved them, scene lists relative to `root`).
#[derive(Debug, Clone, PartialEq)]
pub struct BenchReportOptions {
    /// The workspace: the scene lists, `models/feature-nets` and the real samples beside it.
    pub root: PathBuf,
    /// Output folder (report.md, report.json, *.png).
    pub out: PathBuf,
    /// The bundle whose encoders every variant shares (and whose denoiser the sweep uses).
    pub model: PathBuf,
    /// Where trained variants are kept between runs.
    pub work: PathBuf,
    /// The command line the report states.
    pub command: String,
    /// Held-out test frames, split into `folds` disjoint folds.
    pub test_frames: usize,
    /// Scene list of the test frames (`None`: the one beside the bundle's training list).
    pub test_scenes: Option<PathBuf>,
    /// Disjoint folds of the test frames.
    pub folds: usize,
    /// Training frames behind the baselines (the median scan, the retrieval database).
    pub baseline_frames: usize,
    /// Sample seeds per variant.
    pub seeds: u64,
    /// How the variants are trained.
    pub protocol: Protocol,
    /// Denoiser training steps of every variant.
    pub train_steps: u64,
    /// Training frames of every variant.
    pub train_frames: usize,
    /// Sampler of the model rows.
    pub sampler: SamplerName,
    /// Sampler steps of the model rows.
    pub steps: usize,
    /// Variants to compare (`None`: all).
    pub variants: Option<Vec<Variant>>,
    /// No ablation variants: the bundled model as shipped (and its own unconditional branch).
    pub shipped_only: bool,
    /// Residual weights of a residual bundle's sweep, each in `[0, 1]`.
    pub sweep_residual_weights: Vec<f64>,
    /// Test frames of the sampler sweep.
    pub sweep_frames: usize,
    /// Step counts of the sampler sweep.
    pub sweep_steps: Vec<usize>,
    /// A small, fast configuration ([`BenchReportOptions::shrink_for_quick`]).
    pub quick: bool,
    /// Leave out the real frames.
    pub no_real: bool,
    /// Samples per real frame.
    pub real_seeds: usize,
}

impl BenchReportOptions {
    /// `quick`: 12 test frames in 2 folds, 48 baseline frames, 2 seeds, 40 training steps on 96
    /// frames, 8 sampler steps, the sweep on 3 frames with 4 / 8 / 16 steps: a smoke run whose
    /// numbers show the pipeline, not converged models.
    pub fn shrink_for_quick(&mut self) {
        self.test_frames = 12;
        self.folds = 2;
        self.baseline_frames = 48;
        self.seeds = 2;
        self.train_steps = 40;
        self.train_frames = 96;
        self.steps = 8;
        self.sweep_frames = 3;
        self.sweep_steps = vec![4, 8, 16];
    }

    /// Refuses a residual weight outside `[0, 1]`.
    pub fn check(&self) -> Result<()> {
        match self
            .sweep_residual_weights
            .iter()
            .find(|w| !(0.0..=1.0).contains(*w))
        {
            Some(w) => Err(invalid(
                "sweep_residual_weights",
                format!("{w} is not between 0 and 1"),
            )),
            None => Ok(()),
        }
    }

    /// The variants to compare: every one asked for (all by default); with `shipped_only`, only
    /// the fine-tuning protocol's unconditional branch of a conditional bundle.
    pub fn variant_list(&self, conditional: bool) -> Vec<Variant> {
        if self.shipped_only {
            match self.protocol {
                Protocol::Finetune if conditional => vec![Variant::Unconditional],
                _ => Vec::new(),
            }
        } else {
            self.variants
                .clone()
                .unwrap_or_else(|| Variant::ALL.to_vec())
        }
    }

    /// The report's notes on the protocol and the metrics.
    pub fn notes(&self) -> Vec<String> {
        vec![
            match self.protocol {
                Protocol::Finetune => format!("Protocol `finetune`: every variant starts from the bundled model's denoiser and is trained {} more steps with its switch flipped (weights that no longer fit are freshly initialised); `Veila` is the bundled model fine-tuned the same way (the control). The unconditional row is the bundled network's own unconditional branch (trained by 10% condition dropout), not a separately trained model.", self.train_steps),
                Protocol::Scratch => format!("Protocol `scratch`: every variant is trained from the same seeded initialisation for {} steps.", self.train_steps),
            },
            "All variants share the data, seed, step budget and the frozen encoders of the bundled model; differences smaller than the spread over seeds are not significant.".into(),
            "Reference scans are the true simulated scans projected onto the same range-image grid as the generated ones.".into(),
            "CM-DC: mean absolute relative difference between each generated point's camera depth and the bundled depth encoder's depth head where it projects. CM-SC: percentage of generated points whose class from the shipped range segmentation net (rangenet-small) agrees with the bundled semantic encoder's head where they project (unlabelled excluded). Both over the camera's field of view.".into(),
            "FRD / FPD use the shipped feature networks trained on simulator data (models/feature-nets), per region on the points of that region; with a dozen scans per side the covariances are rank-deficient, so read them as relative numbers between rows, not as converged distances or as comparable to published values.".into(),
        ]
    }
}
