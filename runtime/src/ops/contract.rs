//! The one test contract every op passes (tract's `frame/` suites, here for
//! [`GatedOp`]). An op plugs in by implementing [`OpCase`] next to its
//! kernel (a plain integer description of a layer, its i128 reference and
//! its real-valued twin) and one line of [`op_contract!`] at the end of this
//! file. The contract then checks, on random layers, gates and inputs:
//!
//! * **bit-exact**: the kernel equals the op's plain i128 reference (written
//!   from `docs/blob-format.md` and `docs/cp-and-styles.md`, no shortcuts)
//!   through every path the executor uses: the op's own `run`, the closed
//!   set [`Layer`], and a one-layer blob loaded
//!   by [`Model::from_bytes`] and run by [`Runtime::run_quantised`]. Shapes
//!   cover every tail length (widths 1..=40), weights, biases and inputs
//!   favour their extremes (`-32768`, `32767`, `-128`, `0`), gates come from
//!   every gating at random and boundary phases, ungated layers too. For
//!   every layer the loader accepts, the reference also confirms the claims
//!   of the op's overflow proof on that input (no accumulator wraps, no
//!   intermediate saturates where the proof says it cannot).
//! * **overflow proof**: the worst case the proof accepts (weights, cores,
//!   biases and shifts at the bound) loads and runs bit-exact on the inputs
//!   that reach the bound; its adversarial twins one step past the bound,
//!   and out-of-range records, are refused at load with the exact error.
//! * **fixed vs float**: the fixed-point output is within a bound, derived
//!   per output from the layer's records, of an f64 evaluation of the same
//!   integer weights' real values (no rounding but the f64's own), wherever
//!   no documented saturation acts.
//!
//! The activation (`fixed::elu::elu_q`) and the gate (`Gate::new`) are
//! shared by every op and checked on their own, exhaustively, against the
//! documented ELU and gate in `tests/tests/kernel_reference.rs`.

use std::vec::Vec;

use super::{GatedOp, Layer};
use crate::blob::{
    crc32, AccWidth, Activation, GateSource, Gating, Header, LayerDesc, ModelKind, Node, NodeOp,
    Requant, Section, Slice, Source, Span, WeightFormat, FORMAT_VERSION, MAGIC,
};
use crate::error::Error;
use crate::fixed::elu::elu_q;
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::{macs, Model, Runtime};

// ---------------------------------------------------------------------------
// Random numbers (a seeded xorshift: proptest supplies the seeds).

/// A small deterministic generator.
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    pub(crate) fn next(&mut self) -> u64 {
        let mut s = self.0;
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        self.0 = s;
        s.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// Uniform in `lo..=hi`.
    pub(crate) fn range(&mut self, lo: i64, hi: i64) -> i64 {
        let span = (hi as i128 - lo as i128 + 1) as u128;
        (lo as i128 + (u128::from(self.next()) % span) as i128) as i64
    }

    pub(crate) fn below(&mut self, n: usize) -> usize {
        self.range(0, n as i64 - 1) as usize
    }

    pub(crate) fn chance(&mut self, percent: u64) -> bool {
        self.next() % 100 < percent
    }

    /// In `lo..=hi`, often at or next to the ends or zero.
    pub(crate) fn edgy(&mut self, lo: i64, hi: i64) -> i64 {
        match self.next() % 10 {
            0 => lo,
            1 => hi,
            2 => 0,
            3 => self.range(-2, 2).clamp(lo, hi),
            4 => self.range(lo / 256, hi / 256),
            _ => self.range(lo, hi),
        }
    }

    pub(crate) fn inputs(&mut self, n: usize) -> Vec<i16> {
        (0..n)
            .map(|_| self.edgy(i16::MIN.into(), i16::MAX.into()) as i16)
            .collect()
    }
}

// ---------------------------------------------------------------------------
// What every op shares: shape, biases and output-row records.

