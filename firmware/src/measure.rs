//! What the firmware measures about itself: elapsed SysTick ticks (one tick
//! is 40 instructions under `qemu-system-arm -icount shift=0`, as the MPS2
//! SysTick runs from the 25 MHz system clock and `shift=0` makes each
//! instruction take 1 ns of virtual time), and the stack high-water mark by
//! painting the free stack at boot and finding the deepest overwritten word
//! at the end. Also the per-stage timer the runtime's probe calls
//! ([`StageTimer`]).

use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m::peripheral::{syst::SystClkSource, SCB, SYST};
use cortex_m_rt::exception;
use phasegate::{Mark, Probe};
use phasegate_wire::{StageKind, StageTicks, STAGE_LEN};

/// SysTick's reload value: the full 24-bit range, so it wraps every 2^24
/// ticks (671 million instructions) and the handler counts the wraps.
const RELOAD: u32 = 0x00FF_FFFF;

static WRAPS: AtomicU32 = AtomicU32::new(0);

#[exception]
fn SysTick() {
    WRAPS.fetch_add(1, Ordering::Relaxed);
}

/// Brackets each frame's inference in a QEMU execution trace (`host-sim
/// target --cycles` prices the instructions between two calls): a real call
/// of three instructions outside the timed windows, its symbol unmangled so
/// the trace names it.
#[inline(never)]
#[no_mangle]
pub extern "C" fn phasegate_trace_mark() {
    cortex_m::asm::nop();
}

/// Starts SysTick on the processor clock, counting down from [`RELOAD`] with
/// its wrap interrupt enabled.
pub fn start_ticks(syst: &mut SYST) {
    syst.set_clock_source(SystClkSource::Core);
    syst.set_reload(RELOAD);
    syst.clear_current();
    syst.enable_interrupt();
    syst.enable_counter();
    // The first reload (and its wrap interrupt) comes a tick after
    // enabling; a reading before it would be off by a whole period, so
    // wait for it (the full firmware used to log here first; the inference
    // core calibrates at once).
    while WRAPS.load(Ordering::SeqCst) == 0 && SYST::get_current() == 0 {}
}

/// Ticks since [`start_ticks`], 64-bit.
pub fn now() -> u64 {
    loop {
        let before = WRAPS.load(Ordering::SeqCst);
        let current = SYST::get_current();
        let pending = SCB::is_pendst_pending();
        let after = WRAPS.load(Ordering::SeqCst);
        if before != after {
            continue; // the handler ran in between: read again
        }
        // A wrap whose interrupt has not been taken yet: the counter has
        // just reloaded (it is near the top), count that wrap now.
        let wraps = u64::from(before) + u64::from(pending && current > RELOAD / 2);
        return wraps * (u64::from(RELOAD) + 1) + u64::from(RELOAD - current);
    }
}

/// Ticks between two [`now`] readings, saturated to u32 (2^32 ticks is
/// 172 billion instructions: more than any frame).
pub fn elapsed(from: u64, to: u64) -> u32 {
    u32::try_from(to.saturating_sub(from)).unwrap_or(u32::MAX)
}

/// Iterations of the calibration loop; it executes two instructions per
/// iteration (`subs`, `bne`).
const CALIB_ITERATIONS: u32 = 20_000;
/// Instructions the calibration loop executes.
pub const CALIB_INSTRUCTIONS: u32 = 2 * CALIB_ITERATIONS;

/// Runs a loop of exactly [`CALIB_INSTRUCTIONS`] instructions and returns
/// the ticks it took: 1000 (40 instructions a tick) when QEMU runs with
/// `-icount shift=0`, which is what the host checks before trusting the
/// per-frame figures.
///
/// The loop starts on a tick edge (the counter is polled until it changes,
/// a bounded number of times)
/// and the counter is read in the same assembly block before and after it,
/// so the count is the same whatever the code around it compiles to (at
/// opt-level "z", reading it through [`now`] put it one tick over).
pub fn calibrate() -> u32 {
    let (start, end): (u32, u32);
    // SAFETY: reads SysTick's current-value register (word-aligned MMIO,
    // reads have no side effect) and counts down in registers; no stack.
    unsafe {
        core::arch::asm!(
            // Poll for the edge at most 64 times (a tick is 40 instructions):
            // a counter that does not move must not hang the boot.
            "movs {k}, #64",
            "ldr {c0}, [{cvr}]",
            "1:",
            "ldr {start}, [{cvr}]",
            "cmp {start}, {c0}",
            "bne 3f",
            "subs {k}, {k}, #1",
            "bne 1b",
            "3:",
            "2:",
            "subs {n}, {n}, #1",
            "bne 2b",
            "ldr {end}, [{cvr}]",
            cvr = in(reg) SYST_CVR,
            c0 = out(reg) _,
            k = out(reg) _,
            start = out(reg) start,
            end = out(reg) end,
            n = inout(reg) CALIB_ITERATIONS => _,
            options(nostack, readonly),
        );
    }
    // Counts down and reloads after 0: the difference modulo RELOAD + 1.
    start.wrapping_sub(end) & RELOAD
}

