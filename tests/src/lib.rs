//! Cross-crate and end-to-end tests live in tests/; this library holds
//! what several of them share.

use std::io::Write;
use std::path::{Path, PathBuf};

/// The real PFNN's weight directory (`$PHASEGATE_PFNN_DIR`, else
/// `../shared/pfnn/network` beside the repository), or `None` after
/// saying on stderr that the test is skipped: stderr directly, so that it
/// shows though the harness captures the output of passing tests.
pub fn real_pfnn_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("PHASEGATE_PFNN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/pfnn/network"));
    if dir.join("Xmean.bin").is_file() {
        Some(dir)
    } else {
        let _ = writeln!(
            std::io::stderr(),
            "skipped: real PFNN weights not found at {} (set PHASEGATE_PFNN_DIR)",
            dir.display()
        );
        None
    }
}

pub mod fuzz;
