//! The small CNN encoders' training ([`train_small_cnn`]): sparse depth and semantic supervision
//! from the LiDAR, with the optional image augmentation ([`EncoderAugment`]), seeded per step and
//! slot; and [`varmap_tensors`], the trained weights as named tensors.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::PinholeCamera;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig, SmallCnnLossConfig};

use super::dataset::EncoderExample;
use crate::error::{Error, Result};
use crate::trainer::{AdamW, ParamsAdamW};

/// What one encoder training step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderStep {
    /// Steps done.
    pub step: usize,
    /// Total loss of the batch.
    pub loss: f32,
}

/// Image augmentation of encoder training (issue 18): a random crop-and-zoom with the targets
/// resampled alike, then the photometric pipeline of [`veila_data::augment`] (exposure,
/// vignetting, blur, white balance, noise, colour jitter, JPEG). Depth targets are divided by the
/// zoom `s`: an object zoomed `s` times looks as it would `s` times nearer through the training
/// camera, and the encoder keeps answering for that camera's focal length.
///
/// The example's camera (when it has one) follows the crop: the cropped intrinsics
/// ([`veila_data::augment::CropZoom::camera`]) with the camera frame scaled by `1 / s`, the same
/// "s times nearer" as the depth targets, so that a ground prior computed from it
/// ([`veila_nn::encoders::ground`]) agrees with them: the flat ground's depth through the
/// returned camera is the true one divided by `s`, at the pixels where the crop put it.
///
/// Each example of each update draws its own parameters from `(seed, update, slot)`, so a run is
/// reproducible and the same image is augmented differently every time it is drawn.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EncoderAugment {
    /// Photometric ranges and probabilities.
    pub photometric: veila_data::augment::Photometric,
    /// Crop-and-zoom probability and zoom range.
    pub crop_zoom: veila_data::augment::CropZoomRange,
}

impl EncoderAugment {
    /// Augments one `h x w` example in place with the parameters drawn from `seed`.
    pub fn apply(&self, ex: &mut EncoderExample, (h, w): (usize, usize), seed: u64) -> Result<()> {
        let img = veila_data::augment::rgb_image_from_raw(
            w as u32,
            h as u32,
            std::mem::take(&mut ex.rgb),
        )?;
        let crop = self.crop_zoom.draw(w as u32, h as u32, seed)?;
        let img = if crop != veila_data::augment::CropZoom::identity(w as u32, h as u32) {
            if let Some(cam) = ex.camera.as_mut() {
                let cropped = crop.camera(cam)?;
                *cam = PinholeCamera {
                    cam_from_lidar: glam::Mat4::from_scale(glam::Vec3::splat(1.0 / crop.scale))
                        * cropped.cam_from_lidar,
                    ..cropped
                };
            }
            if let Some(l) = ex.labels.as_mut() {
                *l = crop.resample_nearest(l, w as u32, h as u32)?;
            }
            if !ex.depth_m.is_empty() {
                let inv = 1.0 / crop.scale;
                ex.depth_m = crop
                    .resample_nearest(&ex.depth_m, w as u32, h as u32)?
                    .into_iter()
                    .map(|d| d * inv)
                    .collect();
            }
            crop.resample_rgb(&img)?
        } else {
            img
        };
        ex.rgb = self
            .photometric
            .augment(&img, seed ^ 0x6a09_e667_f3bc_c909)?
            .into_raw();
        Ok(())
    }
}