/// SysTick's current-value register (SYST_CVR).
const SYST_CVR: u32 = 0xE000_E018;

// Bounds of the stack, from cortex-m-rt's link.x: it starts (initial SP) at
// `_stack_start`, the end of RAM, and may grow down to `_stack_end`, the end
// of .bss/.uninit.
extern "C" {
    static _stack_start: u32;
    static _stack_end: u32;
}

/// Word written over the free stack at boot.
const PAINT: u32 = 0x5AFE_C0DE;
/// Bytes left unpainted below the painter's own stack pointer.
const MARGIN: usize = 64;

fn stack_bounds() -> (usize, usize) {
    // Only the addresses of the linker symbols are taken (no read).
    (
        core::ptr::addr_of!(_stack_end) as usize,
        core::ptr::addr_of!(_stack_start) as usize,
    )
}

/// Bytes of stack between the end of static RAM and the initial SP.
pub fn stack_size() -> u32 {
    let (bottom, top) = stack_bounds();
    (top - bottom) as u32
}

/// Paints every free stack word below the caller with [`PAINT`].
#[inline(never)]
pub fn paint_stack() {
    let (bottom, _) = stack_bounds();
    let sp = cortex_m::register::msp::read() as usize;
    let mut p = bottom;
    while p + 4 <= sp.saturating_sub(MARGIN) {
        // SAFETY: [bottom, sp - MARGIN) is RAM below the live stack that
        // nothing else uses (no heap, no other task); word aligned.
        unsafe {
            core::ptr::write_volatile(core::ptr::with_exposed_provenance_mut::<u32>(p), PAINT)
        };
        p += 4;
    }
}

/// Deepest stack use since [`paint_stack`], in bytes below the initial SP:
/// the distance from the top to the lowest word no longer holding the paint.
pub fn stack_high_water() -> u32 {
    let (bottom, top) = stack_bounds();
    let mut p = bottom;
    while p < top {
        // SAFETY: reading RAM inside the stack region, word aligned.
        let w = unsafe { core::ptr::read_volatile(core::ptr::with_exposed_provenance::<u32>(p)) };
        if w != PAINT {
            break;
        }
        p += 4;
    }
    (top - p) as u32
}

/// Stages a frame can have: input, gate, gather and op of each node, output.
pub const MAX_STAGES: usize = 2 * phasegate::blob::MAX_NODES + 3;

/// The runtime's [`Probe`]: SysTick ticks of every stage of one frame,
/// kept as the frame's profile record (`wire::StageTicks`, 8 bytes each).
/// Each mark reads the raw 24-bit counter (no wrap handling): a stage
/// longer than 2^24 ticks (671 million instructions) would be misread, far
/// beyond any frame.
pub struct StageTimer {
    last: u32,
    len: usize,
    record: [u8; STAGE_LEN * MAX_STAGES],
}

impl StageTimer {
    /// A timer with no stages.
    pub const fn new() -> Self {
        StageTimer {
            last: 0,
            len: 0,
            record: [0; STAGE_LEN * MAX_STAGES],
        }
    }

    /// Starts a frame: its input stage begins now.
    #[inline(always)]
    pub fn start(&mut self) {
        self.len = 0;
        self.last = SYST::get_current();
    }

    /// Ends the stage `kind` of `node` now; the next one begins. Not
    /// inlined: one call per mark keeps the executor's code small.
    #[inline(never)]
    pub fn close(&mut self, kind: StageKind, node: u8) {
        let now = SYST::get_current();
        // SysTick counts down, modulo 2^24.
        let ticks = self.last.wrapping_sub(now) & RELOAD;
        self.last = now;
        let at = self.len * STAGE_LEN;
        if let Some(d) = self.record.get_mut(at..at + STAGE_LEN) {
            d.copy_from_slice(&StageTicks { kind, node, ticks }.encode());
        }
        self.len += 1;
    }

    /// The frame's profile record; `None` if it had more than
    /// [`MAX_STAGES`] stages.
    pub fn record(&self) -> Option<&[u8]> {
        self.record.get(..self.len * STAGE_LEN)
    }
}

impl Probe for StageTimer {
    #[inline(always)]
    fn mark(&mut self, at: Mark) {
        match at {
            Mark::Start => self.close(StageKind::Input, 0),
            Mark::Gate => self.close(StageKind::Gate, 0),
            Mark::Gathered(i) => self.close(StageKind::Gather, i),
            Mark::Done(i) => self.close(StageKind::Node, i),
        }
    }
}
