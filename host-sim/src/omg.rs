//! OMG models on the host: the reaching rollout loop of `tools/omg/omg_np.py`
//! (feed `Y` back as the next `X`, overwrite the target block every frame
//! and, in grounded mode, recompute the cost block from the decoded pose),
//! driven by the f64 graph forward ([`OmgNet::step`]) or by the fixed-point
//! runtime ([`FixedOmg`]), and the figures of `host-sim omg-accuracy`:
//! the f64 forward against the committed PyTorch references, and int16 /
//! int8 blobs against the f64 forward, one step and over the 300-frame
//! grounded rollout (`docs/omg.md`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use exporter::net::omg::{read_omg, OmgNet};
use exporter::quantise::QuantOptions;
use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase, Runtime};
use serde::Serialize;

use crate::eval::{host_runtime, HOST_CAPACITY};
use crate::quant_knobs::Int8Knobs;
use phasegate_controller::reach::{self, Reach, ReachLayout};
use phasegate_controller::Network;

/// A `(clips, frames, width)` array.
#[derive(Clone, Debug)]
pub struct Clips {
    /// Clips, frames, width.
    pub dims: [usize; 3],
    /// Values in C order.
    pub data: Vec<f64>,
}

impl Clips {
    /// Frame `t` of clip `c`.
    pub fn row(&self, c: usize, t: usize) -> &[f64] {
        let w = self.dims[2];
        &self.data[(c * self.dims[1] + t) * w..][..w]
    }

    /// Array `name` of an `.npz` read from `path`, which must be 3-D.
    pub(crate) fn take(
        arrays: &mut BTreeMap<String, exporter::npz::NpArray>,
        name: &str,
        path: &Path,
    ) -> Result<Clips> {
        let a = arrays
            .remove(name)
            .with_context(|| format!("{}: no array {name}", path.display()))?;
        let dims = match a.shape[..] {
            [c, t, w] => [c, t, w].map(|d| d as usize),
            _ => bail!(
                "{}: array {name} has shape {:?}, expected (clips, frames, width)",
                path.display(),
                a.shape
            ),
        };
        Ok(Clips { dims, data: a.data })
    }
}

/// The reference arrays committed beside a model (`references.npz`,
/// written by `tools/omg/train/references.py`): held-out frames and targets,
/// and PyTorch's outputs for them, computed in float64 from the stored
/// weights and saved as float32.
#[derive(Clone, Debug)]
pub struct References {
    /// Raw test frames (clips, F, n).
    pub inputs: Clips,
    /// PyTorch one-step outputs for them (clips, F, n).
    pub one_step: Clips,
    /// PyTorch grounded rollouts (clips, 300, n).
    pub rollout: Clips,
    /// The target block of every rollout frame (clips, 300, 9K).
    pub targets: Clips,
}

/// A model directory: the imported model and its references.
pub struct OmgDir {
    /// The directory.
    pub dir: PathBuf,
    /// The imported model.
    pub omg: OmgNet,
    /// Its references.
    pub refs: References,
}

