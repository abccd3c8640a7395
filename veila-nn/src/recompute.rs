//! Activation checkpointing: a block's forward pass keeps no graph, its backward pass runs it again.
//!
//! [`checkpoint`] runs a block (a residual block, a GCMA or PFC layer) on detached inputs, keeps
//! only its output, and puts one node in candle's graph whose inputs are the block's inputs. When
//! the backward pass reaches that node it runs the block again with tracked copies of the inputs,
//! back-propagates the incoming gradient through the recomputed block, hands the inputs' gradients
//! back to candle and leaves the parameters' gradients on a [`RecomputeTape`].
//!
//! Why a tape: candle's custom ops return gradients for their (at most three) tensor inputs only,
//! and a block's weights are not among them. So the caller of `backward()` merges the tape into
//! its [`GradStore`] afterwards ([`RecomputeTape::merge_into`]); the trainer does this after every
//! backward pass. Merging drains the tape, so the next pass starts empty.
//!
//! What the graph keeps per block is its inputs and its output (the next block's input): about
//! `C_in·N + C_out·N` values instead of the block's every intermediate. The cost is a second forward
//! pass of every block during the backward pass. It works the same on every device: the node's
//! forward is a storage copy ([`BackendStorage::try_clone`]), its backward plain candle ops.
//!
//! The recomputed block runs the same kernels on the same inputs, so its gradients equal the plain
//! path's up to the order in which a shared input's gradients are summed (tested in
//! `tests/recompute.rs`). Blocks must be deterministic (no dropout).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use candle_core::backend::BackendStorage;
use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor, TensorId, Var};

use crate::error::{Error, Result};

/// Parameter gradients found by recomputed blocks during a backward pass, waiting to be merged into
/// that pass's [`GradStore`]. Clones share one tape.
#[derive(Debug, Clone, Default)]
pub struct RecomputeTape {
    grads: Arc<Mutex<HashMap<TensorId, (Tensor, Tensor)>>>,
}

impl RecomputeTape {
    /// An empty tape.
    pub fn new() -> Self {
        Self::default()
    }

    fn lock(&self) -> Result<std::sync::MutexGuard<'_, HashMap<TensorId, (Tensor, Tensor)>>> {
        self.grads
            .lock()
            .map_err(|_| Error::Config("the recompute tape's lock is poisoned".into()))
    }

    /// Adds `grad` to the gradient of `param` on the tape.
    fn add(&self, param: &Tensor, grad: &Tensor) -> Result<()> {
        let mut map = self.lock()?;
        let sum = match map.remove(&param.id()) {
            Some((_, prev)) => (prev + grad)?,
            None => grad.clone(),
        };
        map.insert(param.id(), (param.clone(), sum));
        Ok(())
    }

    /// Number of parameters with a gradient on the tape.
    pub fn len(&self) -> Result<usize> {
        Ok(self.lock()?.len())
    }

    /// Whether the tape holds no gradient.
    pub fn is_empty(&self) -> Result<bool> {
        Ok(self.len()? == 0)
    }

    /// Adds every gradient on the tape to `grads` (summing with what the plain graph found for the
    /// same parameter) and empties the tape.
    pub fn merge_into(&self, grads: &mut GradStore) -> Result<()> {
        let drained: Vec<(Tensor, Tensor)> = self.lock()?.drain().map(|(_, v)| v).collect();
        for (param, g) in drained {
            let sum = match grads.remove(&param) {
                Some(prev) => (prev + g)?,
                None => g,
            };
            grads.insert(&param, sum);
        }
        Ok(())
    }

    /// Drops every gradient on the tape (after a backward pass whose gradients are not used).
    pub fn clear(&self) -> Result<()> {
        self.lock()?.clear();
        Ok(())
    }
}

/// Collects trainable tensors: a weight and an optional bias.
pub(crate) fn push_weights(out: &mut Vec<Tensor>, (w, b): (&Tensor, Option<&Tensor>)) {
    out.push(w.clone());
    out.extend(b.cloned());
}

