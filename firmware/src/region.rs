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
