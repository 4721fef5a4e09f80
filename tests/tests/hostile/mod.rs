//! What the robustness tests share: the hostile and extreme blobs they
//! start from and the helpers that damage, reframe and run them. The tests
//! themselves are split by concern into `robustness_*.rs`; every one checks
//! that the runtime answers with an error (the right one where it can be
//! named) and never panics.
//!
//! Blobs used:
//! * `quantised(..)`: a random, small PFNN-shaped float network (20 -> 24 ->
//!   24 -> 12, four Catmull-Rom control points) through the real quantiser
//!   and encoder (`exporter::export::export`), int8 and int16 weights;
//! * `hand_model()`: a hand-made three-layer model with a five-point
//!   Catmull-Rom gating, both weight formats and both accumulator widths,
//!   an ungated last layer;
//! * `cp_and_styles()`: a whole-network CP model (CP, diagonal, CP layers)
//!   and style blobs (CP, diagonal and full adapters) for a small dense
//!   base, all through the real exporter.

#![allow(dead_code, unused_imports)]

pub use exporter::encode::{encode, frame, QKind, QLayer, QModel, Wiring};
pub use exporter::export::export;
pub use exporter::net::{ExpertLayer, GatingMode, Net, NetLayer};
pub use exporter::quantise::QuantOptions;
pub use ndarray::{Array1, Array2};
pub use phasegate::blob::{
    crc32, AccWidth, Activation, GateSource, Gating, Header, LayerDesc, LayerOp, ModelKind, Node,
    NodeOp, Requant, Section, Slice, Source, Span, WeightFormat, REQUANT_RECORD_LEN,
};
pub use phasegate::style::BlendWeight;
pub use phasegate::{
    blob_len_from_prefix, Error, Mix, Model, Phase, Runtime, Style, StyleId, STAGE,
};
pub use proptest::prelude::*;
pub use rand::{Rng, SeedableRng};
pub use rand_chacha::ChaCha8Rng;

pub fn matrix(rng: &mut ChaCha8Rng, rows: usize, cols: usize, scale: f64) -> Array2<f64> {
    Array2::from_shape_fn((rows, cols), |_| rng.gen_range(-scale..scale))
}

pub fn vector(rng: &mut ChaCha8Rng, n: usize, lo: f64, hi: f64) -> Array1<f64> {
    Array1::from_shape_fn(n, |_| rng.gen_range(lo..hi))
}

pub fn expert_layer(rng: &mut ChaCha8Rng, inp: usize, out: usize) -> ExpertLayer {
    let s = 1.5 / (inp as f64).sqrt();
    ExpertLayer {
        w: (0..4).map(|_| matrix(rng, out, inp, s)).collect(),
        b: (0..4).map(|_| vector(rng, out, -0.2, 0.2)).collect(),
    }
}

/// A random PFNN-shaped float network: 20 inputs, two hidden layers of 24,
/// 12 outputs, 4 control points.
pub fn float_net(seed: u64) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (i, h, o) = (20, 24, 12);
    Net {
        mode: GatingMode::Cubic,
        xmean: vector(&mut rng, i, -3.0, 3.0),
        xstd: vector(&mut rng, i, 0.2, 4.0),
        ymean: vector(&mut rng, o, -1.0, 1.0),
        ystd: vector(&mut rng, o, 0.1, 2.0),
        layers: [
            expert_layer(&mut rng, i, h),
            expert_layer(&mut rng, h, h),
            expert_layer(&mut rng, h, o),
        ]
        .into_iter()
        .map(NetLayer::Dense)
        .collect(),
        wiring: exporter::net::Wiring::Chain,
    }
}

/// The float network through the real quantiser and encoder.
pub fn quantised(weights: WeightFormat) -> Vec<u8> {
    let opts = QuantOptions {
        weights,
        calibration_samples: 128,
        ..QuantOptions::default()
    };
    export(&float_net(7), None, &opts).unwrap().0
}

pub fn desc(
    in_dim: u16,
    out_dim: u16,
    experts: u16,
    w: WeightFormat,
    acc: AccWidth,
    act: Activation,
) -> LayerDesc {
    LayerDesc {
        op: LayerOp::Dense,
        in_dim,
        out_dim,
        experts,
        weights: w,
        acc,
        activation: act,
        weight_section: Section::default(),
        bias_section: Section::default(),
        requant_section: Section::default(),
    }
}