/// Reads `config.json`, `model.safetensors` and `references.npz` of `dir`.
pub fn load_dir(dir: &Path) -> Result<OmgDir> {
    let omg = read_omg(&dir.join("model.safetensors"), &dir.join("config.json"))?;
    let path = dir.join("references.npz");
    let mut arrays = exporter::npz::read_npz(&path)?;
    let mut take = |name: &str| Clips::take(&mut arrays, name, &path);
    let refs = References {
        inputs: take("inputs")?,
        one_step: take("one_step")?,
        rollout: take("rollout_grounded")?,
        targets: take("rollout_targets")?,
    };
    let n = omg.config.model_width;
    let t = omg.config.slice("target").len();
    for (name, c, w) in [
        ("inputs", &refs.inputs, n),
        ("one_step", &refs.one_step, n),
        ("rollout_grounded", &refs.rollout, n),
        ("rollout_targets", &refs.targets, t),
    ] {
        if c.dims[2] != w {
            bail!(
                "{}: array {name} has width {}, expected {w}",
                path.display(),
                c.dims[2]
            );
        }
    }
    let [clips, frames, _] = refs.inputs.dims;
    if refs.one_step.dims[..2] != [clips, frames]
        || refs.rollout.dims[..2] != refs.targets.dims[..2]
        || refs.targets.dims[0] != clips
        || frames == 0
        || refs.rollout.dims[1] == 0
    {
        bail!(
            "{}: arrays of different clip or frame counts: inputs {:?}, one_step {:?}, \
             rollout_grounded {:?}, rollout_targets {:?}",
            path.display(),
            refs.inputs.dims,
            refs.one_step.dims,
            refs.rollout.dims,
            refs.targets.dims
        );
    }
    Ok(OmgDir {
        dir: dir.to_path_buf(),
        omg,
        refs,
    })
}

/// The controller's layout of `omg`'s frames (`phasegate_controller::reach`).
pub fn reach_layout(omg: &OmgNet) -> Result<ReachLayout> {
    let cfg = &omg.config;
    let key_joints = cfg
        .key_joint_indices
        .iter()
        .map(|&j| u16::try_from(j))
        .collect::<std::result::Result<heapless::Vec<u16, { reach::MAX_KEY }>, _>>()
        .map_err(|_| {
            anyhow!(
                "key joints {:?}: too many or too large",
                cfg.key_joint_indices
            )
        })?;
    if key_joints.len() != cfg.key_joint_indices.len() {
        bail!(
            "{} key joints: the controller takes at most {}",
            cfg.key,
            reach::MAX_KEY
        );
    }
    Ok(ReachLayout {
        width: cfg.model_width,
        pos: cfg.slice("pos"),
        rot: cfg.slice("rot"),
        cost: cfg.slice("cost"),
        target: cfg.slice("target"),
        key_joints,
        blocks: omg.blocks.clone(),
    })
}

/// What is fed back besides the network's output.
pub use phasegate_controller::CostMode as Mode;

/// The f64 graph forward as the controller's network.
pub struct FloatOmg<'n>(pub &'n OmgNet);

impl Network<f64> for FloatOmg<'_> {
    fn input_dim(&self) -> usize {
        self.0.net.input_dim()
    }
    fn output_dim(&self) -> usize {
        self.0.net.output_dim()
    }
    fn predict(&mut self, _: f64, x: &[f64], y: &mut [f64]) -> phasegate_controller::Result<()> {
        y.copy_from_slice(&self.0.net.forward(x, 0.0));
        Ok(())
    }
    fn mean_output(&self, y: &mut [f64]) -> phasegate_controller::Result<()> {
        y.fill(0.0);
        Ok(())
    }
}

/// Widest frame the host's rollouts take.
pub const MAX_WIDTH: usize = 2048;

/// The controller's reaching loop (`phasegate_controller::Reach`, in f64)
/// from frame `first`: every later frame `t` is one step of `net` with the
/// target block set to `targets[t]`. Returns every frame (raw units).
pub fn rollout(
    omg: &OmgNet,
    first: &[f64],
    targets: &[&[f64]],
    mode: Mode,
    net: &mut impl Network<f64>,
) -> Result<Vec<Vec<f64>>> {
    let mut reach: Box<Reach<f64, MAX_WIDTH>> =
        Box::new(Reach::new(net, reach_layout(omg)?, mode, first)?);
    let mut out = vec![first.to_vec()];
    for (t, target) in targets.iter().enumerate().skip(1) {
        reach
            .set_target_block(target)
            .with_context(|| format!("frame {t}"))?;
        reach.step(net).with_context(|| format!("frame {t}"))?;
        out.push(reach.frame().to_vec());
    }
    Ok(out)
}

