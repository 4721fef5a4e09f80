//! Styles on the target: the STYLES image (style blobs back to back at
//! 16-byte aligned offsets, see `docs/firmware.md`), the per-frame mix
//! schedule of `host-sim target --mix`, and the per-mix figures.

use std::fmt;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use phasegate::blob::LayerOp;
use phasegate::style::BlendWeight;
use phasegate::{Mix, Style, StyleId};

use super::Stats;

/// Alignment of each style blob's offset in the STYLES region (the
/// firmware's `STYLE_ALIGN`).
pub const STYLE_ALIGN: usize = 16;

/// Frames per step of `--mix cycle` when no step is given.
pub const DEFAULT_CYCLE_STEP: usize = 2;

/// Blend weights `--mix cycle` sweeps, in order (0 and 1 included: they
/// must give the two styles bit for bit).
pub const CYCLE_WEIGHTS: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// The STYLES image: each blob at a 16-byte aligned offset, zeros between.
/// The firmware stops at the first aligned offset without the blob magic:
/// the zeros (or erased memory) after the last blob.
pub fn pack_styles(blobs: &[Vec<u8>]) -> Vec<u8> {
    let mut image = Vec::new();
    for b in blobs {
        image.resize(image.len().next_multiple_of(STYLE_ALIGN), 0);
        image.extend_from_slice(b);
    }
    image
}

/// A rig blob read from a file (`--rig`): it goes where the styles would,
/// at the start of the STYLES region.
#[derive(Clone, Debug)]
pub struct RigFile {
    /// Where it came from.
    pub path: PathBuf,
    /// Its bytes.
    pub bytes: Vec<u8>,
    /// Its name.
    pub name: String,
    /// Payload CRC of the motion blob it was built for.
    pub base_crc: u32,
    /// Bit `i` set: node `i` is the rig's.
    pub nodes: u32,
}

impl RigFile {
    /// Reads a rig blob and checks its framing (whether it fits the motion
    /// blob is `Model::with_rig`'s business).
    pub fn read(path: &Path) -> Result<RigFile> {
        let bytes = exporter::atomic::read_input(path)
            .with_context(|| format!("cannot read the rig blob {}", path.display()))?;
        let info = phasegate::RigInfo::from_bytes(&bytes)
            .with_context(|| format!("{} is not a rig blob", path.display()))?;
        Ok(RigFile {
            path: path.to_path_buf(),
            name: info.name.to_owned(),
            base_crc: info.base_crc,
            nodes: info.nodes,
            bytes,
        })
    }
}

/// A style blob read from a file, with what the report says about it.
#[derive(Clone, Debug)]
pub struct StyleFile {
    /// Where it came from.
    pub path: PathBuf,
    /// Its bytes.
    pub bytes: Vec<u8>,
    /// Its name.
    pub name: String,
    /// Base layer it sits beside.
    pub layer: u8,
    /// `full`, `diagonal` or `cp`.
    pub form: &'static str,
    /// CP rank, for CP adapters.
    pub rank: Option<u16>,
    /// Multiply-accumulates it adds to a frame that uses it.
    pub macs: u64,
    /// Payload CRC of the base it was built for.
    pub base_crc: u32,
}

impl StyleFile {
    /// Reads and validates a style blob (on its own; whether it fits the
    /// base is the runtime's `add_style`'s business).
    pub fn read(path: &Path) -> Result<StyleFile> {
        let bytes = exporter::atomic::read_input(path)
            .with_context(|| format!("cannot read the style blob {}", path.display()))?;
        StyleFile::from_bytes(path, bytes)
    }

    /// Validates `bytes` as a style blob.
    pub fn from_bytes(path: &Path, bytes: Vec<u8>) -> Result<StyleFile> {
        let s = Style::from_bytes(&bytes)
            .with_context(|| format!("{} is not a valid style blob", path.display()))?;
        let (form, rank) = match s.kernel().desc().op {
            LayerOp::Dense => ("full", None),
            LayerOp::Diagonal => ("diagonal", None),
            LayerOp::Cp { rank, .. } => ("cp", Some(rank)),
            LayerOp::Rbf { .. } => ("rbf", None),
            LayerOp::Dec { .. } => ("dec", None),
        };
        Ok(StyleFile {
            path: path.to_path_buf(),
            name: s.name().to_string(),
            layer: s.layer(),
            form,
            rank,
            macs: s.macs_per_frame(),
            base_crc: s.base_crc(),
            bytes,
        })
    }
}

