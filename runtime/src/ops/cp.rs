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

use super::common::{
    check_dims, finish_row, i16_at, requant_record, row_l1, too_short, too_small, Sections,
    I32_ROW_BOUND,
};
use super::dense::matrix_kernel;

/// The on-target check of the CP glue (`kernel-check` feature).
#[cfg(all(feature = "kernel-check", phasegate_dsp))]
mod check;
use super::GatedOp;
use crate::blob::records::bias_at;
use crate::blob::REQUANT_RECORD_LEN;
use crate::blob::{AccWidth, Gating, LayerDesc, LayerOp, Requant};
use crate::error::{Error, Result};
use crate::fixed::gate::{Gate, MAX_ACTIVE, ONE};
use crate::fixed::{round_shift, round_shift_sat_i16, round_shift_sat_i32};
#[cfg(all(feature = "kernel-check", phasegate_dsp))]
pub use check::cp_check;

/// Bytes of one middle record.
pub const MID_RECORD_LEN: usize = 8;

/// Rows whose dot products a stage takes before finishing them (a
/// 256-byte buffer on the stack).
const CHUNK: usize = 32;

/// How one rank component turns `t_r * c_r` into the i16 `z_r`:
/// `z = sat16(round(sat32(round(sat32(round(t >> t_shift)) * c >> pre)) * multiplier >> post))`,
/// every rounding half up (as the runtime's `round_shift`).
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
        let t = i64::from(round_shift_sat_i32(t, self.t_shift));
        // |t| <= 2^31 and |c| <= 2^17 (see `CpLayer::middle`): no overflow.
        let p = i64::from(round_shift_sat_i32(t * c, self.pre_shift));
        round_shift_sat_i16(p * i64::from(self.multiplier), self.post_shift)
    }
}

/// Largest `sum_k |g_k|` (Q16) of any gate of `gating`, rounding included.
/// Constant, linear and softmax gates are non-negative and sum to exactly
/// 2^16; the
/// Catmull-Rom basis sums in magnitude to `1 + mu (1 - mu) <= 1.25`, and its
/// Q16 rounding adds at most a few LSB (8 allowed).
pub fn gate_l1_max(gating: &Gating) -> i64 {
    match gating {
        Gating::CatmullRom { .. } => i64::from(ONE) * 5 / 4 + 8,
        _ => i64::from(ONE) + 8,
    }
}

/// The gate's active experts, in gate order: where each expert's entries
/// start in a table of `rows` entries per expert, and its Q16 coefficient.
/// Taken once per stage, so that the per-row blends index flat arrays.
struct Active {
    n: usize,
    first: [usize; MAX_ACTIVE],
    g: [i32; MAX_ACTIVE],
}

impl Active {
    fn new(gate: &Gate, rows: usize) -> Active {
        let mut a = Active {
            n: gate.len().min(MAX_ACTIVE),
            first: [0; MAX_ACTIVE],
            g: [0; MAX_ACTIVE],
        };
        for ((e, g), (first, coef)) in gate.iter().zip(a.first.iter_mut().zip(&mut a.g)) {
            (*first, *coef) = (usize::from(e) * rows, g);
        }
        a
    }

