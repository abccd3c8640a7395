//! The NCCL transport of data-parallel `veila train` on GPUs (feature `nccl`): one NCCL
//! communicator per rank, each on its rank's GPU stream. NCCL needs rank 0's unique id on every
//! rank before it can connect them; it travels through the TCP group ([`super::tcp`]) as one
//! all-reduce (rank 0 contributes the 128 id bytes, the others zeros), so the launch lines stay
//! those of the TCP transport (`MASTER_ADDR` / `MASTER_PORT`).
//!
//! The trainer hands the communicator one flat host buffer per update (gradients and loss); it is
//! copied to the GPU, summed there by NCCL and copied back. NCCL's summation order is fixed by the
//! topology, not the rank order, so a run is deterministic on one machine but its last bits may
//! differ from the TCP transport's.

use std::sync::Arc;

use candle_core::cuda_backend::cudarc;
use cudarc::driver::CudaStream;
use cudarc::nccl::safe::{Comm, Id, ReduceOp};
use veila_diffusion::trainer::distributed::Communicator;

fn nccl_error(what: &str, e: impl std::fmt::Debug) -> veila_diffusion::Error {
    veila_diffusion::Error::Data(format!("NCCL: {what}: {e:?}"))
}

/// One rank's NCCL communicator.
pub(crate) struct NcclGroup {
    comm: Comm,
    stream: Arc<CudaStream>,
}

// SAFETY: an NCCL communicator may be used from any thread, one call at a time; the trainer
// holds it behind a mutex and calls it from one thread (cudarc leaves `Comm` !Send only because
// it wraps a raw pointer).
#[allow(unsafe_code)]
unsafe impl Send for NcclGroup {}

impl NcclGroup {
    /// Connects the ranks of `bootstrap` over NCCL on `device` (this rank's GPU).
    pub(crate) fn connect(
        device: &candle_core::Device,
        bootstrap: &mut dyn Communicator,
    ) -> veila_diffusion::Result<Self> {
        let (rank, world) = (bootstrap.rank(), bootstrap.world_size());
        let mut bytes = vec![0f32; 128];
        if rank == 0 {
            let id = Id::new().map_err(|e| nccl_error("creating the unique id", e))?;
            for (b, c) in bytes.iter_mut().zip(id.internal()) {
                *b = f32::from(*c as u8);
            }
        }
        // every byte is in 0..=255, exact in f32; the sum is rank 0's bytes
        bootstrap.all_reduce_sum(&mut bytes)?;
        let mut internal = [0 as std::ffi::c_char; 128];
        for (c, b) in internal.iter_mut().zip(&bytes) {
            *c = (*b as u8) as std::ffi::c_char;
        }
        let stream = device.as_cuda_device()?.cuda_stream();
        let comm = Comm::from_rank(stream.clone(), rank, world, Id::uninit(internal))
            .map_err(|e| nccl_error("connecting the ranks", e))?;
        Ok(Self { comm, stream })
    }
}

impl Communicator for NcclGroup {
    fn rank(&self) -> usize {
        self.comm.rank()
    }

    fn world_size(&self) -> usize {
        self.comm.world_size()
    }

    fn all_reduce_sum(&mut self, buf: &mut [f32]) -> veila_diffusion::Result<()> {
        let mut d = self
            .stream
            .clone_htod(buf)
            .map_err(|e| nccl_error("copying to the GPU", e))?;
        self.comm
            .all_reduce_in_place(&mut d, &ReduceOp::Sum)
            .map_err(|e| nccl_error("all-reduce", e))?;
        self.stream
            .memcpy_dtoh(&d, buf)
            .map_err(|e| nccl_error("copying from the GPU", e))?;
        self.stream
            .synchronize()
            .map_err(|e| nccl_error("synchronising", e))?;
        Ok(())
    }
}
