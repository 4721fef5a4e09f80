//! The block loops of `asm.rs`, instruction by instruction, with the
//! instructions' semantics from the Armv7-M Architecture Reference Manual
//! (A7.7.134 `SXTB16`, A7.7.115 `SMLAD`, `LDM`/`LDRD` as little-endian word
//! loads), so that the kernel's algorithm (layout, pairing, block and tail
//! split, alignment fallback) is checked on the host against the portable
//! reference. The assembly itself is checked on the target by
//! `firmware/src/bin/kernel-check.rs` under QEMU.

use super::{matrix_pairs, Blocks, Kernel, Packed, Smlad, BLOCK, W16, W16L, W8I};
use crate::blob::WeightFormat;
use crate::ops::dense::{Acc, Portable};
use proptest::prelude::*;

/// `SXTB16 Rd, Rm, ROR #rot`: bytes 0 and 2 of `Rm` rotated right by
/// `rot`, each sign-extended to a half-word.
fn sxtb16(rm: u32, rot: u32) -> u32 {
    let r = rm.rotate_right(rot);
    let half = |b: u32| u32::from(b as u8 as i8 as i16 as u16);
    half(r) | (half(r >> 16) << 16)
}

/// `SMLAD Rd, Rn, Rm, Ra`: `Ra + Rn.lo * Rm.lo + Rn.hi * Rm.hi`, computed
/// exactly and kept modulo 2^32 (the Q flag, which the kernel ignores,
/// records a wrap).
fn smlad(rn: u32, rm: u32, ra: i32) -> i32 {
    let lo = i64::from(rn as i16) * i64::from(rm as i16);
    let hi = i64::from((rn >> 16) as i16) * i64::from((rm >> 16) as i16);
    (i64::from(ra) + lo + hi) as i32
}

/// `SMLALD RdLo, RdHi, Rn, Rm`: `RdHi:RdLo + Rn.lo * Rm.lo + Rn.hi *
/// Rm.hi`, modulo 2^64 (A7.7.118).
fn smlald(rn: u32, rm: u32, acc: i64) -> i64 {
    let lo = i64::from(rn as i16) * i64::from(rm as i16);
    let hi = i64::from((rn >> 16) as i16) * i64::from((rm >> 16) as i16);
    acc.wrapping_add(lo).wrapping_add(hi)
}

/// `LDM r10!, {r2-r5}`: eight inputs as four words, advancing `at`.
fn ldm4(x: &[i16], at: &mut usize) -> [u32; 4] {
    let mut r = [0u32; 4];
    for (k, w) in r.iter_mut().enumerate() {
        let lo = u32::from(x[*at + 2 * k] as u16);
        let hi = u32::from(x[*at + 2 * k + 1] as u16);
        *w = lo | (hi << 16);
    }
    *at += 8;
    r
}

/// `LDRD r12, lr, [p], #8`: two little-endian words, advancing `at`.
fn ldrd(row: &[u8], at: &mut usize) -> (u32, u32) {
    let word = |i: usize| u32::from_le_bytes(row[i..i + 4].try_into().unwrap());
    let r = (word(*at), word(*at + 4));
    *at += 8;
    r
}

/// `i8_step!`.
fn i8_step(acc: &mut i32, row: &[u8], at: &mut usize, x: [u32; 4]) {
    let (r12, lr) = ldrd(row, at);
    let t = sxtb16(r12, 0);
    *acc = smlad(t, x[0], *acc);
    let r12 = sxtb16(r12, 8);
    *acc = smlad(r12, x[1], *acc);
    let t = sxtb16(lr, 0);
    *acc = smlad(t, x[2], *acc);
    let lr = sxtb16(lr, 8);
    *acc = smlad(lr, x[3], *acc);
}

/// `i16_step!`.
fn i16_step(acc: &mut i32, row: &[u8], at: &mut usize, x: [u32; 4]) {
    let (r12, lr) = ldrd(row, at);
    *acc = smlad(r12, x[0], *acc);
    *acc = smlad(lr, x[1], *acc);
    let (r12, lr) = ldrd(row, at);
    *acc = smlad(r12, x[2], *acc);
    *acc = smlad(lr, x[3], *acc);
}