/// The grounded rollout of clip `c` of the references by `net`.
pub fn reference_rollout(
    d: &OmgDir,
    c: usize,
    net: &mut impl Network<f64>,
) -> Result<Vec<Vec<f64>>> {
    let frames = d.refs.targets.dims[1];
    let targets: Vec<&[f64]> = (0..frames).map(|t| d.refs.targets.row(c, t)).collect();
    rollout(
        &d.omg,
        d.refs.inputs.row(c, 0),
        &targets,
        Mode::Grounded,
        net,
    )
}

/// One frame of a blob on the host runtime, raw units in and out (f32 at
/// the runtime's boundary).
pub struct FixedOmg<'b> {
    rt: Box<Runtime<'b, HOST_CAPACITY>>,
    q: Vec<i16>,
    xf: Vec<f32>,
    yf: Vec<f32>,
}

impl<'b> FixedOmg<'b> {
    /// Loads `blob` (an OMG graph blob).
    pub fn new(blob: &'b [u8]) -> Result<Self> {
        Self::with_model(Model::from_bytes(blob).map_err(|e| anyhow!("model blob: {e}"))?)
    }

    /// Loads a motion blob with a rig blob for it (docs/omg.md, "Rig blobs").
    pub fn with_rig(motion: &'b [u8], rig: &'b [u8]) -> Result<Self> {
        Self::with_model(Model::with_rig(motion, rig).map_err(|e| anyhow!("{e}"))?)
    }

    fn with_model(model: Model<'b>) -> Result<Self> {
        let (n_in, n_out) = (model.input_dim(), model.output_dim());
        Ok(FixedOmg {
            rt: host_runtime(model)?,
            q: vec![0; n_in],
            xf: vec![0.0; n_in],
            yf: vec![0.0; n_out],
        })
    }

    /// The loaded model.
    pub fn model(&self) -> &Model<'b> {
        self.rt.model()
    }

    /// The network's output for raw input `x`.
    pub fn run(&mut self, x: &[f64]) -> Result<Vec<f64>> {
        for (d, &s) in self.xf.iter_mut().zip(x) {
            *d = s as f32;
        }
        let zero = Phase::from_radians(0.0).map_err(|e| anyhow!("{e}"))?;
        self.rt
            .quantise_input(&self.xf, &mut self.q)
            .map_err(|e| anyhow!("{e}"))?;
        let y = self
            .rt
            .run_quantised(zero, &self.q)
            .map_err(|e| anyhow!("{e}"))?
            .to_vec();
        self.rt
            .dequantise_output(&y, &mut self.yf)
            .map_err(|e| anyhow!("{e}"))?;
        Ok(self.yf.iter().map(|&v| f64::from(v)).collect())
    }
}

impl Network<f64> for FixedOmg<'_> {
    fn input_dim(&self) -> usize {
        self.xf.len()
    }
    fn output_dim(&self) -> usize {
        self.yf.len()
    }
    fn predict(&mut self, _: f64, x: &[f64], y: &mut [f64]) -> phasegate_controller::Result<()> {
        for (d, &s) in self.xf.iter_mut().zip(x) {
            *d = s as f32;
        }
        self.rt
            .run(Phase::from_radians(0.0)?, &self.xf, &mut self.yf)?;
        for (d, &s) in y.iter_mut().zip(&self.yf) {
            *d = f64::from(s);
        }
        Ok(())
    }
    fn mean_output(&self, y: &mut [f64]) -> phasegate_controller::Result<()> {
        y.fill(0.0);
        Ok(())
    }
}

/// Differences between two sets of frames of one model.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Diff {
    /// Largest `|a - b| / max(|b|, std_j)` (std_j: the model's standard
    /// deviation of feature j): relative where |b| is above the feature's
    /// own spread, in units of that spread below it.
    pub max_rel: f64,
    /// Largest `|a - b|`, model units.
    pub max_abs: f64,
    /// Largest joint position difference (Euclidean, metres).
    pub max_joint_m: f64,
    /// 99th percentile of the joint position differences (metres).
    pub p99_joint_m: f64,
    /// Mean joint position difference (metres).
    pub mean_joint_m: f64,
    /// Frames compared.
    pub frames: usize,
}

