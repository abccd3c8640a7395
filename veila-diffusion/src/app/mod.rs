//! The application: what turns the generic diffusion core into Veila's image-to-LiDAR model. This
//! is the one module of the crate that names `veila-nn` (the tidy test checks it).
//!
//! * [`bundle`]: model bundles (encoders + denoiser + settings in one folder, sha256 manifest
//!   verified on load) and the ablation [`Variant`]s and generative [`Method`]s as config switches.
//! * [`pipeline`]: **the entry point**: a camera rig (images and calibrations) to scans in the
//!   LiDAR's own frame ([`ScanPipeline`]: fit to the encoders, turn into the model's frame, sample,
//!   turn back, unproject), for generation and RePaint edits. Every door calls it.
//! * [`generate`]: the sampling underneath, on views already fitted to the bundle and in the
//!   model's frame (generation, RePaint inpainting).
//! * [`train`]: training a bundle's denoiser and mean network ([`mean`]: the residual targets and
//!   the frozen mean network); [`encoder_train`]: training the small CNN encoders.
//! * [`dataset`]: training examples in memory or read on demand (data of any size).
//! * [`dataset_gen`]: dataset-scale generation (`veila generate --frames`): a scan for every
//!   frame of a KITTI-layout folder or of converted shards, seeded per frame, resumable and
//!   split across workers, into a KITTI-layout folder.
//! * [`train_config`]: the training config of `veila train` (`[data]`, `[model]`, `[train]`,
//!   `[output]`) and the bundle config and recipe settings it gives.
//! * [`train_data`]: converted shards as training examples, in memory or streamed.
//! * [`recipe`]: the one training recipe (encoders, mean network, residual scale, denoiser) that
//!   `veila train` and `cargo xtask train-default` both run.
//! * [`rig`]: camera images and their calibration files as views of a rig, range images as points;
//!   the pipeline's steps (resizing to a bundle's input, the model-frame turn), private to the crate.
//! * [`crossmodal_eval`]: the cross-modal metrics (CM-DC, CM-SC) of
//!   generated scan files for `veila eval`: each scan's calibration, maps or camera image found,
//!   Depth-Anything-V2 / SegFormer run, the scores averaged (the math: `veila_metrics::crossmodal`).
//! * [`progress`]: how a long run (a recipe, a benchmark) shows itself to the binary that drives
//!   it: lines and bars.
//! * [`scoring`]: generated scans scored against simulated frames (the set metrics per fold
//!   with the encoders and feature networks that feed them; `cargo xtask bench-report`).
//! * `sim_examples` (feature `sim`): simulated frames of a split list at a bundle's size, for
//!   training and benchmarks (`cargo xtask train-default`, `bench-report`, `bench-real`).
//! * `real_frames` (feature `sim`): a bundle on the real KITTI / nuScenes frames of the shared
//!   samples against their real scans, with the image-free baselines (`cargo xtask bench-real`,
//!   `bench-report`).
//! * `realism` (feature `sim`): the realism benchmark: realism, texture, faithfulness,
//!   memorisation and diversity of generated scans against their data floors, its whole run and
//!   report (`cargo xtask bench-realism`).
//! * `bench_report` (feature `sim`): the benchmark report: the bundle against the baselines, the
//!   floor and its ablation variants, the sampler sweep, the real frames (`cargo xtask
//!   bench-report`).
//! * `augment` (feature `sim`): the augmentation benchmark: segmenters trained on scarce labels
//!   with and without generated scans pseudo-labelled by a teacher, against the true-scan, mean
//!   network and retrieval controls (`cargo xtask bench-augment`).
//! * `report_files` (feature `sim`): a benchmark's `report.json` and `report.md`.
//! * `sim_recipe` (feature `sim`): the bundled model's recipe on simulator frames (`cargo xtask
//!   train-default`): its options, the run key of its work folder, the folder of its trained
//!   encoders, the provenance it writes, and the run itself.
//! * `feature_net_data` (feature `sim`): simulated training scans of the FRD / FPD feature
//!   networks (`cargo xtask train-feature-nets`).
//! * [`segment`]: LiDAR semantic segmentation (`veila segment`): segmenter model folders,
//!   their training on simulator frames or shards with exact resume, prediction of point
//!   labels, and SemanticKITTI's scores of label folders.
//! * [`nn`]: the Veila U-Net from `veila-nn` as a [`crate::Denoiser`] ([`VeilaDenoiser`]).

#[cfg(feature = "sim")]
pub mod augment;
#[cfg(feature = "sim")]
pub mod bench_report;
pub mod bundle;
pub mod crossmodal_eval;
pub mod dataset;
pub mod dataset_gen;
pub mod encoder_train;
#[cfg(feature = "sim")]
pub mod feature_net_data;
pub mod generate;
pub mod mean;
pub mod nn;
pub mod pipeline;
pub mod progress;
#[cfg(feature = "sim")]
pub mod real_frames;
#[cfg(feature = "sim")]
pub mod realism;
pub mod recipe;
#[cfg(feature = "sim")]
pub mod report_files;
pub mod rig;
pub mod scoring;
pub mod segment;
#[cfg(feature = "sim")]
pub mod sim_examples;
#[cfg(feature = "sim")]
pub mod sim_recipe;
pub mod stage;
pub mod train;
pub mod train_config;
pub mod train_data;

pub use bundle::{
    Bundle, BundleConfig, Method, PriorConfig, ResidualConfig, Variant, attach_prior,
};
pub use dataset::{EncoderExample, ExampleSource, Examples, TrainView};
pub use encoder_train::{
    EncoderAugment, EncoderStep, train_small_cnn, train_small_cnn_from, varmap_tensors,
};
pub use generate::{CameraView, GenerateOptions, RESIDUAL_WEIGHT, SamplerChoice, ViewFeatures};
pub use mean::{
    MeanPredictor, predict_means, raw_residual, regression_weight, residual_scale,
    residual_scale_of, residual_target,
};
pub use nn::{NetCond, VeilaDenoiser};
pub use pipeline::{Scan, ScanPipeline};
pub use recipe::{
    Encoder, EncoderData, EncoderEvent, EncoderSource, Encoders, RecipeInput, RecipeOutcome,
    RecipeSettings, prepare_encoders, run_recipe,
};
// the pipeline's steps are private to the crate (a door that called them instead of the pipeline
// would get scans in the wrong frame)
pub use rig::{RigImage, RigView, load_view, point_colours, scan_points};
pub use stage::{Stage, stage_config};
pub use train::{
    BundleFit, BundleFitOutcome, DenoiserFit, DenoiserFitOutcome, DenoiserTraining, TrainExample,
    fit_bundle, fit_denoiser,
};

// the diffusion core bounds the time input's scale as the network does, without naming it
const _: () = assert!(
    crate::objective::MAX_TIME_INPUT_SCALE == veila_nn::config::MAX_TIME_INPUT_SCALE,
    "the time input's scale has one bound"
);