/// Catmull-Rom over 5 points; layer 0 int16/i32/ELU 6 -> 8, layer 1
/// int8/i64/ELU 8 -> 7, layer 2 ungated int8/i32/identity 7 -> 5.
pub fn hand_model() -> QModel {
    use AccWidth::*;
    use Activation::*;
    use WeightFormat::*;
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut layer = |d: LayerDesc, wmax: i32, bmax: i64, pre: u8, post: u8| {
        let rows = usize::from(d.experts) * usize::from(d.out_dim);
        QLayer {
            desc: d,
            weights: (0..rows * usize::from(d.in_dim))
                .map(|_| rng.gen_range(-wmax..=wmax))
                .collect(),
            bias: (0..rows).map(|_| rng.gen_range(-bmax..=bmax)).collect(),
            requant: (0..d.out_dim)
                .map(|i| Requant {
                    multiplier: rng.gen_range(1 << 30..i32::MAX),
                    pre_shift: pre,
                    post_shift: post,
                    frac: 8 + (i % 4) as u8,
                })
                .collect(),
            cp: None,
            rbf: None,
            gated: d.experts > 1,
        }
    };
    let layers = vec![
        layer(desc(6, 8, 5, I16, I32, Elu), 8000, 1 << 28, 16, 44),
        layer(desc(8, 7, 5, I8, I64, Elu), 127, 1 << 40, 20, 40),
        layer(desc(7, 5, 1, I8, I32, Identity), 127, 1 << 20, 4, 36),
    ];
    QModel {
        kind: QKind::Model(ModelKind::Pfnn),
        gating: Gating::CatmullRom { points: 5 },
        input_stage: (0..6)
            .map(|i| (i as f32 - 2.0, 100.0 * (i + 1) as f32))
            .collect(),
        output_stage: (0..5).map(|i| (0.01 * (i + 1) as f32, i as f32)).collect(),
        layers,
        wiring: Wiring::Chain,
    }
}

pub fn hand_blob() -> Vec<u8> {
    encode(&hand_model()).unwrap()
}

/// Header and payload of a valid blob, to be edited and re-framed with
/// valid CRCs.
#[derive(Clone)]
pub struct Parts {
    pub header: Header,
    pub payload: Vec<u8>,
}

impl Parts {
    pub fn of(blob: &[u8]) -> Parts {
        let header = Model::from_bytes(blob).unwrap().header().decoded();
        let payload = blob[blob.len() - header.payload_len as usize..].to_vec();
        Parts { header, payload }
    }

    /// Frames the header as it stands (its payload CRC and length unchanged).
    pub fn blob(&self) -> Vec<u8> {
        frame(&self.header, &self.payload)
    }

    /// Recomputes the payload CRC and length after an edit of the payload.
    pub fn reseal(&mut self) -> &mut Self {
        self.header.payload_crc = crc32(&self.payload);
        self.header.payload_len = self.payload.len() as u32;
        self
    }

    /// Layer node `i`'s descriptor.
    pub fn layer(&mut self, i: usize) -> &mut LayerDesc {
        layer_mut(&mut self.header, i).expect("a layer node")
    }

    /// Recomputes the arena plan (span lengths from the nodes' widths, then
    /// offsets, with the exporter's planner) and the RAM and MAC figures
    /// after an edit of the nodes; a graph that no longer chains keeps its
    /// old plan.
    pub fn refigure(&mut self) -> &mut Self {
        let h = &mut self.header;
        h.input.len = h.input_dim;
        for n in h.nodes.iter_mut() {
            n.input.len = n.in_dim();
            n.output.len = n.out_dim();
            n.scratch.len = n.layer().map_or(0, |d| {
                <phasegate::ops::Layer<'_> as phasegate::ops::GatedOp<'_>>::scratch(d) as u16
            });
            if let [one] = n.inputs.as_mut_slice() {
                one.len = n.input.len;
            }
        }
        h.output.len = h.output_dim;
        let _ = exporter::plan::plan_arena(h);
        h.macs_per_frame = phasegate::macs(h) as u32;
        self
    }

    pub fn requant_at(&mut self, layer: usize, row: usize) -> &mut [u8] {
        let s = self.layer(layer).requant_section.offset as usize + row * REQUANT_RECORD_LEN;
        &mut self.payload[s..s + REQUANT_RECORD_LEN]
    }

    pub fn load(&self) -> Result<(), Error> {
        Model::from_bytes(&self.blob()).map(|_| ())
    }
}

