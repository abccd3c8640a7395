//! Distribution metrics over BEV histograms: JSD (R2DM / LiDARGen) and the Gaussian-kernel maximum mean
//! discrepancy of R2DM and of LiDARGen.
//!
//! | function | protocol | definition |
//! |---|---|---|
//! | [`jsd`] | `r2dm` (= LiDARGen) | `scipy.spatial.distance.jensenshannon(P, Q)` of the summed, normalised histograms: the JS **distance** `sqrt((KL(P‖M) + KL(Q‖M)) / 2)`, `M = (P+Q)/2`, natural log |
//! | [`mmd_r2dm_dense`], [`mmd_r2dm_sparse`] | `r2dm` | biased MMD², `mean K(X,X) + mean K(Y,Y) - 2 mean K(X,Y)` (diagonals included) over per-scan normalised histograms, `K = exp(-‖a-b‖² / (2 σ²))`, `‖·‖` the Euclidean norm of the flattened histogram, `σ = 0.5` |
//! | [`mmd_lidargen`] | `lidargen` | the same estimator but `‖·‖` is `numpy.linalg.norm(a - b, 2)` of the 2-D `bins x bins` difference, i.e. its **spectral norm** (largest singular value) |
//!
//! Papers print the R2DM MMD multiplied by 10⁴ ([`MMD_PAPER_SCALE`]).
//!
//! Empty inputs: an empty set of scans is [`Error::Empty`]. For JSD a set whose summed histogram is zero is
//! [`Error::NoPointsInWindow`]. For MMD every scan is normalised on its own, so a scan with no point in the
//! window has no defined distribution: it is reported as [`Error::NoPointsInWindow`] naming the scan (the
//! reference implementations divide by zero and propagate NaN). Filter such scans out first if that is the
//! intended protocol.
//!
//! All values are non-negative: rounding can push the biased MMD² (a squared RKHS norm) or the JS divergence
//! an ulp below zero, and such values are clamped to `0`. Identical inputs give exactly `0`.

use faer::{Accum, Mat, Par};
use rayon::prelude::*;

use crate::bev::{BevHistogram, Histogram, SparseBevHistogram};
use crate::{Error, Result};

/// Factor by which papers multiply the R2DM BEV MMD before printing (raw values are ~1e-4).
pub const MMD_PAPER_SCALE: f64 = 1e4;
/// The kernel bandwidth of both R2DM and LiDARGen.
pub const MMD_SIGMA: f64 = 0.5;

/// `scipy.special.rel_entr(x, y)` for `x, y >= 0`.
#[inline]
fn rel_entr(x: f64, y: f64) -> f64 {
    if x > 0.0 && y > 0.0 {
        x * (x / y).ln()
    } else if x == 0.0 && y >= 0.0 {
        0.0
    } else {
        f64::INFINITY
    }
}

/// The Jensen-Shannon **distance** between two non-negative vectors, exactly as
/// `scipy.spatial.distance.jensenshannon(p, q)` (natural log): both are normalised to sum 1, then
/// `sqrt((KL(p‖m) + KL(q‖m)) / 2)` with `m = (p + q) / 2`. Two distributions with disjoint supports give
/// `sqrt(ln 2)`.
///
/// Errors: different lengths, empty vectors, negative or non-finite entries, or an all-zero vector.
pub fn jensen_shannon_distance(p: &[f64], q: &[f64]) -> Result<f64> {
    if p.len() != q.len() {
        return Err(Error::ShapeMismatch {
            what: "jensen_shannon_distance q".into(),
            expected: format!("{} entries", p.len()),
            got: format!("{} entries", q.len()),
        });
    }
    if p.is_empty() {
        return Err(Error::empty("jensen_shannon_distance input"));
    }
    for (name, v) in [("p", p), ("q", q)] {
        if let Some(i) = v.iter().position(|x| !x.is_finite() || *x < 0.0) {
            return Err(Error::NonFinite {
                what: format!("jensen_shannon_distance {name} (or negative)"),
                index: i,
            });
        }
    }
    let (sp, sq): (f64, f64) = (p.iter().sum(), q.iter().sum());
    if sp <= 0.0 || sq <= 0.0 {
        return Err(Error::empty(
            "jensen_shannon_distance distribution (all zeros)",
        ));
    }
    let (mut left, mut right) = (0.0f64, 0.0f64);
    for (&a, &b) in p.iter().zip(q) {
        let (a, b) = (a / sp, b / sq);
        let m = (a + b) / 2.0;
        left += rel_entr(a, m);
        right += rel_entr(b, m);
    }
    Ok(((left + right) / 2.0).max(0.0).sqrt())
}

