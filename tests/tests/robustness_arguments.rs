//! Bad arguments to the runtime, and extreme but valid inputs and phases on
//! real blobs (dense, CP, styles): errors, never panics, pinned outputs.

mod hostile;

use hostile::*;

#[test]
fn runtime_capacity_is_checked_when_it_is_made() {
    // 6 -> 8 -> 7 -> 5: the arena plan's largest step is layer 1's input
    // and output, 8 + 7.
    let blob = hand_blob();
    let model = Model::from_bytes(&blob).unwrap();
    assert_eq!(model.arena_elements(), 15);
    assert_eq!(
        Runtime::<14>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 15,
            capacity: 14
        })
    );
    assert_eq!(
        Runtime::<0>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 15,
            capacity: 0
        })
    );
    assert!(Runtime::<15>::new(model.clone()).is_ok());
    assert_eq!(Runtime::<15>::CAPACITY_BYTES, 30);
    assert_eq!(model.ram_bytes(), Runtime::<15>::CAPACITY_BYTES);
    let q = quantised(WeightFormat::I8);
    let model = Model::from_bytes(&q).unwrap();
    assert_eq!(
        Runtime::<47>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 48,
            capacity: 47
        })
    );
    assert!(Runtime::<48>::new(model).is_ok());
}

#[test]
fn run_refuses_bad_slices_and_non_finite_values() {
    let blob = hand_blob();
    let mut rt: Runtime<'_, 15> = Runtime::new(Model::from_bytes(&blob).unwrap()).unwrap();
    let x = [0.5f32, -1.0, 2.0, 0.0, 0.25, -0.75];
    let p = Phase::from_bits(0x1234_5678);
    let mut y = [0f32; 5];
    rt.run(p, &x, &mut y).unwrap();
    let good = y;

    let mut short = [0f32; 4];
    assert_eq!(
        rt.run(p, &x, &mut short),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 4
        })
    );
    let mut long = [0f32; 6];
    assert_eq!(
        rt.run(p, &x, &mut long),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 6
        })
    );
    assert_eq!(
        rt.run(p, &x[..5], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.run(p, &[0.0; 7], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 7
        })
    );
    assert_eq!(
        rt.run(p, &[], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 0
        })
    );
    assert_eq!(
        rt.run_quantised(p, &[0; 5]).err(),
        Some(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.run_quantised(p, &[0; 9]).err(),
        Some(Error::LengthMismatch {
            expected: 6,
            found: 9
        })
    );
    for (i, bad) in [
        (0, f32::NAN),
        (3, f32::INFINITY),
        (5, f32::NEG_INFINITY),
        (2, -f32::NAN),
    ] {
        let mut xi = x;
        xi[i] = bad;
        assert_eq!(
            rt.run(p, &xi, &mut y),
            Err(Error::NonFinite { index: i as u32 }),
            "{bad} at {i}"
        );
        let mut q = [0i16; 6];
        assert_eq!(
            rt.quantise_input(&xi, &mut q),
            Err(Error::NonFinite { index: i as u32 })
        );
    }
    let mut xi = x;
    (xi[1], xi[4]) = (f32::NAN, f32::NAN);
    assert_eq!(rt.run(p, &xi, &mut y), Err(Error::NonFinite { index: 1 }));
    for r in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        assert_eq!(Phase::from_radians(r), Err(Error::NonFinite { index: 0 }));
    }
    let mut q = [0i16; 5];
    assert_eq!(
        rt.quantise_input(&x, &mut q),
        Err(Error::BufferTooSmall {
            needed: 6,
            capacity: 5
        })
    );
    assert_eq!(
        rt.quantise_input(&x[..5], &mut [0i16; 6]),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.dequantise_output(&[0; 4], &mut [0.0; 5]),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 4
        })
    );
    assert_eq!(
        rt.dequantise_output(&[0; 5], &mut [0.0; 6]),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 6
        })
    );

    // None of that disturbed the runtime.
    rt.run(p, &x, &mut y).unwrap();
    assert_eq!(y, good);
}

#[test]
fn extreme_inputs_and_any_phase_on_real_blobs() {
    for blob in [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ] {
        let model = Model::from_bytes(&blob).unwrap();
        let rt: Runtime<'_, 48> = Runtime::new(model.clone()).unwrap();
        let n = model.input_dim();
        // The input stage saturates: every scale is positive.
        let mut q = vec![0i16; n];
        rt.quantise_input(&vec![f32::MAX; n], &mut q).unwrap();
        assert!(q.iter().all(|&v| v == i16::MAX));
        rt.quantise_input(&vec![-f32::MAX; n], &mut q).unwrap();
        assert!(q.iter().all(|&v| v == i16::MIN));
        let outs = hammer::<48>(model, &phases());
        assert_eq!(outs.len(), 7 * phases().len());
    }
}

