//! CP decomposition by alternating least squares (Kolda & Bader 2009, §3.4).
//!
//! The tensor is given by its frontal slices `X_k` (`I x J`, one per expert:
//! `out x in` weights of expert k). A rank-`R` CP model is
//! `X_k ~ A diag(C[k, :]) B^T` with `A: I x R`, `B: J x R`, `C: K x R`; in the
//! runtime's terms `A` is `A`, `B` is `B` and row `k` of `C` is the core `d_k`.
//!
//! * Initialisation: the leading eigenvectors of `sum_k X_k X_k^T` and
//!   `sum_k X_k^T X_k` (the mode-1 and mode-2 HOSVD bases; random columns
//!   beyond their rank), then `C` by least squares.
//! * Each sweep solves for `A`, `B`, `C` in turn; the normal equations use
//!   the Hadamard product of the other factors' Gram matrices, solved by a
//!   Cholesky factorisation with a tiny ridge for rank-deficient cases.
//!   The MTTKRPs are computed slice by slice (`X_k B`, `X_k^T A`), so the
//!   cost of a sweep is `3 K I J R` multiply-adds and nothing of the size of
//!   a Khatri-Rao product is formed.
//! * `A` and `B` keep unit-norm columns; `C` carries the scale.
//! * Stops when the relative error changes by less than `tol` (relative) or
//!   after `max_iters` sweeps; the error reported is recomputed exactly from
//!   the slices at the end.

use nalgebra::{DMatrix, SymmetricEigen};
use ndarray::{s, Array1, Array2, Axis};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// Knobs of CP-ALS.
#[derive(Clone, Debug)]
pub struct AlsOptions {
    /// Most sweeps.
    pub max_iters: usize,
    /// Stop when the relative error improves by less than this fraction.
    pub tol: f64,
    /// Seed of the random columns (used only where the HOSVD runs out).
    pub seed: u64,
    /// Tikhonov regularisation of every least-squares step, relative to
    /// the mean diagonal of its normal matrix. Post-hoc CP of trained
    /// weights tends to degenerate (pairs of large components that cancel);
    /// those amplify every rounding error of fixed point, and a small ridge
    /// keeps the components' norms near the tensor's at a small cost in fit.
    pub ridge: f64,
}

impl Default for AlsOptions {
    fn default() -> Self {
        AlsOptions {
            max_iters: 200,
            tol: 1e-7,
            seed: 0xC0FFEE,
            ridge: 0.0,
        }
    }
}

/// A rank-`R` CP model of a 3-way tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct CpFactors {
    /// `I x R`.
    pub a: Array2<f64>,
    /// `J x R`.
    pub b: Array2<f64>,
    /// `K x R`.
    pub c: Array2<f64>,
}

impl CpFactors {
    /// The rank.
    pub fn rank(&self) -> usize {
        self.a.ncols()
    }

    /// Slice `k`: `A diag(C[k, :]) B^T`.
    pub fn slice(&self, k: usize) -> Array2<f64> {
        let scaled = &self.a * &self.c.row(k);
        scaled.dot(&self.b.t())
    }
}

/// Outcome of [`cp_als`].
#[derive(Clone, Debug)]
pub struct AlsResult {
    /// The factors.
    pub factors: CpFactors,
    /// `||X - X_hat||_F / ||X||_F`, computed exactly from the slices.
    pub rel_error: f64,
    /// Sweeps run.
    pub iterations: usize,
}

/// Frobenius norm of the difference between the slices and the model,
/// relative to the slices' norm.
pub fn relative_error(slices: &[Array2<f64>], f: &CpFactors) -> f64 {
    let (mut err, mut norm) = (0.0, 0.0);
    for (k, x) in slices.iter().enumerate() {
        let d = x - &f.slice(k);
        err += d.iter().map(|v| v * v).sum::<f64>();
        norm += x.iter().map(|v| v * v).sum::<f64>();
    }
    if norm > 0.0 {
        (err / norm).sqrt()
    } else {
        err.sqrt()
    }
}

