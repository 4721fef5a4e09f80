//! Recovering the PFNN's trained control points from its phase tables.
//!
//! PFNN training learns four control points per tensor; the shipped model only
//! contains the periodic Catmull-Rom spline of those points sampled at `T`
//! phases (`s = 4 i / T`, `T = 50`). The fixed-point runtime wants the four
//! control points back: they are 12.5x smaller than the tables and give the
//! exact spline at every phase instead of the demo's nearest-table
//! approximation. Each table is a fixed linear combination of the control
//! points, so they are recovered by least squares with one `T x 4` basis
//! whose pseudo-inverse is computed once and applied element-wise. The basis
//! is well conditioned (about 1.43 for 50 tables), so nothing is amplified
//! beyond the float32 rounding already in the tables.
//!
//! All arithmetic here is `f64`: the recovered points feed a quantiser whose
//! own error budget must not be eaten by the reference.

use nalgebra::DMatrix;
use ndarray::{Array, Array1, Array2, Dimension, Zip};

use crate::pfnn_dir::LayerTables;

/// Number of control points of the phase spline.
pub const CONTROL_POINTS: usize = 4;

/// Catmull-Rom weights of the four control points at spline position `s`.
///
/// `s` runs over one period in `[0, 4)` (one unit per control point); any real
/// is wrapped into it. Returns `(control point index, weight)` for `k0..k3`
/// in spline order (`k1 = floor(s) mod 4` is the segment start); the weights
/// sum to 1 and at integer `s` the spline passes through control point `s`.
pub fn catmull_rom_weights(s: f64) -> [(usize, f64); 4] {
    let s = s.rem_euclid(CONTROL_POINTS as f64);
    let seg = s.floor();
    let mu = s - seg;
    // `rem_euclid` may round a tiny negative `s` up to exactly 4.0; the
    // modulo maps that back onto control point 0 (mu is then 0).
    let k1 = (seg as usize) % CONTROL_POINTS;
    let (mu2, mu3) = (mu * mu, mu * mu * mu);
    [
        ((k1 + 3) % 4, -0.5 * mu + mu2 - 0.5 * mu3),
        (k1, 1.0 - 2.5 * mu2 + 1.5 * mu3),
        ((k1 + 1) % 4, 0.5 * mu + 2.0 * mu2 - 1.5 * mu3),
        ((k1 + 2) % 4, -0.5 * mu2 + 0.5 * mu3),
    ]
}

/// Spline position of phase table `i` out of `tables`: `s = 4 i / T`.
pub fn table_position(i: usize, tables: usize) -> f64 {
    CONTROL_POINTS as f64 * i as f64 / tables as f64
}

/// The `tables x 4` matrix mapping control points to phase tables.
pub fn spline_basis(tables: usize) -> DMatrix<f64> {
    let mut b = DMatrix::zeros(tables, CONTROL_POINTS);
    for i in 0..tables {
        for (k, w) in catmull_rom_weights(table_position(i, tables)) {
            b[(i, k)] += w;
        }
    }
    b
}

/// Ratio of the largest to the smallest singular value of [`spline_basis`]:
/// the worst-case factor by which rounding in the tables can grow in the
/// recovered control points. Infinite if `tables < 4` (underdetermined).
pub fn basis_condition_number(tables: usize) -> f64 {
    if tables < CONTROL_POINTS {
        return f64::INFINITY;
    }
    let sv = spline_basis(tables).singular_values();
    sv.max() / sv.min()
}

/// How well the recovered spline reproduces the tables it came from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Residual {
    /// Largest absolute difference over all elements of all tables.
    pub max_abs: f64,
    /// `err_frobenius / ref_frobenius`: the headline number.
    pub rel_frobenius: f64,
    /// Frobenius norm of (spline at the table positions - tables).
    pub err_frobenius: f64,
    /// Frobenius norm of the tables.
    pub ref_frobenius: f64,
}

impl Residual {
    fn from_sums(max_abs: f64, err_sq: f64, ref_sq: f64) -> Self {
        let (err, reference) = (err_sq.sqrt(), ref_sq.sqrt());
        let rel_frobenius = if reference > 0.0 {
            err / reference
        } else {
            err
        };
        Self {
            max_abs,
            rel_frobenius,
            err_frobenius: err,
            ref_frobenius: reference,
        }
    }

