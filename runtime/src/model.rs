//! `Model`: a validated, zero-copy view of a blob.

use crate::blob::records::stage_record;
use crate::blob::{
    Framed, GateSource, Gating, Header, LayerDesc, ModelKind, Node, NodeOp, NodeTable, Nodes,
    Requant, Section, Source, MAX_OUTPUT_OFFSET, MAX_OUTPUT_SCALE, REQUANT_RECORD_LEN,
    STAGE_RECORD_LEN,
};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::fixed::softmax::MAX_LOGITS;
use crate::graph::{check_plan, check_structure};
use crate::ops::common::{check_section, section};
use crate::ops::{GatedOp, Layer};

/// Index used in errors about the input and output stages.
pub const STAGE: u8 = 255;

/// Most softmax gates a graph may hold (OMG has one).
pub const MAX_GATES: usize = 2;

/// A blob that passed every check: its header and its payload, borrowed.
///
/// Weights and the node table stay where the blob is (flash on a device);
/// only the header's fixed fields and where each node starts are copied
/// out (under 200 bytes).
#[derive(Clone, Debug)]
pub struct Model<'a> {
    header: Header<NodeTable<'a>>,
    payload: &'a [u8],
    /// Where the nodes outside `own` keep their sections: the motion
    /// blob's payload for a motion blob with a rig, else `payload`.
    #[cfg(feature = "rig")]
    base: &'a [u8],
    /// Bit `i` set: node `i`'s sections are in `payload` (the rig's nodes).
    #[cfg(feature = "rig")]
    own: u32,
    /// The self-test section at the end of the payload, if there is one.
    #[cfg(any(test, feature = "self-test"))]
    self_test: Option<crate::blob::SelfTest<'a>>,
    blob_len: usize,
}