/// Eight inputs of one `I16` row into a 64-bit accumulator: the two-row
/// loop's `i16l_step2!` twice (inputs by `LDRD`, four at a time) and the
/// one-row loop's `i16l_step1!` (by `LDM`) read the same words and pair
/// them the same way.
fn i16l_step(acc: &mut i64, row: &[u8], at: &mut usize, x: [u32; 4]) {
    let (r12, lr) = ldrd(row, at);
    *acc = smlald(r12, x[0], *acc);
    *acc = smlald(lr, x[1], *acc);
    let (r12, lr) = ldrd(row, at);
    *acc = smlald(r12, x[2], *acc);
    *acc = smlald(lr, x[3], *acc);
}

/// The block loops, run on the emulated instructions.
struct Emulated;

/// The loops of `asm.rs`: a block is, twice, eight inputs then each row's
/// step. One row: one block per iteration, the count decremented to zero.
/// Two rows: `unroll` blocks per iteration, `ceil(count / unroll)`
/// iterations, the first entered at block `(-count) mod unroll` (the
/// `TBB`/`TBH` entry of `I8Interleaved` and `SMLALD`; for `I16`'s two
/// blocks, the lone block of an odd count).
fn blocks<A: Acc, const N: usize>(
    rows: [&[u8]; N],
    x: &[i16],
    unroll: usize,
    step: fn(&mut A, &[u8], &mut usize, [u32; 4]),
) -> [A; N] {
    assert!(
        !x.is_empty() && x.len().is_multiple_of(BLOCK),
        "contract: whole blocks"
    );
    let mut acc = [A::ZERO; N];
    let (mut xp, mut wp) = (0usize, [0usize; N]);
    let mut block = |acc: &mut [A; N]| {
        for _ in 0..2 {
            let regs = ldm4(x, &mut xp);
            for ((a, row), p) in acc.iter_mut().zip(rows).zip(&mut wp) {
                step(a, row, p, regs);
            }
        }
    };
    let mut count = x.len() / BLOCK;
    if N == 2 {
        let mut entry = count.wrapping_neg() % unroll;
        let mut iterations = count.div_ceil(unroll);
        while iterations != 0 {
            for _ in entry..unroll {
                block(&mut acc);
            }
            entry = 0;
            iterations -= 1;
        }
    } else {
        loop {
            block(&mut acc);
            count -= 1;
            if count == 0 {
                break;
            }
        }
    }
    for (row, p) in rows.iter().zip(wp) {
        assert_eq!(row.len(), p, "contract: the loop reads each row to its end");
    }
    acc
}

/// The `I8Interleaved` loops: for an odd pair count the last pair against
/// the low pair of its group's word (`i8_last_half!`, by index), then
/// `groups mod 4` single groups (`i8_group!`), then the whole blocks as in
/// [`blocks`].
impl<const N: usize> Blocks<W8I, N> for Emulated {
    unsafe fn run(rows: [&[u8]; N], x: &[i16]) -> [i32; N] {
        assert!(
            !x.is_empty() && x.len().is_multiple_of(2),
            "contract: whole pairs"
        );
        let word = |at: usize| u32::from(x[at] as u16) | (u32::from(x[at + 1] as u16) << 16);
        let mut acc = [0i32; N];
        let mut pairs = x.len() / 2;
        if pairs % 2 == 1 {
            pairs -= 1;
            let xw = word(2 * pairs);
            for (a, row) in acc.iter_mut().zip(rows) {
                let mut at = 2 * pairs;
                *a = smlad(sxtb16(ldr(row, &mut at), 0), xw, *a);
            }
        }
        let groups = pairs / 2;
        let mut wp = [0usize; N];
        for g in 0..groups % 4 {
            let (x01, x23) = (word(4 * g), word(4 * g + 2));
            for ((a, row), at) in acc.iter_mut().zip(rows).zip(&mut wp) {
                let w = ldr(row, at);
                *a = smlad(sxtb16(w, 0), x01, *a);
                *a = smlad(sxtb16(w, 8), x23, *a);
            }
        }
        let done = 4 * (groups % 4);
        if groups >= 4 {
            let rest: [&[u8]; N] = core::array::from_fn(|k| &rows[k][done..4 * groups]);
            let sums = blocks(rest, &x[done..4 * groups], 4, i8_step);
            for (a, s) in acc.iter_mut().zip(sums) {
                *a = a.wrapping_add(s);
            }
        }
        for row in rows {
            assert_eq!(
                row.len(),
                x.len().next_multiple_of(4),
                "contract: the loop reads each row to its end"
            );
        }
        acc
    }
}

