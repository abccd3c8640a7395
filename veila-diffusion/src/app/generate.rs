//! Image-to-LiDAR generation with a [`Bundle`]: camera views in, panoramic range images out, in
//! the model's frame. The path from a rig's own images and calibration to scans in the LiDAR's own
//! frame is [`super::pipeline::ScanPipeline`], built on this.
//!
//! * [`Bundle::encode_views`] runs the frozen encoders on images already resized to the bundle's
//!   `image_width x image_height` (resize with an antialiasing filter, e.g. `image`'s triangle filter,
//!   and adapt the camera with [`veila_geom::PinholeCamera::resized`]; [`super::rig`] does both).
//! * [`Bundle::generate`] samples scans for one camera rig (one or more views); `samples > 1` draws
//!   several scans in one batch, each from its own noise stream of the seed (scan `i` is the
//!   same whatever the number of samples drawn with it).
//! * [`Bundle::inpaint`] regenerates the pixels a mask marks unknown and keeps the rest (RePaint).
//!
//! Everything is seeded: the same bundle, inputs and seed give the same scans.

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_geom::{PinholeCamera, RangeImage};
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::{ConditionInput, Denoiser as Net, GcmaGeometry, PreparedCondition};

use super::bundle::{Bundle, BundleConfig, ResidualConfig};
use super::nn::{NetCond, VeilaDenoiser};
use crate::error::{Error, Result};
use crate::noise::{NoiseSource, PerSample};
use crate::objective::Diffusion;
use crate::sampler::{RepaintConfig, Sampler, SamplerConfig, inpaint};

/// One camera view at the bundle's image size.
#[derive(Debug, Clone, Copy)]
pub struct CameraView<'a> {
    /// `image_width * image_height * 3` bytes, RGB, row-major.
    pub rgb: &'a [u8],
    /// The camera of this (resized) image, LiDAR frame to pixels.
    pub camera: &'a PinholeCamera,
}

/// Frozen encoder features of a set of views: per scale `[views, C_i, H_i, W_i]`.
#[derive(Debug, Clone)]
pub struct ViewFeatures {
    /// `E_s` pyramid.
    pub semantic: Option<Vec<Tensor>>,
    /// `E_d` pyramid.
    pub depth: Option<Vec<Tensor>>,
}

impl ViewFeatures {
    pub(crate) fn repeat(&self, n: usize) -> Result<ConditionInput> {
        let rep = |v: &Option<Vec<Tensor>>| -> Result<Option<Vec<Tensor>>> {
            v.as_ref()
                .map(|list| {
                    list.iter()
                        .map(|t| {
                            let parts = vec![t.clone(); n];
                            Ok(Tensor::cat(&parts, 0)?)
                        })
                        .collect()
                })
                .transpose()
        };
        Ok(ConditionInput {
            semantic: rep(&self.semantic)?,
            depth: rep(&self.depth)?,
            keep: None,
        })
    }

    /// Concatenates the features of several examples (same number of views each) along the batch.
    pub fn cat(items: &[&ViewFeatures]) -> Result<ConditionInput> {
        let join =
            |pick: &dyn Fn(&ViewFeatures) -> &Option<Vec<Tensor>>| -> Result<Option<Vec<Tensor>>> {
                let Some(first) = items.first().and_then(|f| pick(f).as_ref()) else {
                    return Ok(None);
                };
                (0..first.len())
                    .map(|s| {
                        let parts = items
                            .iter()
                            .map(|f| {
                                pick(f).as_ref().map(|v| v[s].clone()).ok_or_else(|| {
                                    Error::Data("examples disagree on which cues they have".into())
                                })
                            })
                            .collect::<Result<Vec<_>>>()?;
                        Ok(Tensor::cat(&parts, 0)?)
                    })
                    .collect::<Result<Vec<_>>>()
                    .map(Some)
            };
        Ok(ConditionInput {
            semantic: join(&|f| &f.semantic)?,
            depth: join(&|f| &f.depth)?,
            keep: None,
        })
    }
}

/// The interval of [`GenerateOptions::residual_weight`] (`--residual-weight` of the commands):
/// 0 (the mean network alone) to 1 (a full sample).
pub const RESIDUAL_WEIGHT: (f64, f64) = (0.0, 1.0);

