//! The transports of data-parallel `veila train`: the all-reduce of every update's gradients and
//! loss across the ranks of a run, behind the trainer's
//! [`Communicator`](veila_diffusion::trainer::distributed::Communicator).
//!
//! * [`tcp`]: a TCP star around rank 0 on the CPU (and the bootstrap of NCCL);
//! * `nccl` (feature `nccl`): NCCL on GPUs.

#[cfg(feature = "nccl")]
pub(crate) mod nccl;
pub(crate) mod tcp;
