//! Fusion of the semantic and depth image features into the conditioning maps `F^(i)`:
//! the Confidence-Aware Conditioning Mechanism (equations 4-6) and its ablations.

use candle_core::Tensor;
use candle_nn::{Conv2dConfig, VarBuilder};

use crate::config::{ConditioningConfig, Cues, Fusion};
use crate::error::{Error, Result, shape_err};
use crate::ops::{Conv1x1, bilinear_resize};

/// CACM at one scale (equations 4-6):
///
/// ```text
/// F~_s = Conv1x1(F_s)                 F~_d = Conv1x1(Interp(F_d))     (eq. 4, Interp = bilinear)
/// c_s  = sigmoid(Conv3x3(F~_s))       c_d  = sigmoid(Conv3x3(F~_d))   (eq. 5, one channel per cue)
/// F    = (c_s F~_s + c_d F~_d) / (c_s + c_d + delta)                  (eq. 6)
/// ```
///
/// Weights: `proj_s`, `proj_d` (1x1), `conf_s`, `conf_d` (3x3, zero padding, 1 output channel).
/// With both confidences at 0 the output is exactly 0 (finite for any `delta > 0`).
#[derive(Debug, Clone)]
pub struct Cacm {
    proj_s: Conv1x1,
    proj_d: Conv1x1,
    conf_s: candle_nn::Conv2d,
    conf_d: candle_nn::Conv2d,
    delta: f64,
    span: tracing::Span,
}

impl Cacm {
    /// `sem_c`, `depth_c`: encoder widths; `out_c`: width of `F^(i)`.
    pub fn new(
        sem_c: usize,
        depth_c: usize,
        out_c: usize,
        delta: f32,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        let conv3 = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        Ok(Self {
            proj_s: Conv1x1::new(sem_c, out_c, true, vb.pp("proj_s"))?,
            proj_d: Conv1x1::new(depth_c, out_c, true, vb.pp("proj_d"))?,
            conf_s: candle_nn::conv2d(out_c, 1, 3, conv3, vb.pp("conf_s"))?,
            conf_d: candle_nn::conv2d(out_c, 1, 3, conv3, vb.pp("conf_d"))?,
            delta: f64::from(delta),
            span: tracing::span!(tracing::Level::TRACE, "cacm"),
        })
    }

    /// Fuses `sem: [N, D_s, H, W]` and `depth: [N, D_d, H', W']` into `[N, out_c, H, W]`.
    pub fn forward(&self, sem: &Tensor, depth: &Tensor) -> Result<Tensor> {
        self.forward_with_confidence(sem, depth).map(|(f, _, _)| f)
    }

    /// As [`Cacm::forward`], also returning the confidence maps `c_s`, `c_d` (`[N, 1, H, W]`).
    pub fn forward_with_confidence(
        &self,
        sem: &Tensor,
        depth: &Tensor,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let _enter = self.span.enter();
        let (_, _, h, w) = sem.dims4()?;
        let fs = self.proj_s.forward(sem)?;
        let fd = self.proj_d.forward(&bilinear_resize(depth, h, w)?)?;
        let cs = candle_nn::ops::sigmoid(&crate::ops::conv2d_module(&self.conf_s, &fs)?)?;
        let cd = candle_nn::ops::sigmoid(&crate::ops::conv2d_module(&self.conf_d, &fd)?)?;
        let num = (fs.broadcast_mul(&cs)? + fd.broadcast_mul(&cd)?)?;
        let den = ((&cs + &cd)? + self.delta)?;
        Ok((num.broadcast_div(&den)?, cs, cd))
    }
}

/// One scale of the fusion, whichever ablation is configured.
#[derive(Debug, Clone)]
enum ScaleFusion {
    Cacm(Cacm),
    /// `Conv1x1(cat(F_s, Interp(F_d)))`: the "w/o CACM" ablation.
    Concat(Conv1x1),
    /// `Conv1x1(F_s)`: "E_s only".
    Semantic(Conv1x1),
    /// `Conv1x1(Interp(F_d))`: "E_d only".
    Depth(Conv1x1),
}

/// Turns encoder pyramids into the fused conditioning maps `F^(i)`, one per scale.
///
/// Weights under `fuse.{i}`; see [`Cacm`] for the CACM names, `proj` for the other variants.
#[derive(Debug, Clone)]
pub struct ConditionFusion {
    scales: Vec<ScaleFusion>,
    sizes: Vec<[usize; 2]>,
    cues: Cues,
}