/// Generation settings.
#[derive(Debug, Clone, PartialEq)]
pub struct GenerateOptions {
    /// Sampler, steps and guidance scale.
    pub sampler: SamplerConfig,
    /// Number of scans to draw for the rig.
    pub samples: usize,
    /// Seed of the initial noise and of stochastic samplers.
    pub seed: u64,
    /// Ignore the views and run the denoiser's unconditional branch (the one classifier-free
    /// guidance trains by condition dropout): the image-free baseline of the same network.
    pub unconditional: bool,
    /// Residual bundles only: how much of the sampled residual goes on top of the mean network's
    /// scan, in `[0, 1]`. `1` is a full sample, with the data's texture and spread; `0` is the
    /// conditional mean alone, the smallest pixel error but smooth (the same as 0 sampler steps).
    /// In between trades one for the other: for a calibrated sampler the squared pixel error grows
    /// as `1 + w²` times the mean's. Other bundles accept only `1`.
    pub residual_weight: f64,
}

impl GenerateOptions {
    /// One scan with `sampler`, seed 0, conditioned on the views, the full residual.
    pub fn new(sampler: SamplerConfig) -> Self {
        Self {
            sampler,
            samples: 1,
            seed: 0,
            unconditional: false,
            residual_weight: 1.0,
        }
    }

    /// Checks these options against `bundle`, as sampling with them does, for a door to call
    /// before any work: the sampler's settings ([`crate::SamplerConfig::validate`]; 0 steps, the mean
    /// network alone, only for a bundle with one, a residual's or a prior's, and an image-conditioned
    /// draw), at least one sample, and a [`residual_weight`](Self::residual_weight) in
    /// [`RESIDUAL_WEIGHT`], other than 1 only for a residual-diffusion bundle, and a
    /// [`start_t`](crate::SamplerConfig::start_t) only for a bundle with a prior.
    pub fn check(&self, bundle: &Bundle) -> Result<()> {
        self.sampler.validate()?;
        let residual = bundle.config.residual.is_some();
        if self.sampler.steps == 0 && bundle.config.mean_net().is_none() {
            return Err(Error::InvalidConfig {
                field: "steps",
                reason: "0 sampler steps (the mean network alone) need a bundle with a mean \
                         network: a residual-diffusion bundle or one with a prior"
                    .into(),
            });
        }
        if self.sampler.steps == 0 && (self.unconditional || !bundle.is_conditional()) {
            return Err(Error::InvalidConfig {
                field: "steps",
                reason:
                    "0 sampler steps (the mean network alone) need the image: the mean network \
                         has no unconditional branch"
                        .into(),
            });
        }
        if self.samples == 0 {
            return Err(Error::InvalidConfig {
                field: "samples",
                reason: "must be at least 1".into(),
            });
        }
        let w = self.residual_weight;
        let (lo, hi) = RESIDUAL_WEIGHT;
        if !(lo..=hi).contains(&w) {
            return Err(Error::InvalidConfig {
                field: "residual_weight",
                reason: format!("must be between {lo} and {hi}, got {w}"),
            });
        }
        if w != 1.0 && !residual {
            return Err(Error::InvalidConfig {
                field: "residual_weight",
                reason: format!(
                    "{w} needs a residual-diffusion bundle (one with a mean network to add a \
                     weighted residual to); leave it at 1"
                ),
            });
        }
        if self.sampler.start_t.is_some() && bundle.config.prior.is_none() {
            return Err(Error::InvalidConfig {
                field: "start_t",
                reason: "a start level needs a bundle with a prior mean network (`prior` in its \
                         bundle.json); leave it out to start from pure noise"
                    .into(),
            });
        }
        Ok(())
    }
}

/// A door's sampler choices over a bundle's own sampler (the `--sampler`, `--spacing`, `--steps`,
/// `--guidance` and `--start-t` of the commands, the keywords of the Python `generate`, a
/// benchmark's row): each `None` keeps what the bundle has.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SamplerChoice {
    /// Another update rule, with its own default spacing (`None`: the bundle's sampler).
    pub name: Option<crate::SamplerName>,
    /// Where the steps lie on the schedule.
    pub spacing: Option<crate::Spacing>,
    /// Network evaluations per branch.
    pub steps: Option<usize>,
    /// Classifier-free guidance scale.
    pub guidance: Option<f64>,
    /// Where a prior's draw starts ([`SamplerConfig::start_t`]); a bundle's own start level stays
    /// with another update rule.
    pub start_t: Option<f64>,
}

