//! Data-parallel training: one process per device, each with its own share of every global batch,
//! gradients averaged across the processes before every update, so all of them take the same step
//! and hold the same weights.
//!
//! * [`ProcessGroup`] says where this process sits: rank, world size, local rank and rendezvous
//!   address, read from the standard launchers' variables ([`ProcessGroup::from_env`]: torchrun's
//!   `RANK` / `WORLD_SIZE` / `LOCAL_RANK` / `MASTER_ADDR` / `MASTER_PORT`, Slurm's `SLURM_PROCID` /
//!   `SLURM_NTASKS` / `SLURM_LOCALID`), and which part of a global batch is this rank's
//!   ([`ProcessGroup::shard`]: contiguous, disjoint, covering it).
//! * [`Communicator`] sums a buffer over the ranks. [`InProcessGroup`] is the stand-in that runs
//!   several ranks as threads of one process (tests); the binaries bring a transport between
//!   processes (NCCL on GPUs, TCP on the CPU).
//! * [`super::Trainer::set_communicator`] makes the trainer all-reduce the flattened gradients (and
//!   the loss, so every rank skips a non-finite update together) and draw its noise from a
//!   per-(seed, step, rank) stream, which keeps resumes exact without any rank's generator state.
//!   Only rank 0 writes checkpoints.

use std::sync::{Arc, Condvar, Mutex};

use crate::error::{Result, invalid};

/// Where this process sits in a data-parallel run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcessGroup {
    /// This process's index, `0..world_size`.
    pub rank: usize,
    /// Number of processes.
    pub world_size: usize,
    /// Index among the processes of this machine (selects its GPU).
    pub local_rank: usize,
    /// Rendezvous address of rank 0 (`MASTER_ADDR`, `MASTER_PORT`), when launched with one.
    pub master: Option<(String, u16)>,
}

impl ProcessGroup {
    /// A run of one process.
    pub fn single() -> Self {
        Self {
            rank: 0,
            world_size: 1,
            local_rank: 0,
            master: None,
        }
    }

    /// From the environment (see [`Self::from_vars`]).
    pub fn from_env() -> Result<Self> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// From launcher variables read through `get`: torchrun's `RANK`, `WORLD_SIZE`, `LOCAL_RANK`
    /// first, else Slurm's `SLURM_PROCID`, `SLURM_NTASKS`, `SLURM_LOCALID`, else a single process.
    /// `MASTER_ADDR` and `MASTER_PORT` (which Slurm scripts export themselves) give the
    /// rendezvous; a world of more than one needs them.
    ///
    /// # Errors
    /// Unparsable numbers, a rank outside the world, or a multi-process world without a
    /// rendezvous address, naming the variable.
    pub fn from_vars(get: impl Fn(&str) -> Option<String>) -> Result<Self> {
        let num = |k: &str| -> Result<Option<usize>> {
            match get(k) {
                None => Ok(None),
                Some(v) => v.trim().parse::<usize>().map(Some).map_err(|_| {
                    invalid(
                        "process group",
                        format!("{k}=`{v}` is not a non-negative integer"),
                    )
                }),
            }
        };
        let (rank, world, local, source) = if let Some(r) = num("RANK")? {
            (
                r,
                num("WORLD_SIZE")?,
                num("LOCAL_RANK")?,
                "RANK / WORLD_SIZE",
            )
        } else if let Some(r) = num("SLURM_PROCID")? {
            (
                r,
                num("SLURM_NTASKS")?,
                num("SLURM_LOCALID")?,
                "SLURM_PROCID / SLURM_NTASKS",
            )
        } else {
            return Ok(Self::single());
        };
        let world = world.ok_or_else(|| {
            invalid(
                "process group",
                format!("{source}: the rank is set but the world size is not"),
            )
        })?;
        if world == 0 || rank >= world {
            return Err(invalid(
                "process group",
                format!("{source}: rank {rank} is outside a world of {world}"),
            ));
        }
        let master = match (get("MASTER_ADDR"), get("MASTER_PORT")) {
            (Some(a), Some(p)) => {
                let port = p.trim().parse::<u16>().map_err(|_| {
                    invalid("process group", format!("MASTER_PORT=`{p}` is not a port"))
                })?;
                Some((a.trim().to_string(), port))
            }
            _ => None,
        };
        if world > 1 && master.is_none() {
            return Err(invalid(
                "process group",
                format!(
                    "{source}: a world of {world} needs MASTER_ADDR and MASTER_PORT (torchrun sets them; export them in a Slurm script)"
                ),
            ));
        }
        Ok(Self {
            rank,
            world_size: world,
            local_rank: local.unwrap_or(0),
            master,
        })
    }

    /// Whether this is rank 0 (the one that writes checkpoints and output).
    pub fn is_main(&self) -> bool {
        self.rank == 0
    }

