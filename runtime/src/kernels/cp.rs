//! The phase-gated CP layer: `W_k = A diag(d_k) B^T`, computed as
//!
//! ```text
//! t = B^T x                                  rank dot products over x
//! c = round(sum_k g_k d_k / 2^16)             the gate-blended core (Q16 gate)
//! z = requant_mid(round(t / 2^t_shift) * c)   rank i16 values, one format per component
//! y = act(requant(2^16 * (A z) + sum_k g_k b_k))
//! ```
//!
//! so a frame costs `rank * (in + out)` multiply-accumulates instead of
//! `active * in * out`, and the `out x in` matrix `W` never exists. Like the
//! dense kernel it is integer only (bit-exact on every target), and every
//! intermediate is bounded by a proof the loader checks ([`CpLayer::check`]):
//! no accumulator wraps and no intermediate saturates before the final i16.

use crate::blob::records::bias_at;
use crate::blob::REQUANT_RECORD_LEN;
use crate::blob::{AccWidth, Activation, Gating, LayerDesc, Requant, WeightFormat};
use crate::error::{Error, Result};
use crate::fixed::gate::{Gate, ONE};
use crate::fixed::{round_shift, sat_i16, sat_i32};
use crate::kernels::dense::finish_row;

/// Bytes of one middle record.
pub const MID_RECORD_LEN: usize = 8;

/// How one rank component turns `t_r * c_r` into the i16 `z_r`:
/// `z = sat16(round(sat32(round(sat32(round(t >> t_shift)) * c >> pre)) * multiplier >> post))`,
/// every rounding half up (as [`crate::fixed::round_shift`]).
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MidRecord {
    /// Signed multiplier.
    pub multiplier: i32,
    /// Right shift of the dot product `t` before it meets the core.
    pub t_shift: u8,
    /// Right shift of the product `t * c` before the multiplication.
    pub pre_shift: u8,
    /// Right shift after the multiplication.
    pub post_shift: u8,
}

impl MidRecord {
    /// Encodes the record: multiplier (i32 LE), t_shift, pre_shift,
    /// post_shift, one reserved zero byte.
    pub fn to_bytes(&self) -> [u8; MID_RECORD_LEN] {
        let m = self.multiplier.to_le_bytes();
        [
            m[0],
            m[1],
            m[2],
            m[3],
            self.t_shift,
            self.pre_shift,
            self.post_shift,
            0,
        ]
    }

    /// Decodes a record; `None` if its reserved byte is not zero.
    pub fn from_bytes(b: &[u8; MID_RECORD_LEN]) -> Option<MidRecord> {
        let [m0, m1, m2, m3, t_shift, pre_shift, post_shift, reserved] = *b;
        (reserved == 0).then_some(MidRecord {
            multiplier: i32::from_le_bytes([m0, m1, m2, m3]),
            t_shift,
            pre_shift,
            post_shift,
        })
    }

    /// `z` of one component from its dot product `t` and blended core `c`.
    #[inline(always)]
    pub fn apply(&self, t: i64, c: i64) -> i16 {
        let t = i64::from(sat_i32(round_shift(t, self.t_shift)));
        // |t| <= 2^31 and |c| <= 2^17 (see `blend_core`): no overflow.
        let p = i64::from(sat_i32(round_shift(t * c, self.pre_shift)));
        sat_i16(round_shift(p * i64::from(self.multiplier), self.post_shift))
    }
}

/// Largest `sum_k |g_k|` (Q16) of any gate of `gating`, rounding included.
/// Constant and linear gates are non-negative and sum to exactly 2^16; the
/// Catmull-Rom basis sums in magnitude to `1 + mu (1 - mu) <= 1.25`, and its
/// Q16 rounding adds at most a few LSB (8 allowed).
pub fn gate_l1_max(gating: &Gating) -> i64 {
    match gating {
        Gating::CatmullRom { .. } => i64::from(ONE) * 5 / 4 + 8,
        _ => i64::from(ONE) + 8,
    }
}

