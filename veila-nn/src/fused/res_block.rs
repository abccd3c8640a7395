//! The whole residual block as one op with a hand-written backward (candle's backward zero-fills
//! and adds a gradient for every edge of its graph, six per block unfused).

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::add_scaled::scaled;
use super::conv::{Conv2dGemm, ConvDims};
use super::group_norm::GroupNormAct;
use super::im2col::{Im2Col, Im2ColSpec};
use super::{GRAIN, on_cpu_f32, slice_f32, tensor_f32, with_f32};
use crate::error::{Result, shape_err};

/// The parameters of one [`res_block`] call, as the block's layers hold them.
#[derive(Debug, Clone, Copy)]
pub struct ResBlockParams<'a> {
    /// GroupNorm 1's per-sample scale and shift, `[B, C_in]` each (its affine weights folded in).
    pub norm1: (&'a Tensor, &'a Tensor),
    /// Convolution 1: weights `[C_out, C_in, k, k]` and bias `[C_out]`.
    pub conv1: (&'a Tensor, Option<&'a Tensor>),
    /// GroupNorm 2's per-sample scale and shift, `[B, C_out]` each (time modulation folded in).
    pub norm2: (&'a Tensor, &'a Tensor),
    /// Convolution 2: weights `[C_out, C_out, k, k]` and bias `[C_out]`.
    pub conv2: (&'a Tensor, Option<&'a Tensor>),
    /// The skip's 1x1 convolution `[C_out, C_in, 1, 1]` and bias, when the channel count changes.
    pub skip: Option<(&'a Tensor, Option<&'a Tensor>)>,
}

/// Group counts, epsilon, residual scale and convolution geometry of one [`res_block`].
#[derive(Debug, Clone, Copy)]
pub struct ResBlockSpec {
    /// GroupNorm 1's group count (divides `C_in`).
    pub groups1: usize,
    /// GroupNorm 2's group count (divides `C_out`).
    pub groups2: usize,
    /// Both GroupNorms' variance epsilon.
    pub eps: f64,
    /// Factor on the residual sum.
    pub scale: f64,
    /// Both convolutions' padding and stride (the kernel comes from the weights; stride 1 and
    /// size-preserving padding, so the skip adds up).
    pub conv: Im2ColSpec,
}

/// What the forward pass of [`ResBlockOp`] keeps for its backward pass.
struct ResBlockSaved {
    /// `SiLU(GN1(x))`, convolution 1's input.
    a1: Vec<f32>,
    /// Convolution 1's output, GroupNorm 2's input.
    h1: Vec<f32>,
    /// `SiLU(GN2(h1))`, convolution 2's input.
    a2: Vec<f32>,
}

/// A residual block as one op: `(skip(x) + conv2(SiLU(GN2(conv1(SiLU(GN1(x))))))) * scale`, from
/// the kernels above, with the small per-sample and weight tensors packed into two flat inputs.
/// candle's backward pass zero-fills and adds a gradient for every edge of its graph; as one node
/// the block has one such edge instead of six, and its intermediate activations live here.
struct ResBlockOp {
    spec: ResBlockSpec,
    /// `(C_in, C_out, k)`.
    channels: (usize, usize, usize),
    conv: Conv2dGemm,
    skip: Option<Conv2dGemm>,
    /// Which of conv 1, conv 2 and the skip have a bias.
    biases: [bool; 3],
    saved: std::sync::Mutex<Option<ResBlockSaved>>,
}

/// Offsets of the packed weights: `[w1, b1?, w2, b2?, ws?, bs?]`.
struct ResBlockLayout {
    w1: std::ops::Range<usize>,
    b1: Option<std::ops::Range<usize>>,
    w2: std::ops::Range<usize>,
    b2: Option<std::ops::Range<usize>>,
    ws: Option<std::ops::Range<usize>>,
    bs: Option<std::ops::Range<usize>>,
    len: usize,
}

