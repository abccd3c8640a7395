//! The runner: seeded mutation of a target's seed files, one input at a time through its reader
//! under `catch_unwind`, a watchdog for hangs, and the table row of each target.

use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use rand::seq::IndexedRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::alloc;

/// The random stream of a target.
pub type FuzzRng = ChaCha8Rng;

/// The bound on each target's peak of live bytes above what was live when it started.
pub const PEAK_LIVE_LIMIT: usize = 512 << 20;

/// The slowest a single input may be (a debug build on a loaded machine included).
pub const SLOWEST_INPUT_LIMIT: Duration = Duration::from_secs(10);

/// An input still running after this long is a hang: the watchdog saves it and aborts.
pub const HANG_LIMIT: Duration = Duration::from_secs(60);

/// What one input did to its reader.
#[derive(Debug)]
pub enum Verdict {
    /// The reader accepted it.
    Ok,
    /// The reader refused it with an error (its message).
    Err(String),
    /// The reader broke a property other than panicking (an error that does not name the file,
    /// a decoy read): a failure like a panic.
    Violation(String),
}

impl Verdict {
    /// `Ok` or `Err(message)` of a reader's result, where an error must mention one of `names`
    /// (the file, or its folder).
    pub fn of<T, E: std::fmt::Display>(r: Result<T, E>, names: &[&str]) -> Verdict {
        match r {
            Ok(_) => Verdict::Ok,
            Err(e) => Verdict::named(e.to_string(), names),
        }
    }

    /// An error message, checked to mention one of `names`.
    pub fn named(msg: String, names: &[&str]) -> Verdict {
        if names.iter().any(|n| msg.contains(n)) {
            Verdict::Err(msg)
        } else {
            Verdict::Violation(format!("the error names none of {names:?}: {msg}"))
        }
    }
}

/// A structure-aware editor: a mutated copy of its input, or `None` where it cannot parse it.
pub type Structured<'a> = &'a dyn Fn(&[u8], &mut FuzzRng) -> Option<Vec<u8>>;

/// The inputs each target runs: `VEILA_FUZZ_INPUTS`, else 200.
pub fn inputs() -> usize {
    std::env::var("VEILA_FUZZ_INPUTS")
        .ok()
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or(200)
}

/// `VEILA_FUZZ_VERBOSE` set: every error message is printed (its first 300 characters).
fn verbose() -> bool {
    std::env::var_os("VEILA_FUZZ_VERBOSE").is_some()
}

fn run_seed() -> u64 {
    std::env::var("VEILA_FUZZ_SEED")
        .ok()
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or(0)
}

/// One target at a time: each one's peak memory is its own.
static SERIAL: Mutex<()> = Mutex::new(());

/// When the input now running started (nanoseconds after [`epoch`]), 0 when none is.
static RUNNING_SINCE: AtomicU64 = AtomicU64::new(0);
/// The target and input now running, for the watchdog.
static CURRENT: Mutex<Option<(String, Vec<u8>)>> = Mutex::new(None);

fn epoch() -> Instant {
    static E: OnceLock<Instant> = OnceLock::new();
    *E.get_or_init(Instant::now)
}

fn failures_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-failures")
}

fn save_failure(target: &str, index: usize, bytes: &[u8]) -> PathBuf {
    let dir = failures_dir();
    let _ = std::fs::create_dir_all(&dir);
    let stem: String = target
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    let p = dir.join(format!("{stem}-{index}.bin"));
    let _ = std::fs::write(&p, bytes);
    p
}

/// Starts the watchdog thread once: an input running past [`HANG_LIMIT`] is saved and the
/// process aborted (a hung reader never returns to be counted).
fn watchdog() {
    static STARTED: OnceLock<()> = OnceLock::new();
    STARTED.get_or_init(|| {
        std::thread::spawn(|| {
            loop {
                std::thread::sleep(Duration::from_millis(500));
                let since = RUNNING_SINCE.load(Ordering::Relaxed);
                if since == 0 {
                    continue;
                }
                let now = epoch().elapsed().as_nanos() as u64;
                if now.saturating_sub(since) > HANG_LIMIT.as_nanos() as u64 {
                    let (name, bytes) = CURRENT
                        .lock()
                        .ok()
                        .and_then(|c| c.clone())
                        .unwrap_or_default();
                    let p = save_failure(&format!("{name}-hang"), 0, &bytes);
                    eprintln!(
                        "fuzz: target {name}: an input has run for more than {HANG_LIMIT:?}: a \
                         hang; it is saved at {}",
                        p.display()
                    );
                    std::process::abort();
                }
            }
        });
    });
}

/// What one target did, as its row of the table.
#[derive(Debug, Default)]
pub struct Stats {
    /// Inputs run.
    pub inputs: usize,
    /// Accepted.
    pub ok: usize,
    /// Refused with an error.
    pub err: usize,
    /// Panics and property violations.
    pub crashes: usize,
    /// The slowest input.
    pub slowest: Duration,
    /// All inputs together.
    pub total: Duration,
    /// The peak of live bytes above the start.
    pub peak_bytes: usize,
}

