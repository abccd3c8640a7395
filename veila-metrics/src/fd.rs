//! Fréchet distance between Gaussian fits of two feature sets (FRD, FPD, FID-style scores).
//!
//! `FD = ‖μ₁ - μ₂‖² + Tr(Σ₁ + Σ₂ - 2 (Σ₁ Σ₂)^{1/2})` with `Σ` the unbiased sample covariance (`numpy.cov(x,
//! rowvar=False)`, divisor `n - 1`), computed in `f64`.
//!
//! **Stable trace term ([`SqrtMethod::Eigen`], the default).** `Σ₁ Σ₂` is not symmetric, and `scipy.linalg.sqrtm`
//! (used by the reference implementations) returns complex round-off for singular covariances. Instead,
//! with `Σ₁ = V Λ Vᵀ` (self-adjoint eigendecomposition) and `A = V Λ^{1/2}` restricted to the eigenvalues
//! above the rank tolerance `d·ε·λ_max`, the matrix `Σ₁^{1/2} Σ₂ Σ₁^{1/2}` is orthogonally similar to the
//! symmetric positive semi-definite `Aᵀ Σ₂ A`, which has the same non-zero eigenvalues as `Σ₁ Σ₂`. Hence
//! `Tr (Σ₁ Σ₂)^{1/2} = Σᵢ sqrt(max(μᵢ, 0))` over the eigenvalues `μᵢ` of `Aᵀ Σ₂ A` (tiny negative ones from
//! rounding clamped to 0). This is exact for singular covariances and for fewer samples than dimensions
//! (the matrix then shrinks to the rank of `Σ₁`). When `Σ₁` is well inside the positive-definite cone its
//! Cholesky factor serves as `A` instead (same eigenvalues, cheaper; see [`trace_sqrt_product_eigen`]).
//! The result is clamped at 0; bitwise identical statistics give exactly 0.
//!
//! **Newton–Schulz ([`SqrtMethod::NewtonSchulz`]).** The coupled iteration `T = (3I - Z Y)/2, Y ← Y T,
//! Z ← T Z` started from `Y = Σ₁Σ₂ / ‖Σ₁Σ₂‖_F, Z = I` (three matrix products per step, no eigensolver), as used
//! by "fast FID" implementations. It converges quadratically on well-conditioned problems but slowly for
//! (near-)zero eigenvalues; benchmarks print its error next to its time.
//!
//! **Streaming statistics.** [`FeatureStats`] keeps `n`, the running mean and `M2 = Σ (x - μ)(x - μ)ᵀ`
//! (the centred sum of outer products). Batches are centred on their own mean before the outer-product
//! accumulation (a matrix product), and batches / shards are combined with Chan et al.'s parallel update
//! `M2 = M2_a + M2_b + δδᵀ n_a n_b / n`, which avoids the cancellation of the naive
//! `Σ xxᵀ - n μμᵀ` form.

use faer::{Accum, Mat, MatRef, Par, Side};

use crate::{Error, Result};

/// How `Tr (Σ₁ Σ₂)^{1/2}` is computed; see the [module docs](self).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SqrtMethod {
    /// Exact: symmetric form through two self-adjoint eigendecompositions.
    #[default]
    Eigen,
    /// Approximate: a fixed number of coupled Newton–Schulz iterations on `Σ₁ Σ₂`.
    NewtonSchulz {
        /// Number of iterations (each costs three `d x d` matrix products).
        iterations: usize,
    },
}

impl SqrtMethod {
    /// The most Newton–Schulz iterations accepted (it converges quadratically: far fewer do).
    pub const MAX_ITERATIONS: usize = 1000;

    /// Refuse settings outside their sense: Newton–Schulz needs 1 to [`Self::MAX_ITERATIONS`]
    /// iterations (0 would return the unconverged starting matrix's trace as if it were a result).
    pub fn check(&self) -> Result<()> {
        match *self {
            SqrtMethod::NewtonSchulz { iterations }
                if !(1..=Self::MAX_ITERATIONS).contains(&iterations) =>
            {
                Err(Error::InvalidParameter {
                    name: "Newton-Schulz iterations",
                    reason: format!(
                        "{iterations}: must be between 1 and {}",
                        Self::MAX_ITERATIONS
                    ),
                })
            }
            _ => Ok(()),
        }
    }
}

/// The largest feature dimension [`FeatureStats::try_new`] accepts: the statistics and the
/// distance hold a few `dim x dim` matrices of `f64` (128 MiB each at this size). A wider feature
/// row is refused before anything is allocated (a `(4, 65536)` array would need 34 GB per matrix).
pub const MAX_FEATURE_DIM: usize = 4096;

