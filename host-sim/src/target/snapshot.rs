//! Snapshot tests of the firmware's decoded defmt log: each scenario boots
//! the firmware under QEMU and compares its log (and exit code) with
//! `firmware/snapshots/<scenario>.log`, next to the firmware's source.
//!
//! Bless new snapshots after an intended change with
//! `PHASEGATE_OVERWRITE_SNAPSHOTS=1 cargo test -p host-sim target::tests::firmware_log_snapshots`
//! (or [`run_snapshots`] with `overwrite = true`), then review the diff in git.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};

use super::{
    boot, build_controller_firmware, build_firmware, controller, firmware_dir, frames, styles,
    synthetic, wire, ElfInfo, MixSpec,
};

/// Where the model comes from in a scenario.
#[derive(Clone, Copy, Debug)]
enum Blob {
    /// Nothing at the MODEL region.
    None,
    /// The embedded default model's blob.
    Default,
    /// The default blob with the last payload byte flipped.
    CorruptPayload,
}

/// What the STYLES region holds in a scenario.
#[derive(Clone, Copy, Debug)]
enum Styles {
    /// Nothing.
    None,
    /// Two styles for the default model ([`synthetic::default_model_styles`]).
    DefaultPair,
    /// A style claiming another base ([`OTHER_BASE_CRC`]).
    OtherBase,
}

/// The base CRC the `style-other-base` scenario's style claims.
const OTHER_BASE_CRC: u32 = 0x0BAD_BA5E;

/// One snapshot scenario.
#[derive(Clone, Copy, Debug)]
struct Scenario {
    name: &'static str,
    blob: Blob,
    styles: Styles,
    /// Feed the golden vectors (else no input image), with every frame's
    /// mix from `cycle` when the scenario has styles (else base).
    golden_inputs: bool,
    /// Run the `controller` firmware on [`CONTROLLER_FRAMES`] commands of
    /// the `walk` script instead (controller mode).
    controller: bool,
}

/// Commands the `controller-walk` scenario runs.
const CONTROLLER_FRAMES: usize = 8;

const SCENARIOS: &[Scenario] = &[
    Scenario {
        name: "golden-default",
        blob: Blob::Default,
        styles: Styles::None,
        golden_inputs: true,
        controller: false,
    },
    Scenario {
        name: "model-only",
        blob: Blob::Default,
        styles: Styles::None,
        golden_inputs: false,
        controller: false,
    },
    Scenario {
        name: "no-model",
        blob: Blob::None,
        styles: Styles::None,
        golden_inputs: false,
        controller: false,
    },
    Scenario {
        name: "corrupt-model",
        blob: Blob::CorruptPayload,
        styles: Styles::None,
        golden_inputs: false,
        controller: false,
    },
    Scenario {
        name: "golden-styles",
        blob: Blob::Default,
        styles: Styles::DefaultPair,
        golden_inputs: true,
        controller: false,
    },
    Scenario {
        name: "style-other-base",
        blob: Blob::Default,
        styles: Styles::OtherBase,
        golden_inputs: false,
        controller: false,
    },
    Scenario {
        name: "controller-walk",
        blob: Blob::Default,
        styles: Styles::None,
        golden_inputs: false,
        controller: true,
    },
];

/// Directory of the expected logs.
pub fn snapshot_dir() -> PathBuf {
    firmware_dir().join("snapshots")
}

/// The text compared for a run: the exit code, then one line per log frame.
pub fn render(exit_code: i32, log: &[String]) -> String {
    let mut s = format!("exit: {exit_code} ({})\n", wire::exit::describe(exit_code));
    for line in log {
        s.push_str(line);
        s.push('\n');
    }
    s
}

/// A small line diff (expected `-`, actual `+`) for the failure message.
fn diff(expected: &str, actual: &str) -> String {
    let (e, a): (Vec<&str>, Vec<&str>) = (expected.lines().collect(), actual.lines().collect());
    let mut out = String::new();
    for i in 0..e.len().max(a.len()) {
        match (e.get(i), a.get(i)) {
            (Some(x), Some(y)) if x == y => {}
            (x, y) => {
                if let Some(x) = x {
                    out.push_str(&format!("  line {}: - {x}\n", i + 1));
                }
                if let Some(y) = y {
                    out.push_str(&format!("  line {}: + {y}\n", i + 1));
                }
            }
        }
    }
    out
}