fn summed<H: Histogram>(set: &[H], what: &str) -> Result<Vec<f64>> {
    if set.is_empty() {
        return Err(Error::empty(format!("{what} set")));
    }
    let n = set[0].num_cells();
    let mut acc = vec![0u64; n];
    for (i, h) in set.iter().enumerate() {
        if h.num_cells() != n {
            return Err(Error::ShapeMismatch {
                what: format!("{what} histogram {i}"),
                expected: format!("{n} cells"),
                got: format!("{} cells", h.num_cells()),
            });
        }
        h.for_each_nonzero(|c, k| acc[c] += k as u64);
    }
    Ok(acc.into_iter().map(|c| c as f64).collect())
}

/// BEV JSD of the R2DM / LiDARGen protocol: the histograms of each set are summed, normalised, and compared
/// with [`jensen_shannon_distance`].
pub fn jsd<H: Histogram>(generated: &[H], reference: &[H]) -> Result<f64> {
    let p = summed(generated, "generated")?;
    let q = summed(reference, "reference")?;
    if p.len() != q.len() {
        return Err(Error::ShapeMismatch {
            what: "reference histograms".into(),
            expected: format!("{} cells", p.len()),
            got: format!("{} cells", q.len()),
        });
    }
    for (v, what) in [(&p, "generated"), (&q, "reference")] {
        if v.iter().all(|&x| x == 0.0) {
            return Err(Error::NoPointsInWindow {
                what: format!("every {what} scan"),
                window: "BEV".into(),
            });
        }
    }
    jensen_shannon_distance(&p, &q)
}

fn check_set<H: Histogram>(set: &[H], what: &str, cells: usize) -> Result<()> {
    if set.is_empty() {
        return Err(Error::empty(format!("{what} set")));
    }
    for (i, h) in set.iter().enumerate() {
        if h.num_cells() != cells {
            return Err(Error::ShapeMismatch {
                what: format!("{what} histogram {i}"),
                expected: format!("{cells} cells"),
                got: format!("{} cells", h.num_cells()),
            });
        }
        if h.total() == 0 {
            return Err(Error::NoPointsInWindow {
                what: format!("{what} scan {i}"),
                window: "BEV".into(),
            });
        }
    }
    Ok(())
}

fn check_sigma(sigma: f64) -> Result<()> {
    if sigma.is_finite() && sigma > 0.0 {
        Ok(())
    } else {
        Err(Error::InvalidParameter {
            name: "sigma",
            reason: format!("{sigma} must be finite and > 0"),
        })
    }
}

/// Combines the three kernel sums; exactly 0 when the blocks are bitwise equal.
fn combine(kxx: f64, nx: usize, kyy: f64, ny: usize, kxy: f64) -> f64 {
    let (nx, ny) = (nx as f64, ny as f64);
    let v = (kxx / (nx * nx) + kyy / (ny * ny)) - 2.0 * (kxy / (nx * ny));
    v.max(0.0)
}

fn normalized_matrix(set: &[BevHistogram]) -> Mat<f64> {
    let d = set[0].counts.len();
    let mut m = Mat::<f64>::zeros(set.len(), d);
    for (i, h) in set.iter().enumerate() {
        let t = h.total as f64;
        for (j, &c) in h.counts.iter().enumerate() {
            if c != 0 {
                m[(i, j)] = c as f64 / t;
            }
        }
    }
    m
}

fn row_norms(m: &Mat<f64>) -> Vec<f64> {
    (0..m.nrows())
        .map(|i| (0..m.ncols()).map(|j| m[(i, j)] * m[(i, j)]).sum())
        .collect()
}

/// Sum over all `(i, j)` of `exp(-max(na_i + nb_j - 2 g_ij, 0) * gamma)`, row sums in parallel, summed in order.
fn kernel_sum_from_gram(g: &Mat<f64>, na: &[f64], nb: &[f64], gamma: f64) -> f64 {
    let rows: Vec<f64> = (0..g.nrows())
        .into_par_iter()
        .map(|i| {
            (0..g.ncols())
                .map(|j| (-(na[i] + nb[j] - 2.0 * g[(i, j)]).max(0.0) * gamma).exp())
                .sum()
        })
        .collect();
    rows.iter().sum()
}

