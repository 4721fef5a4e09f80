//! The block loops in Thumb-2 assembly. Registers are fixed because `LDM`
//! needs its list in ascending order: `r2..r5` eight inputs (`LDM`), `r12`,
//! `lr` two weight words (`LDRD`), `r0`, `r1` the accumulators, `r8`, `r9`
//! the weight pointers, `r10` the input pointer, `r11` the count. A
//! two-row `I8Interleaved` loop needs a thirteenth register for the second
//! half of a word: `r6`, which Rust reserves for LLVM's base pointer, so the
//! loop saves and restores it on the stack and never names it as an operand.
//! The two-row `SMLALD` loop (`I16`, 64-bit accumulators) keeps them in
//! `r0:r1` and `r2:r3` and reads four inputs at a time into `r4`, `r5`.
//! Instruction counts per block of 16 inputs: `I8Interleaved` 2 rows 38
//! (32 MACs) plus the loop's 2 per four blocks, 1 row 22 (loop included);
//! `I16` 2 rows 26 (`SMLAD`) plus 1 per two blocks, `SMLALD` 2 rows 28 plus
//! 2 per eight blocks; 1 row 16. The loops a 512-wide layer spends its time
//! in are unrolled that far because each unrolled block takes a fixed cost
//! off every row (the real PFNN's middle layer: 1.407 -> 1.396 instructions
//! per MAC for int8, 1.120 -> 1.097 for int16, for about 500 B of `.text`).
//! A block count that is not a multiple of the unrolling enters the first
//! iteration part-way, through a `TBB`/`TBH` table (Duff's device): six
//! instructions per call whatever the count, no extra copies of the block.
//! The `I16` two-row loop runs two blocks per iteration after one lone
//! block when the count is odd (`lsrs` leaves the halved count's zero flag
//! for `beq`; the block sets no flags). The
//! `I8Interleaved` and `SMLALD` loops count pairs of inputs in `r11` and
//! take the odd ones before the blocks: a last half group and single groups
//! of four (`I8Interleaved`), single pairs (`SMLALD`).

use super::{Blocks, BLOCK, W16, W16L, W8I};
use core::arch::asm;

/// The block loops of the target.
pub(in crate::ops::dense) struct Asm;

/// One word `$w` of four `I8Interleaved` weights against the input pairs
/// `$x0` (its low pair: `SXTB16` into `$t`) and `$x1` (its high pair:
/// `SXTB16 ROR 8`, in place), multiplied into `$acc`.
macro_rules! i8_word {
    ($acc:literal, $w:literal, $t:literal, $x0:literal, $x1:literal) => {
        concat!(
            "sxtb16 ",
            $t,
            ", ",
            $w,
            "\n",
            "smlad ",
            $acc,
            ", ",
            $t,
            ", ",
            $x0,
            ", ",
            $acc,
            "\n",
            "sxtb16 ",
            $w,
            ", ",
            $w,
            ", ror #8\n",
            "smlad ",
            $acc,
            ", ",
            $w,
            ", ",
            $x1,
            ", ",
            $acc,
            "\n",
        )
    };
}

/// Eight inputs of one `I8Interleaved` row: two words of four weights,
/// each split into its two pairs and multiplied into `$acc` (`$t` scratch).
macro_rules! i8_step {
    ($acc:literal, $ptr:literal, $t:literal) => {
        concat!(
            "ldrd r12, lr, [",
            $ptr,
            "], #8\n",
            i8_word!($acc, "r12", $t, "r2", "r3"),
            i8_word!($acc, "lr", $t, "r4", "r5"),
        )
    };
}

/// Eight inputs of one `I16` row: four words of two weights.
macro_rules! i16_step {
    ($acc:literal, $ptr:literal) => {
        concat!(
            "ldrd r12, lr, [",
            $ptr,
            "], #8\n",
            "smlad ",
            $acc,
            ", r12, r2, ",
            $acc,
            "\n",
            "smlad ",
            $acc,
            ", lr, r3, ",
            $acc,
            "\n",
            "ldrd r12, lr, [",
            $ptr,
            "], #8\n",
            "smlad ",
            $acc,
            ", r12, r4, ",
            $acc,
            "\n",
            "smlad ",
            $acc,
            ", lr, r5, ",
            $acc,
            "\n",
        )
    };
}