    /// `acc[j] = keep * acc[j] + sum_k g_k table[first_k + i + j]` for
    /// every `j` (an entry outside the table adds 0; the loader proved the
    /// tables' lengths). Returns the multiply-accumulates done
    /// ([`crate::mac_count`]).
    /// Wrapping: the callers' bounds keep every sum far below 2^63, so the
    /// order of the additions does not matter.
    #[inline(always)]
    fn blend_into<const B: usize>(
        &self,
        table: &[[u8; B]],
        i: usize,
        read: fn([u8; B]) -> i32,
        keep: i64,
        acc: &mut [i64],
    ) -> usize {
        let entries = |k: usize| {
            let first = self
                .first
                .get(k)
                .map_or(usize::MAX, |f| f.saturating_add(i));
            table.get(first..).unwrap_or(&[])
        };
        let g = |k: usize| i64::from(self.g.get(k).copied().unwrap_or(0));
        let rows = acc.len();
        let four = (self.n == 4)
            .then(|| (entries(0), entries(1), entries(2), entries(3)))
            .filter(|(e0, e1, e2, e3)| [e0, e1, e2, e3].iter().all(|e| e.len() >= rows));
        if let Some((e0, e1, e2, e3)) = four {
            // The cubic gate's four experts walked in step, each row's sum
            // kept in registers (one `LDR` and one `SMLAL` per term),
            // rather than four passes that load and store every row.
            let (g0, g1, g2, g3) = (g(0), g(1), g(2), g(3));
            for ((((a, b0), b1), b2), b3) in acc.iter_mut().zip(e0).zip(e1).zip(e2).zip(e3) {
                // Each product is below 2^62 (32-bit factors).
                *a = a
                    .wrapping_mul(keep)
                    .wrapping_add(i64::from(read(*b0)) * g0)
                    .wrapping_add(i64::from(read(*b1)) * g1)
                    .wrapping_add(i64::from(read(*b2)) * g2)
                    .wrapping_add(i64::from(read(*b3)) * g3);
            }
            return 4 * rows;
        }
        acc.iter_mut().for_each(|a| *a = a.wrapping_mul(keep));
        let mut macs = 0;
        for k in 0..self.n {
            for (a, b) in acc.iter_mut().zip(entries(k)) {
                // One `SMLAL`: both factors are 32-bit.
                *a = a.wrapping_add(i64::from(read(*b)) * g(k));
                macs += 1;
            }
        }
        macs
    }
}

/// A core, i16 LE.
fn core_value(b: [u8; 2]) -> i32 {
    i32::from(i16::from_le_bytes(b))
}

/// A 32-bit bias, i32 LE.
fn bias32_value(b: [u8; 4]) -> i32 {
    i32::from_le_bytes(b)
}

/// A validated CP layer: its descriptor and its payload sections.
#[derive(Clone, Copy, Debug)]
pub struct CpLayer<'a> {
    /// The header's description (its `op` is `LayerOp::Cp`).
    pub desc: LayerDesc,
    /// Rank `R`.
    pub rank: u16,
    /// `B^T`: `rank` rows of `in` weights, in the layer's weight format.
    pub bt: &'a [u8],
    /// `A`: `out` rows of `rank` weights, in the layer's weight format.
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

impl<'a> CpLayer<'a> {
    fn rank(&self) -> usize {
        usize::from(self.rank)
    }

    /// Stage one: `z = requant_mid((B^T x) . c)`; `x` has `in_dim` elements,
    /// `z` at least `rank`.
    pub fn middle(&self, gate: &Gate, x: &[i16], z: &mut [i16]) -> Result<()> {
        let n_in = usize::from(self.desc.in_dim);
        let rank = self.rank();
        let x = x.get(..n_in).ok_or(too_short(n_in, x.len()))?;
        let capacity = z.len();
        let z = z.get_mut(..rank).ok_or(too_small(rank, capacity))?;
        let recs = self.mid.as_chunks::<MID_RECORD_LEN>().0;
        let none = MidRecord {
            multiplier: 0,
            t_shift: 0,
            pre_shift: 0,
            post_shift: 0,
        };
        let cores = self.cores.as_chunks::<2>().0;
        let active = Active::new(gate, rank);
        let mut blended = [0i64; CHUNK];
        self.each_chunk(self.bt, x, z, |first, ts, zs| {
            let recs = recs.get(first..).unwrap_or(&[]);
            // The blended cores `round(sum_k g_k d_k[r] / 2^16)`: with
            // `sum_k |g_k| <= gate_l1_max < 2^17` and `|d| <= 2^15`, below
            // 2^17 in magnitude.
            let Some(cs) = blended.get_mut(..ts.len()) else {
                return;
            };
            // The core blend is part of the layer's MACs; the bias blend
            // below is not (as a dense layer's).
            crate::mac_count::add(active.blend_into(cores, first, core_value, 0, cs));
            for (((zr, &t), &c), rec) in zs.iter_mut().zip(ts.iter()).zip(cs.iter()).zip(recs) {
                let c = round_shift(c, 16);
                *zr = MidRecord::from_bytes(rec).unwrap_or(none).apply(t, c);
            }
        })
    }

