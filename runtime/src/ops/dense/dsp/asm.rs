//! The block loops in Thumb-2 assembly. Registers are fixed because `LDM`
//! needs its list in ascending order: `r2..r5` eight inputs (`LDM`), `r12`,
//! `lr` two weight words (`LDRD`), `r0`, `r1` the accumulators, `r8`, `r9`
//! the weight pointers, `r10` the input pointer, `r11` the block count. A
//! two-row `I8Interleaved` loop needs a thirteenth register for the second
//! half of a word: `r6`, which Rust reserves for LLVM's base pointer, so the
//! loop saves and restores it on the stack and never names it as an operand.
//! Instruction counts per block of 16 inputs: `I8Interleaved` 2 rows 38
//! (32 MACs) plus the loop's 2 per two blocks, 1 row 22 (loop included);
//! `I16` 2 rows 26 plus 1, 1 row 16. The two-row loops run two blocks per
//! iteration, after one lone block when the count is odd (`lsrs` leaves
//! the halved count's zero flag for `beq`; the block sets no flags).

use super::{Blocks, BLOCK, W16, W8I};
use core::arch::asm;

/// The block loops of the target.
pub(in crate::ops::dense) struct Asm;

/// Eight inputs of one `I8Interleaved` row: two words of four weights,
/// each split into its two pairs and multiplied into `$acc` (`$t` scratch).
macro_rules! i8_step {
    ($acc:literal, $ptr:literal, $t:literal) => {
        concat!(
            "ldrd r12, lr, [",
            $ptr,
            "], #8\n",
            "sxtb16 ",
            $t,
            ", r12\n",
            "smlad ",
            $acc,
            ", ",
            $t,
            ", r2, ",
            $acc,
            "\n",
            "sxtb16 r12, r12, ror #8\n",
            "smlad ",
            $acc,
            ", r12, r3, ",
            $acc,
            "\n",
            "sxtb16 ",
            $t,
            ", lr\n",
            "smlad ",
            $acc,
            ", ",
            $t,
            ", r4, ",
            $acc,
            "\n",
            "sxtb16 lr, lr, ror #8\n",
            "smlad ",
            $acc,
            ", lr, r5, ",
            $acc,
            "\n",
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
                "2:",
                load_x!(),
                i8_step!("r0", "r8", "r1"),
                load_x!(),
                i8_step!("r0", "r8", "r1"),
                "subs r11, r11, #1",
                "bne 2b",
                inout("r0") a0,
                out("r1") _,
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

impl Blocks<W8I, 2> for Asm {
    unsafe fn run(rows: [&[u8]; 2], x: &[i16]) -> [i32; 2] {
        let (mut a0, mut a1) = (0i32, 0i32);
        // SAFETY: as for one row, for both rows; `r6` is pushed and popped
        // around the loop (hence no `nostack`), so it is unchanged on exit.
        unsafe {
            asm!(
                "push {{r6}}",
                "lsrs r11, r11, #1",
                "bcc 3f",
                i8_block2!(),
                "3:",
                "beq 5f",
                "2:",
                i8_block2!(),
                i8_block2!(),
                "subs r11, r11, #1",
                "bne 2b",
                "5:",
                "pop {{r6}}",
                inout("r0") a0,
                inout("r1") a1,
                inout("r8") rows[0].as_ptr() => _,
                inout("r9") rows[1].as_ptr() => _,
                inout("r10") x.as_ptr() => _,
                inout("r11") x.len() / BLOCK => _,
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
