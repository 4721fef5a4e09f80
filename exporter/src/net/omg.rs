//! The OMG importer: a trained FE-OMG (or FS-OMG) model as `tools/omg/train`
//! writes it (`model.safetensors` + `config.json`, `models/omg/README.md`)
//! becomes a graph [`Net`] of the ops every graph has (dense, optionally
//! K-expert blended by a softmax gate node, softmax), so it goes through
//! the one quantiser, encoder and report (`exporter omg`, `docs/omg.md`).
//!
//! The graph, 16 nodes (`g` = gate, `e` = encoder, `c` = cost encoder,
//! `m` = gated experts, `d` = decoder; ELU after every node but `gate2`,
//! `enc2`, `cost2`, `moe2` and `out`):
//!
//! ```text
//! gate0..2  input[phase]                 -> K logits    gate.{0,1,2}.w/.b
//! alpha     softmax(gate2)                               (the expert gate)
//! enc0..2   input[pose]                  -> L           enc.{0,1,2}.w/.b
//! cost0..2  input[cost], input[target]   -> Hc          cost.{0,1,2}.w/.b
//! moe0..2   [enc2, cost2], gate alpha    -> 2K+L+6K     experts.w{l} (k,in,out) transposed, experts.b{l}
//! dec0..1   moe2[z]                      -> h           dec.{0,1}.w/.b
//! out       [moe2[dphase], input[phase], dec1, moe2[cost]]
//!           rows 0..2K:   a * dphase + (1 - a) * phase  (the phase update, a = 0.9)
//!           rows 2K..:    dec.2.w @ dec1 + dec.2.b       (the decoded pose)
//!           last 6K rows: the predicted costs C', copied (weight 1)
//! ```
//!
//! The network's output is the model output `Y` without its target block,
//! in the order phase, pose, costs ([`OmgNet::frame`] puts it back into
//! `Y`'s layout and copies the targets from the input, as the model does).
//!
//! Joint-velocity models (`pose_form: "dof_velocity"`,
//! `docs/omg-joint-velocity.md`): the decoder's last layer `dec.2` has D
//! rows, one per degree of freedom of the rig, and the middle rows of
//! `out` are those D rows: the network's output is `[phase', u, cost']`
//! with `u` the desired joint velocity in radians per frame (the output
//! statistics of that block are `norm.dof_mean` / `norm.dof_std`). The
//! pose comes from the reaching controller (limits, integration, forward
//! kinematics on the config's `controller.skeleton`, which [`OmgNet::dof`]
//! carries); one stateless frame is no longer a frame, so
//! [`OmgNet::step`] is for absolute models and [`OmgNet::output`] gives
//! the network output of either.
//! One node has to produce all three because a blob's output is one slice of
//! one node; folding the phase update and the cost copy into the decoder's
//! last layer costs `(2K + 6K) * (12J + 8K) + 2K * 12J` MACs more than the
//! decoder alone (18,208 for R1) and no runtime code.
//!
//! FS (`encoder_columns` in the config): the encoder's first layer reads a
//! few joints' columns; the importer scatters its weights into the columns
//! `min..=max` of those (zeros elsewhere), one input slice.
//!
//! RBF-CAT (spec §2.2): an `rbf` node after the encoder computes
//! `psi = exp(-(sigma |z - mu|)^2)` for the C clusters (the graph's RBF op),
//! and every expert layer reads `[psi, h]`, two slices concatenated.
//! DEC-CAT the same with a `dec` node (`dec.centres` (C, L)): `psi = q`, the
//! Student-t soft assignment of the graph's DEC op (no trained DEC model
//! ships; `tools/omg` does not train one).

#![deny(clippy::arithmetic_side_effects)]

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use ndarray::{Array1, Array2};
use serde::Deserialize;

use super::graph::{Graph, GraphNode, GraphOp};
use super::{ExpertLayer, GatingMode, Net, NetLayer, Wiring};
use crate::error::in_weights;
use crate::io::sizes::{add, mul};
use crate::io::tensors::NpArray;
use crate::ops::{DecLayer, RbfLayer};
use phasegate::blob::{GateSource, Slice, Source};

/// The `format` field of an OMG `config.json`.
pub const FORMAT: &str = "phasegate-omg-1";
/// The quantiser headroom `exporter omg` uses: the calibration inputs
/// (independent normal features around the mean) reach up to 1.8 times
/// smaller activations than the real motion frames of tiny_fe_r1 in some
/// rows (encoder, decoder), which saturate at the default 1.5.
pub const HEADROOM: f64 = 3.0;
/// Training standard deviations below this became 1 (the config's rule).
pub const MIN_STD: f64 = 1e-4;

/// Sizes of an OMG model (`config.json` `sizes`).
#[derive(Clone, Debug, Deserialize)]
pub struct OmgSizes {
    /// Autoencoder hidden width.
    pub ae_hidden: usize,
    /// Pose embedding width L.
    pub latent: usize,
    /// Cost-encoder width.
    pub cost_hidden: usize,
    /// Expert hidden width.
    pub expert_hidden: usize,
    /// Gate hidden width.
    pub gate_hidden: usize,
    /// Experts k.
    pub experts: usize,
    /// RBF clusters C (RBF-CAT: `psi`, C wide, in front of every expert
    /// layer's input).
    #[serde(default)]
    pub clusters: usize,
    /// Degrees of freedom D of a joint-velocity model (the decoder's
    /// output width); 0 otherwise.
    #[serde(default)]
    pub dof: usize,
}

/// The phase update `theta' = a * dtheta + (1 - a) * theta`.
#[derive(Clone, Debug, Deserialize)]
pub struct PhaseUpdate {
    /// `a` (0.9).
    pub a: f64,
}

/// The normalisation block of the config (the statistics are also in the
/// weights file, `norm.mean` / `norm.std`, which the importer uses).
#[derive(Clone, Debug, Deserialize)]
pub struct OmgNormalisation {
    /// The rule in words.
    #[serde(default)]
    pub rule: String,
    /// Per-feature means, if written.
    #[serde(default)]
    pub mean: Option<Vec<f64>>,
    /// Per-feature standard deviations, if written.
    #[serde(default)]
    pub std: Option<Vec<f64>>,
    /// A joint-velocity model's `u` means (`norm.dof_mean`), if written.
    #[serde(default)]
    pub dof_mean: Option<Vec<f64>>,
    /// A joint-velocity model's `u` standard deviations (`norm.dof_std`),
    /// if written.
    #[serde(default)]
    pub dof_std: Option<Vec<f64>>,
}

/// What the importer and the rollouts read from `config.json` (other fields
/// are ignored).
#[derive(Clone, Debug, Deserialize)]
pub struct OmgConfig {
    /// Must be [`FORMAT`].
    pub format: String,
    /// `"FE"`, `"FS"` or `"RBF-CAT"`.
    pub variant: String,
    /// Joints of the rig.
    #[serde(rename = "J")]
    pub joints: usize,
    /// Key joints (hands, feet).
    #[serde(rename = "K")]
    pub key: usize,
    /// Indices of the key joints among the rig's joints.
    pub key_joint_indices: Vec<usize>,
    /// Names of the key joints, in the same order (target scripts name
    /// them; empty in a config that does not give them).
    #[serde(default)]
    pub key_joints: Vec<String>,
    /// Width n of X and Y.
    pub model_width: usize,
    /// Sizes.
    pub sizes: OmgSizes,
    /// Blocks of X and Y: `phase`, `pose`, `cost`, `target`, and within
    /// them `pos`, `rot`, `vel`, `pos_cost`, `rot_cost`, `target_pos`,
    /// `target_rot`.
    pub slices: BTreeMap<String, [usize; 2]>,
    /// Blocks of the last expert layer's output: `dphase`, `z`, `cost`.
    pub out_slices: BTreeMap<String, [usize; 2]>,
    /// The phase update.
    pub phase_update: PhaseUpdate,
    /// `"grounded"` or `"faithful"`: the inference mode trained for.
    pub mode: String,
    /// FS: the columns of X the encoder reads.
    #[serde(default)]
    pub encoder_columns: Option<Vec<usize>>,
    /// Normalisation.
    #[serde(default)]
    pub normalisation: Option<OmgNormalisation>,
    /// `"absolute"` (the decoder outputs the pose block; also when absent)
    /// or `"dof_velocity"` (the decoder outputs the desired joint velocity,
    /// `docs/omg-joint-velocity.md`).
    #[serde(default)]
    pub pose_form: Option<String>,
    /// The reaching controller's parameters of a joint-velocity model.
    #[serde(default)]
    pub controller: Option<OmgControllerJson>,
}

/// `config.json` `controller` as written (checked into an
/// [`OmgSkeleton`] by the importer).
#[derive(Clone, Debug, Deserialize)]
pub struct OmgControllerJson {
    /// Frames per second.
    pub fps: f64,
    /// The joints' acceleration limit, rad/s^2.
    pub a_max: f64,
    /// The rig.
    pub skeleton: OmgSkeletonJson,
}

/// `controller.skeleton` as written.
#[derive(Clone, Debug, Deserialize)]
pub struct OmgSkeletonJson {
    /// J parents (-1: a root), parents before children.
    pub parents: Vec<i64>,
    /// J rest offsets from the parent, metres.
    pub offsets: Vec<[f64; 3]>,
    /// D degrees of freedom in the rig's order.
    pub dofs: Vec<OmgDofJson>,
}

/// One entry of `controller.skeleton.dofs` as written.
#[derive(Clone, Debug, Deserialize)]
pub struct OmgDofJson {
    /// The joint it turns.
    pub joint: i64,
    /// 0 = x, 1 = y, 2 = z.
    pub axis: i64,
    /// Lowest angle, radians.
    pub lower: f64,
    /// Highest angle, radians.
    pub upper: f64,
}