    /// The residual of the union of the two tensor sets (e.g. all layers).
    pub fn combine(self, other: Self) -> Self {
        Self::from_sums(
            self.max_abs.max(other.max_abs),
            self.err_frobenius.powi(2) + other.err_frobenius.powi(2),
            self.ref_frobenius.powi(2) + other.ref_frobenius.powi(2),
        )
    }
}

/// One layer's four recovered control points.
#[derive(Clone, Debug, PartialEq)]
pub struct ControlPoints {
    /// Weight control points, `out x in` each.
    pub w: [Array2<f64>; 4],
    /// Bias control points.
    pub b: [Array1<f64>; 4],
    /// Spline-vs-tables error at the table positions.
    pub residual: Residual,
}

impl ControlPoints {
    /// Weights and bias of the spline at position `s` (see
    /// [`catmull_rom_weights`]). Allocates; meant for tests and tools, not
    /// for the inner loop.
    pub fn evaluate(&self, s: f64) -> (Array2<f64>, Array1<f64>) {
        let mut w = Array2::zeros(self.w[0].raw_dim());
        let mut b = Array1::zeros(self.b[0].raw_dim());
        for (k, g) in catmull_rom_weights(s) {
            w.scaled_add(g, &self.w[k]);
            b.scaled_add(g, &self.b[k]);
        }
        (w, b)
    }
}

/// Least-squares control points of a layer's phase tables (float32 tables,
/// as loaded from disk).
pub fn recover_control_points(tables: &LayerTables) -> ControlPoints {
    recover_control_points_from(&tables.w, &tables.b)
}

/// [`recover_control_points`] for tables of any float type (`f64` tables let
/// tests check the algebra far below float32 rounding).
///
/// All tables of a layer must share one shape. With fewer than four tables
/// the problem is underdetermined and the minimum-norm solution is returned.
pub fn recover_control_points_from<T: Copy + Into<f64>>(
    w: &[Array2<T>],
    b: &[Array1<T>],
) -> ControlPoints {
    let pinv = basis_pseudo_inverse(w.len());
    let w_cp: [Array2<f64>; 4] = std::array::from_fn(|k| project(w, pinv.row(k).iter()));
    let b_cp: [Array1<f64>; 4] = std::array::from_fn(|k| project(b, pinv.row(k).iter()));
    let basis = spline_basis(w.len());
    let (wm, we, wr) = residual_sums(w, &w_cp, &basis);
    let (bm, be, br) = residual_sums(b, &b_cp, &basis);
    ControlPoints {
        w: w_cp,
        b: b_cp,
        residual: Residual::from_sums(wm.max(bm), we + be, wr + br),
    }
}

/// `4 x tables` Moore-Penrose pseudo-inverse of the spline basis.
fn basis_pseudo_inverse(tables: usize) -> DMatrix<f64> {
    if tables == 0 {
        return DMatrix::zeros(CONTROL_POINTS, 0);
    }
    let svd = spline_basis(tables).svd(true, true);
    // Only fails for a negative tolerance; relative 1e-12 drops exactly the
    // null directions of an underdetermined (tables < 4) basis.
    let eps = 1e-12 * svd.singular_values.max();
    svd.pseudo_inverse(eps)
        .unwrap_or_else(|_| DMatrix::zeros(CONTROL_POINTS, tables))
}

/// `sum_i coeff_i * arrays[i]`, accumulated in f64.
fn project<'a, T, D>(arrays: &[Array<T, D>], coeffs: impl Iterator<Item = &'a f64>) -> Array<f64, D>
where
    T: Copy + Into<f64>,
    D: Dimension,
{
    let dim = arrays.first().map(|a| a.raw_dim()).unwrap_or_default();
    let mut acc = Array::<f64, D>::zeros(dim);
    for (a, &c) in arrays.iter().zip(coeffs) {
        Zip::from(&mut acc)
            .and(a)
            .for_each(|o, &x| *o += c * x.into());
    }
    acc
}