/// The core of component `r` blended by `gate`, in core units:
/// `round(sum_k g_k d_k[r] / 2^16)`. With at most 4 active experts, |g| <= 2^16
/// each and |d| <= 2^15, the result is below 2^17 in magnitude.
#[inline(always)]
pub fn blend_core(cores: &[u8], rank: usize, gate: &Gate, r: usize) -> i64 {
    let mut c = 0i64;
    for (e, g) in gate.iter() {
        let d = i16_at(cores, usize::from(e) * rank + r).unwrap_or(0);
        c += i64::from(g) * i64::from(d);
    }
    round_shift(c, 16)
}

/// The `i`-th little-endian i16 of `bytes`.
#[inline(always)]
pub(crate) fn i16_at(bytes: &[u8], i: usize) -> Option<i16> {
    let b = bytes.get(i.checked_mul(2)?..)?.first_chunk::<2>()?;
    Some(i16::from_le_bytes(*b))
}

/// `sum_j w_j x_j` of a row of `WB`-byte weights; `WIDE` selects the i64
/// accumulator, else i32 (which the loader proved cannot wrap).
#[inline(always)]
fn dot<const WB: usize, const WIDE: bool>(row: &[u8], x: &[i16]) -> i64 {
    if WB == 1 {
        if WIDE {
            let mut a = 0i64;
            for (&w, &v) in row.iter().zip(x) {
                a += i64::from(i32::from(w as i8) * i32::from(v));
            }
            a
        } else {
            let mut a = 0i32;
            for (&w, &v) in row.iter().zip(x) {
                a = a.wrapping_add(i32::from(w as i8) * i32::from(v));
            }
            i64::from(a)
        }
    } else {
        let pairs = row.as_chunks::<2>().0;
        if WIDE {
            let mut a = 0i64;
            for (w, &v) in pairs.iter().zip(x) {
                a += i64::from(i32::from(i16::from_le_bytes(*w)) * i32::from(v));
            }
            a
        } else {
            let mut a = 0i32;
            for (w, &v) in pairs.iter().zip(x) {
                a = a.wrapping_add(i32::from(i16::from_le_bytes(*w)) * i32::from(v));
            }
            i64::from(a)
        }
    }
}

/// `sum_j |w_j|` of a row.
fn row_l1(row: &[u8], format: WeightFormat) -> u64 {
    match format {
        WeightFormat::I8 => row
            .iter()
            .map(|&b| u64::from((b as i8).unsigned_abs()))
            .sum(),
        WeightFormat::I16 => row
            .as_chunks::<2>()
            .0
            .iter()
            .map(|c| u64::from(i16::from_le_bytes(*c).unsigned_abs()))
            .sum(),
    }
}

/// A validated CP layer: its descriptor and its payload sections.
#[derive(Clone, Copy, Debug)]
pub struct CpLayer<'a> {
    /// The header's description (its `op` is `LayerOp::Cp`).
    pub desc: LayerDesc,
    /// Rank `R`.
    pub rank: u16,
    /// `B^T`: `rank x in` weights.
    pub bt: &'a [u8],
    /// `A`: `out x rank` weights.
    pub a: &'a [u8],
    /// `experts x rank` i16 cores.
    pub cores: &'a [u8],
    /// `rank` middle records.
    pub mid: &'a [u8],
    /// `experts x out` biases.
    pub bias: &'a [u8],
    /// `out` requantisation records.
    pub requant: &'a [u8],
    /// Position in the network (or style), for error reports.
    pub index: u8,
}

fn too_small(needed: usize, capacity: usize) -> Error {
    Error::BufferTooSmall {
        needed: needed as u32,
        capacity: capacity as u32,
    }
}

impl<'a> CpLayer<'a> {
    fn wb(&self) -> usize {
        self.desc.weights.bytes()
    }

    fn rank(&self) -> usize {
        usize::from(self.rank)
    }