/// One block of two rows of `I8Interleaved`.
macro_rules! i8_block2 {
    () => {
        concat!(
            load_x!(),
            "\n",
            i8_step!("r0", "r8", "r6"),
            i8_step!("r1", "r9", "r6"),
            load_x!(),
            "\n",
            i8_step!("r0", "r8", "r6"),
            i8_step!("r1", "r9", "r6"),
        )
    };
}

/// One block of two rows of `I16`.
macro_rules! i16_block2 {
    () => {
        concat!(
            load_x!(),
            "\n",
            i16_step!("r0", "r8"),
            i16_step!("r1", "r9"),
            load_x!(),
            "\n",
            i16_step!("r0", "r8"),
            i16_step!("r1", "r9"),
        )
    };
}

/// Four inputs of two `I16` rows into 64-bit accumulators `r0:r1` and
/// `r2:r3`: one `LDRD` of inputs (`r4`, `r5`) shared by both rows, one of
/// weights per row (`r12`, `lr`), two `SMLALD`s per row.
macro_rules! i16l_step2 {
    () => {
        concat!(
            "ldrd r4, r5, [r10], #8\n",
            "ldrd r12, lr, [r8], #8\n",
            "smlald r0, r1, r12, r4\n",
            "smlald r0, r1, lr, r5\n",
            "ldrd r12, lr, [r9], #8\n",
            "smlald r2, r3, r12, r4\n",
            "smlald r2, r3, lr, r5\n",
        )
    };
}

/// One block (16 inputs) of two `I16` rows, 64-bit accumulators.
macro_rules! i16l_block2 {
    () => {
        concat!(i16l_step2!(), i16l_step2!(), i16l_step2!(), i16l_step2!())
    };
}

/// Eight inputs (`r2..r5`) of one `I16` row into the 64-bit accumulator
/// `r0:r1`.
macro_rules! i16l_step1 {
    () => {
        concat!(
            "ldrd r12, lr, [r8], #8\n",
            "smlald r0, r1, r12, r2\n",
            "smlald r0, r1, lr, r3\n",
            "ldrd r12, lr, [r8], #8\n",
            "smlald r0, r1, r12, r4\n",
            "smlald r0, r1, lr, r5\n",
        )
    };
}

/// When the pair count `r11` is odd, the last pair of inputs (`r2`) against
/// the low pair of its group's word in each row (`i8_half!`: `SXTB16`;
/// slots 0 and 2 hold its two weights, slots 1 and 3 padding), read by
/// index before the pointers move; `r11` becomes even.
macro_rules! i8_last_half {
    ($($half:ident ! ($($arg:tt)*)),*) => {
        concat!(
            "tst r11, #1\n",
            "beq 6f\n",
            "sub r11, r11, #1\n",
            "ldr r2, [r10, r11, lsl #2]\n",
            $($half!($($arg)*),)*
            "6:\n",
        )
    };
}

/// The last half group of one row (see `i8_last_half!`).
macro_rules! i8_half {
    ($acc:literal, $ptr:literal) => {
        concat!(
            "ldr r12, [",
            $ptr,
            ", r11, lsl #1]\n",
            "sxtb16 r12, r12\n",
            "smlad ",
            $acc,
            ", r12, r2, ",
            $acc,
            "\n",
        )
    };
}

/// Four inputs (`r2`, `r3`) of one `I8Interleaved` row: one word of
/// weights, split into its two pairs.
macro_rules! i8_group {
    ($acc:literal, $ptr:literal) => {
        concat!(
            "ldr r12, [",
            $ptr,
            "], #4\n",
            i8_word!($acc, "r12", "lr", "r2", "r3"),
        )
    };
}

/// The next eight inputs into `r2..r5`.
macro_rules! load_x {
    () => {
        "ldm r10!, {{r2, r3, r4, r5}}"
    };
}