impl<const N: usize> Blocks<W16, N> for Emulated {
    unsafe fn run(rows: [&[u8]; N], x: &[i16]) -> [i32; N] {
        blocks(rows, x, 2, i16_step)
    }
}

/// `LDR r, [p], #4` of a row: one little-endian word, advancing `at`.
fn ldr(row: &[u8], at: &mut usize) -> u32 {
    let w = u32::from_le_bytes(row[*at..*at + 4].try_into().unwrap());
    *at += 4;
    w
}

/// The `I16` loops with 64-bit accumulators: `pairs mod 8` single pairs of
/// inputs (`LDR`, one `SMLALD` per row), then the whole blocks as in
/// [`blocks`].
impl<const N: usize> Blocks<W16L, N> for Emulated {
    unsafe fn run(rows: [&[u8]; N], x: &[i16]) -> [i64; N] {
        assert!(
            !x.is_empty() && x.len().is_multiple_of(2),
            "contract: whole pairs"
        );
        let mut acc = [0i64; N];
        let pairs = x.len() / 2 % 8;
        let mut wp = [0usize; N];
        for p in 0..pairs {
            let xw = u32::from(x[2 * p] as u16) | (u32::from(x[2 * p + 1] as u16) << 16);
            for ((a, row), at) in acc.iter_mut().zip(rows).zip(&mut wp) {
                *a = smlald(ldr(row, at), xw, *a);
            }
        }
        let done = 2 * pairs;
        if done < x.len() {
            let rest: [&[u8]; N] = core::array::from_fn(|k| &rows[k][4 * pairs..]);
            let sums = blocks(rest, &x[done..], 8, i16l_step);
            for (a, s) in acc.iter_mut().zip(sums) {
                *a = a.wrapping_add(s);
            }
        } else {
            for (row, p) in rows.iter().zip(wp) {
                assert_eq!(row.len(), p, "contract: the loop reads each row to its end");
            }
        }
        acc
    }
}

#[test]
fn instruction_semantics() {
    // Bytes 01 7F FF 80: (b0, b2) = (1, -1), (b1, b3) = (127, -128).
    assert_eq!(sxtb16(0x80FF_7F01, 0), 0xFFFF_0001);
    assert_eq!(sxtb16(0x80FF_7F01, 8), 0xFF80_007F);
    // (-32768)^2 twice overflows i32: kept modulo 2^32, like the hardware.
    assert_eq!(smlad(0x8000_8000, 0x8000_8000, 0), i32::MIN);
    assert_eq!(smlad(0x0002_FFFF, 0x0003_0005, 10), 10 - 5 + 6);
    // SMLALD keeps both products' 2^31 exactly.
    assert_eq!(smlald(0x8000_8000, 0x8000_8000, 0), 1 << 31);
    assert_eq!(smlald(0x0002_FFFF, 0x0003_0005, -1 << 40), (-1 << 40) + 1);
}

/// `len` bytes starting `misalign` bytes past a word boundary.
fn placed(bytes: &[u8], misalign: usize) -> (Vec<u32>, usize) {
    let mut buf = vec![0u32; (bytes.len() + misalign).div_ceil(4) + 1];
    let dst: &mut [u8] = as_bytes_mut(&mut buf);
    dst[misalign..misalign + bytes.len()].copy_from_slice(bytes);
    (buf, misalign)
}

/// The bytes of a word buffer (word-aligned at index 0).
fn as_bytes_mut(buf: &mut [u32]) -> &mut [u8] {
    // SAFETY: u8 has no alignment or validity requirements and the length
    // covers exactly the words' bytes.
    unsafe { core::slice::from_raw_parts_mut(buf.as_mut_ptr().cast(), buf.len() * 4) }
}

fn as_bytes(buf: &[u32]) -> &[u8] {
    // SAFETY: as in `as_bytes_mut`, shared.
    unsafe { core::slice::from_raw_parts(buf.as_ptr().cast(), buf.len() * 4) }
}

/// One random case: `experts` rows of `in_dim` weights in `format`, inputs,
/// and where each buffer starts relative to a word boundary.
#[derive(Debug, Clone)]
struct Case {
    format: WeightFormat,
    /// 64-bit accumulators (`I16` only).
    wide: bool,
    w: Vec<Vec<i32>>,
    x: Vec<i16>,
    row_misalign: Vec<usize>,
    x_misalign: usize,
}