    /// Stage one: `z = requant_mid((B^T x) . c)`; `x` has `in_dim` elements,
    /// `z` at least `rank`.
    pub fn middle(&self, gate: &Gate, x: &[i16], z: &mut [i16]) -> Result<()> {
        match (self.desc.weights, self.desc.acc) {
            (WeightFormat::I8, AccWidth::I32) => self.middle_typed::<1, false>(gate, x, z),
            (WeightFormat::I8, AccWidth::I64) => self.middle_typed::<1, true>(gate, x, z),
            (WeightFormat::I16, AccWidth::I32) => self.middle_typed::<2, false>(gate, x, z),
            (WeightFormat::I16, AccWidth::I64) => self.middle_typed::<2, true>(gate, x, z),
        }
    }

    fn middle_typed<const WB: usize, const WIDE: bool>(
        &self,
        gate: &Gate,
        x: &[i16],
        z: &mut [i16],
    ) -> Result<()> {
        let n_in = usize::from(self.desc.in_dim);
        let rank = self.rank();
        let x = x.get(..n_in).ok_or(Error::LengthMismatch {
            expected: n_in as u32,
            found: x.len() as u32,
        })?;
        let capacity = z.len();
        let z = z.get_mut(..rank).ok_or(too_small(rank, capacity))?;
        let rows = self.bt.chunks_exact(n_in * WB);
        let recs = self.mid.as_chunks::<MID_RECORD_LEN>().0;
        for (r, ((zr, row), rec)) in z.iter_mut().zip(rows).zip(recs).enumerate() {
            let t = dot::<WB, WIDE>(row, x);
            let c = blend_core(self.cores, rank, gate, r);
            let rec = MidRecord::from_bytes(rec).unwrap_or(MidRecord {
                multiplier: 0,
                t_shift: 0,
                pre_shift: 0,
                post_shift: 0,
            });
            *zr = rec.apply(t, c);
        }
        Ok(())
    }

    /// Stage two: `y = act(requant(2^16 A z + sum_k g_k b_k))`; `z` has
    /// `rank` elements, `y` at least `out_dim`.
    pub fn output(&self, gate: &Gate, z: &[i16], y: &mut [i16]) -> Result<()> {
        match (self.desc.weights, self.desc.acc) {
            (WeightFormat::I8, AccWidth::I32) => self.output_typed::<1, false>(gate, z, y),
            (WeightFormat::I8, AccWidth::I64) => self.output_typed::<1, true>(gate, z, y),
            (WeightFormat::I16, AccWidth::I32) => self.output_typed::<2, false>(gate, z, y),
            (WeightFormat::I16, AccWidth::I64) => self.output_typed::<2, true>(gate, z, y),
        }
    }

    fn output_typed<const WB: usize, const WIDE: bool>(
        &self,
        gate: &Gate,
        z: &[i16],
        y: &mut [i16],
    ) -> Result<()> {
        let rank = self.rank();
        let out = usize::from(self.desc.out_dim);
        let z = z.get(..rank).ok_or(Error::LengthMismatch {
            expected: rank as u32,
            found: z.len() as u32,
        })?;
        let capacity = y.len();
        let y = y.get_mut(..out).ok_or(too_small(out, capacity))?;
        let width = self.desc.acc.bytes();
        let rows = self.a.chunks_exact(rank * WB);
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for (i, ((yi, row), rec)) in y.iter_mut().zip(rows).zip(recs).enumerate() {
            let acc = dot::<WB, WIDE>(row, z);
            let mut total = acc.saturating_mul(i64::from(ONE));
            for (e, g) in gate.iter() {
                let b = bias_at(self.bias, width, usize::from(e) * out + i).unwrap_or(0);
                total = total.saturating_add(b.saturating_mul(i64::from(g)));
            }
            *yi = finish_row(total, rec, self.desc.activation);
        }
        Ok(())
    }

