//! Geometric Cross-Modal Alignment (equations 7-10) and its precomputed sampling geometry.
//!
//! # Interpretation of equations 7-10
//!
//! Every range pixel `(u, v)` has `K` points `r_k = d_k Ray(u, v)` on its ray (per camera view), projected
//! into the image at `(u'_k, v'_k)` (a [`veila_geom::EpipolarTable`]). Equation 7 averages the features
//! `F(u'_k, v'_k)` with the depth-aware weights `w_k = exp(-d_k / tau) m_k` into one vector `V_(u,v)`, and
//! equation 10 attends with `K_(u,v) = V_(u,v)`. Read literally the attention would be over a single key,
//! so softmax would be 1 and the query (equation 9, which depends on the sample `k`) would be unused. We
//! therefore read `V_(u,v)` as the set of the `K` depth-weighted samples whose normalised mean is
//! equation 7, and attend over the samples:
//!
//! ```text
//! f_k   = bilinear F^(i) at (u'_k, v'_k)                  (zero outside the image)
//! key_k = W_k f_k,   val_k = W_v f_k                       (keys are the samples: K = V up to projection)
//! q_k   = W_q GroupNorm(R)(u, v) + MLP(gamma(r_k))         (eq. 9, one query per sample)
//! s_k   = <q_k, key_k> / sqrt(d_h)                         (per head)
//! a_k   = w_k exp(s_k) / sum_j w_j exp(s_j)                (depth-aware weights as a log-prior, masked)
//! R~    = sum_k a_k val_k                                  (eq. 10)
//! R_hat = R + ZeroConv1x1(R~)                              (zero-initialised, residual)
//! ```
//!
//! With equal logits the weights reduce to `w_k / sum_j w_j`, i.e. exactly equation 7 (projected by
//! `W_v`): the attention only re-weights the paper's depth-aware average. Samples with `m_k = 0` get no
//! weight; a pixel none of whose samples is valid (outside every camera's frustum) gets `R~ = 0`, so its
//! output is `R` plus the zero-conv bias — no NaN. With several views, the `K` samples of every view are
//! concatenated (`S = views x K`) and attended together.
//!
//! # Precomputation
//!
//! [`GcmaGeometry`] turns the tables into tensors once (per U-Net level, for the feature size of the
//! scale that level uses): the active pixels (any valid sample), four bilinear corner indices into the
//! view-concatenated flattened feature maps with their weights, `log w_k`, the validity mask and
//! `gamma(r_k)`. The denoising loop only does `index_select`, weighted sums and small matmuls.

use candle_core::{D, Device, Tensor};
use candle_nn::{Linear, VarBuilder};
use veila_geom::{BeamLayout, EpipolarConfig, EpipolarTable, LidarSensor, PinholeCamera, RayTable};

use crate::config::{DenoiserConfig, GcmaConfig};
use crate::error::{Error, Result, shape_err};
use crate::ops::{Conv1x1, group_norm, groups_for, masked_softmax_last_dim, silu};

/// Precomputed sampling tensors of one U-Net level.
#[derive(Debug, Clone)]
pub struct LevelGeometry {
    level: usize,
    height: usize,
    width: usize,
    feat_size: [usize; 2],
    num_views: usize,
    samples_per_pixel: usize,
    /// `[P]` u32: flat pixel indices (row-major) with at least one valid sample.
    active: Tensor,
    num_active: usize,
    /// 4 x `[P * S]` u32 into the `views * Hf * Wf` flattened feature maps.
    corner_idx: Vec<Tensor>,
    /// 4 x `[P * S]` f32 bilinear weights (0 for taps outside the image or invalid samples).
    corner_w: Vec<Tensor>,
    /// The same corners for the one-op gather ([`crate::gather`]).
    taps: std::sync::Arc<crate::gather::GatherTaps>,
    /// `[P, S]` f32, `ln w_k` on valid samples, 0 elsewhere.
    log_w: Tensor,
    /// `[P, S]` u8, 1 where the sample is valid.
    valid: Tensor,
    /// `[P * S, gamma_dim]` Fourier encoding of the sampled points.
    point_features: Tensor,
}

