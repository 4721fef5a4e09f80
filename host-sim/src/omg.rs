//! OMG models on the host: the reaching rollout loop of `tools/omg/omg_np.py`
//! (feed `Y` back as the next `X`, overwrite the target block every frame
//! and, in grounded mode, recompute the cost block from the decoded pose),
//! driven by the f64 graph forward ([`FloatOmg`]) or by the fixed-point
//! runtime ([`FixedOmg`]), and the figures of `host-sim omg-accuracy`:
//! the f64 forward against the committed PyTorch references, and int16 /
//! int8 blobs against the f64 forward, one step and over the 300-frame
//! grounded rollout (`docs/omg.md`).
//!
//! Joint-velocity models (`docs/omg-joint-velocity.md`) run the same loop
//! (`phasegate_controller::Reach::with_dofs`) from a [`Start`] that also
//! holds the joint angles and velocities; their one-step figures compare
//! network outputs (`[phase', u, cost']`, no pose), their rollouts frames
//! as for every model.

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use exporter::net::omg::{read_omg, OmgNet, OmgSkeleton};
use exporter::quantise::QuantOptions;
use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase, Runtime};
use serde::Serialize;

use crate::eval::{host_runtime, HOST_CAPACITY};
use crate::quant_knobs::Int8Knobs;
use phasegate_controller::reach::{self, Dof, Joint, PoseForm, Reach, ReachLayout, Skeleton};
use phasegate_controller::{Network, Real};

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
    /// A joint-velocity model's start states and joint angles.
    pub dof: Option<DofReferences>,
}

/// The references of a joint-velocity model beside the frames:
/// `rollout_q0`, `rollout_v0` (clips, D) and `rollout_dof` (clips, 300, D).
#[derive(Clone, Debug)]
pub struct DofReferences {
    /// Each rollout's start joint angles, radians.
    pub q0: Vec<Vec<f64>>,
    /// Each rollout's start joint velocities, rad/s.
    pub v0: Vec<Vec<f64>>,
    /// The loop's joint angles at every rollout frame.
    pub dof: Clips,
}

/// Where a rollout starts: the first frame and, for a joint-velocity
/// model, the joint angles and velocities that go with it (empty for an
/// absolute model).
#[derive(Clone, Debug, PartialEq)]
pub struct Start {
    /// The first frame `X` (raw units).
    pub first: Vec<f64>,
    /// Joint angles `q0`, radians (joint-velocity models).
    pub q0: Vec<f64>,
    /// Joint velocities `v0`, rad/s (joint-velocity models).
    pub v0: Vec<f64>,
}

impl Start {
    /// An absolute model's start: the frame alone.
    pub fn frame(first: &[f64]) -> Start {
        Start {
            first: first.to_vec(),
            q0: Vec::new(),
            v0: Vec::new(),
        }
    }

    /// A clip's start from its frame 0 (the model's width) and, for a
    /// joint-velocity model, that frame's joint angles `q0` (the data's
    /// `dof` block; `None` when the data has none) with `v0 = q0 * fps`
    /// (the data's frame 0 is one IK step from rest).
    pub fn clip(omg: &OmgNet, first: &[f64], q0: Option<&[f64]>) -> Result<Start> {
        let Some(form) = &omg.dof else {
            return Ok(Start::frame(first));
        };
        let q0 = q0.context(
            "a joint-velocity model starts a clip from its joint angles: the data has no dof block \
             (regenerate it with tools/omg/generate)",
        )?;
        let d = form.skeleton.dofs.len();
        if q0.len() != d {
            bail!(
                "the data's dof block has {} values, the model's rig {d} DOFs",
                q0.len()
            );
        }
        let fps = form.skeleton.fps;
        Ok(Start {
            first: first.to_vec(),
            q0: q0.to_vec(),
            v0: q0.iter().map(|q| q * fps).collect(),
        })
    }

    /// A joint-velocity model's start from rest for the target block
    /// `targets` ([`reach::rest_frame`]: FK of `q = 0`, zero velocities,
    /// phases 0, the costs grounded on the targets; `q0 = v0 = 0`). An
    /// absolute model has no rest of its own: `None`.
    pub fn rest(omg: &OmgNet, targets: &[f64]) -> Result<Option<Start>> {
        let Some(form) = &omg.dof else {
            return Ok(None);
        };
        let mut first = vec![0.0; omg.config.model_width];
        reach::rest_frame(
            &reach_layout(omg)?,
            &skeleton::<f64>(&form.skeleton)?,
            targets,
            &mut first,
        )
        .map_err(|e| anyhow!("rest frame: {e}"))?;
        let d = form.skeleton.dofs.len();
        Ok(Some(Start {
            first,
            q0: vec![0.0; d],
            v0: vec![0.0; d],
        }))
    }

