//! The denoising U-Net over range images with CACM, GCMA and PFC.

use candle_core::{Device, Tensor};
use candle_nn::{Linear, VarBuilder};

use crate::cacm::ConditionFusion;
use crate::config::DenoiserConfig;
use crate::error::{Error, Result, shape_err};
use crate::fused::{ResBlockParams, ResBlockSpec, add_scaled};
use crate::gcma::{Gcma, GcmaGeometry};
use crate::ops::{
    Conv1x1, GroupNorm, RingConv2d, group_norm, groups_for, silu, sinusoidal_embedding,
};
use crate::pfc::Pfc;
use crate::recompute::{RecomputeTape, checkpoint};

/// Residual block: `GN -> SiLU -> conv3x3 -> AdaGN(t) -> SiLU -> conv3x3`, plus a (1x1-projected) skip,
/// all scaled by `residual_scale`. Convolutions wrap around the azimuth axis ([`RingConv2d`]).
///
/// Weights: `norm1`, `conv1`, `emb` (Linear `T -> 2 C_out`, scale then shift), `norm2`, `conv2`, `skip`
/// (only when the channel count changes).
#[derive(Debug, Clone)]
pub struct ResBlock {
    norm1: GroupNorm,
    conv1: RingConv2d,
    emb: Linear,
    norm2: GroupNorm,
    conv2: RingConv2d,
    skip: Option<Conv1x1>,
    out_c: usize,
    scale: f64,
    span: tracing::Span,
}

impl ResBlock {
    /// `in_c -> out_c` channels, time embedding width `temb`.
    pub fn new(
        in_c: usize,
        out_c: usize,
        temb: usize,
        groups: usize,
        scale: f32,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        Ok(Self {
            norm1: group_norm(groups_for(in_c, groups), in_c, vb.pp("norm1"))?,
            conv1: RingConv2d::new(in_c, out_c, 3, 1, vb.pp("conv1"))?,
            emb: candle_nn::linear(temb, 2 * out_c, vb.pp("emb"))?,
            norm2: group_norm(groups_for(out_c, groups), out_c, vb.pp("norm2"))?,
            conv2: RingConv2d::new(out_c, out_c, 3, 1, vb.pp("conv2"))?,
            skip: if in_c != out_c {
                Some(Conv1x1::new(in_c, out_c, true, vb.pp("skip"))?)
            } else {
                None
            },
            out_c,
            scale: f64::from(scale),
            span: tracing::span!(tracing::Level::TRACE, "res_block"),
        })
    }

    /// The trainable tensors (for activation checkpointing).
    pub(crate) fn params(&self) -> Vec<Tensor> {
        use crate::recompute::{push_linear, push_weights};
        let mut out: Vec<Tensor> = self.norm1.params().into_iter().cloned().collect();
        push_weights(&mut out, self.conv1.weights());
        push_linear(&mut out, &self.emb);
        out.extend(self.norm2.params().into_iter().cloned());
        push_weights(&mut out, self.conv2.weights());
        if let Some(s) = &self.skip {
            push_weights(&mut out, s.weights());
        }
        out
    }