/// Compares frames `a` against `b` (the reference).
pub fn diff(omg: &OmgNet, a: &[Vec<f64>], b: &[Vec<f64>]) -> Diff {
    let std = &omg.net.xstd;
    let pos = omg.config.slice("pos");
    let mut d = Diff {
        frames: a.len(),
        ..Diff::default()
    };
    let mut joints = Vec::new();
    for (x, y) in a.iter().zip(b) {
        for j in 0..x.len() {
            let e = (x[j] - y[j]).abs();
            d.max_abs = d.max_abs.max(e);
            d.max_rel = d.max_rel.max(e / y[j].abs().max(std[j]));
        }
        for j in 0..pos.len() / 3 {
            let p = pos.start + 3 * j;
            joints.push(
                (0..3)
                    .map(|k| (x[p + k] - y[p + k]).powi(2))
                    .sum::<f64>()
                    .sqrt(),
            );
        }
    }
    joints.sort_by(f64::total_cmp);
    if let Some(&m) = joints.last() {
        d.max_joint_m = m;
        d.p99_joint_m = joints[((joints.len() as f64 * 0.99).ceil() as usize).max(1) - 1];
        d.mean_joint_m = joints.iter().sum::<f64>() / joints.len() as f64;
    }
    d
}

/// The f64 graph forward against the PyTorch (float64) references.
#[derive(Clone, Debug, Serialize)]
pub struct FloatAgreement {
    /// One step on the reference inputs vs PyTorch's outputs.
    pub one_step: Diff,
    /// The grounded rollouts vs PyTorch's (all clips' frames).
    pub rollout: Diff,
}

fn frames_of(c: &Clips, clip: usize) -> Vec<Vec<f64>> {
    (0..c.dims[1]).map(|t| c.row(clip, t).to_vec()).collect()
}

/// Every one-step output of `step` on the reference inputs, all clips.
fn one_step(d: &OmgDir, mut step: impl FnMut(&[f64]) -> Result<Vec<f64>>) -> Result<Vec<Vec<f64>>> {
    let [clips, frames, _] = d.refs.inputs.dims;
    let mut out = Vec::new();
    for c in 0..clips {
        for t in 0..frames {
            out.push(step(d.refs.inputs.row(c, t))?);
        }
    }
    Ok(out)
}

fn all_frames(c: &Clips) -> Vec<Vec<f64>> {
    (0..c.dims[0]).flat_map(|k| frames_of(c, k)).collect()
}

/// The f64 rollouts of every reference clip.
pub fn float_rollouts(d: &OmgDir) -> Result<Vec<Vec<f64>>> {
    let mut out = Vec::new();
    for c in 0..d.refs.targets.dims[0] {
        out.extend(reference_rollout(d, c, &mut FloatOmg(&d.omg))?);
    }
    Ok(out)
}

/// Measures [`FloatAgreement`].
pub fn float_agreement(d: &OmgDir) -> Result<FloatAgreement> {
    let y = one_step(d, |x| Ok(d.omg.step(x)))?;
    let ro = float_rollouts(d)?;
    Ok(FloatAgreement {
        one_step: diff(&d.omg, &y, &all_frames(&d.refs.one_step)),
        rollout: diff(&d.omg, &ro, &all_frames(&d.refs.rollout)),
    })
}