    /// This rank's share of a global batch: a contiguous slice; the shares of all ranks are
    /// disjoint and cover `global`, their sizes differ by at most one (the first
    /// `len % world_size` ranks take one more).
    pub fn shard<'a, T>(&self, global: &'a [T]) -> &'a [T] {
        let (start, end) = shard_range(global.len(), self.rank, self.world_size);
        &global[start..end]
    }
}

/// `[start, end)` of rank `rank`'s share of `n` items over `world` ranks.
pub fn shard_range(n: usize, rank: usize, world: usize) -> (usize, usize) {
    let world = world.max(1);
    let (base, extra) = (n / world, n % world);
    let start = rank * base + rank.min(extra);
    let len = base + usize::from(rank < extra);
    (start.min(n), (start + len).min(n))
}

/// Sums buffers element-wise over the ranks of a run.
pub trait Communicator: Send {
    /// This process's rank.
    fn rank(&self) -> usize;
    /// Number of ranks.
    fn world_size(&self) -> usize;
    /// Replaces `buf` by its element-wise sum over all ranks (every rank passes a buffer of the
    /// same length and gets the same result, summed in rank order).
    fn all_reduce_sum(&mut self, buf: &mut [f32]) -> Result<()>;
}

/// A data-parallel run as the training code takes it: the group (for sharding batches) and one
/// communicator shared by the run's stages (they train one after another). Cheap to clone.
#[derive(Clone)]
pub struct Parallel {
    group: ProcessGroup,
    comm: Arc<Mutex<Box<dyn Communicator>>>,
}

impl std::fmt::Debug for Parallel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Parallel")
            .field("group", &self.group)
            .finish_non_exhaustive()
    }
}

impl Parallel {
    /// `comm` must have `group`'s rank and world size.
    pub fn new(group: ProcessGroup, comm: Box<dyn Communicator>) -> Result<Self> {
        if comm.rank() != group.rank || comm.world_size() != group.world_size {
            return Err(invalid(
                "process group",
                format!(
                    "the communicator is rank {} of {}, the group rank {} of {}",
                    comm.rank(),
                    comm.world_size(),
                    group.rank,
                    group.world_size
                ),
            ));
        }
        Ok(Self {
            group,
            comm: Arc::new(Mutex::new(comm)),
        })
    }

    /// The group.
    pub fn group(&self) -> &ProcessGroup {
        &self.group
    }

    /// A communicator for one trainer (all handles share the one connection).
    pub fn communicator(&self) -> Box<dyn Communicator> {
        Box::new(Shared {
            rank: self.group.rank,
            world: self.group.world_size,
            inner: self.comm.clone(),
        })
    }
}

struct Shared {
    rank: usize,
    world: usize,
    inner: Arc<Mutex<Box<dyn Communicator>>>,
}

impl Communicator for Shared {
    fn rank(&self) -> usize {
        self.rank
    }

    fn world_size(&self) -> usize {
        self.world
    }

    fn all_reduce_sum(&mut self, buf: &mut [f32]) -> Result<()> {
        self.inner
            .lock()
            .map_err(|_| invalid("process group", "the communicator lock is poisoned"))?
            .all_reduce_sum(buf)
    }
}

#[derive(Debug)]
struct Round {
    generation: u64,
    slots: Vec<Option<Vec<f32>>>,
    result: Option<Arc<Vec<f32>>>,
    taken: usize,
}

/// Several ranks as threads of one process: the stand-in [`Communicator`] for tests (and for
/// data-parallel runs on one machine without a transport).
#[derive(Debug, Clone)]
pub struct InProcessGroup {
    rank: usize,
    world: usize,
    shared: Arc<(Mutex<Round>, Condvar)>,
}

impl InProcessGroup {
    /// One communicator per rank of a world of `world` (at least 1).
    pub fn new(world: usize) -> Vec<InProcessGroup> {
        let world = world.max(1);
        let shared = Arc::new((
            Mutex::new(Round {
                generation: 0,
                slots: vec![None; world],
                result: None,
                taken: 0,
            }),
            Condvar::new(),
        ));
        (0..world)
            .map(|rank| InProcessGroup {
                rank,
                world,
                shared: shared.clone(),
            })
            .collect()
    }
}

impl Communicator for InProcessGroup {
    fn rank(&self) -> usize {
        self.rank
    }

    fn world_size(&self) -> usize {
        self.world
    }

