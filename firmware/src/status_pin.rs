//! The deadline's status pin on the MPS2-AN386: LED 0 of the FPGA I/O
//! block (`FPGAIO->LED0`, bit 0 of the register at 0x4002_8000, AN386
//! application note section 4.x "FPGA system control"). QEMU's `mps2-an386`
//! machine models this register (`hw/misc/mps2-fpgaio.c`: LED0 reads back
//! what was written, masked to its LEDs), so the firmware reads the level
//! back and reports it with every controller frame: the host sees the pin
//! as the board has it, not as the firmware meant it.

use core::convert::Infallible;

use embedded_hal::digital::{ErrorType, OutputPin};

/// Address of FPGAIO's LED0 register.
const LED0: usize = 0x4002_8000;

/// One LED of FPGAIO's LED0 register, as an `OutputPin`.
pub struct FpgaioLed {
    mask: u32,
}

impl FpgaioLed {
    /// LED `n` (0 or 1 on the AN386).
    pub const fn new(n: u32) -> Self {
        FpgaioLed { mask: 1 << n }
    }

    fn read() -> u32 {
        // SAFETY: LED0 is a 32-bit read/write register of the board's FPGA
        // I/O block, always mapped; reading it has no side effect.
        unsafe { core::ptr::read_volatile(core::ptr::with_exposed_provenance::<u32>(LED0)) }
    }

    fn write(v: u32) {
        // SAFETY: as in `read`; only this pin writes LED0 in this firmware.
        unsafe { core::ptr::write_volatile(core::ptr::with_exposed_provenance_mut::<u32>(LED0), v) }
    }

    /// The LED's level, read back from the register.
    pub fn is_set_high(&self) -> bool {
        Self::read() & self.mask != 0
    }
}

impl ErrorType for FpgaioLed {
    type Error = Infallible;
}

impl OutputPin for FpgaioLed {
    fn set_low(&mut self) -> Result<(), Infallible> {
        Self::write(Self::read() & !self.mask);
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        Self::write(Self::read() | self.mask);
        Ok(())
    }
}