impl<'a> Model<'a> {
    /// Validates `blob` completely (framing, both CRCs, every section, every
    /// requantisation record, the accumulator bound of every row, the header's
    /// RAM and MAC figures). The slice must be exactly one blob.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        Self::load(blob, true)
    }

    /// Like [`Model::from_bytes`], for a blob at the start of a larger
    /// region (a flash partition): bytes after the blob are ignored.
    pub fn from_region(region: &'a [u8]) -> Result<Self> {
        Self::load(region, false)
    }

    fn load(bytes: &'a [u8], exact: bool) -> Result<Self> {
        let Framed {
            header,
            payload,
            blob_len,
        } = Framed::parse(bytes, exact)?;
        if !is_model(&header.kind) {
            return Err(Error::NotAModel);
        }
        #[allow(unused_mut)]
        let mut model = Model {
            header,
            payload,
            #[cfg(feature = "rig")]
            base: payload,
            #[cfg(feature = "rig")]
            own: 0,
            #[cfg(any(test, feature = "self-test"))]
            self_test: None,
            blob_len,
        };
        model.validate()?;
        #[cfg(any(test, feature = "self-test"))]
        {
            model.self_test = crate::blob::SelfTest::find(
                payload,
                model.header.input_dim,
                model.header.output_dim,
            )?;
        }
        Ok(model)
    }

    /// A motion blob and a rig for it as one model (see [`crate::rig`]);
    /// `validate` checks it like a single blob.
    #[cfg(feature = "rig")]
    pub(crate) fn combined(motion: &Model<'a>, rig: Framed<'a>, nodes: u32) -> Result<Self> {
        let model = Model {
            header: rig.header,
            payload: rig.payload,
            base: motion.payload,
            own: nodes,
            // The motion blob's self-test is for the motion blob alone.
            #[cfg(any(test, feature = "self-test"))]
            self_test: None,
            blob_len: rig.blob_len,
        };
        model.validate()?;
        Ok(model)
    }

    /// Bit `i` set: node `i`'s sections are in [`Model::payload`].
    #[cfg(feature = "rig")]
    pub(crate) fn own_nodes(&self) -> u32 {
        self.own
    }

    /// The payload holding node `i`'s sections: the rig's for its nodes,
    /// the motion blob's for the others (a single blob's for all).
    #[inline(always)]
    pub fn node_payload(&self, i: usize) -> &'a [u8] {
        #[cfg(feature = "rig")]
        if (self.own >> (i & 31)) & 1 == 0 {
            return self.base;
        }
        let _ = i;
        self.payload
    }

    /// The header; its nodes decode one at a time ([`Nodes`]), or all
    /// at once with [`Header::decoded`].
    pub fn header(&self) -> &Header<NodeTable<'a>> {
        &self.header
    }

    /// The blob's self-test section (`docs/blob-format.md`, "Self-test
    /// section"), validated at load; `None` when the payload has none, and
    /// for a motion blob combined with a rig (its self-test is the motion
    /// blob's alone). Run it with [`crate::Runtime::run_self_test`].
    #[cfg(any(test, feature = "self-test"))]
    pub fn self_test(&self) -> Option<crate::blob::SelfTest<'a>> {
        self.self_test
    }

    /// Bytes of the whole blob (of the rig blob, for a motion blob with a rig).
    pub fn blob_len(&self) -> usize {
        self.blob_len
    }

    /// Width of the float input.
    pub fn input_dim(&self) -> usize {
        usize::from(self.header.input_dim)
    }

    /// Width of the float output.
    pub fn output_dim(&self) -> usize {
        usize::from(self.header.output_dim)
    }

    /// Activation RAM the model needs, bytes.
    pub fn ram_bytes(&self) -> usize {
        self.header.ram_bytes as usize
    }

    /// Elements (i16) of the activation arena the model needs: the
    /// exporter's plan, checked at load (`ram_bytes / 2`).
    pub fn arena_elements(&self) -> usize {
        self.ram_bytes() / 2
    }

    /// Multiply-accumulates per frame: a function of the header alone.
    pub fn macs_per_frame(&self) -> u32 {
        self.header.macs_per_frame
    }

    /// The gate of this model's gating at `phase`.
    pub fn gate(&self, phase: Phase) -> Gate {
        Gate::new(&self.header.gating, phase)
    }

    /// Node `i`'s layer, bound to its sections, ready to run (`None` for
    /// a softmax gate or past the last node).
    pub fn kernel(&self, i: usize) -> Option<Layer<'a>> {
        let d = *self.header.nodes.node(i)?.layer()?;
        Layer::new(self.node_payload(i), d, i as u8)
    }

    /// The nodes, in evaluation order.
    pub fn nodes(&self) -> &NodeTable<'a> {
        &self.header.nodes
    }

    /// The payload bytes (CRC verified; the rig's, for a motion blob with
    /// a rig: [`Model::node_payload`] says where each node's sections are).
    pub fn payload(&self) -> &'a [u8] {
        self.payload
    }

    /// Input-stage records (offset, scale), one per input.
    pub fn input_stage(&self) -> impl Iterator<Item = (f32, f32)> + 'a {
        stage(self.payload, self.header.input_stage)
    }

    /// Output-stage records (scale, offset), one per output.
    pub fn output_stage(&self) -> impl Iterator<Item = (f32, f32)> + 'a {
        stage(self.payload, self.header.output_stage)
    }

    fn validate(&self) -> Result<()> {
        let h = &self.header;
        validate_gating(&h.gating)?;
        check_structure(h)?;
        let mut gates = 0;
        for i in 0..h.nodes.count() {
            let id = i as u8;
            let n = h.nodes.node(i).ok_or(Error::GraphInvalid { node: id })?;
            match &n.op {
                NodeOp::Layer(d) => {
                    if d.experts != node_gating(&h.gating, &h.nodes, &n).experts() {
                        return Err(Error::GatingMismatch { layer: id });
                    }
                    Layer::bind(self.node_payload(i), *d, id)?;
                }
                NodeOp::Softmax(s) => {
                    gates += 1;
                    if gates > MAX_GATES
                        || s.experts == 0
                        || usize::from(s.experts) > MAX_LOGITS
                        || s.frac > 15
                    {
                        return Err(Error::UnsupportedParameter { layer: id });
                    }
                    self.check_logit_formats(&n, s.frac, id)?;
                }
            }
        }
        // The input stage saturates to i16 whatever its values: finite is
        // enough. The output stage must keep every output within 2^40.
        self.validate_stage(h.input_stage, h.input_dim, [f32::MAX; 2])?;
        self.validate_stage(
            h.output_stage,
            h.output_dim,
            [MAX_OUTPUT_SCALE, MAX_OUTPUT_OFFSET],
        )?;
        check_plan(h)?;
        if u64::from(h.macs_per_frame) != macs(h) {
            return Err(Error::HeaderInconsistent);
        }
        for (i, n) in h.nodes.each().enumerate() {
            if let Some(d) = n.layer() {
                Layer::bind(self.node_payload(i), *d, i as u8)?
                    .check(&node_gating(&h.gating, &h.nodes, &n))?;
            }
        }
        Ok(())
    }

    /// Every logit of a softmax gate comes from a layer row of format
    /// Q`frac` (the gate compares them as plain integers).
    fn check_logit_formats(&self, n: &Node, frac: u8, id: u8) -> Result<()> {
        let bad = Error::UnsupportedParameter { layer: id };
        for s in &n.inputs {
            let Source::Node(j) = s.source else {
                return Err(bad);
            };
            let rows = self.kernel(usize::from(j)).ok_or(bad)?.requant();
            let recs = rows.as_chunks::<REQUANT_RECORD_LEN>().0;
            let start = usize::from(s.start);
            let picked = recs.get(start..start + usize::from(s.len)).ok_or(bad)?;
            if picked
                .iter()
                .any(|r| Requant::from_bytes(r).map(|r| r.frac) != Some(frac))
            {
                return Err(bad);
            }
        }
        Ok(())
    }

    /// A stage section of `dim` records whose two f32 have magnitudes at
    /// most `max` (NaN fails every comparison).
    fn validate_stage(&self, s: Section, dim: u16, max: [f32; 2]) -> Result<()> {
        check_section(self.payload, s, STAGE)?;
        if s.len as usize != usize::from(dim) * STAGE_RECORD_LEN {
            return Err(Error::SectionLength { layer: STAGE });
        }
        if stage(self.payload, s).any(|(a, b)| !(a.abs() <= max[0] && b.abs() <= max[1])) {
            return Err(Error::UnsupportedParameter { layer: STAGE });
        }
        Ok(())
    }
}

