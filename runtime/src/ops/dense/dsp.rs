//! The Armv7E-M DSP kernels of the two layouts whose rows are words of
//! activation-ordered pairs: `I16` (two weights per half-word pair, as
//! stored) and `I8Interleaved` (`SXTB16` and `SXTB16 ROR 8` of a word give
//! `(w0, w1)` and `(w2, w3)`). One `SMLAD` (32-bit accumulator) or `SMLALD`
//! (64-bit) is two MACs.
//!
//! A pass takes one or two experts' rows (two accumulators, two weight
//! streams and the inputs in registers fill the registers the loop can
//! use; four experts take two passes over `x`, after one check of all four
//! rows in [`quad`]). The block loop takes the first [`Packed::head`]
//! inputs (every even width for `I8Interleaved` and for `I16` with 64-bit
//! accumulators, whole blocks of [`BLOCK`] otherwise) when `x` and every
//! row start word-aligned (`LDM`/`LDRD` fault otherwise); the rest of the
//! row, or the whole row when something is misaligned, goes through the
//! portable [`Packed::tail`]. The sums are exact modulo 2^32 (2^64)
//! whatever the order, so the result is the portable kernel's bit for bit
//! (`emulation.rs` proves the algorithm on the host,
//! `firmware/src/bin/kernel-check.rs` the assembly under QEMU).

use super::{Acc, Kernel, Weight, W16, W16L, W8I};
use core::marker::PhantomData;

#[cfg(phasegate_dsp)]
mod asm;
#[cfg(phasegate_dsp)]
pub(super) use asm::Asm;
#[cfg(all(feature = "kernel-check", phasegate_dsp))]
pub(super) mod check;
#[cfg(test)]
mod emulation;

/// Inputs per iteration of every block loop (two `LDM`s of eight).
pub(super) const BLOCK: usize = 16;

/// A layout the block loops read, with the accumulator they keep.
pub(super) trait Packed: Weight {
    /// Bytes of the weights of one input.
    const BYTES: usize;
    /// The block loop takes any non-zero multiple of this many inputs.
    const STEP: usize = BLOCK;

    /// How many of `len` inputs the block loop takes (the rest go to
    /// [`Packed::tail`], which starts at a group boundary).
    fn head(len: usize) -> usize {
        len / Self::STEP * Self::STEP
    }

    /// Bytes of a row that the block loop reads for `n = head(len)` inputs.
    fn head_bytes(n: usize) -> usize {
        n * Self::BYTES
    }
    /// `i32` (`SMLAD`) or `i64` (`SMLALD`).
    type Sum: Acc;

    /// `acc` plus the (wrapping) dot product of a row that starts at a
    /// group boundary with `x`: a plain loop, small rather than fast (it
    /// covers fewer than [`BLOCK`] inputs, or rows that are not
    /// word-aligned).
    fn tail(acc: Self::Sum, row: &[u8], x: &[i16]) -> Self::Sum;
}

impl Packed for W8I {
    const BYTES: usize = 1;
    /// Pairs: a last half group, single groups, whole blocks.
    const STEP: usize = 2;
    type Sum = i32;

    /// An even width whole (a last half group meets the padding of its
    /// group); an odd one up to its last whole group.
    fn head(len: usize) -> usize {
        if len.is_multiple_of(2) {
            len
        } else {
            len / 4 * 4
        }
    }

    /// Whole groups, the padding of a last half group included.
    fn head_bytes(n: usize) -> usize {
        n.next_multiple_of(4)
    }

    /// Group by group: stored `w0 w2 w1 w3` meet `x0 x2 x1 x3`; in the
    /// last, partial group input `s` meets slot `position(s)` (padding
    /// meets nothing).
    #[inline(never)]
    fn tail(mut acc: i32, row: &[u8], x: &[i16]) -> i32 {
        let w8 = |b: u8| i32::from(b as i8);
        let (groups, _) = row.as_chunks::<4>();
        let (xs, rest) = x.as_chunks::<4>();
        for (w, v) in groups.iter().zip(xs) {
            let [x0, x1, x2, x3] = v.map(i32::from);
            let t = w8(w[0]) * x0 + w8(w[1]) * x2 + w8(w[2]) * x1 + w8(w[3]) * x3;
            acc = acc.wrapping_add(t);
        }
        if let Some(w) = groups.get(xs.len()) {
            // Inputs 0, 1, 2 of a partial group sit in slots 0, 2, 1.
            let r = |s: usize| rest.get(s).map_or(0, |&v| i32::from(v));
            acc = acc.wrapping_add(w8(w[0]) * r(0) + w8(w[2]) * r(1) + w8(w[1]) * r(2));
        }
        acc
    }
}

impl Packed for W16 {
    const BYTES: usize = 2;
    type Sum = i32;

    #[inline(never)]
    fn tail(acc: i32, row: &[u8], x: &[i16]) -> i32 {
        tail16(acc, row, x)
    }
}

impl Packed for W16L {
    const BYTES: usize = 2;
    /// Pairs: whole blocks, and before them single words of two inputs.
    const STEP: usize = 2;
    type Sum = i64;

    #[inline(never)]
    fn tail(acc: i64, row: &[u8], x: &[i16]) -> i64 {
        tail16(acc, row, x)
    }
}

/// `acc` plus the dot product of an `I16` row with `x`.
#[inline(always)]
fn tail16<A: Acc>(mut acc: A, row: &[u8], x: &[i16]) -> A {
    for (w, &v) in row.as_chunks::<2>().0.iter().zip(x) {
        acc = acc.mac(i32::from(i16::from_le_bytes(*w)) * i32::from(v));
    }
    acc
}