/// The fields of a layer every op has.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Shape {
    pub(crate) in_dim: usize,
    pub(crate) out_dim: usize,
    pub(crate) experts: usize,
    pub(crate) gated: bool,
    pub(crate) weights: WeightFormat,
    pub(crate) acc: AccWidth,
    pub(crate) activation: Activation,
}

impl Shape {
    /// The gating that drives the layer: `gating` when gated, else `Single`.
    pub(crate) fn gating(&self, gating: Gating) -> Gating {
        if self.gated {
            gating
        } else {
            Gating::Single
        }
    }

    /// Random formats; `in_dim`, `out_dim` in `1..=max`.
    pub(crate) fn random(rng: &mut Rng, gating: Gating, max_in: usize, max_out: usize) -> Shape {
        let gated = rng.chance(75);
        Shape {
            in_dim: rng.range(1, max_in as i64) as usize,
            out_dim: rng.range(1, max_out as i64) as usize,
            experts: if gated {
                usize::from(gating.experts())
            } else {
                1
            },
            gated,
            weights: if rng.chance(50) {
                WeightFormat::I8
            } else {
                WeightFormat::I16
            },
            acc: if rng.chance(50) {
                AccWidth::I32
            } else {
                AccWidth::I64
            },
            activation: if rng.chance(50) {
                Activation::Elu
            } else {
                Activation::Identity
            },
        }
    }

    /// The weight range of the format (readers accept the asymmetric end).
    pub(crate) fn weight_range(&self) -> (i64, i64) {
        match self.weights {
            WeightFormat::I8 | WeightFormat::I8Interleaved => (-128, 127),
            WeightFormat::I16 => (-32768, 32767),
        }
    }

    /// `n` edgy weights.
    pub(crate) fn weights(&self, rng: &mut Rng, n: usize) -> Vec<i32> {
        let (lo, hi) = self.weight_range();
        (0..n).map(|_| rng.edgy(lo, hi) as i32).collect()
    }

    /// The descriptor of an op with these fields (sections filled by the
    /// op's `encode`).
    pub(crate) fn desc(&self, op: crate::blob::LayerOp) -> LayerDesc {
        LayerDesc {
            op,
            in_dim: self.in_dim as u16,
            out_dim: self.out_dim as u16,
            experts: self.experts as u16,
            weights: self.weights,
            acc: self.acc,
            activation: self.activation,
            weight_section: Section::default(),
            bias_section: Section::default(),
            requant_section: Section::default(),
        }
    }
}

/// Rows of `width` weights with `sum |w| <= 65535`, the bound of a 32-bit
/// accumulator (scaled down, so rows at and just under it are common).
pub(crate) fn fit_i32_rows(w: &mut [i32], width: usize) {
    for row in w.chunks_mut(width.max(1)) {
        let l1: i64 = row.iter().map(|&v| i64::from(v).abs()).sum();
        if l1 > 65_535 {
            for v in row.iter_mut() {
                *v = (i64::from(*v) * 65_535 / l1) as i32;
            }
        }
    }
}

/// Biases and output-row records: the part of a layer every op shares.
#[derive(Clone, Debug)]
pub(crate) struct Rows {
    pub(crate) shape: Shape,
    /// `experts x out`, expert-major.
    pub(crate) bias: Vec<i64>,
    /// `out`.
    pub(crate) requant: Vec<Requant>,
}

