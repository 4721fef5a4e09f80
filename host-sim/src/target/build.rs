//! Building the firmware (`cargo build --release` in `firmware/`).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

/// The repository root: `PHASEGATE_REPO`, else the parent of host-sim's
/// manifest directory (where it was compiled).
pub fn repo_root() -> PathBuf {
    match std::env::var_os("PHASEGATE_REPO") {
        Some(p) => PathBuf::from(p),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join(".."),
    }
}

/// The firmware crate: `PHASEGATE_FIRMWARE_DIR`, else `<repo>/firmware`.
pub fn firmware_dir() -> PathBuf {
    match std::env::var_os("PHASEGATE_FIRMWARE_DIR") {
        Some(p) => PathBuf::from(p),
        None => repo_root().join("firmware"),
    }
}

/// Target triple of the firmware.
pub const TARGET: &str = "thumbv7em-none-eabihf";
/// Binary name of the firmware.
pub const BIN: &str = "phasegate-firmware";
/// Binary name of the inference core (`firmware/src/bin/inference_core.rs`).
pub const CORE_BIN: &str = "inference-core";
/// The reach firmware's binary (`src/main.rs` with the `reach` feature).
pub const REACH_BIN: &str = "reach-firmware";

/// Outcome of one `cargo build`.
#[derive(Debug)]
pub struct BuildOutput {
    /// Whether cargo succeeded.
    pub success: bool,
    /// cargo's stderr (diagnostics).
    pub stderr: String,
    /// Where the ELF is (or would be).
    pub elf: PathBuf,
}

/// Runs `cargo build --release --bin phasegate-firmware` in the firmware
/// directory with `features`, into `target_dir` (default
/// `firmware/target`). Does not fail on a build error: see
/// [`BuildOutput::success`].
pub fn cargo_build(features: &[&str], target_dir: Option<&Path>) -> Result<BuildOutput> {
    cargo_build_bin(BIN, features, target_dir)
}

/// [`cargo_build`] of the firmware package's binary `bin`.
pub fn cargo_build_bin(
    bin: &str,
    features: &[&str],
    target_dir: Option<&Path>,
) -> Result<BuildOutput> {
    let dir = firmware_dir();
    let target_dir = target_dir
        .map(Path::to_path_buf)
        .unwrap_or_else(|| dir.join("target"));
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.current_dir(&dir)
        .args(["build", "--release", "--quiet", "--target", TARGET])
        .args(["--bin", bin])
        .arg("--target-dir")
        .arg(&target_dir);
    if !features.is_empty() {
        cmd.arg("--features").arg(features.join(","));
    }
    // The host build's settings must not leak into the target build (the
    // firmware's .cargo/config.toml holds its own flags).
    for var in [
        "RUSTFLAGS",
        "CARGO_ENCODED_RUSTFLAGS",
        "CARGO_BUILD_RUSTFLAGS",
        "CARGO_BUILD_TARGET",
        "CARGO_TARGET_DIR",
        "CARGO_BUILD_TARGET_DIR",
        "CARGO_MANIFEST_DIR",
        "CARGO_PRIMARY_PACKAGE",
    ] {
        cmd.env_remove(var);
    }
    let out = cmd
        .output()
        .with_context(|| format!("cannot run cargo in {}", dir.display()))?;
    exporter::atomic::check_not_interrupted(out.status)?;
    Ok(BuildOutput {
        success: out.status.success(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        elf: target_dir.join(TARGET).join("release").join(bin),
    })
}

/// Builds the firmware (with its boot self-test, the `self-test` feature)
/// if needed (cargo decides) and returns its ELF path.
pub fn build_firmware() -> Result<PathBuf> {
    build_checked(BIN, &["self-test"], None)
}

/// Builds the inference core (beside the firmware, in `firmware/target`)
/// if needed and returns its ELF path. Every op is compiled in (issue 12),
/// the DEC op's feature included, which the QEMU firmware leaves off.
pub fn build_inference_core() -> Result<PathBuf> {
    build_checked(CORE_BIN, &["dec"], None)
}

/// Builds the controller firmware (`--features controller`, into
/// `firmware/target/controller` so that it never replaces the inference
/// firmware's ELF) if needed and returns its ELF path.
pub fn build_controller_firmware() -> Result<PathBuf> {
    build_checked(
        BIN,
        &["controller"],
        Some(&firmware_dir().join("target").join("controller")),
    )
}

/// Builds the reach firmware (the firmware's `reach-firmware` binary,
/// `--features reach`) if needed and returns its ELF path. It shares the
/// controller build's directory, `firmware/target/controller`: the same
/// compiled dependencies, its own ELF.
pub fn build_reach_firmware() -> Result<PathBuf> {
    build_checked(
        REACH_BIN,
        &["reach"],
        Some(&firmware_dir().join("target").join("controller")),
    )
}

fn build_checked(bin: &str, features: &[&str], target_dir: Option<&Path>) -> Result<PathBuf> {
    let out = cargo_build_bin(bin, features, target_dir)?;
    if !out.success {
        let with = if features.is_empty() {
            String::new()
        } else {
            format!(" --features {}", features.join(","))
        };
        bail!(
            "firmware build failed (cargo build --release --bin {bin}{with} in {}):\n{}\n(is the target installed? rustup target add {TARGET})",
            firmware_dir().display(),
            out.stderr.trim_end()
        );
    }
    Ok(out.elf)
}
