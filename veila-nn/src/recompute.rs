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
//! What the graph keeps per block is its inputs and its output (the next block's input, held once:
//! the node's forward pass copies the output into its own storage and drops the original): about
//! `C_in·N + C_out·N` values instead of the block's every intermediate. A decoder block takes its
//! skip connection as a separate input and concatenates inside, so the concatenation is not kept. The cost is a second forward
//! pass of every block during the backward pass. It works the same on every device: the node's
//! forward is a storage copy ([`BackendStorage::try_clone`]), its backward plain candle ops.
//!
//! [`with_backward`] puts the same node in the graph with a hand-written gradient (candle ops)
//! instead of a recomputation, for ops whose composition's backward pass keeps far more than the
//! gradient needs (GCMA's bilinear gather: its gradient is a scatter).
//!
//! The recomputed block runs the same kernels on the same inputs, so its gradients equal the plain
//! path's up to the order in which a shared input's gradients are summed (tested in
//! `tests/it/recompute.rs`). Blocks must be deterministic (no dropout).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use candle_core::backend::BackendStorage;
use candle_core::backprop::GradStore;
use candle_core::{
    CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Storage, Tensor, TensorId, Var,
};

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

/// A block as [`checkpoint`] runs it: on its inputs (one to three), in order.
pub type BlockFn = dyn Fn(&[&Tensor]) -> Result<Tensor> + Send + Sync;

/// A gradient rule as [`with_backward`] takes it: from the node's inputs (detached) and the
/// gradient of its output, the inputs' gradients in order (`None` for an input without one).
pub type GradFn = dyn Fn(&[&Tensor], &Tensor) -> Result<Vec<Option<Tensor>>> + Send + Sync;

/// How a node's backward pass finds its inputs' gradients.
enum Rule {
    /// Recompute the block (or its pieces, whose outputs are the node's output concatenated along
    /// `dim`, each with its length along `dim`: one piece at a time) and back-propagate through it;
    /// the parameters' gradients go on `tape`.
    Recompute {
        pieces: Vec<(Arc<BlockFn>, usize)>,
        dim: usize,
        params: Vec<Tensor>,
        tape: RecomputeTape,
    },
    /// A hand-written gradient in candle ops.
    Explicit(Arc<GradFn>),
}

/// The graph node of a checkpointed block (or of an op with a hand-written gradient). Its inputs
/// are the block's; the block's output waits in `pending` until candle runs the node's forward
/// pass, which copies it into the node's own storage and drops it, so the graph holds each block
/// output once.
struct Checkpoint {
    rule: Rule,
    pending: Mutex<Option<Tensor>>,
}

fn to_candle(e: Error) -> candle_core::Error {
    match e {
        Error::Candle(c) => c,
        other => candle_core::Error::Msg(other.to_string()),
    }
}

impl Checkpoint {
    /// The block's output, taken from `pending` (the node's forward pass runs once).
    fn take_output(&self) -> candle_core::Result<Tensor> {
        self.pending
            .lock()
            .map_err(|_| candle_core::Error::Msg("a checkpoint's lock is poisoned".into()))?
            .take()
            .ok_or_else(|| candle_core::Error::Msg("a checkpoint node ran twice".into()))
    }

    /// The node's forward pass: a copy of the block's output in this backend's storage.
    fn copy_output<S>(
        &self,
        pick: impl Fn(&Storage) -> Option<&S>,
    ) -> candle_core::Result<(S, Shape)>
    where
        S: BackendStorage,
    {
        let out = self.take_output()?;
        let (storage, layout) = out.storage_and_layout();
        let Some(s) = pick(&storage) else {
            candle_core::bail!("a checkpoint's output is on another device than its inputs")
        };
        Ok((s.try_clone(layout)?, layout.shape().clone()))
    }

    fn cpu_out(&self) -> candle_core::Result<(CpuStorage, Shape)> {
        self.copy_output(|s| match s {
            Storage::Cpu(c) => Some(c),
            _ => None,
        })
    }

