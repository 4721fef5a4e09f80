//! Linker-defined flash and RAM regions (memory.x) as byte slices, shared
//! by the full firmware and the inference core.

/// A linker-defined region as a byte slice.
///
/// # Safety
/// `[start, end)` must be memory that nothing writes while the slice lives.
pub unsafe fn region(start: *const u8, end: *const u8) -> &'static [u8] {
    let (s, e) = (start as usize, end as usize);
    // SAFETY: caller's contract; the regions are reserved in memory.x and the
    // firmware never writes them (the QEMU loader fills them before reset).
    unsafe {
        core::slice::from_raw_parts(
            core::ptr::with_exposed_provenance::<u8>(s),
            e.saturating_sub(s),
        )
    }
}

/// The region that holds the model blob: `model` (MODEL), unless it does
/// not start with the blob magic and `big` (BIGMODEL, memory.x) does.
#[allow(dead_code, reason = "the inference core reads MODEL only")]
pub fn model_region(model: &'static [u8], big: &'static [u8]) -> &'static [u8] {
    let magic = &phasegate::blob::MAGIC[..];
    if !model.starts_with(magic) && big.starts_with(magic) {
        big
    } else {
        model
    }
}