/// The descriptor of layer node `i` (panics on a softmax gate).
pub fn lay(h: &mut Header, i: usize) -> &mut LayerDesc {
    layer_mut(h, i).expect("a layer node")
}

/// A copy of the descriptor of layer node `i`.
pub fn layer_of(h: &Header, i: usize) -> LayerDesc {
    *h.nodes[i].layer().expect("a layer node")
}

/// The descriptor of node `i`, if it is a layer.
pub fn layer_mut(h: &mut Header, i: usize) -> Option<&mut LayerDesc> {
    match &mut h.nodes.get_mut(i)?.op {
        NodeOp::Layer(d) => Some(d),
        NodeOp::Softmax(_) => None,
    }
}

pub fn payload_start(blob: &[u8]) -> usize {
    (12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]))).next_multiple_of(16)
}

/// The one error a single flipped bit at `pos` must give.
pub fn single_flip_error(blob: &[u8], damaged: &[u8], pos: usize) -> Error {
    let header_end = 12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]));
    match pos {
        0..4 => Error::BadMagic,
        4..6 => Error::UnsupportedVersion {
            found: u16::from_le_bytes([damaged[4], damaged[5]]),
            supported: phasegate::blob::FORMAT_VERSION,
        },
        6..8 => {
            let h = 12 + usize::from(u16::from_le_bytes([damaged[6], damaged[7]]));
            if h > blob.len() {
                Error::Truncated {
                    needed: h as u32,
                    available: blob.len() as u32,
                }
            } else {
                Error::HeaderCorrupt
            }
        }
        p if p < header_end => Error::HeaderCorrupt,
        p if p < payload_start(blob) => Error::HeaderMalformed,
        _ => Error::PayloadCorrupt,
    }
}

pub fn is_header_class(e: &Error) -> bool {
    matches!(
        e,
        Error::BadMagic
            | Error::UnsupportedVersion { .. }
            | Error::HeaderCorrupt
            | Error::HeaderMalformed
            | Error::Truncated { .. }
            | Error::TrailingBytes { .. }
    )
}

/// Loads a model blob exactly (`true`) or from a region (`false`).
pub fn load_model(bytes: &[u8], exact: bool) -> Result<(), Error> {
    if exact {
        Model::from_bytes(bytes).map(|_| ())
    } else {
        Model::from_region(bytes).map(|_| ())
    }
}

/// Loads a style blob exactly (`true`) or from a region (`false`).
pub fn load_style(bytes: &[u8], exact: bool) -> Result<(), Error> {
    if exact {
        Style::from_bytes(bytes).map(|_| ())
    } else {
        Style::from_region(bytes).map(|_| ())
    }
}

pub fn flip_all(blob: &[u8], seed: u64, random_flips: usize) -> usize {
    flip_all_with(blob, seed, random_flips, load_model)
}

pub fn flip_all_with(
    blob: &[u8],
    seed: u64,
    random_flips: usize,
    load: fn(&[u8], bool) -> Result<(), Error>,
) -> usize {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let start = payload_start(blob);
    // Every bit of preamble, header and padding, then random bits, half of
    // them in the header region and half in the payload.
    let exhaustive = (0..start * 8).map(|b| (b / 8, b % 8));
    let random: Vec<(usize, usize)> = (0..random_flips)
        .map(|i| {
            let pos = if i % 2 == 0 {
                rng.gen_range(0..start)
            } else {
                rng.gen_range(start..blob.len())
            };
            (pos, rng.gen_range(0..8))
        })
        .collect();
    let mut count = 0;
    for (pos, bit) in exhaustive.chain(random) {
        let mut d = blob.to_vec();
        d[pos] ^= 1 << bit;
        let want = single_flip_error(blob, &d, pos);
        assert_eq!(load(&d, true).unwrap_err(), want, "bit {bit} of byte {pos}");
        assert_eq!(
            load(&d, false).unwrap_err(),
            want,
            "bit {bit} of byte {pos}"
        );
        count += 1;
    }
    count
}