impl ResBlockOp {
    fn layout(&self) -> ResBlockLayout {
        let (ci, co, k) = self.channels;
        let mut at = 0;
        let mut take = |len: usize| {
            let r = at..at + len;
            at += len;
            r
        };
        let w1 = take(co * ci * k * k);
        let b1 = self.biases[0].then(|| take(co));
        let w2 = take(co * co * k * k);
        let b2 = self.biases[1].then(|| take(co));
        let ws = self.skip.map(|_| take(co * ci));
        let bs = (self.skip.is_some() && self.biases[2]).then(|| take(co));
        ResBlockLayout {
            w1,
            b1,
            w2,
            b2,
            ws,
            bs,
            len: at,
        }
    }

    /// `(B, H, W)` of the input, checked against the packed inputs' lengths.
    fn check(
        &self,
        x: &[usize],
        small: usize,
        weights: usize,
    ) -> candle_core::Result<(usize, usize, usize)> {
        let (ci, co, _) = self.channels;
        let &[b, c, h, w] = x else {
            candle_core::bail!("residual block: input {x:?} is not 4-d")
        };
        if c != ci || small != 2 * b * (ci + co) || weights != self.layout().len {
            candle_core::bail!(
                "residual block: input {x:?}, {small} per-sample and {weights} weight values for {:?}",
                self.channels
            )
        }
        Ok((b, h, w))
    }

    fn conv_dims(
        &self,
        (b, h, w): (usize, usize, usize),
    ) -> candle_core::Result<(ConvDims, ConvDims, Option<ConvDims>)> {
        let (ci, co, k) = self.channels;
        let d1 = self.conv.dims(&[b, ci, h, w], &[co, ci, k, k])?;
        let d2 = self.conv.dims(&[b, co, h, w], &[co, co, k, k])?;
        let ds = self
            .skip
            .map(|s| s.dims(&[b, ci, h, w], &[co, ci, 1, 1]))
            .transpose()?;
        if (d1.ho, d1.wo) != (h, w) {
            candle_core::bail!(
                "residual block: {:?} changes the size {h}x{w}",
                self.spec.conv
            )
        }
        Ok((d1, d2, ds))
    }

    fn norm(&self, groups: usize) -> GroupNormAct {
        GroupNormAct {
            groups,
            eps: self.spec.eps,
            silu: true,
        }
    }
}