    #[cfg(feature = "cuda")]
    fn cuda_out(&self) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        self.copy_output(|s| match s {
            Storage::Cuda(c) => Some(c),
            _ => None,
        })
    }

    /// The inputs' gradients for the output's gradient `grad` (`None` for an input outside the
    /// graph), by the node's rule.
    fn backward(&self, inputs: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        match &self.rule {
            Rule::Recompute {
                pieces,
                dim,
                params,
                tape,
            } => recompute(pieces, *dim, params, tape, inputs, grad),
            Rule::Explicit(f) => {
                let detached: Vec<Tensor> = inputs.iter().map(|t| t.detach()).collect();
                let refs: Vec<&Tensor> = detached.iter().collect();
                let grads = f(&refs, &grad.detach())?;
                if grads.len() != inputs.len() {
                    return Err(Error::Config(format!(
                        "a gradient rule gave {} gradients for {} inputs",
                        grads.len(),
                        inputs.len()
                    )));
                }
                // an input outside the graph gets none (candle would add it up for nothing)
                Ok(grads
                    .into_iter()
                    .zip(inputs)
                    .map(|(g, t)| g.filter(|_| t.track_op()))
                    .collect())
            }
        }
    }

    fn backward_candle(
        &self,
        inputs: &[&Tensor],
        grad: &Tensor,
    ) -> candle_core::Result<Vec<Option<Tensor>>> {
        self.backward(inputs, grad).map_err(to_candle)
    }
}

/// Runs a block (its `pieces`, outputs concatenated along `dim`) again on its inputs (tracked
/// copies of those that take part in the graph) and back-propagates `grad` through it: the
/// inputs' gradients are returned (`None` for an input outside the graph), the parameters' go on
/// `tape`. A block of several pieces does this one piece at a time: each piece's gradients are
/// added up before the next piece is recomputed, so only one piece's graph exists at a time.
fn recompute(
    pieces: &[(Arc<BlockFn>, usize)],
    dim: usize,
    params: &[Tensor],
    tape: &RecomputeTape,
    inputs: &[&Tensor],
    grad: &Tensor,
) -> Result<Vec<Option<Tensor>>> {
    let vars = inputs
        .iter()
        .map(|t| {
            t.track_op()
                .then(|| Var::from_tensor(&t.detach()))
                .transpose()
        })
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let fresh: Vec<Tensor> = inputs
        .iter()
        .zip(&vars)
        .map(|(t, v)| {
            v.as_ref()
                .map_or_else(|| t.detach(), |v| v.as_tensor().clone())
        })
        .collect();
    let fresh: Vec<&Tensor> = fresh.iter().collect();
    let grad = grad.detach();
    let mut sums: Vec<Option<Tensor>> = vec![None; vars.len()];
    let mut start = 0;
    for (piece, len) in pieces {
        let y = piece(&fresh)?;
        let g = if pieces.len() == 1 {
            grad.clone()
        } else {
            grad.narrow(dim, start, *len)?
        };
        start += len;
        let grads = (y * g)?.sum_all()?.backward()?;
        for p in params {
            if let Some(g) = grads.get(p) {
                tape.add(p, g)?;
            }
        }
        for (sum, v) in sums.iter_mut().zip(&vars) {
            let Some(g) = v.as_ref().and_then(|v| grads.get(v.as_tensor())) else {
                continue;
            };
            *sum = Some(match sum.take() {
                Some(prev) => (prev + g)?,
                None => g.clone(),
            });
        }
    }
    Ok(sums)
}

impl CustomOp1 for Checkpoint {
    fn name(&self) -> &'static str {
        "veila-checkpoint"
    }

    fn cpu_fwd(&self, _: &CpuStorage, _: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        self.cpu_out()
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        self.cuda_out()
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> candle_core::Result<Option<Tensor>> {
        let mut g = self.backward_candle(&[x], grad)?;
        Ok(g.swap_remove(0))
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
        _: &CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        self.cpu_out()
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        self.cuda_out()
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let mut g = self.backward_candle(&[a, b], grad)?.into_iter();
        Ok((g.next().flatten(), g.next().flatten()))
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
        _: &CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        self.cpu_out()
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        self.cuda_out()
    }

    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let mut g = self.backward_candle(&[a, b, c], grad)?.into_iter();
        Ok((g.next().flatten(), g.next().flatten(), g.next().flatten()))
    }
}

