//! Image-to-LiDAR generation with a [`Bundle`]: camera views in, panoramic range images out.
//!
//! * [`Bundle::encode_views`] runs the frozen encoders on images already resized to the bundle's
//!   `image_width x image_height` (resize with an antialiasing filter, e.g. `image`'s triangle filter,
//!   and adapt the camera with [`veila_geom::PinholeCamera::resized`]; [`super::rig`] does both).
//! * [`Bundle::generate`] samples scans for one camera rig (one or more views); `samples > 1` draws
//!   several scans in one batch.
//! * [`Bundle::inpaint`] regenerates the pixels a mask marks unknown and keeps the rest (RePaint).
//!
//! Everything is seeded: the same bundle, inputs and seed give the same scans.

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use veila_geom::{PinholeCamera, RangeImage};
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::{ConditionInput, Denoiser as Net, GcmaGeometry};

use super::bundle::{Bundle, BundleConfig};
use super::nn::{NetCond, VeilaDenoiser};
use crate::error::{Error, Result};
use crate::noise::randn;
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
}

/// Draws scans for [`Bundle::generate`] and [`Bundle::inpaint`] (`inpainting`: the known scan,
/// its mask and the RePaint settings).
pub(crate) fn sample(
    bundle: &Bundle,
    views: &[CameraView<'_>],
    options: &GenerateOptions,
    inpainting: Option<(&RangeImage, &[bool], &RepaintConfig)>,
    mut on_step: impl FnMut(usize, usize),
) -> Result<Vec<RangeImage>> {
    if options.samples == 0 {
        return Err(Error::InvalidConfig {
            field: "samples",
            reason: "must be at least 1".into(),
        });
    }
    let device = bundle.denoiser_device().clone();
    let (h, w) = bundle.grid();
    let c = bundle.config.channels();
    let n = options.samples;
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let conditional = bundle.is_conditional() && !options.unconditional;
    if conditional && views.is_empty() {
        return Err(Error::InvalidConfig {
            field: "views",
            reason: "this bundle is image-conditioned: give at least one camera view".into(),
        });
    }
    let nv = if conditional { views.len() } else { 1 };
    let residual = bundle.config.residual.as_ref();
    if options.sampler.steps == 0 && residual.is_none() {
        return Err(Error::InvalidConfig {
            field: "steps",
            reason: "0 sampler steps work only for residual bundles (their mean network alone)"
                .into(),
        });
    }
    let weight = options.residual_weight;
    if !(0.0..=1.0).contains(&weight) {
        return Err(Error::InvalidConfig {
            field: "residual_weight",
            reason: format!("must be in [0, 1], got {weight}"),
        });
    }
    if weight != 1.0 && residual.is_none() {
        return Err(Error::InvalidConfig {
            field: "residual_weight",
            reason: "only residual-diffusion bundles have a residual to weight".into(),
        });
    }
    // inpainting: the known scan, encoded, and its mask (1 = keep)
    let known = match inpainting {
        Some((scan, mask, _)) => {
            let view: Vec<&RangeImage> = vec![scan; n];
            let x0 = bundle.config.encoding.encode_batch(&view, &device)?;
            let m: Vec<f32> = mask.iter().map(|&k| if k { 1.0 } else { 0.0 }).collect();
            Some((x0, Tensor::from_vec(m, (1, 1, h, w), &device)?))
        }
        None => None,
    };
    let feats = if conditional {
        Some(bundle.encode_views(views)?.repeat(n)?)
    } else {
        None
    };
    let cams: Vec<PinholeCamera> = views.iter().map(|v| *v.camera).collect();
    // the image condition of one network (its own CACM weights; GCMA geometry when it has it)
    let condition = |net: &Net| -> Result<Option<(Option<GcmaGeometry>, ConditionInput)>> {
        let Some(f) = &feats else { return Ok(None) };
        let geometry = match &net.config().conditioning {
            Some(cc) if cc.gcma.is_some() => {
                Some(net.geometry(&cams, &bundle.config.epipolar, &device)?)
            }
            _ => None,
        };
        Ok(Some((geometry, f.clone())))
    };
    // residual diffusion: the mean network's one pass first
    let mean = match bundle.mean_for_views(nv)? {
        Some(mnet) => {
            let prep = condition(&mnet)?;
            let image = match &prep {
                Some((g, f)) => Some(mnet.prepare_condition(f, g.as_ref())?),
                None => None,
            };
            let mdiff = Diffusion::new(super::bundle::ResidualConfig::mean_diffusion())?;
            let msampler = Sampler::new(
                &mdiff,
                SamplerConfig {
                    steps: 1,
                    guidance_scale: 1.0,
                    ..options.sampler.clone()
                },
            )?;
            let zeros = Tensor::zeros((n, c, h, w), DType::F32, &device)?;
            let cond = NetCond { image, mean: None };
            Some(msampler.sample_from(
                &VeilaDenoiser::new(mnet),
                zeros,
                Some(&cond),
                &mut rng,
                |_| {},
            )?)
        }
        None => None,
    };
    let x = match (&mean, residual) {
        (Some(mu), Some(_)) if options.sampler.steps == 0 || weight == 0.0 => {
            on_step(0, 0);
            mu.clone()
        }
        _ => {
            let diffusion = Diffusion::new(bundle.config.diffusion.clone())?;
            let sampler = Sampler::new(&diffusion, options.sampler.clone())?;
            let net = bundle.net_for_views(nv)?;
            let prep = condition(&net)?;
            let image = match &prep {
                Some((g, f)) => Some(net.prepare_condition(f, g.as_ref())?),
                None => None,
            };
            let cond = NetCond {
                image,
                mean: mean.clone(),
            };
            let cond = (cond.image.is_some() || cond.mean.is_some()).then_some(cond);
            let model = VeilaDenoiser::new(net);
            let x = match inpainting {
                None => {
                    let x_t = randn(&mut rng, &[n, c, h, w], &device)?;
                    sampler.sample_from(&model, x_t, cond.as_ref(), &mut rng, |info| {
                        on_step(info.index + 1, info.total)
                    })?
                }
                Some((_, _, repaint)) => {
                    let (x0, m) = known.as_ref().expect("encoded above");
                    // a residual denoiser inpaints the known scan's scaled residual
                    let x0 = match (&mean, residual) {
                        (Some(mu), Some(r)) => {
                            let s = Tensor::from_slice(&r.scale, (1, c, 1, 1), &device)?;
                            (x0 - mu)?.broadcast_div(&s)?
                        }
                        _ => x0.clone(),
                    };
                    inpaint(&sampler, &model, &x0, m, cond.as_ref(), repaint, &mut rng)?
                }
            };
            match (&mean, residual) {
                (Some(mu), Some(r)) => {
                    let scale: Vec<f32> = r.scale.iter().map(|&s| s * weight as f32).collect();
                    let s = Tensor::from_slice(&scale, (1, c, 1, 1), &device)?;
                    (mu + x.broadcast_mul(&s)?)?
                }
                _ => x,
            }
        }
    };
    // the known pixels exactly as given (a residual bundle's sum would round them)
    let x = match &known {
        Some((x0, m)) => {
            let m = m.broadcast_as(x.shape())?;
            (x0.broadcast_mul(&m)? + x.broadcast_mul(&m.affine(-1.0, 1.0)?)?)?
        }
        None => x,
    };
    bundle.config.encoding.decode_batch(&x)
}
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
