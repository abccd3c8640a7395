//! Which worker of a job split across several this process is: `--shard-index/--shard-count`,
//! else the Slurm array or Kubernetes Indexed Job it runs in. Shared by the commands that split
//! their work so (`convert`, `generate --frames`); the rule is the library's,
//! `veila_data::convert::worker_shard`.

use anyhow::Result;
use clap::Args;

/// `--shard-index` and `--shard-count`.
#[derive(Debug, Clone, Copy, Args)]
pub(crate) struct WorkerArgs {
    /// This worker's index, 0 to 65535, below --shard-count (default: from Slurm / Kubernetes
    /// environment variables, else 0).
    #[arg(long, value_parser = crate::bounds::int::<usize>(0, 65_535))]
    pub(crate) shard_index: Option<usize>,
    /// Number of workers, 1 to 65536 (default: from the environment, else 1).
    #[arg(long, value_parser = crate::bounds::int::<usize>(1, 65_536))]
    pub(crate) shard_count: Option<usize>,
}

impl WorkerArgs {
    /// Whether either flag was given.
    pub(crate) fn given(&self) -> bool {
        self.shard_index.is_some() || self.shard_count.is_some()
    }

    /// `(index, count)` of this worker: the flags, else `SLURM_ARRAY_TASK_ID` (minus
    /// `SLURM_ARRAY_TASK_MIN`) of `SLURM_ARRAY_TASK_COUNT`, else `JOB_COMPLETION_INDEX` of
    /// `--shard-count` or `VEILA_SHARD_COUNT`, else worker 0 of 1.
    pub(crate) fn resolve(&self) -> Result<(usize, usize)> {
        Ok(veila_data::convert::worker_shard(
            self.shard_index,
            self.shard_count,
            &|k| std::env::var(k).ok(),
        )?)
    }
}
