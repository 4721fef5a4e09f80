//! Selects the dense kernels at compile time: targets whose name says they
//! have the Armv7E-M DSP extension (`thumbv7em-*`) get the `SMLAD` kernels
//! (`cfg(phasegate_dsp)`, `src/ops/dense/dsp.rs`). Stable Rust does not
//! expose `target_feature = "dsp"`, so the target triple decides.

fn main() {
    println!("cargo::rustc-check-cfg=cfg(phasegate_dsp)");
    println!("cargo::rerun-if-env-changed=TARGET");
    let target = std::env::var("TARGET").unwrap_or_default();
    if target.starts_with("thumbv7em-") {
        println!("cargo::rustc-cfg=phasegate_dsp");
    }
}