/// One checked degree of freedom.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OmgDof {
    /// The joint it turns.
    pub joint: usize,
    /// 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    /// Lowest angle, radians.
    pub lower: f64,
    /// Highest angle, radians (at least `lower`).
    pub upper: f64,
}

/// The checked skeleton and rates of a joint-velocity model (what the
/// reaching controller's `Skeleton` is built from).
#[derive(Clone, Debug, PartialEq)]
pub struct OmgSkeleton {
    /// Frames per second.
    pub fps: f64,
    /// The joints' acceleration limit, rad/s^2.
    pub a_max: f64,
    /// Per joint its parent (`None`: a root), parents before children.
    pub parents: Vec<Option<usize>>,
    /// Per joint its rest offset, metres.
    pub offsets: Vec<[f64; 3]>,
    /// The DOFs, in the order of `u` and of the data's `dof` block.
    pub dofs: Vec<OmgDof>,
}

/// Where a joint-velocity model's `u` is and the rig it moves.
#[derive(Clone, Debug, PartialEq)]
pub struct DofForm {
    /// Where `u` (D values, radians per frame) is in the net's output.
    pub u: Range<usize>,
    /// The rig.
    pub skeleton: OmgSkeleton,
}

/// Most joints and DOFs the controller takes (its `MAX_JOINTS`,
/// `MAX_DOFS`).
pub const MAX_SKELETON: usize = 64;

/// Checks `controller` of the config of a model of `joints` joints and
/// `dofs` DOFs (`sizes.dof`); errors name the field.
fn skeleton(c: &OmgControllerJson, joints: usize, dofs: usize) -> Result<OmgSkeleton> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !positive(c.fps) {
        bail!("controller.fps = {}, expected a finite rate above 0", c.fps);
    }
    if !positive(c.a_max) {
        bail!(
            "controller.a_max = {}, expected a finite limit above 0",
            c.a_max
        );
    }
    let sk = &c.skeleton;
    if sk.parents.len() != joints || sk.offsets.len() != joints {
        bail!(
            "controller.skeleton has {} parents and {} offsets, but J = {joints}",
            sk.parents.len(),
            sk.offsets.len()
        );
    }
    if joints > MAX_SKELETON {
        bail!(
            "controller.skeleton has {joints} joints; the controller takes at most {MAX_SKELETON}"
        );
    }
    if sk.dofs.len() != dofs {
        bail!(
            "controller.skeleton.dofs has {} entries, but sizes.dof = {dofs}",
            sk.dofs.len()
        );
    }
    if dofs > MAX_SKELETON {
        bail!("controller.skeleton has {dofs} DOFs; the controller takes at most {MAX_SKELETON}");
    }
    let mut parents = Vec::with_capacity(joints);
    for (j, &p) in sk.parents.iter().enumerate() {
        parents.push(match p {
            -1 => None,
            p if p >= 0 && (p as usize) < j => Some(p as usize),
            p => bail!(
                "controller.skeleton.parents[{j}] = {p}, expected -1 (a root) or a joint before {j}"
            ),
        });
    }
    for (j, o) in sk.offsets.iter().enumerate() {
        if let Some(v) = o.iter().find(|v| !(v.is_finite() && v.abs() <= 100.0)) {
            bail!(
                "controller.skeleton.offsets[{j}] holds {v}, expected finite metres within 100 m"
            );
        }
    }
    let mut seen = std::collections::BTreeSet::new();
    let mut out = Vec::with_capacity(dofs);
    for (d, f) in sk.dofs.iter().enumerate() {
        let at = format!("controller.skeleton.dofs[{d}]");
        if !(0..joints as i64).contains(&f.joint) {
            bail!(
                "{at}.joint = {}, expected a joint below J = {joints}",
                f.joint
            );
        }
        if !(0..3).contains(&f.axis) {
            bail!("{at}.axis = {}, expected 0, 1 or 2", f.axis);
        }
        if !(f.lower.is_finite() && f.upper.is_finite() && f.lower <= f.upper) {
            bail!(
                "{at}: lower = {}, upper = {}, expected finite limits with lower <= upper",
                f.lower,
                f.upper
            );
        }
        if !seen.insert((f.joint, f.axis)) {
            bail!("{at}: a second DOF on joint {} axis {}", f.joint, f.axis);
        }
        out.push(OmgDof {
            joint: f.joint as usize,
            axis: f.axis as usize,
            lower: f.lower,
            upper: f.upper,
        });
    }
    Ok(OmgSkeleton {
        fps: c.fps,
        a_max: c.a_max,
        parents,
        offsets: sk.offsets.clone(),
        dofs: out,
    })
}

/// Largest size a config may give (`J`, `K`, `model_width`, every
/// `sizes` field): a blob's widths are u16, so nothing wider exports, and
/// with every size below it no sum or product the importer forms can
/// overflow (they are checked all the same).
pub const MAX_CONFIG_SIZE: usize = u16::MAX as usize;

/// Blocks of X that hold others, and the blocks inside each.
const NESTED_BLOCKS: [(&str, &[&str]); 3] = [
    ("pose", &["pos", "rot", "vel"]),
    ("cost", &["pos_cost", "rot_cost"]),
    ("target", &["target_pos", "target_rot"]),
];

/// The first pair of `blocks` (name, range) that share a column.
fn first_overlap<'a>(
    blocks: &[(&'a str, Range<usize>)],
) -> Option<(&'a str, Range<usize>, &'a str, Range<usize>)> {
    blocks.iter().enumerate().find_map(|(i, (a, ra))| {
        blocks[..i].iter().find_map(|(b, rb)| {
            (ra.start < rb.end && rb.start < ra.end).then(|| (*b, rb.clone(), *a, ra.clone()))
        })
    })
}

impl OmgConfig {
    /// Refuses a size above [`MAX_CONFIG_SIZE`], naming the field.
    fn check_sizes(&self) -> Result<()> {
        let s = &self.sizes;
        for (field, v) in [
            ("J", self.joints),
            ("K", self.key),
            ("model_width", self.model_width),
            ("sizes.ae_hidden", s.ae_hidden),
            ("sizes.latent", s.latent),
            ("sizes.cost_hidden", s.cost_hidden),
            ("sizes.expert_hidden", s.expert_hidden),
            ("sizes.gate_hidden", s.gate_hidden),
            ("sizes.experts", s.experts),
            ("sizes.clusters", s.clusters),
            ("sizes.dof", s.dof),
        ] {
            if v > MAX_CONFIG_SIZE {
                bail!("{field} = {v}: at most {MAX_CONFIG_SIZE} (a blob's widths are 16-bit)");
            }
        }
        Ok(())
    }

    /// Refuses blocks of X that overlap (phase, pose, cost, target), a
    /// sub-block outside its block or overlapping a sibling, the last
    /// expert layer's `dphase`, `z` and `cost` overlapping, and
    /// `encoder_columns` naming a column twice: each would build a network
    /// other than the one trained, without a word.
    fn check_layout(&self) -> Result<()> {
        let top = ["phase", "pose", "cost", "target"]
            .into_iter()
            .map(|n| Ok((n, self.block(n)?)))
            .collect::<Result<Vec<_>>>()?;
        if let Some((a, ra, b, rb)) = first_overlap(&top) {
            bail!("slices.{a} {ra:?} and slices.{b} {rb:?} overlap: X's blocks must be disjoint");
        }
        for (outer, inner) in NESTED_BLOCKS {
            let o = self.block(outer)?;
            let subs = inner
                .iter()
                .map(|&n| Ok((n, self.block(n)?)))
                .collect::<Result<Vec<_>>>()?;
            if let Some((n, r)) = subs
                .iter()
                .find(|(_, r)| r.start < o.start || r.end > o.end)
            {
                bail!("slices.{n} {r:?} is not inside slices.{outer} {o:?}");
            }
            if let Some((a, ra, b, rb)) = first_overlap(&subs) {
                bail!("slices.{a} {ra:?} and slices.{b} {rb:?} overlap");
            }
        }
        let outs = ["dphase", "z", "cost"]
            .into_iter()
            .map(|n| Ok((n, self.out_block(n)?)))
            .collect::<Result<Vec<_>>>()?;
        if let Some((a, ra, b, rb)) = first_overlap(&outs) {
            bail!(
                "out_slices.{a} {ra:?} and out_slices.{b} {rb:?} overlap: the last expert \
                 layer's blocks must be disjoint"
            );
        }
        if let Some(cols) = &self.encoder_columns {
            let mut seen = std::collections::BTreeSet::new();
            if let Some((i, c)) = cols.iter().enumerate().find(|(_, c)| !seen.insert(**c)) {
                bail!("encoder_columns[{i}] = {c}: the column is named twice");
            }
        }
        Ok(())
    }

    /// Block `name` of X / Y.
    ///
    /// # Panics
    /// If the block is missing ([`net_from_omg`] checks the blocks it needs).
    pub fn slice(&self, name: &str) -> Range<usize> {
        let [a, b] = self.slices[name];
        a..b
    }

    fn block(&self, name: &str) -> Result<Range<usize>> {
        let &[a, b] = self
            .slices
            .get(name)
            .ok_or_else(|| anyhow!("slices has no {name:?} block"))?;
        if a > b || b > self.model_width {
            bail!(
                "slices.{name} = [{a}, {b}] is not within the model width {}",
                self.model_width
            );
        }
        Ok(a..b)
    }

    fn out_block(&self, name: &str) -> Result<Range<usize>> {
        let &[a, b] = self
            .out_slices
            .get(name)
            .ok_or_else(|| anyhow!("out_slices has no {name:?} block"))?;
        if a >= b {
            bail!("out_slices.{name} = [{a}, {b}] is empty");
        }
        Ok(a..b)
    }
}

/// An imported OMG model: the graph net and where `Y`'s blocks are.
#[derive(Clone, Debug)]
pub struct OmgNet {
    /// The config it was built from.
    pub config: OmgConfig,
    /// The graph (input X, output `[phase', pose', cost']`, or for a
    /// joint-velocity model `[phase', u, cost']`).
    pub net: Net,
    /// Where the net's output blocks go in `Y`: (range in the net's
    /// output, range in `Y`) for phase, pose and cost (a joint-velocity
    /// model's pose entry is empty: its pose comes from the controller).
    pub blocks: [(Range<usize>, Range<usize>); 3],
    /// `Y`'s target block (copied from X).
    pub target: Range<usize>,
    /// A joint-velocity model's `u` block and skeleton (`None`: absolute).
    pub dof: Option<DofForm>,
}

impl OmgNet {
    /// The model's `Y` (width n) from the net's output and the frame's `X`:
    /// the computed blocks in their places and the targets copied from
    /// `X` (a joint-velocity model's pose block stays `X`'s: the
    /// controller makes the next one).
    pub fn frame(&self, net_out: &[f64], x: &[f64]) -> Vec<f64> {
        let mut y = match self.dof {
            None => vec![0.0; self.config.model_width],
            Some(_) => x.to_vec(),
        };
        for (from, to) in &self.blocks {
            y[to.clone()].copy_from_slice(&net_out[from.clone()]);
        }
        y[self.target.clone()].copy_from_slice(&x[self.target.clone()]);
        y
    }

    /// The network's output for frame `X` in f64, raw units: `[phase',
    /// pose', cost']`, or `[phase', u, cost']` for a joint-velocity model.
    pub fn output(&self, x: &[f64]) -> Vec<f64> {
        self.net.forward(x, 0.0)
    }

    /// One frame of an absolute model in f64, raw units: `Y = step(X)`.
    /// For a joint-velocity model the next frame needs the controller's
    /// state (`phasegate_controller::Reach`): use [`OmgNet::output`].
    pub fn step(&self, x: &[f64]) -> Vec<f64> {
        self.frame(&self.output(x), x)
    }
}

fn get<'a>(arrays: &'a BTreeMap<String, NpArray>, name: &str) -> Result<&'a NpArray> {
    arrays
        .get(name)
        .ok_or_else(|| in_weights(format!("tensor {name:?} is missing")))
}