/// Streaming, mergeable first and second moments of feature rows (see the [module docs](self)).
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    dim: usize,
    n: u64,
    mean: Vec<f64>,
    m2: Mat<f64>,
}

impl FeatureStats {
    /// Empty statistics for `dim`-dimensional rows.
    pub fn new(dim: usize) -> Self {
        Self {
            dim,
            n: 0,
            mean: vec![0.0; dim],
            m2: Mat::zeros(dim, dim),
        }
    }

    /// Empty statistics for `dim`-dimensional rows, `dim` checked against [`MAX_FEATURE_DIM`]
    /// (use this where the dimension comes from an input; `what` names it in the error).
    pub fn try_new(dim: usize, what: &str) -> Result<Self> {
        if dim > MAX_FEATURE_DIM {
            let gb = (dim as f64).powi(2) * 8.0 / 1e9;
            return Err(Error::ShapeMismatch {
                what: what.to_string(),
                expected: format!("at most {MAX_FEATURE_DIM} features per row"),
                got: format!("{dim} (a {dim} x {dim} covariance would take {gb:.1} GB)"),
            });
        }
        Ok(Self::new(dim))
    }

    /// Statistics of a row-major `rows.len() / dim` x `dim` matrix (`dim` at most
    /// [`MAX_FEATURE_DIM`]).
    pub fn from_rows<T: Copy + Into<f64>>(rows: &[T], dim: usize, what: &str) -> Result<Self> {
        let mut s = Self::try_new(dim, what)?;
        s.push_rows(rows, what)?;
        Ok(s)
    }

    /// Feature dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of rows seen.
    pub fn count(&self) -> u64 {
        self.n
    }

    /// Running mean.
    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    /// Adds a batch of rows (row-major, `rows.len()` a multiple of `dim`). Rows with NaN or infinite values
    /// are rejected ([`Error::NonFinite`] with the flat index); nothing is added on error.
    pub fn push_rows<T: Copy + Into<f64>>(&mut self, rows: &[T], what: &str) -> Result<()> {
        let d = self.dim;
        if d == 0 {
            return Err(Error::InvalidParameter {
                name: "dim",
                reason: "feature dimension must be > 0".into(),
            });
        }
        if !rows.len().is_multiple_of(d) {
            return Err(Error::ShapeMismatch {
                what: what.to_string(),
                expected: format!("a multiple of {d} values"),
                got: format!("{} values", rows.len()),
            });
        }
        let k = rows.len() / d;
        if k == 0 {
            return Ok(());
        }
        let mut x = Mat::<f64>::from_fn(k, d, |i, j| rows[i * d + j].into());
        for i in 0..k {
            for j in 0..d {
                if !x[(i, j)].is_finite() {
                    return Err(Error::NonFinite {
                        what: what.to_string(),
                        index: i * d + j,
                    });
                }
            }
        }
        let mut mb = vec![0.0f64; d];
        for i in 0..k {
            for j in 0..d {
                mb[j] += x[(i, j)];
            }
        }
        for v in &mut mb {
            *v /= k as f64;
        }
        for i in 0..k {
            for j in 0..d {
                x[(i, j)] -= mb[j];
            }
        }
        let mut m2b = Mat::<f64>::zeros(d, d);
        faer::linalg::matmul::matmul(
            m2b.as_mut(),
            Accum::Replace,
            x.transpose(),
            x.as_ref(),
            1.0,
            Par::rayon(0),
        );
        self.merge_parts(k as u64, &mb, &m2b);
        Ok(())
    }

    fn merge_parts(&mut self, nb: u64, mb: &[f64], m2b: &Mat<f64>) {
        if nb == 0 {
            return;
        }
        if self.n == 0 {
            self.n = nb;
            self.mean.copy_from_slice(mb);
            self.m2 = m2b.clone();
            return;
        }
        let (na_f, nb_f) = (self.n as f64, nb as f64);
        let n = na_f + nb_f;
        let delta: Vec<f64> = mb.iter().zip(&self.mean).map(|(b, a)| b - a).collect();
        let w = na_f * nb_f / n;
        let d = self.dim;
        for i in 0..d {
            for j in 0..d {
                self.m2[(i, j)] += m2b[(i, j)] + delta[i] * delta[j] * w;
            }
        }
        for (m, dl) in self.mean.iter_mut().zip(&delta) {
            *m += dl * nb_f / n;
        }
        self.n += nb;
    }