/// Whether a blob of `kind` runs alone (styles and rigs run beside one).
fn is_model(kind: &ModelKind) -> bool {
    match kind {
        ModelKind::Style { .. } => false,
        #[cfg(feature = "rig")]
        ModelKind::Rig { .. } => false,
        _ => true,
    }
}

/// A header-level phase gating: counts in range, and not `Softmax`
/// (which only a gate node can drive).
pub(crate) fn validate_gating(g: &Gating) -> Result<u16> {
    let ok = match *g {
        Gating::Single => true,
        Gating::Constant { tables } | Gating::Linear { tables } => tables >= 1,
        Gating::CatmullRom { points } => points >= 4,
        Gating::Softmax { .. } => false,
    };
    if ok {
        Ok(g.experts())
    } else {
        Err(Error::UnsupportedParameter { layer: STAGE })
    }
}

/// The gating that drives node `n` of `nodes`: none, the phase gating
/// `phase`, or its softmax gate's.
pub fn node_gating<N: Nodes + ?Sized>(phase: &Gating, nodes: &N, n: &Node) -> Gating {
    match n.gate {
        GateSource::None => Gating::Single,
        GateSource::Phase => *phase,
        GateSource::Node(j) => match nodes.node(usize::from(j)).map(|g| g.op) {
            Some(NodeOp::Softmax(s)) => Gating::Softmax { experts: s.experts },
            _ => Gating::Single,
        },
    }
}

fn stage(payload: &[u8], s: Section) -> impl Iterator<Item = (f32, f32)> + '_ {
    let bytes = section(payload, s).unwrap_or(&[]);
    bytes
        .as_chunks::<STAGE_RECORD_LEN>()
        .0
        .iter()
        .map(stage_record)
}

/// Multiply-accumulates per frame, summed over the layer nodes
/// ([`GatedOp::macs`] of each op: dense `active x in x out`; CP
/// `rank x (in + out + active)`; diagonal `active x out`), `active` being
/// the number of experts the node's gate makes active (1 when ungated).
/// Softmax gates and concatenations do no multiply-accumulates.
pub fn macs<N: Nodes>(h: &Header<N>) -> u64 {
    h.nodes
        .each()
        .filter_map(|n| {
            let d: &LayerDesc = n.layer()?;
            Some(Layer::macs(
                d,
                node_gating(&h.gating, &h.nodes, &n).active() as u64,
            ))
        })
        .sum()
}