impl LevelGeometry {
    /// U-Net level this geometry serves.
    pub fn level(&self) -> usize {
        self.level
    }
    /// Range-image size `(H, W)` at this level.
    pub fn range_size(&self) -> (usize, usize) {
        (self.height, self.width)
    }
    /// Feature-map size `[H_f, W_f]` the gather indices address.
    pub fn feature_size(&self) -> [usize; 2] {
        self.feat_size
    }
    /// Number of pixels with at least one valid sample.
    pub fn num_active(&self) -> usize {
        self.num_active
    }
    /// Samples per pixel over all views (`views x K`).
    pub fn samples_per_pixel(&self) -> usize {
        self.samples_per_pixel
    }

    /// The precomputed sampling tensors by name, for implementations of [`Gcma`] outside candle
    /// (`cargo xtask bench-model --export` writes them for the PyTorch yardstick, so that it runs
    /// on this exact geometry): `active` (`[P]` u32), `corner_idx.{c}` (`[P * S]` u32 into the
    /// `views * H_f * W_f` flattened feature maps) and `corner_w.{c}` (`[P * S]` f32) for the
    /// bilinear corners `c = 0..4`, `log_w` (`[P, S]` f32), `valid` (`[P, S]` u8) and
    /// `point_features` (`[P * S, gamma_dim]` f32); see the module docs for their use.
    pub fn named_tensors(&self) -> Vec<(String, Tensor)> {
        let mut out = vec![("active".to_string(), self.active.clone())];
        for (c, (i, w)) in self.corner_idx.iter().zip(&self.corner_w).enumerate() {
            out.push((format!("corner_idx.{c}"), i.clone()));
            out.push((format!("corner_w.{c}"), w.clone()));
        }
        out.push(("log_w".to_string(), self.log_w.clone()));
        out.push(("valid".to_string(), self.valid.clone()));
        out.push(("point_features".to_string(), self.point_features.clone()));
        out
    }
}

/// The sampling geometry of every GCMA level for one camera rig (one [`EpipolarTable`] per view and
/// level), precomputed once and shared by every denoising step and every sample of that rig.
///
/// A batch of one rig passes it to [`crate::Denoiser::prepare_condition`]; a batch whose samples
/// have different rigs (KITTI's three calibrations, nuScenes' per-log ones) passes one per sample
/// to [`crate::Denoiser::prepare_condition_per_sample`], and GCMA attends each rig's samples with
/// its own. Building costs one projection per sample point (`H W K` per level and view) and is
/// meant to happen once per rig, outside the denoising loop.
#[derive(Debug, Clone)]
pub struct GcmaGeometry {
    levels: Vec<LevelGeometry>,
    num_views: usize,
}

/// The sensor seen at U-Net level `level` (rows and columns divided by `2^level`): uniform layouts keep
/// their field of view; per-beam layouts average the elevations of each group of `2^level` rows. Pixel
/// centres are the centres of the `2^level x 2^level` blocks of full-resolution pixels.
pub fn sensor_at_level(sensor: &LidarSensor, level: usize) -> Result<LidarSensor> {
    let f = 1u32 << level;
    if !sensor.rows.is_multiple_of(f) || !sensor.cols.is_multiple_of(f) {
        return Err(Error::Config(format!(
            "sensor {}x{} is not divisible by 2^{level} for level {level}",
            sensor.rows, sensor.cols
        )));
    }
    let mut s = sensor.clone();
    s.rows = sensor.rows / f;
    s.cols = sensor.cols / f;
    if level > 0 && matches!(sensor.beams, BeamLayout::PerBeam { .. }) {
        let elevations_deg = (0..s.rows)
            .map(|r| {
                let sum: f64 = (0..f)
                    .map(|j| f64::from(sensor.row_elevation_rad(r * f + j)))
                    .sum();
                (sum / f64::from(f)).to_degrees() as f32
            })
            .collect();
        s.beams = BeamLayout::PerBeam {
            elevations_deg,
            row_source: veila_geom::RowSource::NearestElevation,
        };
    }
    Ok(s)
}

