//! AdamW with exportable state.
//!
//! The update is exactly candle-nn's `AdamW` (same operations in the same order; a test checks
//! bit-for-bit agreement; a fused update, [`AdamW::set_fused`], must keep those roundings), but the moments and step counter can be saved and restored, which
//! `candle_nn::AdamW` does not allow and exact resume needs.

use std::collections::HashMap;
use std::sync::Arc;

use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};
pub use candle_nn::ParamsAdamW;

use crate::error::{Error, Result};

#[derive(Debug)]
struct Slot {
    name: String,
    var: Var,
    m: Var,
    v: Var,
}

/// One parameter's tensors in a fused update: the parameter, its gradient, its two moments.
pub type AdamSlot<'a> = (&'a Var, &'a Tensor, &'a Var, &'a Var);

/// An AdamW update of every slot at once, with hyper-parameters, the step number (from 1) and
/// the gradients' factor; `Ok(false)` where it does not run for these tensors.
pub type FusedAdamW =
    dyn Fn(&[AdamSlot<'_>], &ParamsAdamW, usize, f64) -> candle_core::Result<bool> + Send + Sync;

struct Fused(Arc<FusedAdamW>);

impl std::fmt::Debug for Fused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FusedAdamW")
    }
}

/// AdamW over named variables (decoupled weight decay, bias-corrected moments).
#[derive(Debug)]
pub struct AdamW {
    slots: Vec<Slot>,
    step_t: usize,
    params: ParamsAdamW,
    fused: Option<Fused>,
}

impl AdamW {
    /// Creates the optimizer for `vars` (non-float variables are ignored).
    pub fn new(vars: Vec<(String, Var)>, params: ParamsAdamW) -> Result<Self> {
        let slots = vars
            .into_iter()
            .filter(|(_, v)| v.dtype().is_float())
            .map(|(name, var)| {
                let m = Var::zeros(var.shape(), var.dtype(), var.device())?;
                let v = Var::zeros(var.shape(), var.dtype(), var.device())?;
                Ok(Slot { name, var, m, v })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            slots,
            step_t: 0,
            params,
            fused: None,
        })
    }

    /// Hyper-parameters.
    pub fn params(&self) -> &ParamsAdamW {
        &self.params
    }

    /// Current learning rate.
    pub fn learning_rate(&self) -> f64 {
        self.params.lr
    }

    /// Sets the learning rate for the next step.
    pub fn set_learning_rate(&mut self, lr: f64) {
        self.params.lr = lr;
    }

    /// Number of steps taken (for bias correction).
    pub fn step_count(&self) -> usize {
        self.step_t
    }

    /// Runs every update through `fused` where it accepts the parameters (it returns `Ok(false)`
    /// where it does not run, and the per-tensor update runs instead): the application layer
    /// passes `veila-nn`'s one-launch GPU AdamW, which has this update's arithmetic.
    pub fn set_fused(&mut self, fused: Option<Arc<FusedAdamW>>) {
        self.fused = fused.map(Fused);
    }

    /// One update; every gradient is multiplied by `grad_scale` first (gradient clipping). With a
    /// [fused update](Self::set_fused) that accepts the parameters (on a GPU: one launch for all of
    /// them), that; otherwise about 14 tensor ops per parameter.
    pub fn step(&mut self, grads: &GradStore, grad_scale: f64) -> Result<()> {
        self.step_t += 1;
        if let Some(Fused(f)) = &self.fused {
            let slots: Vec<AdamSlot<'_>> = self
                .slots
                .iter()
                .filter_map(|s| {
                    grads
                        .get(s.var.as_tensor())
                        .map(|g| (&s.var, g, &s.m, &s.v))
                })
                .collect();
            if f(&slots, &self.params, self.step_t, grad_scale)? {
                return Ok(());
            }
        }
        let p = &self.params;
        let lr = p.lr;
        let lr_lambda = lr * p.weight_decay;
        let scale_m = 1f64 / (1f64 - p.beta1.powi(self.step_t as i32));
        let scale_v = 1f64 / (1f64 - p.beta2.powi(self.step_t as i32));
        for s in &self.slots {
            let Some(g) = grads.get(s.var.as_tensor()) else {
                continue;
            };
            let g = if grad_scale == 1.0 {
                g.clone()
            } else {
                (g * grad_scale)?
            };
            let next_m = ((s.m.as_tensor() * p.beta1)? + (&g * (1.0 - p.beta1))?)?;
            let next_v = ((s.v.as_tensor() * p.beta2)? + (g.sqr()? * (1.0 - p.beta2))?)?;
            let m_hat = (&next_m * scale_m)?;
            let v_hat = (&next_v * scale_v)?;
            let next_theta = (s.var.as_tensor() * (1f64 - lr_lambda))?;
            let adjusted = (m_hat / (v_hat.sqrt()? + p.eps)?)?;
            let next_theta = (next_theta - (adjusted * lr)?)?;
            s.m.set(&next_m)?;
            s.v.set(&next_v)?;
            s.var.set(&next_theta)?;
        }
        Ok(())
    }

    /// The moments as `m.<name>` / `v.<name>` tensors.
    pub fn state_tensors(&self) -> HashMap<String, Tensor> {
        let mut out = HashMap::with_capacity(2 * self.slots.len());
        for s in &self.slots {
            out.insert(format!("m.{}", s.name), s.m.as_tensor().clone());
            out.insert(format!("v.{}", s.name), s.v.as_tensor().clone());
        }
        out
    }

    /// Restores moments and step counter; every moment must be present with the right shape.
    pub fn load_state(&mut self, tensors: &HashMap<String, Tensor>, step_t: usize) -> Result<()> {
        let mut problems = Vec::new();
        for s in &self.slots {
            for (prefix, var) in [("m", &s.m), ("v", &s.v)] {
                let key = format!("{prefix}.{}", s.name);
                match tensors.get(&key) {
                    None => problems.push(format!("missing {key}")),
                    Some(t) if t.shape() != var.shape() => {
                        problems.push(format!("{key}: shape {:?} != {:?}", t.dims(), var.dims()))
                    }
                    Some(_) => {}
                }
            }
        }
        if !problems.is_empty() {
            return Err(Error::Data(format!(
                "optimizer state: {}",
                problems.join(", ")
            )));
        }
        for s in &self.slots {
            for (prefix, var) in [("m", &s.m), ("v", &s.v)] {
                if let Some(t) = tensors.get(&format!("{prefix}.{}", s.name)) {
                    var.set(&t.to_dtype(var.dtype())?.to_device(var.device())?)?;
                }
            }
        }
        self.step_t = step_t;
        Ok(())
    }
}
