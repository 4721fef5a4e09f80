//! Cortex-M4 cycle estimates (`host-sim target --cycles`): instructions are
//! not cycles, so the firmware runs once more under QEMU with an execution
//! trace (`-d exec,nochain,in_asm`): every translated block's instructions
//! (QEMU's own disassembly) and every execution of a block, in order. The
//! firmware brackets each frame's inference with a call to
//! `phasegate_trace_mark`, so the executed instructions of each frame are
//! known one by one, with every branch's outcome (the next block's address),
//! and each is priced with the Cortex-M4 Technical Reference Manual's cycle
//! counts (ARM DDI 0439B, table 3-1 and, for the FPU, table 7-1).
//!
//! What the model knows and what it assumes:
//! - ALU, multiply and DSP multiply-accumulate (`MUL`, `MLA`, `SMLAL`,
//!   `SMLAD`, `SMLALD`, ...): 1 cycle; `SDIV`/`UDIV` 2 to 12 (early
//!   termination; 7 in the estimate).
//! - single loads 2 cycles, 1 when the instruction before was a single load
//!   (the TRM's pipelining of neighbouring `LDR`s, and of an `STR` after an
//!   `LDR`; the check that the address does not depend on the loaded
//!   register is not made); single stores 2; `LDRD`/`STRD` 3; `LDM`, `STM`,
//!   `PUSH`, `POP` 1 + registers; `VLDM`/`VSTM`/`VPUSH`/`VPOP` 1 + words.
//! - a taken branch, or any write to the PC, adds the pipeline refill P,
//!   which the TRM gives as 1 to 3: the estimate uses 2 and the range
//!   reports 1 and 3; a branch not taken costs 1.
//! - `IT` 1 cycle (0 in the low bound: it can fold into the instruction
//!   before).
//! - FPU: `VMLA`/`VMLS`/`VFMA` and negated forms 3, `VDIV`/`VSQRT` 14,
//!   `VLDR`/`VSTR` 2, the rest 1.
//! - memory has no wait states (as in QEMU: zero-wait SRAM, or flash behind
//!   an accelerator that always hits). Every data access is counted
//!   (`data_accesses`), so a part's wait states can be added by hand:
//!   W wait states on all data accesses add W x data_accesses cycles.
//! - exception entry and exit are not modelled (no interrupt fires inside
//!   a frame: SysTick wraps every 2^24 ticks).

use std::collections::HashMap;
use std::io::BufRead;
use std::rc::Rc;

use anyhow::{bail, Context, Result};
use serde::Serialize;

/// The firmware's marker function (`firmware/src/measure.rs`), called just
/// before and just after each frame's inference.
pub const MARK_SYMBOL: &str = "phasegate_trace_mark";

/// The QEMU options that write the trace to `path`.
pub fn qemu_trace_args(path: &std::path::Path) -> Vec<std::ffi::OsString> {
    vec![
        "-d".into(),
        "exec,nochain,in_asm".into(),
        "-D".into(),
        path.as_os_str().to_owned(),
    ]
}

/// How an instruction is priced.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Hash, Serialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    /// Data processing, moves, shifts, extends, saturation, packing: 1.
    Alu,
    /// Multiplies and multiply-accumulates, including the DSP ones: 1.
    Multiply,
    /// `SDIV`, `UDIV`: 2 to 12.
    Divide,
    /// Single loads (`LDR`, `LDRB`, `LDRSH`, ...): 2, or 1 pipelined.
    Load,
    /// Single stores: 2, or 1 after a load.
    Store,
    /// `LDRD`, `STRD`, `LDM`, `STM`, `PUSH`, `POP`: 1 + registers.
    Multiple,
    /// Branches (`B`, `BL`, `BX`, `CBZ`, `TBB`, ...): 1 (+ P if taken).
    Branch,
    /// `IT`: 0 or 1.
    It,
    /// FPU data processing and moves: 1.
    Float,
    /// FPU multiply-accumulate: 3.
    FloatMac,
    /// `VDIV`, `VSQRT`: 14.
    FloatDivSqrt,
    /// `VLDR`, `VSTR`: 2; `VLDM`, `VSTM`, `VPUSH`, `VPOP`: 1 + words.
    FloatMemory,
    /// Barriers, system and hint instructions: 1.
    System,
    /// Anything the table does not know: counted as 1, and reported.
    Unknown,
}