    /// Merges the statistics of another shard (same dimension) into `self`.
    pub fn merge(&mut self, other: &FeatureStats) -> Result<()> {
        if other.dim != self.dim {
            return Err(Error::ShapeMismatch {
                what: "merged feature statistics".into(),
                expected: format!("dimension {}", self.dim),
                got: format!("dimension {}", other.dim),
            });
        }
        let (nb, mb, m2b) = (other.n, other.mean.clone(), other.m2.clone());
        self.merge_parts(nb, &mb, &m2b);
        Ok(())
    }

    /// The unbiased covariance (`numpy.cov(rowvar=False)`, divisor `n - 1`), row-major `dim x dim`.
    pub fn covariance(&self) -> Result<Vec<f64>> {
        let c = self.covariance_mat("feature statistics")?;
        let d = self.dim;
        Ok((0..d * d).map(|k| c[(k / d, k % d)]).collect())
    }

    fn covariance_mat(&self, what: &str) -> Result<Mat<f64>> {
        if self.n < 2 {
            return Err(Error::TooFewSamples {
                what: what.to_string(),
                needed: 2,
                got: self.n as usize,
            });
        }
        let s = 1.0 / (self.n as f64 - 1.0);
        let d = self.dim;
        Ok(Mat::from_fn(d, d, |i, j| {
            0.5 * (self.m2[(i, j)] + self.m2[(j, i)]) * s
        }))
    }
}

/// Fréchet distance between two feature sets given as statistics, with the exact method.
pub fn frechet_distance(a: &FeatureStats, b: &FeatureStats) -> Result<f64> {
    frechet_distance_with(a, b, SqrtMethod::Eigen)
}

/// Fréchet distance between two feature sets given as statistics.
pub fn frechet_distance_with(
    a: &FeatureStats,
    b: &FeatureStats,
    method: SqrtMethod,
) -> Result<f64> {
    method.check()?;
    if a.dim != b.dim {
        return Err(Error::ShapeMismatch {
            what: "second feature set".into(),
            expected: format!("dimension {}", a.dim),
            got: format!("dimension {}", b.dim),
        });
    }
    let s1 = a.covariance_mat("first feature set")?;
    let s2 = b.covariance_mat("second feature set")?;
    fd_impl(&a.mean, s1.as_ref(), &b.mean, s2.as_ref(), method)
}

/// Fréchet distance between two row-major feature matrices (`f32` or `f64`) with `dim` columns.
pub fn frechet_distance_rows<T: Copy + Into<f64>>(
    a: &[T],
    b: &[T],
    dim: usize,
    method: SqrtMethod,
) -> Result<f64> {
    let sa = FeatureStats::from_rows(a, dim, "first feature matrix")?;
    let sb = FeatureStats::from_rows(b, dim, "second feature matrix")?;
    frechet_distance_with(&sa, &sb, method)
}

/// Fréchet distance from means and covariances (row-major `d x d`; only symmetric inputs make sense, the
/// average of `Σ` and `Σᵀ` is used).
pub fn frechet_distance_from_moments(
    mu1: &[f64],
    sigma1: &[f64],
    mu2: &[f64],
    sigma2: &[f64],
    method: SqrtMethod,
) -> Result<f64> {
    method.check()?;
    let d = mu1.len();
    if d > MAX_FEATURE_DIM {
        return Err(Error::ShapeMismatch {
            what: "mu1".into(),
            expected: format!("at most {MAX_FEATURE_DIM} features"),
            got: d.to_string(),
        });
    }
    for (what, len, want) in [
        ("mu2", mu2.len(), d),
        ("sigma1", sigma1.len(), d * d),
        ("sigma2", sigma2.len(), d * d),
    ] {
        if len != want {
            return Err(Error::ShapeMismatch {
                what: what.into(),
                expected: format!("{want} values"),
                got: format!("{len}"),
            });
        }
    }
    let s1 = Mat::from_fn(d, d, |i, j| 0.5 * (sigma1[i * d + j] + sigma1[j * d + i]));
    let s2 = Mat::from_fn(d, d, |i, j| 0.5 * (sigma2[i * d + j] + sigma2[j * d + i]));
    fd_impl(mu1, s1.as_ref(), mu2, s2.as_ref(), method)
}

fn check_finite_mat(m: MatRef<'_, f64>, what: &str) -> Result<()> {
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            if !m[(i, j)].is_finite() {
                return Err(Error::NonFinite {
                    what: what.into(),
                    index: i * m.ncols() + j,
                });
            }
        }
    }
    Ok(())
}