/// (max abs error, sum of squared errors, sum of squared table values) of
/// the spline through `cps` evaluated at every table position.
fn residual_sums<T, D>(
    tables: &[Array<T, D>],
    cps: &[Array<f64, D>; 4],
    basis: &DMatrix<f64>,
) -> (f64, f64, f64)
where
    T: Copy + Into<f64>,
    D: Dimension,
{
    let (mut max_abs, mut err_sq, mut ref_sq) = (0.0f64, 0.0, 0.0);
    for (i, table) in tables.iter().enumerate() {
        let g = [basis[(i, 0)], basis[(i, 1)], basis[(i, 2)], basis[(i, 3)]];
        Zip::from(table)
            .and(&cps[0])
            .and(&cps[1])
            .and(&cps[2])
            .and(&cps[3])
            .for_each(|&t, &a0, &a1, &a2, &a3| {
                let t: f64 = t.into();
                let e = g[0] * a0 + g[1] * a1 + g[2] * a2 + g[3] * a3 - t;
                max_abs = max_abs.max(e.abs());
                err_sq += e * e;
                ref_sq += t * t;
            });
    }
    (max_abs, err_sq, ref_sq)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pfnn_dir::{fixtures::real_pfnn_dir, load_pfnn_dir};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_points(
        rng: &mut ChaCha8Rng,
        rows: usize,
        cols: usize,
    ) -> ([Array2<f64>; 4], [Array1<f64>; 4]) {
        let w = std::array::from_fn(|_| {
            Array2::from_shape_fn((rows, cols), |_| rng.gen_range(-1.0..1.0))
        });
        let b = std::array::from_fn(|_| Array1::from_shape_fn(rows, |_| rng.gen_range(-1.0..1.0)));
        (w, b)
    }

    /// Samples the spline through known points at the table positions.
    fn tables_from(
        w: &[Array2<f64>; 4],
        b: &[Array1<f64>; 4],
        tables: usize,
    ) -> (Vec<Array2<f64>>, Vec<Array1<f64>>) {
        let cp = ControlPoints {
            w: w.clone(),
            b: b.clone(),
            residual: Residual::from_sums(0.0, 0.0, 0.0),
        };
        (0..tables)
            .map(|i| cp.evaluate(table_position(i, tables)))
            .unzip()
    }

    fn max_diff<D: Dimension>(a: &Array<f64, D>, b: &Array<f64, D>) -> f64 {
        Zip::from(a)
            .and(b)
            .fold(0.0f64, |m, x, y| m.max((x - y).abs()))
    }

    #[test]
    fn weights_sum_to_one_and_interpolate() {
        for i in 0..400 {
            let s = -8.0 + i as f64 * 0.0437;
            let total: f64 = catmull_rom_weights(s).iter().map(|p| p.1).sum();
            assert!((total - 1.0).abs() < 1e-14, "s={s}");
        }
        for k in 0..4 {
            let w = catmull_rom_weights(k as f64);
            assert_eq!(w[1], (k, 1.0));
            assert!(w.iter().filter(|p| p.0 != k).all(|p| p.1 == 0.0));
        }
    }

    #[test]
    fn weights_match_the_published_formula() {
        // W = a1 + mu (a2 - a0)/2 + mu^2 (a0 - 5/2 a1 + 2 a2 - 1/2 a3)
        //     + mu^3 (3/2 a1 - 3/2 a2 + 1/2 a3 - 1/2 a0), k1 = floor(s).
        let a = [0.3, -1.7, 2.9, 0.55];
        for &s in &[0.1, 1.25, 2.5, 3.99, 5.7, -0.3] {
            let ss: f64 = f64::rem_euclid(s, 4.0);
            let k1 = ss.floor() as usize;
            let mu = ss - ss.floor();
            let (a0, a1, a2, a3) = (a[(k1 + 3) % 4], a[k1], a[(k1 + 1) % 4], a[(k1 + 2) % 4]);
            let expect = a1
                + mu * (a2 - a0) / 2.0
                + mu * mu * (a0 - 2.5 * a1 + 2.0 * a2 - 0.5 * a3)
                + mu.powi(3) * (1.5 * a1 - 1.5 * a2 + 0.5 * a3 - 0.5 * a0);
            let got: f64 = catmull_rom_weights(s).iter().map(|&(k, g)| g * a[k]).sum();
            assert!((got - expect).abs() < 1e-14, "s={s}");
        }
    }

    #[test]
    fn tiny_negative_position_wraps_to_zero() {
        let w = catmull_rom_weights(-1e-18);
        let total: f64 = w.iter().map(|p| p.1).sum();
        assert!((total - 1.0).abs() < 1e-15);
        assert!(w.iter().all(|&(k, _)| k < 4));
    }

    #[test]
    fn condition_number_of_the_50_table_basis() {
        let c = basis_condition_number(50);
        assert!((c - 1.43).abs() < 0.01, "cond = {c}");
        assert_eq!(basis_condition_number(3), f64::INFINITY);
    }

    #[test]
    fn recovers_known_points_to_f64_precision() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (w, b) = random_points(&mut rng, 7, 5);
        let (tw, tb) = tables_from(&w, &b, 50);
        let cp = recover_control_points_from(&tw, &tb);
        for k in 0..4 {
            assert!(max_diff(&cp.w[k], &w[k]) < 1e-12);
            assert!(max_diff(&cp.b[k], &b[k]) < 1e-12);
        }
        assert!(cp.residual.max_abs < 1e-12, "{:?}", cp.residual);
        assert!(cp.residual.rel_frobenius < 1e-13, "{:?}", cp.residual);
    }

    #[test]
    fn works_for_other_table_counts() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (w, b) = random_points(&mut rng, 3, 2);
        for tables in [4, 8, 13, 64] {
            let (tw, tb) = tables_from(&w, &b, tables);
            let cp = recover_control_points_from(&tw, &tb);
            assert!(max_diff(&cp.w[2], &w[2]) < 1e-12, "tables={tables}");
        }
    }

    #[test]
    fn float32_tables_leave_a_float32_sized_residual() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (w, b) = random_points(&mut rng, 6, 4);
        let (tw, tb) = tables_from(&w, &b, 50);
        let layer = LayerTables {
            w: tw.iter().map(|a| a.mapv(|x| x as f32)).collect(),
            b: tb.iter().map(|a| a.mapv(|x| x as f32)).collect(),
        };
        let cp = recover_control_points(&layer);
        let r = cp.residual;
        assert!(r.rel_frobenius > 1e-9 && r.rel_frobenius < 1e-7, "{r:?}");
        assert!(max_diff(&cp.w[0], &w[0]) < 1e-7);
    }

    #[test]
    fn noisy_tables_show_up_in_the_residual() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (w, b) = random_points(&mut rng, 4, 4);
        let (mut tw, tb) = tables_from(&w, &b, 50);
        tw[17][[1, 2]] += 0.5;
        let cp = recover_control_points_from(&tw, &tb);
        assert!(cp.residual.max_abs > 0.3, "{:?}", cp.residual);
        assert!(cp.residual.rel_frobenius > 1e-3);
    }

    #[test]
    fn residuals_combine_like_one_big_tensor() {
        let a = Residual::from_sums(0.1, 9.0, 100.0);
        let b = Residual::from_sums(0.3, 16.0, 300.0);
        let c = a.combine(b);
        assert_eq!(c.max_abs, 0.3);
        assert!((c.rel_frobenius - 0.25).abs() < 1e-15);
    }

    #[test]
    fn no_tables_gives_zero_points_without_panicking() {
        let cp = recover_control_points_from::<f32>(&[], &[]);
        assert_eq!(cp.w[0].dim(), (0, 0));
        assert_eq!(cp.residual.max_abs, 0.0);
    }

    #[test]
    fn real_pfnn_tables_are_an_exact_spline() {
        let Some(dir) = real_pfnn_dir() else { return };
        let t = load_pfnn_dir(&dir).expect("real PFNN should load");
        let mut total: Option<Residual> = None;
        for (l, layer) in t.layers.iter().enumerate() {
            let r = recover_control_points(layer).residual;
            println!(
                "layer {l}: max_abs {:.3e}, rel_frobenius {:.3e}",
                r.max_abs, r.rel_frobenius
            );
            assert!(r.rel_frobenius < 1e-6, "layer {l}: {r:?}");
            total = Some(total.map_or(r, |t| t.combine(r)));
        }
        println!("all layers: {total:?}");
    }
}