fn case() -> impl Strategy<Value = Case> {
    (
        prop_oneof![
            Just((WeightFormat::I8Interleaved, false)),
            Just((WeightFormat::I16, false)),
            Just((WeightFormat::I16, true))
        ],
        prop_oneof![Just(1usize), Just(2), Just(4)],
        1usize..=300,
        any::<u64>(),
        prop_oneof![4 => Just(0usize), 1 => 1usize..4],
        prop_oneof![4 => Just(0usize), 1 => Just(1)],
    )
        .prop_map(|((format, wide), experts, in_dim, seed, rmis, xmis)| {
            let mut s = seed | 1;
            let mut next = move || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                s
            };
            let (lo, span) = match format {
                WeightFormat::I16 => (-32768i64, 65536u64),
                _ => (-128, 256),
            };
            let mut edgy = |span: u64, lo: i64| match next() % 8 {
                0 => lo,
                1 => lo + span as i64 - 1,
                _ => lo + (next() % span) as i64,
            };
            let w = (0..experts)
                .map(|_| (0..in_dim).map(|_| edgy(span, lo) as i32).collect())
                .collect();
            let x = (0..in_dim).map(|_| edgy(65536, -32768) as i16).collect();
            let row_misalign = (0..experts)
                .map(|k| if k == 0 { rmis } else { 0 })
                .collect();
            Case {
                format,
                wide,
                w,
                x,
                row_misalign,
                x_misalign: xmis,
            }
        })
}

/// A row in `format`'s storage.
fn encode(row: &[i32], format: WeightFormat) -> Vec<u8> {
    let mut out = vec![0u8; format.row_bytes(row.len())];
    for (j, &v) in row.iter().enumerate() {
        let s = format.position(j);
        match format {
            WeightFormat::I16 => out[2 * s..2 * s + 2].copy_from_slice(&(v as i16).to_le_bytes()),
            _ => out[s] = v as i8 as u8,
        }
    }
    out
}

/// The kernels' dot products for `c`: (Smlad over Emulated, Portable, exact
/// sum, modulo 2^32 for 32-bit accumulators).
fn run(c: &Case) -> (Vec<i64>, Vec<i64>, Vec<i64>) {
    let stored: Vec<_> =
        c.w.iter()
            .zip(&c.row_misalign)
            .map(|(r, &m)| placed(&encode(r, c.format), m))
            .collect();
    let rows: Vec<&[u8]> = stored
        .iter()
        .zip(&c.w)
        .map(|((buf, m), r)| &as_bytes(buf)[*m..*m + c.format.row_bytes(r.len())])
        .collect();
    let xbuf = placed_x(c);
    let x = &xbuf.0[xbuf.1..xbuf.1 + c.x.len()];
    let exact = exact_sums(c, &c.w);
    fn both<K: Kernel>(rows: &[&[u8]], x: &[i16]) -> Vec<i64> {
        match rows.len() {
            1 => K::dot1([rows[0]], x).to_vec(),
            2 => K::dot2([rows[0], rows[1]], x).to_vec(),
            _ => K::dot4([rows[0], rows[1], rows[2], rows[3]], x).to_vec(),
        }
    }
    match c.format {
        WeightFormat::I16 if c.wide => (
            both::<Smlad<W16L, Emulated>>(&rows, x),
            both::<Portable<W16L, i64>>(&rows, x),
            exact,
        ),
        WeightFormat::I16 => (
            both::<Smlad<W16, Emulated>>(&rows, x),
            both::<Portable<W16, i32>>(&rows, x),
            exact,
        ),
        _ => (
            both::<Smlad<W8I, Emulated>>(&rows, x),
            both::<Portable<W8I, i32>>(&rows, x),
            exact,
        ),
    }
}

/// `c.x` in a buffer, starting `c.x_misalign` half-words past a word
/// boundary: (buffer, start).
fn placed_x(c: &Case) -> (Vec<i16>, usize) {
    let mut xbuf = vec![0i16; c.x.len() + 2];
    let off = xbuf.as_ptr() as usize % 4 / 2;
    let start = (off + c.x_misalign) % 2;
    xbuf[start..start + c.x.len()].copy_from_slice(&c.x);
    (xbuf, start)
}