impl Class {
    /// Display name in the report.
    pub fn name(self) -> &'static str {
        match self {
            Class::Alu => "ALU",
            Class::Multiply => "multiply / MAC",
            Class::Divide => "divide",
            Class::Load => "load",
            Class::Store => "store",
            Class::Multiple => "load/store pair or multiple",
            Class::Branch => "branch",
            Class::It => "IT",
            Class::Float => "FPU",
            Class::FloatMac => "FPU multiply-accumulate",
            Class::FloatDivSqrt => "FPU divide / sqrt",
            Class::FloatMemory => "FPU load/store",
            Class::System => "system",
            Class::Unknown => "unclassified",
        }
    }
}

/// One decoded instruction of a translated block.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Insn {
    /// Address.
    pub addr: u32,
    /// Length in bytes (2 or 4).
    pub len: u8,
    /// Pricing class.
    pub class: Class,
    /// Registers (words) moved, for [`Class::Multiple`] and
    /// [`Class::FloatMemory`] multiples; 0 otherwise.
    pub words: u8,
    /// Whether it writes the PC (a branch, `POP {.., pc}`, `LDR pc, ..`).
    pub writes_pc: bool,
    /// Whether a branch is conditional (may fall through).
    pub conditional: bool,
}

const CONDS: [&str; 16] = [
    "eq", "ne", "cs", "hs", "cc", "lo", "mi", "pl", "vs", "vc", "hi", "ls", "ge", "lt", "gt", "le",
];