fn fd_impl(
    mu1: &[f64],
    s1: MatRef<'_, f64>,
    mu2: &[f64],
    s2: MatRef<'_, f64>,
    method: SqrtMethod,
) -> Result<f64> {
    method.check()?;
    let d = mu1.len();
    if d == 0 {
        return Err(Error::empty("feature dimension"));
    }
    for (what, mu) in [("mu1", mu1), ("mu2", mu2)] {
        if let Some(i) = mu.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: what.into(),
                index: i,
            });
        }
    }
    check_finite_mat(s1, "sigma1")?;
    check_finite_mat(s2, "sigma2")?;
    if mu1 == mu2 && s1 == s2 {
        return Ok(0.0);
    }
    let mean_term: f64 = mu1.iter().zip(mu2).map(|(a, b)| (a - b) * (a - b)).sum();
    let tr1: f64 = (0..d).map(|i| s1[(i, i)]).sum();
    let tr2: f64 = (0..d).map(|i| s2[(i, i)]).sum();
    let tr_sqrt = match method {
        SqrtMethod::Eigen => trace_sqrt_product_eigen(s1, s2)?,
        SqrtMethod::NewtonSchulz { iterations } => {
            trace_sqrt_product_newton_schulz(s1, s2, iterations)?
        }
    };
    let fd = mean_term + tr1 + tr2 - 2.0 * tr_sqrt;
    // `f64::max` would turn a NaN into 0, a perfect score: a non-finite result is an error instead
    if !fd.is_finite() {
        return Err(Error::Linalg(format!(
            "the Fréchet distance is not finite ({fd}); the trace term was {tr_sqrt}"
        )));
    }
    Ok(fd.max(0.0))
}

/// `Tr (S1 S2)^{1/2}` for symmetric positive semi-definite `S1`, `S2`, exactly (see the module docs).
///
/// Fast path: when `S1` is numerically positive definite (its Cholesky factor `L` exists and
/// `min L_ii² > d·ε·max S1_ii`), `A = L` is used instead of `V Λ^{1/2}` (any `A` with `A Aᵀ = S1` works), which
/// replaces the first eigendecomposition by a Cholesky factorisation and halves the matrix products.
/// Otherwise the eigendecomposition path drops the eigenvalues of `S1` below its rank tolerance
/// `d·ε·λ_max` (their square roots would be `√ε`-level noise).
pub fn trace_sqrt_product_eigen(s1: MatRef<'_, f64>, s2: MatRef<'_, f64>) -> Result<f64> {
    use faer::linalg::matmul::triangular::{BlockStructure, matmul as tri_matmul};
    let d = s1.nrows();
    let max_diag = (0..d).map(|i| s1[(i, i)]).fold(0.0f64, f64::max);
    if max_diag <= 0.0 {
        return Ok(0.0);
    }
    let par = Par::rayon(0);
    if let Ok(llt) = s1.llt(Side::Lower) {
        let l = llt.L();
        let min_l2 = (0..d)
            .map(|i| l[(i, i)] * l[(i, i)])
            .fold(f64::INFINITY, f64::min);
        if min_l2 > d as f64 * f64::EPSILON * max_diag {
            // C = S2 L, M = Lᵀ C (lower half only)
            let mut c = Mat::<f64>::zeros(d, d);
            tri_matmul(
                c.as_mut(),
                BlockStructure::Rectangular,
                Accum::Replace,
                s2,
                BlockStructure::Rectangular,
                l,
                BlockStructure::TriangularLower,
                1.0,
                par,
            );
            let mut m = Mat::<f64>::zeros(d, d);
            tri_matmul(
                m.as_mut(),
                BlockStructure::TriangularLower,
                Accum::Replace,
                l.transpose(),
                BlockStructure::TriangularUpper,
                c.as_ref(),
                BlockStructure::Rectangular,
                1.0,
                par,
            );
            let mu = m
                .self_adjoint_eigenvalues(Side::Lower)
                .map_err(|e| Error::Linalg(format!("eigenvalues: {e:?}")))?;
            return Ok(mu.iter().map(|&v| v.max(0.0).sqrt()).sum());
        }
    }
    let evd = s1
        .self_adjoint_eigen(Side::Lower)
        .map_err(|e| Error::Linalg(format!("eigendecomposition: {e:?}")))?;
    let u = evd.U();
    let lam = evd.S().column_vector();
    // eigenvalues below the rank tolerance are zero: their square roots (~sqrt(eps)) would otherwise leak
    // into the trace
    let lam_max = (0..d).map(|i| lam[i]).fold(0.0f64, f64::max);
    let floor = lam_max * d as f64 * f64::EPSILON;
    let keep: Vec<usize> = (0..d).filter(|&i| lam[i] > floor).collect();
    if keep.is_empty() {
        return Ok(0.0);
    }
    let r = keep.len();
    let a = Mat::<f64>::from_fn(d, r, |i, k| u[(i, keep[k])] * lam[keep[k]].sqrt());
    let mut c = Mat::<f64>::zeros(d, r);
    faer::linalg::matmul::matmul(c.as_mut(), Accum::Replace, s2, a.as_ref(), 1.0, par);
    let mut m = Mat::<f64>::zeros(r, r);
    faer::linalg::matmul::matmul(
        m.as_mut(),
        Accum::Replace,
        a.transpose(),
        c.as_ref(),
        1.0,
        par,
    );
    let mu = m
        .self_adjoint_eigenvalues(Side::Lower)
        .map_err(|e| Error::Linalg(format!("eigenvalues: {e:?}")))?;
    Ok(mu.iter().map(|&v| v.max(0.0).sqrt()).sum())
}