/// `--mix`: which mix each frame uses.
///
/// ```text
/// SPEC := "cycle" [":" STEP] | ITEM ("," ITEM)*
/// ITEM := MIX ["*" COUNT]                  COUNT consecutive frames (default 1)
/// MIX  := "base" | ID | "blend:" ID ":" ID ":" WEIGHT
/// ```
///
/// A list repeats: frame `i` uses entry `i mod total count`. `ID` is a
/// style's index (the order of `--style`), `WEIGHT` a number in `[0, 1]`,
/// rounded to the nearest U1F15 (2^-15). `cycle` switches every STEP
/// frames (default 2) through base, style 0, style 1, and the blend
/// 0 -> 1 at weights 0, 0.25, 0.5, 0.75 and 1 (8 steps, then again).
#[derive(Clone, Debug, PartialEq)]
pub enum MixSpec {
    /// The `cycle` schedule, STEP frames per step.
    Cycle {
        /// Frames per step.
        step: usize,
    },
    /// A repeating list of (mix, consecutive frames).
    List(Vec<(Mix, usize)>),
}

impl Default for MixSpec {
    fn default() -> Self {
        MixSpec::List(vec![(Mix::Base, 1)])
    }
}

fn parse_id(s: &str) -> Result<StyleId> {
    let id: u8 = s
        .trim()
        .parse()
        .with_context(|| format!("{s:?} is not a style id (0 to 255)"))?;
    Ok(StyleId(id))
}

/// U1F15 weight nearest to `w` in `[0, 1]`.
pub fn blend_weight(w: f64) -> Result<BlendWeight> {
    ensure!(
        w.is_finite() && (0.0..=1.0).contains(&w),
        "blend weight {w} is not in [0, 1]"
    );
    Ok(BlendWeight::from_bits((w * 32768.0).round() as u16))
}

fn parse_mix(s: &str) -> Result<Mix> {
    let s = s.trim();
    if s == "base" {
        return Ok(Mix::Base);
    }
    if let Some(rest) = s.strip_prefix("blend:") {
        let parts: Vec<&str> = rest.split(':').collect();
        let [from, to, w] = parts[..] else {
            bail!("{s:?}: a blend is blend:FROM:TO:WEIGHT");
        };
        let w: f64 = w
            .trim()
            .parse()
            .with_context(|| format!("{s:?}: {w:?} is not a number"))?;
        return Ok(Mix::Blend {
            from: parse_id(from)?,
            to: parse_id(to)?,
            weight: blend_weight(w).with_context(|| format!("{s:?}"))?,
        });
    }
    parse_id(s)
        .map(Mix::One)
        .with_context(|| format!("{s:?}: a mix is base, a style id, or blend:FROM:TO:WEIGHT"))
}

impl std::str::FromStr for MixSpec {
    type Err = anyhow::Error;

    /// Parses a SPEC; the error is one line holding its whole cause.
    fn from_str(spec: &str) -> Result<MixSpec> {
        parse_spec(spec).map_err(|e| anyhow::anyhow!("{e:#}"))
    }
}

fn parse_spec(spec: &str) -> Result<MixSpec> {
    let spec = spec.trim();
    if let Some(rest) = spec.strip_prefix("cycle") {
        let step = match rest.strip_prefix(':') {
            None if rest.is_empty() => DEFAULT_CYCLE_STEP,
            Some(n) => n
                .trim()
                .parse()
                .with_context(|| format!("cycle:STEP needs a frame count, not {n:?}"))?,
            None => bail!("did you mean cycle or cycle:STEP?"),
        };
        ensure!(step >= 1, "cycle:STEP: STEP must be at least 1");
        return Ok(MixSpec::Cycle { step });
    }
    let mut items = Vec::new();
    for item in spec.split(',') {
        let (mix, count) = match item.split_once('*') {
            Some((m, n)) => (
                m,
                n.trim()
                    .parse::<usize>()
                    .with_context(|| format!("{item:?}: {n:?} is not a count"))?,
            ),
            None => (item, 1),
        };
        ensure!(count >= 1, "{item:?}: a count must be at least 1");
        items.push((parse_mix(mix)?, count));
    }
    Ok(MixSpec::List(items))
}

impl fmt::Display for MixSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MixSpec::Cycle { step } => write!(f, "cycle:{step}"),
            MixSpec::List(items) => {
                for (i, (mix, count)) in items.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    f.write_str(&mix_spec_item(*mix))?;
                    if *count > 1 {
                        write!(f, "*{count}")?;
                    }
                }
                Ok(())
            }
        }
    }
}

/// A mix as `--mix` writes it.
pub fn mix_spec_item(mix: Mix) -> String {
    match mix {
        Mix::Base => "base".into(),
        Mix::One(StyleId(a)) => a.to_string(),
        Mix::Blend { from, to, weight } => format!(
            "blend:{}:{}:{}",
            from.0,
            to.0,
            f64::from(weight.to_bits()) / 32768.0
        ),
    }
}