/// Classifies a base mnemonic (lower case, no `.w`/`.n`/`.f32` suffix, no
/// condition).
fn class_of(base: &str) -> Option<Class> {
    const ALU: &[&str] = &[
        "mov", "movs", "mvn", "mvns", "movw", "movt", "add", "adds", "addw", "adc", "adcs", "sub",
        "subs", "subw", "sbc", "sbcs", "rsb", "rsbs", "neg", "negs", "cmp", "cmn", "tst", "teq",
        "and", "ands", "orr", "orrs", "orn", "orns", "eor", "eors", "bic", "bics", "lsl", "lsls",
        "lsr", "lsrs", "asr", "asrs", "ror", "rors", "rrx", "rrxs", "sxtb", "sxth", "uxtb", "uxth",
        "sxtab", "sxtah", "uxtab", "uxtah", "sxtb16", "uxtb16", "sxtab16", "uxtab16", "ubfx",
        "sbfx", "bfi", "bfc", "clz", "rbit", "rev", "rev16", "revsh", "adr", "ssat", "usat",
        "ssat16", "usat16", "qadd", "qsub", "qdadd", "qdsub", "qadd16", "qsub16", "qadd8", "qsub8",
        "sadd16", "ssub16", "sadd8", "ssub8", "uadd16", "usub16", "uadd8", "usub8", "shadd16",
        "shsub16", "uqadd16", "uqsub16", "uqadd8", "uqsub8", "sasx", "ssax", "qasx", "qsax",
        "pkhbt", "pkhtb", "sel", "usad8", "usada8",
    ];
    const MUL: &[&str] = &[
        "mul", "muls", "mla", "mls", "smull", "umull", "smlal", "umlal", "umaal", "smlabb",
        "smlabt", "smlatb", "smlatt", "smlawb", "smlawt", "smulbb", "smulbt", "smultb", "smultt",
        "smulwb", "smulwt", "smlad", "smladx", "smlsd", "smlsdx", "smlald", "smlaldx", "smlsld",
        "smlsldx", "smlalbb", "smlalbt", "smlaltb", "smlaltt", "smuad", "smuadx", "smusd",
        "smusdx", "smmul", "smmulr", "smmla", "smmlar", "smmls", "smmlsr",
    ];
    const LOAD: &[&str] = &[
        "ldr", "ldrb", "ldrh", "ldrsb", "ldrsh", "ldrex", "ldrexb", "ldrexh", "ldrt", "ldrbt",
        "ldrht", "ldrsbt", "ldrsht", "pld", "pli",
    ];
    const STORE: &[&str] = &[
        "str", "strb", "strh", "strex", "strexb", "strexh", "strt", "strbt", "strht",
    ];
    const MULTIPLE: &[&str] = &[
        "ldrd", "strd", "ldm", "ldmia", "ldmfd", "ldmdb", "ldmea", "stm", "stmia", "stmea",
        "stmdb", "stmfd", "push", "pop",
    ];
    const BRANCH: &[&str] = &["b", "bl", "blx", "bx", "cbz", "cbnz", "tbb", "tbh"];
    const FLOAT_MAC: &[&str] = &[
        "vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms",
    ];
    const FLOAT: &[&str] = &[
        "vadd", "vsub", "vmul", "vnmul", "vabs", "vneg", "vcmp", "vcmpe", "vcvt", "vcvtr", "vcvta",
        "vcvtb", "vcvtt", "vmov", "vmrs", "vmsr", "vsel", "vmaxnm", "vminnm", "vrinta", "vrintm",
        "vrintn", "vrintp", "vrintr", "vrintx", "vrintz",
    ];
    const FLOAT_MEM: &[&str] = &[
        "vldr", "vstr", "vldm", "vldmia", "vldmdb", "vstm", "vstmia", "vstmdb", "vpush", "vpop",
    ];
    const SYSTEM: &[&str] = &[
        "nop", "dmb", "dsb", "isb", "mrs", "msr", "cpsid", "cpsie", "svc", "bkpt", "wfi", "wfe",
        "sev", "yield", "udf", "clrex",
    ];
    let tables: [(&[&str], Class); 11] = [
        (ALU, Class::Alu),
        (MUL, Class::Multiply),
        (LOAD, Class::Load),
        (STORE, Class::Store),
        (MULTIPLE, Class::Multiple),
        (BRANCH, Class::Branch),
        (FLOAT_MAC, Class::FloatMac),
        (FLOAT, Class::Float),
        (FLOAT_MEM, Class::FloatMemory),
        (SYSTEM, Class::System),
        (&["sdiv", "udiv"], Class::Divide),
    ];
    if base.starts_with("it") && base.len() <= 5 && base[2..].chars().all(|c| c == 't' || c == 'e')
    {
        return Some(Class::It);
    }
    if base == "vdiv" || base == "vsqrt" {
        return Some(Class::FloatDivSqrt);
    }
    tables
        .iter()
        .find(|(names, _)| names.contains(&base))
        .map(|&(_, c)| c)
}

/// Counts the registers of a register list `{r4, r5, lr}` or `{d8, d9}`, in
/// words (a `d` register is two).
fn list_words(operands: &str) -> u8 {
    let (Some(open), Some(close)) = (operands.find('{'), operands.find('}')) else {
        return 0;
    };
    let mut words = 0u8;
    for item in operands[open + 1..close].split(',') {
        let item = item.trim();
        let per = if item.starts_with('d') { 2 } else { 1 };
        let span = match item.split_once('-') {
            Some((a, b)) => {
                let n = |s: &str| s.trim().get(1..).and_then(|v| v.parse::<u8>().ok());
                match (n(a), n(b)) {
                    (Some(a), Some(b)) if b >= a => b - a + 1,
                    _ => 1,
                }
            }
            None => 1,
        };
        words = words.saturating_add(span.saturating_mul(per));
    }
    words
}

