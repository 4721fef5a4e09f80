//! [`Staging`]: the frame's input and output buffers, shared by the
//! firmware binaries.

/// Capacity (elements) of the staging buffers: the real PFNN has 342 inputs
/// and 311 outputs.
pub const W: usize = 512;

/// One frame's inputs and outputs, as floats and quantised, and its output
/// record.
pub struct Staging {
    pub inputs: [f32; W],
    pub inputs_q: [i16; W],
    pub outputs_q: [i16; W],
    pub outputs: [f32; W],
    pub record: [u8; 8 + 6 * W],
}

impl Staging {
    /// All zero: a constant, so a `static` holding it starts in `.bss` and is
    /// never built on the stack and copied (which a runtime initialiser is
    /// at opt-level "z").
    pub const ZERO: Staging = Staging {
        inputs: [0.0; W],
        inputs_q: [0; W],
        outputs_q: [0; W],
        outputs: [0.0; W],
        record: [0; 8 + 6 * W],
    };
}