impl CustomOp3 for ResBlockOp {
    fn name(&self) -> &'static str {
        "veila-res-block"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = slice_f32(s1, l1, "residual block input")?;
        let small = slice_f32(s2, l2, "residual block norms")?;
        let wts = slice_f32(s3, l3, "residual block weights")?;
        let (b, h, w) = self.check(l1.dims(), small.len(), wts.len())?;
        let (ci, co, _) = self.channels;
        let (d1, d2, ds) = self.conv_dims((b, h, w))?;
        let n = h * w;
        let lay = self.layout();
        let (sc1, rest) = small.split_at(b * ci);
        let (sh1, rest) = rest.split_at(b * ci);
        let (sc2, sh2) = rest.split_at(b * co);
        let a1 = self
            .norm(self.spec.groups1)
            .forward_slices(x, sc1, sh1, (ci, n));
        let h1 = self
            .conv
            .forward_vec(d1, &a1, &wts[lay.w1], lay.b1.map(|r| &wts[r]))?;
        let a2 = self
            .norm(self.spec.groups2)
            .forward_slices(&h1, sc2, sh2, (co, n));
        let mut out = self
            .conv
            .forward_vec(d2, &a2, &wts[lay.w2], lay.b2.map(|r| &wts[r]))?;
        let skip = match (self.skip, ds, lay.ws) {
            (Some(conv), Some(d), Some(ws)) => {
                Some(conv.forward_vec(d, x, &wts[ws], lay.bs.map(|r| &wts[r]))?)
            }
            _ => None,
        };
        let skip: &[f32] = skip.as_deref().unwrap_or(x);
        let s = self.spec.scale as f32;
        out.par_chunks_mut(GRAIN)
            .zip(skip.par_chunks(GRAIN))
            .for_each(|(o, k)| {
                for (o, k) in o.iter_mut().zip(k) {
                    *o = (k + *o) * s;
                }
            });
        *self
            .saved
            .lock()
            .map_err(|_| candle_core::Error::Msg("residual block: poisoned".into()))? =
            Some(ResBlockSaved { a1, h1, a2 });
        Ok((CpuStorage::F32(out), Shape::from((b, co, h, w))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        small: &Tensor,
        weights: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let guard = self
            .saved
            .lock()
            .map_err(|_| candle_core::Error::Msg("residual block: poisoned".into()))?;
        let Some(saved) = guard.as_ref() else {
            candle_core::bail!("residual block: backward pass before a forward pass")
        };
        let (b, h, w) = self.check(x.dims(), small.elem_count(), weights.elem_count())?;
        let (ci, co, _) = self.channels;
        let (d1, d2, ds) = self.conv_dims((b, h, w))?;
        let n = h * w;
        let lay = self.layout();
        let sm = tensor_f32(small, "residual block norms")?;
        let wts = tensor_f32(weights, "residual block weights")?;
        let (sc1, rest) = sm.split_at(b * ci);
        let (sh1, rest) = rest.split_at(b * ci);
        let (sc2, sh2) = rest.split_at(b * co);
        let s = self.spec.scale as f32;
        let (dx, dsmall, dw) = with_f32(x, "residual block input", |xs| {
            with_f32(grad, "residual block gradient", |g| {
                // both branches of the sum get g * scale
                let gs = scaled(g, s);
                let mut dw = vec![0f32; lay.len];
                // a convolution's weight and bias gradients into their places in `dw`
                let mut put = |w: std::ops::Range<usize>,
                               b: Option<std::ops::Range<usize>>,
                               (dwv, dbv): (Vec<f32>, Vec<f32>)| {
                    dw[w].copy_from_slice(&dwv);
                    if let Some(r) = b {
                        dw[r].copy_from_slice(&dbv);
                    }
                };
                let (da2, dw2, db2) =
                    self.conv
                        .backward_slices(&d2, &saved.a2, &wts[lay.w2.clone()], &gs)?;
                put(lay.w2.clone(), lay.b2.clone(), (dw2, db2));
                let (dh1, dsc2, dsh2) = self.norm(self.spec.groups2).backward_slices(
                    &saved.h1,
                    sc2,
                    sh2,
                    &da2,
                    (co, n),
                );
                let (da1, dw1, db1) =
                    self.conv
                        .backward_slices(&d1, &saved.a1, &wts[lay.w1.clone()], &dh1)?;
                put(lay.w1.clone(), lay.b1.clone(), (dw1, db1));
                let (mut dx, dsc1, dsh1) =
                    self.norm(self.spec.groups1)
                        .backward_slices(xs, sc1, sh1, &da1, (ci, n));
                // the skip's share of dx
                match (self.skip, ds, lay.ws.clone()) {
                    (Some(conv), Some(d), Some(r)) => {
                        let (dxs, dws, dbs) = conv.backward_slices(&d, xs, &wts[r.clone()], &gs)?;
                        put(r, lay.bs.clone(), (dws, dbs));
                        add_into(&mut dx, &dxs);
                    }
                    _ => add_into(&mut dx, &gs),
                }
                let dsmall = [dsc1, dsh1, dsc2, dsh2].concat();
                Ok((dx, dsmall, dw))
            })
        })?;
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, x.shape(), dev)?),
            Some(Tensor::from_vec(dsmall, small.shape(), dev)?),
            Some(Tensor::from_vec(dw, weights.shape(), dev)?),
        ))
    }
}

/// `acc += v`, elementwise over the rayon pool.
fn add_into(acc: &mut [f32], v: &[f32]) {
    acc.par_chunks_mut(GRAIN)
        .zip(v.par_chunks(GRAIN))
        .for_each(|(a, v)| {
            for (a, v) in a.iter_mut().zip(v) {
                *a += v;
            }
        });
}