impl Rows {
    /// Edgy biases of the accumulator width (64-bit ones mostly within
    /// `2^bias_log2`) and records: 30% anything the loader accepts, else
    /// what a quantiser writes (normalised multiplier, shifts that land
    /// most outputs inside i16).
    pub(crate) fn random(rng: &mut Rng, shape: Shape, bias_log2: u32) -> Rows {
        let bias = (0..shape.experts * shape.out_dim)
            .map(|_| match shape.acc {
                AccWidth::I32 => rng.edgy(i32::MIN.into(), i32::MAX.into()),
                AccWidth::I64 => {
                    let b = 1i64 << bias_log2;
                    rng.edgy(-b, b)
                }
            })
            .collect();
        let elu = shape.activation == Activation::Elu;
        let requant = (0..shape.out_dim)
            .map(|_| {
                let frac = if elu {
                    rng.range(0, 15) as u8
                } else {
                    rng.next() as u8
                };
                if rng.chance(30) {
                    Requant {
                        multiplier: rng.edgy(i32::MIN.into(), i32::MAX.into()) as i32,
                        pre_shift: rng.range(0, 62) as u8,
                        post_shift: rng.range(0, 62) as u8,
                        frac,
                    }
                } else {
                    Requant {
                        multiplier: rng.range(1 << 30, i32::MAX.into()) as i32,
                        pre_shift: rng.range(8, 36) as u8,
                        post_shift: rng.range(28, 52) as u8,
                        frac,
                    }
                }
            })
            .collect();
        Rows {
            shape,
            bias,
            requant,
        }
    }

    /// Every bias at one end of its accumulator's range, at random (the
    /// worst cases of ops whose bias sums saturate).
    pub(crate) fn extreme_biases(&mut self, rng: &mut Rng) {
        for b in &mut self.bias {
            *b = match (self.shape.acc, rng.chance(50)) {
                (AccWidth::I32, true) => i32::MAX.into(),
                (AccWidth::I32, false) => i32::MIN.into(),
                (AccWidth::I64, true) => i64::MAX,
                (AccWidth::I64, false) => i64::MIN,
            };
        }
    }

    /// Bias of expert `k`, row `i`.
    pub(crate) fn bias(&self, k: usize, i: usize) -> i128 {
        i128::from(self.bias[k * self.shape.out_dim + i])
    }

    /// Appends the bias and record sections to `p` and fills them in `d`.
    pub(crate) fn encode(&self, p: &mut Payload, d: &mut LayerDesc) {
        d.bias_section = p.push(
            &self
                .bias
                .iter()
                .flat_map(|&b| match self.shape.acc {
                    AccWidth::I32 => (b as i32).to_le_bytes().to_vec(),
                    AccWidth::I64 => b.to_le_bytes().to_vec(),
                })
                .collect::<Vec<_>>(),
        );
        d.requant_section = p.push(
            &self
                .requant
                .iter()
                .flat_map(|r| r.to_bytes())
                .collect::<Vec<_>>(),
        );
    }
}

// ---------------------------------------------------------------------------
// The shared reference arithmetic (docs/blob-format.md, "Inference arithmetic").

/// `v / 2^s` rounded half up, exactly (`>>` on i128 is floor division).
pub(crate) fn rhu(v: i128, s: u8) -> i128 {
    if s == 0 {
        v
    } else {
        (v + (1i128 << (s - 1))) >> s
    }
}

pub(crate) fn sat(v: i128, bits: u32) -> i128 {
    let hi = (1i128 << (bits - 1)) - 1;
    v.clamp(-hi - 1, hi)
}

pub(crate) fn fits(v: i128, bits: u32) -> bool {
    sat(v, bits) == v
}

/// The output-row tail of every op: `t = sat32(rhu(total, pre))`,
/// `u = sat16(rhu(t m, post))`, then the activation at the row's format.
pub(crate) fn finish(total: i128, r: &Requant, activation: Activation) -> i16 {
    let t = sat(rhu(total, r.pre_shift), 32);
    let u = sat(rhu(t * i128::from(r.multiplier), r.post_shift), 16) as i16;
    match activation {
        Activation::Identity => u,
        Activation::Elu => elu_q(u, r.frac),
    }
}

