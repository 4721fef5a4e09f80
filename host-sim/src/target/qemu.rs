//! Running the firmware under `qemu-system-arm -machine mps2-an386
//! -icount shift=0`, with the blob and the input image loaded raw at their
//! regions, in a fresh working directory (where the firmware writes its
//! output file through semihosting).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use super::wire;

/// The QEMU binary: `PHASEGATE_QEMU`, else `qemu-system-arm` on the PATH.
pub fn qemu_binary() -> PathBuf {
    std::env::var_os("PHASEGATE_QEMU")
        .map(PathBuf::from)
        .unwrap_or_else(|| "qemu-system-arm".into())
}

/// Whether the QEMU binary runs at all.
pub fn qemu_available() -> bool {
    Command::new(qemu_binary())
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// A raw image for `-device loader`.
#[derive(Clone, Debug)]
pub struct Load {
    /// File to load.
    pub file: PathBuf,
    /// Address of its first byte.
    pub addr: u64,
}

/// What one QEMU run left behind.
#[derive(Debug)]
pub struct QemuRun {
    /// QEMU's exit code: the firmware's semihosting exit code.
    pub exit_code: i32,
    /// Semihosting stdout: the binary defmt stream.
    pub stdout: Vec<u8>,
    /// QEMU's own messages.
    pub stderr: String,
    /// The firmware's output file, if it wrote one.
    pub output_file: Option<Vec<u8>>,
    /// The firmware's profile file (network mode), if it wrote one.
    pub profile_file: Option<Vec<u8>>,
    /// Wall time of the run.
    pub wall: Duration,
}

/// Commas in QEMU option values are written doubled.
fn qemu_escape(p: &Path) -> String {
    p.display().to_string().replace(',', ",,")
}

/// Boots `elf` with `loads`, waits at most `timeout`.
pub fn run(elf: &Path, loads: &[Load], timeout: Duration) -> Result<QemuRun> {
    run_with(elf, loads, timeout, &[])
}

/// [`run`] with `extra` QEMU options (an execution trace, [`super::cycles`]).
pub fn run_with(
    elf: &Path,
    loads: &[Load],
    timeout: Duration,
    extra: &[std::ffi::OsString],
) -> Result<QemuRun> {
    let dir = tempfile::Builder::new()
        .prefix("phasegate-qemu-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let mut cmd = Command::new(qemu_binary());
    cmd.current_dir(dir.path())
        .args(["-machine", "mps2-an386", "-cpu", "cortex-m4"])
        .args([
            "-display",
            "none",
            "-monitor",
            "none",
            "-serial",
            "none",
            "-nodefaults",
        ])
        // Virtual time advances 1 ns per instruction (2^0): with the 25 MHz
        // SysTick, one tick is 40 instructions.
        .args(["-icount", "shift=0"])
        .args(["-semihosting-config", "enable=on,target=native"])
        .arg("-kernel")
        .arg(elf)
        .args(extra);
    for l in loads {
        let file = std::path::absolute(&l.file).unwrap_or_else(|_| l.file.clone());
        cmd.arg("-device").arg(format!(
            "loader,file={},addr={:#x},force-raw=on",
            qemu_escape(&file),
            l.addr
        ));
    }
    cmd.stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let start = Instant::now();
    let mut child = cmd.spawn().with_context(|| {
        format!(
            "cannot start {} (install QEMU: apt-get install qemu-system-arm)",
            qemu_binary().display()
        )
    })?;
    let mut stdout_pipe = child.stdout.take().context("no stdout pipe")?;
    let mut stderr_pipe = child.stderr.take().context("no stderr pipe")?;
    let out_reader = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = stdout_pipe.read_to_end(&mut v);
        v
    });
    let err_reader = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = stderr_pipe.read_to_end(&mut v);
        v
    });
    let status = loop {
        if let Some(status) = child.try_wait().context("waiting for QEMU")? {
            exporter::atomic::check_not_interrupted(status)?;
            break status;
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            let _ = child.wait();
            let err = err_reader.join().unwrap_or_default();
            bail!(
                "QEMU did not finish within {:.0} s (killed); its stderr: {}",
                timeout.as_secs_f64(),
                String::from_utf8_lossy(&err).trim()
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let wall = start.elapsed();
    let stdout = out_reader.join().unwrap_or_default();
    let stderr = String::from_utf8_lossy(&err_reader.join().unwrap_or_default()).into_owned();
    let Some(exit_code) = status.code() else {
        bail!(
            "QEMU was killed by a signal ({status}); stderr: {}",
            stderr.trim()
        );
    };
    let output_file = std::fs::read(dir.path().join(wire::OUTPUT_FILE)).ok();
    let profile_file = std::fs::read(dir.path().join(wire::PROFILE_FILE)).ok();
    Ok(QemuRun {
        exit_code,
        stdout,
        stderr,
        output_file,
        profile_file,
        wall,
    })
}