impl GcmaGeometry {
    /// Builds the epipolar tables of every camera at every GCMA level of `cfg` and precomputes them.
    ///
    /// Errors if `cfg` has no GCMA, if the number of cameras differs from `conditioning.num_views`, or if
    /// a camera / epipolar config is invalid.
    pub fn new(
        cfg: &DenoiserConfig,
        cameras: &[PinholeCamera],
        epi: &EpipolarConfig,
        device: &Device,
    ) -> Result<Self> {
        let (cc, g) = gcma_cfg(cfg)?;
        if cameras.len() != cc.num_views {
            return Err(Error::Config(format!(
                "the model expects {} camera view(s), got {}",
                cc.num_views,
                cameras.len()
            )));
        }
        let mut per_level = Vec::new();
        for level in gcma_levels(g) {
            let sensor = sensor_at_level(&cfg.sensor, level)?;
            let rays = RayTable::new(&sensor)?;
            let tables = cameras
                .iter()
                .map(|cam| EpipolarTable::build(&rays, cam, epi))
                .collect::<std::result::Result<Vec<_>, _>>()?;
            per_level.push((level, tables));
        }
        Self::from_tables(cfg, &per_level, device)
    }

    /// Precomputes from explicit tables: `(level, one table per view)` for every GCMA level of `cfg`.
    /// Each table must have the range size of its level (`H / 2^level x W / 2^level`).
    pub fn from_tables(
        cfg: &DenoiserConfig,
        tables: &[(usize, Vec<EpipolarTable>)],
        device: &Device,
    ) -> Result<Self> {
        let (cc, g) = gcma_cfg(cfg)?;
        let mut levels = Vec::new();
        for level in gcma_levels(g) {
            let Some((_, views)) = tables.iter().find(|(l, _)| *l == level) else {
                return Err(Error::Config(format!(
                    "no epipolar tables given for GCMA level {level}"
                )));
            };
            if views.len() != cc.num_views {
                return Err(Error::Config(format!(
                    "level {level}: the model expects {} view(s), got {} table(s)",
                    cc.num_views,
                    views.len()
                )));
            }
            let feat_size = cc.feature_sizes[cc.scale_for_level(level)];
            let (h, w) = (cfg.height() >> level, cfg.width() >> level);
            levels.push(build_level(
                level,
                h,
                w,
                feat_size,
                views,
                &g.point_encoding,
                device,
            )?);
        }
        Ok(Self {
            levels,
            num_views: cc.num_views,
        })
    }

    /// Number of camera views.
    pub fn num_views(&self) -> usize {
        self.num_views
    }

    /// The precomputed levels.
    pub fn levels(&self) -> &[LevelGeometry] {
        &self.levels
    }

    /// The geometry of U-Net level `level`, if GCMA runs there.
    pub fn level(&self, level: usize) -> Option<&LevelGeometry> {
        self.levels.iter().find(|l| l.level == level)
    }
}

fn gcma_cfg(cfg: &DenoiserConfig) -> Result<(&crate::config::ConditioningConfig, &GcmaConfig)> {
    cfg.validate()?;
    let cc = cfg
        .conditioning
        .as_ref()
        .ok_or_else(|| Error::Config("the model is unconditional".into()))?;
    let g = cc
        .gcma
        .as_ref()
        .ok_or_else(|| Error::Config("the model has no GCMA".into()))?;
    Ok((cc, g))
}

fn gcma_levels(g: &GcmaConfig) -> Vec<usize> {
    let mut l = g.levels.clone();
    l.sort_unstable();
    l.dedup();
    l
}