/// Decodes one QEMU `in_asm` line: `0x0000a0b4:  f8d1 3004  ldr.w r3, [r1, #4]`.
pub fn parse_insn(line: &str) -> Option<Insn> {
    let (addr, rest) = line.split_once(':')?;
    let addr = u32::from_str_radix(addr.trim().strip_prefix("0x")?, 16).ok()?;
    let mut fields = rest.split_whitespace().peekable();
    let mut halves = 0u8;
    while let Some(f) = fields.peek() {
        if f.len() == 4 && f.chars().all(|c| c.is_ascii_hexdigit()) && halves < 2 {
            halves += 1;
            fields.next();
        } else {
            break;
        }
    }
    if halves == 0 {
        return None;
    }
    let mnemonic = fields.next()?.to_ascii_lowercase();
    let operands: String = fields.collect::<Vec<_>>().join(" ").to_ascii_lowercase();
    let stem = mnemonic.split('.').next().unwrap_or("");
    // A condition suffix (inside an IT block, or a conditional branch).
    let (base, cond) = match class_of(stem) {
        Some(_) => (stem, false),
        None => match CONDS
            .iter()
            .find_map(|c| stem.strip_suffix(c).filter(|b| class_of(b).is_some()))
        {
            Some(b) => (b, true),
            None => (stem, false),
        },
    };
    let class = class_of(base).unwrap_or(Class::Unknown);
    let list_pc = operands.contains('{') && operands.contains("pc");
    let dest_pc = operands.split(',').next().map(str::trim) == Some("pc");
    let writes_pc = match class {
        Class::Branch => true,
        Class::Multiple => {
            base.starts_with("ld") && base != "ldrd" && list_pc || base == "pop" && list_pc
        }
        Class::Load | Class::Alu => dest_pc,
        _ => false,
    };
    let words = match class {
        Class::Multiple if base == "ldrd" || base == "strd" => 2,
        Class::Multiple => list_words(&operands),
        Class::FloatMemory if operands.contains('{') => list_words(&operands),
        _ => 0,
    };
    let conditional = class == Class::Branch && (cond || base == "cbz" || base == "cbnz");
    Some(Insn {
        addr,
        len: 2 * halves,
        class,
        words,
        writes_pc,
        conditional,
    })
}

/// Pricing parameters: the TRM's ranges, one end or the middle.
#[derive(Clone, Copy, Debug)]
pub struct Pricing {
    /// Pipeline refill after a taken branch (P, 1 to 3).
    pub refill: u64,
    /// `IT` (0 when folded, else 1).
    pub it: u64,
    /// `SDIV`/`UDIV` (2 to 12).
    pub divide: u64,
}

impl Pricing {
    /// The low end of every range.
    pub const LOW: Pricing = Pricing {
        refill: 1,
        it: 0,
        divide: 2,
    };
    /// The estimate.
    pub const TYPICAL: Pricing = Pricing {
        refill: 2,
        it: 1,
        divide: 7,
    };
    /// The high end of every range.
    pub const HIGH: Pricing = Pricing {
        refill: 3,
        it: 1,
        divide: 12,
    };

    /// Cycles of `insn`; `pipelined`: the instruction before was a single
    /// load; `taken`: control went elsewhere than the next instruction.
    pub fn cycles(&self, insn: &Insn, pipelined: bool, taken: bool) -> u64 {
        let refill = if insn.writes_pc && taken {
            self.refill
        } else {
            0
        };
        let words = u64::from(insn.words);
        let base = match insn.class {
            Class::Alu | Class::Multiply | Class::Float | Class::System | Class::Unknown => 1,
            Class::Divide => self.divide,
            Class::Load | Class::Store => {
                if pipelined {
                    1
                } else {
                    2
                }
            }
            Class::Multiple => 1 + words,
            Class::Branch => 1,
            Class::It => self.it,
            Class::FloatMac => 3,
            Class::FloatDivSqrt => 14,
            Class::FloatMemory => {
                if words == 0 {
                    2
                } else {
                    1 + words
                }
            }
        };
        base + refill
    }
}

/// One class's share of a frame.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ClassShare {
    /// Instructions executed.
    pub instructions: u64,
    /// Cycles at [`Pricing::TYPICAL`].
    pub cycles: u64,
}