/// A blob against the f64 forward.
#[derive(Clone, Debug, Serialize)]
pub struct FixedAgreement {
    /// "int16" or "int8".
    pub weights: &'static str,
    /// Blob bytes.
    pub blob_bytes: usize,
    /// MACs per frame.
    pub macs_per_frame: u32,
    /// Activation RAM, bytes.
    pub ram_bytes: usize,
    /// One step on the reference inputs vs the f64 forward.
    pub one_step: Diff,
    /// Largest one-step error of the pose block's positions, metres (per
    /// coordinate).
    pub one_step_pos_max_m: f64,
    /// The fixed-point grounded rollouts vs the f64 ones (all clips, all
    /// frames).
    pub rollout: Diff,
    /// The same over each clip's first [`HORIZONS`] frames.
    pub rollout_by_horizon: Vec<(usize, Diff)>,
}

/// Rollout lengths the differences are also given for.
pub const HORIZONS: [usize; 3] = [30, 100, 200];

/// `diff` over each clip's first `h` frames of rollouts laid out clip
/// after clip, `frames` per clip.
fn diff_within(omg: &OmgNet, a: &[Vec<f64>], b: &[Vec<f64>], frames: usize, h: usize) -> Diff {
    let pick = |v: &[Vec<f64>]| -> Vec<Vec<f64>> {
        v.iter()
            .enumerate()
            .filter(|(i, _)| i % frames < h)
            .map(|(_, r)| r.clone())
            .collect()
    };
    diff(omg, &pick(a), &pick(b))
}

/// How sensitive the model's own grounded rollout is: the f64 rollout of
/// the net with every dense weight moved by uniform noise of half an int8
/// step (per row, the step of the row's largest weight over its experts,
/// as the quantiser's scale), against the unperturbed f64 rollout. A model
/// whose rollout diverges under this noise cannot follow its f64 rollout
/// at int8, whatever the rounding.
pub fn int8_sized_noise(d: &OmgDir, seed: u64) -> Result<Diff> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut noisy = d.omg.clone();
    for l in &mut noisy.net.layers {
        let exporter::net::NetLayer::Dense(e) = l else {
            continue;
        };
        let rows = e.w[0].nrows();
        for r in 0..rows {
            let max =
                e.w.iter()
                    .flat_map(|w| w.row(r).to_vec())
                    .fold(0.0, |m: f64, v| m.max(v.abs()));
            let step = max / 127.0;
            for w in &mut e.w {
                for v in w.row_mut(r) {
                    if *v != 0.0 {
                        *v += (rng.gen::<f64>() - 0.5) * step;
                    }
                }
            }
        }
    }
    let ro_float = float_rollouts(d)?;
    let mut ro = Vec::new();
    for c in 0..d.refs.targets.dims[0] {
        ro.extend(reference_rollout(d, c, &mut FloatOmg(&noisy))?);
    }
    Ok(diff(&d.omg, &ro, &ro_float))
}

/// Measures a blob of `d`'s model against its f64 forward.
pub fn fixed_agreement(d: &OmgDir, blob: &[u8], weights: &'static str) -> Result<FixedAgreement> {
    let model = Model::from_bytes(blob).map_err(|e| anyhow!("model blob: {e}"))?;
    agreement(d, model, FixedOmg::new(blob)?, weights)
}

/// Measures a motion blob with a rig blob against the f64 forward of
/// `d`'s model (the rig's); `blob_bytes` is the rig blob's.
pub fn rig_agreement(
    d: &OmgDir,
    motion: &[u8],
    rig: &[u8],
    weights: &'static str,
) -> Result<FixedAgreement> {
    let model = Model::with_rig(motion, rig).map_err(|e| anyhow!("{e}"))?;
    agreement(d, model, FixedOmg::with_rig(motion, rig)?, weights)
}