fn build_level(
    level: usize,
    h: usize,
    w: usize,
    feat_size: [usize; 2],
    views: &[EpipolarTable],
    enc: &veila_geom::FourierEncoding,
    device: &Device,
) -> Result<LevelGeometry> {
    let [fh, fw] = feat_size;
    let k = views.first().map_or(0, |t| t.num_samples());
    for (v, t) in views.iter().enumerate() {
        if t.rows as usize != h
            || t.cols as usize != w
            || t.num_samples() != k
            || t.valid.len() != h * w * k
        {
            return Err(Error::Config(format!(
                "level {level}, view {v}: epipolar table is {}x{} with {} samples, expected {h}x{w} with {k}",
                t.rows,
                t.cols,
                t.num_samples()
            )));
        }
    }
    let s = views.len() * k;
    let gathers: Vec<_> = views.iter().map(|t| t.bilinear_gather(fh, fw)).collect();
    let sample_ok =
        |t: &EpipolarTable, i: usize| t.valid[i] && t.weight[i] > 0.0 && t.weight[i].is_finite();
    let active: Vec<u32> = (0..h * w)
        .filter(|p| {
            views
                .iter()
                .any(|t| (0..k).any(|kk| sample_ok(t, p * k + kk)))
        })
        .map(|p| p as u32)
        .collect();
    let n = active.len() * s;
    let mut idx: [Vec<u32>; 4] = std::array::from_fn(|_| Vec::with_capacity(n));
    let mut wts: [Vec<f32>; 4] = std::array::from_fn(|_| Vec::with_capacity(n));
    let mut log_w = Vec::with_capacity(n);
    let mut valid = Vec::with_capacity(n);
    let mut gamma = Vec::with_capacity(n * enc.dim());
    let view_stride = (fh * fw) as u32;
    for &p in &active {
        let (row, col) = (p / w as u32, p % w as u32);
        for (v, (t, g)) in views.iter().zip(&gathers).enumerate() {
            for kk in 0..k {
                let i = p as usize * k + kk;
                let ok = sample_ok(t, i);
                for c in 0..4 {
                    idx[c].push(v as u32 * view_stride + g.indices[i][c]);
                    wts[c].push(if ok { g.weights[i][c] } else { 0.0 });
                }
                log_w.push(if ok { t.weight[i].ln() } else { 0.0 });
                valid.push(u8::from(ok));
                enc.encode(t.sample_point_lidar(row, col, kk), &mut gamma);
            }
        }
    }
    let num_active = active.len();
    let gdim = enc.dim();
    let taps = crate::gather::GatherTaps::new(idx, wts, device)?;
    Ok(LevelGeometry {
        level,
        height: h,
        width: w,
        feat_size,
        num_views: views.len(),
        samples_per_pixel: s,
        active: Tensor::from_vec(active, num_active, device)?,
        num_active,
        corner_idx: taps.index_tensors().to_vec(),
        corner_w: taps.weight_tensors().to_vec(),
        taps: std::sync::Arc::new(taps),
        log_w: Tensor::from_vec(log_w, (num_active, s), device)?,
        valid: Tensor::from_vec(valid, (num_active, s), device)?,
        point_features: Tensor::from_vec(gamma, (n, gdim), device)?,
    })
}

/// GCMA's attention of every active pixel over its samples (the module docs' `s_k`, `a_k`, `R~`):
/// `qr: [B, P, d]` (the pixel's query), `pos: [P, S, d]` (each sample's point encoding, added to
/// it), `kv: [B, P * S, 2d]` (each sample's key then value), `log_w`/`valid: [P, S]` (the
/// depth-aware log-prior and the mask) -> `[B, P, d]`, `heads` heads of `d / heads` channels.
///
/// One graph node ([`crate::recompute::with_backward`]) whose backward pass is written out
/// ([`sample_attention_grad`]): candle's backward pass through the composition
/// ([`sample_attention_reference`]) kept every `[B, P, S, d]` product and a gradient for each,
/// and the largest of them at the paper's level 0 is most of a GCMA layer's backward peak.
pub fn sample_attention(
    qr: &Tensor,
    pos: &Tensor,
    kv: &Tensor,
    log_w: &Tensor,
    valid: &Tensor,
    heads: usize,
) -> Result<Tensor> {
    let (lw, vd) = (log_w.clone(), valid.clone());
    crate::recompute::with_backward(
        &[qr, pos, kv],
        |t| sample_attention_reference(t[0], t[1], t[2], log_w, valid, heads),
        std::sync::Arc::new(move |t: &[&Tensor], g: &Tensor| {
            let (gq, gp, gkv) = sample_attention_grad(t[0], t[1], t[2], &lw, &vd, heads, g)?;
            Ok(vec![Some(gq), Some(gp), Some(gkv)])
        }),
    )
}