/// The priced instructions of one bracketed frame.
#[derive(Clone, Debug, Default, Serialize)]
pub struct FrameCycles {
    /// Instructions executed between the marks (the marker excluded).
    pub instructions: u64,
    /// Cycles at [`Pricing::LOW`], [`Pricing::TYPICAL`], [`Pricing::HIGH`].
    pub cycles: [u64; 3],
    /// Taken branches and other PC writes.
    pub taken_branches: u64,
    /// Words read or written by data accesses (each load or store single is
    /// one access).
    pub data_accesses: u64,
    /// Per class, at [`Pricing::TYPICAL`].
    pub mix: std::collections::BTreeMap<Class, ClassShare>,
}

impl FrameCycles {
    fn add(&mut self, insn: &Insn, pipelined: bool, taken: bool) {
        self.instructions += 1;
        let prices = [Pricing::LOW, Pricing::TYPICAL, Pricing::HIGH];
        for (c, p) in self.cycles.iter_mut().zip(prices) {
            *c += p.cycles(insn, pipelined, taken);
        }
        if insn.writes_pc && taken {
            self.taken_branches += 1;
        }
        self.data_accesses += match insn.class {
            Class::Load | Class::Store => 1,
            Class::Multiple => u64::from(insn.words),
            Class::FloatMemory => u64::from(insn.words.max(1)),
            _ => 0,
        };
        let share = self.mix.entry(insn.class).or_default();
        share.instructions += 1;
        share.cycles += Pricing::TYPICAL.cycles(insn, pipelined, taken);
    }
}

/// A block execution whose last instruction's outcome waits for the next
/// block's address.
struct Pending {
    block: Rc<Vec<Insn>>,
    /// Instructions executed (less than the block when QEMU rewound it at
    /// an I/O access).
    executed: usize,
    counted: bool,
}

/// Reads a QEMU trace and prices each bracketed frame.
pub fn price_trace(reader: impl BufRead) -> Result<Vec<FrameCycles>> {
    let mut frames = Vec::new();
    let mut open: Option<FrameCycles> = None;
    let mut by_ptr: HashMap<u64, Rc<Vec<Insn>>> = HashMap::new();
    let mut translated: HashMap<u32, Rc<Vec<Insn>>> = HashMap::new();
    let mut block: Option<Vec<Insn>> = None;
    let mut pending: Option<Pending> = None;
    let mut pipelined = false;

    // Prices the pending block now that the next one's address is known.
    let settle = |pending: &mut Option<Pending>,
                  next_pc: Option<u32>,
                  open: &mut Option<FrameCycles>,
                  pipelined: &mut bool| {
        let Some(p) = pending.take() else { return };
        let Some(frame) = open.as_mut().filter(|_| p.counted) else {
            *pipelined = false;
            return;
        };
        let run = p.block.get(..p.executed).unwrap_or(&p.block);
        for (i, insn) in run.iter().enumerate() {
            let fall = insn.addr.wrapping_add(u32::from(insn.len));
            let taken = if i + 1 == run.len() {
                insn.writes_pc && next_pc.is_some_and(|n| n != fall)
            } else {
                false
            };
            frame.add(insn, *pipelined, taken);
            *pipelined = insn.class == Class::Load;
        }
    };

    for (n, line) in reader.lines().enumerate() {
        let line = line.with_context(|| format!("trace line {}", n + 1))?;
        if line.starts_with("IN:") {
            block = Some(Vec::new());
            continue;
        }
        if let Some(b) = block.as_mut() {
            if let Some(insn) = parse_insn(&line) {
                b.push(insn);
                continue;
            }
            if let Some(first) = b.first() {
                translated.insert(first.addr, Rc::new(std::mem::take(b)));
            }
            block = None;
        }
        if let Some(rest) = line.strip_prefix("Trace ") {
            let (ptr, pc, symbol) = parse_exec(rest)
                .with_context(|| format!("trace line {}: cannot parse {line:?}", n + 1))?;
            settle(&mut pending, Some(pc), &mut open, &mut pipelined);
            if symbol == MARK_SYMBOL {
                match open.take() {
                    Some(f) => frames.push(f),
                    None => open = Some(FrameCycles::default()),
                }
                // The marker itself is not part of the frame.
                pending = None;
                continue;
            }
            let blk = match translated.remove(&pc) {
                Some(b) => {
                    by_ptr.insert(ptr, b.clone());
                    b
                }
                None => match by_ptr.get(&ptr) {
                    Some(b) => b.clone(),
                    None => bail!(
                        "trace line {}: block {pc:#x} runs but was never translated",
                        n + 1
                    ),
                },
            };
            pending = Some(Pending {
                executed: blk.len(),
                block: blk,
                counted: open.is_some(),
            });
        } else if let Some(rest) = line.strip_prefix("Stopped execution of TB chain before ") {
            // Logged but not run: the block runs again and is logged again.
            let pc = rest
                .split('[')
                .nth(1)
                .and_then(|s| s.split(']').next())
                .and_then(|s| u32::from_str_radix(s, 16).ok());
            if pending
                .as_ref()
                .and_then(|p| p.block.first())
                .map(|i| i.addr)
                == pc
            {
                pending = None;
            }
        } else if let Some(rest) =
            line.strip_prefix("cpu_io_recompile: rewound execution of TB to ")
        {
            // The block ran up to the I/O access; it restarts there.
            if let (Some(p), Ok(at)) = (pending.as_mut(), u32::from_str_radix(rest.trim(), 16)) {
                p.executed = p.block.iter().take_while(|i| i.addr != at).count();
            }
        }
    }
    settle(&mut pending, None, &mut open, &mut pipelined);
    Ok(frames)
}