fn check_shape(a: &NpArray, name: &str, want: &[usize], why: &str) -> Result<()> {
    let got: Vec<usize> = a.shape.iter().map(|&d| d as usize).collect();
    if got != want {
        return Err(in_weights(format!(
            "tensor {name:?} has shape {got:?}, expected {want:?} ({why})"
        )));
    }
    Ok(())
}

/// `name.{i}.w` (out, in) and `name.{i}.b` (out) of an MLP, checked against
/// the input width `inp` and the output width `out`.
fn linear(
    arrays: &BTreeMap<String, NpArray>,
    name: &str,
    inp: usize,
    out: usize,
    why: &str,
) -> Result<ExpertLayer> {
    let (wn, bn) = (format!("{name}.w"), format!("{name}.b"));
    let w = get(arrays, &wn)?;
    check_shape(w, &wn, &[out, inp], why)?;
    let b = get(arrays, &bn)?;
    check_shape(b, &bn, &[out], why)?;
    Ok(ExpertLayer {
        w: vec![Array2::from_shape_vec((out, inp), w.data.clone())?],
        b: vec![Array1::from(b.data.clone())],
    })
}

/// A three-layer MLP `name.{0,1,2}`: `inp -> hidden -> hidden -> out`.
fn mlp(
    arrays: &BTreeMap<String, NpArray>,
    name: &str,
    inp: usize,
    hidden: usize,
    out: usize,
    what: &str,
) -> Result<[ExpertLayer; 3]> {
    Ok([
        linear(
            arrays,
            &format!("{name}.0"),
            inp,
            hidden,
            &format!("{what} {inp} -> {hidden}"),
        )?,
        linear(
            arrays,
            &format!("{name}.1"),
            hidden,
            hidden,
            &format!("{what} {hidden} -> {hidden}"),
        )?,
        linear(
            arrays,
            &format!("{name}.2"),
            hidden,
            out,
            &format!("{what} {hidden} -> {out}"),
        )?,
    ])
}

/// Expert layer `l`: `experts.w{l}` (k, in, out), `experts.b{l}` (k, out).
fn experts(
    arrays: &BTreeMap<String, NpArray>,
    l: usize,
    k: usize,
    inp: usize,
    out: usize,
) -> Result<ExpertLayer> {
    let (wn, bn) = (format!("experts.w{l}"), format!("experts.b{l}"));
    let why = format!("expert layer {l}: {k} experts, {inp} -> {out}");
    let w = get(arrays, &wn)?;
    check_shape(w, &wn, &[k, inp, out], &why)?;
    let b = get(arrays, &bn)?;
    check_shape(b, &bn, &[k, out], &why)?;
    // Shapes checked: (k, in, out) and (k, out) hold exactly the data.
    let w = ndarray::Array3::from_shape_vec((k, inp, out), w.data.clone())?;
    let b = Array2::from_shape_vec((k, out), b.data.clone())?;
    Ok(ExpertLayer {
        w: w.outer_iter()
            .map(|e| e.t().as_standard_layout().into_owned())
            .collect(),
        b: b.outer_iter().map(|e| e.to_owned()).collect(),
    })
}

/// The RBF layer of RBF-CAT: `rbf.centres` (C, L) and `rbf.scales` (C,),
/// `psi_j = exp(-(sigma_j |z - mu_j|)^2)`.
fn rbf_layer(arrays: &BTreeMap<String, NpArray>, c: usize, latent: usize) -> Result<RbfLayer> {
    let why = format!("RBF layer: {c} clusters over the latent {latent}");
    let mu = get(arrays, "rbf.centres")?;
    check_shape(mu, "rbf.centres", &[c, latent], &why)?;
    let sigma = get(arrays, "rbf.scales")?;
    check_shape(sigma, "rbf.scales", &[c], &why)?;
    Ok(RbfLayer {
        centres: vec![Array2::from_shape_vec((c, latent), mu.data.clone())?],
        sigma: vec![Array1::from(sigma.data.clone())],
        b: vec![Array1::zeros(c)],
    })
}

/// The DEC layer of DEC-CAT: `dec.centres` (C, L), `q_j = (1 + |z -
/// mu_j|^2)^-1` normalised over the C centres (the author's code, alpha =
/// 1; spec §2.2).
fn dec_layer(arrays: &BTreeMap<String, NpArray>, c: usize, latent: usize) -> Result<DecLayer> {
    let why = format!("DEC layer: {c} clusters over the latent {latent}");
    let mu = get(arrays, "dec.centres")?;
    check_shape(mu, "dec.centres", &[c, latent], &why)?;
    Ok(DecLayer {
        centres: vec![Array2::from_shape_vec((c, latent), mu.data.clone())?],
        b: vec![Array1::zeros(c)],
    })
}

fn input_slice(r: &Range<usize>) -> Result<Slice> {
    Ok(Slice {
        source: Source::Input,
        start: u16::try_from(r.start)?,
        len: u16::try_from(r.len())?,
    })
}

fn node_slice(node: usize, r: &Range<usize>) -> Result<Slice> {
    Ok(Slice {
        source: Source::Node(u8::try_from(node)?),
        start: u16::try_from(r.start)?,
        len: u16::try_from(r.len())?,
    })
}

/// `parts` laid end to end: the range of each, checked.
fn spans<const N: usize>(parts: &[usize; N], what: &str) -> Result<[Range<usize>; N]> {
    let mut at = 0usize;
    let mut out: [Range<usize>; N] = std::array::from_fn(|_| 0..0);
    for (r, &len) in out.iter_mut().zip(parts) {
        let end = add(at, len, what)?;
        *r = at..end;
        at = end;
    }
    Ok(out)
}

/// The sum of `parts`, checked.
fn sum(parts: &[usize], what: &str) -> Result<usize> {
    parts.iter().try_fold(0usize, |acc, &p| add(acc, p, what))
}

/// The normalisation statistics: `norm.mean` / `norm.std` of the weights
/// file (n each), std below [`MIN_STD`] taken as 1 (the training rule), and
/// the config's copies, when it has them, equal to them.
fn normalisation(
    cfg: &OmgConfig,
    arrays: &BTreeMap<String, NpArray>,
) -> Result<(Array1<f64>, Array1<f64>)> {
    let n = cfg.model_width;
    let why = format!("model width {n}");
    let m = get(arrays, "norm.mean")?;
    check_shape(m, "norm.mean", &[n], &why)?;
    let s = get(arrays, "norm.std")?;
    check_shape(s, "norm.std", &[n], &why)?;
    if let Some(i) = s.data.iter().position(|v| *v < 0.0) {
        return Err(in_weights(format!(
            "tensor \"norm.std\" is negative at index {i}"
        )));
    }
    let std: Array1<f64> = s
        .data
        .iter()
        .map(|&v| if v < MIN_STD { 1.0 } else { v })
        .collect();
    let mean = Array1::from(m.data.clone());
    if let Some(nm) = &cfg.normalisation {
        for (what, cfgv, ours) in [("mean", &nm.mean, &mean), ("std", &nm.std, &std)] {
            let Some(v) = cfgv else { continue };
            if v.len() != n {
                bail!(
                    "config normalisation.{what} has {} values, not {n}",
                    v.len()
                );
            }
            if let Some(i) = (0..n).find(|&i| (v[i] - ours[i]).abs() > 1e-6 * (1.0 + v[i].abs())) {
                bail!(
                    "normalisation.{what}[{i}] = {}, but the weights' norm.{what}[{i}] = {}",
                    v[i],
                    ours[i]
                );
            }
        }
    }
    Ok((mean, std))
}

