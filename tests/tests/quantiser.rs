//! Quantiser regressions found by review, checked through the runtime.

use exporter::export::export;
use exporter::net::{ExpertLayer, GatingMode, Net, NetLayer};
use exporter::quantise::QuantOptions;
use ndarray::{Array1, Array2};
use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase, Runtime};

/// A hidden row whose calibrated range is tiny (|pre| < 0.33) wants a scale
/// finer than Q15; it must be capped at Q15, where ELU's -1 still fits,
/// or its negative values come out up to 25% wrong.
#[test]
fn tiny_hidden_rows_stay_in_q15() {
    let mut seed = 9u32;
    let mut rnd = move || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        f64::from((seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5)
    };
    let mut l0 = Array2::from_shape_fn((4, 4), |_| rnd());
    for j in 0..4 {
        l0[(0, j)] = 1e-4 * (j + 1) as f64;
    }
    let mut b0 = Array1::from_shape_fn(4, |_| rnd() * 0.1);
    b0[0] = -0.2;
    let mut l1 = Array2::from_shape_fn((4, 4), |_| rnd());
    for i in 0..4 {
        l1[(i, 0)] = 5.0;
    }
    let l2 = Array2::from_shape_fn((2, 4), |_| rnd());
    let experts = |w: &Array2<f64>, b: &Array1<f64>| ExpertLayer {
        w: vec![w.clone(); 4],
        b: vec![b.clone(); 4],
    };
    let net = Net {
        mode: GatingMode::Cubic,
        xmean: Array1::zeros(4),
        xstd: Array1::ones(4),
        ymean: Array1::zeros(2),
        ystd: Array1::ones(2),
        layers: [
            experts(&l0, &b0),
            experts(&l1, &Array1::zeros(4)),
            experts(&l2, &Array1::zeros(2)),
        ]
        .into_iter()
        .map(NetLayer::Dense)
        .collect(),
        wiring: exporter::net::Wiring::Chain,
    };
    for weights in [WeightFormat::I16, WeightFormat::I8] {
        let (blob, _) = export(
            &net,
            None,
            &QuantOptions {
                weights,
                ..QuantOptions::default()
            },
        )
        .unwrap();
        let model = Model::from_bytes(&blob).unwrap();
        assert!(
            model
                .kernel(0)
                .unwrap()
                .requant()
                .chunks(8)
                .all(|r| r[6] <= 15),
            "{weights:?}: a hidden row finer than Q15"
        );
        let mut rt: Runtime<'_, 16> = Runtime::new(model).unwrap();
        let x = [0.3f32, -0.2, 0.1, 0.5];
        let mut y = [0.0f32; 2];
        rt.run(Phase::from_bits(0), &x, &mut y).unwrap();
        let want = net.forward(&x.map(f64::from), 0.0);
        let tol = if weights == WeightFormat::I16 {
            2e-4
        } else {
            2e-2
        };
        for (a, b) in y.iter().zip(&want) {
            assert!((f64::from(*a) - b).abs() < tol, "{weights:?}: {a} vs {b}");
        }
    }
}