/// `0: 0x7fc260000100 [00800408/00000400/00000110/ff020200] Reset` ->
/// (host pointer, guest pc, symbol).
fn parse_exec(rest: &str) -> Option<(u64, u32, &str)> {
    let (_, rest) = rest.split_once(": ")?;
    let (ptr, rest) = rest.split_once(' ')?;
    let ptr = u64::from_str_radix(ptr.strip_prefix("0x")?, 16).ok()?;
    let inner = rest.strip_prefix('[')?;
    let (fields, symbol) = inner.split_once(']')?;
    let pc = u32::from_str_radix(fields.split('/').nth(1)?, 16).ok()?;
    Some((ptr, pc, symbol.trim()))
}

/// The median frame of a traced run, and the table `host-sim target` prints.
#[derive(Clone, Debug, Serialize)]
pub struct CycleReport {
    /// Frames bracketed in the trace.
    pub frames: usize,
    /// The frame with the median typical cycle count.
    pub median: FrameCycles,
}

impl CycleReport {
    /// The median frame of `frames`; `None` when the trace bracketed none.
    pub fn of(mut frames: Vec<FrameCycles>) -> Option<CycleReport> {
        let n = frames.len();
        frames.sort_by_key(|f| f.cycles[1]);
        let median = frames.get(n / 2)?.clone();
        Some(CycleReport { frames: n, median })
    }

