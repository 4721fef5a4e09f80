//! The PFNN importer: the demo's phase tables (a weight directory or a
//! PFNN-shaped `.npz`) as a [`Net`] of three dense gated layers, ELU after
//! the first two, read by the phase in one of three [`GatingMode`]s so that
//! every fixed-point configuration has a float twin with the same phase
//! behaviour:
//!
//! * constant: all tables are experts;
//! * linear: every `T/10`-th table (the demo's 10 keyframes when `T = 50`);
//! * cubic: the 4 Catmull-Rom control points recovered from the tables by
//!   least squares ([`recover_control_points`]).

use ndarray::Array1;

use crate::control_points::{recover_control_points, Residual};
use crate::net::{ExpertLayer, GatingMode, Net, NetLayer};
use crate::pfnn_dir::{LayerTables, PfnnTables};

/// Keyframes of the demo's linear mode (table `5 i` of 50 for `i < 10`).
pub const LINEAR_KEYFRAMES: usize = 10;

impl Net {
    /// The float PFNN of the phase tables `t`, read in `mode`.
    ///
    /// * linear: if `T` is not a multiple of 10 there is no keyframe choice
    ///   and all `T` tables are blended linearly instead;
    /// * cubic: the spline-vs-tables residual over all layers is returned
    ///   alongside, since a large one means the tables were not made by a
    ///   4-point spline and cubic mode is wrong for this model.
    pub fn from_pfnn_tables(t: &PfnnTables, mode: GatingMode) -> (Net, Option<Residual>) {
        let stats = |a: &Array1<f32>| a.mapv(f64::from);
        let (layers, residual): (Vec<ExpertLayer>, _) = match mode {
            GatingMode::Constant => (table_experts(t, &all_tables(t)), None),
            GatingMode::Linear => (table_experts(t, &linear_keyframes(t)), None),
            GatingMode::Cubic => {
                let cps = t.layers.each_ref().map(recover_control_points);
                let residual = cps.iter().map(|c| c.residual).reduce(Residual::combine);
                let layers = cps
                    .into_iter()
                    .map(|c| ExpertLayer {
                        w: c.w.into(),
                        b: c.b.into(),
                    })
                    .collect();
                (layers, residual)
            }
        };
        let net = Net {
            mode,
            xmean: stats(&t.xmean),
            xstd: stats(&t.xstd),
            ymean: stats(&t.ymean),
            ystd: stats(&t.ystd),
            layers: layers.into_iter().map(NetLayer::Dense).collect(),
            wiring: crate::net::Wiring::Chain,
        };
        (net, residual)
    }
}

fn table_experts(t: &PfnnTables, pick: &[usize]) -> Vec<ExpertLayer> {
    t.layers.iter().map(|l| from_tables(l, pick)).collect()
}

fn from_tables(t: &LayerTables, pick: &[usize]) -> ExpertLayer {
    ExpertLayer {
        w: pick.iter().map(|&i| t.w[i].mapv(f64::from)).collect(),
        b: pick.iter().map(|&i| t.b[i].mapv(f64::from)).collect(),
    }
}

fn all_tables(t: &PfnnTables) -> Vec<usize> {
    (0..t.layers[0].tables()).collect()
}