/// A residual block `(skip(x) + conv2(SiLU(GN2(conv1(SiLU(GN1(x))))))) * scale` as one op on CPU
/// f32 tensors (`skip` is a 1x1 convolution when given, the identity otherwise); `None` when a
/// tensor is not CPU f32 or the kernels are off (then compose the layers instead). The GroupNorms'
/// scales and shifts are per sample (`[B, C]`), with their affine weights and any modulation
/// folded in, as in [`crate::fused::group_norm_act`]. Same arithmetic as that composition, kernel for kernel.
pub fn res_block(x: &Tensor, p: ResBlockParams<'_>, spec: ResBlockSpec) -> Result<Option<Tensor>> {
    let mut all = vec![
        x, p.norm1.0, p.norm1.1, p.norm2.0, p.norm2.1, p.conv1.0, p.conv2.0,
    ];
    all.extend(p.conv1.1);
    all.extend(p.conv2.1);
    if let Some((w, b)) = p.skip {
        all.push(w);
        all.extend(b);
    }
    if !all.iter().all(|t| on_cpu_f32(t)) {
        return Ok(None);
    }
    let (b, ci, _, _) = x.dims4()?;
    let (co, wc, kh, kw) = p.conv1.0.dims4()?;
    if wc != ci || kh != kw || p.conv2.0.dims() != [co, co, kh, kw] {
        return Err(shape_err(
            "residual block weights",
            format!("[C_out, {ci}, k, k] and [C_out, C_out, k, k]"),
            p.conv1.0.dims(),
        ));
    }
    if spec.groups1 == 0
        || spec.groups2 == 0
        || !ci.is_multiple_of(spec.groups1)
        || !co.is_multiple_of(spec.groups2)
    {
        return Err(shape_err(
            "residual block input",
            format!(
                "channels divisible by {} and {}",
                spec.groups1, spec.groups2
            ),
            x.dims(),
        ));
    }
    for (t, want) in [
        (p.norm1.0, [b, ci]),
        (p.norm1.1, [b, ci]),
        (p.norm2.0, [b, co]),
        (p.norm2.1, [b, co]),
    ] {
        if t.dims() != want {
            return Err(shape_err(
                "residual block scale/shift",
                format!("{want:?}"),
                t.dims(),
            ));
        }
    }
    for bias in [p.conv1.1, p.conv2.1, p.skip.and_then(|s| s.1)]
        .into_iter()
        .flatten()
    {
        if bias.dims() != [co] {
            return Err(shape_err(
                "residual block bias",
                format!("[{co}]"),
                bias.dims(),
            ));
        }
    }
    match p.skip {
        Some((sw, _)) if sw.dims() != [co, ci, 1, 1] => {
            return Err(shape_err(
                "residual block skip",
                format!("[{co}, {ci}, 1, 1]"),
                sw.dims(),
            ));
        }
        None if ci != co => {
            return Err(shape_err(
                "residual block skip",
                format!("a [{co}, {ci}, 1, 1] projection"),
                &[],
            ));
        }
        _ => {}
    }
    let flat = |t: &Tensor| t.flatten_all();
    let small = Tensor::cat(
        &[
            flat(p.norm1.0)?,
            flat(p.norm1.1)?,
            flat(p.norm2.0)?,
            flat(p.norm2.1)?,
        ],
        0,
    )?;
    let mut parts = vec![flat(p.conv1.0)?];
    parts.extend(p.conv1.1.cloned());
    parts.push(flat(p.conv2.0)?);
    parts.extend(p.conv2.1.cloned());
    if let Some((sw, sb)) = p.skip {
        parts.push(flat(sw)?);
        parts.extend(sb.cloned());
    }
    let weights = Tensor::cat(&parts, 0)?;
    let op = ResBlockOp {
        spec,
        channels: (ci, co, kh),
        conv: Conv2dGemm {
            cols: Im2Col {
                spec: Im2ColSpec {
                    kernel: (kh, kw),
                    ones_row: false,
                    ..spec.conv
                },
            },
            parallel: None,
            tile_rows: None,
        },
        skip: p.skip.map(|_| Conv2dGemm {
            cols: Im2Col {
                spec: Im2ColSpec::POINTWISE,
            },
            parallel: None,
            tile_rows: None,
        }),
        biases: [
            p.conv1.1.is_some(),
            p.conv2.1.is_some(),
            p.skip.is_some_and(|s| s.1.is_some()),
        ],
        saved: std::sync::Mutex::new(None),
    };
    Ok(Some(x.contiguous()?.apply_op3(&small, &weights, op)?))
}