    /// `x: [B, in, H, W]`, `emb: [B, T]` (already through SiLU) `-> [B, out, H, W]`.
    pub fn forward(&self, x: &Tensor, emb: &Tensor) -> Result<Tensor> {
        let _enter = self.span.enter();
        let e = crate::ops::linear(&self.emb, emb)?;
        let (sc, sh) = (
            e.narrow(1, 0, self.out_c)?,
            e.narrow(1, self.out_c, self.out_c)?,
        );
        if crate::fused::takes_kernels(x)
            && self.conv1.spec().stride == (1, 1)
            && self.norm1.eps() == self.norm2.eps()
        {
            // one op on the CPU (same kernels, one gradient edge instead of six)
            let norm1 = self.norm1.affine(x.dim(0)?)?;
            let norm2 = self.norm2.modulated_affine(&sc, &sh)?;
            let fused = crate::fused::res_block(
                x,
                ResBlockParams {
                    norm1: (&norm1.0, &norm1.1),
                    conv1: self.conv1.weights(),
                    norm2: (&norm2.0, &norm2.1),
                    conv2: self.conv2.weights(),
                    skip: self.skip.as_ref().map(Conv1x1::weights),
                },
                ResBlockSpec {
                    groups1: self.norm1.groups(),
                    groups2: self.norm2.groups(),
                    eps: self.norm1.eps(),
                    scale: self.scale,
                    conv: self.conv1.spec(),
                },
            )?;
            if let Some(y) = fused {
                return Ok(y);
            }
        }
        let h = self.conv1.forward(&self.norm1.forward_silu(x)?)?;
        let h = self.norm2.forward_modulated_silu(&h, &sc, &sh)?;
        let h = self.conv2.forward(&h)?;
        let skip = match &self.skip {
            Some(s) => s.forward(x)?,
            None => x.clone(),
        };
        add_scaled(&skip, &h, self.scale)
    }
}

/// Image conditioning as the encoders deliver it.
///
/// Every list has one tensor per feature scale, `[B * views, D_i, H_i, W_i]` with the views of a sample
/// adjacent (index `b * views + v`); 5-D `[B, views, D_i, H_i, W_i]` is accepted too.
#[derive(Debug, Clone, Default)]
pub struct ConditionInput {
    /// Semantic encoder (`E_s`) pyramid; required unless the model is depth-only.
    pub semantic: Option<Vec<Tensor>>,
    /// Depth encoder (`E_d`) pyramid; required unless the model is semantic-only.
    pub depth: Option<Vec<Tensor>>,
    /// Per-sample `[B]` factor on every conditioning branch: 1 = use the image, 0 = drop it (classifier-free
    /// guidance dropout during training; a zero row gives exactly the unconditional output).
    pub keep: Option<Tensor>,
}

/// A condition prepared once per image (CACM output and the camera geometry) and reused by every
/// denoising step: the fused maps do not depend on `x_t` or `t`.
#[derive(Debug, Clone)]
pub struct PreparedCondition<'g> {
    /// Fused maps `F^(i)`, `[B * views, C_i, H_i, W_i]`.
    pub fused: Vec<Tensor>,
    /// Sampling geometry (required when the model has GCMA): the rig of every sample, unless the
    /// condition came from [`Denoiser::prepare_condition_per_sample`] with several rigs (then
    /// `None`: each sample has its own).
    pub geometry: Option<&'g GcmaGeometry>,
    /// See [`ConditionInput::keep`].
    pub keep: Option<Tensor>,
    batch: usize,
    /// Samples of different rigs ([`Denoiser::prepare_condition_per_sample`]): each distinct
    /// geometry with the batch indices that use it.
    groups: Option<RigGroups<'g>>,
}

/// A batch's samples grouped by rig, and the permutation back from group order to batch order.
#[derive(Debug, Clone)]
struct RigGroups<'g> {
    groups: Vec<GeometryGroup<'g>>,
    /// `[B]` u32: where sample `b` lands in the concatenation of the groups' outputs.
    inverse: Tensor,
}

/// The samples of a batch that share one rig.
#[derive(Debug, Clone)]
struct GeometryGroup<'g> {
    geometry: &'g GcmaGeometry,
    /// `[n]` u32 batch indices.
    samples: Tensor,
    /// `[n * views]` u32 indices into the `B * views` fused maps.
    views: Tensor,
}

impl PreparedCondition<'_> {
    /// Batch size `B` the condition was prepared for.
    pub fn batch(&self) -> usize {
        self.batch
    }

    /// The same condition with another per-sample keep factor (`[B]`).
    pub fn with_keep(mut self, keep: Option<Tensor>) -> Self {
        self.keep = keep;
        self
    }

    /// Number of distinct rigs in the batch (1 for a shared geometry, 0 without GCMA).
    pub fn num_rigs(&self) -> usize {
        match (&self.groups, self.geometry) {
            (Some(g), _) => g.groups.len(),
            (None, Some(_)) => 1,
            (None, None) => 0,
        }
    }
}