/// The query `[B, P, S, h, dh]`, keys and values `[B, P, S, h, dh]` and attention weights
/// `[B, P, h, S]` of [`sample_attention`].
fn attention_parts(
    qr: &Tensor,
    pos: &Tensor,
    kv: &Tensor,
    log_w: &Tensor,
    valid: &Tensor,
    heads: usize,
) -> Result<(Tensor, Tensor, Tensor, Tensor)> {
    let (b, p, d) = qr.dims3()?;
    let (_, s, _) = pos.dims3()?;
    if heads == 0
        || !d.is_multiple_of(heads)
        || pos.dims() != [p, s, d]
        || kv.dims() != [b, p * s, 2 * d]
    {
        return Err(shape_err(
            "GCMA attention inputs",
            format!("[B, P, d], [P, S, d], [B, P * S, 2d] with d divisible by {heads} heads"),
            kv.dims(),
        ));
    }
    let dh = d / heads;
    let g = kv.reshape((b, p, s, 2, heads, dh))?;
    let keys = g.narrow(3, 0, 1)?.squeeze(3)?; // [B, P, S, heads, dh]
    let vals = g.narrow(3, 1, 1)?.squeeze(3)?;
    let q = qr
        .reshape((b, p, 1, heads, dh))?
        .broadcast_add(&pos.reshape((1, p, s, heads, dh))?)?;
    let logits = ((&q * &keys)?.sum(D::Minus1)? / (dh as f64).sqrt())?; // [B, P, S, heads]
    let logits = logits.transpose(2, 3)?; // [B, P, heads, S]
    let log_w = log_w.to_dtype(qr.dtype())?.reshape((1, p, 1, s))?;
    let a = masked_softmax_last_dim(&logits, &log_w, &valid.reshape((1, p, 1, s))?)?;
    Ok((q, keys, vals, a))
}

/// [`sample_attention`] from candle ops, with candle's own backward pass: the test oracle.
pub fn sample_attention_reference(
    qr: &Tensor,
    pos: &Tensor,
    kv: &Tensor,
    log_w: &Tensor,
    valid: &Tensor,
    heads: usize,
) -> Result<Tensor> {
    let (b, p, d) = qr.dims3()?;
    let (_, s, _) = pos.dims3()?;
    let (_, _, vals, a) = attention_parts(qr, pos, kv, log_w, valid, heads)?;
    let dh = d / heads;
    // [B, P, heads, 1, S] x [B, P, heads, S, dh] -> [B, P, heads, 1, dh]
    let a = a.contiguous()?.reshape((b * p * heads, 1, s))?;
    let vals = vals
        .permute((0, 1, 3, 2, 4))?
        .contiguous()?
        .reshape((b * p * heads, s, dh))?;
    Ok(a.matmul(&vals)?.reshape((b, p, d))?)
}