fn augment_seed(seed: u64, step: usize, slot: usize) -> u64 {
    let mut z = seed
        ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (slot as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Trains a [`SmallCnn`] on images with per-pixel targets: `images[i]` is `h * w * 3` RGB bytes,
/// `labels[i]` (class ids of the learning map) and/or `depth_m[i]` (metres, 0 = no ground truth)
/// `h * w` values, `cameras[i]` the image's camera (needed when `cfg` has the ground prior,
/// ignored otherwise). AdamW with a cosine learning rate, seeded batches; returns the network and its
/// `VarMap`. With `augment`, every drawn example is augmented first ([`EncoderAugment`]).
/// [`train_small_cnn_from`] reads the examples on demand instead.
#[allow(clippy::too_many_arguments)]
pub fn train_small_cnn(
    cfg: &SmallCnnConfig,
    images: &[Vec<u8>],
    labels: Option<&[Vec<u32>]>,
    depth_m: Option<&[Vec<f32>]>,
    cameras: Option<&[PinholeCamera]>,
    hw: (usize, usize),
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    augment: Option<&EncoderAugment>,
    device: &Device,
    on_step: impl FnMut(EncoderStep),
) -> Result<(SmallCnn, VarMap)> {
    if let Some(c) = cameras
        && c.len() != images.len()
    {
        return Err(Error::Data(format!(
            "encoder training: {} images but {} cameras",
            images.len(),
            c.len()
        )));
    }
    let get = |i: usize| -> Result<EncoderExample> {
        Ok(EncoderExample {
            rgb: images[i].clone(),
            camera: cameras.map(|c| c[i]),
            labels: labels.map(|l| l[i].clone()),
            depth_m: depth_m.map(|d| d[i].clone()).unwrap_or_default(),
        })
    };
    train_small_cnn_from(
        cfg,
        images.len(),
        &get,
        (labels.is_some(), depth_m.is_some()),
        hw,
        steps,
        batch_size,
        lr,
        seed,
        augment,
        device,
        on_step,
    )
}

/// [`train_small_cnn`] on `n` examples read by `get` when a batch needs them (bounded memory);
/// `(labels, depth)` says which targets the loss uses. The same examples give the same weights.
#[allow(clippy::too_many_arguments)]
pub fn train_small_cnn_from(
    cfg: &SmallCnnConfig,
    n: usize,
    get: &dyn Fn(usize) -> Result<EncoderExample>,
    (use_labels, use_depth): (bool, bool),
    (h, w): (usize, usize),
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    augment: Option<&EncoderAugment>,
    device: &Device,
    mut on_step: impl FnMut(EncoderStep),
) -> Result<(SmallCnn, VarMap)> {
    if n == 0 || batch_size == 0 {
        return Err(Error::Data(
            "encoder training needs images and a batch size".into(),
        ));
    }
    let varmap = VarMap::new();
    let net = SmallCnn::new(
        cfg,
        veila_nn::seeded_var_builder(&varmap, seed, DType::F32, device),
    )?;
    let vars: Vec<(String, candle_core::Var)> = {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
        let mut v: Vec<_> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    };
    let mut opt = AdamW::new(
        vars,
        ParamsAdamW {
            lr,
            weight_decay: 1e-4,
            ..ParamsAdamW::default()
        },
    )?;
    let loss_cfg = SmallCnnLossConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for step in 0..steps {
        let progress = step as f64 / steps.max(1) as f64;
        opt.set_learning_rate(lr * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()));
        let idx: Vec<usize> = (0..batch_size).map(|_| rng.random_range(0..n)).collect();
        let mut batch = idx.iter().map(|&i| get(i)).collect::<Result<Vec<_>>>()?;
        if let Some(a) = augment {
            for (slot, e) in batch.iter_mut().enumerate() {
                a.apply(e, (h, w), augment_seed(seed, step, slot))?;
            }
        }
        // colours, and the ground prior of each (augmented) example's camera when configured
        let imgs = batch
            .iter()
            .map(|e| Ok(cfg.input_tensor(&e.rgb, h, w, e.camera.as_ref(), device)?))
            .collect::<Result<Vec<_>>>()?;
        let image = Tensor::cat(&imgs, 0)?;
        // random horizontal flips (targets flipped with the image)
        let flip = rng.random_bool(0.5);
        let image = if flip { flip_w(&image)? } else { image };
        let lab = if use_labels {
            let mut rows: Vec<u32> = Vec::with_capacity(batch_size * h * w);
            for e in &batch {
                let l = e.labels.as_ref().ok_or_else(|| {
                    Error::Data(
                        "the semantic encoder needs per-pixel train ids: an example has none"
                            .into(),
                    )
                })?;
                rows.extend_from_slice(l);
            }
            let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
            Some(if flip { flip_w(&t)? } else { t })
        } else {
            None
        };
        let dep = if use_depth {
            let rows: Vec<f32> = batch
                .iter()
                .flat_map(|e| e.depth_m.iter().copied())
                .collect();
            let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
            Some(if flip { flip_w(&t)? } else { t })
        } else {
            None
        };
        let loss = net.loss(&image, lab.as_ref(), dep.as_ref(), &loss_cfg)?;
        let grads = loss.total.backward()?;
        opt.step(&grads, 1.0)?;
        on_step(EncoderStep {
            step: step + 1,
            loss: loss.total.to_dtype(DType::F32)?.to_scalar::<f32>()?,
        });
    }
    Ok((net, varmap))
}

/// Reverses the last axis.
fn flip_w(t: &Tensor) -> Result<Tensor> {
    let w = t.dim(t.rank() - 1)?;
    let idx: Vec<u32> = (0..w as u32).rev().collect();
    let idx = Tensor::from_vec(idx, w, t.device())?;
    Ok(t.index_select(&idx, t.rank() - 1)?)
}

/// The tensors of a `VarMap` by name (for [`Bundle::save`](crate::app::Bundle::save)).
pub fn varmap_tensors(varmap: &VarMap) -> Result<HashMap<String, Tensor>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
    Ok(data
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect())
}