    /// The loader's proof for this layer, for any i16 input and any phase of
    /// `gating`:
    ///
    /// * with 32-bit accumulators, `sum |w| * 2^15 <= i32::MAX` for every
    ///   row of `B^T` and of `A` (so no dot product wraps);
    /// * the shifted dot product `t >> t_shift` fits an i32, and
    ///   `|t'| * |c| >> pre_shift` fits an i32 (no saturation in stage one);
    /// * `2^16 |A z| + gate_l1 * max_k |b_k|` is below 2^63 and fits an i32
    ///   after the row's pre-shift (no saturation in stage two).
    ///
    /// Every record's shifts are at most [`Requant::MAX_SHIFT`] and their
    /// reserved bytes zero.
    pub fn check(&self, gating: &Gating) -> Result<()> {
        let li = self.index;
        let (rank, n_in, out) = (
            self.rank(),
            usize::from(self.desc.in_dim),
            usize::from(self.desc.out_dim),
        );
        let wb = self.wb();
        let narrow = self.desc.acc == AccWidth::I32;
        let overflow = |row: usize| Error::AccumulatorOverflow {
            layer: li,
            row: row as u16,
        };
        let bad = Error::UnsupportedParameter { layer: li };
        let g1 = gate_l1_max(gating) as u128;
        let i32_max = i32::MAX as u128;
        let recs = self.mid.as_chunks::<MID_RECORD_LEN>().0;
        if recs.len() != rank || self.bt.len() != rank * n_in * wb {
            return Err(Error::SectionLength { layer: li });
        }
        for (r, (row, rec)) in self.bt.chunks_exact(n_in * wb).zip(recs).enumerate() {
            let rec = MidRecord::from_bytes(rec).ok_or(bad)?;
            if rec.t_shift > Requant::MAX_SHIFT
                || rec.pre_shift > Requant::MAX_SHIFT
                || rec.post_shift > Requant::MAX_SHIFT
            {
                return Err(bad);
            }
            let t = u128::from(row_l1(row, self.desc.weights)) << 15;
            if narrow && t > i32_max {
                return Err(overflow(r));
            }
            let t = (t >> rec.t_shift) + 1;
            let dmax = (0..usize::from(self.desc.experts))
                .filter_map(|k| i16_at(self.cores, k * rank + r))
                .map(|d| u128::from(d.unsigned_abs()))
                .max()
                .unwrap_or(0);
            let c = ((g1 * dmax) >> 16) + 1;
            if t > i32_max || ((t * c) >> rec.pre_shift) + 1 > i32_max {
                return Err(overflow(r));
            }
        }
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        if recs.len() != out || self.a.len() != out * rank * wb {
            return Err(Error::SectionLength { layer: li });
        }
        let width = self.desc.acc.bytes();
        for (i, (row, rec)) in self.a.chunks_exact(rank * wb).zip(recs).enumerate() {
            let rec = Requant::from_bytes(rec).ok_or(bad)?;
            let elu_frac_bad = self.desc.activation == Activation::Elu && rec.frac > 15;
            if rec.pre_shift > Requant::MAX_SHIFT
                || rec.post_shift > Requant::MAX_SHIFT
                || elu_frac_bad
            {
                return Err(bad);
            }
            let s = u128::from(row_l1(row, self.desc.weights)) << 15;
            if narrow && s > i32_max {
                return Err(overflow(i));
            }
            let bmax = (0..usize::from(self.desc.experts))
                .filter_map(|k| bias_at(self.bias, width, k * out + i))
                .map(|b| u128::from(b.unsigned_abs()))
                .max()
                .unwrap_or(0);
            let total = (s << 16) + g1 * bmax;
            if total >= 1 << 63 || (total >> rec.pre_shift) + 1 > i32_max {
                return Err(overflow(i));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blob::{LayerOp, Section};
    use crate::fixed::elu::elu_q;
    use crate::fixed::phase::Phase;
    use proptest::prelude::*;

    /// A CP layer as plain integers, for building test sections.
    #[derive(Clone, Debug)]
    struct Plain {
        n_in: usize,
        out: usize,
        rank: usize,
        experts: usize,
        bt: Vec<i32>,
        a: Vec<i32>,
        cores: Vec<i16>,
        mid: Vec<MidRecord>,
        bias: Vec<i64>,
        requant: Vec<Requant>,
        format: WeightFormat,
        acc: AccWidth,
        activation: Activation,
    }

    struct Bytes {
        bt: Vec<u8>,
        a: Vec<u8>,
        cores: Vec<u8>,
        mid: Vec<u8>,
        bias: Vec<u8>,
        requant: Vec<u8>,
    }

    fn weights(w: &[i32], f: WeightFormat) -> Vec<u8> {
        w.iter()
            .flat_map(|&v| match f {
                WeightFormat::I8 => vec![v as i8 as u8],
                WeightFormat::I16 => (v as i16).to_le_bytes().to_vec(),
            })
            .collect()
    }

    impl Plain {
        fn bytes(&self) -> Bytes {
            Bytes {
                bt: weights(&self.bt, self.format),
                a: weights(&self.a, self.format),
                cores: self.cores.iter().flat_map(|c| c.to_le_bytes()).collect(),
                mid: self.mid.iter().flat_map(|m| m.to_bytes()).collect(),
                bias: self
                    .bias
                    .iter()
                    .flat_map(|&b| match self.acc {
                        AccWidth::I32 => (b as i32).to_le_bytes().to_vec(),
                        AccWidth::I64 => b.to_le_bytes().to_vec(),
                    })
                    .collect(),
                requant: self.requant.iter().flat_map(|r| r.to_bytes()).collect(),
            }
        }

        fn layer<'a>(&self, b: &'a Bytes) -> CpLayer<'a> {
            let s = Section::default();
            CpLayer {
                desc: LayerDesc {
                    op: LayerOp::Cp {
                        rank: self.rank as u16,
                        a: s,
                        cores: s,
                        mid: s,
                    },
                    in_dim: self.n_in as u16,
                    out_dim: self.out as u16,
                    experts: self.experts as u16,
                    weights: self.format,
                    acc: self.acc,
                    activation: self.activation,
                    gated: self.experts > 1,
                    weight_section: s,
                    bias_section: s,
                    requant_section: s,
                },
                rank: self.rank as u16,
                bt: &b.bt,
                a: &b.a,
                cores: &b.cores,
                mid: &b.mid,
                bias: &b.bias,
                requant: &b.requant,
                index: 0,
            }
        }

        /// The plain reference: the formulas of the module doc, written
        /// out with i128 and no shortcuts.
        fn reference(&self, gate: &Gate, x: &[i16]) -> Vec<i16> {
            let rs = |v: i128, s: u8| -> i128 {
                if s == 0 {
                    v
                } else {
                    (v + (1i128 << (s - 1))).div_euclid(1i128 << s)
                }
            };
            let clamp = |v: i128, lo: i128, hi: i128| v.clamp(lo, hi);
            let i32r = (i128::from(i32::MIN), i128::from(i32::MAX));
            let mut z = vec![0i16; self.rank];
            for (r, zr) in z.iter_mut().enumerate() {
                let t: i128 = (0..self.n_in)
                    .map(|j| i128::from(self.bt[r * self.n_in + j]) * i128::from(x[j]))
                    .sum();
                let c: i128 = gate
                    .iter()
                    .map(|(e, g)| {
                        i128::from(g) * i128::from(self.cores[usize::from(e) * self.rank + r])
                    })
                    .sum();
                let c = rs(c, 16);
                let m = self.mid[r];
                let t = clamp(rs(t, m.t_shift), i32r.0, i32r.1);
                let p = clamp(rs(t * c, m.pre_shift), i32r.0, i32r.1);
                *zr = clamp(
                    rs(p * i128::from(m.multiplier), m.post_shift),
                    -32768,
                    32767,
                ) as i16;
            }
            (0..self.out)
                .map(|i| {
                    let acc: i128 = (0..self.rank)
                        .map(|r| i128::from(self.a[i * self.rank + r]) * i128::from(z[r]))
                        .sum();
                    let mut total = acc * 65536;
                    for (e, g) in gate.iter() {
                        total +=
                            i128::from(g) * i128::from(self.bias[usize::from(e) * self.out + i]);
                    }
                    let q = &self.requant[i];
                    let t = clamp(rs(total, q.pre_shift), i32r.0, i32r.1);
                    let v = clamp(
                        rs(t * i128::from(q.multiplier), q.post_shift),
                        -32768,
                        32767,
                    ) as i16;
                    match self.activation {
                        Activation::Identity => v,
                        Activation::Elu => elu_q(v, q.frac),
                    }
                })
                .collect()
        }
    }

    prop_compose! {
        fn plain()(
            n_in in 1usize..24, out in 1usize..20, rank in 1usize..12,
            wide in any::<bool>(), i16w in any::<bool>(), elu in any::<bool>(),
            seed in any::<u64>(),
        ) -> Plain {
            let mut s = seed | 1;
            let mut next = move || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; s };
            let format = if i16w { WeightFormat::I16 } else { WeightFormat::I8 };
            let wmax: i64 = if i16w { 32767 } else { 127 };
            let mut w = |n: usize| (0..n).map(|_| (next() % (2 * wmax as u64 + 1)) as i64 - wmax)
                .map(|v| v as i32).collect::<Vec<_>>();
            let bt = w(rank * n_in);
            let a = w(out * rank);
            let experts = 4;
            let cores = (0..experts * rank).map(|_| (next() >> 16) as i16).collect();
            let mid = (0..rank).map(|_| MidRecord {
                multiplier: (next() >> 34) as i32 + (1 << 29),
                t_shift: (next() % 12) as u8,
                pre_shift: (next() % 30) as u8 + 8,
                post_shift: (next() % 20) as u8 + 25,
            }).collect();
            let bias = (0..experts * out).map(|_| (next() >> 40) as i64 - (1 << 23)).collect();
            let requant = (0..out).map(|_| Requant {
                multiplier: (next() >> 34) as i32 + (1 << 29),
                pre_shift: (next() % 30) as u8 + 10,
                post_shift: (next() % 20) as u8 + 25,
                frac: (next() % 16) as u8,
            }).collect();
            Plain { n_in, out, rank, experts, bt, a, cores, mid, bias, requant, format,
                acc: if wide || i16w { AccWidth::I64 } else { AccWidth::I32 },
                activation: if elu { Activation::Elu } else { Activation::Identity } }
        }
    }

