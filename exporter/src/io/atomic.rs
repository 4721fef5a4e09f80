//! All-or-nothing file output: write a temporary file in the destination's
//! directory, flush it, then rename it over the destination. A failure at
//! any point leaves no partial file behind.
//!
//! The command-line tools also refuse to write over one of their own
//! inputs (`-o model.npz` for `--weights model.npz`): [`guard_inputs`]
//! (called first thing by `exporter` and `host-sim`) makes every reader
//! that goes through [`read_input`] or [`note_input`] remember the file,
//! and [`write_atomic`] then refuses that destination before writing.

use anyhow::{bail, Context, Result};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

static GUARD: AtomicBool = AtomicBool::new(false);
static INPUTS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// From now on, files read through [`read_input`] / [`note_input`] may not
/// be written by [`write_atomic`] in this process. Off by default, so that
/// library users (tests, `golden --write`) may rewrite what they read.
pub fn guard_inputs() {
    GUARD.store(true, Ordering::Relaxed);
}

/// Remembers `path` (a file or directory) as an input of this run.
pub fn note_input(path: &Path) {
    if !GUARD.load(Ordering::Relaxed) {
        return;
    }
    if let (Ok(c), Ok(mut v)) = (std::fs::canonicalize(path), INPUTS.lock()) {
        v.push(c);
    }
}

/// `std::fs::read`, remembering `path` as an input ([`note_input`]).
pub fn read_input(path: &Path) -> std::io::Result<Vec<u8>> {
    let bytes = std::fs::read(path)?;
    note_input(path);
    Ok(bytes)
}

/// Whether `path` is (or is inside) an input of this run.
fn is_input(path: &Path) -> bool {
    let Ok(dest) = std::fs::canonicalize(path) else {
        return false; // does not exist yet: cannot be an input
    };
    INPUTS
        .lock()
        .map(|v| {
            v.iter()
                .any(|i| dest == *i || (i.is_dir() && dest.starts_with(i)))
        })
        .unwrap_or(false)
}

/// Writes `bytes` to `path` atomically; refuses a path that is one of the
/// run's inputs ([`guard_inputs`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    if GUARD.load(Ordering::Relaxed) && is_input(path) {
        bail!(
            "{}: the output is also an input of this command; refusing to overwrite it",
            path.display()
        );
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::Builder::new()
        .prefix(".phasegate-")
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| {
            // The reason alone: tempfile's message names its random
            // temporary file, which never existed.
            let why = if !dir.exists() {
                "no such directory".to_string()
            } else if !dir.is_dir() {
                "not a directory".to_string()
            } else {
                e.kind().to_string() // "permission denied", ...
            };
            anyhow::anyhow!(
                "cannot write {}: cannot create a file in {}: {why}",
                path.display(),
                dir.display()
            )
        })?;
    tmp.write_all(bytes)
        .and_then(|_| tmp.as_file().sync_all())
        .with_context(|| format!("cannot write {}", path.display()))?;
    // tempfile creates 0600; a model or report is an ordinary file.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let _ = tmp
            .as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644));
    }
    tmp.persist(path)
        .map_err(|e| e.error)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}
