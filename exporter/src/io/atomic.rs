//! All-or-nothing file output: write a temporary file in the destination's
//! directory, flush it, then rename it over the destination. A failure at
//! any point leaves no partial file behind, and a command's several outputs
//! (a blob, its report, grid and snapped weights) are written together or
//! not at all ([`write_together`]).
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
/// The temporary files staged and not yet renamed into place; held while
/// the renames run, so that an interrupt waits for them.
static STAGED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

/// Exit code of a run interrupted by Ctrl-C or SIGTERM (128 + SIGINT).
pub const INTERRUPTED: i32 = 130;

/// Makes Ctrl-C and SIGTERM end the run with one line and exit code
/// [`INTERRUPTED`], leaving no partial output: temporaries being staged
/// are removed, and an interrupt that comes while a command's outputs are
/// being renamed into place waits until all of them are (so the run leaves
/// every output or none). Called first thing by `exporter` and `host-sim`.
pub fn clean_up_on_interrupt() {
    let _ = ctrlc::set_handler(|| end_interrupted());
}

/// Ends the run as interrupted: the staged temporaries removed (after any
/// renames in progress), one line, exit [`INTERRUPTED`]. The signal
/// handler calls it, and so does a tool's `main` whose command failed with
/// [`Interrupted`]; whichever comes first ends the process, the other
/// waits for it.
pub fn end_interrupted() -> ! {
    static ENDING: Mutex<()> = Mutex::new(());
    let _first = ENDING.lock();
    let staged = STAGED.lock().map(|v| v.clone()).unwrap_or_default();
    for p in staged {
        let _ = std::fs::remove_file(p);
    }
    eprintln!("error: interrupted; no output written");
    std::process::exit(INTERRUPTED);
}

/// The error of a command whose child process (a build, QEMU) was ended
/// by an interrupt: Ctrl-C reaches the whole process group, and the
/// child's failure may be seen before the tool's own handler runs. A
/// tool's `main` ends such a run with [`end_interrupted`], not with the
/// child's failure.
#[derive(Debug)]
pub struct Interrupted;

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("interrupted")
    }
}

impl std::error::Error for Interrupted {}

/// `Err(Interrupted)` if `status` is that of a child ended by SIGINT or
/// SIGTERM.
pub fn check_not_interrupted(status: std::process::ExitStatus) -> Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if matches!(status.signal(), Some(2 | 15)) {
            return Err(Interrupted.into());
        }
    }
    let _ = status;
    Ok(())
}

/// Whether `e` (a command's error) is, or was caused by, an interrupt.
pub fn is_interrupted(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.is::<Interrupted>())
}

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
    write_together(&[(path, bytes)])
}

