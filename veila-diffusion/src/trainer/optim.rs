//! AdamW with exportable state.
//!
//! The update is exactly candle-nn's `AdamW` (same operations in the same order; a test checks
//! bit-for-bit agreement), but the moments and step counter can be saved and restored, which
//! `candle_nn::AdamW` does not allow and exact resume needs.

use std::collections::HashMap;

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

/// AdamW over named variables (decoupled weight decay, bias-corrected moments).
#[derive(Debug)]
pub struct AdamW {
    slots: Vec<Slot>,
    step_t: usize,
    params: ParamsAdamW,
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

    /// One update; every gradient is multiplied by `grad_scale` first (gradient clipping).
    pub fn step(&mut self, grads: &GradStore, grad_scale: f64) -> Result<()> {
        self.step_t += 1;
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