/// The real-valued twin of [`finish`]: `total * m / 2^(pre + post)` and
/// the activation in f64, with the bound of the two roundings (and of the
/// ELU table, `docs/fixed-point.md`) on top of `total_err`, the bound on
/// `|total - total_real|`. `None` when a saturation acts (the i32 after
/// the pre-shift, the final i16).
pub(crate) fn finish_float(
    total: i128,
    total_real: f64,
    total_err: f64,
    r: &Requant,
    activation: Activation,
) -> Option<(f64, f64)> {
    if !fits(rhu(total, r.pre_shift), 32) {
        return None;
    }
    let m = f64::from(r.multiplier);
    let scale = m / 2f64.powi(i32::from(r.pre_shift) + i32::from(r.post_shift));
    let u = total_real * scale;
    let post = m.abs() / 2f64.powi(i32::from(r.post_shift));
    let bound = 0.5 + post * (0.5 + total_err / 2f64.powi(i32::from(r.pre_shift)));
    if u.abs() + bound >= 32767.0 {
        return None;
    }
    Some(match activation {
        Activation::Identity => (u, bound),
        Activation::Elu => {
            let f = f64::from(r.frac.min(15));
            let lsb = 2f64.powf(f);
            let v = if u > 0.0 { u } else { (u / lsb).exp_m1() * lsb };
            (v, bound + 0.5 + 2f64.powf(f - 14.0))
        }
    })
}

/// A gate as (expert, Q16 coefficient) pairs.
pub(crate) fn gate_list(gate: &Gate) -> Vec<(usize, i128)> {
    gate.iter()
        .map(|(e, g)| (usize::from(e), i128::from(g)))
        .collect()
}

// ---------------------------------------------------------------------------
// Blobs.

/// A payload under construction: sections 4-aligned, gaps zero.
#[derive(Default)]
pub(crate) struct Payload(pub(crate) Vec<u8>);

impl Payload {
    pub(crate) fn push(&mut self, bytes: &[u8]) -> Section {
        while !self.0.len().is_multiple_of(4) {
            self.0.push(0);
        }
        let offset = self.0.len() as u32;
        self.0.extend_from_slice(bytes);
        Section {
            offset,
            len: bytes.len() as u32,
        }
    }

    pub(crate) fn weights(&mut self, w: &[i32], f: WeightFormat) -> Section {
        self.rows(w, w.len().max(1), f)
    }

    /// Rows of `width` weights in `f`'s storage order (and padding).
    pub(crate) fn rows(&mut self, w: &[i32], width: usize, f: WeightFormat) -> Section {
        let mut bytes = Vec::new();
        for row in w.chunks(width) {
            let mut stored = vec![0u8; f.row_bytes(row.len())];
            for (j, &v) in row.iter().enumerate() {
                let s = f.position(j) * f.bytes();
                match f {
                    WeightFormat::I8 | WeightFormat::I8Interleaved => stored[s] = v as i8 as u8,
                    WeightFormat::I16 => {
                        stored[s..s + 2].copy_from_slice(&(v as i16).to_le_bytes())
                    }
                }
            }
            bytes.extend(stored);
        }
        self.push(&bytes)
    }
}

