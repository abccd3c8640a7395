//! The convolution's matrix products: [`matmul_into`] on `gemm` (candle's matrix-product crate) and
//! [`matmul_abt`], the weight gradient's `a · bᵀ` on `pulp`'s run-time-dispatched vector types.

use rayon::prelude::*;

/// `dst (m x n) = [dst +] lhs (m x k) · rhs (k x n)` with `gemm` (candle's own matrix-product
/// crate), every matrix given as `(slice, row stride, column stride)`; `accumulate` adds to `dst`,
/// `threaded` spreads the product over candle's thread count (the result is the same either way:
/// `gemm` splits the output, not the sum). The strides are checked against the slices, so the call
/// is in bounds.
pub(super) fn matmul_into(
    dst: (&mut [f32], usize, usize),
    (m, n, k): (usize, usize, usize),
    accumulate: bool,
    lhs: (&[f32], usize, usize),
    rhs: (&[f32], usize, usize),
    threaded: bool,
) -> candle_core::Result<()> {
    fn fits(len: usize, rows: usize, cols: usize, rs: usize, cs: usize) -> bool {
        rows == 0 || cols == 0 || (rows - 1) * rs + (cols - 1) * cs < len
    }
    let (d, d_rs, d_cs) = dst;
    if !fits(d.len(), m, n, d_rs, d_cs)
        || !fits(lhs.0.len(), m, k, lhs.1, lhs.2)
        || !fits(rhs.0.len(), k, n, rhs.1, rhs.2)
    {
        candle_core::bail!("matmul_into: a matrix does not fit its slice ({m}x{k} · {k}x{n})")
    }
    if m == 0 || n == 0 {
        return Ok(());
    }
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    d[i * d_rs + j * d_cs] = 0.0;
                }
            }
        }
        return Ok(());
    }
    // rayon's count, not `candle_core::utils::get_num_threads()`: candle 0.11 reads
    // `/proc/cpuinfo` on every call of that unless RAYON_NUM_THREADS is set
    let threads = rayon::current_num_threads();
    let parallelism = if threaded && threads > 1 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: `fits` checked that every element the three strided matrices address lies inside its
    // slice; `dst` is borrowed mutably and does not alias `lhs` or `rhs`.
    #[allow(unsafe_code)]
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            d.as_mut_ptr(),
            d_cs as isize,
            d_rs as isize,
            accumulate,
            lhs.0.as_ptr(),
            lhs.2 as isize,
            lhs.1 as isize,
            rhs.0.as_ptr(),
            rhs.2 as isize,
            rhs.1 as isize,
            if accumulate { 1.0 } else { 0.0 },
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
    Ok(())
}

/// `dst (m x nb, row-major) = a (m x len) · bᵀ` for `b (nb x len)` (or `dst +=` with
/// `accumulate`), rows `a_rs` and `b_rs` floats apart: every output is a dot product of two
/// contiguous rows. This is the weight gradient of a convolution (`g ·
/// colᵀ`, summed over the pixels), for which `gemm` first copies both operands into packed panels
/// (a transposing gather of the whole column matrix: most of that product's time, and more with
/// AVX-512's wider panels); here the rows are read in place, 4 x 3 outputs at a time in vector
/// accumulators (`pulp`: AVX-512, AVX2 + FMA or scalar, chosen at run time; fused multiply-adds
/// where the CPU has them, so the last bits depend on the CPU, as `gemm`'s do).
///
/// The rows of `b` are taken a group of [`abt_group`] at a time, and every block of `a`'s rows
/// is run against one group before the next group starts: the group then stays in the core's
/// second-level cache while `a` streams past it, instead of the whole of `b` (a convolution's
/// columns: 9.4 MB for a sample at 32 channels and 32 x 256 pixels) being read again from memory
/// for every four rows of `a`. Each output is still one dot product summed in the same order, so
/// the grouping changes no bit of the result.
struct Abt<'a> {
    dst: &'a mut [f32],
    a: &'a [f32],
    b: &'a [f32],
    m: usize,
    nb: usize,
    len: usize,
    a_rs: usize,
    b_rs: usize,
    accumulate: bool,
    /// Rows of `b` in a group (a multiple of 3, the block's width).
    group: usize,
}

/// About half the second-level cache of the smallest core this runs on (1 MiB on Zen 5, 1.25
/// MiB on Ice Lake): the bytes of `b`'s rows [`Abt`] keeps there at once.
const ABT_GROUP_BYTES: usize = 512 * 1024;

/// The rows of `b` in one of [`Abt`]'s groups for rows of `len` floats: as many as fit
/// [`ABT_GROUP_BYTES`], a multiple of 3, at least 3.
fn abt_group(len: usize) -> usize {
    let fit = ABT_GROUP_BYTES / (len.max(1) * std::mem::size_of::<f32>());
    (fit / 3 * 3).max(3)
}

