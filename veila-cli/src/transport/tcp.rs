//! The CPU transport of data-parallel `veila train`: a TCP star around rank 0 at
//! `MASTER_ADDR:MASTER_PORT` (what torchrun and Slurm scripts export). Rank 0 listens, the
//! others connect and announce their rank; an all-reduce sends every buffer to rank 0, which sums
//! them in rank order and sends the sum back, so all ranks hold identical bytes.
//!
//! Hand-written over `std::net` because the only well-kept collective libraries (NCCL, Gloo, MPI)
//! need native installs this CPU build does not assume; on GPUs the NCCL path replaces it.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use veila_diffusion::Error;
use veila_diffusion::trainer::distributed::{Communicator, ProcessGroup};

const MAGIC: &[u8; 4] = b"VLA1";
/// Largest buffer accepted from a peer (4 Gi values): bounds memory on a corrupt length.
const MAX_VALUES: u64 = 1 << 32;

fn err(rank: usize, what: impl std::fmt::Display) -> Error {
    Error::Distributed(format!("rank {rank}: {what}"))
}

/// A rank's end of the TCP star.
pub(crate) struct TcpGroup {
    rank: usize,
    world: usize,
    /// Rank 0: one stream per other rank, in rank order. Others: the stream to rank 0.
    peers: Vec<TcpStream>,
}

impl TcpGroup {
    /// Rank 0 binds `MASTER_ADDR:MASTER_PORT` and waits for the others; the others connect,
    /// retrying, until `timeout`.
    pub(crate) fn connect(
        group: &ProcessGroup,
        timeout: Duration,
    ) -> veila_diffusion::Result<Self> {
        let rank = group.rank;
        let (host, port) = group
            .master
            .clone()
            .ok_or_else(|| err(rank, "no MASTER_ADDR / MASTER_PORT"))?;
        let addr = format!("{host}:{port}");
        let deadline = Instant::now() + timeout;
        if rank == 0 {
            let listener = TcpListener::bind(&addr)
                .map_err(|e| err(0, format!("cannot listen on {addr}: {e}")))?;
            listener
                .set_nonblocking(true)
                .map_err(|e| err(0, format!("{addr}: {e}")))?;
            let mut slots: Vec<Option<TcpStream>> = (1..group.world_size).map(|_| None).collect();
            while slots.iter().any(Option::is_none) {
                match listener.accept() {
                    Ok((mut s, _)) => {
                        s.set_nonblocking(false)
                            .and_then(|_| s.set_nodelay(true))
                            .map_err(|e| err(0, e))?;
                        let mut hello = [0u8; 12];
                        s.read_exact(&mut hello)
                            .map_err(|e| err(0, format!("handshake: {e}")))?;
                        let r =
                            u32::from_le_bytes(hello[4..8].try_into().unwrap_or_default()) as usize;
                        let w = u32::from_le_bytes(hello[8..12].try_into().unwrap_or_default())
                            as usize;
                        if &hello[..4] != MAGIC || w != group.world_size || r == 0 || r >= w {
                            return Err(err(
                                0,
                                format!(
                                    "a peer announced rank {r} of {w} (this run: world {})",
                                    group.world_size
                                ),
                            ));
                        }
                        if slots[r - 1].is_some() {
                            return Err(err(0, format!("rank {r} connected twice")));
                        }
                        slots[r - 1] = Some(s);
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        if Instant::now() > deadline {
                            let missing: Vec<usize> = slots
                                .iter()
                                .enumerate()
                                .filter(|(_, s)| s.is_none())
                                .map(|(i, _)| i + 1)
                                .collect();
                            return Err(err(
                                0,
                                format!(
                                    "ranks {missing:?} did not connect to {addr} within {timeout:?}"
                                ),
                            ));
                        }
                        std::thread::sleep(Duration::from_millis(20));
                    }
                    Err(e) => return Err(err(0, format!("{addr}: {e}"))),
                }
            }
            Ok(Self {
                rank,
                world: group.world_size,
                peers: slots.into_iter().flatten().collect(),
            })
        } else {
            let stream = loop {
                let attempt = addr
                    .to_socket_addrs()
                    .map_err(|e| err(rank, format!("{addr}: {e}")))?
                    .find_map(|a| TcpStream::connect_timeout(&a, Duration::from_secs(2)).ok());
                match attempt {
                    Some(s) => break s,
                    None if Instant::now() > deadline => {
                        return Err(err(
                            rank,
                            format!("rank 0 did not answer at {addr} within {timeout:?}"),
                        ));
                    }
                    None => std::thread::sleep(Duration::from_millis(100)),
                }
            };
            stream.set_nodelay(true).map_err(|e| err(rank, e))?;
            let mut s = stream;
            let mut hello = Vec::with_capacity(12);
            hello.extend_from_slice(MAGIC);
            hello.extend_from_slice(&(rank as u32).to_le_bytes());
            hello.extend_from_slice(&(group.world_size as u32).to_le_bytes());
            s.write_all(&hello)
                .map_err(|e| err(rank, format!("handshake with {addr}: {e}")))?;
            Ok(Self {
                rank,
                world: group.world_size,
                peers: vec![s],
            })
        }
    }
}