/// `host-sim omg-accuracy DIR --motion M --rig R`: the pair against the
/// f64 forward of `dir`'s model, as a table and as figures.
pub fn rig_pair_report(dir: &Path, motion: &Path, rig: &Path) -> Result<(String, FixedAgreement)> {
    let read = |p: &Path| {
        exporter::atomic::read_input(p).with_context(|| format!("cannot read {}", p.display()))
    };
    let (m, r) = (read(motion)?, read(rig)?);
    let d = load_dir(dir)?;
    let a = rig_agreement(&d, &m, &r, "rig")
        .with_context(|| format!("{} with {}", rig.display(), motion.display()))?;
    let horizons: Vec<String> = a
        .rollout_by_horizon
        .iter()
        .map(|(h, x)| format!("{h}: {:.4}", x.p99_joint_m * 100.0))
        .collect();
    let text = format!(
        "{} + rig {} vs the f64 forward of {}\n  motion blob {} bytes, rig blob {} bytes; \
         the pair needs {} bytes of activation RAM ({} i16 elements), {} MACs per frame\n  \
         one step: joint p99 {:.4} cm, max {:.4} cm, position max {:.4} cm\n  \
         grounded rollout: joint p99 {:.4} cm, max {:.4} cm, mean {:.4} cm; p99 by horizon (cm) {}\n",
        motion.display(),
        rig.display(),
        dir.display(),
        m.len(),
        r.len(),
        a.ram_bytes,
        a.ram_bytes / 2,
        a.macs_per_frame,
        a.one_step.p99_joint_m * 100.0,
        a.one_step.max_joint_m * 100.0,
        a.one_step_pos_max_m * 100.0,
        a.rollout.p99_joint_m * 100.0,
        a.rollout.max_joint_m * 100.0,
        a.rollout.mean_joint_m * 100.0,
        horizons.join(", ")
    );
    Ok((text, a))
}

fn agreement(
    d: &OmgDir,
    model: Model<'_>,
    mut fx: FixedOmg<'_>,
    weights: &'static str,
) -> Result<FixedAgreement> {
    let yf = one_step(d, |x| Ok(d.omg.frame(&fx.run(x)?, x)))?;
    let yr = one_step(d, |x| Ok(d.omg.step(x)))?;
    let pos = d.omg.config.slice("pos");
    let one_step_pos_max_m = yf
        .iter()
        .zip(&yr)
        .flat_map(|(a, b)| pos.clone().map(move |j| (a[j] - b[j]).abs()))
        .fold(0.0, f64::max);
    let ro_float = float_rollouts(d)?;
    let mut ro_fixed = Vec::new();
    for c in 0..d.refs.targets.dims[0] {
        ro_fixed.extend(reference_rollout(d, c, &mut fx)?);
    }
    Ok(FixedAgreement {
        weights,
        blob_bytes: model.blob_len(),
        macs_per_frame: model.macs_per_frame(),
        ram_bytes: model.ram_bytes(),
        one_step: diff(&d.omg, &yf, &yr),
        one_step_pos_max_m,
        rollout: diff(&d.omg, &ro_fixed, &ro_float),
        rollout_by_horizon: HORIZONS
            .iter()
            .map(|&h| {
                let frames = d.refs.targets.dims[1];
                (h, diff_within(&d.omg, &ro_fixed, &ro_float, frames, h))
            })
            .collect(),
    })
}

/// The quantiser options `exporter omg` uses when given only
/// `--weight-bits`: `weights`, headroom [`exporter::net::omg::HEADROOM`].
pub fn exporter_options(weights: WeightFormat) -> QuantOptions {
    QuantOptions {
        weights,
        headroom: exporter::net::omg::HEADROOM,
        ..QuantOptions::default()
    }
}

/// Exports `d`'s model with `opts` at `weights`.
pub fn export(d: &OmgDir, weights: WeightFormat, opts: &QuantOptions) -> Result<Vec<u8>> {
    let opts = QuantOptions {
        weights,
        ..opts.clone()
    };
    Ok(exporter::export::export(&d.omg.net, None, &opts)?.0)
}

/// `host-sim omg-accuracy`'s figures for one model directory.
#[derive(Clone, Debug, Serialize)]
pub struct OmgAccuracy {
    /// The directory.
    pub dir: String,
    /// f64 forward vs PyTorch.
    pub float: FloatAgreement,
    /// int16 and int8 blobs vs the f64 forward.
    pub fixed: Vec<FixedAgreement>,
    /// [`int8_sized_noise`] with seeds 0 and 1.
    pub int8_sized_noise: Vec<Diff>,
}

