//! Which rows of a graph blob saturate on given inputs: the f64 graph's
//! pre-activations against the range of each row's format (its
//! requantisation record's Q`frac`: `32767 / 2^frac` real units).
//!
//! A saturated row is no rounding error but a clipped value, the same on
//! every frame that reaches it, and a closed loop feeds it back:
//! small_rbfcat_r1's int16 blob once clipped four arm velocities at -4
//! standard deviations for dozens of frames (`docs/omg.md`). The exporter
//! calibrates on normal inputs; this measures the blob on real motion.

use anyhow::{bail, Result};
use exporter::inspect::row_formats;
use exporter::net::{Net, Wiring};
use phasegate::Model;
use serde::Serialize;

/// One node's rows that left their range on some input.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NodeSaturation {
    /// The node.
    pub node: usize,
    /// Its rows that saturated on at least one input.
    pub rows: Vec<usize>,
    /// Inputs on which at least one of its rows saturated.
    pub inputs: usize,
    /// Largest |pre-activation| over its range (above 1).
    pub worst: f64,
}

/// What [`saturated`] found.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Saturation {
    /// Inputs checked.
    pub inputs: usize,
    /// The nodes with saturated rows (none: every row stayed in range).
    pub nodes: Vec<NodeSaturation>,
}

impl Saturation {
    /// One line: `none`, or per node its rows, the share of inputs and
    /// the worst excess.
    pub fn summary(&self) -> String {
        if self.nodes.is_empty() {
            return "none".into();
        }
        self.nodes
            .iter()
            .map(|n| {
                format!(
                    "node {}: {} rows on {:.2} % of frames (up to {:.2}x its range)",
                    n.node,
                    n.rows.len(),
                    100.0 * n.inputs as f64 / self.inputs.max(1) as f64,
                    n.worst
                )
            })
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// The rows of `model` (a graph blob of `net`) whose f64 pre-activation
/// on some of `inputs` (raw model units) is beyond their format's range.
pub fn saturated(model: &Model<'_>, net: &Net, inputs: &[Vec<f64>]) -> Result<Saturation> {
    let Wiring::Graph(g) = &net.wiring else {
        bail!("saturation is measured on graph models");
    };
    // Per layer node: each row's range in real units.
    let ranges: Vec<Option<Vec<f64>>> = (0..g.nodes.len())
        .map(|i| {
            model
                .kernel(i)
                .map(|_| row_formats(model, i))
                .transpose()
                .map(|f| f.map(|f| f.iter().map(|&q| 32767.0 / f64::from(q).exp2()).collect()))
        })
        .collect::<Result<_>>()?;
    let mut out: Vec<NodeSaturation> = Vec::new();
    for x in inputs {
        let t = net.graph_trace(g, x, 0.0);
        for (i, range) in ranges.iter().enumerate() {
            let Some(range) = range else { continue };
            if range.len() != t.pre[i].len() {
                bail!(
                    "node {i}: the blob has {} rows, the net {}",
                    range.len(),
                    t.pre[i].len()
                );
            }
            let over: Vec<(usize, f64)> = t.pre[i]
                .iter()
                .zip(range)
                .enumerate()
                .map(|(r, (p, m))| (r, p.abs() / m))
                .filter(|&(_, q)| q > 1.0)
                .collect();
            if over.is_empty() {
                continue;
            }
            let at = match out.iter().position(|s| s.node == i) {
                Some(at) => at,
                None => {
                    out.push(NodeSaturation {
                        node: i,
                        rows: Vec::new(),
                        inputs: 0,
                        worst: 0.0,
                    });
                    out.len() - 1
                }
            };
            let s = &mut out[at];
            s.inputs += 1;
            for (r, q) in over {
                if !s.rows.contains(&r) {
                    s.rows.push(r);
                }
                s.worst = s.worst.max(q);
            }
        }
    }
    for s in &mut out {
        s.rows.sort_unstable();
    }
    out.sort_by_key(|s| s.node);
    Ok(Saturation {
        inputs: inputs.len(),
        nodes: out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::omg::{export, exporter_options, load_dir};
    use phasegate::blob::{Source, WeightFormat};

    /// The exporter keeps tiny_fe_r1's output rows wide enough for its
    /// reference frames; forced to Q15 (+-1 std) they saturate, and the
    /// check names the node, its rows and how far beyond they went.
    #[test]
    fn finds_the_output_rows_a_narrow_format_clips() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        let d = load_dir(&dir).unwrap();
        let Wiring::Graph(g) = &d.omg.net.wiring else {
            panic!("an OMG model is a graph")
        };
        let Source::Node(out) = g.output.source else {
            panic!("the output is a node's")
        };
        let out = usize::from(out);
        let [clips, frames, _] = d.refs.inputs.dims;
        let inputs: Vec<Vec<f64>> = (0..clips)
            .flat_map(|c| (0..frames).map(move |t| (c, t)))
            .map(|(c, t)| d.refs.inputs.row(c, t).to_vec())
            .collect();
        let check = |opts| {
            let blob = export(&d, WeightFormat::I16, &opts).unwrap();
            saturated(&Model::from_bytes(&blob).unwrap(), &d.omg.net, &inputs).unwrap()
        };
        let s = check(exporter_options(WeightFormat::I16));
        assert_eq!(s.inputs, inputs.len());
        assert!(s.nodes.iter().all(|n| n.node != out), "{}", s.summary());

        let mut narrow = exporter_options(WeightFormat::I16);
        narrow
            .row_formats
            .insert(out, vec![15; usize::from(g.output.len)]);
        let s = check(narrow);
        let n = s
            .nodes
            .iter()
            .find(|n| n.node == out)
            .expect("the output saturates");
        assert!(!n.rows.is_empty() && n.rows.windows(2).all(|w| w[0] < w[1]));
        assert!(n.inputs > 0 && n.inputs <= inputs.len());
        assert!(n.worst > 1.0, "{}", n.worst);
        assert!(s
            .summary()
            .contains(&format!("node {out}: {} rows", n.rows.len())));
    }
}