    /// Stage two: `y = act(requant(2^16 A z + sum_k g_k b_k))`; `z` has
    /// `rank` elements, `y` at least `out_dim`.
    pub fn output(&self, gate: &Gate, z: &[i16], y: &mut [i16]) -> Result<()> {
        let rank = self.rank();
        let out = usize::from(self.desc.out_dim);
        let z = z.get(..rank).ok_or(too_short(rank, z.len()))?;
        let capacity = y.len();
        let y = y.get_mut(..out).ok_or(too_small(out, capacity))?;
        let width = self.desc.acc.bytes();
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        let bias32 = self.bias.as_chunks::<4>().0;
        // With 32-bit accumulators and biases, `|2^16 acc| < 2^47` and
        // `sum_k |g_k b_k| <= 2^31 sum_k |g_k| < 2^62` when the gate's L1
        // norm is below 2^31: no saturation can act, so plain i64
        // arithmetic gives the saturating blend's bits without the M4's
        // costly overflow checks (as in the dense layer).
        let l1: u64 = gate.iter().map(|(_, g)| u64::from(g.unsigned_abs())).sum();
        let exact = self.desc.acc == AccWidth::I32 && l1 < 1 << 31;
        let activation = self.desc.activation;
        let active = Active::new(gate, out);
        self.each_chunk(self.a, z, y, |first, totals, ys| {
            let recs = recs.get(first..).unwrap_or(&[]);
            if exact {
                let _ = active.blend_into(bias32, first, bias32_value, ONE.into(), totals);
            } else {
                for (k, t) in totals.iter_mut().enumerate() {
                    let mut total = t.saturating_mul(i64::from(ONE));
                    for (e, g) in gate.iter() {
                        let at = usize::from(e) * out + first + k;
                        let b = bias_at(self.bias, width, at).unwrap_or(0);
                        total = total.saturating_add(b.saturating_mul(i64::from(g)));
                    }
                    *t = total;
                }
            }
            for ((yi, &total), rec) in ys.iter_mut().zip(totals.iter()).zip(recs) {
                *yi = finish_row(total, rec, activation);
            }
        })
    }

    /// The dot products of every row of `matrix` (rows of `x.len()`
    /// weights in the layer's format) with `x`, [`CHUNK`] rows at a time,
    /// each chunk handed to `finish(first row, dots, out rows)` (which may
    /// reuse the dots' buffer): two rows
    /// per pass over `x` where the format's kernel has a two-row loop (the
    /// dense layer's kernels: the DSP loops on Armv7E-M), and the per-row
    /// work in one tight loop rather than a call per row.
    #[inline(always)]
    fn each_chunk(
        &self,
        matrix: &[u8],
        x: &[i16],
        out: &mut [i16],
        mut finish: impl FnMut(usize, &mut [i64], &mut [i16]),
    ) -> Result<()> {
        let kernel = matrix_kernel(self.desc.weights, self.desc.acc);
        let rb = self.desc.weights.row_bytes(x.len()).max(1);
        let short = Error::SectionLength { layer: self.index };
        if out
            .len()
            .checked_mul(rb)
            .is_none_or(|need| matrix.len() < need)
        {
            return Err(short);
        }
        let mut buffer = [0i64; CHUNK];
        for (c, (chunk, m)) in out
            .chunks_mut(CHUNK)
            .zip(matrix.chunks(CHUNK.saturating_mul(rb)))
            .enumerate()
        {
            let dots = buffer.get_mut(..chunk.len()).ok_or(short)?;
            kernel.rows(m, rb, x, dots).ok_or(short)?;
            finish(c * CHUNK, dots, chunk);
        }
        Ok(())
    }
}

