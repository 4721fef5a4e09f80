//! The on-target check of the CP layer's glue around the DSP kernels
//! (`kernel-check` feature; run by `firmware/src/bin/kernel-check.rs`
//! under QEMU): seeded random `I8Interleaved` CP layers (every input width
//! 1..=70 and rank 1..=40, so every block tail of both products, odd and
//! even row counts, more output rows than a chunk, 1, 2 or 4 active
//! experts, full-range weights, inputs, cores, biases and records, the
//! input sometimes off a word) through [`CpLayer::run`] and through a plain
//! scalar reference of the same arithmetic (`docs/cp-and-styles.md`),
//! bit for bit. The kernels themselves have their own cases
//! (`ops::dense::kernel_check`).

use super::{CpLayer, MidRecord, MID_RECORD_LEN};
use crate::blob::{
    AccWidth, Activation, Gating, LayerDesc, LayerOp, Requant, Section, WeightFormat,
    REQUANT_RECORD_LEN,
};
use crate::fixed::gate::{Gate, ONE};
use crate::fixed::phase::Phase;
use crate::fixed::round_shift;
use crate::ops::check_rng::Rng;
use crate::ops::common::finish_row;

const MAX_IN: usize = 70;
const MAX_RANK: usize = 40;
const MAX_OUT: usize = 40;
const EXPERTS: usize = 4;

/// Word-aligned buffers of one case.
#[repr(C, align(4))]
struct Buffers {
    bt: [u8; MAX_RANK * (MAX_IN + 2)],
    a: [u8; MAX_OUT * MAX_RANK],
    cores: [u8; EXPERTS * MAX_RANK * 2],
    mid: [u8; MAX_RANK * MID_RECORD_LEN],
    bias: [u8; EXPERTS * MAX_OUT * 4],
    requant: [u8; MAX_OUT * REQUANT_RECORD_LEN],
    x: [i16; MAX_IN + 2],
    z: [i16; MAX_RANK],
    y: [i16; MAX_OUT],
}

/// The wrapping 32-bit dot product of a stored `I8Interleaved` row with
/// `x`, weight by weight through the format's `position`.
fn dot(row: &[u8], x: &[i16]) -> i64 {
    let f = WeightFormat::I8Interleaved;
    let mut acc = 0i32;
    for (j, &v) in x.iter().enumerate() {
        let w = row.get(f.position(j)).map_or(0, |&b| i32::from(b as i8));
        acc = acc.wrapping_add(w * i32::from(v));
    }
    i64::from(acc)
}