/// A valid blob built to saturate: all-positive weights at full scale,
/// 64-bit accumulators and biases at the extremes, the largest multiplier
/// and no shift. Every output row must come out pinned at the i16 rail
/// that the sign of its inputs selects, whatever the phase.
#[test]
fn saturating_blob_pins_its_outputs() {
    let experts = 5u16;
    let mut layers = Vec::new();
    for (i, (inp, out)) in [(6u16, 8u16), (8, 4)].into_iter().enumerate() {
        let rows = usize::from(experts) * usize::from(out);
        layers.push(QLayer {
            desc: desc(
                inp,
                out,
                experts,
                if i == 0 {
                    WeightFormat::I16
                } else {
                    WeightFormat::I8
                },
                AccWidth::I64,
                Activation::Identity,
            ),
            weights: vec![if i == 0 { 32767 } else { 127 }; rows * usize::from(inp)],
            bias: vec![0; rows],
            requant: vec![
                Requant {
                    multiplier: i32::MAX,
                    pre_shift: 0,
                    post_shift: 0,
                    frac: 0
                };
                usize::from(out)
            ],
            cp: None,
            rbf: None,
            gated: true,
        });
    }
    let m = QModel {
        kind: QKind::Model(ModelKind::Pfnn),
        gating: Gating::CatmullRom { points: experts },
        input_stage: vec![(0.0, 1.0); 6],
        output_stage: vec![(1.0, 0.0); 4],
        layers,
        wiring: Wiring::Chain,
    };
    let blob = encode(&m).unwrap();
    let outs = hammer::<16>(Model::from_bytes(&blob).unwrap(), &phases());
    let per = phases().len();
    // The five experts are equal and the gate sums to exactly 1.0 at every
    // phase, so each output is the sign of sum(x) pinned to a rail.
    // Inputs: +MAX, -MAX, alternating (+32767 -32768 ...: negative), the
    // other alternation (also negative), 0, 1e30, a subnormal (rounds to 0).
    let expect = [i16::MAX, i16::MIN, i16::MIN, i16::MIN, 0, i16::MAX, 0];
    for (k, &e) in expect.iter().enumerate() {
        for o in &outs[k * per..(k + 1) * per] {
            assert_eq!(o, &[e; 4], "input pattern {k}");
        }
    }

    // The same with biases at the i64 extremes: the blend saturates in i64
    // instead of wrapping, then the requantisation saturates.
    let mut m2 = m.clone();
    for l in &mut m2.layers {
        for (j, b) in l.bias.iter_mut().enumerate() {
            *b = if j % 2 == 0 { i64::MAX } else { i64::MIN };
        }
    }
    let blob2 = encode(&m2).unwrap();
    let outs2 = hammer::<16>(Model::from_bytes(&blob2).unwrap(), &phases());
    assert_eq!(outs2.len(), 7 * per);
    assert!(outs2
        .iter()
        .flatten()
        .all(|&v| v == i16::MAX || v == i16::MIN || v == 0));
}

/// An i32 layer at the exact accumulator bound, fed the worst input.
#[test]
fn i32_row_at_the_bound_does_not_wrap() {
    let d = desc(
        2,
        2,
        1,
        WeightFormat::I16,
        AccWidth::I32,
        Activation::Identity,
    );
    let m = QModel {
        kind: QKind::Model(ModelKind::Mlp),
        gating: Gating::Single,
        input_stage: vec![(0.0, 1.0); 2],
        output_stage: vec![(1.0, 0.0); 2],
        layers: vec![QLayer {
            desc: d,
            // Row 0: sum |w| = 65535, the largest that loads.
            weights: vec![-32768, -32767, 32767, 32767],
            bias: vec![i32::MIN as i64, i32::MAX as i64],
            // Identity requantisation of the blended sum (Q16 gate): >> 16, then * 1.
            requant: vec![
                Requant {
                    multiplier: 1,
                    pre_shift: 16,
                    post_shift: 16,
                    frac: 0
                };
                2
            ],
            cp: None,
            rbf: None,
            gated: false,
        }],
        wiring: Wiring::Chain,
    };
    let blob = encode(&m).unwrap();
    let mut rt: Runtime<'_, 4> = Runtime::new(Model::from_bytes(&blob).unwrap()).unwrap();
    // acc0 = 65535 * 32768 = 2147450880 = i32::MAX - 32767; + bias i32::MIN = -32768.
    let y = rt
        .run_quantised(Phase::from_bits(0), &[-32768, -32768])
        .unwrap()
        .to_vec();
    // Row 0: (2147450880 - 2147483648) = -32768 -> >>16 -> -0.5 -> rounds up to 0.
    // Row 1: -65534*32768 + i32::MAX = -2147418112 + 2147483647 = 65535 -> 1.
    assert_eq!(y, [0, 1]);
}

#[test]
fn cp_models_and_styles_take_extreme_inputs_at_any_phase() {
    let b = cp_and_styles();
    let outs = hammer::<64>(Model::from_bytes(&b.cp).unwrap(), &phases());
    assert_eq!(outs.len(), 7 * phases().len());
    let styles: Vec<Style<'_>> = b
        .styles
        .iter()
        .map(|s| Style::from_bytes(s).unwrap())
        .collect();
    let some_phases: Vec<u32> = phases().into_iter().step_by(16).collect();
    let runs = hammer_styled(Model::from_bytes(&b.base).unwrap(), &styles, &some_phases);
    assert_eq!(runs, mixes(3).len() * 7 * some_phases.len());
}