/// The gradients of [`sample_attention`] (`qr`, `pos`, `kv`) for the output's gradient
/// `grad: [B, P, d]`, recomputing the attention weights: the softmax's backward pass
/// `a (g_a - sum_j a_j g_a_j)` (masked samples have `a = 0` and get nothing), then the products'.
/// Half-precision inputs are computed in f32, the gradients returned in their dtypes.
pub fn sample_attention_grad(
    qr: &Tensor,
    pos: &Tensor,
    kv: &Tensor,
    log_w: &Tensor,
    valid: &Tensor,
    heads: usize,
    grad: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    let dt = crate::fused::compute_dtype(qr.dtype());
    let (b, p, d) = qr.dims3()?;
    let (_, s, _) = pos.dims3()?;
    if grad.dims() != [b, p, d] {
        return Err(shape_err(
            "GCMA attention gradient",
            format!("[{b}, {p}, {d}]"),
            grad.dims(),
        ));
    }
    let (qr32, pos32, kv32) = (qr.to_dtype(dt)?, pos.to_dtype(dt)?, kv.to_dtype(dt)?);
    let (q, keys, vals, a) = attention_parts(&qr32, &pos32, &kv32, log_w, valid, heads)?;
    drop((qr32, pos32));
    let dh = d / heads;
    let at = a.transpose(2, 3)?.contiguous()?.unsqueeze(4)?; // [B, P, S, heads, 1]
    drop(a);
    let go = grad.to_dtype(dt)?.reshape((b, p, 1, heads, dh))?;
    let g_vals = at.broadcast_mul(&go)?;
    let g_a = vals.broadcast_mul(&go)?.sum_keepdim(4)?; // [B, P, S, heads, 1]
    drop(vals);
    let dot = (&at * &g_a)?.sum_keepdim(2)?;
    let g_l = ((at * g_a.broadcast_sub(&dot)?)? / (dh as f64).sqrt())?;
    let g_keys = g_l.broadcast_mul(&q)?;
    drop(q);
    let g_q = g_l.broadcast_mul(&keys)?;
    drop((keys, kv32));
    let g_qr = g_q.sum(2)?.reshape((b, p, d))?;
    let g_pos = g_q.sum(0)?.reshape((p, s, d))?;
    drop(g_q);
    let g_kv = Tensor::stack(&[g_keys, g_vals], 3)?.reshape((b, p * s, 2 * d))?;
    Ok((
        g_qr.to_dtype(qr.dtype())?,
        g_pos.to_dtype(pos.dtype())?,
        g_kv.to_dtype(kv.dtype())?,
    ))
}

/// One GCMA block: attends from every range pixel to the image features at its epipolar samples.
///
/// Weights: `norm` (GroupNorm of `R`), `q` (1x1, `C -> d`), `kv` (1x1 without bias, `C_f -> 2d`, keys
/// then values), `pos.0` / `pos.2` (MLP `gamma_dim -> d -> d`, SiLU), `out` (zero-initialised 1x1,
/// `d -> C`). See the module docs for the equations.
#[derive(Debug, Clone)]
pub struct Gcma {
    norm: crate::ops::GroupNorm,
    q: Conv1x1,
    kv: Conv1x1,
    pos0: Linear,
    pos2: Linear,
    out: Conv1x1,
    attn_dim: usize,
    num_heads: usize,
    channels: usize,
    feat_channels: usize,
    span: tracing::Span,
}

impl Gcma {
    /// A block for range features with `channels` channels attending to fused maps with `feat_channels`.
    pub fn new(
        cfg: &GcmaConfig,
        channels: usize,
        feat_channels: usize,
        max_groups: usize,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        let d = cfg.attn_dim;
        let gdim = cfg.point_encoding.dim();
        Ok(Self {
            norm: group_norm(groups_for(channels, max_groups), channels, vb.pp("norm"))?,
            q: Conv1x1::new(channels, d, true, vb.pp("q"))?,
            kv: Conv1x1::new(feat_channels, 2 * d, false, vb.pp("kv"))?,
            pos0: candle_nn::linear(gdim, d, vb.pp("pos.0"))?,
            pos2: candle_nn::linear(d, d, vb.pp("pos.2"))?,
            out: Conv1x1::zeros(d, channels, vb.pp("out"))?,
            attn_dim: d,
            num_heads: cfg.num_heads,
            channels,
            feat_channels,
            span: tracing::span!(tracing::Level::TRACE, "gcma"),
        })
    }