/// A block loop over `N` (1 or 2) rows of layout `W`.
pub(super) trait Blocks<W: Packed, const N: usize> {
    /// The rows' (wrapping) dot products with `x`.
    ///
    /// # Safety
    ///
    /// `x.len()` is a non-zero multiple of [`Packed::STEP`], every row is
    /// `W::head_bytes(x.len())` long, and `x` and every row start
    /// word-aligned.
    unsafe fn run(rows: [&[u8]; N], x: &[i16]) -> [W::Sum; N];
}

fn word_aligned<T>(s: &[T]) -> bool {
    (s.as_ptr() as usize).is_multiple_of(4)
}

/// `rows`' dot products with `x`: the block loop `L` over the whole blocks,
/// [`Packed::tail`] over the rest. Not inlined: one copy per layout and row
/// count keeps the firmware's `.text` in budget.
#[inline(never)]
fn pass<W: Packed, L: Blocks<W, N>, const N: usize>(rows: [&[u8]; N], x: &[i16]) -> [W::Sum; N] {
    let n = W::head(x.len());
    let mut heads: [&[u8]; N] = [&[]; N];
    let mut fits = n > 0 && word_aligned(x);
    for (head, row) in heads.iter_mut().zip(rows) {
        match row.get(..W::head_bytes(n)) {
            Some(h) if word_aligned(h) => *head = h,
            _ => fits = false,
        }
    }
    let (mut acc, done) = match x.get(..n) {
        // SAFETY: `head` is `n` inputs, a non-zero multiple of STEP, each
        // row head is `W::head_bytes(n)` bytes, and all start word-aligned.
        Some(head) if fits => (unsafe { L::run(heads, head) }, n),
        _ => ([W::Sum::ZERO; N], 0),
    };
    if done < x.len() {
        let rest = x.get(done..).unwrap_or(&[]);
        for (a, row) in acc.iter_mut().zip(rows) {
            *a = W::tail(*a, row.get(done * W::BYTES..).unwrap_or(&[]), rest);
        }
    }
    acc
}

/// The kernel of layout `W` with block loop `L` ([`Asm`] on the target).
pub(super) struct Smlad<W, L>(PhantomData<(W, L)>);

impl<W: Packed, L: Blocks<W, 1> + Blocks<W, 2>> Kernel for Smlad<W, L> {
    fn dot1(r: [&[u8]; 1], x: &[i16]) -> [i64; 1] {
        pass::<W, L, 1>(r, x).map(Acc::widen)
    }

    fn dot2(r: [&[u8]; 2], x: &[i16]) -> [i64; 2] {
        pass::<W, L, 2>(r, x).map(Acc::widen)
    }

    fn dot4(r: [&[u8]; 4], x: &[i16]) -> [i64; 4] {
        quad::<W, L>(r, x)
    }
}

/// `out[p]` = rows `2p` and `2p + 1` of `matrix` (consecutive rows of
/// `rb` bytes) with `x`, through the two-row loop straight, after one check
/// for the whole matrix: that the loop takes the whole width, each row is
/// exactly its length, and `x` and the matrix start word-aligned (a CP
/// factor's usual case). `false`, and `out` to be recomputed, when the
/// check fails or the matrix is short.
#[inline(never)]
pub(super) fn matrix_pairs<W: Packed, L: Blocks<W, 2>>(
    matrix: &[u8],
    rb: usize,
    x: &[i16],
    out: &mut [[i64; 2]],
) -> bool {
    let whole = W::head(x.len()) == x.len() && !x.is_empty() && word_aligned(x);
    let fits = rb == W::head_bytes(x.len()) && rb.is_multiple_of(4) && word_aligned(matrix);
    if !(whole && fits) {
        return false;
    }
    let mut rows = matrix.chunks_exact(rb);
    for pair in out {
        let (Some(r0), Some(r1)) = (rows.next(), rows.next()) else {
            return false;
        };
        // SAFETY: `x` is a non-zero multiple of STEP inputs (`head` takes
        // it whole) and word-aligned; each row is `W::head_bytes(x.len())`
        // bytes and starts word-aligned (the matrix does, and the row
        // length is a multiple of 4).
        *pair = unsafe { L::run([r0, r1], x) }.map(Acc::widen);
    }
    true
}

/// Four rows: two passes of two, in one call. When the block loop takes
/// the whole width and every row and `x` are word-aligned (the usual case:
/// a cubic gate's layer), the two loops run straight after one check of
/// all four rows; otherwise two [`pass`]es.
#[inline(never)]
fn quad<W: Packed, L: Blocks<W, 2>>(r: [&[u8]; 4], x: &[i16]) -> [i64; 4] {
    let whole = W::head(x.len()) == x.len() && !x.is_empty() && word_aligned(x);
    let bytes = W::head_bytes(x.len());
    if whole && r.iter().all(|row| row.len() == bytes && word_aligned(row)) {
        // SAFETY: `x` is a non-zero multiple of STEP inputs (`head` takes it
        // whole), each row is `W::head_bytes(x.len())` bytes, and all start
        // word-aligned.
        let ([a, b], [c, d]) = unsafe { (L::run([r[0], r[1]], x), L::run([r[2], r[3]], x)) };
        return [a, b, c, d].map(Acc::widen);
    }
    let [a, b] = pass::<W, L, 2>([r[0], r[1]], x);
    let [c, d] = pass::<W, L, 2>([r[2], r[3]], x);
    [a, b, c, d].map(Acc::widen)
}