/// A whole blob, framed as `docs/blob-format.md` specifies, of the chain
/// of layers `descs` (phase-gated when `gated`) over `payload`, with
/// identity input and output stages and the simplest valid arena plan:
/// every buffer after the previous one, nothing reused.
pub(crate) fn blob(
    gating: Gating,
    gated: bool,
    descs: &[LayerDesc],
    mut payload: Payload,
) -> Vec<u8> {
    let (first, last) = (descs[0], descs[descs.len() - 1]);
    let stage = |p: &mut Payload, n: u16, rec: [f32; 2]| {
        let bytes: Vec<u8> = (0..n)
            .flat_map(|_| rec.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<_>>())
            .collect();
        p.push(&bytes)
    };
    let input_stage = stage(&mut payload, first.in_dim, [0.0, 1.0]);
    let output_stage = stage(&mut payload, last.out_dim, [1.0, 0.0]);
    let mut end = 0u16;
    let mut next = |len: usize| {
        let s = Span {
            offset: end,
            len: len as u16,
        };
        end += len as u16;
        s
    };
    let input = next(usize::from(first.in_dim));
    let mut nodes = crate::blob::NodeVec::new();
    let mut prev = (Source::Input, input);
    for (i, d) in descs.iter().enumerate() {
        let scratch = next(<Layer<'_> as GatedOp<'_>>::scratch(d));
        let output = next(usize::from(d.out_dim));
        let node = Node {
            op: NodeOp::Layer(*d),
            inputs: [Slice {
                source: prev.0,
                start: 0,
                len: d.in_dim,
            }]
            .into_iter()
            .collect(),
            gate: if gated {
                GateSource::Phase
            } else {
                GateSource::None
            },
            input: prev.1,
            scratch,
            output,
        };
        nodes.push(node).unwrap();
        prev = (Source::Node(i as u8), output);
    }
    let mut header = Header {
        kind: ModelKind::Pfnn,
        gating,
        input_dim: first.in_dim,
        output_dim: last.out_dim,
        nodes,
        input,
        output: Slice {
            source: prev.0,
            start: 0,
            len: last.out_dim,
        },
        input_stage,
        output_stage,
        ram_bytes: 2 * u32::from(end),
        macs_per_frame: 0,
        payload_len: payload.0.len() as u32,
        payload_crc: crc32(&payload.0),
    };
    header.macs_per_frame = macs(&header) as u32;
    let h = postcard::to_allocvec(&header).unwrap();
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(h.len() as u16).to_le_bytes());
    let mut covered = out.clone();
    covered.extend_from_slice(&h);
    out.extend_from_slice(&crc32(&covered).to_le_bytes());
    out.extend_from_slice(&h);
    while !out.len().is_multiple_of(16) {
        out.push(0);
    }
    out.extend_from_slice(&payload.0);
    out
}

// ---------------------------------------------------------------------------
// The op's side of the contract.

/// A layer of one op as plain integers, with everything the contract needs.
pub(crate) trait OpCase: Clone + core::fmt::Debug + Sized {
    /// The op under test.
    type Op<'a>: GatedOp<'a>;

    /// A random layer with the common fields of `shape` (an op may adjust
    /// its dimensions, e.g. diagonal sets `out = in`) and values the loader
    /// mostly accepts, often at their extremes.
    fn random(rng: &mut Rng, shape: Shape, gating: Gating) -> Self;

    /// The common fields.
    fn rows(&self) -> &Rows;

    /// Appends the layer's sections to `p`; returns its descriptor.
    fn encode(&self, p: &mut Payload) -> LayerDesc;

    /// The plain i128 reference on `x` with the gate `g`: the outputs, and
    /// whether the claims of the op's overflow proof held on this input.
    fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool);

    /// The f64 value of each output with its error bound, from the same
    /// integer weights' real values; `None` where a saturation acts.
    fn float(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<Option<(f64, f64)>>;

    /// The worst case the proof accepts (the op's sizes and values at the
    /// bound), with inputs that drive it there.
    fn worst_case(rng: &mut Rng, shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>);

    /// Twins of an accepted `worst` one step past a bound of the proof,
    /// with the error the loader must give.
    fn past_the_bound(worst: &Self, gating: Gating) -> Vec<(Self, Error)>;
}

// ---------------------------------------------------------------------------
// The contract.

/// A random gating; `Softmax` stands for a softmax gate node's, whose
/// coefficients [`gate_for`] draws from random logits.
pub(crate) fn random_gating(rng: &mut Rng) -> Gating {
    match rng.below(5) {
        4 => Gating::Softmax {
            experts: rng.range(1, 8) as u16,
        },
        0 => Gating::Single,
        1 => Gating::Constant {
            tables: rng.range(1, 8) as u16,
        },
        2 => Gating::Linear {
            tables: rng.range(1, 8) as u16,
        },
        _ => Gating::CatmullRom {
            points: rng.range(4, 8) as u16,
        },
    }
}