/// Runs `block(inputs)` keeping only its output in the graph; the backward pass recomputes it.
///
/// `inputs`: one to three tensors, the block's differentiable inputs (a residual block's input,
/// its skip connection and the time embedding, for example). `params` are the block's trainable
/// tensors: their gradients go on `tape`. When no input takes part in a graph (evaluation), the
/// block simply runs: there is nothing to recompute for.
pub fn checkpoint(
    inputs: &[&Tensor],
    params: Vec<Tensor>,
    tape: &RecomputeTape,
    block: Arc<BlockFn>,
) -> Result<Tensor> {
    checkpoint_pieces(inputs, params, tape, vec![block], 0)
}

/// [`checkpoint`] for a block computed in pieces: its output is the pieces' outputs concatenated
/// along `dim`, and the backward pass recomputes and back-propagates one piece at a time, so that
/// only one piece's intermediates exist at once (a convolution a tile of output rows at a time).
/// The graph holds one node, one output; every piece reads all of `inputs`.
pub fn checkpoint_pieces(
    inputs: &[&Tensor],
    params: Vec<Tensor>,
    tape: &RecomputeTape,
    pieces: Vec<Arc<BlockFn>>,
    dim: usize,
) -> Result<Tensor> {
    let detached: Vec<Tensor> = inputs.iter().map(|t| t.detach()).collect();
    let refs: Vec<&Tensor> = detached.iter().collect();
    let outs = pieces
        .iter()
        .map(|p| p(&refs).map(|t| t.detach()))
        .collect::<Result<Vec<_>>>()?;
    drop(refs);
    drop(detached);
    let out = match outs.as_slice() {
        [] => return Err(Error::Config("a checkpointed block has no pieces".into())),
        [one] => one.clone(),
        many => Tensor::cat(many, dim)?,
    };
    if !inputs.iter().any(|t| t.track_op()) {
        return Ok(out);
    }
    // a single piece takes the whole gradient: its length is never read
    let lens = match outs.as_slice() {
        [_] => vec![0],
        many => many
            .iter()
            .map(|t| t.dim(dim))
            .collect::<candle_core::Result<Vec<_>>>()?,
    };
    drop(outs);
    checkpoint_node(
        inputs,
        Rule::Recompute {
            pieces: pieces.into_iter().zip(lens).collect(),
            dim,
            params,
            tape: tape.clone(),
        },
        out,
    )
}

/// `op(inputs)` (one to three inputs) as one graph node whose backward pass is `grad` (candle ops,
/// so it runs on every device): the graph keeps the inputs and the output, and neither the op's
/// intermediates nor those of a recomputation exist in the backward pass (a gather's gradient is
/// a scatter, not the backward pass of four `index_select`s and their products). `op` runs on
/// detached inputs; when no input takes part in a graph its output is returned as it is.
pub fn with_backward(
    inputs: &[&Tensor],
    op: impl FnOnce(&[&Tensor]) -> Result<Tensor>,
    grad: Arc<GradFn>,
) -> Result<Tensor> {
    let detached: Vec<Tensor> = inputs.iter().map(|t| t.detach()).collect();
    let out = op(&detached.iter().collect::<Vec<_>>())?.detach();
    drop(detached);
    if !inputs.iter().any(|t| t.track_op()) {
        return Ok(out);
    }
    checkpoint_node(inputs, Rule::Explicit(grad), out)
}

/// The graph node of [`checkpoint_pieces`] or [`with_backward`] for its detached output `out`.
fn checkpoint_node(inputs: &[&Tensor], rule: Rule, out: Tensor) -> Result<Tensor> {
    // the node copies the output's storage as it lies: make it exactly the output
    let out = if out.layout().contiguous_offsets() == Some((0, out.elem_count())) {
        out
    } else {
        out.force_contiguous()?
    };
    let op = Checkpoint {
        rule,
        pending: Mutex::new(Some(out)),
    };
    Ok(match inputs {
        [a] => a.apply_op1(op)?,
        [a, b] => a.apply_op2(b, op)?,
        [a, b, c] => a.apply_op3(b, c, op)?,
        _ => {
            return Err(Error::Config(format!(
                "a checkpointed block takes one to three inputs, not {}",
                inputs.len()
            )));
        }
    })
}