impl MixSpec {
    /// The mix of each of `frames` frames.
    pub fn schedule(&self, frames: usize) -> Vec<Mix> {
        match self {
            MixSpec::Cycle { step } => {
                let (a, b) = (StyleId(0), StyleId(1));
                let mut steps = vec![Mix::Base, Mix::One(a), Mix::One(b)];
                steps.extend(CYCLE_WEIGHTS.iter().map(|&w| Mix::Blend {
                    from: a,
                    to: b,
                    weight: BlendWeight::from_bits((w * 32768.0).round() as u16),
                }));
                (0..frames)
                    .map(|i| steps[(i / step) % steps.len()])
                    .collect()
            }
            MixSpec::List(items) => {
                let period: Vec<Mix> = items
                    .iter()
                    .flat_map(|&(m, n)| std::iter::repeat_n(m, n))
                    .collect();
                (0..frames).map(|i| period[i % period.len()]).collect()
            }
        }
    }

    /// Whether the schedule uses any style.
    pub fn uses_styles(&self) -> bool {
        match self {
            MixSpec::Cycle { .. } => true,
            MixSpec::List(items) => items.iter().any(|(m, _)| *m != Mix::Base),
        }
    }

    /// The schedule `host-sim target` uses when `--mix` is not given:
    /// `base` without styles, `base*2,0*2` with one, `cycle` with more.
    pub fn default_for(styles: usize) -> MixSpec {
        match styles {
            0 => MixSpec::default(),
            1 => MixSpec::List(vec![(Mix::Base, 2), (Mix::One(StyleId(0)), 2)]),
            _ => MixSpec::Cycle {
                step: DEFAULT_CYCLE_STEP,
            },
        }
    }
}

/// The styles a mix uses (both for a blend, whatever its weight: the
/// runtime runs both adapters).
pub fn mix_styles(mix: Mix) -> Vec<StyleId> {
    match mix {
        Mix::Base => vec![],
        Mix::One(a) => vec![a],
        Mix::Blend { from, to, .. } => vec![from, to],
    }
}

/// Multiply-accumulates of a frame with `mix`: the base's plus those of
/// every adapter it runs.
pub fn frame_macs(base: u64, styles: &[StyleFile], mix: Mix) -> u64 {
    base + mix_styles(mix)
        .iter()
        .map(|id| styles.get(usize::from(id.0)).map_or(0, |s| s.macs))
        .sum::<u64>()
}

/// Checks that every style a schedule uses was given.
pub fn check_schedule(mixes: &[Mix], styles: usize) -> Result<()> {
    for (i, &mix) in mixes.iter().enumerate() {
        for id in mix_styles(mix) {
            ensure!(
                usize::from(id.0) < styles,
                "frame {i}: the mix {} uses style {}, but {styles} --style blob(s) were given",
                mix_spec_item(mix),
                id.0
            );
        }
    }
    Ok(())
}

/// The frames that used one kind of mix (blends grouped over weights).
#[derive(Clone, Debug, PartialEq)]
pub struct MixGroup {
    /// `base`, `style 0`, `blend 0 -> 1`.
    pub label: String,
    /// Blend weights seen, in order of first use.
    pub weights: Vec<f64>,
    /// Frames.
    pub frames: usize,
    /// Inference instructions per frame.
    pub infer: Stats,
    /// MACs of each of these frames.
    pub macs: u64,
}

impl MixGroup {
    /// Median inference instructions per MAC.
    pub fn instructions_per_mac(&self) -> f64 {
        self.infer.median as f64 / self.macs.max(1) as f64
    }
}

fn group_label(mix: Mix) -> String {
    match mix {
        Mix::Base => "base".into(),
        Mix::One(a) => format!("style {}", a.0),
        Mix::Blend { from, to, .. } => format!("blend {} -> {}", from.0, to.0),
    }
}

/// Groups frames by mix kind, in order of first use.
pub fn mix_groups(
    mixes: &[Mix],
    infer_instructions: &[u64],
    base_macs: u64,
    styles: &[StyleFile],
) -> Vec<MixGroup> {
    let mut groups: Vec<(MixGroup, Vec<u64>)> = Vec::new();
    for (&mix, &instr) in mixes.iter().zip(infer_instructions) {
        let label = group_label(mix);
        let pos = match groups.iter().position(|(g, _)| g.label == label) {
            Some(p) => p,
            None => {
                groups.push((
                    MixGroup {
                        label,
                        weights: Vec::new(),
                        frames: 0,
                        infer: Stats::default(),
                        macs: frame_macs(base_macs, styles, mix),
                    },
                    Vec::new(),
                ));
                groups.len() - 1
            }
        };
        let (g, values) = &mut groups[pos];
        g.frames += 1;
        values.push(instr);
        if let Mix::Blend { weight, .. } = mix {
            let w = f64::from(weight.to_bits()) / 32768.0;
            if !g.weights.contains(&w) {
                g.weights.push(w);
            }
        }
    }
    groups
        .into_iter()
        .map(|(mut g, v)| {
            g.infer = Stats::of(&v);
            g
        })
        .collect()
}