/// A phase at, or next to, a segment boundary, at the ends, or anywhere.
pub(crate) fn random_phase(rng: &mut Rng, gating: Gating) -> Phase {
    let n = u64::from(gating.experts().max(1));
    Phase::from_bits(match rng.below(4) {
        0 => {
            let k = rng.range(0, n as i64 - 1) as u64;
            (((k << 32) / n) as u32)
                .wrapping_add(rng.range(0, 2) as u32)
                .wrapping_sub(1)
        }
        1 => [0, u32::MAX, 1 << 31][rng.below(3)],
        _ => rng.next() as u32,
    })
}

/// The gate of a gated layer at `phase`: the phase gating's, or for
/// `Softmax` the softmax of logits drawn from the phase's bits (often tied
/// or far apart, so coefficients at 0 and at 1 are common).
pub(crate) fn gate_for(gating: Gating, phase: Phase) -> Gate {
    let Gating::Softmax { experts } = gating else {
        return Gate::new(&gating, phase);
    };
    let mut rng = Rng::new(u64::from(phase.to_bits()));
    let frac = rng.range(0, 15) as u8;
    let logits: Vec<i16> = (0..experts)
        .map(|_| rng.edgy(-32768, 32767) as i16)
        .collect();
    Gate::softmax(&logits, frac).unwrap()
}

/// Whether the loader, on a one-layer blob, accepts the layer `desc` of
/// `shape` over `payload`; `Softmax` gatings, which need a gate node,
/// ask the op itself.
fn load_verdict<C: OpCase>(
    gating: Gating,
    shape: Shape,
    desc: LayerDesc,
    payload: Payload,
) -> Result<(), Error> {
    if matches!(gating, Gating::Softmax { .. }) {
        return C::Op::bind(&payload.0, desc, 0)?.check(&shape.gating(gating));
    }
    Model::from_bytes(&blob(gating, shape.gated, &[desc], payload)).map(|_| ())
}

/// What one layer's runs showed.
#[derive(Default, Debug)]
pub(crate) struct Stats {
    pub(crate) accepted: usize,
    pub(crate) refused: usize,
    /// Outputs neither zero nor on an i16 rail.
    pub(crate) interesting: usize,
    /// Outputs compared with the float twin.
    pub(crate) float_checked: usize,
    /// Of those, outputs whose bound is at most 3 LSB (records such as a
    /// quantiser writes), and their largest error.
    pub(crate) tight: usize,
    pub(crate) worst_tight_error: f64,
}