/// Writes every file or none: each goes to a temporary file beside its
/// destination first, and only when all of them are complete and flushed
/// are they renamed into place. A destination that is an input of the run,
/// a directory, or named twice is refused before anything is written; a
/// failure while staging removes the temporaries and leaves every
/// destination as it was. (The renames come last and stay within each
/// destination's own directory, where nothing checked above can make one
/// fail; an I/O error there names the file.)
pub fn write_together(files: &[(&Path, &[u8])]) -> Result<()> {
    for (i, (path, _)) in files.iter().enumerate() {
        if GUARD.load(Ordering::Relaxed) && is_input(path) {
            bail!(
                "{}: the output is also an input of this command; refusing to overwrite it",
                path.display()
            );
        }
        if path.is_dir() {
            bail!("cannot write {}: it is a directory", path.display());
        }
        let key = destination_key(path);
        if files[..i].iter().any(|(p, _)| destination_key(p) == key) {
            bail!("{}: named as two outputs of this command", path.display());
        }
    }
    let mut staged = Vec::with_capacity(files.len());
    let mut mine: Vec<PathBuf> = Vec::with_capacity(files.len());
    let result = (|| {
        for (path, bytes) in files {
            let tmp = stage(path, bytes, &mut mine)?;
            staged.push((*path, tmp));
        }
        // Held through the renames: an interrupt now waits for all of them.
        let _renaming = STAGED.lock();
        for (path, tmp) in staged.drain(..) {
            tmp.persist(path)
                .map_err(|e| e.error)
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
        Ok(())
    })();
    // What was not renamed is removed as `staged` drops; forget it all.
    drop(staged);
    if let Ok(mut v) = STAGED.lock() {
        v.retain(|p| !mine.contains(p));
    }
    result
}

/// The files of one command, gathered while it runs and written together
/// at the end ([`write_together`]): a command with several outputs adds
/// each as it is made and calls [`Outputs::commit`] once, so that nothing
/// lands unless everything does.
#[derive(Debug, Default)]
pub struct Outputs {
    files: Vec<(PathBuf, Vec<u8>)>,
    dirs: Vec<PathBuf>,
}

impl Outputs {
    /// No outputs yet.
    pub fn new() -> Outputs {
        Outputs::default()
    }

    /// `bytes` to be written to `path`.
    pub fn add(&mut self, path: impl Into<PathBuf>, bytes: Vec<u8>) {
        self.files.push((path.into(), bytes));
    }

    /// A directory (an output directory such as `--out-dir`) that
    /// [`Outputs::commit`] creates, with its parents, if it does not exist,
    /// and removes again if writing fails.
    pub fn dir(&mut self, dir: impl Into<PathBuf>) {
        self.dirs.push(dir.into());
    }

    /// The destinations gathered so far, in order.
    pub fn paths(&self) -> impl Iterator<Item = &Path> {
        self.files.iter().map(|(p, _)| p.as_path())
    }

    /// Writes every file or none; directories this call created are
    /// removed again on failure.
    pub fn commit(self) -> Result<()> {
        let mut created = Vec::new();
        let result = (|| {
            for d in &self.dirs {
                let mut missing = Vec::new();
                let mut at = Some(d.as_path());
                while let Some(p) = at.filter(|p| !p.as_os_str().is_empty() && !p.exists()) {
                    missing.push(p.to_path_buf());
                    at = p.parent();
                }
                for m in missing.into_iter().rev() {
                    std::fs::create_dir(&m)
                        .with_context(|| format!("cannot create {}", m.display()))?;
                    created.push(m);
                }
            }
            let refs: Vec<(&Path, &[u8])> = self
                .files
                .iter()
                .map(|(p, b)| (p.as_path(), b.as_slice()))
                .collect();
            write_together(&refs)
        })();
        if result.is_err() {
            for d in created.iter().rev() {
                let _ = std::fs::remove_dir(d);
            }
        }
        result
    }
}

/// The directory of `path` (canonical where it exists) joined with its
/// file name: two spellings of one destination compare equal.
fn destination_key(path: &Path) -> PathBuf {
    let dir = parent_dir(path);
    let dir = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    match path.file_name() {
        Some(name) => dir.join(name),
        None => dir,
    }
}

/// The directory `path` is written in (`.` for a bare file name).
fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// `bytes` in a flushed temporary file in `path`'s directory, removed
/// again when dropped unless persisted.
/// Writes `bytes` to a new temporary file beside `path`, known to the
/// interrupt handler (and added to `mine`) from the moment it exists, so
/// that an interrupt during a long write removes it too.
fn stage(path: &Path, bytes: &[u8], mine: &mut Vec<PathBuf>) -> Result<tempfile::NamedTempFile> {
    let dir = parent_dir(path);
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
    mine.push(tmp.path().to_path_buf());
    if let Ok(mut v) = STAGED.lock() {
        v.push(tmp.path().to_path_buf());
    }
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
    Ok(tmp)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn outputs_land_together_in_directories_made_for_them() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("a/b");
        let mut out = Outputs::new();
        out.dir(&dir);
        out.add(dir.join("x"), b"1".to_vec());
        out.add(tmp.path().join("y"), b"2".to_vec());
        assert_eq!(out.paths().count(), 2);
        out.commit().unwrap();
        assert_eq!(std::fs::read(dir.join("x")).unwrap(), b"1");
        assert_eq!(std::fs::read(tmp.path().join("y")).unwrap(), b"2");
        assert_eq!(names(tmp.path()), ["a", "y"]);
    }

    #[test]
    fn a_failed_output_leaves_no_file_no_temporary_and_no_directory_it_made() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("new/deeper");
        std::fs::create_dir(tmp.path().join("blocker")).unwrap();
        let mut out = Outputs::new();
        out.dir(&dir);
        out.add(dir.join("x"), b"1".to_vec());
        out.add(tmp.path().join("blocker"), b"2".to_vec());
        let err = out.commit().unwrap_err().to_string();
        assert!(err.contains("is a directory"), "{err}");
        assert_eq!(names(tmp.path()), ["blocker"]);

        let mut out = Outputs::new();
        out.add(tmp.path().join("x"), b"1".to_vec());
        out.add(tmp.path().join("blocker/../x"), b"2".to_vec());
        let err = out.commit().unwrap_err().to_string();
        assert!(err.contains("two outputs"), "{err}");
        assert_eq!(names(tmp.path()), ["blocker"]);
    }
}