/// The exact dot products of `rows` with `c.x` (modulo 2^32 with 32-bit
/// accumulators).
fn exact_sums(c: &Case, rows: &[Vec<i32>]) -> Vec<i64> {
    rows.iter()
        .map(|r| {
            let s: i64 = r
                .iter()
                .zip(&c.x)
                .map(|(&w, &v)| i64::from(w) * i64::from(v))
                .sum();
            if c.wide {
                s
            } else {
                i64::from(s as i32)
            }
        })
        .collect()
}

/// `matrix_pairs` for `c`'s rows and its first row again (2, 3 or 5
/// rows, so a last odd row too) stored one after another from
/// `c.row_misalign[0]`: (Smlad over Emulated, Portable, exact).
fn run_matrix(c: &Case) -> (Vec<i64>, Vec<i64>, Vec<i64>) {
    let mut w = c.w.clone();
    w.push(c.w[0].clone());
    let rb = c.format.row_bytes(c.x.len());
    let bytes: Vec<u8> = w.iter().flat_map(|r| encode(r, c.format)).collect();
    let (buf, m) = placed(&bytes, c.row_misalign[0]);
    let matrix = &as_bytes(&buf)[m..m + bytes.len()];
    let xbuf = placed_x(c);
    let x = &xbuf.0[xbuf.1..xbuf.1 + c.x.len()];
    /// The pairs through `matrix_pairs` (when its check passes: the
    /// aligned cases), the last odd row through the portable kernel, as
    /// `MatrixKernel::rows` does.
    fn fast<W: Packed>(matrix: &[u8], rb: usize, x: &[i16], n: usize) -> Vec<i64>
    where
        Emulated: Blocks<W, 2>,
    {
        let mut out = vec![[0i64; 2]; n / 2];
        if !matrix_pairs::<W, Emulated>(matrix, rb, x, &mut out) {
            return portable::<Portable<W, W::Sum>>(matrix, rb, x);
        }
        let short = &matrix[..2 * rb * (n / 2) - 1];
        assert!(!matrix_pairs::<W, Emulated>(short, rb, x, &mut out));
        let mut v: Vec<i64> = out.concat();
        if n % 2 == 1 {
            v.push(Portable::<W, W::Sum>::dot1([&matrix[(n - 1) * rb..]], x)[0]);
        }
        v
    }
    fn portable<K: Kernel>(matrix: &[u8], rb: usize, x: &[i16]) -> Vec<i64> {
        matrix
            .chunks_exact(rb)
            .map(|r| K::dot1([r], x)[0])
            .collect()
    }
    let n = w.len();
    let exact = exact_sums(c, &w);
    match c.format {
        WeightFormat::I16 if c.wide => (
            fast::<W16L>(matrix, rb, x, n),
            portable::<Portable<W16L, i64>>(matrix, rb, x),
            exact,
        ),
        WeightFormat::I16 => (
            fast::<W16>(matrix, rb, x, n),
            portable::<Portable<W16, i32>>(matrix, rb, x),
            exact,
        ),
        _ => (
            fast::<W8I>(matrix, rb, x, n),
            portable::<Portable<W8I, i32>>(matrix, rb, x),
            exact,
        ),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// A whole matrix's rows (`matrix_pairs`, the CP factors' path: one
    /// check for the matrix, then the two-row loop on each pair) equal the
    /// portable kernel's and the exact sums, aligned or not; a matrix one
    /// byte short is refused.
    #[test]
    fn smlad_matrix_rows_equal_portable(c in case()) {
        let (fast, portable, exact) = run_matrix(&c);
        prop_assert_eq!(&fast, &portable);
        prop_assert_eq!(&portable, &exact);
    }

    /// The DSP algorithm equals the portable kernel bit for bit (and both
    /// the exact sum, modulo 2^32 with 32-bit accumulators), for every tail
    /// length of the block and every entry into the unrolled loops, one
    /// iteration or several (in_dim 1..=300), 1, 2 and 4 experts, both
    /// accumulator widths of `I16`, full-range weights and inputs,
    /// aligned rows (the block loop) and misaligned ones (the fallback).
    #[test]
    fn smlad_equals_portable(c in case()) {
        let (fast, portable, exact) = run(&c);
        prop_assert_eq!(&fast, &portable);
        prop_assert_eq!(&portable, &exact);
    }
}