#[derive(Debug, Clone)]
struct Level {
    res: Vec<ResBlock>,
    gcma: Option<Gcma>,
    resample: Option<RingConv2d>,
}

/// The Veila denoiser: a U-Net over `[B, C, H, W]` range images predicting `[B, C_out, H, W]` (noise,
/// `v` or `x_0`, as the diffusion code chooses).
///
/// Layout (weight prefixes in brackets): ray-direction Fourier features concatenated to the input,
/// `[in_conv]` 3x3, encoder levels `[down.{l}.res.{j}]` + optional `[down.{l}.gcma]` +
/// `[down.{l}.downsample]` (stride-2 3x3), middle `[mid.res.0]`, `[mid.pfc]`, `[mid.res.1]`, decoder
/// levels `[up.{l}.res.{j}]` (with skip concatenation) + optional `[up.{l}.gcma]` + `[up.{l}.upsample]`
/// (nearest x2 then 3x3), `[out_norm]`, `[out_conv]`. Time embedding `[time.0]`, `[time.2]`; condition
/// fusion `[cond.fuse.{i}]`; the "w/o GCMA" global condition `[cond.pool]`. Every 3x3 convolution pads
/// circularly in azimuth and with zeros vertically.
#[derive(Debug, Clone)]
pub struct Denoiser {
    cfg: DenoiserConfig,
    ray_features: Option<Tensor>,
    in_conv: RingConv2d,
    time0: Linear,
    time2: Linear,
    down: Vec<Level>,
    mid0: ResBlock,
    pfc: Option<Pfc>,
    mid1: ResBlock,
    up: Vec<Level>,
    out_norm: GroupNorm,
    out_conv: RingConv2d,
    fusion: Option<ConditionFusion>,
    pool: Option<Linear>,
    /// Set when residual blocks, GCMA and PFC recompute their activations in the backward pass.
    recompute: Option<RecomputeTape>,
    span: tracing::Span,
}

/// The `[1, D, H, W]` Fourier features of every pixel's unit ray direction for `cfg` (`None` when off).
pub fn ray_feature_tensor(cfg: &DenoiserConfig, device: &Device) -> Result<Option<Tensor>> {
    let Some(enc) = cfg.ray_features else {
        return Ok(None);
    };
    let rays = veila_geom::RayTable::new(&cfg.sensor)?;
    let (h, w, d) = (cfg.height(), cfg.width(), enc.dim());
    let mut pix = Vec::with_capacity(d);
    let mut chw = vec![0f32; d * h * w];
    for (p, dir) in rays.dirs().iter().enumerate() {
        pix.clear();
        enc.encode(*dir, &mut pix);
        for (c, v) in pix.iter().enumerate() {
            chw[c * h * w + p] = *v;
        }
    }
    Ok(Some(crate::ops::image_tensor(chw, d, h, w, device)?))
}