/// Kernel sum over all row pairs of `a` and `b`, the Gram matrix formed in blocks of rows of `a` so that
/// memory stays `O(BLOCK · rows(b))` however many scans there are.
fn kernel_sum_dense(a: &Mat<f64>, na: &[f64], b: &Mat<f64>, nb: &[f64], gamma: f64) -> f64 {
    const BLOCK: usize = 512;
    let mut total = 0.0;
    let mut start = 0;
    while start < a.nrows() {
        let rows = BLOCK.min(a.nrows() - start);
        let mut g = Mat::<f64>::zeros(rows, b.nrows());
        faer::linalg::matmul::matmul(
            g.as_mut(),
            Accum::Replace,
            a.as_ref().subrows(start, rows),
            b.transpose(),
            1.0,
            Par::rayon(0),
        );
        total += kernel_sum_from_gram(&g, &na[start..start + rows], nb, gamma);
        start += rows;
    }
    total
}

/// R2DM's BEV MMD (raw, not scaled) on dense histograms, through Gram matrices (`‖a-b‖² = ‖a‖² + ‖b‖² - 2a·b`
/// in `f64`, negatives from rounding clamped to 0) computed with dense matrix products in blocks of 512 scans.
/// Memory: the normalised histograms in `f64` (`8 · bins²` bytes per scan) plus one Gram block.
pub fn mmd_r2dm_dense(
    generated: &[BevHistogram],
    reference: &[BevHistogram],
    sigma: f64,
) -> Result<f64> {
    check_sigma(sigma)?;
    let cells = generated.first().map(|h| h.counts.len()).unwrap_or(0);
    check_set(generated, "generated", cells)?;
    check_set(reference, "reference", cells)?;
    let x = normalized_matrix(generated);
    let y = normalized_matrix(reference);
    let (nx, ny) = (row_norms(&x), row_norms(&y));
    let gamma = 1.0 / (2.0 * sigma * sigma);
    let kxx = kernel_sum_dense(&x, &nx, &x, &nx, gamma);
    let kyy = kernel_sum_dense(&y, &ny, &y, &ny, gamma);
    let kxy = kernel_sum_dense(&x, &nx, &y, &ny, gamma);
    Ok(combine(kxx, x.nrows(), kyy, y.nrows(), kxy))
}

struct SparseRow {
    cells: Vec<u32>,
    vals: Vec<f64>,
    norm2: f64,
}

fn sparse_rows(set: &[SparseBevHistogram]) -> Vec<SparseRow> {
    set.iter()
        .map(|h| {
            let t = h.total as f64;
            let vals: Vec<f64> = h.counts.iter().map(|&c| c as f64 / t).collect();
            let norm2 = vals.iter().map(|v| v * v).sum();
            SparseRow {
                cells: h.cells.clone(),
                vals,
                norm2,
            }
        })
        .collect()
}

fn kernel_sum_sparse(a: &[SparseRow], b: &[SparseRow], cells: usize, gamma: f64) -> f64 {
    let rows: Vec<f64> = a
        .par_iter()
        .map_init(
            || vec![0.0f64; cells],
            |buf, ra| {
                for (&c, &v) in ra.cells.iter().zip(&ra.vals) {
                    buf[c as usize] = v;
                }
                let mut s = 0.0;
                for rb in b {
                    let dot: f64 = rb
                        .cells
                        .iter()
                        .zip(&rb.vals)
                        .map(|(&c, &v)| buf[c as usize] * v)
                        .sum();
                    s += (-(ra.norm2 + rb.norm2 - 2.0 * dot).max(0.0) * gamma).exp();
                }
                for &c in &ra.cells {
                    buf[c as usize] = 0.0;
                }
                s
            },
        )
        .collect();
    rows.iter().sum()
}