/// A named edit of a header and the error it must give.
pub type Case = (&'static str, Box<dyn Fn(&mut Header)>, Error);

pub fn refused(p: &Parts) -> Error {
    let blob = p.blob();
    let e = Model::from_bytes(&blob).unwrap_err();
    assert_eq!(Model::from_region(&blob).unwrap_err(), e);
    e
}

/// Frames raw header bytes with a valid CRC, as the document says.
pub fn frame_raw(header: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut out = b"PGMB".to_vec();
    out.extend(phasegate::blob::FORMAT_VERSION.to_le_bytes());
    out.extend(u16::try_from(header.len()).unwrap().to_le_bytes());
    let crc = crc32(&out.iter().chain(header).copied().collect::<Vec<_>>());
    out.extend(crc.to_le_bytes());
    out.extend(header);
    out.resize(out.len().next_multiple_of(16), 0);
    out.extend(payload);
    out
}

/// Phases: the edges of the cycle and of every expert's segment, plus a
/// stride through all of u32.
pub fn phases() -> Vec<u32> {
    let mut v = vec![
        0,
        1,
        u32::MAX,
        u32::MAX - 1,
        1 << 31,
        (1 << 31) - 1,
        1 << 30,
        3 << 30,
    ];
    for n in [4u64, 5, 10, 50] {
        for k in 0..n {
            let edge = ((k << 32) / n) as u32;
            v.extend([edge, edge.wrapping_sub(1), edge.wrapping_add(1)]);
        }
    }
    v.extend((0..2048u32).map(|i| i.wrapping_mul(0x0020_0003) ^ (i << 7)));
    v
}

pub fn extreme_inputs(n: usize) -> Vec<Vec<f32>> {
    let alt = |a: f32, b: f32| (0..n).map(|i| if i % 2 == 0 { a } else { b }).collect();
    vec![
        vec![f32::MAX; n],
        vec![-f32::MAX; n],
        alt(f32::MAX, -f32::MAX),
        alt(-f32::MAX, f32::MAX),
        vec![0.0; n],
        vec![1e30; n],
        vec![f32::MIN_POSITIVE / 8.0; n],
    ]
}

/// Runs every extreme input at every phase; returns the quantised outputs.
pub fn hammer<const W: usize>(model: Model<'_>, phases: &[u32]) -> Vec<Vec<i16>> {
    let Ok(mut rt) = Runtime::<W>::new(model) else {
        return Vec::new();
    };
    run_extremes(&mut rt, phases)
}

/// Every extreme input at every phase through `rt`, by both paths (float
/// in and out, and quantised), which must agree to the bit; returns the
/// quantised outputs.
pub fn run_extremes<const W: usize, const S: usize, const N: usize>(
    rt: &mut Runtime<'_, W, S, N>,
    phases: &[u32],
) -> Vec<Vec<i16>> {
    let (n, m) = (rt.model().input_dim(), rt.model().output_dim());
    let mut outs = Vec::new();
    for x in extreme_inputs(n) {
        let mut q = vec![0i16; n];
        rt.quantise_input(&x, &mut q).unwrap();
        for &ph in phases {
            let mut y = vec![0f32; m];
            rt.run(Phase::from_bits(ph), &x, &mut y).unwrap();
            let yq = rt.run_quantised(Phase::from_bits(ph), &q).unwrap().to_vec();
            let mut back = vec![0f32; m];
            rt.dequantise_output(&yq, &mut back).unwrap();
            assert_eq!(
                back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                y.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            outs.push(yq);
        }
    }
    outs
}

pub fn loads_and_runs(bytes: &[u8]) {
    for m in [Model::from_bytes(bytes), Model::from_region(bytes)]
        .into_iter()
        .flatten()
    {
        hammer::<64>(m, &[0, 0x4000_0000, u32::MAX]);
    }
    let _ = blob_len_from_prefix(bytes);
}

/// One random edit of a header.
#[derive(Clone, Debug)]
pub enum Edit {
    Dim {
        layer: usize,
        which: u8,
        value: u16,
    },
    Experts {
        layer: usize,
        value: u16,
    },
    Gated {
        layer: usize,
    },
    Section {
        layer: usize,
        which: u8,
        offset: u32,
        len: u32,
    },
    Format {
        layer: usize,
        weights: bool,
        acc: bool,
        elu: bool,
    },
    Gating(Gating),
    Figures {
        ram: u32,
        macs: u32,
    },
    Model {
        input: u16,
        output: u16,
    },
    Payload {
        at: usize,
        byte: u8,
    },
    /// One of a node's spans (0 input, 1 scratch, 2 output) or, for
    /// node 255, the model's input span.
    Span {
        node: usize,
        which: u8,
        offset: u16,
        len: u16,
    },
    /// A node's first input slice, or the model's output (node 255).
    Slice {
        node: usize,
        source: Option<u8>,
        start: u16,
        len: u16,
    },
    /// A node's gate source.
    Gate {
        node: usize,
        source: Option<Option<u8>>,
    },
    /// A node turned into a softmax gate.
    Softmax {
        node: usize,
        experts: u16,
        frac: u8,
    },
}

pub fn arb_edit() -> impl Strategy<Value = Edit> {
    let small = prop_oneof![0u16..12, any::<u16>()];
    prop_oneof![
        (0usize..3, 0u8..2, small.clone()).prop_map(|(layer, which, value)| Edit::Dim {
            layer,
            which,
            value
        }),
        (0usize..3, small.clone()).prop_map(|(layer, value)| Edit::Experts { layer, value }),
        (0usize..3).prop_map(|layer| Edit::Gated { layer }),
        (
            0usize..3,
            0u8..3,
            prop_oneof![0u32..2048, any::<u32>()],
            prop_oneof![0u32..512, any::<u32>()]
        )
            .prop_map(|(layer, which, offset, len)| Edit::Section {
                layer,
                which,
                offset,
                len
            }),
        (0usize..3, any::<bool>(), any::<bool>(), any::<bool>()).prop_map(
            |(layer, weights, acc, elu)| Edit::Format {
                layer,
                weights,
                acc,
                elu
            }
        ),
        prop_oneof![
            Just(Gating::Single),
            small.clone().prop_map(|tables| Gating::Constant { tables }),
            small.clone().prop_map(|tables| Gating::Linear { tables }),
            small
                .clone()
                .prop_map(|points| Gating::CatmullRom { points }),
        ]
        .prop_map(Edit::Gating),
        (any::<u32>(), any::<u32>()).prop_map(|(ram, macs)| Edit::Figures { ram, macs }),
        (small.clone(), small).prop_map(|(input, output)| Edit::Model { input, output }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, byte)| Edit::Payload { at, byte }),
        (
            prop_oneof![0usize..3, Just(255)],
            0u8..3,
            prop_oneof![0u16..64, any::<u16>()],
            prop_oneof![0u16..32, any::<u16>()]
        )
            .prop_map(|(node, which, offset, len)| Edit::Span {
                node,
                which,
                offset,
                len
            }),
        (
            prop_oneof![0usize..3, Just(255)],
            proptest::option::of(0u8..4),
            0u16..12,
            prop_oneof![0u16..12, any::<u16>()]
        )
            .prop_map(|(node, source, start, len)| Edit::Slice {
                node,
                source,
                start,
                len
            }),
        (
            0usize..3,
            proptest::option::of(proptest::option::of(0u8..4))
        )
            .prop_map(|(node, source)| Edit::Gate { node, source }),
        (0usize..3, 0u16..10, 0u8..17).prop_map(|(node, experts, frac)| Edit::Softmax {
            node,
            experts,
            frac
        }),
    ]
}

pub fn apply(p: &mut Parts, e: &Edit) {
    let n = p.header.nodes.len().max(1);
    match *e {
        Edit::Dim {
            layer,
            which,
            value,
        } => {
            if let Some(l) = layer_mut(&mut p.header, layer % n) {
                if which == 0 {
                    l.in_dim = value;
                } else {
                    l.out_dim = value;
                }
            }
        }
        Edit::Experts { layer, value } => {
            if let Some(l) = layer_mut(&mut p.header, layer % n) {
                l.experts = value;
            }
        }
        Edit::Gated { layer } => {
            if let Some(node) = p.header.nodes.get_mut(layer % n) {
                node.gate = match node.gate {
                    GateSource::None => GateSource::Phase,
                    _ => GateSource::None,
                };
            }
        }
        Edit::Section {
            layer,
            which,
            offset,
            len,
        } => {
            if let Some(l) = layer_mut(&mut p.header, layer % n) {
                let s = match which {
                    0 => &mut l.weight_section,
                    1 => &mut l.bias_section,
                    _ => &mut l.requant_section,
                };
                *s = Section { offset, len };
            }
        }
        Edit::Format {
            layer,
            weights,
            acc,
            elu,
        } => {
            if let Some(l) = layer_mut(&mut p.header, layer % n) {
                l.weights = if weights {
                    WeightFormat::I16
                } else {
                    WeightFormat::I8
                };
                l.acc = if acc { AccWidth::I64 } else { AccWidth::I32 };
                l.activation = if elu {
                    Activation::Elu
                } else {
                    Activation::Identity
                };
            }
        }
        Edit::Gating(g) => p.header.gating = g,
        Edit::Figures { ram, macs } => (p.header.ram_bytes, p.header.macs_per_frame) = (ram, macs),
        Edit::Model { input, output } => {
            (p.header.input_dim, p.header.output_dim) = (input, output)
        }
        Edit::Payload { at, byte } => {
            let len = p.payload.len();
            p.payload[at % len] = byte;
        }
        Edit::Span {
            node,
            which,
            offset,
            len,
        } => {
            let span = Span { offset, len };
            match p.header.nodes.get_mut(node) {
                None => p.header.input = span,
                Some(x) => match which {
                    0 => x.input = span,
                    1 => x.scratch = span,
                    _ => x.output = span,
                },
            }
        }
        Edit::Slice {
            node,
            source,
            start,
            len,
        } => {
            let slice = Slice {
                source: source.map_or(Source::Input, Source::Node),
                start,
                len,
            };
            match p.header.nodes.get_mut(node) {
                None => p.header.output = slice,
                Some(x) => {
                    if let Some(first) = x.inputs.first_mut() {
                        *first = slice;
                    }
                }
            }
        }
        Edit::Gate { node, source } => {
            if let Some(x) = p.header.nodes.get_mut(node % n) {
                x.gate = match source {
                    None => GateSource::None,
                    Some(None) => GateSource::Phase,
                    Some(Some(j)) => GateSource::Node(j),
                };
            }
        }
        Edit::Softmax {
            node,
            experts,
            frac,
        } => {
            if let Some(x) = p.header.nodes.get_mut(node % n) {
                x.op = NodeOp::Softmax(phasegate::blob::SoftmaxDesc { experts, frac });
            }
        }
    }
}

pub struct CpAndStyles {
    pub cp: Vec<u8>,
    pub base: Vec<u8>,
    pub styles: Vec<Vec<u8>>,
}

pub fn cp_and_styles() -> CpAndStyles {
    use host_sim::target::synthetic;
    let opts = QuantOptions {
        calibration_samples: 128,
        ..QuantOptions::default()
    };
    let cp = exporter::export::export(&synthetic::cp_net(3, 20, 24, 12, 6), None, &opts)
        .unwrap()
        .0;
    let pfnn = synthetic::pfnn_base(4, 20, 24, 12);
    let base = export(&pfnn, None, &opts).unwrap().0;
    let net = pfnn.clone();
    let styles = ["cp", "diagonal", "full"]
        .iter()
        .enumerate()
        .map(|(i, form)| {
            let ad = synthetic::adapter(form, 24, 5, 30 + i as u64);
            synthetic::style_blob(&base, &net, &ad, form, None).unwrap()
        })
        .collect();
    CpAndStyles { cp, base, styles }
}

/// Every mix of `styles` (none, each one, each ordered pair blended at
/// weights 0, 1/2 and 1).
pub fn mixes(styles: usize) -> Vec<Mix> {
    let mut v = vec![Mix::Base];
    for a in 0..styles as u8 {
        v.push(Mix::One(StyleId(a)));
        for b in 0..styles as u8 {
            for w in [0.0, 0.5, 1.0] {
                v.push(Mix::Blend {
                    from: StyleId(a),
                    to: StyleId(b),
                    weight: BlendWeight::from_num(w),
                });
            }
        }
    }
    v
}

/// Runs extreme inputs at `phases` through the styled runtime with every
/// mix; the float and the integer paths agree bit for bit.
pub fn hammer_styled(base: Model<'_>, styles: &[Style<'_>], phases: &[u32]) -> usize {
    let Ok(mut rt) = Runtime::<'_, 64, 256, 4>::new(base) else {
        return 0;
    };
    let attached = styles.iter().filter(|s| rt.add_style(**s).is_ok()).count();
    let mut runs = 0;
    for mix in mixes(attached) {
        rt.set_mix(mix).unwrap();
        runs += run_extremes(&mut rt, phases).len();
    }
    runs
}

/// Splits a blob into its postcard header bytes and its payload.
pub fn raw_parts(blob: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let header_len = usize::from(u16::from_le_bytes([blob[6], blob[7]]));
    (
        blob[12..12 + header_len].to_vec(),
        blob[payload_start(blob)..].to_vec(),
    )
}

/// Built once: the exporter's calibration is the slow part.
pub fn cp_and_styles_cached() -> &'static CpAndStyles {
    static BLOBS: std::sync::OnceLock<CpAndStyles> = std::sync::OnceLock::new();
    BLOBS.get_or_init(cp_and_styles)
}
