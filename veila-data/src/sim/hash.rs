//! Counter-based hashes for the simulator's per-ray random numbers: a value depends only on (seed,
//! pixel, stream), never on the order or thread rays are traced in.

/// SplitMix64: a well-mixed 64-bit hash, used for per-ray deterministic random numbers.
pub(crate) fn splitmix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// A uniform number in `[0, 1)` from a hash of (seed, pixel, stream).
#[inline]
pub(crate) fn hash_unit(seed: u64, pixel: u64, stream: u64) -> f32 {
    let h = splitmix(seed ^ splitmix(pixel.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ stream));
    (h >> 40) as f32 / (1u64 << 24) as f32
}
