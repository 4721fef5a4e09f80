//! Sizes computed from untrusted input, checked.
//!
//! Every reader of a file the tools can be handed (`.npy`, `.npz`,
//! `.safetensors`, PFNN `.bin` directories, graph descriptions) takes its
//! element and byte counts from here, so a header that declares a shape
//! whose element count overflows is refused in one place instead of being
//! wrapped to a small number (an empty array that a later slice index
//! panics on). The parser modules carry
//! `#![deny(clippy::arithmetic_side_effects)]`, so an unchecked `+`, `-`
//! or `*` on integers there fails `cargo clippy -D warnings` (CI); the test
//! `parser_modules_deny_unchecked_arithmetic` keeps the attribute on them.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{anyhow, Result};

/// The number of elements of an array of `shape` (the product of its
/// dimensions), or `None` if it does not fit a `usize`.
pub fn element_count(shape: &[u64]) -> Option<usize> {
    shape
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(usize::try_from(d).ok()?))
}

/// [`element_count`] as an error that names the shape.
pub fn elements(shape: &[u64]) -> Result<usize> {
    element_count(shape).ok_or_else(|| {
        anyhow!("shape {shape:?} declares more elements than fit in memory (the count overflows)")
    })
}

/// [`elements`], refusing an empty array: a zero-element array could
/// still declare a huge dimension (`[2^62, 0]`) that a consumer would loop
/// over or allocate for, and no input of the tools is legitimately empty.
pub fn nonempty(shape: &[u64]) -> Result<usize> {
    match elements(shape)? {
        0 => Err(anyhow!("shape {shape:?} has no elements")),
        n => Ok(n),
    }
}

/// Bytes of `count` elements of `width` bytes each, or an error.
pub fn bytes_of(shape: &[u64], width: usize) -> Result<usize> {
    elements(shape)?.checked_mul(width).ok_or_else(|| {
        anyhow!("shape {shape:?} of {width}-byte elements declares more bytes than fit in memory")
    })
}

/// `a + b`, or an error naming `what`.
pub fn add(a: usize, b: usize, what: &str) -> Result<usize> {
    a.checked_add(b)
        .ok_or_else(|| anyhow!("{what}: {a} + {b} overflows"))
}

/// `a * b`, or an error naming `what`.
pub fn mul(a: usize, b: usize, what: &str) -> Result<usize> {
    a.checked_mul(b)
        .ok_or_else(|| anyhow!("{what}: {a} x {b} overflows"))
}

/// The dimensions of a 2-D or 3-D shape as `usize`, or an error.
pub fn dims<const N: usize>(shape: &[u64]) -> Option<[usize; N]> {
    let arr: [u64; N] = shape.try_into().ok()?;
    let mut out = [0usize; N];
    for (o, d) in out.iter_mut().zip(arr) {
        *o = usize::try_from(d).ok()?;
    }
    Some(out)
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::*;

    #[test]
    fn counts_are_checked() {
        assert_eq!(element_count(&[]), Some(1));
        assert_eq!(element_count(&[3, 4, 5]), Some(60));
        assert_eq!(element_count(&[0, u64::MAX]), Some(0));
        assert_eq!(element_count(&[1 << 32, 1 << 32]), None);
        assert_eq!(element_count(&[1 << 32, 1 << 32, 0]), None);
        assert!(bytes_of(&[1 << 62], 8).is_err());
        assert_eq!(bytes_of(&[2, 3], 4).unwrap(), 24);
        assert!(nonempty(&[1 << 62, 0]).is_err());
        assert_eq!(nonempty(&[2, 3]).unwrap(), 6);
        assert_eq!(dims::<2>(&[2, 3]), Some([2, 3]));
        assert_eq!(dims::<2>(&[2, 3, 4]), None);
    }

    /// The parser modules keep `deny(clippy::arithmetic_side_effects)`:
    /// with it, clippy (`-D warnings` in CI) refuses any unchecked integer
    /// `+ - * / %` or `<<` there, so a size computed from a file cannot
    /// silently wrap again.
    #[test]
    fn parser_modules_deny_unchecked_arithmetic() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        for f in PARSER_MODULES {
            let text = std::fs::read_to_string(root.join(f)).unwrap();
            assert!(
                text.contains("#![deny(clippy::arithmetic_side_effects)]"),
                "{f} lost its arithmetic lint"
            );
        }
    }

    /// Every module that reads a size from a file the tools are handed.
    const PARSER_MODULES: &[&str] = &[
        "exporter/src/io/sizes.rs",
        "exporter/src/io/tensors.rs",
        "exporter/src/io/samples.rs",
        "exporter/src/npz.rs",
        "exporter/src/cp/import.rs",
        "exporter/src/pfnn_dir.rs",
        "exporter/src/net/json.rs",
        "exporter/src/net/omg.rs",
        "host-sim/src/npy.rs",
        "host-sim/src/compare.rs",
        "format/src/blob/framing.rs",
        "format/src/blob/records.rs",
    ];
}