/// Measures everything for `dir`, the blobs quantised with `opts` (its
/// weight format aside), the int8 blob also with `int8`'s knobs.
pub fn measure(dir: &Path, opts: &QuantOptions, int8: &Int8Knobs) -> Result<OmgAccuracy> {
    let d = load_dir(dir)?;
    let float = float_agreement(&d)?;
    let int16 = export(&d, WeightFormat::I16, opts)?;
    let int8_opts = QuantOptions {
        weights: WeightFormat::I8,
        ..opts.clone()
    };
    let (int8, _) = int8.export(&d.omg.net, None, int8_opts)?;
    let fixed = vec![
        fixed_agreement(&d, &int16, "int16")?,
        fixed_agreement(&d, &int8, "int8")?,
    ];
    Ok(OmgAccuracy {
        dir: dir.display().to_string(),
        float,
        fixed,
        int8_sized_noise: vec![int8_sized_noise(&d, 0)?, int8_sized_noise(&d, 1)?],
    })
}

impl OmgAccuracy {
    /// The figures as a table.
    pub fn table(&self) -> String {
        let mut s = format!("{}\n", self.dir);
        let f = &self.float;
        s += &format!(
            "f64 forward vs PyTorch float64: one step ({} frames) max rel {:.2e}, max abs {:.2e}; \
             grounded rollout ({} frames) max rel {:.2e}, max abs {:.2e}, max joint {:.2e} m\n",
            f.one_step.frames,
            f.one_step.max_rel,
            f.one_step.max_abs,
            f.rollout.frames,
            f.rollout.max_rel,
            f.rollout.max_abs,
            f.rollout.max_joint_m
        );
        s += "blob   bytes   MACs/frame  RAM B | one step vs f64: pos max cm  joint p99 cm  joint max cm | \
              rollout vs f64: joint p99 cm  joint max cm  mean cm\n";
        for x in &self.fixed {
            s += &format!(
                "{:<6} {:>7} {:>10} {:>6} | {:>27.3} {:>13.3} {:>13.3} | {:>29.3} {:>13.3} {:>8.3}\n",
                x.weights,
                x.blob_bytes,
                x.macs_per_frame,
                x.ram_bytes,
                100.0 * x.one_step_pos_max_m,
                100.0 * x.one_step.p99_joint_m,
                100.0 * x.one_step.max_joint_m,
                100.0 * x.rollout.p99_joint_m,
                100.0 * x.rollout.max_joint_m,
                100.0 * x.rollout.mean_joint_m,
            );
        }
        for x in &self.fixed {
            s += &format!("{:<6} rollout joint p99 cm over the first", x.weights);
            for (h, d) in &x.rollout_by_horizon {
                s += &format!(" {h} frames {:.3},", 100.0 * d.p99_joint_m);
            }
            s += &format!(" 300 frames {:.3}\n", 100.0 * x.rollout.p99_joint_m);
        }
        for (seed, n) in self.int8_sized_noise.iter().enumerate() {
            s += &format!(
                "f64 with int8-sized weight noise (seed {seed}) vs f64: rollout joint p99 {:.3} cm, \
                 max {:.3} cm\n",
                100.0 * n.p99_joint_m,
                100.0 * n.max_joint_m
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exporter::net::omg::OmgConfig;

    #[test]
    fn the_layout_follows_the_config() {
        // J = 2, K = 1, key joint 1.
        let json = r#"{"format":"phasegate-omg-1","variant":"FE","J":2,"K":1,
            "key_joint_indices":[1],"model_width":41,
            "sizes":{"ae_hidden":1,"latent":1,"cost_hidden":1,"expert_hidden":1,"gate_hidden":1,"experts":1},
            "slices":{"phase":[0,2],"pos":[2,8],"rot":[8,20],"vel":[20,26],"pose":[2,26],
              "cost":[26,32],"pos_cost":[26,29],"rot_cost":[29,32],"target":[32,41],
              "target_pos":[32,35],"target_rot":[35,41]},
            "out_slices":{"dphase":[0,2],"z":[2,3],"cost":[3,9]},
            "phase_update":{"a":0.9},"mode":"grounded"}"#;
        let config: OmgConfig = serde_json::from_str(json).unwrap();
        let omg = OmgNet {
            config,
            net: exporter::net::Net {
                mode: exporter::net::GatingMode::Constant,
                xmean: Default::default(),
                xstd: Default::default(),
                ymean: Default::default(),
                ystd: Default::default(),
                layers: vec![],
                wiring: Default::default(),
            },
            blocks: [(0..2, 0..2), (2..26, 2..26), (26..32, 26..32)],
            target: 32..41,
        };
        let l = reach_layout(&omg).unwrap();
        assert_eq!(
            (l.pos, l.rot, l.cost, l.target),
            (2..8, 8..20, 26..32, 32..41)
        );
        assert_eq!(l.key_joints.as_slice(), &[1]);
        assert_eq!(l.width, 41);
    }

    /// Name, shape and values of one array of an `.npz`.
    type Array = (&'static str, Vec<u64>, Vec<f32>);

    /// A copy of the committed tiny FE whose `references.npz` holds
    /// `arrays` instead of its own.
    fn with_references(arrays: &[Array]) -> (tempfile::TempDir, PathBuf) {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("m");
        std::fs::create_dir(&dir).unwrap();
        for f in ["config.json", "model.safetensors"] {
            std::fs::copy(src.join(f), dir.join(f)).unwrap();
        }
        exporter::npz::write_npz(&dir.join("references.npz"), arrays).unwrap();
        (tmp, dir)
    }

    #[test]
    fn damaged_references_are_refused_naming_the_file_and_the_array() {
        let (n, t) = (440u64, 36u64);
        let a = |c: u64, f: u64, w: u64| vec![0.5f32; (c * f * w) as usize];
        let good = |name: &'static str| match name {
            "inputs" | "one_step" => (name, vec![1, 2, n], a(1, 2, n)),
            "rollout_grounded" => (name, vec![1, 3, n], a(1, 3, n)),
            _ => (name, vec![1, 3, t], a(1, 3, t)),
        };
        let names = ["inputs", "one_step", "rollout_grounded", "rollout_targets"];
        let all: Vec<_> = names.iter().map(|&k| good(k)).collect();
        let (_t, dir) = with_references(&all);
        let d = load_dir(&dir).unwrap();
        assert_eq!(d.refs.rollout.dims, [1, 3, 440]);

        let cases: [(Vec<Array>, &str); 4] = [
            (all[..3].to_vec(), "no array rollout_targets"),
            (
                vec![
                    all[0].clone(),
                    ("one_step", vec![2, n], a(1, 2, n)),
                    all[2].clone(),
                    all[3].clone(),
                ],
                "array one_step has shape [2, 440], expected (clips, frames, width)",
            ),
            (
                vec![
                    all[0].clone(),
                    all[1].clone(),
                    ("rollout_grounded", vec![1, 3, 7], a(1, 3, 7)),
                    all[3].clone(),
                ],
                "array rollout_grounded has width 7, expected 440",
            ),
            (
                vec![
                    all[0].clone(),
                    all[1].clone(),
                    ("rollout_grounded", vec![1, 4, n], a(1, 4, n)),
                    all[3].clone(),
                ],
                "arrays of different clip or frame counts",
            ),
        ];
        for (arrays, want) in cases {
            let (_t, dir) = with_references(&arrays);
            let e = format!("{:#}", load_dir(&dir).err().unwrap());
            assert!(e.contains("references.npz"), "{e}");
            assert!(e.contains(want), "{e}");
        }
    }
}