/// `Tr (S1 S2)^{1/2}` approximated with `iterations` coupled Newton–Schulz steps (see the module docs).
///
/// Errors ([`Error::Linalg`]) when the iteration diverges: a non-finite iterate (it stops at the first
/// one), or a final residual `‖Y² − P‖_F / ‖P‖_F` (`P = S1 S2 / ‖S1 S2‖_F`) larger than the starting
/// one. Rank-deficient covariances (fewer samples than features) make it diverge; use the exact
/// [`trace_sqrt_product_eigen`] there.
pub fn trace_sqrt_product_newton_schulz(
    s1: MatRef<'_, f64>,
    s2: MatRef<'_, f64>,
    iterations: usize,
) -> Result<f64> {
    let d = s1.nrows();
    let par = Par::rayon(0);
    let mut p = Mat::<f64>::zeros(d, d);
    faer::linalg::matmul::matmul(p.as_mut(), Accum::Replace, s1, s2, 1.0, par);
    let norm = p.norm_l2();
    if norm == 0.0 {
        return Ok(0.0);
    }
    if !norm.is_finite() {
        return Err(Error::Linalg(format!("Newton–Schulz: ‖Σ₁Σ₂‖_F is {norm}")));
    }
    let residual = |y: &Mat<f64>, pn: &Mat<f64>| -> f64 {
        let mut yy = Mat::<f64>::zeros(d, d);
        faer::linalg::matmul::matmul(
            yy.as_mut(),
            Accum::Replace,
            y.as_ref(),
            y.as_ref(),
            1.0,
            par,
        );
        let diff = Mat::<f64>::from_fn(d, d, |i, j| yy[(i, j)] - pn[(i, j)]);
        diff.norm_l2() / pn.norm_l2()
    };
    let mut y = Mat::<f64>::from_fn(d, d, |i, j| p[(i, j)] / norm);
    let pn = y.clone();
    let start = residual(&y, &pn);
    let mut z = Mat::<f64>::identity(d, d);
    let mut t = Mat::<f64>::zeros(d, d);
    let mut tmp = Mat::<f64>::zeros(d, d);
    for k in 0..iterations {
        // t = (3 I - z y) / 2
        faer::linalg::matmul::matmul(
            t.as_mut(),
            Accum::Replace,
            z.as_ref(),
            y.as_ref(),
            -0.5,
            par,
        );
        for i in 0..d {
            t[(i, i)] += 1.5;
        }
        faer::linalg::matmul::matmul(
            tmp.as_mut(),
            Accum::Replace,
            y.as_ref(),
            t.as_ref(),
            1.0,
            par,
        );
        std::mem::swap(&mut y, &mut tmp);
        faer::linalg::matmul::matmul(
            tmp.as_mut(),
            Accum::Replace,
            t.as_ref(),
            z.as_ref(),
            1.0,
            par,
        );
        std::mem::swap(&mut z, &mut tmp);
        if !(y.norm_l2().is_finite() && z.norm_l2().is_finite()) {
            return Err(Error::Linalg(format!(
                "Newton–Schulz diverged: non-finite iterate after {} of {iterations} iterations \
                 (rank-deficient covariances? use the exact eigendecomposition)",
                k + 1
            )));
        }
    }
    let end = residual(&y, &pn);
    if end.is_nan() || end > start.max(f64::EPSILON) {
        return Err(Error::Linalg(format!(
            "Newton–Schulz diverged: residual ‖Y² − P‖/‖P‖ grew from {start:.3e} to {end:.3e} in \
             {iterations} iterations (rank-deficient covariances? use the exact eigendecomposition)"
        )));
    }
    let tr: f64 = (0..d).map(|i| y[(i, i)]).sum();
    Ok(tr * norm.sqrt())
}