fn send(s: &mut TcpStream, buf: &[f32]) -> std::io::Result<()> {
    let mut bytes = Vec::with_capacity(8 + 4 * buf.len());
    bytes.extend_from_slice(&(buf.len() as u64).to_le_bytes());
    for v in buf {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    s.write_all(&bytes)
}

fn recv(s: &mut TcpStream, want: usize) -> std::io::Result<Vec<f32>> {
    let mut len = [0u8; 8];
    s.read_exact(&mut len)?;
    let n = u64::from_le_bytes(len);
    if n > MAX_VALUES || n as usize != want {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("a peer sent {n} values, {want} expected"),
        ));
    }
    let mut bytes = vec![0u8; 4 * want];
    s.read_exact(&mut bytes)?;
    Ok(bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

impl Communicator for TcpGroup {
    fn rank(&self) -> usize {
        self.rank
    }

    fn world_size(&self) -> usize {
        self.world
    }

    fn all_reduce_sum(&mut self, buf: &mut [f32]) -> veila_diffusion::Result<()> {
        let rank = self.rank;
        if rank == 0 {
            let mut sum = buf.to_vec();
            for (i, s) in self.peers.iter_mut().enumerate() {
                let v =
                    recv(s, buf.len()).map_err(|e| err(0, format!("from rank {}: {e}", i + 1)))?;
                for (a, b) in sum.iter_mut().zip(&v) {
                    *a += b;
                }
            }
            for (i, s) in self.peers.iter_mut().enumerate() {
                send(s, &sum).map_err(|e| err(0, format!("to rank {}: {e}", i + 1)))?;
            }
            buf.copy_from_slice(&sum);
        } else {
            let s = &mut self.peers[0];
            send(s, buf).map_err(|e| err(rank, format!("to rank 0: {e}")))?;
            let v = recv(s, buf.len()).map_err(|e| err(rank, format!("from rank 0: {e}")))?;
            buf.copy_from_slice(&v);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn three_ranks_over_loopback_sum_in_rank_order() {
        // a free port from the OS
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let handles: Vec<_> = (0..3)
            .map(|rank| {
                std::thread::spawn(move || {
                    let g = ProcessGroup {
                        rank,
                        world_size: 3,
                        local_rank: rank,
                        master: Some(("127.0.0.1".into(), port)),
                    };
                    let mut c = TcpGroup::connect(&g, Duration::from_secs(20)).unwrap();
                    let mut out = Vec::new();
                    for round in 0..20 {
                        let mut buf = vec![rank as f32 + round as f32, 0.5, -(rank as f32)];
                        c.all_reduce_sum(&mut buf).unwrap();
                        out.push(buf);
                    }
                    out
                })
            })
            .collect();
        let res: Vec<_> = handles.into_iter().map(|h| h.join().unwrap()).collect();
        for round in 0..20 {
            let want = vec![3.0 + 3.0 * round as f32, 1.5, -3.0];
            for r in &res {
                assert_eq!(r[round], want);
            }
        }
    }

    #[test]
    fn a_missing_rank_times_out_naming_it() {
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let g = ProcessGroup {
            rank: 0,
            world_size: 3,
            local_rank: 0,
            master: Some(("127.0.0.1".into(), port)),
        };
        let e = TcpGroup::connect(&g, Duration::from_millis(300))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("ranks [1, 2]") && e.contains(&port.to_string()),
            "{e}"
        );
    }
}
