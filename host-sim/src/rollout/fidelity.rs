//! Fidelity of the device controller on a real PFNN: long rollouts of the
//! int16 and int8 cubic blobs and of an f32 float controller, each against
//! the f64 float controller, over every built-in script; and the bars of
//! issue 3 checked on them.

use anyhow::{Context, Result};
use exporter::atomic::Outputs;
use exporter::export::export;
use exporter::net::{GatingMode, Net};
use exporter::quantise::QuantOptions;
use phasegate::blob::WeightFormat;
use serde::Serialize;
use std::fmt::Write;
use std::path::Path;

use super::compare::{compare, Summary};
use super::metrics::{sanity, Sanity};
use super::script::{Script, BUILTIN};
use super::{run, Rollout};
use crate::controller::{reference_f32, reference_f64, Controller, FixedController};
use crate::quant_knobs::Int8Knobs;

/// The controllers compared with the f64 reference, in table order.
pub const VARIANTS: [&str; 3] = ["f32 float", "int16 cubic", "int8 cubic"];

/// One controller on one script.
#[derive(Clone, Debug, Serialize)]
pub struct VariantResult {
    /// One of [`VARIANTS`].
    pub name: &'static str,
    /// Against the f64 reference.
    pub errors: Summary,
    /// Its own sanity metrics.
    pub sanity: Sanity,
}

/// Everything measured on one script.
#[derive(Clone, Debug, Serialize)]
pub struct ScriptResult {
    /// Script name.
    pub script: String,
    /// Sanity metrics of the f64 reference.
    pub reference: Sanity,
    /// [`VARIANTS`], in order.
    pub variants: Vec<VariantResult>,
}

/// The whole measurement.
#[derive(Clone, Debug, Serialize)]
pub struct Fidelity {
    /// Frames per script.
    pub frames: usize,
    /// Bytes of the int16 and int8 blobs.
    pub blob_bytes: [usize; 2],
    /// Per script.
    pub scripts: Vec<ScriptResult>,
}

/// The blobs a fidelity run compares.
pub struct Blobs {
    /// int16 weights, cubic.
    pub int16: Vec<u8>,
    /// int8 weights, cubic.
    pub int8: Vec<u8>,
}

/// Exports the cubic float network at both weight widths, the int8 blob
/// with `int8`'s quantiser knobs.
pub fn export_blobs(net: &Net, int8: &Int8Knobs) -> Result<Blobs> {
    let opts = |weights| QuantOptions {
        weights,
        ..Default::default()
    };
    let int16 = exporter::progress::during("exporting the int16 blob", || {
        export(net, None, &opts(WeightFormat::I16))
    })?
    .0;
    Ok(Blobs {
        int16,
        int8: int8.export(net, None, opts(WeightFormat::I8))?.0,
    })
}

/// Loads a PFNN weight directory as the cubic float network.
pub fn load_cubic(dir: &Path) -> Result<Net> {
    let tables = exporter::pfnn_dir::load_pfnn_dir_auto(dir, None)
        .with_context(|| format!("loading {}", dir.display()))?;
    Ok(Net::from_pfnn_tables(&tables, GatingMode::Cubic).0)
}

/// The four rollouts of one script: f64 reference first, then [`VARIANTS`].
pub fn rollouts(net: &Net, blobs: &Blobs, script: &Script, frames: usize) -> Result<[Rollout; 4]> {
    let mut f64c = reference_f64(net)?;
    let mut f32c = reference_f32(net)?;
    let mut i16c = FixedController::new(&blobs.int16, "int16 cubic")?;
    let mut i8c = FixedController::new(&blobs.int8, "int8 cubic")?;
    let ctls: [&mut dyn Controller; 4] = [&mut f64c, &mut f32c, &mut i16c, &mut i8c];
    let mut out = Vec::new();
    for c in ctls {
        out.push(run(c, script, frames)?);
    }
    out.try_into()
        .map_err(|_| anyhow::anyhow!("four rollouts expected"))
}

/// One script's rollout files: destination and bytes.
type Staged = Vec<(std::path::PathBuf, Vec<u8>)>;