    proptest! {
        /// The kernel equals the plain i128 reference bit for bit, whatever
        /// the weights, records, input and phase.
        #[test]
        fn kernel_matches_plain_reference(
            p in plain(),
            xs in proptest::collection::vec(any::<i16>(), 24),
            phase in any::<u32>(),
        ) {
            let bytes = p.bytes();
            let layer = p.layer(&bytes);
            let gate = Gate::new(&Gating::CatmullRom { points: 4 }, Phase::from_bits(phase));
            let x = &xs[..p.n_in];
            let mut z = vec![0i16; p.rank];
            let mut y = vec![0i16; p.out];
            layer.middle(&gate, x, &mut z).unwrap();
            layer.output(&gate, &z, &mut y).unwrap();
            prop_assert_eq!(y, p.reference(&gate, x));
        }
    }

    #[test]
    fn mid_record_round_trips_and_rejects_reserved() {
        let m = MidRecord {
            multiplier: -7,
            t_shift: 3,
            pre_shift: 20,
            post_shift: 40,
        };
        let mut b = m.to_bytes();
        assert_eq!(MidRecord::from_bytes(&b), Some(m));
        b[7] = 1;
        assert_eq!(MidRecord::from_bytes(&b), None);
    }

    #[test]
    fn gate_l1_bound_holds_for_every_phase() {
        for g in [
            Gating::CatmullRom { points: 4 },
            Gating::CatmullRom { points: 7 },
            Gating::Linear { tables: 10 },
            Gating::Constant { tables: 50 },
            Gating::Single,
        ] {
            for i in 0..=u16::MAX {
                let gate = Gate::new(&g, Phase::from_bits((u32::from(i) << 16) | 0x5A5A));
                let l1: i64 = gate.iter().map(|(_, w)| i64::from(w).abs()).sum();
                assert!(l1 <= gate_l1_max(&g), "{g:?} {i}: {l1}");
            }
        }
    }
}