    /// Lines for the report.
    pub fn render(&self, macs: u64) -> String {
        use std::fmt::Write;
        let m = &self.median;
        let [lo, typ, hi] = m.cycles;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "Cortex-M4 cycle estimate (median of {} traced frames; TRM cycle table, zero-wait memory; docs/performance.md):",
            self.frames
        );
        let _ = writeln!(
            s,
            "  {} instructions (trace), {typ} cycles (range {lo} .. {hi}), {:.3} cycles per instruction, {:.3} cycles per MAC",
            m.instructions,
            typ as f64 / m.instructions.max(1) as f64,
            typ as f64 / macs.max(1) as f64
        );
        let _ = writeln!(
            s,
            "  {:.2} ms per frame at 168 MHz ({:.2} .. {:.2}); {} taken branches; {} data accesses (each wait state on every data access adds that many cycles)",
            typ as f64 / 168e3,
            lo as f64 / 168e3,
            hi as f64 / 168e3,
            m.taken_branches,
            m.data_accesses
        );
        let _ = writeln!(s, "  | class | instructions | cycles | share of cycles |");
        let _ = writeln!(s, "  |---|---|---|---|");
        let mut rows: Vec<_> = m.mix.iter().collect();
        rows.sort_by_key(|(_, v)| std::cmp::Reverse(v.cycles));
        for (class, share) in rows {
            let _ = writeln!(
                s,
                "  | {} | {} | {} | {:.1} % |",
                class.name(),
                share.instructions,
                share.cycles,
                100.0 * share.cycles as f64 / typ.max(1) as f64
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn insn(line: &str) -> Insn {
        parse_insn(line).unwrap_or_else(|| panic!("{line}"))
    }

    #[test]
    fn qemu_disassembly_lines_decode_to_their_classes() {
        let i = insn("0x0000a0b4:  f8d1 3004  ldr.w    r3, [r1, #4]");
        assert_eq!((i.addr, i.len, i.class), (0xa0b4, 4, Class::Load));
        assert_eq!(
            insn("0x00000408:  2200       movs     r2, #0").class,
            Class::Alu
        );
        assert_eq!(
            insn("0x10:  fb22 0c03  smlad    ip, r2, r3, ip").class,
            Class::Multiply
        );
        assert_eq!(insn("0x10:  fa2f f283  sxtb16   r2, r3").class, Class::Alu);
        let b = insn("0x0000040c:  d001       beq      #0x412");
        assert_eq!(
            (b.class, b.conditional, b.writes_pc),
            (Class::Branch, true, true)
        );
        let bls = insn("0x0000040c:  d901       bls      #0x412");
        assert!(bls.conditional, "bls is B.LS, not BL + S");
        let bl = insn("0x00000400:  f004 ff96  bl       #0x5330");
        assert_eq!((bl.class, bl.conditional), (Class::Branch, false));
        let pop = insn("0x00005334:  bd80       pop      {r7, pc}");
        assert_eq!(
            (pop.class, pop.words, pop.writes_pc),
            (Class::Multiple, 2, true)
        );
        let push = insn("0x00005330:  b580       push     {r4, r5, r6, r7, lr}");
        assert_eq!((push.words, push.writes_pc), (5, false));
        assert_eq!(insn("0x10:  e9d1 2300  ldrd     r2, r3, [r1]").words, 2);
        let vpush = insn("0x10:  ed2d 8b04  vpush    {d8, d9}");
        assert_eq!((vpush.class, vpush.words), (Class::FloatMemory, 4));
        assert_eq!(insn("0x10:  bf08       it       eq").class, Class::It);
        assert_eq!(insn("0x10:  bf0c       ite      eq").class, Class::It);
        let moveq = insn("0x10:  2001       moveq    r0, #1");
        assert_eq!((moveq.class, moveq.writes_pc), (Class::Alu, false));
        assert_eq!(
            insn("0x10:  ee20 0a01  vmul.f32 s0, s0, s2").class,
            Class::Float
        );
        assert_eq!(
            insn("0x10:  ee00 0a01  vmla.f32 s0, s0, s2").class,
            Class::FloatMac
        );
        assert_eq!(
            insn("0x10:  eeb1 0ac0  vsqrt.f32 s0, s0").class,
            Class::FloatDivSqrt
        );
        assert_eq!(
            insn("0x10:  fb90 f0f1  sdiv     r0, r0, r1").class,
            Class::Divide
        );
        let ldr_pc = insn("0x10:  f8df f004  ldr.w    pc, [pc, #4]");
        assert!(ldr_pc.writes_pc);
        assert_eq!(insn("0x10:  4770       bx       lr").class, Class::Branch);
        assert!(parse_insn("Trace 0: 0x7f [0/400/0/0] Reset").is_none());
    }

    #[test]
    fn the_cycle_table_follows_the_trm() {
        let p = Pricing::TYPICAL;
        let ldr = insn("0x10:  6808       ldr      r0, [r1]");
        assert_eq!(p.cycles(&ldr, false, false), 2);
        assert_eq!(
            p.cycles(&ldr, true, false),
            1,
            "neighbouring loads pipeline"
        );
        let b = insn("0x10:  d001       bne      #0x16");
        assert_eq!(p.cycles(&b, false, false), 1, "not taken");
        assert_eq!(p.cycles(&b, false, true), 3, "1 + P");
        assert_eq!(Pricing::LOW.cycles(&b, false, true), 2);
        assert_eq!(Pricing::HIGH.cycles(&b, false, true), 4);
        let pop = insn("0x10:  bdf0       pop      {r4, r5, r6, r7, pc}");
        assert_eq!(p.cycles(&pop, false, true), 1 + 5 + 2, "1 + N + P");
        let ldrd = insn("0x10:  e9d1 2300  ldrd     r2, r3, [r1]");
        assert_eq!(p.cycles(&ldrd, false, false), 3);
        let smlad = insn("0x10:  fb22 0c03  smlad    ip, r2, r3, ip");
        assert_eq!(p.cycles(&smlad, false, false), 1);
    }

    /// A hand-made trace: a marker, a 3-instruction loop block run twice
    /// (taken, then falling through), a block cut short by an I/O rewind,
    /// a logged-but-stopped entry, and the closing marker.
    #[test]
    fn a_trace_is_priced_between_the_marks() {
        let trace = "\
----------------
IN: phasegate_trace_mark
0x00000100:  bf00       nop
0x00000102:  4770       bx       lr

Trace 0: 0x7f0000000100 [00800408/00000100/00000110/ff020200] phasegate_trace_mark
----------------
IN: kernel
0x00000200:  6808       ldr      r0, [r1]
0x00000202:  684a       ldr      r2, [r1, #4]
0x00000204:  3901       subs     r1, #1
0x00000206:  d1fb       bne      #0x200

Trace 0: 0x7f0000000200 [00800408/00000200/00000110/ff020200] kernel
Trace 0: 0x7f0000000200 [00800408/00000200/00000110/ff020200] kernel
Stopped execution of TB chain before 0x7f0000000200 [00000200] kernel
Trace 0: 0x7f0000000200 [00800408/00000200/00000110/ff020200] kernel
----------------
IN: io
0x00000208:  2000       movs     r0, #0
0x0000020a:  6808       ldr      r0, [r1]
0x0000020c:  2001       movs     r0, #1

Trace 0: 0x7f0000000300 [00800408/00000208/00000110/ff020200] io
cpu_io_recompile: rewound execution of TB to 0000020a
----------------
IN: io
0x0000020a:  6808       ldr      r0, [r1]
0x0000020c:  2001       movs     r0, #1

Trace 0: 0x7f0000000400 [00800408/0000020a/00000110/ff020200] io
Trace 0: 0x7f0000000100 [00800408/00000100/00000110/ff020200] phasegate_trace_mark
Trace 0: 0x7f0000000200 [00800408/00000200/00000110/ff020200] kernel
";
        let frames = price_trace(std::io::Cursor::new(trace)).unwrap();
        assert_eq!(
            frames.len(),
            1,
            "the block after the closing mark is outside"
        );
        let f = &frames[0];
        // loop twice (4 + 4), movs, then ldr + movs after the rewind.
        assert_eq!(f.instructions, 11);
        // First pass: ldr 2, ldr 1 (pipelined), subs 1, bne taken 3 = 7;
        // second: 2 + 1 + 1 + 1 (falls through) = 5; movs 1; ldr 2, movs 1.
        assert_eq!(f.cycles[1], 7 + 5 + 1 + 2 + 1);
        assert_eq!(f.taken_branches, 1);
        assert_eq!(f.data_accesses, 5);
        assert_eq!(f.mix[&Class::Load].instructions, 5);
    }

    #[test]
    fn a_block_that_was_never_translated_is_an_error() {
        let trace = "Trace 0: 0x7f0000000100 [00800408/00000100/00000110/ff020200] x\n";
        let e = price_trace(std::io::Cursor::new(trace)).unwrap_err();
        assert!(e.to_string().contains("never translated"), "{e}");
    }
}