impl pulp::WithSimd for Abt<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Abt {
            dst,
            a,
            b,
            m,
            nb,
            len,
            a_rs,
            b_rs,
            accumulate,
            group,
        } = self;
        let a_span = |i: usize| i * a_rs..i * a_rs + len;
        let b_span = |i: usize| i * b_rs..i * b_rs + len;
        let put = |d: &mut f32, t: f32| {
            if accumulate {
                *d += t;
            } else {
                *d = t;
            }
        };
        let dot = |x: &[f32], y: &[f32]| -> f32 {
            let (xs, xt) = S::as_simd_f32s(x);
            let (ys, yt) = S::as_simd_f32s(y);
            let mut acc = simd.splat_f32s(0.0);
            for (p, q) in xs.iter().zip(ys) {
                acc = simd.mul_add_f32s(*p, *q, acc);
            }
            let mut t = simd.reduce_sum_f32s(acc);
            for (p, q) in xt.iter().zip(yt) {
                t += p * q;
            }
            t
        };
        let group = group.max(3);
        for j0 in (0..nb).step_by(group) {
            let j_end = (j0 + group).min(nb);
            for i in (0..m).step_by(4) {
                for j in (j0..j_end).step_by(3) {
                    if i + 4 > m || j + 3 > nb {
                        for ii in i..(i + 4).min(m) {
                            for jj in j..(j + 3).min(nb) {
                                put(&mut dst[ii * nb + jj], dot(&a[a_span(ii)], &b[b_span(jj)]));
                            }
                        }
                        continue;
                    }
                    let ar = |r: usize| S::as_simd_f32s(&a[a_span(i + r)]);
                    let br = |q: usize| S::as_simd_f32s(&b[b_span(j + q)]);
                    let ((a0, a0t), (a1, a1t), (a2, a2t), (a3, a3t)) = (ar(0), ar(1), ar(2), ar(3));
                    let ((b0, b0t), (b1, b1t), (b2, b2t)) = (br(0), br(1), br(2));
                    let z = simd.splat_f32s(0.0);
                    let (mut c00, mut c01, mut c02) = (z, z, z);
                    let (mut c10, mut c11, mut c12) = (z, z, z);
                    let (mut c20, mut c21, mut c22) = (z, z, z);
                    let (mut c30, mut c31, mut c32) = (z, z, z);
                    for ((((x0, x1), x2), x3), ((y0, y1), y2)) in a0
                        .iter()
                        .zip(a1)
                        .zip(a2)
                        .zip(a3)
                        .zip(b0.iter().zip(b1).zip(b2))
                    {
                        c00 = simd.mul_add_f32s(*x0, *y0, c00);
                        c01 = simd.mul_add_f32s(*x0, *y1, c01);
                        c02 = simd.mul_add_f32s(*x0, *y2, c02);
                        c10 = simd.mul_add_f32s(*x1, *y0, c10);
                        c11 = simd.mul_add_f32s(*x1, *y1, c11);
                        c12 = simd.mul_add_f32s(*x1, *y2, c12);
                        c20 = simd.mul_add_f32s(*x2, *y0, c20);
                        c21 = simd.mul_add_f32s(*x2, *y1, c21);
                        c22 = simd.mul_add_f32s(*x2, *y2, c22);
                        c30 = simd.mul_add_f32s(*x3, *y0, c30);
                        c31 = simd.mul_add_f32s(*x3, *y1, c31);
                        c32 = simd.mul_add_f32s(*x3, *y2, c32);
                    }
                    let acc = [
                        [c00, c01, c02],
                        [c10, c11, c12],
                        [c20, c21, c22],
                        [c30, c31, c32],
                    ];
                    let (at, bt) = ([a0t, a1t, a2t, a3t], [b0t, b1t, b2t]);
                    for r in 0..4 {
                        for q in 0..3 {
                            let mut t = simd.reduce_sum_f32s(acc[r][q]);
                            for (p, v) in at[r].iter().zip(bt[q]) {
                                t += p * v;
                            }
                            put(&mut dst[(i + r) * nb + j + q], t);
                        }
                    }
                }
            }
        }
    }
}