fn to_na(m: &Array2<f64>) -> DMatrix<f64> {
    DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

/// The `r` leading eigenvectors of the symmetric `g` as columns; random
/// unit columns where `r` exceeds its size.
fn leading_eigvecs(g: &Array2<f64>, r: usize, rng: &mut ChaCha8Rng) -> Array2<f64> {
    let n = g.nrows();
    let eig = SymmetricEigen::new(to_na(g));
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let mut out = Array2::zeros((n, r));
    for (col, &i) in order.iter().take(r).enumerate() {
        for row in 0..n {
            out[(row, col)] = eig.eigenvectors[(row, i)];
        }
    }
    for col in n.min(r)..r {
        let v: Array1<f64> = (0..n).map(|_| StandardNormal.sample(rng)).collect();
        let norm = v.dot(&v).sqrt().max(1e-300);
        out.column_mut(col).assign(&(v / norm));
    }
    out
}

/// Solves `X (V + ridge mean(diag V) I) = M` for `X` (`V` symmetric
/// positive semi-definite, `R x R`).
fn solve_right(m: &Array2<f64>, v: &Array2<f64>, ridge: f64) -> Array2<f64> {
    let r = v.nrows();
    let trace: f64 = (0..r).map(|i| v[(i, i)]).sum();
    let ridge = (1e-13 + ridge) * trace / r.max(1) as f64 + f64::MIN_POSITIVE;
    let mut vn = to_na(v);
    for i in 0..r {
        vn[(i, i)] += ridge;
    }
    let rhs = to_na(&m.t().to_owned());
    let sol = match vn.clone().cholesky() {
        Some(ch) => ch.solve(&rhs),
        None => vn
            .pseudo_inverse(1e-12)
            .map(|p| p * &rhs)
            .unwrap_or_else(|_| DMatrix::zeros(r, m.nrows())),
    };
    Array2::from_shape_fn((m.nrows(), r), |(i, j)| sol[(j, i)])
}

fn gram(m: &Array2<f64>) -> Array2<f64> {
    m.t().dot(m)
}

/// Normalises the columns of `m` to unit norm; returns the norms.
fn normalise_columns(m: &mut Array2<f64>) -> Array1<f64> {
    let norms = m.map_axis(Axis(0), |c| c.dot(&c).sqrt());
    for (mut c, &n) in m.axis_iter_mut(Axis(1)).zip(&norms) {
        if n > 0.0 {
            c /= n;
        }
    }
    norms
}

/// `M3[k, r] = sum_ij X_k[i, j] A[i, r] B[j, r]`.
fn mttkrp3(slices: &[Array2<f64>], a: &Array2<f64>, b: &Array2<f64>) -> Array2<f64> {
    let mut m = Array2::zeros((slices.len(), a.ncols()));
    for (k, x) in slices.iter().enumerate() {
        let xb = x.dot(b);
        let row = (&xb * a).sum_axis(Axis(0));
        m.row_mut(k).assign(&row);
    }
    m
}

/// Rank-`rank` CP-ALS of the tensor with frontal slices `slices` (all the
/// same shape, at least one).
///
/// # Panics
/// If `slices` is empty, the slices differ in shape or `rank` is zero.
pub fn cp_als(slices: &[Array2<f64>], rank: usize, opts: &AlsOptions) -> AlsResult {
    assert!(
        !slices.is_empty() && rank > 0,
        "CP-ALS needs a tensor and a rank"
    );
    let (i_dim, j_dim) = slices[0].dim();
    assert!(
        slices.iter().all(|x| x.dim() == (i_dim, j_dim)),
        "CP-ALS slices differ in shape"
    );
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let norm_sq: f64 = slices
        .iter()
        .map(|x| x.iter().map(|v| v * v).sum::<f64>())
        .sum();
    let mut g1 = Array2::zeros((i_dim, i_dim));
    let mut g2 = Array2::zeros((j_dim, j_dim));
    for x in slices {
        g1 += &x.dot(&x.t());
        g2 += &x.t().dot(x);
    }
    let mut a = leading_eigvecs(&g1, rank, &mut rng);
    let mut b = leading_eigvecs(&g2, rank, &mut rng);
    let mut c = solve_right(
        &mttkrp3(slices, &a, &b),
        &(&gram(&a) * &gram(&b)),
        opts.ridge,
    );
    let mut prev = f64::INFINITY;
    let mut iterations = 0;
    for it in 0..opts.max_iters {
        iterations = it + 1;
        // A
        let mut m1 = Array2::zeros((i_dim, rank));
        for (k, x) in slices.iter().enumerate() {
            m1 += &(x.dot(&b) * c.row(k));
        }
        a = solve_right(&m1, &(&gram(&b) * &gram(&c)), opts.ridge);
        normalise_columns(&mut a);
        // B
        let mut m2 = Array2::zeros((j_dim, rank));
        for (k, x) in slices.iter().enumerate() {
            m2 += &(x.t().dot(&a) * c.row(k));
        }
        b = solve_right(&m2, &(&gram(&a) * &gram(&c)), opts.ridge);
        normalise_columns(&mut b);
        // C
        let m3 = mttkrp3(slices, &a, &b);
        let v = &gram(&a) * &gram(&b);
        c = solve_right(&m3, &v, opts.ridge);
        // Error from the normal equations: ||X||^2 - 2<X, Xh> + ||Xh||^2.
        let inner: f64 = (&m3 * &c).sum();
        let model_sq: f64 = (&v * &gram(&c)).sum();
        let err =
            ((norm_sq - 2.0 * inner + model_sq).max(0.0) / norm_sq.max(f64::MIN_POSITIVE)).sqrt();
        if (prev.is_finite() && (prev - err).abs() <= opts.tol * prev) || err < 1e-13 {
            break;
        }
        prev = err;
    }
    let factors = CpFactors { a, b, c };
    let rel_error = relative_error(slices, &factors);
    AlsResult {
        factors,
        rel_error,
        iterations,
    }
}

/// Sorts components by decreasing weight `||c_r||` (for readable reports
/// and deterministic layouts); the model is unchanged.
pub fn sort_components(f: &mut CpFactors) {
    let weights = f.c.map_axis(Axis(0), |c| c.dot(&c));
    let mut order: Vec<usize> = (0..f.rank()).collect();
    order.sort_by(|&i, &j| weights[j].total_cmp(&weights[i]));
    let pick = |m: &Array2<f64>| {
        let mut out = Array2::zeros(m.dim());
        for (to, &from) in order.iter().enumerate() {
            out.column_mut(to).assign(&m.column(from));
        }
        out
    };
    *f = CpFactors {
        a: pick(&f.a),
        b: pick(&f.b),
        c: pick(&f.c),
    };
}

/// The first `rank` components of `f` (after [`sort_components`], the
/// strongest ones).
pub fn truncate(f: &CpFactors, rank: usize) -> CpFactors {
    let r = rank.min(f.rank());
    CpFactors {
        a: f.a.slice(s![.., ..r]).to_owned(),
        b: f.b.slice(s![.., ..r]).to_owned(),
        c: f.c.slice(s![.., ..r]).to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> Array2<f64> {
        Array2::from_shape_fn((rows, cols), |_| StandardNormal.sample(rng))
    }

    fn known_rank(i: usize, j: usize, k: usize, r: usize, seed: u64) -> Vec<Array2<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let f = CpFactors {
            a: random(i, r, &mut rng),
            b: random(j, r, &mut rng),
            c: random(k, r, &mut rng),
        };
        (0..k).map(|kk| f.slice(kk)).collect()
    }

    /// The bar: a tensor of known rank is recovered to 1e-6.
    #[test]
    fn recovers_tensors_of_known_rank() {
        for (dims, r, seed) in [
            ((30, 20, 4), 3, 1u64),
            ((40, 25, 6), 5, 2),
            ((24, 24, 4), 4, 3),
            ((50, 30, 10), 8, 4),
        ] {
            let x = known_rank(dims.0, dims.1, dims.2, r, seed);
            let res = cp_als(
                &x,
                r,
                &AlsOptions {
                    max_iters: 2000,
                    tol: 1e-14,
                    ..AlsOptions::default()
                },
            );
            println!(
                "{dims:?} rank {r}: {:.2e} in {} sweeps",
                res.rel_error, res.iterations
            );
            assert!(
                res.rel_error < 1e-6,
                "{dims:?} rank {r}: {} after {} sweeps",
                res.rel_error,
                res.iterations
            );
        }
    }

    #[test]
    fn error_falls_with_rank_and_vanishes_at_full_rank() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let x: Vec<_> = (0..4).map(|_| random(12, 8, &mut rng)).collect();
        let errs: Vec<f64> = [1, 4, 8, 16, 32]
            .iter()
            .map(|&r| cp_als(&x, r, &AlsOptions::default()).rel_error)
            .collect();
        for w in errs.windows(2) {
            assert!(w[1] <= w[0] + 1e-9, "{errs:?}");
        }
        // Rank K * min(I, J) = 32 is always enough for K = 4 slices.
        assert!(errs[4] < 1e-4, "{errs:?}");
    }

    #[test]
    fn sort_and_truncate_keep_the_model() {
        let x = known_rank(10, 9, 4, 3, 5);
        let mut f = cp_als(&x, 3, &AlsOptions::default()).factors;
        let before = relative_error(&x, &f);
        sort_components(&mut f);
        assert!((relative_error(&x, &f) - before).abs() < 1e-12);
        let w: Vec<f64> = f.c.map_axis(Axis(0), |c| c.dot(&c)).to_vec();
        assert!(w.windows(2).all(|p| p[0] >= p[1]));
        assert_eq!(truncate(&f, 2).rank(), 2);
    }
}