/// Runs every script in `scripts` (the built-ins if empty), two at a time;
/// writes each rollout to `out_dir/<script>-<controller>.npz` if given
/// (all of them or none).
pub fn measure(
    net: &Net,
    blobs: &Blobs,
    scripts: &[String],
    frames: usize,
    out_dir: Option<&Path>,
) -> Result<Fidelity> {
    let (f, records) = measure_staged(net, blobs, scripts, frames, out_dir)?;
    records.commit()?;
    Ok(f)
}

/// [`measure`], with the rollouts for `out_dir` gathered instead of
/// written, so that a command writes them together with its other files.
pub fn measure_staged(
    net: &Net,
    blobs: &Blobs,
    scripts: &[String],
    frames: usize,
    out_dir: Option<&Path>,
) -> Result<(Fidelity, Outputs)> {
    let names: Vec<String> = if scripts.is_empty() {
        BUILTIN.iter().map(|s| s.to_string()).collect()
    } else {
        scripts.to_vec()
    };
    let loaded = names
        .iter()
        .map(|n| Script::load(n))
        .collect::<Result<Vec<_>>>()?;
    let one = |script: &Script| -> Result<(ScriptResult, Staged)> {
        let rs = rollouts(net, blobs, script, frames)?;
        let mut staged = Staged::new();
        if let Some(d) = out_dir {
            for (r, tag) in rs.iter().zip(["f64", "f32", "int16", "int8"]) {
                staged.push((d.join(format!("{}-{tag}.npz", script.name)), r.to_npz()?));
            }
        }
        let [reference, rest @ ..] = &rs;
        let variants = rest
            .iter()
            .zip(VARIANTS)
            .map(|(r, name)| {
                Ok(VariantResult {
                    name,
                    errors: compare(reference, r)?.summary,
                    sanity: sanity(r),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((
            ScriptResult {
                script: script.name.clone(),
                reference: sanity(reference),
                variants,
            },
            staged,
        ))
    };
    let bar = exporter::progress::bar(loaded.len() as u64, "rollouts", "scripts");
    // Two workers (the CI machine has two cores); results in script order.
    let mut results: Vec<Option<Result<(ScriptResult, Staged)>>> =
        (0..loaded.len()).map(|_| None).collect();
    std::thread::scope(|s| {
        let chunks: Vec<_> = results
            .chunks_mut(loaded.len().div_ceil(2).max(1))
            .collect();
        let mut start = 0;
        for chunk in chunks {
            let mine = &loaded[start..start + chunk.len()];
            start += chunk.len();
            let (one, bar) = (&one, &bar);
            s.spawn(move || {
                for (slot, script) in chunk.iter_mut().zip(mine) {
                    *slot = Some(one(script));
                    bar.inc(1);
                }
            });
        }
    });
    bar.finish_and_clear();
    let (scripts, staged): (Vec<_>, Vec<_>) = results
        .into_iter()
        .map(|r| r.unwrap_or_else(|| Err(anyhow::anyhow!("worker did not finish"))))
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .unzip();
    let mut outputs = Outputs::new();
    if let Some(d) = out_dir {
        outputs.dir(d);
    }
    for (path, bytes) in staged.into_iter().flatten() {
        outputs.add(path, bytes);
    }
    Ok((
        Fidelity {
            frames,
            blob_bytes: [blobs.int16.len(), blobs.int8.len()],
            scripts,
        },
        outputs,
    ))
}

/// Joint p99 bar for the int16 blob: `max(2 units, 3 x f32's figure)`.
pub fn joint_bar(f32_worst_frame_p99: f64) -> f64 {
    (3.0 * f32_worst_frame_p99).max(2.0)
}

/// Issue 13's closed-loop bar for the int8 blob: worst-frame joint p99
/// against the f64 controller, units.
pub const INT8_JOINT_BAR: f64 = 3.0;

/// Issue 13's bar on the int8 blob's root drift at the last frame, units.
pub const INT8_DRIFT_BAR: f64 = 5.0;

/// Phase bar for the int16 blob: `max(0.05 rad, 3 x f32's figure)`.
pub fn phase_bar(f32_phase_error_max: f64) -> f64 {
    (3.0 * f32_phase_error_max).max(0.05)
}

/// Allowed sanity-metric difference: `max(10% of the reference, 0.5)`.
pub fn sanity_bar(reference: f64) -> f64 {
    (0.1 * reference.abs()).max(0.5)
}

impl Fidelity {
    /// Every bar of issue 3 that does not hold, in words (empty when all do).
    ///
    /// The per-frame bars compare like with like: the int16 blob's worst
    /// frame (largest per-frame joint p99, largest phase error) against the
    /// f32 controller's worst frame on the same script.
    pub fn violations(&self) -> Vec<String> {
        let mut v = Vec::new();
        for s in &self.scripts {
            let find = |n: &str| s.variants.iter().find(|x| x.name == n);
            let (Some(f32r), Some(i16r)) = (find(VARIANTS[0]), find(VARIANTS[1])) else {
                v.push(format!("{}: missing controllers", s.script));
                continue;
            };
            let jb = joint_bar(f32r.errors.worst_frame_p99);
            if i16r.errors.worst_frame_p99 > jb {
                v.push(format!(
                    "{}: int16 joint p99 {:.3} > bar {jb:.3}",
                    s.script, i16r.errors.worst_frame_p99
                ));
            }
            let pb = phase_bar(f32r.errors.phase_error_max);
            if i16r.errors.phase_error_max > pb {
                v.push(format!(
                    "{}: int16 phase error {:.4} rad > bar {pb:.4}",
                    s.script, i16r.errors.phase_error_max
                ));
            }
            for blob in s.variants.iter().filter(|x| x.name != VARIANTS[0]) {
                for ((name, m), (_, r)) in blob.sanity.headline().iter().zip(s.reference.headline())
                {
                    if (m - r).abs() > sanity_bar(r) {
                        v.push(format!(
                            "{}: {} {name} {m:.3} vs float {r:.3} (allowed +-{:.3})",
                            s.script,
                            blob.name,
                            sanity_bar(r)
                        ));
                    }
                }
            }
        }
        v
    }

    /// Issue 13's closed-loop bars that the int8 blob misses, in words
    /// (empty when both hold on every script).
    pub fn int8_misses(&self) -> Vec<String> {
        let mut v = Vec::new();
        for s in &self.scripts {
            let Some(i8r) = s.variants.iter().find(|x| x.name == VARIANTS[2]) else {
                v.push(format!("{}: no int8 controller", s.script));
                continue;
            };
            let e = &i8r.errors;
            if e.worst_frame_p99 > INT8_JOINT_BAR {
                v.push(format!(
                    "{}: int8 worst-frame joint p99 {:.2} > {INT8_JOINT_BAR}",
                    s.script, e.worst_frame_p99
                ));
            }
            if e.root_drift_final > INT8_DRIFT_BAR {
                v.push(format!(
                    "{}: int8 final root drift {:.2} > {INT8_DRIFT_BAR}",
                    s.script, e.root_drift_final
                ));
            }
        }
        v
    }

    /// The full table, as Markdown.
    pub fn table(&self) -> String {
        let mut t = String::new();
        let _ = writeln!(
            t,
            "Each controller against the f64 float controller, {} frames per script (positions in capture units, about 1 cm; angles in radians).\n",
            self.frames
        );
        let _ = writeln!(t, "| script | controller | joint mean | joint p99 | worst-frame p99 (bar) | joint max | root drift final / max | heading drift max | phase error mean / max (bar) |");
        let _ = writeln!(t, "|---|---|---|---|---|---|---|---|---|");
        for s in &self.scripts {
            let f32_figs = s.variants.first().map(|f| f.errors).unwrap_or_default();
            for v in &s.variants {
                let e = &v.errors;
                let (jb, pb) = if v.name == VARIANTS[1] {
                    (
                        format!(" (<= {:.2})", joint_bar(f32_figs.worst_frame_p99)),
                        format!(" (<= {:.3})", phase_bar(f32_figs.phase_error_max)),
                    )
                } else {
                    (String::new(), String::new())
                };
                let _ = writeln!(
                    t,
                    "| {} | {} | {:.4} | {:.4} | {:.4}{jb} | {:.4} | {:.3} / {:.3} | {:.5} | {:.5} / {:.5}{pb} |",
                    s.script,
                    v.name,
                    e.joint_mean,
                    e.joint_p99,
                    e.worst_frame_p99,
                    e.joint_max,
                    e.root_drift_final,
                    e.root_drift_max,
                    e.heading_drift_max,
                    e.phase_error_mean,
                    e.phase_error_max
                );
            }
        }
        let _ = writeln!(
            t,
            "\nPhysical sanity (bar for the blobs: within max(10%, 0.5) of f64):\n"
        );
        let _ = writeln!(t, "| script | controller | bone length error | foot skating (units/s) | ground penetration | phase advance (rad/s) | contact share |");
        let _ = writeln!(t, "|---|---|---|---|---|---|---|");
        for s in &self.scripts {
            let rows = std::iter::once(("f64 float", &s.reference))
                .chain(s.variants.iter().map(|v| (v.name, &v.sanity)));
            for (name, m) in rows {
                let _ = writeln!(
                    t,
                    "| {} | {name} | {:.3} | {:.2} | {:.3} | {:.3} | {:.2} |",
                    s.script,
                    m.bone_error_mean,
                    m.skate_mean,
                    m.penetration_mean,
                    m.phase_rate,
                    m.contact_share
                );
            }
        }
        let _ = writeln!(
            t,
            "\nblobs: int16 cubic {} bytes, int8 cubic {} bytes",
            self.blob_bytes[0], self.blob_bytes[1]
        );
        t
    }
}

/// `host-sim fidelity`.
#[derive(Debug, clap::Args)]
pub struct FidelityArgs {
    /// The PFNN weight directory.
    #[arg(long)]
    pub pfnn: std::path::PathBuf,
    /// Frames per script.
    #[arg(long, default_value_t = 600, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
    pub frames: usize,
    /// Scripts (built-in names, tour names `tour-SEED-INDEX` or JSON
    /// files); all built-ins if none.
    #[arg(long = "script")]
    pub scripts: Vec<String>,
    /// Write every rollout here as `<script>-<f64|f32|int16|int8>.npz`.
    #[arg(long)]
    pub out_dir: Option<std::path::PathBuf>,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub int8: Int8Knobs,
}

/// `host-sim fidelity`: prints the table; fails if a bar does not hold.
pub fn fidelity_cmd(args: &FidelityArgs) -> Result<()> {
    let net = load_cubic(&args.pfnn)?;
    let blobs = export_blobs(&net, &args.int8)?;
    let (f, mut staged) = measure_staged(
        &net,
        &blobs,
        &args.scripts,
        args.frames,
        args.out_dir.as_deref(),
    )?;
    print!("{}", f.table());
    if let Some(p) = &args.json {
        staged.add(p, serde_json::to_vec_pretty(&f)?);
    }
    staged.commit()?;
    // Issue 13's int8 bars are reported, not enforced: the default int8
    // blob misses them, and calibrated on random tours they hold for some
    // tour seeds and not others (docs/fixed-point.md, "Rounding for the
    // closed loop").
    let misses = f.int8_misses();
    if misses.is_empty() {
        println!(
            "int8 closed-loop bars (worst-frame joint p99 <= {INT8_JOINT_BAR}, final root drift <= {INT8_DRIFT_BAR}): met on every script"
        );
    } else {
        println!(
            "int8 closed-loop bars missed (docs/fixed-point.md, \"Rounding for the closed loop\"):\n  {}",
            misses.join("\n  ")
        );
    }
    let v = f.violations();
    if v.is_empty() {
        println!("all fidelity bars hold");
        Ok(())
    } else {
        anyhow::bail!("fidelity bars missed:\n  {}", v.join("\n  "))
    }
}