impl<'a> GatedOp<'a> for CpLayer<'a> {
    /// `rank x (in + out + active)`: the two factor products and the core
    /// blend.
    fn macs(desc: &LayerDesc, active: u64) -> u64 {
        u64::from(rank_of(desc)) * (u64::from(desc.in_dim) + u64::from(desc.out_dim) + active)
    }

    /// The middle vector, `rank` elements.
    fn scratch(desc: &LayerDesc) -> usize {
        usize::from(rank_of(desc))
    }

    /// `rank >= 1` (`UnsupportedParameter`); `weight_section`: `B^T`,
    /// `rank` rows of `in` weights; `a`: `out` rows of `rank` weights (rows
    /// padded to 4 bytes for `I8Interleaved`, as a dense layer's); `cores`:
    /// `experts x rank` i16; `mid`: `rank` records; then biases and records.
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
        let LayerOp::Cp {
            rank,
            a,
            cores,
            mid,
        } = desc.op
        else {
            return Err(Error::UnsupportedParameter { layer: index });
        };
        if rank == 0 {
            return Err(Error::UnsupportedParameter { layer: index });
        }
        check_dims(&desc, index)?;
        let s = Sections::new(payload, index);
        let r = u64::from(rank);
        let row_bytes = |len: u16| desc.weights.row_bytes(usize::from(len)) as u64;
        let bt = s.get(desc.weight_section, r * row_bytes(desc.in_dim))?;
        let a = s.get(a, u64::from(desc.out_dim) * row_bytes(rank))?;
        let cores = s.get(cores, u64::from(desc.experts) * r * 2)?;
        let mid = s.get(mid, r * MID_RECORD_LEN as u64)?;
        let (bias, requant) = s.rows(&desc)?;
        Ok(CpLayer {
            desc,
            rank,
            bt,
            a,
            cores,
            mid,
            bias,
            requant,
            index,
        })
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
    fn check(&self, gating: &Gating) -> Result<()> {
        let li = self.index;
        let (rank, n_in, out) = (
            self.rank(),
            usize::from(self.desc.in_dim),
            usize::from(self.desc.out_dim),
        );
        let (bt_rb, a_rb) = (
            self.desc.weights.row_bytes(n_in),
            self.desc.weights.row_bytes(rank),
        );
        let narrow = self.desc.acc == AccWidth::I32;
        let overflow = |row: usize| Error::AccumulatorOverflow {
            layer: li,
            row: row as u16,
        };
        let bad = Error::UnsupportedParameter { layer: li };
        let g1 = gate_l1_max(gating) as u128;
        let i32_max = i32::MAX as u128;
        let recs = self.mid.as_chunks::<MID_RECORD_LEN>().0;
        if recs.len() != rank || self.bt.len() != rank * bt_rb {
            return Err(Error::SectionLength { layer: li });
        }
        for (r, (row, rec)) in self.bt.chunks_exact(bt_rb.max(1)).zip(recs).enumerate() {
            let rec = MidRecord::from_bytes(rec).ok_or(bad)?;
            if rec.t_shift > Requant::MAX_SHIFT
                || rec.pre_shift > Requant::MAX_SHIFT
                || rec.post_shift > Requant::MAX_SHIFT
            {
                return Err(bad);
            }
            let t = u128::from(row_l1(row, self.desc.weights)) << 15;
            if narrow && t > u128::from(I32_ROW_BOUND) {
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
        if recs.len() != out || self.a.len() != out * a_rb {
            return Err(Error::SectionLength { layer: li });
        }
        let width = self.desc.acc.bytes();
        for (i, (row, rec)) in self.a.chunks_exact(a_rb.max(1)).zip(recs).enumerate() {
            let rec = requant_record(rec, self.desc.activation, li)?;
            let s = u128::from(row_l1(row, self.desc.weights)) << 15;
            if narrow && s > u128::from(I32_ROW_BOUND) {
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

    fn desc(&self) -> &LayerDesc {
        &self.desc
    }

    fn desc_mut(&mut self) -> &mut LayerDesc {
        &mut self.desc
    }

    fn requant(&self) -> &'a [u8] {
        self.requant
    }

    /// [`CpLayer::middle`] into `scratch`, then [`CpLayer::output`].
    fn run(&self, gate: &Gate, x: &[i16], scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
        self.middle(gate, x, scratch)?;
        self.output(gate, scratch, y)
    }
}

/// The rank of a `Cp` descriptor (0 for other ops).
fn rank_of(desc: &LayerDesc) -> u16 {
    match desc.op {
        LayerOp::Cp { rank, .. } => rank,
        _ => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed::phase::Phase;

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

/// The CP op's side of the test contract (`ops::contract`).
#[cfg(test)]
pub(crate) mod case {
    use super::{gate_l1_max, CpLayer, MidRecord};
    use crate::blob::{AccWidth, Gating, LayerDesc, LayerOp, Section, WeightFormat};
    use crate::error::Error;
    use crate::ops::contract::{
        finish, finish_float, fit_i32_rows, fits, rhu, sat, OpCase, Payload, Rng, Rows, Shape,
    };

    const I32_MAX: u128 = i32::MAX as u128;

    /// A CP layer as plain integers.
    #[derive(Clone, Debug)]
    pub(crate) struct Cp {
        rows: Rows,
        rank: usize,
        /// `B^T`: `rank x in`.
        bt: Vec<i32>,
        /// `A`: `out x rank`.
        a: Vec<i32>,
        /// `experts x rank`.
        cores: Vec<i16>,
        mid: Vec<MidRecord>,
        gating: Gating,
    }

    fn l1(row: &[i32]) -> u128 {
        row.iter().map(|&w| u128::from(w.unsigned_abs())).sum()
    }

    /// What one component computes, exactly, for the reference and the
    /// float twin.
    struct Middle {
        /// `sum_j Bt[r, j] x_j`.
        t: i128,
        /// `sum_k g_k d_k[r]` (Q16 gate times the cores).
        c_q16: i128,
        z: i16,
        /// No saturation acted (`t'`, `p`, `z`).
        exact: bool,
        /// The claims of the proof held (`t` in i32 with 32-bit
        /// accumulators, neither `sat32` acted).
        claims: bool,
    }

    impl Cp {
        fn bt_row(&self, r: usize) -> &[i32] {
            let n = self.rows.shape.in_dim;
            &self.bt[r * n..][..n]
        }

        fn a_row(&self, i: usize) -> &[i32] {
            &self.a[i * self.rank..][..self.rank]
        }

        fn dmax(&self, r: usize) -> u128 {
            (0..self.rows.shape.experts)
                .map(|k| u128::from(self.cores[k * self.rank + r].unsigned_abs()))
                .max()
                .unwrap_or(0)
        }

        /// The proof's bound of `|t >> t_shift|` and of `|c|` for
        /// component `r`, as `CpLayer::check` states it.
        fn mid_bounds(&self, r: usize, t_shift: u8) -> (u128, u128) {
            let g1 = gate_l1_max(&self.gating) as u128;
            let t = ((l1(self.bt_row(r)) << 15) >> t_shift) + 1;
            (t, ((g1 * self.dmax(r)) >> 16) + 1)
        }

        /// The proof's bound of `|total|` for output row `i`.
        fn out_bound(&self, i: usize) -> u128 {
            let g1 = gate_l1_max(&self.gating) as u128;
            let bmax = (0..self.rows.shape.experts)
                .map(|k| self.rows.bias(k, i).unsigned_abs())
                .max()
                .unwrap_or(0);
            ((l1(self.a_row(i)) << 15) << 16) + g1 * bmax
        }

        /// Smallest shifts the proof accepts, plus `slack`.
        fn fit_shifts(&mut self, rng: &mut Rng, slack: i64) {
            for r in 0..self.rank {
                let mut ts = 0u8;
                while self.mid_bounds(r, ts).0 > I32_MAX {
                    ts += 1;
                }
                let (t, c) = self.mid_bounds(r, ts);
                let mut pre = 0u8;
                while ((t * c) >> pre) + 1 > I32_MAX {
                    pre += 1;
                }
                self.mid[r].t_shift = ts + rng.range(0, slack) as u8;
                self.mid[r].pre_shift = pre + rng.range(0, slack) as u8;
            }
            for i in 0..self.rows.shape.out_dim {
                let total = self.out_bound(i);
                let mut pre = 0u8;
                while (total >> pre) + 1 > I32_MAX {
                    pre += 1;
                }
                self.rows.requant[i].pre_shift = pre + rng.range(0, slack) as u8;
            }
        }

        fn middle(&self, g: &[(usize, i128)], x: &[i16], r: usize) -> Middle {
            let t: i128 = self
                .bt_row(r)
                .iter()
                .zip(x)
                .map(|(&w, &v)| i128::from(w) * i128::from(v))
                .sum();
            let c_q16: i128 = g
                .iter()
                .map(|&(k, gk)| gk * i128::from(self.cores[k * self.rank + r]))
                .sum();
            let c = rhu(c_q16, 16);
            let m = self.mid[r];
            let t1 = rhu(t, m.t_shift);
            let p = rhu(sat(t1, 32) * c, m.pre_shift);
            let z = rhu(sat(p, 32) * i128::from(m.multiplier), m.post_shift);
            let narrow = self.rows.shape.acc == AccWidth::I32;
            Middle {
                t,
                c_q16,
                z: sat(z, 16) as i16,
                exact: fits(t1, 32) && fits(p, 32) && fits(z, 16),
                claims: (!narrow || fits(t, 32)) && fits(t1, 32) && fits(p, 32),
            }
        }

        /// Output row `i` from the middle vector `z`: the exact total and
        /// the kernel's (`sat64(2^16 s)`, then `+ sat64(g_k b_k)` in gate
        /// order, saturating), and the dot product `s`.
        fn total(&self, g: &[(usize, i128)], z: &[i16], i: usize) -> (i128, i128, i128) {
            let s: i128 = self
                .a_row(i)
                .iter()
                .zip(z)
                .map(|(&w, &v)| i128::from(w) * i128::from(v))
                .sum();
            let mut kernel = sat(s * 65536, 64);
            let mut exact = s * 65536;
            for &(k, gk) in g {
                let b = self.rows.bias(k, i);
                kernel = sat(kernel + sat(b * gk, 64), 64);
                exact += b * gk;
            }
            (exact, kernel, s)
        }
    }

    impl OpCase for Cp {
        type Op<'a> = CpLayer<'a>;

        fn random(rng: &mut Rng, mut shape: Shape, gating: Gating) -> Self {
            if shape.weights == WeightFormat::I8 && rng.chance(50) {
                shape.weights = WeightFormat::I8Interleaved;
            }
            let rank = rng.range(1, 40) as usize;
            let narrow = shape.acc == AccWidth::I32;
            let mut bt = shape.weights(rng, rank * shape.in_dim);
            let mut a = shape.weights(rng, shape.out_dim * rank);
            if narrow && rng.chance(90) {
                fit_i32_rows(&mut bt, shape.in_dim);
                fit_i32_rows(&mut a, rank);
            }
            let cores = (0..shape.experts * rank)
                .map(|_| rng.edgy(i16::MIN.into(), i16::MAX.into()) as i16)
                .collect();
            let mid = (0..rank)
                .map(|_| MidRecord {
                    multiplier: if rng.chance(30) {
                        rng.edgy(i32::MIN.into(), i32::MAX.into()) as i32
                    } else {
                        rng.range(1 << 30, i32::MAX.into()) as i32
                    },
                    t_shift: rng.range(0, 62) as u8,
                    pre_shift: rng.range(0, 62) as u8,
                    post_shift: rng.range(24, 46) as u8,
                })
                .collect();
            let mut case = Cp {
                rows: Rows::random(rng, shape, 44),
                rank,
                bt,
                a,
                cores,
                mid,
                gating,
            };
            if rng.chance(85) {
                let slack = rng.range(0, 3);
                case.fit_shifts(rng, slack);
            }
            case
        }

        fn rows(&self) -> &Rows {
            &self.rows
        }

        fn encode(&self, p: &mut Payload) -> LayerDesc {
            let f = self.rows.shape.weights;
            let none = Section::default();
            let mut d = self.rows.shape.desc(LayerOp::Cp {
                rank: self.rank as u16,
                a: none,
                cores: none,
                mid: none,
            });
            d.weight_section = p.rows(&self.bt, self.rows.shape.in_dim, f);
            let a = p.rows(&self.a, self.rank, f);
            let cores = p.push(
                &self
                    .cores
                    .iter()
                    .flat_map(|c| c.to_le_bytes())
                    .collect::<Vec<_>>(),
            );
            let mid = p.push(
                &self
                    .mid
                    .iter()
                    .flat_map(|m| m.to_bytes())
                    .collect::<Vec<_>>(),
            );
            d.op = LayerOp::Cp {
                rank: self.rank as u16,
                a,
                cores,
                mid,
            };
            self.rows.encode(p, &mut d);
            d
        }

        /// The table of `docs/cp-and-styles.md`, step by step in i128:
        /// `t_r`, `c_r = rhu(sum g d, 16)`,
        /// `z_r = sat16(rhu(sat32(rhu(sat32(rhu(t, t_shift)) c, pre)) m, post))`,
        /// `y_i = act(requant(2^16 sum_r A z + sum_k g_k b_k))`.
        fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool) {
            let mids: Vec<Middle> = (0..self.rank).map(|r| self.middle(g, x, r)).collect();
            let mut claims = mids.iter().all(|m| m.claims);
            let z: Vec<i16> = mids.iter().map(|m| m.z).collect();
            let s = self.rows.shape;
            let y = (0..s.out_dim)
                .map(|i| {
                    let (exact, kernel, dot) = self.total(g, &z, i);
                    let r = &self.rows.requant[i];
                    claims &= (s.acc == AccWidth::I64 || fits(dot, 32))
                        && fits(exact, 64)
                        && fits(rhu(exact, r.pre_shift), 32);
                    finish(kernel, r, s.activation)
                })
                .collect();
            (y, claims)
        }

        /// The real values of the same integers: `z_r = t_r c_r m /
        /// 2^(t_shift + pre + post)` with the exact blended core
        /// `c_r = sum g_k d_k / 2^16`, then `y = requant(2^16 A z + sum g b)`.
        /// Each `z_r` is off by at most
        /// `|m|/2^post ((|c|/2 + |t|/2^(t_shift+1) + 1/4) / 2^pre + 1/2) + 1/2`
        /// (four roundings); `A` carries that to the output total.
        fn float(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<Option<(f64, f64)>> {
            let s = self.rows.shape;
            let mids: Vec<Middle> = (0..self.rank).map(|r| self.middle(g, x, r)).collect();
            let z: Vec<i16> = mids.iter().map(|m| m.z).collect();
            if !mids.iter().all(|m| m.exact) {
                return vec![None; s.out_dim];
            }
            let (zf, ze): (Vec<f64>, Vec<f64>) = mids
                .iter()
                .zip(&self.mid)
                .map(|(m, rec)| {
                    let c = m.c_q16 as f64 / 65536.0;
                    let t = m.t as f64;
                    let ts = 2f64.powi(i32::from(rec.t_shift));
                    let pre = 2f64.powi(i32::from(rec.pre_shift));
                    let post = 2f64.powi(i32::from(rec.post_shift));
                    let mult = f64::from(rec.multiplier);
                    let value = t / ts * c / pre * mult / post;
                    let err = mult.abs() / post
                        * ((0.5 * c.abs() + 0.5 * t.abs() / ts + 0.25) / pre + 0.5)
                        + 0.5;
                    (value, err)
                })
                .unzip();
            (0..s.out_dim)
                .map(|i| {
                    let (exact, _, _) = self.total(g, &z, i);
                    if !fits(exact, 64) {
                        return None;
                    }
                    let row = self.a_row(i);
                    let sf: f64 = row.iter().zip(&zf).map(|(&w, v)| f64::from(w) * v).sum();
                    let se: f64 = row
                        .iter()
                        .zip(&ze)
                        .map(|(&w, e)| f64::from(w).abs() * e)
                        .sum();
                    let bias: f64 = g
                        .iter()
                        .map(|&(k, gk)| (self.rows.bias(k, i) * gk) as f64)
                        .sum();
                    let r = &self.rows.requant[i];
                    finish_float(exact, 65536.0 * sf + bias, 65536.0 * se, r, s.activation)
                })
                .collect()
        }

        /// Every bound of the proof reached at once: rows of `B^T` and `A`
        /// at `sum |w| = 65535` (32-bit accumulators; every weight at the
        /// minimum with 64-bit ones), cores at -32768, 64-bit biases as
        /// large as the output bound allows, and every shift the smallest
        /// the proof accepts.
        fn worst_case(rng: &mut Rng, mut shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>) {
            let narrow = shape.acc == AccWidth::I32;
            let (lo, hi) = shape.weight_range();
            let n_min = match shape.weights {
                WeightFormat::I16 => 1,
                WeightFormat::I8 | WeightFormat::I8Interleaved => 511,
            };
            let mut rank = rng.range(1, 4) as usize;
            if narrow {
                shape.in_dim = n_min + 1 + rng.below(2);
                rank = n_min + 1 + rng.below(2);
            }
            let pattern = |rng: &mut Rng, n: usize| -> Vec<i32> {
                let mut row = vec![lo as i32; n];
                if narrow {
                    row[n_min..].iter_mut().for_each(|v| *v = 0);
                    row[n_min] = hi as i32;
                    let shift = rng.below(n);
                    row.rotate_right(shift);
                }
                row
            };
            let mut case = Cp::random(rng, shape, gating);
            case.rank = rank;
            case.bt = (0..rank).flat_map(|_| pattern(rng, shape.in_dim)).collect();
            case.a = (0..shape.out_dim)
                .flat_map(|_| pattern(rng, rank))
                .collect();
            case.cores = vec![i16::MIN; shape.experts * rank];
            case.mid = (0..rank)
                .map(|_| MidRecord {
                    multiplier: rng.range(1 << 30, i32::MAX.into()) as i32,
                    t_shift: 0,
                    pre_shift: 0,
                    post_shift: rng.range(24, 46) as u8,
                })
                .collect();
            let g1 = gate_l1_max(&gating) as u128;
            for i in 0..shape.out_dim {
                let dots = (l1(case.a_row(i)) << 15) << 16;
                for k in 0..shape.experts {
                    let b = &mut case.rows.bias[k * shape.out_dim + i];
                    let big = match shape.acc {
                        AccWidth::I32 => i32::MAX as u128,
                        AccWidth::I64 => ((1u128 << 63) - 1 - dots) / g1,
                    } as i64;
                    *b = if rng.chance(50) { big } else { -big };
                }
            }
            case.fit_shifts(rng, 0);
            let row0 = case.bt_row(0).to_vec();
            let push = |neg: bool| -> Vec<i16> {
                row0.iter()
                    .map(|&w| match (w > 0) ^ neg {
                        _ if w == 0 => 0,
                        true => i16::MIN,
                        false => i16::MAX,
                    })
                    .collect()
            };
            let inputs = vec![push(false), push(true), rng.inputs(shape.in_dim)];
            (case, inputs)
        }

        /// Each shift one below the smallest the proof accepts; with
        /// 32-bit accumulators a row of `B^T` and a row of `A` one unit
        /// past `sum |w| = 65535`; with 64-bit biases, one bias one unit
        /// past the output bound.
        fn past_the_bound(worst: &Self, _gating: Gating) -> Vec<(Self, Error)> {
            let s = worst.rows.shape;
            let overflow = |row: usize| Error::AccumulatorOverflow {
                layer: 0,
                row: row as u16,
            };
            let (r, i) = (worst.rank - 1, s.out_dim - 1);
            let mut twins = Vec::new();
            if worst.mid[r].t_shift > 0 {
                let mut t = worst.clone();
                t.mid[r].t_shift -= 1;
                twins.push((t, overflow(r)));
            }
            if worst.mid[r].pre_shift > 0 {
                let mut t = worst.clone();
                t.mid[r].pre_shift -= 1;
                twins.push((t, overflow(r)));
            }
            if worst.rows.requant[i].pre_shift > 0 {
                let mut t = worst.clone();
                t.rows.requant[i].pre_shift -= 1;
                twins.push((t, overflow(i)));
            }
            let (lo, _) = s.weight_range();
            if s.acc == AccWidth::I32 {
                let mut t = worst.clone();
                let n = s.in_dim;
                if let Some(v) = t.bt[r * n..][..n].iter_mut().find(|v| **v > 0) {
                    *v = lo as i32;
                    twins.push((t, overflow(r)));
                }
                let mut t = worst.clone();
                let n = worst.rank;
                if let Some(v) = t.a[i * n..][..n].iter_mut().find(|v| **v > 0) {
                    *v = lo as i32;
                    twins.push((t, overflow(i)));
                }
            } else {
                let mut t = worst.clone();
                let b = &mut t.rows.bias[i];
                *b += b.signum();
                twins.push((t, overflow(i)));
            }
            twins
        }
    }
}