impl SamplerChoice {
    /// The sampler these choices make of `bundle`'s. An unconditional bundle samples at guidance
    /// 1 whatever is asked (it has no second branch; [`Self::ignores_guidance`] says when a door
    /// should tell its user). Nothing is validated here: [`GenerateOptions::check`] does that, the
    /// same way for every door.
    pub fn resolve(&self, bundle: &Bundle) -> SamplerConfig {
        let base = &bundle.config.sampler;
        let steps = self.steps.unwrap_or(base.steps);
        let mut cfg = match self.name {
            None => SamplerConfig {
                steps,
                ..base.clone()
            },
            Some(name) => name.config(steps),
        };
        if let Some(spacing) = self.spacing {
            cfg.spacing = spacing;
        }
        cfg.guidance_scale = self.guidance.unwrap_or(base.guidance_scale);
        cfg.start_t = self.start_t.or(base.start_t);
        if !bundle.is_conditional() {
            cfg.guidance_scale = 1.0;
        }
        cfg
    }

    /// Whether a guidance scale other than 1 was asked of an unconditional bundle, which
    /// [`Self::resolve`] sets to 1.
    pub fn ignores_guidance(&self, bundle: &Bundle) -> bool {
        !bundle.is_conditional() && self.guidance.is_some_and(|g| g != 1.0)
    }
}

impl GenerateOptions {
    /// The options of each batch when `self.samples` scans are drawn in batches of at most
    /// `max_batch` (memory then does not grow with the number of samples): `(index of the batch's
    /// first scan, options)`. Batch 0 keeps `self.seed`, so a run of up to `max_batch` samples draws
    /// exactly what one batch of all of them would; later batches a SplitMix64 mix of the seed and the batch index. `veila
    /// generate` draws its `--samples` this way (batches of 8), so the same options give the same
    /// scans there and here.
    pub fn batches(&self, max_batch: usize) -> impl Iterator<Item = (usize, GenerateOptions)> + '_ {
        let max_batch = max_batch.max(1);
        (0..self.samples.div_ceil(max_batch)).map(move |b| {
            let first = b * max_batch;
            (
                first,
                GenerateOptions {
                    samples: max_batch.min(self.samples - first),
                    seed: batch_seed(self.seed, b),
                    ..self.clone()
                },
            )
        })
    }
}