fn print_row(name: &str, s: &Stats) {
    println!(
        "| {name} | {} | {} | {} | {} | {:.1} | {:.0} | {:.1} MiB |",
        s.inputs,
        s.ok,
        s.err,
        s.crashes,
        s.slowest.as_secs_f64() * 1e3,
        s.total.as_secs_f64() * 1e6 / s.inputs.max(1) as f64,
        s.peak_bytes as f64 / (1 << 20) as f64
    );
}

/// Runs target `name`: checks that every seed is accepted, then feeds [`inputs`] mutated copies
/// of them to `run` (which writes its input into place and reads it) and asserts the properties
/// of the module docs. `structured` are the editors that understand the seeds' format.
pub fn fuzz(
    name: &str,
    seeds: &[Vec<u8>],
    structured: &[Structured<'_>],
    run: &dyn Fn(&[u8]) -> Verdict,
) -> Stats {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    watchdog();
    assert!(!seeds.is_empty(), "{name}: no seed");
    for (i, s) in seeds.iter().enumerate() {
        match run(s) {
            Verdict::Ok => {}
            v => panic!("{name}: seed {i} is not accepted, so the target tests nothing: {v:?}"),
        }
    }
    let n = inputs();
    let mut rng = FuzzRng::seed_from_u64(fnv1a(name.as_bytes()) ^ run_seed());
    let mut stats = Stats::default();
    let mut failures: Vec<String> = Vec::new();
    alloc::reset_peak();
    let base = alloc::live();
    for i in 0..n {
        let seed = seeds.choose(&mut rng).expect("a seed");
        let bytes = mutate(seed, seeds, structured, &mut rng);
        if let Ok(mut c) = CURRENT.lock() {
            *c = Some((name.to_string(), bytes.clone()));
        }
        let t0 = Instant::now();
        RUNNING_SINCE.store(
            epoch().elapsed().as_nanos().max(1) as u64,
            Ordering::Relaxed,
        );
        let verdict = std::panic::catch_unwind(AssertUnwindSafe(|| run(&bytes)));
        RUNNING_SINCE.store(0, Ordering::Relaxed);
        let dt = t0.elapsed();
        stats.inputs += 1;
        stats.total += dt;
        stats.slowest = stats.slowest.max(dt);
        match verdict {
            Ok(Verdict::Ok) => stats.ok += 1,
            Ok(Verdict::Err(e)) => {
                stats.err += 1;
                if verbose() {
                    let short: String = e.chars().take(300).collect();
                    println!("  {name} #{i}: {short}");
                }
            }
            Ok(Verdict::Violation(why)) => {
                stats.crashes += 1;
                let p = save_failure(name, i, &bytes);
                failures.push(format!("input {i} ({}): {why}", p.display()));
            }
            Err(panic) => {
                stats.crashes += 1;
                let p = save_failure(name, i, &bytes);
                let msg = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default();
                failures.push(format!("input {i} ({}): panicked: {msg}", p.display()));
            }
        }
    }
    stats.peak_bytes = alloc::peak().saturating_sub(base);
    if let Ok(mut c) = CURRENT.lock() {
        *c = None;
    }
    print_row(name, &stats);
    assert!(
        failures.is_empty(),
        "{name}: {} of {n} inputs crashed or broke a property:\n{}",
        failures.len(),
        failures.join("\n")
    );
    assert!(
        stats.peak_bytes <= PEAK_LIVE_LIMIT,
        "{name}: {} bytes live at the peak, more than the bound of {PEAK_LIVE_LIMIT}",
        stats.peak_bytes
    );
    assert!(
        stats.slowest <= SLOWEST_INPUT_LIMIT,
        "{name}: the slowest input took {:?}, more than {SLOWEST_INPUT_LIMIT:?}",
        stats.slowest
    );
    stats
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// One input: three times in four a structure-aware edit (when the target has editors and one
/// applies), followed a quarter of the time by one byte-level mutation; else one to four
/// byte-level mutations.
pub fn mutate(
    seed: &[u8],
    corpus: &[Vec<u8>],
    structured: &[Structured<'_>],
    rng: &mut FuzzRng,
) -> Vec<u8> {
    let mut b = seed.to_vec();
    let mut edited = false;
    if !structured.is_empty() && rng.random_bool(0.75) {
        let editor = structured.choose(rng).expect("an editor");
        if let Some(x) = editor(&b, rng) {
            b = x;
            edited = true;
        }
    }
    let k = if edited {
        usize::from(rng.random_bool(0.25))
    } else {
        rng.random_range(1..=4)
    };
    for _ in 0..k {
        byte_mutation(&mut b, corpus, rng);
    }
    b
}

/// Boundary values for binary fields, as little-endian bit patterns.
const INTERESTING: [u64; 20] = [
    0,
    1,
    0x7f,
    0x80,
    0xff,
    0x7fff,
    0x8000,
    0xffff,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    1 << 32,
    0x7fff_ffff_ffff_ffff,
    0x8000_0000_0000_0000,
    u64::MAX,
    0x7fc0_0000,           // f32 NaN
    0x7f80_0000,           // f32 infinity
    0x7149_f2ca,           // f32 1e30
    0x7ff8_0000_0000_0000, // f64 NaN
    0x7e37_e43c_8800_759c, // f64 1e300
];

/// Tokens that break text formats: boundary numbers, non-numbers, paths, quotes and brackets,
/// control characters, invalid UTF-8.
pub const TEXT_TOKENS: [&[u8]; 26] = [
    b"-1",
    b"0",
    b"-0",
    b"2147483648",
    b"4294967296",
    b"9223372036854775808",
    b"18446744073709551616",
    b"1e300",
    b"-1e300",
    b"1e-300",
    b"NaN",
    b"nan",
    b"inf",
    b"-inf",
    b"../",
    b"/etc/passwd",
    b"\0",
    b"\"",
    b"'",
    b"{",
    b"}",
    b"[",
    b"]",
    b"\n",
    b"\x1b[2J",
    b"\xff\xfe",
];

fn byte_mutation(b: &mut Vec<u8>, corpus: &[Vec<u8>], rng: &mut FuzzRng) {
    let n = b.len();
    match rng.random_range(0..11) {
        0 if n > 0 => {
            let at = rng.random_range(0..n);
            b[at] ^= 1 << rng.random_range(0..8);
        }
        1 if n > 0 => {
            let at = rng.random_range(0..n);
            b[at] = rng.random();
        }
        2 if n > 0 => {
            let v = *INTERESTING.choose(rng).expect("a value");
            let width = *[1usize, 2, 4, 8].choose(rng).expect("a width");
            // the value's low `width` bytes, little-endian or (a fifth of the time) big-endian
            let le = v.to_le_bytes();
            let mut bytes = le[..width].to_vec();
            if rng.random_bool(0.2) {
                bytes.reverse();
            }
            let at = rng.random_range(0..n);
            let len = width.min(n - at);
            b[at..at + len].copy_from_slice(&bytes[..len]);
        }
        3 => {
            let keep = rng.random_range(0..=n);
            b.truncate(keep);
        }
        4 => {
            let at = rng.random_range(0..=n);
            let len = rng.random_range(1..=16);
            let ins: Vec<u8> = (0..len).map(|_| rng.random()).collect();
            b.splice(at..at, ins);
        }
        5 => {
            let at = rng.random_range(0..=n);
            let tok = *TEXT_TOKENS.choose(rng).expect("a token");
            b.splice(at..at, tok.iter().copied());
        }
        6 if n > 0 => {
            let at = rng.random_range(0..n);
            let len = rng.random_range(1..=64.min(n - at).max(1));
            b.drain(at..(at + len).min(n));
        }
        7 if n > 0 => {
            let at = rng.random_range(0..n);
            let len = rng.random_range(1..=256).min(n - at);
            let run = b[at..at + len].to_vec();
            let end = at + len;
            b.splice(end..end, run);
        }
        8 => {
            // splice: a run of another seed (or this one) overwrites or enters this input
            let other = corpus.choose(rng).expect("a seed");
            if other.is_empty() {
                return;
            }
            let from = rng.random_range(0..other.len());
            let len = rng.random_range(1..=512).min(other.len() - from);
            let chunk = &other[from..from + len];
            let at = rng.random_range(0..=n);
            if rng.random_bool(0.5) {
                b.splice(at..at, chunk.iter().copied());
            } else {
                let end = (at + len).min(n);
                b.splice(at..end, chunk.iter().copied());
            }
        }
        9 if n > 0 => {
            // a run of zeros or of 0xff (lengths and counts wiped or maxed)
            let at = rng.random_range(0..n);
            let len = rng.random_range(1..=32).min(n - at);
            let v = if rng.random_bool(0.5) { 0 } else { 0xff };
            b[at..at + len].fill(v);
        }
        10 if n > 1 => {
            // tail of the input dropped at a random point and repeated from another
            let cut = rng.random_range(0..n);
            let from = rng.random_range(0..n);
            let tail = b[from..].to_vec();
            b.truncate(cut);
            b.extend_from_slice(&tail);
        }
        _ => {}
    }
}

/// A temporary folder of a target's files.
pub fn tempdir() -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix("veila-fuzz-")
        .tempdir()
        .expect("a temporary folder")
}

/// Writes `bytes` to `path`, replacing what a previous input left (a removed file, a directory).
pub fn put(path: &Path, bytes: &[u8]) {
    if path.is_dir() {
        let _ = std::fs::remove_dir_all(path);
    }
    std::fs::write(path, bytes).expect("writing a fuzz input");
}