impl ConditionFusion {
    /// Builds the fusion for `cfg`.
    pub fn new(cfg: &ConditioningConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let mut scales = Vec::new();
        for i in 0..cfg.num_scales() {
            let vb = vb.pp(format!("fuse.{i}"));
            let out = cfg.cond_channels[i];
            let s = match cfg.cues {
                Cues::Both => match cfg.fusion {
                    Fusion::Cacm => ScaleFusion::Cacm(Cacm::new(
                        cfg.semantic_channels[i],
                        cfg.depth_channels[i],
                        out,
                        cfg.cacm_delta,
                        vb,
                    )?),
                    Fusion::Concat => ScaleFusion::Concat(Conv1x1::new(
                        cfg.semantic_channels[i] + cfg.depth_channels[i],
                        out,
                        true,
                        vb.pp("proj"),
                    )?),
                },
                Cues::SemanticOnly => ScaleFusion::Semantic(Conv1x1::new(
                    cfg.semantic_channels[i],
                    out,
                    true,
                    vb.pp("proj"),
                )?),
                Cues::DepthOnly => ScaleFusion::Depth(Conv1x1::new(
                    cfg.depth_channels[i],
                    out,
                    true,
                    vb.pp("proj"),
                )?),
            };
            scales.push(s);
        }
        Ok(Self {
            scales,
            sizes: cfg.feature_sizes.clone(),
            cues: cfg.cues,
        })
    }

    /// Fuses per-scale features (`[N, D, H, W]`, `N` = batch x views) into `F^(i)`, `[N, C_i, H_i, W_i]`.
    ///
    /// `semantic` is required unless the config is depth-only, `depth` unless it is semantic-only; each
    /// must have one tensor per scale. Semantic maps must already be `feature_sizes[i]`; depth maps of any
    /// size are resized bilinearly to it.
    pub fn forward(
        &self,
        semantic: Option<&[Tensor]>,
        depth: Option<&[Tensor]>,
    ) -> Result<Vec<Tensor>> {
        let n = self.scales.len();
        let need = |name: &str, t: Option<&[Tensor]>| -> Result<Vec<Tensor>> {
            match t {
                Some(v) if v.len() == n => Ok(v.to_vec()),
                Some(v) => Err(shape_err(
                    format!("{name} feature list"),
                    format!("{n} scales"),
                    &[v.len()],
                )),
                None => Err(Error::Config(format!("this model needs {name} features"))),
            }
        };
        let sem = if self.cues != Cues::DepthOnly {
            Some(need("semantic", semantic)?)
        } else {
            None
        };
        let dep = if self.cues != Cues::SemanticOnly {
            Some(need("depth", depth)?)
        } else {
            None
        };
        let mut out = Vec::with_capacity(n);
        for (i, s) in self.scales.iter().enumerate() {
            let [h, w] = self.sizes[i];
            let check_sem = |t: &Tensor| -> Result<()> {
                let d = t.dims();
                if d.len() != 4 || d[2] != h || d[3] != w {
                    return Err(shape_err(
                        format!("semantic feature {i}"),
                        format!("[N, C, {h}, {w}]"),
                        d,
                    ));
                }
                Ok(())
            };
            let f = match s {
                ScaleFusion::Cacm(m) => {
                    let (fs, fd) = (
                        &sem.as_ref().expect("checked")[i],
                        &dep.as_ref().expect("checked")[i],
                    );
                    check_sem(fs)?;
                    m.forward(fs, fd)?
                }
                ScaleFusion::Concat(p) => {
                    let (fs, fd) = (
                        &sem.as_ref().expect("checked")[i],
                        &dep.as_ref().expect("checked")[i],
                    );
                    check_sem(fs)?;
                    p.forward(&Tensor::cat(&[fs, &bilinear_resize(fd, h, w)?], 1)?)?
                }
                ScaleFusion::Semantic(p) => {
                    let fs = &sem.as_ref().expect("checked")[i];
                    check_sem(fs)?;
                    p.forward(fs)?
                }
                ScaleFusion::Depth(p) => {
                    p.forward(&bilinear_resize(&dep.as_ref().expect("checked")[i], h, w)?)?
                }
            };
            out.push(f);
        }
        Ok(out)
    }
}
