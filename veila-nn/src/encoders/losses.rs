//! Training losses of the small CNN heads ([`super::small_cnn`]).
//!
//! * [`semantic_cross_entropy`]: per-pixel softmax cross-entropy averaged over labelled pixels,
//!   with an ignore index (0 = SemanticKITTI "unlabelled").
//! * [`log_depth_l1`]: mean `|ln d_pred - ln d_gt|` over valid pixels.
//! * [`silog`]: the scale-invariant log loss of Eigen et al. (2014),
//!   `mean(g^2) - lambda * mean(g)^2` with `g = ln d_pred - ln d_gt` over valid pixels
//!   (`lambda = 0` is the log-MSE, `lambda = 1` fully scale-invariant; 0.85 is common for metric
//!   depth). It is returned without the square root some papers add, so its gradient stays finite
//!   at a perfect fit.
//!
//! A depth target is valid where it is finite and `> 0` (sparse LiDAR ground truth marks missing
//! pixels with 0; NaN and infinity are also treated as missing). Invalid pixels contribute exactly
//! nothing, not even NaN, and when no pixel is valid the losses are 0.

use candle_core::{DType, Tensor};

/// Mask (f32, 1 = valid) of depth targets that are finite and `> 0`.
pub fn depth_valid_mask(target_depth_m: &Tensor) -> crate::Result<Tensor> {
    let t = target_depth_m.to_dtype(DType::F32)?;
    let positive = t.gt(0f32)?;
    let finite = t.lt(f32::INFINITY)?;
    Ok((positive.to_dtype(DType::F32)? * finite.to_dtype(DType::F32)?)?.to_dtype(DType::F32)?)
}

fn flat_pair(pred: &Tensor, target: &Tensor, who: &str) -> crate::Result<(Tensor, Tensor)> {
    if pred.elem_count() != target.elem_count() || pred.rank() < 2 || target.rank() < 2 {
        input_bail!(
            "{who}: prediction {:?} and target {:?} must have the same number of pixels",
            pred.dims(),
            target.dims()
        );
    }
    if pred.dim(0)? != target.dim(0)? {
        input_bail!(
            "{who}: batch of prediction {:?} differs from target {:?}",
            pred.dims(),
            target.dims()
        );
    }
    let b = pred.dim(0)?;
    let p = pred.to_dtype(DType::F32)?.reshape((b, ()))?;
    let t = target.to_dtype(DType::F32)?.reshape((b, ()))?;
    Ok((p, t))
}

/// Log-depth residual `g = pred - ln(target)` (0 where invalid) and the valid mask, both `[B, N]`.
fn log_residual(
    pred_log_depth: &Tensor,
    target_depth_m: &Tensor,
    who: &str,
) -> crate::Result<(Tensor, Tensor)> {
    let (p, t) = flat_pair(pred_log_depth, target_depth_m, who)?;
    let mask = depth_valid_mask(&t)?;
    let safe_t = mask.ne(0f32)?.where_cond(&t, &t.ones_like()?)?;
    let g = ((p - safe_t.log()?)? * &mask)?;
    Ok((g, mask))
}

fn count(mask: &Tensor) -> crate::Result<Tensor> {
    Ok(mask.sum_all()?.maximum(1f32)?)
}

/// Mean absolute log-depth error over valid pixels; `pred_log_depth` is `ln` of metres, `[B, 1, H,
/// W]` or `[B, H, W]`, the target is metric depth of the same pixel count.
pub fn log_depth_l1(pred_log_depth: &Tensor, target_depth_m: &Tensor) -> crate::Result<Tensor> {
    let (g, mask) = log_residual(pred_log_depth, target_depth_m, "log_depth_l1")?;
    Ok(g.abs()?.sum_all()?.broadcast_div(&count(&mask)?)?)
}

/// Scale-invariant log loss `mean(g^2) - lambda * mean(g)^2` over all valid pixels of the batch
/// (`lambda` in `[0, 1]`).
pub fn silog(
    pred_log_depth: &Tensor,
    target_depth_m: &Tensor,
    lambda: f64,
) -> crate::Result<Tensor> {
    if !(0.0..=1.0).contains(&lambda) {
        input_bail!("silog: lambda must be in [0, 1], got {lambda}");
    }
    let (g, mask) = log_residual(pred_log_depth, target_depth_m, "silog")?;
    let n = count(&mask)?;
    let mean_sq = g.sqr()?.sum_all()?.broadcast_div(&n)?;
    let mean = g.sum_all()?.broadcast_div(&n)?;
    Ok((mean_sq - (mean.sqr()? * lambda)?)?)
}

/// Softmax cross-entropy of `logits` `[B, K, H, W]` against integer `labels` `[B, H, W]` (any
/// integer dtype), averaged over pixels whose label is not `ignore_index`.
///
/// # Errors
/// When shapes disagree or a non-ignored label is `>= K` (a wrong label map, e.g. raw SemanticKITTI
/// ids instead of the 20-class learning map).
pub fn semantic_cross_entropy(
    logits: &Tensor,
    labels: &Tensor,
    ignore_index: Option<u32>,
) -> crate::Result<Tensor> {
    let (b, k, h, w) = logits.dims4()?;
    let ld = labels.dims();
    if ld != [b, h, w] {
        input_bail!(
            "semantic_cross_entropy: labels {ld:?} do not match logits {:?} (expected [{b}, {h}, {w}])",
            logits.dims()
        );
    }
    let labels = labels.to_dtype(DType::U32)?;
    let ignored = match ignore_index {
        Some(ix) => labels.eq(ix)?,
        None => labels.zeros_like()?.to_dtype(DType::U8)?,
    };
    let zeros = labels.zeros_like()?;
    let safe = ignored.where_cond(&zeros, &labels)?;
    let max_label = safe.max_all()?.to_scalar::<u32>()?;
    if max_label as usize >= k {
        input_bail!("semantic_cross_entropy: label {max_label} is out of range for {k} classes");
    }
    let valid = (ignored.to_dtype(DType::F32)? * -1.0)?.affine(1.0, 1.0)?;
    let logp = candle_nn::ops::log_softmax(&logits.to_dtype(DType::F32)?, 1)?;
    let picked = logp
        .gather(&safe.unsqueeze(1)?.contiguous()?, 1)?
        .squeeze(1)?;
    let nll = (picked.neg()? * &valid)?;
    Ok(nll.sum_all()?.broadcast_div(&count(&valid)?)?)
}

/// Fraction of non-ignored pixels whose argmax class equals the label (a training diagnostic).
pub fn pixel_accuracy(
    logits: &Tensor,
    labels: &Tensor,
    ignore_index: Option<u32>,
) -> crate::Result<f32> {
    let pred = logits.argmax(1)?;
    let labels = labels.to_dtype(DType::U32)?;
    let valid = match ignore_index {
        Some(ix) => labels.ne(ix)?.to_dtype(DType::F32)?,
        None => labels.ones_like()?.to_dtype(DType::F32)?,
    };
    let hit = (pred.eq(&labels)?.to_dtype(DType::F32)? * &valid)?;
    let n = valid.sum_all()?.to_scalar::<f32>()?;
    if n == 0.0 {
        return Ok(0.0);
    }
    Ok(hit.sum_all()?.to_scalar::<f32>()? / n)
}