    fn all_reduce_sum(&mut self, buf: &mut [f32]) -> Result<()> {
        let poisoned = || invalid("in-process group", "a rank panicked (lock poisoned)");
        let (lock, cv) = &*self.shared;
        let mut round = lock.lock().map_err(|_| poisoned())?;
        // wait until the previous round's result has been taken by every rank
        while round.result.is_some() {
            round = cv.wait(round).map_err(|_| poisoned())?;
        }
        let generation = round.generation;
        if round.slots[self.rank].is_some() {
            return Err(invalid("in-process group", "a rank joined a round twice"));
        }
        round.slots[self.rank] = Some(buf.to_vec());
        if round.slots.iter().all(Option::is_some) {
            let n = buf.len();
            let mut sum = vec![0f32; n];
            for slot in round.slots.iter_mut() {
                let v = slot.take().unwrap_or_default();
                if v.len() != n {
                    return Err(invalid(
                        "in-process group",
                        format!("ranks passed buffers of {} and {n} values", v.len()),
                    ));
                }
                for (s, x) in sum.iter_mut().zip(&v) {
                    *s += x;
                }
            }
            round.result = Some(Arc::new(sum));
            round.taken = 0;
            cv.notify_all();
        }
        while round.generation == generation && round.result.is_none() {
            round = cv.wait(round).map_err(|_| poisoned())?;
        }
        let result = round
            .result
            .clone()
            .ok_or_else(|| invalid("in-process group", "round ended without a result"))?;
        buf.copy_from_slice(&result);
        round.taken += 1;
        if round.taken == self.world {
            round.result = None;
            round.generation += 1;
            cv.notify_all();
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn launcher_variables_give_the_process_group() {
        let vars = |pairs: &[(&str, &str)]| {
            let pairs: Vec<(String, String)> = pairs
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect();
            move |k: &str| pairs.iter().find(|(a, _)| a == k).map(|(_, v)| v.clone())
        };
        assert_eq!(
            ProcessGroup::from_vars(vars(&[])).unwrap(),
            ProcessGroup::single()
        );
        let torchrun = vars(&[
            ("RANK", "3"),
            ("WORLD_SIZE", "8"),
            ("LOCAL_RANK", "1"),
            ("MASTER_ADDR", "node0"),
            ("MASTER_PORT", "29500"),
            ("SLURM_PROCID", "0"),
        ]);
        let g = ProcessGroup::from_vars(torchrun).unwrap();
        assert_eq!((g.rank, g.world_size, g.local_rank), (3, 8, 1));
        assert_eq!(g.master, Some(("node0".into(), 29500)));
        assert!(!g.is_main());
        let slurm = vars(&[
            ("SLURM_PROCID", "5"),
            ("SLURM_NTASKS", "6"),
            ("SLURM_LOCALID", "2"),
            ("MASTER_ADDR", "10.0.0.1"),
            ("MASTER_PORT", "12345"),
        ]);
        let g = ProcessGroup::from_vars(slurm).unwrap();
        assert_eq!((g.rank, g.world_size, g.local_rank), (5, 6, 2));
        for (bad, what) in [
            (vec![("RANK", "2"), ("WORLD_SIZE", "2")], "outside"),
            (vec![("RANK", "x"), ("WORLD_SIZE", "2")], "RANK=`x`"),
            (vec![("RANK", "0")], "world size"),
            (vec![("RANK", "0"), ("WORLD_SIZE", "2")], "MASTER_ADDR"),
            (
                vec![
                    ("RANK", "0"),
                    ("WORLD_SIZE", "2"),
                    ("MASTER_ADDR", "a"),
                    ("MASTER_PORT", "99999"),
                ],
                "MASTER_PORT",
            ),
        ] {
            let e = ProcessGroup::from_vars(vars(&bad)).unwrap_err().to_string();
            assert!(e.contains(what), "{bad:?}: {e}");
        }
        // one process needs no rendezvous
        let g = ProcessGroup::from_vars(vars(&[("RANK", "0"), ("WORLD_SIZE", "1")])).unwrap();
        assert_eq!(g.world_size, 1);
    }

    #[test]
    fn shards_are_disjoint_and_cover_the_batch() {
        for n in 0..20usize {
            for world in 1..6usize {
                let items: Vec<usize> = (0..n).collect();
                let mut seen = Vec::new();
                let mut sizes = Vec::new();
                for rank in 0..world {
                    let g = ProcessGroup {
                        rank,
                        world_size: world,
                        local_rank: 0,
                        master: None,
                    };
                    let s = g.shard(&items);
                    sizes.push(s.len());
                    seen.extend_from_slice(s);
                }
                assert_eq!(seen, items, "n {n} world {world}");
                let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
                assert!(hi - lo <= 1, "n {n} world {world}: {sizes:?}");
            }
        }
    }

    #[test]
    fn in_process_all_reduce_sums_in_rank_order_over_many_rounds() {
        let comms = InProcessGroup::new(3);
        let handles: Vec<_> = comms
            .into_iter()
            .map(|mut c| {
                std::thread::spawn(move || {
                    let mut out = Vec::new();
                    for round in 0..50 {
                        let r = c.rank() as f32;
                        let mut buf = vec![r + round as f32, 10.0 * r, 1.0];
                        c.all_reduce_sum(&mut buf).unwrap();
                        out.push(buf);
                    }
                    out
                })
            })
            .collect();
        let results: Vec<Vec<Vec<f32>>> = handles.into_iter().map(|h| h.join().unwrap()).collect();
        for round in 0..50 {
            let want = vec![3.0 + 3.0 * round as f32, 30.0, 3.0];
            for r in &results {
                assert_eq!(r[round], want, "round {round}");
            }
        }
    }
}