    /// The target block of a rest frame whose key joints are their own
    /// targets (each key joint's position and forward/up axes): what the
    /// targets a script leaves unnamed hold when it starts from rest.
    pub fn rest_targets(omg: &OmgNet) -> Result<Vec<f64>> {
        let cfg = &omg.config;
        let k = cfg.key;
        let mut t = vec![0.0; 9 * k];
        for h in 0..k {
            t[3 * k + 6 * h + 2] = 1.0;
            t[3 * k + 6 * h + 4] = 1.0;
        }
        let Some(rest) = Start::rest(omg, &t)? else {
            bail!("an absolute model has no rest frame of its own");
        };
        let (pos, rot) = (cfg.slice("pos"), cfg.slice("rot"));
        for (h, &j) in cfg.key_joint_indices.iter().enumerate() {
            t[3 * h..3 * h + 3].copy_from_slice(&rest.first[pos.start + 3 * j..][..3]);
            t[3 * k + 6 * h..3 * k + 6 * h + 6]
                .copy_from_slice(&rest.first[rot.start + 6 * j..][..6]);
        }
        Ok(t)
    }
}

/// The controller's skeleton of a joint-velocity model, in `R`.
pub fn skeleton<R: Real>(sk: &OmgSkeleton) -> Result<Skeleton<R>> {
    let joints = sk
        .parents
        .iter()
        .zip(&sk.offsets)
        .map(|(p, o)| {
            Ok(Joint {
                parent: p.map(u16::try_from).transpose()?,
                offset: o.map(R::lit),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let dofs = sk
        .dofs
        .iter()
        .map(|d| {
            Ok(Dof {
                joint: u16::try_from(d.joint)?,
                axis: u8::try_from(d.axis)?,
                lower: R::lit(d.lower),
                upper: R::lit(d.upper),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Skeleton::new(joints, dofs, R::lit(sk.fps), R::lit(sk.a_max))
        .map_err(|e| anyhow!("controller.skeleton: {e}"))
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
    let mut refs = References {
        inputs: take("inputs")?,
        one_step: take("one_step")?,
        rollout: take("rollout_grounded")?,
        targets: take("rollout_targets")?,
        dof: None,
    };
    let n = omg.config.model_width;
    let t = omg.config.slice("target").len();
    // A joint-velocity model's one step is its network output.
    let n_one = match omg.dof {
        None => n,
        Some(_) => omg.net.output_dim(),
    };
    for (name, c, w) in [
        ("inputs", &refs.inputs, n),
        ("one_step", &refs.one_step, n_one),
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
    if let Some(form) = &omg.dof {
        let d = form.skeleton.dofs.len();
        let [clips, frames, _] = refs.rollout.dims;
        let mut two = |name: &str| -> Result<Vec<Vec<f64>>> {
            let a = arrays
                .remove(name)
                .with_context(|| format!("{}: no array {name}", path.display()))?;
            if a.shape != [clips as u64, d as u64] {
                bail!(
                    "{}: array {name} has shape {:?}, expected [{clips}, {d}] (clips, DOFs)",
                    path.display(),
                    a.shape
                );
            }
            Ok(a.data.chunks(d.max(1)).map(<[f64]>::to_vec).collect())
        };
        let (q0, v0) = (two("rollout_q0")?, two("rollout_v0")?);
        let dof = Clips::take(&mut arrays, "rollout_dof", &path)?;
        if dof.dims != [clips, frames, d] {
            bail!(
                "{}: array rollout_dof has shape {:?}, expected [{clips}, {frames}, {d}]",
                path.display(),
                dof.dims
            );
        }
        refs.dof = Some(DofReferences { q0, v0, dof });
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
        pose: match &omg.dof {
            None => PoseForm::Absolute,
            Some(form) => PoseForm::DofVelocity {
                out: form.u.clone(),
                vel: cfg.slice("vel"),
            },
        },
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
/// from `start`: every later frame `t` is one step of `net` with the
/// target block set to `targets[t]`. Returns every frame (raw units).
pub fn rollout(
    omg: &OmgNet,
    start: &Start,
    targets: &[&[f64]],
    mode: Mode,
    net: &mut impl Network<f64>,
) -> Result<Vec<Vec<f64>>> {
    Ok(rollout_dofs(omg, start, targets, mode, net)?.0)
}

/// Every frame of a rollout, and its joint angles (one empty row per frame
/// for an absolute model).
pub type FramesAndDofs = (Vec<Vec<f64>>, Vec<Vec<f64>>);

/// [`rollout`], and the joint angles of every frame (empty for an
/// absolute model).
pub fn rollout_dofs(
    omg: &OmgNet,
    start: &Start,
    targets: &[&[f64]],
    mode: Mode,
    net: &mut impl Network<f64>,
) -> Result<FramesAndDofs> {
    let layout = reach_layout(omg)?;
    let first = &start.first;
    let mut reach: Box<Reach<f64, MAX_WIDTH>> = Box::new(match &omg.dof {
        None => Reach::new(net, layout, mode, first)?,
        Some(form) => Reach::with_dofs(
            net,
            layout,
            mode,
            first,
            skeleton(&form.skeleton)?,
            &start.q0,
            &start.v0,
        )?,
    });
    let mut out = vec![first.to_vec()];
    let mut dofs = vec![reach.dof().to_vec()];
    for (t, target) in targets.iter().enumerate().skip(1) {
        reach
            .set_target_block(target)
            .with_context(|| format!("frame {t}"))?;
        reach.step(net).with_context(|| format!("frame {t}"))?;
        out.push(reach.frame().to_vec());
        dofs.push(reach.dof().to_vec());
    }
    Ok((out, dofs))
}

/// Where reference clip `c`'s rollout starts: its first input frame and,
/// for a joint-velocity model, `rollout_q0` / `rollout_v0`.
pub fn reference_start(d: &OmgDir, c: usize) -> Start {
    let mut s = Start::frame(d.refs.inputs.row(c, 0));
    if let Some(r) = &d.refs.dof {
        s.q0 = r.q0[c].clone();
        s.v0 = r.v0[c].clone();
    }
    s
}

/// The grounded rollout of clip `c` of the references by `net`.
pub fn reference_rollout(
    d: &OmgDir,
    c: usize,
    net: &mut impl Network<f64>,
) -> Result<Vec<Vec<f64>>> {
    Ok(reference_rollout_dofs(d, c, net)?.0)
}

/// [`reference_rollout`] with the joint angles of every frame.
pub fn reference_rollout_dofs(
    d: &OmgDir,
    c: usize,
    net: &mut impl Network<f64>,
) -> Result<FramesAndDofs> {
    let frames = d.refs.targets.dims[1];
    let targets: Vec<&[f64]> = (0..frames).map(|t| d.refs.targets.row(c, t)).collect();
    rollout_dofs(
        &d.omg,
        &reference_start(d, c),
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

/// Compares network outputs `a` against `b` (the reference), relative to
/// the output statistics (`max_rel` as in [`diff`]); no joint figures:
/// a joint-velocity model's output has no pose.
pub fn diff_outputs(omg: &OmgNet, a: &[Vec<f64>], b: &[Vec<f64>]) -> Diff {
    let std = &omg.net.ystd;
    let mut d = Diff {
        frames: a.len(),
        ..Diff::default()
    };
    for (x, y) in a.iter().zip(b) {
        for j in 0..x.len() {
            let e = (x[j] - y[j]).abs();
            d.max_abs = d.max_abs.max(e);
            d.max_rel = d.max_rel.max(e / y[j].abs().max(std[j]));
        }
    }
    d
}

/// One step of `omg` compared the way its form allows: frames ([`diff`])
/// for an absolute model, network outputs ([`diff_outputs`]) for a
/// joint-velocity one.
fn diff_one_step(omg: &OmgNet, a: &[Vec<f64>], b: &[Vec<f64>]) -> Diff {
    match omg.dof {
        None => diff(omg, a, b),
        Some(_) => diff_outputs(omg, a, b),
    }
}

/// The one-step result of `omg` for frame `x` from its network output
/// `out`: the next frame (absolute) or the output itself (joint velocity).
fn one_step_of(omg: &OmgNet, out: &[f64], x: &[f64]) -> Vec<f64> {
    match omg.dof {
        None => omg.frame(out, x),
        Some(_) => out.to_vec(),
    }
}

/// The f64 graph forward against the PyTorch (float64) references.
#[derive(Clone, Debug, Serialize)]
pub struct FloatAgreement {
    /// One step on the reference inputs vs PyTorch's outputs (frames; a
    /// joint-velocity model's network outputs).
    pub one_step: Diff,
    /// The grounded rollouts vs PyTorch's (all clips' frames).
    pub rollout: Diff,
    /// A joint-velocity model's rollout joint angles vs `rollout_dof`:
    /// the largest difference, radians.
    pub rollout_dof_max_rad: Option<f64>,
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
    let y = one_step(d, |x| Ok(one_step_of(&d.omg, &d.omg.output(x), x)))?;
    let mut ro = Vec::new();
    let mut dof_max: Option<f64> = None;
    for c in 0..d.refs.targets.dims[0] {
        let (frames, dofs) = reference_rollout_dofs(d, c, &mut FloatOmg(&d.omg))?;
        ro.extend(frames);
        if let Some(r) = &d.refs.dof {
            for (t, q) in dofs.iter().enumerate() {
                let m = q
                    .iter()
                    .zip(r.dof.row(c, t))
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                dof_max = Some(dof_max.unwrap_or(0.0).max(m));
            }
        }
    }
    Ok(FloatAgreement {
        one_step: diff_one_step(&d.omg, &y, &all_frames(&d.refs.one_step)),
        rollout: diff(&d.omg, &ro, &all_frames(&d.refs.rollout)),
        rollout_dof_max_rad: dof_max,
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
    /// One step on the reference inputs vs the f64 forward (frames; a
    /// joint-velocity model's network outputs, no joint figures).
    pub one_step: Diff,
    /// Largest one-step error of the pose block's positions, metres (per
    /// coordinate; 0 for a joint-velocity model).
    pub one_step_pos_max_m: f64,
    /// A joint-velocity model's largest one-step error of `u`, radians
    /// per frame.
    pub one_step_u_max_rad: Option<f64>,
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
    let yf = one_step(d, |x| Ok(one_step_of(&d.omg, &fx.run(x)?, x)))?;
    let yr = one_step(d, |x| Ok(one_step_of(&d.omg, &d.omg.output(x), x)))?;
    let largest = |r: Range<usize>| {
        yf.iter()
            .zip(&yr)
            .flat_map(|(a, b)| r.clone().map(move |j| (a[j] - b[j]).abs()))
            .fold(0.0, f64::max)
    };
    let (one_step_pos_max_m, one_step_u_max_rad) = match &d.omg.dof {
        None => (largest(d.omg.config.slice("pos")), None),
        Some(form) => (0.0, Some(largest(form.u.clone()))),
    };
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
        one_step: diff_one_step(&d.omg, &yf, &yr),
        one_step_pos_max_m,
        one_step_u_max_rad,
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
        let dof = f.rollout_dof_max_rad.is_some();
        s += &format!(
            "f64 forward vs PyTorch float64: one step ({} {}) max rel {:.2e}, max abs {:.2e}; \
             grounded rollout ({} frames) max rel {:.2e}, max abs {:.2e}, max joint {:.2e} m{}\n",
            f.one_step.frames,
            if dof { "network outputs" } else { "frames" },
            f.one_step.max_rel,
            f.one_step.max_abs,
            f.rollout.frames,
            f.rollout.max_rel,
            f.rollout.max_abs,
            f.rollout.max_joint_m,
            f.rollout_dof_max_rad
                .map_or(String::new(), |r| format!(", joint angles max {r:.2e} rad"))
        );
        if dof {
            s += "blob   bytes   MACs/frame  RAM B | one step vs f64: u max rad/frame  output max rel | \
                  rollout vs f64: joint p99 cm  joint max cm  mean cm\n";
        } else {
            s += "blob   bytes   MACs/frame  RAM B | one step vs f64: pos max cm  joint p99 cm  joint max cm | \
                  rollout vs f64: joint p99 cm  joint max cm  mean cm\n";
        }
        for x in &self.fixed {
            let one = match x.one_step_u_max_rad {
                Some(u) => format!("{u:>32.2e} {:>15.2e}", x.one_step.max_rel),
                None => format!(
                    "{:>27.3} {:>13.3} {:>13.3}",
                    100.0 * x.one_step_pos_max_m,
                    100.0 * x.one_step.p99_joint_m,
                    100.0 * x.one_step.max_joint_m
                ),
            };
            s += &format!(
                "{:<6} {:>7} {:>10} {:>6} | {one} | {:>29.3} {:>13.3} {:>8.3}\n",
                x.weights,
                x.blob_bytes,
                x.macs_per_frame,
                x.ram_bytes,
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
pub(crate) mod tests {
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
            dof: None,
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

    /// The first committed absolute R1 model (`models/omg/*`, by name;
    /// frames of 440 values, 36 target values); `None` when every one
    /// outputs joint velocities.
    fn absolute_r1_model() -> Option<PathBuf> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg");
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(&root)
            .ok()?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        dirs.sort();
        dirs.into_iter().find(|d| {
            let Ok(bytes) = std::fs::read(d.join("config.json")) else {
                return false;
            };
            let v: serde_json::Value = serde_json::from_slice(&bytes).unwrap_or_default();
            v["rig"] == "R1"
                && v["model_width"] == 440
                && v["pose_form"].as_str().is_none_or(|f| f == "absolute")
        })
    }

    /// A copy of a committed absolute R1 model ([`absolute_r1_model`])
    /// whose `references.npz` holds `arrays` instead of its own.
    fn with_references(src: &Path, arrays: &[Array]) -> (tempfile::TempDir, PathBuf) {
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
        let Some(src) = absolute_r1_model() else {
            eprintln!("SKIPPED: no absolute R1 model under models/omg");
            return;
        };
        let (n, t) = (440u64, 36u64);
        let a = |c: u64, f: u64, w: u64| vec![0.5f32; (c * f * w) as usize];
        let good = |name: &'static str| match name {
            "inputs" | "one_step" => (name, vec![1, 2, n], a(1, 2, n)),
            "rollout_grounded" => (name, vec![1, 3, n], a(1, 3, n)),
            _ => (name, vec![1, 3, t], a(1, 3, t)),
        };
        let names = ["inputs", "one_step", "rollout_grounded", "rollout_targets"];
        let all: Vec<_> = names.iter().map(|&k| good(k)).collect();
        let (_t, dir) = with_references(&src, &all);
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
            let (_t, dir) = with_references(&src, &arrays);
            let e = format!("{:#}", load_dir(&dir).err().unwrap());
            assert!(e.contains("references.npz"), "{e}");
            assert!(e.contains(want), "{e}");
        }
    }

    /// A joint-velocity model to test with: `$PHASEGATE_DOF_MODEL`, or the
    /// committed embedded default `models/omg/tiny_fe_r1`.
    pub(crate) fn dof_model() -> PathBuf {
        let dir = std::env::var_os("PHASEGATE_DOF_MODEL").map_or_else(
            || Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1"),
            PathBuf::from,
        );
        assert!(
            dir.join("config.json").exists(),
            "no joint-velocity model at {} (set PHASEGATE_DOF_MODEL)",
            dir.display()
        );
        dir
    }

    /// The f64 loop reproduces PyTorch's rollouts of a joint-velocity
    /// model (frames and joint angles) and its one-step network outputs,
    /// as `tools/omg` requires of every model (1e-4 relative); the layout
    /// is the joint-velocity form; a rest start is FK of `q = 0`.
    #[test]
    fn a_dof_model_reproduces_its_references_and_starts_from_rest() {
        let dir = dof_model();
        let d = load_dir(&dir).unwrap();
        let form = d.omg.dof.as_ref().expect("a dof_velocity model");
        let l = reach_layout(&d.omg).unwrap();
        assert_eq!(
            l.pose,
            PoseForm::DofVelocity {
                out: form.u.clone(),
                vel: d.omg.config.slice("vel"),
            }
        );
        assert!(d.refs.dof.is_some());
        let f = float_agreement(&d).unwrap();
        eprintln!(
            "f64 vs PyTorch: one step max rel {:.2e}, rollout max rel {:.2e}, joint angles {:.2e} rad",
            f.one_step.max_rel,
            f.rollout.max_rel,
            f.rollout_dof_max_rad.unwrap()
        );
        assert!(f.one_step.max_rel < 1e-4, "{:?}", f.one_step);
        assert!(f.rollout.max_rel < 1e-4, "{:?}", f.rollout);
        assert!(f.rollout_dof_max_rad.unwrap() < 1e-5);
        assert_eq!(
            f.rollout.frames,
            d.refs.rollout.dims[0] * d.refs.rollout.dims[1]
        );

        // From rest: q0 = v0 = 0, the rig's rest positions, the targets.
        let t = Start::rest_targets(&d.omg).unwrap();
        let rest = Start::rest(&d.omg, &t).unwrap().unwrap();
        assert!(rest.q0.iter().chain(&rest.v0).all(|&v| v == 0.0));
        let rig: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("rig.json")).unwrap()).unwrap();
        let pos = d.omg.config.slice("pos");
        for (j, p) in rig["rest_positions"].as_array().unwrap().iter().enumerate() {
            for k in 0..3 {
                let want = p[k].as_f64().unwrap();
                assert!(
                    (rest.first[pos.start + 3 * j + k] - want).abs() < 1e-5,
                    "joint {j}"
                );
            }
        }
        let c = d.omg.config.slice("cost");
        assert!(
            rest.first[c].iter().all(|v| v.abs() < 1e-6),
            "own targets: no cost"
        );
        let targets: Vec<&[f64]> = vec![&t; 5];
        let (frames, dofs) = rollout_dofs(
            &d.omg,
            &rest,
            &targets,
            Mode::Grounded,
            &mut FloatOmg(&d.omg),
        )
        .unwrap();
        assert_eq!((frames.len(), dofs.len()), (5, 5));
        assert!(dofs[4]
            .iter()
            .zip(&form.skeleton.dofs)
            .all(|(q, f)| *q >= f.lower && *q <= f.upper));
        // An absolute model has no rest of its own.
        let abs = OmgNet {
            dof: None,
            ..d.omg.clone()
        };
        assert!(Start::rest(&abs, &t).unwrap().is_none());
        if let Some(dir) = absolute_r1_model() {
            assert!(load_dir(&dir).unwrap().refs.dof.is_none());
        }
    }

    /// A held-out clip of the generated data starts with its own joint
    /// angles, `v0 = q0 * fps`.
    #[test]
    fn a_dof_clip_starts_from_the_datas_joint_angles() {
        let dir = dof_model();
        let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/omg");
        if !data.join("R1/clips.json").exists() {
            eprintln!(
                "OMG data set absent at {}: a held-out clip's start not checked \
                 (python3 -m tools.omg.generate --out data/omg --seed 0 --rigs R1,R4)",
                data.display()
            );
            return;
        }
        let d = load_dir(&dir).unwrap();
        let held = crate::omg_reach::HeldOut::read_splits(&data, "R1", 440, &["test"], 2).unwrap();
        let s = held.start(&d.omg, 1).unwrap();
        assert_eq!(s.q0.len(), 30);
        assert!(s.q0.iter().zip(&s.v0).all(|(q, v)| *v == q * 60.0));
        assert!(s.q0.iter().any(|&q| q != 0.0));
        // The references' clips start the same way.
        let r = d.refs.dof.as_ref().unwrap();
        for (q, v) in r.q0.iter().zip(&r.v0) {
            for (a, b) in q.iter().zip(v) {
                assert!((a * 60.0 - b).abs() < 1e-6);
            }
        }
        assert!(Start::clip(&d.omg, &held.clips[0][0], None)
            .unwrap_err()
            .to_string()
            .contains("no dof block"));
        assert!(Start::clip(&d.omg, &held.clips[0][0], Some(&[0.0; 3])).is_err());
    }

    /// A joint-velocity model's references without their start states or
    /// with a one step of frame width are refused naming the array.
    #[test]
    fn damaged_dof_references_are_refused_naming_the_array() {
        let dir = dof_model();
        let mut arrays = exporter::npz::read_npz(&dir.join("references.npz")).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        for f in ["config.json", "model.safetensors"] {
            std::fs::copy(dir.join(f), tmp.path().join(f)).unwrap();
        }
        let write = |a: &BTreeMap<String, exporter::npz::NpArray>| {
            let list: Vec<(&str, Vec<u64>, Vec<f32>)> = a
                .iter()
                .map(|(k, v)| {
                    (
                        k.as_str(),
                        v.shape.clone(),
                        v.data.iter().map(|&x| x as f32).collect(),
                    )
                })
                .collect();
            exporter::npz::write_npz(&tmp.path().join("references.npz"), &list).unwrap();
            format!("{:#}", load_dir(tmp.path()).err().unwrap())
        };
        let mut a = arrays.clone();
        a.remove("rollout_v0");
        assert!(write(&a).contains("no array rollout_v0"));
        let mut a = arrays.clone();
        a.get_mut("rollout_q0").unwrap().shape = vec![1, 60];
        assert!(write(&a).contains("array rollout_q0 has shape [1, 60], expected [2, 30]"));
        let x = arrays.remove("inputs").unwrap();
        arrays.insert("one_step".into(), x.clone());
        arrays.insert("inputs".into(), x);
        assert!(write(&arrays).contains("array one_step has width 440, expected 62"));
    }
}