impl Blocks<W8I, 1> for Asm {
    unsafe fn run(rows: [&[u8]; 1], x: &[i16]) -> [i32; 1] {
        let mut a0 = 0i32;
        // SAFETY: the caller's contract: `x.len() / BLOCK >= 1` blocks of
        // 16 inputs (32 bytes) and 16 weights (16 bytes) each, word-aligned
        // (`LDM`, `LDRD`); only those are read. Registers as in the module
        // docs; the flags are clobbered (no `preserves_flags`).
        unsafe {
            asm!(
                i8_last_half!(i8_half!("r0", "r8")),
                "lsrs r11, r11, #1",
                "1:",
                "tst r11, #3",
                "beq 4f",
                "ldrd r2, r3, [r10], #8",
                i8_group!("r0", "r8"),
                "sub r11, r11, #1",
                "b 1b",
                "4:",
                "lsrs r11, r11, #2",
                "beq 5f",
                "2:",
                load_x!(),
                i8_step!("r0", "r8", "r1"),
                load_x!(),
                i8_step!("r0", "r8", "r1"),
                "subs r11, r11, #1",
                "bne 2b",
                "5:",
                inout("r0") a0,
                out("r1") _,
                inout("r8") rows[0].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / 2 => _,
                out("r2") _, out("r3") _, out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
                options(readonly, nostack),
            );
        }
        [a0]
    }
}

impl Blocks<W8I, 2> for Asm {
    // Not inlined: `pass` and `quad` share one copy (`.text`).
    #[inline(never)]
    unsafe fn run(rows: [&[u8]; 2], x: &[i16]) -> [i32; 2] {
        let (mut a0, mut a1) = (0i32, 0i32);
        // SAFETY: as for one row, for both rows; `r6` is pushed and popped
        // around the loop (hence no `nostack`), so it is unchanged on exit.
        unsafe {
            asm!(
                "push {{r6}}",
                i8_last_half!(i8_half!("r0", "r8"), i8_half!("r1", "r9")),
                "lsrs r11, r11, #1",
                "1:",
                "tst r11, #3",
                "beq 4f",
                "ldrd r2, r3, [r10], #8",
                i8_group!("r0", "r8"),
                i8_group!("r1", "r9"),
                "sub r11, r11, #1",
                "b 1b",
                "4:",
                "lsrs r11, r11, #2",
                "beq 5f",
                // `b` blocks: `ceil(b / 4)` iterations, the first entered at
                // block `(-b) mod 4` of the four (Duff's device, `TBB`).
                "rsb r12, r11, #0",
                "and r12, r12, #3",
                "adds r11, r11, #3",
                "lsrs r11, r11, #2",
                "tbb [pc, r12]",
                "0:",
                ".byte (20f - 0b) / 2",
                ".byte (21f - 0b) / 2",
                ".byte (22f - 0b) / 2",
                ".byte (23f - 0b) / 2",
                "20:",
                i8_block2!(),
                "21:",
                i8_block2!(),
                "22:",
                i8_block2!(),
                "23:",
                i8_block2!(),
                "subs r11, r11, #1",
                "bne 20b",
                "5:",
                "pop {{r6}}",
                inout("r0") a0,
                inout("r1") a1,
                inout("r8") rows[0].as_ptr() => _,
                inout("r9") rows[1].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / 2 => _,
                out("r2") _, out("r3") _, out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
            );
        }
        [a0, a1]
    }
}

impl Blocks<W16, 1> for Asm {
    unsafe fn run(rows: [&[u8]; 1], x: &[i16]) -> [i32; 1] {
        let mut a0 = 0i32;
        // SAFETY: as for `I8Interleaved`, with 32 weight bytes per block.
        unsafe {
            asm!(
                "2:",
                load_x!(),
                i16_step!("r0", "r8"),
                load_x!(),
                i16_step!("r0", "r8"),
                "subs r11, r11, #1",
                "bne 2b",
                inout("r0") a0,
                inout("r8") rows[0].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / BLOCK => _,
                out("r2") _, out("r3") _, out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
                options(readonly, nostack),
            );
        }
        [a0]
    }
}

impl Blocks<W16, 2> for Asm {
    // Not inlined: `pass` and `quad` share one copy (`.text`).
    #[inline(never)]
    unsafe fn run(rows: [&[u8]; 2], x: &[i16]) -> [i32; 2] {
        let (mut a0, mut a1) = (0i32, 0i32);
        // SAFETY: as for one row, for both rows.
        unsafe {
            asm!(
                "lsrs r11, r11, #1",
                "bcc 3f",
                i16_block2!(),
                "3:",
                "beq 5f",
                "2:",
                i16_block2!(),
                i16_block2!(),
                "subs r11, r11, #1",
                "bne 2b",
                "5:",
                inout("r0") a0,
                inout("r1") a1,
                inout("r8") rows[0].as_ptr() => _,
                inout("r9") rows[1].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / BLOCK => _,
                out("r2") _, out("r3") _, out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
                options(readonly, nostack),
            );
        }
        [a0, a1]
    }
}

