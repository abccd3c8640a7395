//! The process settings the engine runs best with, for the programs built on this crate (the
//! `veila` and `xtask` binaries call [`tune_process`] first in `main`): candle and the allocator
//! read them from the environment or their option tables once, so they must be set before any
//! other thread exists. Also what the benchmarks state of the process: its cores
//! ([`cpu_cores`]) and its CPU time ([`cpu_seconds`]).
//!
//! With the `mimalloc` feature the module also names the allocator the binaries install
//! (`#[global_allocator] static GLOBAL: veila_nn::process::MiMalloc = veila_nn::process::MiMalloc;`):
//! mimalloc keeps freed blocks for reuse, while with glibc's allocator every large tensor of a
//! sampling step is a fresh `mmap` and page-faults in again (measured: ~30% of a training step).

#[cfg(feature = "mimalloc")]
pub use mimalloc::MiMalloc;

/// `mi_option_purge_delay` of `mimalloc.h` (v2 and v3; libmimalloc-sys names no constant for it):
/// the option just before `use_numa_nodes`, which the assertion pins.
#[cfg(feature = "mimalloc")]
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;
#[cfg(feature = "mimalloc")]
const _: () = assert!(libmimalloc_sys::mi_option_use_numa_nodes == MI_OPTION_PURGE_DELAY + 1);

/// User and system CPU time of this process in seconds (Linux `/proc/self/stat`, 100 ticks per
/// second; `None` where it cannot be read), for the benchmarks' CPU time over wall time.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // fields after the parenthesised command name; utime and stime are fields 14 and 15 (1-based)
    let rest = stat.get(stat.rfind(')')? + 2..)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ut: f64 = f.get(11)?.parse().ok()?;
    let st: f64 = f.get(12)?.parse().ok()?;
    Some((ut + st) / 100.0)
}

/// The CPU cores this process may use (the available parallelism; 1 where it is unknown), as
/// rayon's default and the benchmark reports count them.
pub fn cpu_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// The machine as a benchmark report names it: "1 CPU core", "2 CPU cores".
pub fn cpu_cores_phrase() -> String {
    match cpu_cores() {
        1 => "1 CPU core".to_string(),
        n => format!("{n} CPU cores"),
    }
}

/// Process settings that candle and mimalloc read from the environment, set where the user has
/// not.
///
/// * `RAYON_NUM_THREADS` (rayon's own default, the available parallelism): without it candle 0.11
///   counts the physical cores from `/proc/cpuinfo` on every matrix product (~2 % of a training step
///   in `cargo xtask bench-model`, in the kernel's `show_cpuinfo`);
/// * `CANDLE_NUM_THREADS=1`: candle's own elementwise kernels run on the calling thread, while
///   the engine's kernels ([`crate::fused`]) and the matrix products use rayon's threads. candle
///   0.11's barrier pool otherwise keeps one worker per core spinning (25,000 iterations) after
///   each of its ops, on the cores that rayon's threads need next: 264 → 236 ms per training step of
///   `cargo xtask bench-model` on 2 cores (BENCHMARKS.md);
/// * with the `mimalloc` feature, mimalloc's purge delay, 10 s (unless `MIMALLOC_PURGE_DELAY` is
///   set): by default it hands freed memory back to the OS within a second and the next step's
///   tensors fault it in again as freshly zeroed huge pages (50,000 faults and ~5 % of a training
///   step); 10 s spans any run of steps and still returns memory to an idle process.
///
/// # Safety
///
/// Call it at the start of `main`, before any other thread exists: it writes the process
/// environment, which nothing may read concurrently.
#[allow(unsafe_code)]
pub unsafe fn tune_process() {
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        let n = cpu_cores();
        // SAFETY: the caller guarantees that no other thread exists (nothing reads the
        // environment concurrently).
        unsafe {
            std::env::set_var("RAYON_NUM_THREADS", n.to_string());
        }
    }
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        // SAFETY: as above (no other thread).
        unsafe {
            std::env::set_var("CANDLE_NUM_THREADS", "1");
        }
    }
    #[cfg(feature = "mimalloc")]
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: `mi_option_set` writes one entry of mimalloc's option table; the index is pinned
        // by the assertion above and the value is in the option's domain (ms, -1 = never).
        unsafe {
            libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, 10_000);
        }
    }
}