/// R2DM's BEV MMD (raw) on sparse histograms: the same value as [`mmd_r2dm_dense`] up to rounding, with
/// each dot product costing the number of occupied cells instead of `bins²`.
pub fn mmd_r2dm_sparse(
    generated: &[SparseBevHistogram],
    reference: &[SparseBevHistogram],
    sigma: f64,
) -> Result<f64> {
    check_sigma(sigma)?;
    let cells = generated.first().map(|h| h.num_cells()).unwrap_or(0);
    check_set(generated, "generated", cells)?;
    check_set(reference, "reference", cells)?;
    let (x, y) = (sparse_rows(generated), sparse_rows(reference));
    let gamma = 1.0 / (2.0 * sigma * sigma);
    let kxx = kernel_sum_sparse(&x, &x, cells, gamma);
    let kyy = kernel_sum_sparse(&y, &y, cells, gamma);
    let kxy = kernel_sum_sparse(&x, &y, cells, gamma);
    Ok(combine(kxx, x.len(), kyy, y.len(), kxy))
}

/// Spectral norm (largest singular value) of a square matrix given row-major.
pub fn spectral_norm(values: &[f64], n: usize) -> Result<f64> {
    if values.len() != n * n {
        return Err(Error::ShapeMismatch {
            what: "spectral_norm input".into(),
            expected: format!("{} values", n * n),
            got: format!("{}", values.len()),
        });
    }
    if n == 0 {
        return Ok(0.0);
    }
    if values.iter().all(|&v| v == 0.0) {
        return Ok(0.0);
    }
    let m = Mat::<f64>::from_fn(n, n, |i, j| values[i * n + j]);
    let s = m
        .singular_values()
        .map_err(|e| Error::Linalg(format!("SVD failed: {e:?}")))?;
    Ok(s.first().copied().unwrap_or(0.0))
}

/// LiDARGen's BEV MMD (raw): the R2DM estimator with the distance between two normalised histograms taken
/// as the spectral norm of their `bins x bins` difference (`numpy.linalg.norm(a - b, 2)` on 2-D arrays).
/// Costs one small SVD per pair (LiDARGen runs it in a Python double loop).
pub fn mmd_lidargen(
    generated: &[BevHistogram],
    reference: &[BevHistogram],
    sigma: f64,
) -> Result<f64> {
    check_sigma(sigma)?;
    let cells = generated.first().map(|h| h.counts.len()).unwrap_or(0);
    check_set(generated, "generated", cells)?;
    check_set(reference, "reference", cells)?;
    let bins = generated[0].bins;
    if bins * bins != cells {
        return Err(Error::ShapeMismatch {
            what: "generated histogram".into(),
            expected: format!("{} cells for {bins} bins", bins * bins),
            got: format!("{cells}"),
        });
    }
    let x: Vec<Vec<f64>> = generated.iter().filter_map(|h| h.normalized()).collect();
    let y: Vec<Vec<f64>> = reference.iter().filter_map(|h| h.normalized()).collect();
    let gamma = 1.0 / (2.0 * sigma * sigma);
    let block = |a: &[Vec<f64>], b: &[Vec<f64>]| -> Result<f64> {
        let rows: Vec<Result<f64>> = a
            .par_iter()
            .map(|ra| {
                let mut diff = vec![0.0; cells];
                let mut s = 0.0;
                for rb in b {
                    for k in 0..cells {
                        diff[k] = ra[k] - rb[k];
                    }
                    let d = spectral_norm(&diff, bins)?;
                    s += (-(d * d) * gamma).exp();
                }
                Ok(s)
            })
            .collect();
        let mut total = 0.0;
        for r in rows {
            total += r?;
        }
        Ok(total)
    };
    let kxx = block(&x, &x)?;
    let kyy = block(&y, &y)?;
    let kxy = block(&x, &y)?;
    Ok(combine(kxx, x.len(), kyy, y.len(), kxy))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn js_disjoint_is_sqrt_ln2() {
        let d = jensen_shannon_distance(&[1.0, 0.0], &[0.0, 3.0]).unwrap();
        assert!((d - std::f64::consts::LN_2.sqrt()).abs() < 1e-15);
    }

    #[test]
    fn js_identical_is_exactly_zero() {
        let p = [0.1, 0.7, 0.2, 0.0, 1e-300];
        assert_eq!(jensen_shannon_distance(&p, &p).unwrap(), 0.0);
    }

    #[test]
    fn spectral_norm_of_diagonal() {
        let v = [3.0, 0.0, 0.0, -5.0];
        assert!((spectral_norm(&v, 2).unwrap() - 5.0).abs() < 1e-14);
    }
}