/// Outcome of one scenario.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Same as the snapshot.
    Same,
    /// Snapshot written (overwrite mode, or it did not exist).
    Written,
    /// Differs; the message holds the diff.
    Differs(String),
}

/// Runs every scenario, compares (or, with `overwrite`, rewrites) its
/// snapshot, and reports every difference before failing.
pub fn run_snapshots(overwrite: bool) -> Result<Vec<(&'static str, Outcome)>> {
    let golden = frames::golden_root().join("default");
    let blob_path = golden.join("model.blob");
    let blob = std::fs::read(&blob_path)
        .with_context(|| format!("cannot read {}", blob_path.display()))?;
    let model = phasegate::Model::from_bytes(&blob).context("the default blob")?;
    let mut golden = frames::golden_for(&blob, model.input_dim(), model.output_dim())?
        .context("no golden vectors for the default blob")?;
    let image = golden.image(model.output_dim());
    golden.mixes = MixSpec::Cycle {
        step: styles::DEFAULT_CYCLE_STEP,
    }
    .schedule(golden.len());
    let styled_image = golden.image(model.output_dim());
    let pair = styles::pack_styles(&synthetic::default_model_styles()?);
    let other = styles::pack_styles(&[synthetic::default_model_style_for_crc(OTHER_BASE_CRC)?]);
    let elf_path = build_firmware()?;
    let elf = ElfInfo::read(&elf_path)?;
    let ctl_path = build_controller_firmware()?;
    let ctl_elf = ElfInfo::read(&ctl_path)?;
    let walk = crate::rollout::Script::builtin("walk").context("the walk script")?;
    let ctl_image = controller::controller_image(
        &controller::script_commands(&walk, CONTROLLER_FRAMES),
        &[wire::encode_mix(phasegate::Mix::Base); CONTROLLER_FRAMES],
    );
    let scratch = tempfile::tempdir()?;
    let corrupt_path = scratch.path().join("corrupt.blob");
    let mut corrupt = blob.clone();
    if let Some(b) = corrupt.last_mut() {
        *b ^= 0x01;
    }
    std::fs::write(&corrupt_path, &corrupt)?;

    let mut results = Vec::new();
    for s in SCENARIOS {
        let blob: Option<&Path> = match s.blob {
            Blob::None => None,
            Blob::Default => Some(&blob_path),
            Blob::CorruptPayload => Some(&corrupt_path),
        };
        let (style_image, input_image) = match s.styles {
            Styles::None => (None, &image),
            Styles::DefaultPair => (Some(&pair[..]), &styled_image),
            Styles::OtherBase => (Some(&other[..]), &image),
        };
        let img = if s.controller {
            Some(&ctl_image[..])
        } else {
            s.golden_inputs.then_some(&input_image[..])
        };
        let (elf, elf_path) = if s.controller {
            (&ctl_elf, &ctl_path)
        } else {
            (&elf, &elf_path)
        };
        let booted = boot(
            elf,
            elf_path,
            blob,
            style_image,
            img,
            Duration::from_secs(120),
        )
        .with_context(|| format!("scenario {}", s.name))?;
        let actual = render(booted.run.exit_code, &booted.log);
        let path = snapshot_dir().join(format!("{}.log", s.name));
        let outcome = match std::fs::read_to_string(&path) {
            Ok(expected) if expected == actual => Outcome::Same,
            Ok(_) | Err(_) if overwrite => {
                std::fs::write(&path, &actual)
                    .with_context(|| format!("cannot write {}", path.display()))?;
                Outcome::Written
            }
            Ok(expected) => Outcome::Differs(diff(&expected, &actual)),
            Err(_) => Outcome::Differs(format!(
                "  no snapshot {} yet; actual:\n{actual}",
                path.display()
            )),
        };
        results.push((s.name, outcome));
    }
    let failed: Vec<String> = results
        .iter()
        .filter_map(|(name, o)| match o {
            Outcome::Differs(d) => Some(format!("{name}:\n{d}")),
            _ => None,
        })
        .collect();
    if !failed.is_empty() {
        bail!(
            "{} of {} firmware log snapshots differ (in {}):\n{}\nIf the change is intended, bless it: \
             PHASEGATE_OVERWRITE_SNAPSHOTS=1 cargo test -p host-sim firmware_log_snapshots",
            failed.len(),
            results.len(),
            snapshot_dir().display(),
            failed.join("")
        );
    }
    Ok(results)
}