    /// The attended features `R~` scattered back to `[B, d, H, W]` (zero at inactive pixels), before the
    /// zero convolution. `feat`: fused maps `[B * views, C_f, H_f, W_f]` (views of one sample adjacent).
    pub fn attend(&self, r: &Tensor, feat: &Tensor, geom: &LevelGeometry) -> Result<Tensor> {
        let _enter = self.span.enter();
        let (b, c, h, w) = r.dims4()?;
        if c != self.channels || (h, w) != (geom.height, geom.width) {
            return Err(shape_err(
                format!("GCMA input at level {}", geom.level),
                format!("[B, {}, {}, {}]", self.channels, geom.height, geom.width),
                r.dims(),
            ));
        }
        let views = geom.num_views;
        let [fh, fw] = geom.feat_size;
        let fd = feat.dims();
        if fd.len() != 4
            || fd[0] != b * views
            || fd[1] != self.feat_channels
            || fd[2] != fh
            || fd[3] != fw
        {
            return Err(shape_err(
                format!("conditioning map for GCMA level {}", geom.level),
                format!(
                    "[{}, {}, {fh}, {fw}] (batch x views, C, H, W)",
                    b * views,
                    self.feat_channels
                ),
                fd,
            ));
        }
        let (d, heads) = (self.attn_dim, self.num_heads);
        let (p, s) = (geom.num_active, geom.samples_per_pixel);
        let dtype = r.dtype();
        if p == 0 {
            return Ok(Tensor::zeros((b, d, h, w), dtype, r.device())?);
        }
        // keys and values of every feature pixel of every view, channels last: [B, V * Hf * Wf, 2d]
        let kv = self.kv.forward(feat)?.reshape((b, views, 2 * d, fh * fw))?;
        let kv = kv
            .permute((0, 1, 3, 2))?
            .contiguous()?
            .reshape((b, views * fh * fw, 2 * d))?;
        // bilinear gather at the samples (whole 2d-rows per tap, one op): [B, P * S, 2d]
        let g = crate::gather::bilinear_gather(&kv, &geom.taps)?;
        // queries: W_q GN(R) at the active pixels [B, P, d], plus MLP(gamma(r_k)) [P, S, d]
        let qr = self
            .q
            .forward(&self.norm.forward(r)?)?
            .reshape((b, d, h * w))?;
        let qr = qr.index_select(&geom.active, 2)?.transpose(1, 2)?;
        let pos = crate::ops::linear(
            &self.pos2,
            &silu(&crate::ops::linear(
                &self.pos0,
                &geom.point_features.to_dtype(dtype)?,
            )?)?,
        )?
        .reshape((p, s, d))?;
        let out = sample_attention(&qr, &pos, &g, &geom.log_w, &geom.valid, heads)?;
        let out = out.transpose(1, 2)?.contiguous()?; // [B, d, P]
        let full =
            Tensor::zeros((b, d, h * w), dtype, r.device())?.index_add(&geom.active, &out, 2)?;
        Ok(full.reshape((b, d, h, w))?)
    }

    /// The trainable tensors (for activation checkpointing).
    pub(crate) fn params(&self) -> Vec<Tensor> {
        use crate::recompute::{push_linear, push_weights};
        let mut out: Vec<Tensor> = self.norm.params().into_iter().cloned().collect();
        push_weights(&mut out, self.q.weights());
        push_weights(&mut out, self.kv.weights());
        push_linear(&mut out, &self.pos0);
        push_linear(&mut out, &self.pos2);
        push_weights(&mut out, self.out.weights());
        out
    }

    /// `R_hat = R + keep * ZeroConv(R~)`; `keep: [B]` (1 = conditioned, 0 = dropped for classifier-free
    /// guidance) scales the residual branch per sample.
    pub fn forward(
        &self,
        r: &Tensor,
        feat: &Tensor,
        geom: &LevelGeometry,
        keep: Option<&Tensor>,
    ) -> Result<Tensor> {
        let delta = self.out.forward(&self.attend(r, feat, geom)?)?;
        let delta = match keep {
            Some(k) => {
                delta.broadcast_mul(&k.to_dtype(delta.dtype())?.reshape((r.dim(0)?, 1, 1, 1))?)?
            }
            None => delta,
        };
        Ok((r + delta)?)
    }
}