/// Collects a `Linear` layer's weight and bias.
pub(crate) fn push_linear(out: &mut Vec<Tensor>, l: &candle_nn::Linear) {
    push_weights(out, (l.weight(), l.bias()));
}

/// A block as [`checkpoint`] runs it: the differentiable input, the optional second one.
pub type BlockFn = dyn Fn(&Tensor, Option<&Tensor>) -> Result<Tensor> + Send + Sync;

/// The graph node of a checkpointed block.
struct Checkpoint {
    block: Arc<BlockFn>,
    params: Vec<Tensor>,
    tape: RecomputeTape,
}

/// The node's forward pass: the block's output, computed before the node was applied, copied into
/// the node's own storage (it arrives contiguous from offset 0, see [`checkpoint`]).
fn copy_out<S: BackendStorage>(s: &S, l: &Layout) -> candle_core::Result<(S, Shape)> {
    Ok((s.try_clone(l)?, l.shape().clone()))
}

fn to_candle(e: Error) -> candle_core::Error {
    match e {
        Error::Candle(c) => c,
        other => candle_core::Error::Msg(other.to_string()),
    }
}

impl Checkpoint {
    /// Runs the block again on tracked copies of its inputs and back-propagates `grad` through
    /// it: the inputs' gradients are returned, the parameters' go on the tape.
    fn recompute(
        &self,
        x: &Tensor,
        c: Option<&Tensor>,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let xv = Var::from_tensor(&x.detach())?;
        let cv = c.map(|c| Var::from_tensor(&c.detach())).transpose()?;
        let y = (self.block)(xv.as_tensor(), cv.as_ref().map(Var::as_tensor))?;
        let surrogate = (y * grad.detach())?.sum_all()?;
        let grads = surrogate.backward()?;
        for p in &self.params {
            if let Some(g) = grads.get(p) {
                self.tape.add(p, g)?;
            }
        }
        Ok((
            grads.get(xv.as_tensor()).cloned(),
            cv.and_then(|cv| grads.get(cv.as_tensor()).cloned()),
        ))
    }
}

impl CustomOp2 for Checkpoint {
    fn name(&self) -> &'static str {
        "veila-checkpoint"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        out: &CpuStorage,
        l: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        copy_out(out, l)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        out: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        copy_out(out, l)
    }

    fn bwd(
        &self,
        x: &Tensor,
        _out: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let (gx, _) = self.recompute(x, None, grad).map_err(to_candle)?;
        Ok((gx, None))
    }
}

impl CustomOp3 for Checkpoint {
    fn name(&self) -> &'static str {
        "veila-checkpoint"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
        out: &CpuStorage,
        l: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        copy_out(out, l)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
        out: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        copy_out(out, l)
    }

    fn bwd(
        &self,
        x: &Tensor,
        c: &Tensor,
        _out: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (gx, gc) = self.recompute(x, Some(c), grad).map_err(to_candle)?;
        Ok((gx, gc, None))
    }
}

/// Runs `block(x, c)` keeping only its output in the graph; the backward pass recomputes it.
///
/// `params` are the block's trainable tensors: their gradients go on `tape`. When neither input
/// takes part in a graph (evaluation), the block simply runs: there is nothing to recompute for.
pub fn checkpoint(
    x: &Tensor,
    c: Option<&Tensor>,
    params: Vec<Tensor>,
    tape: &RecomputeTape,
    block: Arc<BlockFn>,
) -> Result<Tensor> {
    if !x.track_op() && !c.is_some_and(Tensor::track_op) {
        return block(x, c);
    }
    let out = block(&x.detach(), c.map(Tensor::detach).as_ref())?.detach();
    // the node copies the output's storage as it lies: make it exactly the output
    let out = if out.layout().contiguous_offsets() == Some((0, out.elem_count())) {
        out
    } else {
        out.force_contiguous()?
    };
    let op = Checkpoint {
        block,
        params,
        tape: tape.clone(),
    };
    Ok(match c {
        Some(c) => x.apply_op3(c, &out, op)?,
        None => x.apply_op2(&out, op)?,
    })
}
