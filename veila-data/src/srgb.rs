//! The sRGB transfer functions of IEC 61966-2-1, shared by the simulator's camera, the weather
//! camera effects and `augment`: one formula each way, and an exact 8-bit encoder that reproduces the
//! formula's rounding with a threshold table (no `powf` per pixel).

/// Decoding: encoded `v` in `[0, 1]` to linear light; `v / 12.92` for `v <= 0.04045`, else
/// `((v + 0.055) / 1.055)^2.4` (the linear segment for negatives).
pub(crate) fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Encoding: linear light `l` in `[0, 1]` to encoded; `12.92 l` for `l <= 0.0031308`, else
/// `1.055 l^(1/2.4) - 0.055`.
pub(crate) fn linear_to_srgb(l: f32) -> f32 {
    if l <= 0.003_130_8 {
        12.92 * l
    } else {
        1.055 * l.powf(1.0 / 2.4) - 0.055
    }
}

/// The 8-bit encoding by the formula: clamped to `[0, 1]` (NaN to 0), encoded, scaled by 255 and
/// rounded to nearest (the slow path [`linear_to_srgb_u8`] reproduces).
fn linear_to_srgb_u8_formula(x: f32) -> u8 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    (linear_to_srgb(x) * 255.0).round().clamp(0.0, 255.0) as u8
}

/// For each code k in 1..=255, the smallest non-negative f32 whose encoding is >= k (bisection on the
/// bit patterns, which order like the values for non-negative floats).
fn srgb_thresholds() -> &'static [f32; 255] {
    static T: std::sync::OnceLock<[f32; 255]> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let mut t = [0f32; 255];
        for (k, slot) in t.iter_mut().enumerate() {
            let want = (k + 1) as u8;
            let (mut lo, mut hi) = (0u32, 1.0f32.to_bits());
            while lo < hi {
                let mid = lo + (hi - lo) / 2;
                if linear_to_srgb_u8_formula(f32::from_bits(mid)) >= want {
                    hi = mid;
                } else {
                    lo = mid + 1;
                }
            }
            *slot = f32::from_bits(lo);
        }
        t
    })
}

/// The 8-bit sRGB code of linear light `x` (clamped to `[0, 1]`; NaN to 0), rounding to nearest:
/// exactly the formula's result, found in a table of the 255 code thresholds.
#[allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > 0)` also sends NaN to 0
pub(crate) fn linear_to_srgb_u8(x: f32) -> u8 {
    if !(x > 0.0) {
        return 0;
    }
    srgb_thresholds().partition_point(|t| *t <= x) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_encoding_equals_the_formula() {
        let mut x = 0.0f32;
        while x <= 1.001 {
            assert_eq!(linear_to_srgb_u8(x), linear_to_srgb_u8_formula(x), "{x}");
            x += 1.7e-5;
        }
        for t in srgb_thresholds() {
            let below = f32::from_bits(t.to_bits() - 1);
            assert_eq!(linear_to_srgb_u8(*t), linear_to_srgb_u8_formula(*t));
            assert_eq!(linear_to_srgb_u8(below), linear_to_srgb_u8_formula(below));
        }
        assert_eq!(linear_to_srgb_u8(f32::NAN), 0);
        assert_eq!(linear_to_srgb_u8(f32::INFINITY), 255);
        assert_eq!(linear_to_srgb_u8(-1.0), 0);
    }
}