impl Denoiser {
    /// Builds the network for `cfg` (validated first) with weights from `vb`.
    pub fn new(cfg: &DenoiserConfig, vb: VarBuilder<'_>) -> Result<Self> {
        cfg.validate()?;
        let groups = cfg.norm_groups;
        let rs = cfg.residual_scale;
        let temb = cfg.time_embed_dim();
        let nl = cfg.num_levels();
        let gcma_cfg = cfg
            .conditioning
            .as_ref()
            .and_then(|c| c.gcma.as_ref().map(|g| (c, g)));
        let gcma_at =
            |level: usize, decoder: bool, ch: usize, vb: VarBuilder<'_>| -> Result<Option<Gcma>> {
                match gcma_cfg {
                    Some((cc, g)) if g.levels.contains(&level) && (!decoder || g.decoder) => {
                        let fc = cc.cond_channels[cc.scale_for_level(level)];
                        Ok(Some(Gcma::new(g, ch, fc, groups, vb)?))
                    }
                    _ => Ok(None),
                }
            };
        let in_c = cfg.in_channels + cfg.ray_feature_channels();
        let in_conv = RingConv2d::new(in_c, cfg.base_channels, 3, 1, vb.pp("in_conv"))?;
        let mut skips = vec![cfg.base_channels];
        let mut ch = cfg.base_channels;
        let mut down = Vec::with_capacity(nl);
        for l in 0..nl {
            let vbl = vb.pp(format!("down.{l}"));
            let out = cfg.level_channels(l);
            let mut res = Vec::new();
            for j in 0..cfg.num_res_blocks {
                res.push(ResBlock::new(
                    ch,
                    out,
                    temb,
                    groups,
                    rs,
                    vbl.pp(format!("res.{j}")),
                )?);
                ch = out;
                skips.push(ch);
            }
            let gcma = gcma_at(l, false, ch, vbl.pp("gcma"))?;
            let resample = if l + 1 < nl {
                skips.push(ch);
                Some(RingConv2d::new(ch, ch, 3, 2, vbl.pp("downsample"))?)
            } else {
                None
            };
            down.push(Level {
                res,
                gcma,
                resample,
            });
        }
        let mid0 = ResBlock::new(ch, ch, temb, groups, rs, vb.pp("mid.res.0"))?;
        let pfc = match &cfg.pfc {
            Some(p) => Some(Pfc::new(p, ch, groups, vb.pp("mid.pfc"))?),
            None => None,
        };
        let mid1 = ResBlock::new(ch, ch, temb, groups, rs, vb.pp("mid.res.1"))?;
        let mut up = Vec::with_capacity(nl);
        for l in (0..nl).rev() {
            let vbl = vb.pp(format!("up.{l}"));
            let out = cfg.level_channels(l);
            let mut res = Vec::new();
            for j in 0..=cfg.num_res_blocks {
                let skip_c = skips
                    .pop()
                    .ok_or_else(|| Error::Config("internal: skip bookkeeping".into()))?;
                res.push(ResBlock::new(
                    ch + skip_c,
                    out,
                    temb,
                    groups,
                    rs,
                    vbl.pp(format!("res.{j}")),
                )?);
                ch = out;
            }
            let gcma = gcma_at(l, true, ch, vbl.pp("gcma"))?;
            let resample = if l > 0 {
                Some(RingConv2d::new(ch, ch, 3, 1, vbl.pp("upsample"))?)
            } else {
                None
            };
            up.push(Level {
                res,
                gcma,
                resample,
            });
        }
        let out_norm = group_norm(groups_for(ch, groups), ch, vb.pp("out_norm"))?;
        let out_conv = RingConv2d::new(ch, cfg.out_channels, 3, 1, vb.pp("out_conv"))?;
        let (fusion, pool) = match &cfg.conditioning {
            Some(cc) => {
                let fusion = ConditionFusion::new(cc, vb.pp("cond"))?;
                let pool = if cc.gcma.is_none() {
                    let last = *cc
                        .cond_channels
                        .last()
                        .ok_or_else(|| Error::Config("no scales".into()))?;
                    Some(candle_nn::linear(last, temb, vb.pp("cond.pool"))?)
                } else {
                    None
                };
                (Some(fusion), pool)
            }
            None => (None, None),
        };
        Ok(Self {
            ray_features: ray_feature_tensor(cfg, vb.device())?
                .map(|t| t.to_dtype(vb.dtype()))
                .transpose()?,
            cfg: cfg.clone(),
            in_conv,
            time0: candle_nn::linear(cfg.time.dim, temb, vb.pp("time.0"))?,
            time2: candle_nn::linear(temb, temb, vb.pp("time.2"))?,
            down,
            mid0,
            pfc,
            mid1,
            up,
            out_norm,
            out_conv,
            fusion,
            pool,
            recompute: None,
            span: tracing::span!(tracing::Level::TRACE, "denoiser"),
        })
    }

    /// The configuration the network was built from.
    pub fn config(&self) -> &DenoiserConfig {
        &self.cfg
    }

    /// The `[1, D, H, W]` ray-direction features concatenated to the input (`None` when disabled).
    pub fn ray_features(&self) -> Option<&Tensor> {
        self.ray_features.as_ref()
    }

    /// Replaces the ray-direction features (same shape), e.g. rolled in azimuth for an equivariance check
    /// or computed for a sensor with measured per-beam angles.
    pub fn set_ray_features(&mut self, features: Tensor) -> Result<()> {
        match &self.ray_features {
            Some(old) if old.dims() == features.dims() => {
                self.ray_features = Some(features);
                Ok(())
            }
            Some(old) => Err(shape_err(
                "ray features",
                format!("{:?}", old.dims()),
                features.dims(),
            )),
            None => Err(Error::Config(
                "ray features are disabled in this model".into(),
            )),
        }
    }

    /// Switches activation checkpointing for training ([`crate::recompute`]): with `on`, every
    /// residual block, GCMA and PFC layer is recomputed in the backward pass, and whoever calls
    /// `backward()` on a loss of this network's output must merge [`Self::recompute_tape`] into
    /// the gradients afterwards.
    pub fn set_recompute_blocks(&mut self, on: bool) {
        self.recompute = on.then(RecomputeTape::new);
    }

    /// Whether the blocks are recomputed in the backward pass.
    pub fn recomputes_blocks(&self) -> bool {
        self.recompute.is_some()
    }

    /// The tape on which recomputed blocks leave their parameters' gradients (`None` without
    /// activation checkpointing); see [`RecomputeTape::merge_into`].
    pub fn recompute_tape(&self) -> Option<&RecomputeTape> {
        self.recompute.as_ref()
    }

    /// A residual block, recomputed in the backward pass when checkpointing is on.
    fn res_block(&self, rb: &ResBlock, x: &Tensor, emb: &Tensor) -> Result<Tensor> {
        let Some(tape) = &self.recompute else {
            return rb.forward(x, emb);
        };
        let block = rb.clone();
        checkpoint(
            &[x, emb],
            rb.params(),
            tape,
            std::sync::Arc::new(move |t: &[&Tensor]| block.forward(t[0], t[1])),
        )
    }

    /// A decoder's residual block on `[x, skip]` (concatenated in channels). When checkpointing is
    /// on, the concatenation happens inside the recomputed block, so the graph keeps `x` and `skip`
    /// (which it holds anyway) rather than a third, concatenated copy.
    fn res_block_skip(
        &self,
        rb: &ResBlock,
        x: &Tensor,
        skip: &Tensor,
        emb: &Tensor,
    ) -> Result<Tensor> {
        let Some(tape) = &self.recompute else {
            return rb.forward(&Tensor::cat(&[x, skip], 1)?, emb);
        };
        let block = rb.clone();
        checkpoint(
            &[x, skip, emb],
            rb.params(),
            tape,
            std::sync::Arc::new(move |t: &[&Tensor]| {
                block.forward(&Tensor::cat(&[t[0], t[1]], 1)?, t[2])
            }),
        )
    }

    /// A decoder's upsampling (nearest, then a convolution), recomputed in the backward pass when
    /// checkpointing is on: the graph then keeps the small input, not the upsampled copy that the
    /// convolution reads (4 x the input).
    fn upsample(&self, conv: &RingConv2d, x: &Tensor) -> Result<Tensor> {
        let up = |conv: &RingConv2d, x: &Tensor| conv.forward(&crate::ops::upsample_nearest(x, 2)?);
        let Some(tape) = &self.recompute else {
            return up(conv, x);
        };
        let mut params = Vec::new();
        crate::recompute::push_weights(&mut params, conv.weights());
        let conv = conv.clone();
        checkpoint(
            &[x],
            params,
            tape,
            std::sync::Arc::new(move |t: &[&Tensor]| up(&conv, t[0])),
        )
    }

    /// A GCMA layer, recomputed in the backward pass when checkpointing is on.
    fn gcma_block(
        &self,
        blk: &Gcma,
        r: &Tensor,
        feat: &Tensor,
        geom: &crate::gcma::LevelGeometry,
        keep: Option<&Tensor>,
    ) -> Result<Tensor> {
        let Some(tape) = &self.recompute else {
            return blk.forward(r, feat, geom, keep);
        };
        let (block, geom, keep) = (blk.clone(), geom.clone(), keep.cloned());
        checkpoint(
            &[r, feat],
            blk.params(),
            tape,
            std::sync::Arc::new(move |t: &[&Tensor]| {
                block.forward(t[0], t[1], &geom, keep.as_ref())
            }),
        )
    }

    /// Whether the model takes an image condition.
    pub fn is_conditional(&self) -> bool {
        self.cfg.conditioning.is_some()
    }

    /// Builds the GCMA sampling geometry for `cameras` (one per view) with this model's config.
    pub fn geometry(
        &self,
        cameras: &[veila_geom::PinholeCamera],
        epi: &veila_geom::EpipolarConfig,
        device: &Device,
    ) -> Result<GcmaGeometry> {
        GcmaGeometry::new(&self.cfg, cameras, epi, device)
    }

    /// Runs the condition fusion (CACM or its ablation) once; the result is reused for every step.
    /// `geometry` is required when the model has GCMA and must have been built for this config.
    pub fn prepare_condition<'g>(
        &self,
        input: &ConditionInput,
        geometry: Option<&'g GcmaGeometry>,
    ) -> Result<PreparedCondition<'g>> {
        let (Some(cc), Some(fusion)) = (&self.cfg.conditioning, &self.fusion) else {
            return Err(Error::Config(
                "the model is unconditional; pass no condition".into(),
            ));
        };
        let views = cc.num_views;
        let flatten = |list: &Option<Vec<Tensor>>| -> Result<Option<Vec<Tensor>>> {
            list.as_ref()
                .map(|v| {
                    v.iter()
                        .map(|t| match t.dims() {
                            [b, nv, c, h, w] if *nv == views => {
                                Ok(t.reshape((b * nv, *c, *h, *w))?)
                            }
                            [_, _, _, _] => Ok(t.clone()),
                            d => Err(shape_err(
                                "image feature",
                                "[B*views, C, H, W] or [B, views, C, H, W]",
                                d,
                            )),
                        })
                        .collect()
                })
                .transpose()
        };
        let sem = flatten(&input.semantic)?;
        let dep = flatten(&input.depth)?;
        let fused = fusion.forward(sem.as_deref(), dep.as_deref())?;
        let n = fused[0].dim(0)?;
        if n % views != 0 {
            return Err(shape_err(
                "image features",
                format!("a multiple of {views} views in dim 0"),
                fused[0].dims(),
            ));
        }
        if cc.gcma.is_some() {
            match geometry {
                None => {
                    return Err(Error::Config(
                        "this model has GCMA: pass a GcmaGeometry".into(),
                    ));
                }
                Some(g) if g.num_views() != views => {
                    return Err(Error::Config(format!(
                        "geometry has {} view(s), the model {views}",
                        g.num_views()
                    )));
                }
                Some(_) => {}
            }
        }
        Ok(PreparedCondition {
            fused,
            geometry,
            keep: input.keep.clone(),
            batch: n / views,
            groups: None,
        })
    }

    /// [`Self::prepare_condition`] for a batch whose samples have their own rigs:
    /// `geometries[b]` is sample `b`'s (the same reference for samples of one rig). GCMA then
    /// attends each rig's samples with its geometry; a batch of one rig runs as a shared one.
    pub fn prepare_condition_per_sample<'g>(
        &self,
        input: &ConditionInput,
        geometries: &[&'g GcmaGeometry],
    ) -> Result<PreparedCondition<'g>> {
        let first = geometries.first().copied();
        let mut prepared = self.prepare_condition(input, first)?;
        if first.is_none() || geometries.len() != prepared.batch {
            return Err(Error::Config(format!(
                "{} geometries for a batch of {}",
                geometries.len(),
                prepared.batch
            )));
        }
        let mut distinct: Vec<(&'g GcmaGeometry, Vec<u32>)> = Vec::new();
        for (b, g) in geometries.iter().enumerate() {
            if g.num_views() != geometries[0].num_views() {
                return Err(Error::Config(format!(
                    "geometry {b} has {} view(s), geometry 0 {}",
                    g.num_views(),
                    geometries[0].num_views()
                )));
            }
            match distinct.iter_mut().find(|(d, _)| std::ptr::eq(*d, *g)) {
                Some((_, v)) => v.push(b as u32),
                None => distinct.push((g, vec![b as u32])),
            }
        }
        if distinct.len() == 1 {
            return Ok(prepared);
        }
        let views = geometries[0].num_views() as u32;
        let device = prepared.fused[0].device().clone();
        let mut inverse = vec![0u32; geometries.len()];
        for (pos, &b) in distinct.iter().flat_map(|(_, v)| v).enumerate() {
            inverse[b as usize] = pos as u32;
        }
        let inverse = Tensor::from_vec(inverse, geometries.len(), &device)?;
        let groups = distinct
            .into_iter()
            .map(|(geometry, samples)| {
                let view_idx: Vec<u32> = samples
                    .iter()
                    .flat_map(|&b| (0..views).map(move |v| b * views + v))
                    .collect();
                let (nv, ns) = (view_idx.len(), samples.len());
                Ok(GeometryGroup {
                    geometry,
                    views: Tensor::from_vec(view_idx, nv, &device)?,
                    samples: Tensor::from_vec(samples, ns, &device)?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        prepared.geometry = None;
        prepared.groups = Some(RigGroups { groups, inverse });
        Ok(prepared)
    }

    /// Predicts from the noisy range image `x: [B, C_in, H, W]` at noise level `t: [B]` (the scalar the
    /// diffusion code uses; see [`crate::TimeEmbeddingConfig::input_scale`]) under an optional prepared
    /// image condition; `None` runs the network unconditionally (every conditioning branch skipped).
    pub fn forward(
        &self,
        x: &Tensor,
        t: &Tensor,
        cond: Option<&PreparedCondition<'_>>,
    ) -> Result<Tensor> {
        let _enter = self.span.enter();
        let (b, c, h, w) = x.dims4()?;
        if c != self.cfg.in_channels || h != self.cfg.height() || w != self.cfg.width() {
            return Err(shape_err(
                "x",
                format!(
                    "[B, {}, {}, {}]",
                    self.cfg.in_channels,
                    self.cfg.height(),
                    self.cfg.width()
                ),
                x.dims(),
            ));
        }
        if t.dims() != [b] {
            return Err(shape_err("t", format!("[{b}]"), t.dims()));
        }
        if let Some(cd) = cond {
            if cd.batch != b {
                return Err(shape_err("condition batch", format!("{b}"), &[cd.batch]));
            }
            if let Some(k) = &cd.keep
                && k.dims() != [b]
            {
                return Err(shape_err("keep", format!("[{b}]"), k.dims()));
            }
        }
        let dtype = x.dtype();
        let mut emb = crate::ops::linear(
            &self.time2,
            &silu(&crate::ops::linear(
                &self.time0,
                &sinusoidal_embedding(
                    t,
                    self.cfg.time.dim,
                    self.cfg.time.max_period,
                    self.cfg.time.input_scale,
                )?
                .to_dtype(dtype)?,
            )?)?,
        )?;
        if let (Some(pool), Some(cd)) = (&self.pool, cond) {
            let last = cd
                .fused
                .last()
                .ok_or_else(|| Error::Config("no fused scales".into()))?;
            let (n, cf, _, _) = last.dims4()?;
            let pooled = last
                .to_dtype(dtype)?
                .flatten_from(2)?
                .mean(2)?
                .reshape((b, n / b, cf))?
                .mean(1)?;
            let mut g = crate::ops::linear(pool, &pooled)?;
            if let Some(k) = &cd.keep {
                g = g.broadcast_mul(&k.to_dtype(dtype)?.unsqueeze(1)?)?;
            }
            emb = (emb + g)?;
        }
        let emb = silu(&emb)?;
        let gcma = |blk: &Gcma, hcur: &Tensor, level: usize| -> Result<Option<Tensor>> {
            let Some(cd) = cond else { return Ok(None) };
            let cc = self
                .cfg
                .conditioning
                .as_ref()
                .ok_or_else(|| Error::Config("unconditional".into()))?;
            fn level_of(g: &GcmaGeometry, level: usize) -> Result<&crate::gcma::LevelGeometry> {
                g.level(level)
                    .ok_or_else(|| Error::Config(format!("the geometry has no GCMA level {level}")))
            }
            // the fused maps in the activations' dtype (mixed precision)
            let feat = &cd.fused[cc.scale_for_level(level)].to_dtype(hcur.dtype())?;
            let Some(groups) = &cd.groups else {
                let geom = cd.geometry.ok_or_else(|| {
                    Error::Config("this model has GCMA: pass a GcmaGeometry".into())
                })?;
                return Ok(Some(self.gcma_block(
                    blk,
                    hcur,
                    feat,
                    level_of(geom, level)?,
                    cd.keep.as_ref(),
                )?));
            };
            // each rig's samples with its geometry, then back into batch order
            let mut outs = Vec::with_capacity(groups.groups.len());
            for g in &groups.groups {
                let keep = cd
                    .keep
                    .as_ref()
                    .map(|k| k.index_select(&g.samples, 0))
                    .transpose()?;
                outs.push(self.gcma_block(
                    blk,
                    &hcur.index_select(&g.samples, 0)?,
                    &feat.index_select(&g.views, 0)?,
                    level_of(g.geometry, level)?,
                    keep.as_ref(),
                )?);
            }
            Ok(Some(
                Tensor::cat(&outs, 0)?.index_select(&groups.inverse, 0)?,
            ))
        };

        let input = match &self.ray_features {
            Some(rf) => Tensor::cat(
                &[x, &rf.to_dtype(dtype)?.broadcast_as((b, rf.dim(1)?, h, w))?],
                1,
            )?,
            None => x.clone(),
        };
        let mut hcur = self.in_conv.forward(&input)?;
        let mut skips = vec![hcur.clone()];
        for (l, lev) in self.down.iter().enumerate() {
            for (j, rb) in lev.res.iter().enumerate() {
                hcur = self.res_block(rb, &hcur, &emb)?;
                if j + 1 == lev.res.len()
                    && let Some(g) = &lev.gcma
                    && let Some(out) = gcma(g, &hcur, l)?
                {
                    hcur = out;
                }
                skips.push(hcur.clone());
            }
            if lev.res.is_empty()
                && let Some(g) = &lev.gcma
                && let Some(out) = gcma(g, &hcur, l)?
            {
                hcur = out;
            }
            if let Some(ds) = &lev.resample {
                hcur = ds.forward(&hcur)?;
                skips.push(hcur.clone());
            }
        }
        hcur = self.res_block(&self.mid0, &hcur, &emb)?;
        if let Some(p) = &self.pfc {
            hcur = match &self.recompute {
                Some(tape) => {
                    let block = p.clone();
                    checkpoint(
                        &[&hcur],
                        p.params(),
                        tape,
                        std::sync::Arc::new(move |t: &[&Tensor]| block.forward(t[0])),
                    )?
                }
                None => p.forward(&hcur)?,
            };
        }
        hcur = self.res_block(&self.mid1, &hcur, &emb)?;
        let nl = self.up.len();
        for (i, lev) in self.up.iter().enumerate() {
            let l = nl - 1 - i;
            for rb in &lev.res {
                let s = skips
                    .pop()
                    .ok_or_else(|| Error::Config("internal: skip bookkeeping".into()))?;
                hcur = self.res_block_skip(rb, &hcur, &s, &emb)?;
            }
            if let Some(g) = &lev.gcma
                && let Some(out) = gcma(g, &hcur, l)?
            {
                hcur = out;
            }
            if let Some(us) = &lev.resample {
                hcur = self.upsample(us, &hcur)?;
            }
        }
        let out = self.out_conv.forward(&self.out_norm.forward_silu(&hcur)?)?;
        Ok(out)
    }
}