/// The noise seed of batch `b` of [`GenerateOptions::batches`]: batch 0 keeps `seed`, later
/// batches a SplitMix64 mix of the seed and the batch index.
fn batch_seed(seed: u64, batch: usize) -> u64 {
    if batch == 0 {
        return seed;
    }
    let mut z = seed ^ (batch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Generation with a bundle on views already fitted to it. These methods work in the model's
/// frame: the cameras are taken as they are and the scans come out on the bundle's grid as
/// sampled. [`super::pipeline::ScanPipeline`] is the path from a rig's own images and cameras to
/// scans in the LiDAR's own frame, and what the doors (CLI, Python, example) call.
impl Bundle {
    /// Runs the frozen encoders on views at the bundle's image size.
    pub fn encode_views(&self, views: &[CameraView<'_>]) -> Result<ViewFeatures> {
        encode_views(
            &self.config,
            self.semantic.as_ref(),
            self.depth.as_ref(),
            views,
            self.denoiser_device(),
        )
    }

    /// A retrieval descriptor of one view: the coarsest feature map of each frozen encoder,
    /// flattened (the spatial layout stays: where things are matters), each scaled to unit norm.
    /// Images whose descriptors are near by cosine look alike to the model (the retrieval baseline
    /// picks the training scan of the nearest image).
    pub fn image_descriptor(&self, view: CameraView<'_>) -> Result<Vec<f32>> {
        let f = self.encode_views(&[view])?;
        let mut out = Vec::new();
        for pyramid in [&f.semantic, &f.depth].into_iter().flatten() {
            let Some(last) = pyramid.last() else { continue };
            let v = last.flatten_all()?.to_vec1::<f32>()?;
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
            out.extend(v.iter().map(|x| x / n));
        }
        Ok(out)
    }

    /// Draws `options.samples` scans for one camera rig, in the model's frame. `on_step(done,
    /// total)` is called after each sampler step. Views are ignored by unconditional bundles.
    /// A bundle with a prior starts at the sampler's [`start_t`](crate::SamplerConfig::start_t)
    /// from its mean network's scan; an unconditional draw
    /// ([`GenerateOptions::unconditional`]) has no image for it and starts from pure noise.
    pub fn generate(
        &self,
        views: &[CameraView<'_>],
        options: &GenerateOptions,
        on_step: impl FnMut(usize, usize),
    ) -> Result<Vec<RangeImage>> {
        sample(self, views, options, None, on_step)
    }

    /// Keeps the pixels where `known_mask` (`rows * cols`, row-major) is true at the values of
    /// `known` and regenerates the rest, consistent with the kept part and the views (RePaint; the
    /// sampler must be DDPM or DDIM). In the model's frame, like [`Bundle::generate`]. RePaint
    /// runs the whole schedule: a prior's start level is not used.
    pub fn inpaint(
        &self,
        views: &[CameraView<'_>],
        known: &RangeImage,
        known_mask: &[bool],
        options: &GenerateOptions,
        repaint: &RepaintConfig,
    ) -> Result<Vec<RangeImage>> {
        check_inpainting_input(self, known, known_mask)?;
        sample(
            self,
            views,
            options,
            Some((known, known_mask, repaint)),
            |_, _| {},
        )
    }
}

/// A scan to inpaint is on the bundle's grid and its mask has a value per pixel.
pub(crate) fn check_inpainting_input(
    bundle: &Bundle,
    known: &RangeImage,
    known_mask: &[bool],
) -> Result<()> {
    let (h, w) = bundle.grid();
    if (known.rows as usize, known.cols as usize) != (h, w) || known_mask.len() != h * w {
        return Err(Error::Shape {
            what: "inpainting input",
            expected: format!("a {h} x {w} scan and {} mask values", h * w),
            got: format!(
                "a {} x {} scan and {} mask values",
                known.rows,
                known.cols,
                known_mask.len()
            ),
        });
    }
    Ok(())
}

/// Draws scans for [`Bundle::generate`] and [`Bundle::inpaint`] (`inpainting`: the known scan,
/// its mask and the RePaint settings).
fn sample(
    bundle: &Bundle,
    views: &[CameraView<'_>],
    options: &GenerateOptions,
    inpainting: Option<(&RangeImage, &[bool], &RepaintConfig)>,
    mut on_step: impl FnMut(usize, usize),
) -> Result<Vec<RangeImage>> {
    let conditional = check_options(bundle, views, options)?;
    let mut rng = per_sample_rng(options.seed, options.samples);
    let known = encode_known(bundle, inpainting, options.samples)?;
    let batch = Batch::new(bundle, views, options, conditional)?;
    // the mean network's scan: a residual bundle's mean, or where a prior's draw starts
    // (`check_options` allows a start level only with a prior; an unconditional draw has no image
    // for it, and RePaint runs the whole schedule)
    let start_t = (conditional && inpainting.is_none())
        .then_some(options.sampler.start_t)
        .flatten();
    // the mean network alone: 0 steps (any bundle with one), or a residual's weight 0
    let mean_alone = options.sampler.steps == 0 || options.residual_weight == 0.0;
    let mean = if bundle.config.residual.is_some() || start_t.is_some() || mean_alone {
        batch.mean_pass(&mut rng)?
    } else {
        None
    };
    let x = match mean {
        Some(mu) if mean_alone => {
            on_step(0, 0);
            mu
        }
        mean => {
            let (mean, start) = match start_t {
                Some(t) => (None, mean.map(|mu| (mu, t))),
                None => (mean, None),
            };
            let repaint = inpainting.map(|(_, _, r)| r).zip(known.as_ref());
            batch.denoise(
                mean.as_ref(),
                start.as_ref(),
                repaint,
                &mut rng,
                &mut on_step,
            )?
        }
    };
    let x = paste_known(x, known.as_ref())?;
    bundle.config.encoding.decode_batch(&x)
}

/// The options against the bundle ([`GenerateOptions::check`]) and views for an image-conditioned
/// bundle. Returns whether the draw is image-conditioned.
fn check_options(
    bundle: &Bundle,
    views: &[CameraView<'_>],
    options: &GenerateOptions,
) -> Result<bool> {
    options.check(bundle)?;
    let conditional = bundle.is_conditional() && !options.unconditional;
    if conditional && views.is_empty() {
        return Err(Error::InvalidConfig {
            field: "views",
            reason: "this bundle is image-conditioned: give at least one camera view".into(),
        });
    }
    Ok(conditional)
}

/// One noise stream per sample (stream `i` of the seed): a scan does not depend on how many
/// others are drawn with it, and a single scan draws what the seed's first stream gives.
fn per_sample_rng(seed: u64, samples: usize) -> PerSample<ChaCha8Rng> {
    PerSample(
        (0..samples as u64)
            .map(|i| {
                let mut r = ChaCha8Rng::seed_from_u64(seed);
                r.set_stream(i);
                r
            })
            .collect(),
    )
}

/// Inpainting: the known scan, encoded for each of `samples`, and its mask (1 = keep).
fn encode_known(
    bundle: &Bundle,
    inpainting: Option<(&RangeImage, &[bool], &RepaintConfig)>,
    samples: usize,
) -> Result<Option<(Tensor, Tensor)>> {
    let Some((scan, mask, _)) = inpainting else {
        return Ok(None);
    };
    let device = bundle.denoiser_device();
    let (h, w) = bundle.grid();
    let view: Vec<&RangeImage> = vec![scan; samples];
    let x0 = bundle.config.encoding.encode_batch(&view, device)?;
    let m: Vec<f32> = mask.iter().map(|&k| if k { 1.0 } else { 0.0 }).collect();
    Ok(Some((x0, Tensor::from_vec(m, (1, 1, h, w), device)?)))
}

/// The known pixels exactly as given (a residual bundle's sum would round them).
fn paste_known(x: Tensor, known: Option<&(Tensor, Tensor)>) -> Result<Tensor> {
    let Some((x0, m)) = known else {
        return Ok(x);
    };
    let m = m.broadcast_as(x.shape())?;
    Ok((x0.broadcast_mul(&m)? + x.broadcast_mul(&m.affine(-1.0, 1.0)?)?)?)
}

/// An image condition as one network takes it (its GCMA geometry when it has GCMA, and the
/// views' features).
type Condition = Option<(Option<GcmaGeometry>, ConditionInput)>;

/// `condition` prepared for `net` (its own CACM weights).
fn prepare<'g>(net: &Net, condition: &'g Condition) -> Result<Option<PreparedCondition<'g>>> {
    match condition {
        Some((g, f)) => Ok(Some(net.prepare_condition(f, g.as_ref())?)),
        None => Ok(None),
    }
}

/// What the steps of one [`sample`] draw share: the bundle, the options, the batch's shape and the
/// views' features.
struct Batch<'a> {
    bundle: &'a Bundle,
    options: &'a GenerateOptions,
    device: Device,
    /// `[samples, channels, rows, cols]`.
    shape: [usize; 4],
    /// Camera views the networks take (1 when the draw is unconditional).
    views: usize,
    /// The views' features, repeated for every sample (`None`: unconditional).
    features: Option<ConditionInput>,
    cameras: Vec<PinholeCamera>,
}

impl<'a> Batch<'a> {
    /// Encodes the views when the draw is `conditional`.
    fn new(
        bundle: &'a Bundle,
        views: &[CameraView<'_>],
        options: &'a GenerateOptions,
        conditional: bool,
    ) -> Result<Self> {
        let n = options.samples;
        let (h, w) = bundle.grid();
        let features = if conditional {
            Some(bundle.encode_views(views)?.repeat(n)?)
        } else {
            None
        };
        Ok(Self {
            bundle,
            options,
            device: bundle.denoiser_device().clone(),
            shape: [n, bundle.config.channels(), h, w],
            views: if conditional { views.len() } else { 1 },
            features,
            cameras: views.iter().map(|v| *v.camera).collect(),
        })
    }

    fn residual(&self) -> Option<&'a ResidualConfig> {
        self.bundle.config.residual.as_ref()
    }

    /// One value per channel as a `[1, C, 1, 1]` tensor.
    fn per_channel(&self, values: &[f32]) -> Result<Tensor> {
        Ok(Tensor::from_slice(
            values,
            (1, self.shape[1], 1, 1),
            &self.device,
        )?)
    }

    /// The image condition of one network (its GCMA geometry when it has GCMA).
    fn condition(&self, net: &Net) -> Result<Condition> {
        let Some(f) = &self.features else {
            return Ok(None);
        };
        let geometry = match &net.config().conditioning {
            Some(cc) if cc.gcma.is_some() => {
                Some(net.geometry(&self.cameras, &self.bundle.config.epipolar, &self.device)?)
            }
            _ => None,
        };
        Ok(Some((geometry, f.clone())))
    }

    /// The mean network's one pass (`None` without one): a residual bundle's, or a prior's.
    fn mean_pass(&self, rng: &mut PerSample<ChaCha8Rng>) -> Result<Option<Tensor>> {
        let Some(mnet) = self.bundle.mean_for_views(self.views)? else {
            return Ok(None);
        };
        let condition = self.condition(&mnet)?;
        let image = prepare(&mnet, &condition)?;
        let mdiff = Diffusion::new(ResidualConfig::mean_diffusion())?;
        let msampler = Sampler::new(
            &mdiff,
            SamplerConfig {
                steps: 1,
                guidance_scale: 1.0,
                ..self.options.sampler.clone()
            },
        )?;
        let zeros = Tensor::zeros(&self.shape, DType::F32, &self.device)?;
        let cond = NetCond { image, mean: None };
        Ok(Some(msampler.sample_from(
            &VeilaDenoiser::new(mnet),
            zeros,
            Some(&cond),
            rng,
            |_| {},
        )?))
    }

    /// The denoiser's sampler run from noise, or from a prior's scan `μ` at level `t` (`start`:
    /// `α_t·μ + σ_t·ε`), or RePaint on the known scan (`repaint`: its settings and the encoded
    /// scan and mask), then a residual bundle's residual added to its mean (`mean`).
    fn denoise(
        &self,
        mean: Option<&Tensor>,
        start: Option<&(Tensor, f64)>,
        repaint: Option<(&RepaintConfig, &(Tensor, Tensor))>,
        rng: &mut PerSample<ChaCha8Rng>,
        on_step: &mut impl FnMut(usize, usize),
    ) -> Result<Tensor> {
        let diffusion = Diffusion::new(self.bundle.config.diffusion.clone())?;
        let sampler = self.sampler(&diffusion, mean)?;
        let net = self.bundle.net_for_views(self.views)?;
        let condition = self.condition(&net)?;
        let cond = NetCond {
            image: prepare(&net, &condition)?,
            mean: mean.cloned(),
        };
        let cond = (cond.image.is_some() || cond.mean.is_some()).then_some(cond);
        let model = VeilaDenoiser::new(net);
        let x = match (repaint, start) {
            (None, Some((mu, t))) => {
                let level = diffusion.schedule().level(*t);
                let eps = rng.noise(&self.shape, &self.device)?;
                let x_t = diffusion.q_sample(mu, &eps, &vec![level; self.shape[0]])?;
                sampler.sample_from_level(&model, x_t, level, cond.as_ref(), rng, |info| {
                    on_step(info.index + 1, info.total)
                })?
            }
            (None, None) => {
                let x_t = rng.noise(&self.shape, &self.device)?;
                sampler.sample_from(&model, x_t, cond.as_ref(), rng, |info| {
                    on_step(info.index + 1, info.total)
                })?
            }
            (Some((repaint, (x0, m))), _) => {
                let x0 = self.known_residual(x0, mean)?;
                inpaint(&sampler, &model, &x0, m, cond.as_ref(), repaint, rng)?
            }
        };
        self.add_mean(x, mean)
    }

    /// The denoiser's sampler; a residual's clip is the data's `[-c, c]`, mapped to each pixel's
    /// residual interval.
    fn sampler<'d>(&self, diffusion: &'d Diffusion, mean: Option<&Tensor>) -> Result<Sampler<'d>> {
        let mut sampler = Sampler::new(diffusion, self.options.sampler.clone())?;
        if let (Some(mu), Some(r), Some(clip)) =
            (mean, self.residual(), self.options.sampler.clip_x0)
        {
            let s = self.per_channel(&r.scale)?;
            let lo = mu.affine(-1.0, -clip)?.broadcast_div(&s)?;
            let hi = mu.affine(-1.0, clip)?.broadcast_div(&s)?;
            sampler = sampler.with_x0_bounds(lo, hi);
        }
        Ok(sampler)
    }

    /// What a residual denoiser inpaints: the known scan's scaled residual (the scan itself for
    /// direct diffusion).
    fn known_residual(&self, x0: &Tensor, mean: Option<&Tensor>) -> Result<Tensor> {
        match (mean, self.residual()) {
            (Some(mu), Some(r)) => Ok((x0 - mu)?.broadcast_div(&self.per_channel(&r.scale)?)?),
            _ => Ok(x0.clone()),
        }
    }

    /// `μ + weight · scale · x` for a residual bundle (`x` itself for direct diffusion).
    fn add_mean(&self, x: Tensor, mean: Option<&Tensor>) -> Result<Tensor> {
        match (mean, self.residual()) {
            (Some(mu), Some(r)) => {
                let weight = self.options.residual_weight as f32;
                let scale: Vec<f32> = r.scale.iter().map(|&s| s * weight).collect();
                Ok((mu + x.broadcast_mul(&self.per_channel(&scale)?)?)?)
            }
            _ => Ok(x),
        }
    }
}

/// The frozen encoders' features of views at the bundle's image size (shared with training).
pub(crate) fn encode_views(
    cfg: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    views: &[CameraView<'_>],
    device: &Device,
) -> Result<ViewFeatures> {
    let (ih, iw) = (cfg.image_height, cfg.image_width);
    for (i, v) in views.iter().enumerate() {
        if v.rgb.len() != ih * iw * 3
            || (v.camera.width as usize, v.camera.height as usize) != (iw, ih)
        {
            return Err(Error::Shape {
                what: "camera view",
                expected: format!("a {iw} x {ih} RGB image and a camera of that size"),
                got: format!(
                    "view {i}: {} bytes, camera {} x {}",
                    v.rgb.len(),
                    v.camera.width,
                    v.camera.height
                ),
            });
        }
    }
    let images: Vec<&[u8]> = views.iter().map(|v| v.rgb).collect();
    let cameras: Vec<PinholeCamera> = views.iter().map(|v| *v.camera).collect();
    // each encoder gets the images fitted to it by its kind (a patch encoder: the nearest
    // multiple of its patch, resampled as its reference processor does); a small CNN with the
    // ground prior gets each view's channel from that view's camera
    let run = |e: Option<&AnyEncoder>| -> Result<Option<Vec<Tensor>>> {
        e.map(|e| {
            Ok(
                e.encode_rgb8_with_cameras(&images, Some(&cameras), ih, iw, device)?
                    .into_iter()
                    .map(|t| t.detach())
                    .collect(),
            )
        })
        .transpose()
    };
    Ok(ViewFeatures {
        semantic: run(semantic)?,
        depth: run(depth)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_cover_every_sample_once_and_keep_the_first_seed() {
        let options = GenerateOptions {
            samples: 20,
            seed: 42,
            ..GenerateOptions::new(SamplerConfig::ddpm(4))
        };
        let batches: Vec<(usize, GenerateOptions)> = options.batches(8).collect();
        let firsts: Vec<usize> = batches.iter().map(|(f, _)| *f).collect();
        let sizes: Vec<usize> = batches.iter().map(|(_, o)| o.samples).collect();
        assert_eq!(firsts, [0, 8, 16]);
        assert_eq!(sizes, [8, 8, 4]);
        // batch 0 draws what one batch of all samples would; the others their own noise
        assert_eq!(batches[0].1.seed, 42);
        let mut seeds: Vec<u64> = batches.iter().map(|(_, o)| o.seed).collect();
        seeds.sort_unstable();
        seeds.dedup();
        assert_eq!(seeds.len(), 3);
        // everything but the count and the seed is the run's
        for (_, o) in &batches {
            assert_eq!(o.sampler, options.sampler);
            assert_eq!(o.residual_weight, options.residual_weight);
        }
        // a run that fits one batch is that batch
        let small = GenerateOptions {
            samples: 5,
            ..options.clone()
        };
        let one: Vec<_> = small.batches(8).collect();
        assert_eq!(one, [(0, small.clone())]);
        assert_eq!(
            options.batches(0).count(),
            20,
            "a batch holds at least one scan"
        );
    }
}