/// Runs `case` on `inputs` through every path and compares each with the
/// reference; checks the proof's claims and the float bound.
pub(crate) fn check_layer<C: OpCase>(
    case: &C,
    gating: Gating,
    inputs: &[(Vec<i16>, Phase)],
    stats: &mut Stats,
) {
    let mut payload = Payload::default();
    let desc = case.encode(&mut payload);
    let (n_in, out) = (usize::from(desc.in_dim), usize::from(desc.out_dim));
    let p = &payload.0;
    let bound = C::Op::bind(p, desc, 0).unwrap_or_else(|e| panic!("bind: {e:?} {case:?}"));
    let shape = case.rows().shape;
    let verdict = bound.check(&shape.gating(gating));
    let loaded = load_verdict::<C>(gating, shape, desc, payload_clone(&payload));
    assert_eq!(loaded, verdict, "the loader and the op disagree");
    if verdict.is_err() {
        stats.refused += 1;
        return;
    }
    stats.accepted += 1;
    let any = <Layer<'_> as GatedOp<'_>>::bind(p, desc, 0).unwrap();
    // The executor's path needs a phase gating (a softmax gate node's
    // path through it is checked by the graph tests).
    let blob = blob(gating, shape.gated, &[desc], payload_clone(&payload));
    let model = Model::from_bytes(&blob).ok();
    let mut rt: Option<Box<Runtime<'_, 4096>>> = model.map(|m| Box::new(Runtime::new(m).unwrap()));
    for (x, phase) in inputs {
        let x = &x[..n_in];
        let gate = if shape.gated {
            gate_for(gating, *phase)
        } else {
            Gate::SINGLE
        };
        let g = gate_list(&gate);
        let (want, claims) = case.reference(&g, x);
        let ctx = || format!("{case:?}\ngate {g:?}\ninput {x:?}");
        assert!(claims, "accepted, but the proof's claims fail: {}", ctx());
        // The op's own kernel, exact and oversized buffers.
        let mut scratch = vec![0i16; C::Op::scratch(&desc)];
        let mut y = vec![0i16; out];
        bound.run(&gate, x, &mut scratch, &mut y).unwrap();
        assert_eq!(y, want, "run: {}", ctx());
        let mut big = vec![0x5A5Ai16; out + 3];
        let mut scratch = vec![0i16; C::Op::scratch(&desc) + 5];
        bound.run(&gate, x, &mut scratch, &mut big).unwrap();
        assert_eq!(big[..out], want[..], "run, long buffers: {}", ctx());
        // The closed set, and the loaded model through the executor.
        let mut y = vec![0i16; out];
        let mut scratch = vec![0i16; any.scratch_elements()];
        any.run(&gate, x, &mut scratch, &mut y).unwrap();
        assert_eq!(y, want, "Layer::run: {}", ctx());
        if let Some(rt) = rt.as_mut() {
            let y = rt.run_quantised(*phase, x).unwrap();
            assert_eq!(y, &want[..], "Runtime: {}", ctx());
        }
        stats.interesting += want
            .iter()
            .filter(|&&v| v != 0 && v != i16::MAX && v != i16::MIN)
            .count();
        // Fixed vs float.
        for (i, f) in case.float(&g, x).into_iter().enumerate() {
            if let Some((value, bound)) = f {
                let err = (f64::from(want[i]) - value).abs();
                assert!(
                    err <= bound + 1e-6 * (1.0 + value.abs()),
                    "row {i}: fixed {} vs float {value}, error {err} > bound {bound}: {}",
                    want[i],
                    ctx()
                );
                stats.float_checked += 1;
                if bound <= 3.0 {
                    stats.tight += 1;
                    stats.worst_tight_error = stats.worst_tight_error.max(err);
                }
            }
        }
    }
}

fn payload_clone(p: &Payload) -> Payload {
    Payload(p.0.clone())
}

/// One random layer of op `C` with `n` random (input, phase) pairs.
pub(crate) fn bit_exact<C: OpCase>(seed: u64, n: usize, stats: &mut Stats) -> (Gating, Shape) {
    let mut rng = Rng::new(seed);
    let gating = random_gating(&mut rng);
    let shape = Shape::random(&mut rng, gating, 40, 24);
    let case = C::random(&mut rng, shape, shape.gating(gating));
    let n_in = usize::from(case.encode(&mut Payload::default()).in_dim);
    let inputs: Vec<_> = (0..n)
        .map(|_| (rng.inputs(n_in), random_phase(&mut rng, gating)))
        .collect();
    check_layer(&case, gating, &inputs, stats);
    (gating, case.rows().shape)
}