/// The output statistics of a joint-velocity model's `u` block:
/// `norm.dof_mean` / `norm.dof_std` (D each), std below [`MIN_STD`] taken
/// as 1 as for the others.
fn dof_statistics(
    cfg: &OmgConfig,
    arrays: &BTreeMap<String, NpArray>,
    d: usize,
) -> Result<(Array1<f64>, Array1<f64>)> {
    let why = format!("sizes.dof = {d}: the u block's output statistics");
    let m = get(arrays, "norm.dof_mean")?;
    check_shape(m, "norm.dof_mean", &[d], &why)?;
    let s = get(arrays, "norm.dof_std")?;
    check_shape(s, "norm.dof_std", &[d], &why)?;
    for (name, a) in [("norm.dof_mean", m), ("norm.dof_std", s)] {
        if let Some(i) = a.data.iter().position(|v| !v.is_finite()) {
            return Err(in_weights(format!(
                "tensor {name:?} is not finite at index {i}"
            )));
        }
    }
    if let Some(i) = s.data.iter().position(|v| *v < 0.0) {
        return Err(in_weights(format!(
            "tensor \"norm.dof_std\" is negative at index {i}"
        )));
    }
    let std: Array1<f64> = s
        .data
        .iter()
        .map(|&v| if v < MIN_STD { 1.0 } else { v })
        .collect();
    let mean = Array1::from(m.data.clone());
    // The config's copies, when present, must equal the tensors.
    if let Some(nm) = &cfg.normalisation {
        for (what, cfgv, ours) in [
            ("dof_mean", &nm.dof_mean, &mean),
            ("dof_std", &nm.dof_std, &std),
        ] {
            let Some(v) = cfgv else { continue };
            if v.len() != d {
                bail!(
                    "config normalisation.{what} has {} values, not {d}",
                    v.len()
                );
            }
            if let Some(i) = (0..d).find(|&i| (v[i] - ours[i]).abs() > 1e-6 * (1.0 + v[i].abs())) {
                bail!(
                    "normalisation.{what}[{i}] = {}, but the weights' norm.{what}[{i}] = {}",
                    v[i],
                    ours[i]
                );
            }
        }
    }
    Ok((mean, std))
}

/// Builds the graph net of an OMG model from its config and tensors. Errors
/// name the tensor or config field; [`read_omg`] adds the file.
pub fn net_from_omg(cfg: &OmgConfig, arrays: &BTreeMap<String, NpArray>) -> Result<OmgNet> {
    if cfg.format != FORMAT {
        bail!("config format {:?}, expected {FORMAT:?}", cfg.format);
    }
    let cat = match cfg.variant.as_str() {
        "FE" | "FS" => 0,
        "RBF-CAT" | "DEC-CAT" if cfg.sizes.clusters > 0 => cfg.sizes.clusters,
        v @ ("RBF-CAT" | "DEC-CAT") => bail!("variant {v} needs sizes.clusters > 0"),
        v => bail!("variant {v:?} (expected FE, FS, RBF-CAT or DEC-CAT)"),
    };
    cfg.check_sizes()?;
    let (j, k) = (cfg.joints, cfg.key);
    let s = &cfg.sizes;
    let phase = cfg.block("phase")?;
    let pose = cfg.block("pose")?;
    let cost = cfg.block("cost")?;
    let target = cfg.block("target")?;
    for (name, r, want) in [
        ("phase", &phase, mul(2, k, "2 K")?),
        ("pose", &pose, mul(12, j, "12 J")?),
        ("cost", &cost, mul(6, k, "6 K")?),
    ] {
        if r.len() != want {
            bail!(
                "slices.{name} has {} columns, but J = {j}, K = {k} make it {want}",
                r.len()
            );
        }
    }
    for sub in [
        "pos",
        "rot",
        "vel",
        "pos_cost",
        "rot_cost",
        "target_pos",
        "target_rot",
    ] {
        cfg.block(sub)?;
    }
    cfg.check_layout()?;
    if cfg.key_joint_indices.len() != k || cfg.key_joint_indices.iter().any(|&i| i >= j) {
        bail!(
            "key_joint_indices {:?}: expected {k} joint indices below J = {j}",
            cfg.key_joint_indices
        );
    }
    let a = cfg.phase_update.a;
    if !(a.is_finite() && a > 0.0 && a <= 1.0) {
        bail!("phase_update.a = {a}: expected 0 < a <= 1");
    }
    let dphase = cfg.out_block("dphase")?;
    let z = cfg.out_block("z")?;
    let ocost = cfg.out_block("cost")?;
    if dphase.len() != phase.len() || z.len() != s.latent || ocost.len() != cost.len() {
        bail!(
            "out_slices dphase {dphase:?}, z {z:?}, cost {ocost:?} must have {}, {} (latent) \
             and {} columns",
            phase.len(),
            s.latent,
            cost.len()
        );
    }
    let moe_out = dphase.end.max(z.end).max(ocost.end);
    let (mean, std) = normalisation(cfg, arrays)?;
    // The decoder's output: the pose block, or a joint-velocity model's D
    // desired joint velocities (with their own output statistics).
    let dof = match cfg.pose_form.as_deref() {
        None | Some("absolute") => None,
        Some("dof_velocity") => {
            let d = s.dof;
            if d == 0 {
                bail!("pose_form \"dof_velocity\" needs sizes.dof > 0 (the rig's DOFs)");
            }
            let c = cfg.controller.as_ref().ok_or_else(|| {
                anyhow!(
                    "pose_form \"dof_velocity\" needs a controller block (fps, a_max, skeleton)"
                )
            })?;
            let sk = skeleton(c, j, d)?;
            // The network output's u block, when the config names it.
            if let Some(&[a, b]) = cfg.out_slices.get("u") {
                let np = phase.len();
                let want = np..add(np, d, "out_slices.u")?;
                if (a..b) != want {
                    bail!(
                        "out_slices.u = [{a}, {b}], but the network output is [phase', u, cost'] \
                         with u at [{np}, {}]",
                        want.end
                    );
                }
            }
            Some((sk, dof_statistics(cfg, arrays, d)?))
        }
        Some(f) => bail!("pose_form = {f:?}, expected \"absolute\" or \"dof_velocity\""),
    };
    let dec_out = dof.as_ref().map_or(pose.len(), |(sk, _)| sk.dofs.len());

    // The encoder's input: the pose block, or (FS) the span of its columns.
    let (enc_in, enc_w0) = match &cfg.encoder_columns {
        None => (pose.clone(), None),
        Some(cols) => {
            let (&lo, &hi) = (
                cols.iter()
                    .min()
                    .ok_or_else(|| anyhow!("encoder_columns is empty"))?,
                cols.iter().max().unwrap_or(&0),
            );
            if hi >= cfg.model_width {
                bail!("encoder_columns: column {hi} is outside the model width");
            }
            (lo..add(hi, 1, "encoder_columns")?, Some(cols.clone()))
        }
    };
    let enc_cols = enc_w0.as_ref().map_or(enc_in.len(), Vec::len);
    let gate = mlp(
        arrays,
        "gate",
        phase.len(),
        s.gate_hidden,
        s.experts,
        "gate",
    )?;
    let mut enc = mlp(arrays, "enc", enc_cols, s.ae_hidden, s.latent, "encoder")?;
    if let Some(cols) = &enc_w0 {
        let w = &enc[0].w[0];
        let mut full = Array2::zeros((w.nrows(), enc_in.len()));
        for (c, &col) in cols.iter().enumerate() {
            // lo <= col <= hi: inside the span.
            full.column_mut(col.saturating_sub(enc_in.start))
                .assign(&w.column(c));
        }
        enc[0].w[0] = full;
    }
    let costs = mlp(
        arrays,
        "cost",
        add(cost.len(), target.len(), "the cost encoder's input")?,
        s.cost_hidden,
        s.cost_hidden,
        "cost encoder",
    )?;
    let h = s.expert_hidden;
    let moe = [
        experts(
            arrays,
            0,
            s.experts,
            sum(&[cat, s.latent, s.cost_hidden], "expert layer 0's input")?,
            h,
        )?,
        experts(
            arrays,
            1,
            s.experts,
            add(cat, h, "expert layer 1's input")?,
            h,
        )?,
        experts(
            arrays,
            2,
            s.experts,
            add(cat, h, "expert layer 2's input")?,
            moe_out,
        )?,
    ];
    // The clustering layer, `(node name, layer)`.
    let clustering = match (cat, cfg.variant.as_str()) {
        (0, _) => None,
        (_, "DEC-CAT") => Some(("dec", NetLayer::Dec(dec_layer(arrays, cat, s.latent)?))),
        _ => Some(("rbf", NetLayer::Rbf(rbf_layer(arrays, cat, s.latent)?))),
    };
    let dec = mlp(arrays, "dec", s.latent, s.ae_hidden, dec_out, "decoder")?;

    // The output node: [dphase, phase, dec1, cost'] -> [phase', pose', cost']
    // (or [phase', u, cost']).
    let (np, nh, nc) = (phase.len(), s.ae_hidden, cost.len());
    // Row blocks [phase', decoded, cost'] over column blocks [dphase,
    // phase, dec1, cost'].
    let out_rows = spans(&[np, dec_out, nc], "the output node's rows")?;
    let out_cols = spans(&[np, np, nh, nc], "the output node's inputs")?;
    let (rows, cols) = (out_rows[2].end, out_cols[3].end);
    let mut w = Array2::zeros((rows, cols));
    let mut b = Array1::zeros(rows);
    let blend = [a, 1.0 - a];
    for (block, weight) in out_cols[..2].iter().zip(blend) {
        w.slice_mut(ndarray::s![out_rows[0].clone(), block.clone()])
            .diag_mut()
            .fill(weight);
    }
    let [_, _, dec2] = &dec;
    w.slice_mut(ndarray::s![out_rows[1].clone(), out_cols[2].clone()])
        .assign(&dec2.w[0]);
    b.slice_mut(ndarray::s![out_rows[1].clone()])
        .assign(&dec2.b[0]);
    w.slice_mut(ndarray::s![out_rows[2].clone(), out_cols[3].clone()])
        .diag_mut()
        .fill(1.0);
    let out_layer = ExpertLayer {
        w: vec![w],
        b: vec![b],
    };

    let mut layers: Vec<NetLayer> = Vec::new();
    let mut nodes: Vec<GraphNode> = Vec::new();
    let mut add = |name: &str,
                   layer: Option<NetLayer>,
                   inputs: Vec<Slice>,
                   gate: GateSource,
                   elu: bool|
     -> usize {
        let op = match layer {
            Some(l) => {
                layers.push(l);
                GraphOp::Layer {
                    layer: layers.len().saturating_sub(1), // just pushed
                    elu,
                }
            }
            None => GraphOp::Softmax,
        };
        nodes.push(GraphNode {
            name: name.to_string(),
            op,
            inputs,
            gate,
        });
        nodes.len().saturating_sub(1)
    };
    let whole = |n: usize, width: usize| node_slice(n, &(0..width));
    let [g0, g1, g2] = gate;
    let mut prev = add(
        "gate0",
        Some(NetLayer::Dense(g0)),
        vec![input_slice(&phase)?],
        GateSource::None,
        true,
    );
    prev = add(
        "gate1",
        Some(NetLayer::Dense(g1)),
        vec![whole(prev, s.gate_hidden)?],
        GateSource::None,
        true,
    );
    let logits = add(
        "gate2",
        Some(NetLayer::Dense(g2)),
        vec![whole(prev, s.gate_hidden)?],
        GateSource::None,
        false,
    );
    let alpha = add(
        "alpha",
        None,
        vec![whole(logits, s.experts)?],
        GateSource::None,
        false,
    );
    let [e0, e1, e2] = enc;
    prev = add(
        "enc0",
        Some(NetLayer::Dense(e0)),
        vec![input_slice(&enc_in)?],
        GateSource::None,
        true,
    );
    prev = add(
        "enc1",
        Some(NetLayer::Dense(e1)),
        vec![whole(prev, s.ae_hidden)?],
        GateSource::None,
        true,
    );
    let zn = add(
        "enc2",
        Some(NetLayer::Dense(e2)),
        vec![whole(prev, s.ae_hidden)?],
        GateSource::None,
        false,
    );
    let [c0, c1, c2] = costs;
    let cost_inputs = if cost.end == target.start {
        vec![input_slice(&(cost.start..target.end))?]
    } else {
        vec![input_slice(&cost)?, input_slice(&target)?]
    };
    prev = add(
        "cost0",
        Some(NetLayer::Dense(c0)),
        cost_inputs,
        GateSource::None,
        true,
    );
    prev = add(
        "cost1",
        Some(NetLayer::Dense(c1)),
        vec![whole(prev, s.cost_hidden)?],
        GateSource::None,
        true,
    );
    let cn = add(
        "cost2",
        Some(NetLayer::Dense(c2)),
        vec![whole(prev, s.cost_hidden)?],
        GateSource::None,
        false,
    );
    let g = GateSource::Node(u8::try_from(alpha)?);
    let [m0, m1, m2] = moe;
    // RBF-CAT and DEC-CAT: psi in front of every expert layer's input.
    let psi = match clustering {
        Some((name, l)) => vec![whole(
            add(
                name,
                Some(l),
                vec![whole(zn, s.latent)?],
                GateSource::None,
                false,
            ),
            cat,
        )?],
        None => Vec::new(),
    };
    let with_psi = |rest: Vec<Slice>| psi.iter().copied().chain(rest).collect::<Vec<_>>();
    prev = add(
        "moe0",
        Some(NetLayer::Dense(m0)),
        with_psi(vec![whole(zn, s.latent)?, whole(cn, s.cost_hidden)?]),
        g,
        true,
    );
    prev = add(
        "moe1",
        Some(NetLayer::Dense(m1)),
        with_psi(vec![whole(prev, h)?]),
        g,
        true,
    );
    let mo = add(
        "moe2",
        Some(NetLayer::Dense(m2)),
        with_psi(vec![whole(prev, h)?]),
        g,
        false,
    );
    let [d0, d1, _] = dec;
    prev = add(
        "dec0",
        Some(NetLayer::Dense(d0)),
        vec![node_slice(mo, &z)?],
        GateSource::None,
        true,
    );
    prev = add(
        "dec1",
        Some(NetLayer::Dense(d1)),
        vec![whole(prev, nh)?],
        GateSource::None,
        true,
    );
    let out = add(
        "out",
        Some(NetLayer::Dense(out_layer)),
        vec![
            node_slice(mo, &dphase)?,
            input_slice(&phase)?,
            whole(prev, nh)?,
            node_slice(mo, &ocost)?,
        ],
        GateSource::None,
        false,
    );
    let output = whole(out, rows)?;

    // An absolute model's decoded rows are the pose (dec_out == its
    // width); a joint-velocity model's pose entry is empty.
    let blocks = match dof {
        None => [
            (out_rows[0].clone(), phase.clone()),
            (out_rows[1].clone(), pose.clone()),
            (out_rows[2].clone(), cost.clone()),
        ],
        Some(_) => [
            (out_rows[0].clone(), phase.clone()),
            (np..np, pose.start..pose.start),
            (out_rows[2].clone(), cost.clone()),
        ],
    };
    // The output statistics, block after block: phase, pose (or the
    // joint velocities'), costs.
    let pick = |v: &Array1<f64>, dofs: Option<&Array1<f64>>| -> Array1<f64> {
        let at = |r: &Range<usize>| v.slice(ndarray::s![r.clone()]).to_vec();
        let middle = match dofs {
            None => at(&pose),
            Some(d) => d.to_vec(),
        };
        [at(&phase), middle, at(&cost)].concat().into()
    };
    let net = Net {
        mode: GatingMode::Constant,
        ymean: pick(&mean, dof.as_ref().map(|(_, (m, _))| m)),
        ystd: pick(&std, dof.as_ref().map(|(_, (_, s))| s)),
        xmean: mean,
        xstd: std,
        layers,
        wiring: Wiring::Graph(Graph { nodes, output }),
    };
    Ok(OmgNet {
        config: cfg.clone(),
        net,
        blocks,
        target,
        dof: dof.map(|(skeleton, _)| DofForm {
            u: out_rows[1].clone(),
            skeleton,
        }),
    })
}

