//! Deterministic random streams: one ChaCha8 generator per (seed, effect, sensor, chunk), so results do not
//! depend on the number of threads or on the order in which chunks are processed.

use std::sync::atomic::{AtomicU64, Ordering};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Points per random-stream chunk on the LiDAR side (fixed: chunk boundaries never depend on threads).
pub(crate) const CHUNK: usize = 2048;

static STREAMS_CREATED: AtomicU64 = AtomicU64::new(0);

/// How many random streams the weather simulator has constructed in this process (diagnostics: clear
/// weather must construct none).
pub fn rng_streams_created() -> u64 {
    STREAMS_CREATED.load(Ordering::Relaxed)
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A ChaCha8 stream for `(seed, tag, index)`; `tag` names the effect and sensor.
pub(crate) fn stream(seed: u64, tag: u64, index: u64) -> ChaCha8Rng {
    STREAMS_CREATED.fetch_add(1, Ordering::Relaxed);
    let mut a = seed;
    let mut b = tag ^ splitmix64(&mut a);
    let mut s = index ^ splitmix64(&mut b);
    let mut bytes = [0u8; 32];
    for c in bytes.chunks_exact_mut(8) {
        c.copy_from_slice(&splitmix64(&mut s).to_le_bytes());
    }
    ChaCha8Rng::from_seed(bytes)
}

/// Stream tags (effect x sensor).
pub(crate) mod tag {
    pub const LIDAR_FOG: u64 = 0x11;
    pub const LIDAR_RAIN: u64 = 0x12;
    pub const LIDAR_SNOW_FIELD: u64 = 0x13;
    pub const CAMERA_RAIN: u64 = 0x21;
    pub const CAMERA_SNOW: u64 = 0x22;
    pub const CAMERA_NOISE: u64 = 0x23;
}