/// Whether [`CpLayer::run`] and the scalar reference agree on case `seed`.
pub fn cp_check(seed: u64) -> bool {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let f = WeightFormat::I8Interleaved;
    let n_in = 1 + rng.below(MAX_IN as u64) as usize;
    let rank = 1 + rng.below(MAX_RANK as u64) as usize;
    let out = 1 + rng.below(MAX_OUT as u64) as usize;
    let gating = match rng.below(3) {
        0 => Gating::Single,
        1 => Gating::Linear { tables: 4 },
        _ => Gating::CatmullRom { points: 4 },
    };
    let gate = Gate::new(&gating, Phase::from_bits(rng.next() as u32));
    let activation = if rng.below(2) == 0 {
        Activation::Elu
    } else {
        Activation::Identity
    };
    let mut b = Buffers {
        bt: [0; MAX_RANK * (MAX_IN + 2)],
        a: [0; MAX_OUT * MAX_RANK],
        cores: [0; EXPERTS * MAX_RANK * 2],
        mid: [0; MAX_RANK * MID_RECORD_LEN],
        bias: [0; EXPERTS * MAX_OUT * 4],
        requant: [0; MAX_OUT * REQUANT_RECORD_LEN],
        x: [0; MAX_IN + 2],
        z: [0; MAX_RANK],
        y: [0; MAX_OUT],
    };
    for byte in
        b.bt.iter_mut()
            .chain(b.a.iter_mut())
            .chain(b.cores.iter_mut())
    {
        *byte = rng.next() as u8;
    }
    for c in b.bias.as_chunks_mut::<4>().0 {
        *c = (rng.edgy(-(1 << 24), 1 << 25) as i32).to_le_bytes();
    }
    for m in b.mid.as_chunks_mut::<MID_RECORD_LEN>().0 {
        *m = MidRecord {
            multiplier: rng.edgy(i64::from(i32::MIN), 1 << 32) as i32,
            t_shift: rng.below(20) as u8,
            pre_shift: rng.below(40) as u8,
            post_shift: 20 + rng.below(30) as u8,
        }
        .to_bytes();
    }
    for r in b.requant.as_chunks_mut::<REQUANT_RECORD_LEN>().0 {
        *r = Requant {
            multiplier: rng.edgy(i64::from(i32::MIN), 1 << 32) as i32,
            pre_shift: 8 + rng.below(40) as u8,
            post_shift: 20 + rng.below(30) as u8,
            frac: rng.below(16) as u8,
        }
        .to_bytes();
    }
    for v in b.x.iter_mut() {
        *v = rng.edgy(-32768, 65536) as i16;
    }
    let (bt_rb, a_rb) = (f.row_bytes(n_in), f.row_bytes(rank));
    let x_at = usize::from(rng.below(5) == 0);
    let none = Section::default();
    let layer = CpLayer {
        desc: LayerDesc {
            op: LayerOp::Cp {
                rank: rank as u16,
                a: none,
                cores: none,
                mid: none,
            },
            in_dim: n_in as u16,
            out_dim: out as u16,
            experts: EXPERTS as u16,
            weights: f,
            acc: AccWidth::I32,
            activation,
            weight_section: none,
            bias_section: none,
            requant_section: none,
        },
        rank: rank as u16,
        bt: b.bt.get(..rank * bt_rb).unwrap_or(&[]),
        a: b.a.get(..out * a_rb).unwrap_or(&[]),
        cores: b.cores.get(..EXPERTS * rank * 2).unwrap_or(&[]),
        mid: b.mid.get(..rank * MID_RECORD_LEN).unwrap_or(&[]),
        bias: b.bias.get(..EXPERTS * out * 4).unwrap_or(&[]),
        requant: b.requant.get(..out * REQUANT_RECORD_LEN).unwrap_or(&[]),
        index: 0,
    };
    let x = b.x.get(x_at..x_at + n_in).unwrap_or(&[]);
    if crate::ops::GatedOp::run(&layer, &gate, x, &mut b.z, &mut b.y).is_err() {
        return false;
    }
    // The reference, component by component and row by row.
    let row = |m: &'static str, i: usize| -> &[u8] {
        let (bytes, rb) = if m == "bt" {
            (layer.bt, bt_rb)
        } else {
            (layer.a, a_rb)
        };
        bytes.get(i * rb..(i + 1) * rb).unwrap_or(&[])
    };
    let table = |bytes: &[u8], at: usize, n: usize| -> i64 {
        match bytes.get(at * n..(at + 1) * n) {
            Some(&[l, h]) => i64::from(i16::from_le_bytes([l, h])),
            Some(&[b0, b1, b2, b3]) => i64::from(i32::from_le_bytes([b0, b1, b2, b3])),
            _ => 0,
        }
    };
    let mut z = [0i16; MAX_RANK];
    let mids = layer.mid.as_chunks::<MID_RECORD_LEN>().0;
    for (r, (zr, rec)) in z.iter_mut().zip(mids).enumerate() {
        let t = dot(row("bt", r), x);
        let c: i64 = gate
            .iter()
            .map(|(e, g)| i64::from(g) * table(layer.cores, usize::from(e) * rank + r, 2))
            .sum();
        *zr = MidRecord::from_bytes(rec).map_or(0, |m| m.apply(t, round_shift(c, 16)));
    }
    let (z, got_z) = (z.get(..rank).unwrap_or(&[]), b.z.get(..rank).unwrap_or(&[]));
    if z != got_z {
        return false;
    }
    let recs = layer.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
    for (i, (rec, &got)) in recs.iter().zip(&b.y).enumerate() {
        let acc = dot(row("a", i), z);
        let bias: i64 = gate
            .iter()
            .map(|(e, g)| i64::from(g) * table(layer.bias, usize::from(e) * out + i, 4))
            .sum();
        if finish_row(acc * i64::from(ONE) + bias, rec, activation) != got {
            return false;
        }
    }
    true
}