/// The proof's boundary for op `C`: the worst case loads and runs
/// bit-exact with its claims holding; each twin past the bound, and each
/// out-of-range output record, is refused with its error.
pub(crate) fn proof_boundary<C: OpCase>(seed: u64) {
    let mut rng = Rng::new(seed);
    let gating = random_gating(&mut rng);
    let shape = Shape::random(&mut rng, gating, 8, 6);
    let (worst, inputs) = C::worst_case(&mut rng, shape, shape.gating(gating));
    let inputs: Vec<_> = inputs
        .into_iter()
        .map(|x| (x, random_phase(&mut rng, gating)))
        .collect();
    let mut stats = Stats::default();
    check_layer(&worst, gating, &inputs, &mut stats);
    assert_eq!(stats.accepted, 1, "the worst case was refused: {worst:?}");
    let load = |c: &C| {
        let mut p = Payload::default();
        let d = c.encode(&mut p);
        load_verdict::<C>(gating, shape, d, p)
    };
    let twins = C::past_the_bound(&worst, shape.gating(gating));
    for (twin, err) in &twins {
        assert_eq!(load(twin), Err(*err), "{twin:?}");
    }
    // Output records out of range, in any op: shifts above 62, an ELU row
    // finer than Q15, a reserved byte set.
    let row = rng.below(worst.rows().shape.out_dim);
    let bad = Err(Error::UnsupportedParameter { layer: 0 });
    let mut p = Payload::default();
    let d = worst.encode(&mut p);
    let at = d.requant_section.offset as usize + 8 * row;
    let mut patches: Vec<(usize, u8)> = vec![(at + 4, 63), (at + 5, 63), (at + 7, 1)];
    if d.activation == Activation::Elu {
        patches.push((at + 6, 16));
    }
    for (byte, value) in patches {
        let mut q = payload_clone(&p);
        q.0[byte] = value;
        assert_eq!(
            load_verdict::<C>(gating, shape, d, q),
            bad,
            "record byte {byte} = {value}"
        );
    }
}

/// The contract, for op `$case` (an [`OpCase`]): a module of tests named
/// `$name`.
macro_rules! op_contract {
    ($name:ident, $case:ty, $formats:expr) => {
        mod $name {
            use super::*;
            use proptest::prelude::*;

            proptest! {
                #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

                /// Bit-exact against the i128 reference through every path,
                /// and fixed vs float within bound, on random layers.
                #[test]
                fn matches_the_reference_and_the_float_bound(seed in any::<u64>()) {
                    bit_exact::<$case>(seed, 8, &mut Stats::default());
                }

                /// The overflow proof at its bound.
                #[test]
                fn overflow_proof_accepts_the_worst_case_and_refuses_past_it(seed in any::<u64>()) {
                    proof_boundary::<$case>(seed);
                }
            }

            /// Fixed seeds: every configuration is covered, most layers
            /// load, many outputs are off the rails, many are compared with
            /// the float twin.
            #[test]
            fn covers_every_configuration() {
                let mut stats = Stats::default();
                let mut seen = std::collections::BTreeSet::new();
                let mut widths = std::collections::BTreeSet::new();
                for seed in 0..2000u64 {
                    let (gating, s) = bit_exact::<$case>(seed, 12, &mut stats);
                    widths.insert(s.in_dim);
                    let g = match gating {
                        Gating::Single => 0,
                        Gating::Constant { .. } => 1,
                        Gating::Linear { .. } => 2,
                        Gating::CatmullRom { .. } => 3,
                        Gating::Softmax { .. } => 4,
                    };
                    seen.insert((g, s.gated, s.weights as u8, s.acc as u8, s.activation as u8));
                }
                std::eprintln!("{}: {stats:?}", stringify!($name));
                // gatings x gated x weight formats x accumulators x activations
                assert_eq!(seen.len(), 5 * 2 * $formats * 2 * 2, "{seen:?}");
                // Every input width (so every tail of any unrolling) 1..=40.
                assert_eq!(widths.len(), 40, "{widths:?}");
                assert!(stats.accepted >= 600, "{stats:?}");
                assert!(stats.interesting >= 5_000, "{stats:?}");
                assert!(stats.float_checked >= 1_000, "{stats:?}");
                assert!(stats.tight >= 500, "{stats:?}");
            }
        }
    };
}

// Dense and CP layers also read `I8Interleaved`.
op_contract!(dense, crate::ops::dense::case::Dense, 3);
op_contract!(cp, crate::ops::cp::case::Cp, 3);
op_contract!(diagonal, crate::ops::diagonal::case::Diagonal, 2);
// RBF centres are int16 only.
op_contract!(rbf, crate::ops::rbf::case::Rbf, 1);
// DEC centres too.
op_contract!(dec, crate::ops::dec::case::Dec, 1);