fn linear_keyframes(t: &PfnnTables) -> Vec<usize> {
    let tables = t.layers[0].tables();
    if tables.is_multiple_of(LINEAR_KEYFRAMES) {
        let step = tables / LINEAR_KEYFRAMES;
        (0..LINEAR_KEYFRAMES).map(|i| i * step).collect()
    } else {
        all_tables(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control_points::table_position;
    use crate::net::{elu, wrap_phase};
    use crate::pfnn_dir::fixtures::{random_tables, real_pfnn_dir};
    use crate::pfnn_dir::{load_pfnn_dir, PfnnDims};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;
    use std::f64::consts::TAU;

    const SMALL: PfnnDims = PfnnDims {
        input: 6,
        hidden: 8,
        output: 5,
        tables: 50,
    };

    /// Tables that are float32 samples of an exact 4-point spline, like the
    /// real model's.
    fn spline_tables(dims: PfnnDims, seed: u64) -> PfnnTables {
        let mut t = random_tables(PfnnDims { tables: 4, ..dims }, seed);
        for layer in &mut t.layers {
            let cp = crate::control_points::ControlPoints {
                w: std::array::from_fn(|k| layer.w[k].mapv(f64::from)),
                b: std::array::from_fn(|k| layer.b[k].mapv(f64::from)),
                residual: recover_control_points(layer).residual,
            };
            let (w, b): (Vec<_>, Vec<_>) = (0..dims.tables)
                .map(|i| {
                    let (w, b) = cp.evaluate(table_position(i, dims.tables));
                    (w.mapv(|x| x as f32), b.mapv(|x| x as f32))
                })
                .unzip();
            *layer = LayerTables { w, b };
        }
        t
    }

    fn random_input(net: &Net, rng: &mut ChaCha8Rng) -> Vec<f64> {
        (0..net.input_dim())
            .map(|i| {
                let z: f64 = rng.sample(StandardNormal);
                net.xmean[i] + net.xstd[i] * z
            })
            .collect()
    }

    /// max |a - b| / max(|b|, 1), the error measure of reference_check.py.
    fn rel_err(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / y.abs().max(1.0))
            .fold(0.0, f64::max)
    }

    /// The phase of table `i`, nudged up by 1e-9 of a table: exactly at
    /// `2pi i / T` the float product `p / 2pi * T` may round to just below
    /// `i`, and constant mode (like the demo) then picks table `i - 1`.
    fn table_phase(i: usize, tables: usize) -> f64 {
        TAU * (i as f64 + 1e-9) / tables as f64
    }

    #[test]
    fn mode_names_round_trip() {
        for m in GatingMode::ALL {
            assert_eq!(m.to_string().parse::<GatingMode>(), Ok(m));
        }
        assert_eq!("Cubic".parse::<GatingMode>(), Ok(GatingMode::Cubic));
        let e = "spline".parse::<GatingMode>().unwrap_err();
        assert!(e.to_string().contains("\"spline\""), "{e}");
    }

    #[test]
    fn elu_matches_definition() {
        assert_eq!(elu(2.5), 2.5);
        assert_eq!(elu(0.0), 0.0);
        assert!((elu(-1.0) - (-1.0f64).exp() + 1.0).abs() < 1e-16);
        assert_eq!(elu(-1e3), -1.0);
    }

    #[test]
    fn phase_wraps_into_one_cycle() {
        assert_eq!(wrap_phase(-1e-20), 0.0);
        assert!((wrap_phase(-0.5) - (TAU - 0.5)).abs() < 1e-15);
        assert!((wrap_phase(3.0 * TAU + 1.0) - 1.0).abs() < 1e-12);
        for p in [-1e-20, -7.0, 0.0, 1.0, TAU, 100.0] {
            let w = wrap_phase(p);
            assert!((0.0..TAU).contains(&w), "{p} -> {w}");
        }
    }

    #[test]
    fn gate_weights_sum_to_one_in_every_mode() {
        let t = random_tables(SMALL, 1);
        for mode in GatingMode::ALL {
            let (net, _) = Net::from_pfnn_tables(&t, mode);
            for i in -300..300 {
                let p = i as f64 * 0.0531;
                let g = net.gate(p);
                let sum: f64 = g.iter().map(|e| e.1).sum();
                assert!((sum - 1.0).abs() < 1e-14, "{mode} p={p}: {g:?}");
                assert!(g.iter().all(|&(k, _)| k < net.layers[0].experts()));
            }
        }
    }

    #[test]
    fn constant_gate_picks_the_table_at_or_below() {
        let (net, res) = Net::from_pfnn_tables(&random_tables(SMALL, 2), GatingMode::Constant);
        assert!(res.is_none());
        assert_eq!(net.layers[0].experts(), 50);
        for i in 0..50 {
            assert_eq!(net.gate(table_phase(i, 50)), vec![(i, 1.0)], "table {i}");
            let mid = table_phase(i, 50) + 0.5 * TAU / 50.0;
            assert_eq!(net.gate(mid), vec![(i, 1.0)]);
        }
        assert_eq!(net.gate(TAU - 1e-12), vec![(49, 1.0)]);
        assert_eq!(net.gate(-1e-9), vec![(49, 1.0)]);
        assert_eq!(net.gate(TAU), vec![(0, 1.0)]);
    }

    #[test]
    fn constant_floors_like_the_demo_even_just_below_a_table() {
        let (net, _) = Net::from_pfnn_tables(&random_tables(SMALL, 2), GatingMode::Constant);
        // (2pi * 19 / 50) / 2pi * 50 evaluates to 18.999999999999996 in f64;
        // the demo's `(int)((P / (2*M_PI)) * 50)` truncates it to 18 too.
        let p = TAU * 19.0 / 50.0;
        assert!(p / TAU * 50.0 < 19.0);
        assert_eq!(net.gate(p), vec![(18, 1.0)]);
    }

    #[test]
    fn linear_uses_every_fifth_table_like_the_demo() {
        let t = random_tables(SMALL, 3);
        let (net, _) = Net::from_pfnn_tables(&t, GatingMode::Linear);
        assert_eq!(net.layers[1].experts(), LINEAR_KEYFRAMES);
        for k in 0..LINEAR_KEYFRAMES {
            assert_eq!(
                net.layers[1].as_dense().unwrap().w[k],
                t.layers[1].w[5 * k].mapv(f64::from)
            );
        }
        let g = net.gate(TAU * 3.25 / 10.0);
        assert_eq!(g[0].0, 3);
        assert_eq!(g[1].0, 4);
        assert!((g[1].1 - 0.25).abs() < 1e-12);
        // Between the last keyframe (table 45) and the first.
        let g = net.gate(TAU * 9.5 / 10.0);
        assert_eq!((g[0].0, g[1].0), (9, 0));
    }

    #[test]
    fn linear_on_a_keyframe_equals_that_table() {
        let t = random_tables(SMALL, 4);
        let (lin, _) = Net::from_pfnn_tables(&t, GatingMode::Linear);
        let (con, _) = Net::from_pfnn_tables(&t, GatingMode::Constant);
        let mut rng = ChaCha8Rng::seed_from_u64(40);
        for k in 0..LINEAR_KEYFRAMES {
            // Exactly on the keyframe for linear; linear is continuous, so
            // the rounding that may land just below it does not matter.
            let p = TAU * k as f64 / LINEAR_KEYFRAMES as f64;
            let on_table = table_phase(5 * k, 50);
            assert_eq!(con.gate(on_table), vec![(5 * k, 1.0)]);
            let x = random_input(&con, &mut rng);
            let err = rel_err(&lin.forward(&x, p), &con.forward(&x, on_table));
            assert!(err < 1e-13, "keyframe {k}: {err}");
        }
    }

    #[test]
    fn linear_falls_back_to_all_tables_when_not_a_multiple_of_ten() {
        let t = random_tables(PfnnDims { tables: 7, ..SMALL }, 5);
        let (net, _) = Net::from_pfnn_tables(&t, GatingMode::Linear);
        assert_eq!(net.layers[2].experts(), 7);
    }

    #[test]
    fn cubic_at_table_phases_reproduces_the_tables() {
        let t = spline_tables(SMALL, 6);
        let (cubic, res) = Net::from_pfnn_tables(&t, GatingMode::Cubic);
        let res = res.expect("cubic reports a residual");
        assert!(res.rel_frobenius < 1e-7, "{res:?}");
        let (con, _) = Net::from_pfnn_tables(&t, GatingMode::Constant);
        let mut rng = ChaCha8Rng::seed_from_u64(60);
        for i in 0..50 {
            let p = table_phase(i, 50);
            assert_eq!(con.gate(p)[0].0, i);
            let x = random_input(&con, &mut rng);
            let err = rel_err(&cubic.forward(&x, p), &con.forward(&x, p));
            assert!(err < 1e-6, "table {i}: {err}");
        }
    }

    #[test]
    fn trace_is_consistent_with_forward() {
        let t = random_tables(SMALL, 8);
        let (net, _) = Net::from_pfnn_tables(&t, GatingMode::Cubic);
        let x = random_input(&net, &mut ChaCha8Rng::seed_from_u64(80));
        let tr = net.forward_trace(&x, 1.234);
        assert_eq!(tr.y, net.forward(&x, 1.234));
        assert_eq!(tr.gate, net.gate(1.234));
        assert_eq!(tr.pre[0].len(), SMALL.hidden);
        for (i, (&xi, xn)) in x.iter().zip(&tr.inputs[0]).enumerate() {
            let expect = (xi - net.xmean[i]) / net.xstd[i];
            assert!((xn - expect).abs() < 1e-15);
        }
        for (j, y) in tr.y.iter().enumerate() {
            let expect = tr.pre[2][j] * net.ystd[j] + net.ymean[j];
            assert!((y - expect).abs() < 1e-12);
        }
    }

    #[test]
    fn forward_matches_a_hand_computed_single_table() {
        let t = random_tables(PfnnDims { tables: 1, ..SMALL }, 9);
        let (net, _) = Net::from_pfnn_tables(&t, GatingMode::Constant);
        let x = random_input(&net, &mut ChaCha8Rng::seed_from_u64(90));
        let f = |l: usize| {
            (
                t.layers[l].w[0].mapv(f64::from),
                t.layers[l].b[0].mapv(f64::from),
            )
        };
        let xn = (&Array1::from(x.clone()) - &t.xmean.mapv(f64::from)) / &t.xstd.mapv(f64::from);
        let (w0, b0) = f(0);
        let (w1, b1) = f(1);
        let (w2, b2) = f(2);
        let h0 = (w0.dot(&xn) + b0).mapv(elu);
        let h1 = (w1.dot(&h0) + b1).mapv(elu);
        let y = (w2.dot(&h1) + b2) * &t.ystd.mapv(f64::from) + &t.ymean.mapv(f64::from);
        assert!(rel_err(&net.forward(&x, 5.0), &y.to_vec()) < 1e-14);
    }

    #[test]
    #[should_panic(expected = "Net input has 3 values, the model expects 6")]
    fn wrong_input_length_panics_with_a_clear_message() {
        let (net, _) = Net::from_pfnn_tables(&random_tables(SMALL, 10), GatingMode::Linear);
        net.forward(&[0.0; 3], 0.0);
    }

    #[test]
    fn real_pfnn_cubic_matches_the_tables_and_the_demo_modes() {
        let Some(dir) = real_pfnn_dir() else { return };
        let t = load_pfnn_dir(&dir).expect("real PFNN should load");
        let (cubic, res) = Net::from_pfnn_tables(&t, GatingMode::Cubic);
        let res = res.expect("cubic reports a residual");
        println!("real PFNN control-point residual: {res:?}");
        assert!(res.rel_frobenius < 1e-6);
        let (con, _) = Net::from_pfnn_tables(&t, GatingMode::Constant);
        let (lin, _) = Net::from_pfnn_tables(&t, GatingMode::Linear);
        let mut rng = ChaCha8Rng::seed_from_u64(123);
        let (mut at_tables, mut const_vs_cubic, mut lin_vs_cubic) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..50 {
            let x = random_input(&con, &mut rng);
            let p = table_phase(i, 50);
            at_tables = at_tables.max(rel_err(&cubic.forward(&x, p), &con.forward(&x, p)));
            let p = rng.gen_range(0.0..TAU);
            let yc = cubic.forward(&x, p);
            let abs = |a: &[f64], b: &[f64]| {
                a.iter()
                    .zip(b)
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0, f64::max)
            };
            const_vs_cubic = const_vs_cubic.max(abs(&con.forward(&x, p), &yc));
            lin_vs_cubic = lin_vs_cubic.max(abs(&lin.forward(&x, p), &yc));
        }
        println!(
            "cubic vs tables at table phases: {at_tables:.3e} (rel); \
             max |constant - cubic| {const_vs_cubic:.3}, max |linear - cubic| {lin_vs_cubic:.3} (model units)"
        );
        assert!(at_tables < 1e-4, "{at_tables}");
    }
}