/// [`Abt`] on the CPU's widest vector unit: `dst (m x nb) (+)= a · bᵀ`, `a`'s `m` and `b`'s `nb`
/// rows of `len` floats starting `a_rs` and `b_rs` floats apart. With `threaded`, blocks of output
/// rows are spread over rayon's threads (each output is one thread's, so the result does not
/// depend on the thread count).
pub(super) fn matmul_abt(
    dst: &mut [f32],
    (a, a_rs): (&[f32], usize),
    (b, b_rs): (&[f32], usize),
    (m, nb, len): (usize, usize, usize),
    accumulate: bool,
    threaded: bool,
) -> candle_core::Result<()> {
    let spans = |rows: usize, rs: usize| if rows == 0 { 0 } else { (rows - 1) * rs + len };
    let (a_need, b_need) = (spans(m, a_rs), spans(nb, b_rs));
    if dst.len() != m * nb || a.len() < a_need || b.len() < b_need || a_rs < len || b_rs < len {
        candle_core::bail!(
            "matmul_abt: a matrix does not fit its slice ({m}x{len} · ({nb}x{len})ᵀ, row \
             strides {a_rs} and {b_rs})"
        )
    }
    let (a, b) = (&a[..a_need], &b[..b_need]);
    let run = |dst: &mut [f32], a: &[f32], m: usize| {
        pulp::Arch::new().dispatch(Abt {
            dst,
            a,
            b,
            m,
            nb,
            len,
            a_rs,
            b_rs,
            accumulate,
            group: abt_group(len),
        });
    };
    const ROWS: usize = 4;
    if threaded && rayon::current_num_threads() > 1 && m > ROWS && nb > 0 {
        // a block's rows of `a`: ROWS strides, the last block's up to the end of `a`
        dst.par_chunks_mut(ROWS * nb)
            .enumerate()
            .for_each(|(blk, d)| {
                let start = blk * ROWS * a_rs;
                let rows = d.len() / nb;
                run(d, &a[start..start + spans(rows, a_rs)], rows)
            });
    } else {
        run(dst, a, m);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fused::pattern;

    #[test]
    fn matmul_abt_matches_an_f64_reference_on_every_vector_unit() {
        // whole 4 x 3 blocks, partial blocks in both directions, rows with a lane remainder
        for (m, nb, len) in [(8, 9, 64), (6, 7, 37), (1, 1, 5), (16, 144, 1000)] {
            let a = pattern(m * len, 0.37);
            let b = pattern(nb * len, 0.11);
            let want: Vec<f64> = (0..m * nb)
                .map(|ij| {
                    let (i, j) = (ij / nb, ij % nb);
                    (0..len)
                        .map(|p| f64::from(a[i * len + p]) * f64::from(b[j * len + p]))
                        .sum()
                })
                .collect();
            let scale = want.iter().fold(0f64, |s, v| s.max(v.abs())).max(1.0);
            let check = |got: &[f32], what: &str| {
                for (g, w) in got.iter().zip(&want) {
                    assert!(
                        (f64::from(*g) - w).abs() <= 1e-5 * scale,
                        "{what} {m}x{nb}x{len}: {g} against {w}"
                    );
                }
            };
            for threaded in [false, true] {
                let mut dst = vec![f32::NAN; m * nb];
                matmul_abt(
                    &mut dst,
                    (&a, len),
                    (&b, len),
                    (m, nb, len),
                    false,
                    threaded,
                )
                .unwrap();
                check(&dst, "dispatched");
                // the same rows inside wider ones (a column tile of a convolution), accumulated
                // onto a start of one half of the product: the other half is added on top
                let widen = |v: &[f32], rows: usize| -> Vec<f32> {
                    let mut out = vec![f32::NAN; rows * (len + 3)];
                    for r in 0..rows {
                        out[r * (len + 3) + 1..r * (len + 3) + 1 + len]
                            .copy_from_slice(&v[r * len..(r + 1) * len]);
                    }
                    out
                };
                let (wa, wb) = (widen(&a, m), widen(&b, nb));
                let half = len / 2;
                let mut acc = vec![0f32; m * nb];
                for (lo, n) in [(0, half), (half, len - half)] {
                    matmul_abt(
                        &mut acc,
                        (&wa[1 + lo..], len + 3),
                        (&wb[1 + lo..], len + 3),
                        (m, nb, n),
                        true,
                        threaded,
                    )
                    .unwrap();
                }
                check(&acc, "strided, accumulated");
            }
            // the product of contiguous rows in groups of `group` rows of `b`
            fn product<'a>(
                dst: &'a mut [f32],
                (a, b): (&'a [f32], &'a [f32]),
                (m, nb, len): (usize, usize, usize),
                group: usize,
            ) -> Abt<'a> {
                Abt {
                    dst,
                    a,
                    b,
                    m,
                    nb,
                    len,
                    a_rs: len,
                    b_rs: len,
                    accumulate: false,
                    group,
                }
            }
            let mut scalar = vec![f32::NAN; m * nb];
            pulp::Simd::vectorize(
                pulp::Scalar::new(),
                product(&mut scalar, (&a, &b), (m, nb, len), abt_group(len)),
            );
            check(&scalar, "scalar");
            // the groups of `b`'s rows change no bit: one group of 3 rows, of 6, of all of them
            let grouped = |group: usize| -> Vec<u32> {
                let mut dst = vec![f32::NAN; m * nb];
                pulp::Arch::new().dispatch(product(&mut dst, (&a, &b), (m, nb, len), group));
                dst.iter().map(|v| v.to_bits()).collect()
            };
            let whole = grouped(nb.div_ceil(3) * 3);
            for group in [3, 6] {
                assert_eq!(
                    grouped(group),
                    whole,
                    "{m}x{nb}x{len} in groups of {group} rows"
                );
            }
        }
        let mut small = vec![0f32; 4];
        assert!(
            matmul_abt(
                &mut small,
                (&[0.0; 3], 3),
                (&[0.0; 6], 3),
                (2, 2, 3),
                false,
                false
            )
            .is_err()
        );
        assert!(
            matmul_abt(
                &mut small,
                (&[0.0; 9], 2),
                (&[0.0; 9], 3),
                (2, 2, 3),
                false,
                false
            )
            .is_err()
        );
    }
}