/// A 64-bit accumulator from its two halves (`RdLo`, `RdHi` of `SMLALD`).
fn wide(lo: u32, hi: u32) -> i64 {
    ((u64::from(hi) << 32) | u64::from(lo)) as i64
}

impl Blocks<W16L, 1> for Asm {
    unsafe fn run(rows: [&[u8]; 1], x: &[i16]) -> [i64; 1] {
        let (lo, hi): (u32, u32);
        // SAFETY: the caller's contract: `x.len() / 2 >= 1` pairs of inputs
        // (4 bytes) and weights (4 bytes), word-aligned (`LDM`, `LDRD`);
        // only those are read: `pairs mod 8` single pairs, then the blocks
        // (`lsrs` by 3: the block count, zero flag when there is none).
        // `r0:r1` is the accumulator.
        unsafe {
            asm!(
                "1:",
                "tst r11, #7",
                "beq 4f",
                "ldr r2, [r10], #4",
                "ldr r12, [r8], #4",
                "smlald r0, r1, r12, r2",
                "sub r11, r11, #1",
                "b 1b",
                "4:",
                "lsrs r11, r11, #3",
                "beq 5f",
                "2:",
                load_x!(),
                i16l_step1!(),
                load_x!(),
                i16l_step1!(),
                "subs r11, r11, #1",
                "bne 2b",
                "5:",
                inout("r0") 0u32 => lo,
                inout("r1") 0u32 => hi,
                inout("r8") rows[0].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / 2 => _,
                out("r2") _, out("r3") _, out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
                options(readonly, nostack),
            );
        }
        [wide(lo, hi)]
    }
}

impl Blocks<W16L, 2> for Asm {
    // Not inlined: `pass` and `quad` share one copy (`.text`).
    #[inline(never)]
    unsafe fn run(rows: [&[u8]; 2], x: &[i16]) -> [i64; 2] {
        let (lo0, hi0, lo1, hi1): (u32, u32, u32, u32);
        // SAFETY: as for one row, for both rows; `r0:r1` and `r2:r3` are the
        // accumulators, inputs come four at a time by `LDRD` (`r4`, `r5`).
        // After the single pairs, `lsrs` by 4 leaves the halved block count,
        // the odd block in the carry and the zero flag as in `I16`.
        unsafe {
            asm!(
                "1:",
                "tst r11, #7",
                "beq 4f",
                "ldr r4, [r10], #4",
                "ldr r12, [r8], #4",
                "smlald r0, r1, r12, r4",
                "ldr r12, [r9], #4",
                "smlald r2, r3, r12, r4",
                "sub r11, r11, #1",
                "b 1b",
                "4:",
                "lsrs r11, r11, #3",
                "beq 5f",
                // `b` blocks: `ceil(b / 8)` iterations, the first entered at
                // block `(-b) mod 8` of the eight (`TBH`: the offsets pass 255).
                "rsb r12, r11, #0",
                "and r12, r12, #7",
                "adds r11, r11, #7",
                "lsrs r11, r11, #3",
                "tbh [pc, r12, lsl #1]",
                "0:",
                ".hword (20f - 0b) / 2",
                ".hword (21f - 0b) / 2",
                ".hword (22f - 0b) / 2",
                ".hword (23f - 0b) / 2",
                ".hword (24f - 0b) / 2",
                ".hword (25f - 0b) / 2",
                ".hword (26f - 0b) / 2",
                ".hword (27f - 0b) / 2",
                "20:",
                i16l_block2!(),
                "21:",
                i16l_block2!(),
                "22:",
                i16l_block2!(),
                "23:",
                i16l_block2!(),
                "24:",
                i16l_block2!(),
                "25:",
                i16l_block2!(),
                "26:",
                i16l_block2!(),
                "27:",
                i16l_block2!(),
                "subs r11, r11, #1",
                "bne 20b",
                "5:",
                inout("r0") 0u32 => lo0,
                inout("r1") 0u32 => hi0,
                inout("r2") 0u32 => lo1,
                inout("r3") 0u32 => hi1,
                inout("r8") rows[0].as_ptr() => _,
                inout("r9") rows[1].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / 2 => _,
                out("r4") _, out("r5") _,
                out("r12") _, out("lr") _,
                options(readonly, nostack),
            );
        }
        [wide(lo0, hi0), wide(lo1, hi1)]
    }
}
