//! One training stage of a bundle ([`Stage`]: the denoiser or the mean network, and its config,
//! [`stage_config`]), and what the two stages' training and the frozen mean network share: the
//! camera views and GCMA of a network, the frozen encoders' features of a batch of examples, and
//! the per-sample rig condition.

use candle_core::Device;
use veila_geom::PinholeCamera;
use veila_nn::Denoiser as Net;
use veila_nn::encoders::kind::AnyEncoder;

use super::bundle::{BundleConfig, ResidualConfig};
use super::dataset::{Rigs, TrainExample};
use super::generate::{ViewFeatures, encode_views};
use crate::error::{Error, Result};

/// Which network of a bundle a training run fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// The denoiser (`config.denoiser` with `config.diffusion`). For a residual bundle every
    /// example needs its mean prediction ([`super::DenoiserFit::means`]) and the targets become the
    /// scaled residuals ([`super::residual_target`]).
    Denoiser,
    /// The mean network of a residual bundle (`residual.mean_net`, one-pass regression), with
    /// the range and intensity of dropped rays left out of the loss ([`super::regression_weight`]).
    Mean,
}

impl Stage {
    /// Its name in progress lines: `denoiser` or `mean network`.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Denoiser => "denoiser",
            Stage::Mean => "mean network",
        }
    }
}

/// The network config and process of one training stage of `config`.
pub fn stage_config(
    config: &BundleConfig,
    stage: Stage,
) -> Result<(veila_nn::DenoiserConfig, crate::DiffusionConfig)> {
    match stage {
        Stage::Denoiser => Ok((config.denoiser.clone(), config.diffusion.clone())),
        Stage::Mean => {
            let r = config.residual.as_ref().ok_or_else(|| {
                Error::Data("this bundle has no mean network (not residual diffusion)".into())
            })?;
            Ok((r.mean_net.clone(), ResidualConfig::mean_diffusion()))
        }
    }
}

/// How many camera views `net` takes (1 when unconditional).
pub(super) fn num_views(net: &Net) -> usize {
    net.config()
        .conditioning
        .as_ref()
        .map_or(1, |c| c.num_views.max(1))
}

/// Whether `net` has GCMA (and so needs the cameras' geometry).
pub(super) fn has_gcma(net: &Net) -> bool {
    net.config()
        .conditioning
        .as_ref()
        .is_some_and(|c| c.gcma.is_some())
}

/// The frozen encoders' features of `examples` (their first `views` camera views), as one batch.
pub(super) fn encode_examples(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    examples: &[TrainExample],
    views: usize,
    device: &Device,
) -> Result<veila_nn::ConditionInput> {
    let feats = examples
        .iter()
        .map(|ex| encode_views(config, semantic, depth, &ex.views(views)?, device))
        .collect::<Result<Vec<_>>>()?;
    let refs: Vec<&ViewFeatures> = feats.iter().collect();
    ViewFeatures::cat(&refs)
}

/// `input` prepared for `net`, each sample attending with the GCMA geometry of its rig
/// (`cameras[b]`, one camera per view), built the first time the rig appears in `rigs`
/// (`None`: the network has no GCMA).
pub(super) fn rig_condition<'g>(
    net: &Net,
    rigs: Option<&'g Rigs>,
    input: &veila_nn::ConditionInput,
    cameras: &[&[PinholeCamera]],
    epipolar: &veila_geom::EpipolarConfig,
    device: &Device,
) -> Result<veila_nn::PreparedCondition<'g>> {
    let Some(rigs) = rigs else {
        return Ok(net.prepare_condition(input, None)?);
    };
    let geoms = cameras
        .iter()
        .map(|c| rigs.get(c, || Ok(net.geometry(c, epipolar, device)?)))
        .collect::<Result<Vec<_>>>()?;
    Ok(net.prepare_condition_per_sample(input, &geoms)?)
}
