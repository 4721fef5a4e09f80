//! The DSP dense kernels on the Cortex-M4 under QEMU: builds the firmware's
//! `kernel-check` binary (`firmware/src/bin/kernel-check.rs`) and runs it;
//! it exits 0 only when the assembly kernels equal the portable reference
//! bit for bit on every seeded random case (the host half of the proof is
//! `runtime/src/ops/dense/dsp/emulation.rs`).

use std::process::Command;

use host_sim::target::build::{cargo_build_bin, firmware_dir, TARGET};
use host_sim::target::qemu::{qemu_available, qemu_binary};

#[test]
fn dsp_kernels_equal_the_portable_ones_under_qemu() {
    if !qemu_available() {
        eprintln!("skipped: {} is not available", qemu_binary().display());
        return;
    }
    let target_dir = firmware_dir().join("target").join("kernel-check");
    let build =
        cargo_build_bin("kernel-check", &["kernel-check"], Some(&target_dir)).expect("cargo runs");
    assert!(
        build.success,
        "kernel-check build failed:\n{}",
        build.stderr
    );
    let elf = target_dir.join(TARGET).join("release").join("kernel-check");
    assert!(elf.is_file(), "no kernel-check ELF at {}", elf.display());
    let status = Command::new(qemu_binary())
        .args(["-machine", "mps2-an386", "-cpu", "cortex-m4"])
        .args(["-display", "none", "-monitor", "none", "-serial", "none"])
        .args(["-icount", "shift=0"])
        .args(["-semihosting-config", "enable=on,target=native"])
        .arg("-kernel")
        .arg(&elf)
        .stdout(std::process::Stdio::null())
        .status()
        .expect("QEMU runs");
    assert_eq!(
        status.code(),
        Some(0),
        "kernel mismatch or fault on the target: {status}"
    );
}
