//! The on-target half of the kernels' equivalence proof (`kernel-check`
//! feature; run by `firmware/src/bin/kernel-check.rs` under QEMU): seeded
//! random cases of the host emulation test's kinds (both layouts, `I16`
//! with 32- and 64-bit accumulators, 1, 2 and 4 experts, every input width
//! 1..=300 so every tail and every entry into the unrolled loops, full-range weights
//! and inputs, random padding, word-aligned and misaligned rows and
//! inputs) through the assembly kernel and the portable one, bit for bit.

use super::{Asm, Smlad};
use crate::blob::WeightFormat;
use crate::ops::check_rng::Rng;
use crate::ops::dense::{Kernel, Portable, W16, W16L, W8I};

/// Widest case, in inputs.
const MAX_IN: usize = 300;
/// Bytes of one row buffer: the widest `I16` row and a misalignment.
const ROW_CAP: usize = 2 * MAX_IN + 4;

/// Word-aligned buffers of one case.
#[repr(C, align(4))]
struct Buffers {
    rows: [[u8; ROW_CAP]; 4],
    x: [i16; MAX_IN + 2],
}

/// Whether the assembly kernel and the portable one agree on case `seed`.
pub fn kernel_check(seed: u64) -> bool {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    // `I16` twice: 32-bit (`SMLAD`) and 64-bit (`SMLALD`) accumulators.
    let (format, wide) = match rng.below(3) {
        0 => (WeightFormat::I8Interleaved, false),
        1 => (WeightFormat::I16, false),
        _ => (WeightFormat::I16, true),
    };
    let experts = 1usize << rng.below(3);
    let n_in = 1 + rng.below(MAX_IN as u64) as usize;
    let row_misalign = if rng.below(5) == 0 {
        1 + rng.below(3) as usize
    } else {
        0
    };
    let x_misalign = usize::from(rng.below(5) == 0);
    let mut b = Buffers {
        rows: [[0; ROW_CAP]; 4],
        x: [0; MAX_IN + 2],
    };
    for row in b.rows.iter_mut() {
        for byte in row.iter_mut() {
            *byte = rng.next() as u8;
        }
    }
    for v in b.x.iter_mut() {
        *v = rng.edgy(-32768, 65536) as i16;
    }
    let len = format.row_bytes(n_in);
    let mut rows: [&[u8]; 4] = [&[]; 4];
    for (k, (slot, buf)) in rows.iter_mut().zip(&b.rows).enumerate() {
        let start = if k == 0 { row_misalign } else { 0 };
        *slot = buf.get(start..start + len).unwrap_or(&[]);
    }
    let x = b.x.get(x_misalign..x_misalign + n_in).unwrap_or(&[]);
    match format {
        WeightFormat::I16 if wide => {
            agree::<Smlad<W16L, Asm>, Portable<W16L, i64>>(experts, rows, x)
        }
        WeightFormat::I16 => agree::<Smlad<W16, Asm>, Portable<W16, i32>>(experts, rows, x),
        _ => agree::<Smlad<W8I, Asm>, Portable<W8I, i32>>(experts, rows, x),
    }
}

fn agree<F: Kernel, P: Kernel>(experts: usize, r: [&[u8]; 4], x: &[i16]) -> bool {
    match experts {
        1 => F::dot1([r[0]], x) == P::dot1([r[0]], x),
        2 => F::dot2([r[0], r[1]], x) == P::dot2([r[0], r[1]], x),
        _ => F::dot4(r, x) == P::dot4(r, x),
    }
}