/// An OMG model from the bytes of its `model.safetensors` and the text of
/// its `config.json` (models embedded in a binary); errors name neither
/// file, [`read_omg`] adds the names.
pub fn omg_from_bytes(weights: &[u8], config: &str) -> Result<OmgNet> {
    let cfg: OmgConfig = serde_json::from_str(config).context("not an OMG config")?;
    let arrays = crate::io::tensors::parse_safetensors(weights)?;
    net_from_omg(&cfg, &arrays)
}

/// Reads an OMG model: `config` (`config.json`) and `weights`
/// (`model.safetensors`). Every error is one line naming the file.
pub fn read_omg(weights: &Path, config: &Path) -> Result<OmgNet> {
    // Through `read_input`: the config is an input no output may overwrite.
    let bytes = crate::io::atomic::read_input(config)
        .with_context(|| format!("cannot read {}", config.display()))?;
    let text = String::from_utf8(bytes)
        .map_err(|_| anyhow!("{}: not an OMG config: not UTF-8 text", config.display()))?;
    let cfg: OmgConfig = serde_json::from_str(&text)
        .with_context(|| format!("{}: not an OMG config", config.display()))?;
    let arrays = crate::io::tensors::read_arrays(weights)?;
    net_from_omg(&cfg, &arrays).map_err(|e| super::json::name_the_file(e, config, weights))
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
pub(crate) mod tests {
    use super::*;
    use crate::net::elu;
    use rand::{Rng, SeedableRng};

    /// A tiny FE model: J = 2, K = 1 (n = 24 + 2 + 6 + 9 = ... see below).
    pub(crate) fn tiny(seed: u64) -> (OmgConfig, BTreeMap<String, NpArray>) {
        let (j, k) = (2usize, 1usize);
        let (np, npose, nc, nt) = (2 * k, 12 * j, 6 * k, 9 * k);
        let n = np + npose + nc + nt;
        let (hae, l, hc, he, hg, ke) = (5, 3, 4, 6, 3, 2);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut arrays = BTreeMap::new();
        let mut put = |name: &str, shape: &[usize], rng: &mut rand_chacha::ChaCha8Rng| {
            let len = shape.iter().product();
            arrays.insert(
                name.to_string(),
                NpArray {
                    shape: shape.iter().map(|&d| d as u64).collect(),
                    data: (0..len).map(|_| rng.gen_range(-0.6..0.6)).collect(),
                },
            );
        };
        for (name, dims) in [
            ("gate", [np, hg, hg, ke]),
            ("enc", [npose, hae, hae, l]),
            ("cost", [nc + nt, hc, hc, hc]),
            ("dec", [l, hae, hae, npose]),
        ] {
            for i in 0..3 {
                put(&format!("{name}.{i}.w"), &[dims[i + 1], dims[i]], &mut rng);
                put(&format!("{name}.{i}.b"), &[dims[i + 1]], &mut rng);
            }
        }
        let mo = np + l + nc;
        for (i, (a, b)) in [(l + hc, he), (he, he), (he, mo)].into_iter().enumerate() {
            put(&format!("experts.w{i}"), &[ke, a, b], &mut rng);
            put(&format!("experts.b{i}"), &[ke, b], &mut rng);
        }
        put("norm.mean", &[n], &mut rng);
        put("norm.std", &[n], &mut rng);
        let s = arrays.get_mut("norm.std").unwrap();
        s.data.iter_mut().for_each(|v| *v = v.abs() + 0.1);
        s.data[3] = 0.0; // constant feature: std := 1
        let sl = |a: usize, b: usize| [a, b];
        let cfg = OmgConfig {
            format: FORMAT.into(),
            variant: "FE".into(),
            joints: j,
            key: k,
            key_joint_indices: vec![1],
            key_joints: vec!["LeftHand".into()],
            model_width: n,
            sizes: OmgSizes {
                ae_hidden: hae,
                latent: l,
                cost_hidden: hc,
                expert_hidden: he,
                gate_hidden: hg,
                experts: ke,
                clusters: 0,
                dof: 0,
            },
            slices: [
                ("phase", sl(0, np)),
                ("pose", sl(np, np + npose)),
                ("pos", sl(np, np + 3 * j)),
                ("rot", sl(np + 3 * j, np + 9 * j)),
                ("vel", sl(np + 9 * j, np + npose)),
                ("cost", sl(np + npose, np + npose + nc)),
                ("pos_cost", sl(np + npose, np + npose + 3 * k)),
                ("rot_cost", sl(np + npose + 3 * k, np + npose + nc)),
                ("target", sl(np + npose + nc, n)),
                ("target_pos", sl(np + npose + nc, np + npose + nc + 3 * k)),
                ("target_rot", sl(np + npose + nc + 3 * k, n)),
            ]
            .into_iter()
            .map(|(a, b)| (a.to_string(), b))
            .collect(),
            out_slices: [
                ("dphase", sl(0, np)),
                ("z", sl(np, np + l)),
                ("cost", sl(np + l, mo)),
            ]
            .into_iter()
            .map(|(a, b)| (a.to_string(), b))
            .collect(),
            phase_update: PhaseUpdate { a: 0.9 },
            mode: "grounded".into(),
            encoder_columns: None,
            normalisation: None,
            pose_form: None,
            controller: None,
        };
        (cfg, arrays)
    }

    /// The forward pass as `tools/omg/omg_np.py` writes it, straight from
    /// the tensors: the model's `Y`.
    fn reference(cfg: &OmgConfig, t: &BTreeMap<String, NpArray>, raw: &[f64]) -> Vec<f64> {
        let (y, _) = reference_parts(cfg, t, raw);
        y
    }

    /// A joint-velocity model's forward pass straight from the tensors:
    /// the network output `[phase', u, cost']` in raw units.
    fn reference_dof(cfg: &OmgConfig, t: &BTreeMap<String, NpArray>, raw: &[f64]) -> Vec<f64> {
        let (y, u) = reference_parts(cfg, t, raw);
        let v = |n: &str| t[n].data.clone();
        let dstd: Vec<f64> = v("norm.dof_std")
            .into_iter()
            .map(|s| if s < MIN_STD { 1.0 } else { s })
            .collect();
        let u: Vec<f64> = (0..u.len())
            .map(|i| u[i] * dstd[i] + v("norm.dof_mean")[i])
            .collect();
        [&y[cfg.slice("phase")], &u[..], &y[cfg.slice("cost")]].concat()
    }

    /// `Y` (its pose block the decoder's output when that has the pose's
    /// width) and the decoder's output, normalised.
    fn reference_parts(
        cfg: &OmgConfig,
        t: &BTreeMap<String, NpArray>,
        raw: &[f64],
    ) -> (Vec<f64>, Vec<f64>) {
        let v = |n: &str| t[n].data.clone();
        let std: Vec<f64> = v("norm.std")
            .into_iter()
            .map(|s| if s < MIN_STD { 1.0 } else { s })
            .collect();
        let mean = v("norm.mean");
        let x: Vec<f64> = (0..raw.len())
            .map(|i| (raw[i] - mean[i]) / std[i])
            .collect();
        let lin = |w: &NpArray, b: &[f64], x: &[f64]| -> Vec<f64> {
            let (o, i) = (w.shape[0] as usize, w.shape[1] as usize);
            (0..o)
                .map(|r| b[r] + (0..i).map(|c| w.data[r * i + c] * x[c]).sum::<f64>())
                .collect()
        };
        let mlp = |name: &str, mut x: Vec<f64>| {
            for i in 0..3 {
                x = lin(
                    &t[&format!("{name}.{i}.w")],
                    &v(&format!("{name}.{i}.b")),
                    &x,
                );
                if i < 2 {
                    x = x.into_iter().map(elu).collect();
                }
            }
            x
        };
        let r = |n: &str| cfg.slice(n);
        let zc = mlp("enc", x[r("pose")].to_vec());
        let mut cin = x[r("cost")].to_vec();
        cin.extend_from_slice(&x[r("target")]);
        let c = mlp("cost", cin);
        let logits = mlp("gate", x[r("phase")].to_vec());
        let m = logits.iter().copied().fold(f64::MIN, f64::max);
        let e: Vec<f64> = logits.iter().map(|l| (l - m).exp()).collect();
        let alpha: Vec<f64> = e.iter().map(|v| v / e.iter().sum::<f64>()).collect();
        let centres = t.get("rbf.centres").or(t.get("dec.centres"));
        let psi: Vec<f64> = match (centres, t.get("rbf.scales")) {
            (Some(mu), Some(sigma)) if cfg.variant == "RBF-CAT" => {
                let l = zc.len();
                (0..sigma.data.len())
                    .map(|j| {
                        let d2: f64 = (0..l).map(|i| (zc[i] - mu.data[j * l + i]).powi(2)).sum();
                        (-(sigma.data[j] * sigma.data[j]) * d2).exp()
                    })
                    .collect()
            }
            (Some(mu), _) if cfg.variant == "DEC-CAT" => {
                let l = zc.len();
                let t: Vec<f64> = (0..mu.data.len() / l)
                    .map(|j| {
                        let d2: f64 = (0..l).map(|i| (zc[i] - mu.data[j * l + i]).powi(2)).sum();
                        1.0 / (1.0 + d2)
                    })
                    .collect();
                let sum: f64 = t.iter().sum();
                t.iter().map(|t| t / sum).collect()
            }
            _ => Vec::new(),
        };
        let mut hv = [zc, c].concat();
        for l in 0..3 {
            hv = [psi.clone(), hv].concat();
            let w = &t[&format!("experts.w{l}")];
            let b = v(&format!("experts.b{l}"));
            let (k, i, o) = (
                w.shape[0] as usize,
                w.shape[1] as usize,
                w.shape[2] as usize,
            );
            let mut out = vec![0.0; o];
            for (e, a) in alpha.iter().enumerate().take(k) {
                for (oo, acc) in out.iter_mut().enumerate() {
                    let d: f64 = (0..i)
                        .map(|ii| hv[ii] * w.data[(e * i + ii) * o + oo])
                        .sum();
                    *acc += a * (d + b[e * o + oo]);
                }
            }
            hv = if l < 2 {
                out.into_iter().map(elu).collect()
            } else {
                out
            };
        }
        let os = |n: &str| {
            let [a, b] = cfg.out_slices[n];
            a..b
        };
        let mut y = vec![0.0; raw.len()];
        for (i, col) in r("phase").enumerate() {
            y[col] = 0.9 * hv[os("dphase")][i] + 0.1 * x[col];
        }
        let pose = mlp("dec", hv[os("z")].to_vec());
        if pose.len() == r("pose").len() {
            y[r("pose")].copy_from_slice(&pose);
        }
        y[r("cost")].copy_from_slice(&hv[os("cost")]);
        y[r("target")].copy_from_slice(&x[r("target")]);
        (
            (0..y.len()).map(|i| y[i] * std[i] + mean[i]).collect(),
            pose,
        )
    }

    /// [`tiny`] as RBF-CAT: `clusters` RBF units in front of every expert
    /// layer's input.
    fn tiny_rbf_cat(seed: u64, clusters: usize) -> (OmgConfig, BTreeMap<String, NpArray>) {
        let (mut cfg, mut arrays) = tiny(seed);
        cfg.variant = "RBF-CAT".into();
        cfg.sizes.clusters = clusters;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed + 100);
        for i in 0..3 {
            let w = arrays.get_mut(&format!("experts.w{i}")).unwrap();
            let (k, inp, out) = (
                w.shape[0] as usize,
                w.shape[1] as usize,
                w.shape[2] as usize,
            );
            w.shape[1] += clusters as u64;
            w.data = (0..k * (inp + clusters) * out)
                .map(|_| rng.gen_range(-0.6..0.6))
                .collect();
        }
        let l = cfg.sizes.latent;
        arrays.insert(
            "rbf.centres".into(),
            NpArray {
                shape: vec![clusters as u64, l as u64],
                data: (0..clusters * l)
                    .map(|_| rng.gen_range(-1.0..1.0))
                    .collect(),
            },
        );
        arrays.insert(
            "rbf.scales".into(),
            NpArray {
                shape: vec![clusters as u64],
                data: (0..clusters).map(|_| rng.gen_range(0.1..1.5)).collect(),
            },
        );
        (cfg, arrays)
    }

    /// [`tiny_rbf_cat`] as DEC-CAT: its centres as `dec.centres`.
    fn tiny_dec_cat(seed: u64, clusters: usize) -> (OmgConfig, BTreeMap<String, NpArray>) {
        let (mut cfg, mut arrays) = tiny_rbf_cat(seed, clusters);
        cfg.variant = "DEC-CAT".into();
        let mu = arrays.remove("rbf.centres").unwrap();
        arrays.remove("rbf.scales");
        arrays.insert("dec.centres".into(), mu);
        (cfg, arrays)
    }

    /// The imported graph's f64 step equals [`reference`] on 20 random
    /// inputs of `seed`.
    fn assert_graph_matches_reference(
        cfg: &OmgConfig,
        arrays: &BTreeMap<String, NpArray>,
        seed: u64,
    ) {
        let m = net_from_omg(cfg, arrays).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..20 {
            let x: Vec<f64> = (0..cfg.model_width)
                .map(|_| rng.gen_range(-2.0..2.0))
                .collect();
            let want = reference(cfg, arrays, &x);
            for (i, (g, w)) in m.step(&x).iter().zip(&want).enumerate() {
                assert!((g - w).abs() < 1e-12, "{i}: {g} vs {w}");
            }
        }
    }

    #[test]
    fn dec_cat_puts_q_in_front_of_every_expert_layer() {
        let (cfg, arrays) = tiny_dec_cat(6, 4);
        assert_graph_matches_reference(&cfg, &arrays, 7);
        let mut a = arrays.clone();
        a.get_mut("dec.centres").unwrap().shape = vec![3, 4];
        assert!(err(&cfg, &a).contains("dec.centres"), "{}", err(&cfg, &a));
        let mut c = cfg.clone();
        c.sizes.clusters = 0;
        assert!(err(&c, &arrays).contains("DEC-CAT needs sizes.clusters > 0"));
    }

    #[test]
    fn rbf_cat_puts_psi_in_front_of_every_expert_layer() {
        let (cfg, arrays) = tiny_rbf_cat(4, 3);
        assert_graph_matches_reference(&cfg, &arrays, 5);
        let mut c = cfg.clone();
        c.sizes.clusters = 0;
        assert!(err(&c, &arrays).contains("needs sizes.clusters > 0"));
        let mut a = arrays.clone();
        a.get_mut("rbf.scales").unwrap().shape = vec![2];
        assert!(err(&cfg, &a).contains("rbf.scales"), "{}", err(&cfg, &a));
    }

    #[test]
    fn the_graph_computes_the_omg_forward_pass() {
        let (cfg, arrays) = tiny(1);
        let m = net_from_omg(&cfg, &arrays).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        for _ in 0..20 {
            let x: Vec<f64> = (0..cfg.model_width)
                .map(|_| rng.gen_range(-2.0..2.0))
                .collect();
            let (got, want) = (m.step(&x), reference(&cfg, &arrays, &x));
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() < 1e-12, "{g} vs {w}");
            }
        }
        let Wiring::Graph(g) = &m.net.wiring else {
            panic!()
        };
        assert_eq!(g.nodes.len(), 16);
        // The constant feature's std became 1.
        assert_eq!(m.net.xstd[3], 1.0);
    }

    #[test]
    fn fs_scatters_the_encoder_columns() {
        let (mut cfg, mut arrays) = tiny(2);
        // FS: the encoder reads columns 4, 7 and 9 only.
        let cols = vec![4usize, 7, 9];
        cfg.variant = "FS".into();
        cfg.encoder_columns = Some(cols.clone());
        let h = cfg.sizes.ae_hidden;
        let w0: Vec<f64> = (0..h * 3).map(|i| (i as f64 * 0.37).sin()).collect();
        arrays.insert(
            "enc.0.w".into(),
            NpArray {
                shape: vec![h as u64, 3],
                data: w0.clone(),
            },
        );
        let m = net_from_omg(&cfg, &arrays).unwrap();
        let x: Vec<f64> = (0..cfg.model_width)
            .map(|i| (i as f64 * 0.11).cos())
            .collect();
        // The same model with the encoder reading a full-width pose block
        // whose other columns have zero weights.
        let mut full = arrays.clone();
        let np = cfg.slice("pose");
        let mut wf = vec![0.0; h * np.len()];
        for r in 0..h {
            for (c, &col) in cols.iter().enumerate() {
                wf[r * np.len() + col - np.start] = w0[r * 3 + c];
            }
        }
        full.insert(
            "enc.0.w".into(),
            NpArray {
                shape: vec![h as u64, np.len() as u64],
                data: wf,
            },
        );
        let mut fe = cfg.clone();
        fe.variant = "FE".into();
        fe.encoder_columns = None;
        let want = reference(&fe, &full, &x);
        for (g, w) in m.step(&x).iter().zip(&want) {
            assert!((g - w).abs() < 1e-12);
        }
    }

    /// [`tiny`] as a joint-velocity model: its 2 joints (a root and a
    /// child 0.3 m up), D = 3 DOFs (root.y, child.x, child.z), `dec.2` of
    /// D rows and the `u` block's statistics (one constant: std 0).
    pub(crate) fn tiny_dof(seed: u64) -> (OmgConfig, BTreeMap<String, NpArray>) {
        let (mut cfg, mut arrays) = tiny(seed);
        let d = 3usize;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed + 200);
        let h = cfg.sizes.ae_hidden;
        let mut put = |name: &str, shape: &[usize], lo: f64, hi: f64| {
            let len = shape.iter().product();
            arrays.insert(
                name.to_string(),
                NpArray {
                    shape: shape.iter().map(|&v| v as u64).collect(),
                    data: (0..len).map(|_| rng.gen_range(lo..hi)).collect(),
                },
            );
        };
        put("dec.2.w", &[d, h], -0.6, 0.6);
        put("dec.2.b", &[d], -0.6, 0.6);
        put("norm.dof_mean", &[d], -0.01, 0.01);
        put("norm.dof_std", &[d], 0.001, 0.02);
        arrays.get_mut("norm.dof_std").unwrap().data[1] = 0.0;
        cfg.sizes.dof = d;
        cfg.pose_form = Some("dof_velocity".into());
        cfg.controller = Some(OmgControllerJson {
            fps: 60.0,
            a_max: 5.0,
            skeleton: OmgSkeletonJson {
                parents: vec![-1, 0],
                offsets: vec![[0.0, 1.0, 0.0], [0.0, 0.3, 0.0]],
                dofs: [(0, 1), (1, 0), (1, 2)]
                    .iter()
                    .map(|&(joint, axis)| OmgDofJson {
                        joint,
                        axis,
                        lower: -0.5,
                        upper: 0.5,
                    })
                    .collect(),
            },
        });
        (cfg, arrays)
    }

    #[test]
    fn a_dof_model_outputs_phase_u_and_costs() {
        let (cfg, arrays) = tiny_dof(11);
        let m = net_from_omg(&cfg, &arrays).unwrap();
        let (np, nc) = (2, 6);
        let form = m.dof.as_ref().unwrap();
        assert_eq!(form.u, np..np + 3);
        assert_eq!(m.net.output_dim(), np + 3 + nc);
        assert_eq!(form.skeleton.parents, vec![None, Some(0)]);
        assert_eq!(form.skeleton.dofs[2].axis, 2);
        assert_eq!((form.skeleton.fps, form.skeleton.a_max), (60.0, 5.0));
        // The u block's statistics are the dof tensors (std 0 -> 1).
        assert_eq!(m.net.ystd[np + 1], 1.0);
        assert_eq!(m.net.ymean[np], arrays["norm.dof_mean"].data[0]);
        assert_eq!(m.blocks[1], (np..np, 2..2));
        assert_eq!(m.blocks[2], (np + 3..np + 3 + nc, cfg.slice("cost")));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        for _ in 0..20 {
            let x: Vec<f64> = (0..cfg.model_width)
                .map(|_| rng.gen_range(-2.0..2.0))
                .collect();
            let (got, want) = (m.output(&x), reference_dof(&cfg, &arrays, &x));
            assert_eq!(got.len(), want.len());
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                assert!((g - w).abs() < 1e-12, "{i}: {g} vs {w}");
            }
            // frame(): the phase and costs in place, the pose kept.
            let y = m.frame(&got, &x);
            assert_eq!(y[cfg.slice("pose")], x[cfg.slice("pose")]);
            assert_eq!(y[cfg.slice("cost")], got[np + 3..]);
        }
        // An absolute model has no dof form and its old output.
        let (cfg, arrays) = tiny(11);
        let a = net_from_omg(&cfg, &arrays).unwrap();
        assert!(a.dof.is_none());
        assert_eq!(a.net.output_dim(), 2 + 24 + 6);
    }

    #[test]
    fn bad_dof_configs_and_tensors_are_named() {
        let (cfg, arrays) = tiny_dof(13);
        let with = |f: &dyn Fn(&mut OmgSkeletonJson)| {
            let mut c = cfg.clone();
            f(&mut c.controller.as_mut().unwrap().skeleton);
            err(&c, &arrays)
        };
        assert_eq!(
            with(&|s| s.dofs[2].axis = 5),
            "controller.skeleton.dofs[2].axis = 5, expected 0, 1 or 2"
        );
        assert_eq!(
            with(&|s| s.dofs[0].joint = 2),
            "controller.skeleton.dofs[0].joint = 2, expected a joint below J = 2"
        );
        assert_eq!(
            with(&|s| s.dofs[1].lower = 0.9),
            "controller.skeleton.dofs[1]: lower = 0.9, upper = 0.5, expected finite limits with lower <= upper"
        );
        assert_eq!(
            with(&|s| s.dofs[2].axis = 0),
            "controller.skeleton.dofs[2]: a second DOF on joint 1 axis 0"
        );
        assert_eq!(
            with(&|s| s.parents[1] = 1),
            "controller.skeleton.parents[1] = 1, expected -1 (a root) or a joint before 1"
        );
        assert!(with(&|s| s.offsets[0][1] = f64::NAN)
            .starts_with("controller.skeleton.offsets[0] holds NaN"));
        assert_eq!(
            with(&|s| {
                s.parents.pop();
            }),
            "controller.skeleton has 1 parents and 2 offsets, but J = 2"
        );
        let mut c = cfg.clone();
        c.controller.as_mut().unwrap().a_max = 0.0;
        assert_eq!(
            err(&c, &arrays),
            "controller.a_max = 0, expected a finite limit above 0"
        );
        let mut c = cfg.clone();
        c.controller.as_mut().unwrap().fps = f64::INFINITY;
        assert!(err(&c, &arrays).starts_with("controller.fps = inf"));
        let mut c = cfg.clone();
        c.sizes.dof = 4;
        assert_eq!(
            err(&c, &arrays),
            "controller.skeleton.dofs has 3 entries, but sizes.dof = 4"
        );
        let mut c = cfg.clone();
        c.controller = None;
        assert!(err(&c, &arrays).contains("needs a controller block"));
        let mut c = cfg.clone();
        c.pose_form = Some("joints".into());
        assert_eq!(
            err(&c, &arrays),
            "pose_form = \"joints\", expected \"absolute\" or \"dof_velocity\""
        );
        let mut c = cfg.clone();
        c.out_slices.insert("u".into(), [2, 4]);
        assert!(err(&c, &arrays).starts_with("out_slices.u = [2, 4], but the network output"));
        c.out_slices.insert("u".into(), [2, 5]);
        assert!(net_from_omg(&c, &arrays).is_ok());
        c.normalisation = Some(OmgNormalisation {
            rule: String::new(),
            mean: None,
            std: None,
            dof_mean: None,
            dof_std: Some(vec![0.5; 3]),
        });
        assert!(err(&c, &arrays).starts_with("normalisation.dof_std[0] = 0.5, but the weights'"));
        let mut a = arrays.clone();
        a.remove("norm.dof_std");
        assert_eq!(err(&cfg, &a), "tensor \"norm.dof_std\" is missing");
        let mut a = arrays.clone();
        a.get_mut("norm.dof_mean").unwrap().shape = vec![4];
        assert!(err(&cfg, &a).starts_with("tensor \"norm.dof_mean\" has shape [4], expected [3]"));
        let mut a = arrays.clone();
        a.get_mut("norm.dof_std").unwrap().data[0] = -1.0;
        assert_eq!(
            err(&cfg, &a),
            "tensor \"norm.dof_std\" is negative at index 0"
        );
        // dec.2 of the pose's width instead of D rows.
        let (_, abs) = tiny(13);
        let mut a = arrays.clone();
        a.insert("dec.2.w".into(), abs["dec.2.w"].clone());
        assert_eq!(
            err(&cfg, &a),
            "tensor \"dec.2.w\" has shape [24, 5], expected [3, 5] (decoder 5 -> 3)"
        );
    }

    /// `read_omg` names the file: the config's fields, the tensors of
    /// `model.safetensors`.
    #[test]
    fn dof_refusals_name_the_file() {
        let (cfg, arrays) = tiny_dof(14);
        let tmp = tempfile::tempdir().unwrap();
        let (w, c) = (
            tmp.path().join("model.safetensors"),
            tmp.path().join("config.json"),
        );
        let tensors: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
            .iter()
            .filter(|(k, _)| *k != "norm.dof_std")
            .map(|(k, a)| {
                (
                    k.as_str(),
                    a.shape.clone(),
                    a.data.iter().map(|&v| v as f32).collect(),
                )
            })
            .collect();
        crate::io::tensors::write_safetensors(&w, &tensors).unwrap();
        let mut json = config_json(&cfg);
        json["controller"]["skeleton"]["dofs"][1]["axis"] = serde_json::json!(7);
        std::fs::write(&c, serde_json::to_string(&json).unwrap()).unwrap();
        let e = format!("{:#}", read_omg(&w, &c).unwrap_err());
        assert!(
            e.ends_with("config.json: controller.skeleton.dofs[1].axis = 7, expected 0, 1 or 2"),
            "{e}"
        );
        json["controller"]["skeleton"]["dofs"][1]["axis"] = serde_json::json!(0);
        std::fs::write(&c, serde_json::to_string(&json).unwrap()).unwrap();
        let e = format!("{:#}", read_omg(&w, &c).unwrap_err());
        assert!(
            e.ends_with(&format!(
                "model.safetensors: tensor \"norm.dof_std\" is missing (the weights of {})",
                c.display()
            )),
            "{e}"
        );
    }

    /// `cfg` as a `config.json` would hold it.
    fn config_json(cfg: &OmgConfig) -> serde_json::Value {
        let s = &cfg.sizes;
        let c = cfg.controller.as_ref().unwrap();
        serde_json::json!({
            "format": cfg.format, "variant": cfg.variant, "J": cfg.joints, "K": cfg.key,
            "key_joint_indices": cfg.key_joint_indices, "model_width": cfg.model_width,
            "sizes": {"ae_hidden": s.ae_hidden, "latent": s.latent, "cost_hidden": s.cost_hidden,
                "expert_hidden": s.expert_hidden, "gate_hidden": s.gate_hidden,
                "experts": s.experts, "dof": s.dof},
            "slices": cfg.slices, "out_slices": cfg.out_slices,
            "phase_update": {"a": cfg.phase_update.a}, "mode": cfg.mode,
            "pose_form": cfg.pose_form,
            "controller": {"fps": c.fps, "a_max": c.a_max, "skeleton": {
                "parents": c.skeleton.parents, "offsets": c.skeleton.offsets,
                "dofs": c.skeleton.dofs.iter().map(|d| serde_json::json!({
                    "joint": d.joint, "axis": d.axis, "lower": d.lower, "upper": d.upper
                })).collect::<Vec<_>>()}},
        })
    }

    fn err(cfg: &OmgConfig, arrays: &BTreeMap<String, NpArray>) -> String {
        format!("{:#}", net_from_omg(cfg, arrays).unwrap_err())
    }

    #[test]
    fn missing_and_ill_shaped_tensors_and_bad_configs_are_named() {
        let (cfg, arrays) = tiny(3);
        let mut a = arrays.clone();
        a.remove("experts.b1");
        assert_eq!(err(&cfg, &a), "tensor \"experts.b1\" is missing");
        let mut a = arrays.clone();
        a.get_mut("dec.1.w").unwrap().shape = vec![4, 5];
        assert_eq!(
            err(&cfg, &a),
            "tensor \"dec.1.w\" has shape [4, 5], expected [5, 5] (decoder 5 -> 5)"
        );
        let mut c = cfg.clone();
        c.sizes.latent = 4;
        assert!(
            err(&c, &arrays).starts_with("out_slices dphase 0..2, z 2..5, cost 5..11 must have")
        );
        let mut c = cfg.clone();
        c.variant = "VAE".into();
        assert!(err(&c, &arrays).contains("expected FE, FS, RBF-CAT or DEC-CAT"));
        let mut c = cfg.clone();
        c.phase_update.a = 1.5;
        assert_eq!(
            err(&c, &arrays),
            "phase_update.a = 1.5: expected 0 < a <= 1"
        );
        let mut c = cfg.clone();
        c.slices.insert("pose".into(), [2, 20]);
        assert_eq!(
            err(&c, &arrays),
            "slices.pose has 18 columns, but J = 2, K = 1 make it 24"
        );
        let mut c = cfg.clone();
        c.normalisation = Some(OmgNormalisation {
            rule: String::new(),
            mean: Some(vec![0.0; c.model_width]),
            std: None,
            dof_mean: None,
            dof_std: None,
        });
        assert!(err(&c, &arrays)
            .starts_with("normalisation.mean[0] = 0, but the weights' norm.mean[0] = "));
    }

    /// Sizes whose products would wrap to the right block widths, and
    /// layouts that would build another network than the one trained, are
    /// refused with the field named.
    #[test]
    fn wrapping_sizes_and_overlapping_or_repeated_columns_are_refused() {
        let (cfg, arrays) = tiny(3);
        // 12 J and 2 K, 6 K wrap (mod 2^64) to the tiny model's 24, 2, 6.
        let mut c = cfg.clone();
        c.joints = 2 + (1 << 62);
        assert_eq!(
            err(&c, &arrays),
            "J = 4611686018427387906: at most 65535 (a blob's widths are 16-bit)"
        );
        let mut c = cfg.clone();
        c.key = 1 + (1 << 63);
        assert!(err(&c, &arrays).starts_with("K = 9223372036854775809: at most 65535"));
        let mut c = cfg.clone();
        c.sizes.expert_hidden = usize::MAX;
        assert!(err(&c, &arrays).starts_with("sizes.expert_hidden = 18446744073709551615: at most"));

        let mut c = cfg.clone();
        c.slices.insert("target".into(), [31, 40]);
        assert_eq!(
            err(&c, &arrays),
            "slices.cost 26..32 and slices.target 31..40 overlap: X's blocks must be disjoint"
        );
        let mut c = cfg.clone();
        c.slices.insert("rot".into(), [7, 20]);
        assert_eq!(
            err(&c, &arrays),
            "slices.pos 2..8 and slices.rot 7..20 overlap"
        );
        let mut c = cfg.clone();
        c.slices.insert("pos_cost".into(), [20, 29]);
        assert_eq!(
            err(&c, &arrays),
            "slices.pos_cost 20..29 is not inside slices.cost 26..32"
        );
        let mut c = cfg.clone();
        c.out_slices.insert("z".into(), [1, 4]);
        assert_eq!(
            err(&c, &arrays),
            "out_slices.dphase 0..2 and out_slices.z 1..4 overlap: the last expert layer's \
             blocks must be disjoint"
        );
        let mut c = cfg.clone();
        c.encoder_columns = Some(vec![2, 3, 3]);
        assert_eq!(
            err(&c, &arrays),
            "encoder_columns[2] = 3: the column is named twice"
        );
    }
}
