//! OMG models and the fixed-point grid, for quantisation-aware training
//! (docs/omg.md, "A model trained for its int8 blob"):
//!
//! * [`grid`]: for every weight tensor the exporter quantises row by row,
//!   the integer units per real unit of each input column (the producers'
//!   row formats, powers of two). A row's weight `w_ij` becomes
//!   `round(w_ij / u_j * s_i)` with `s_i = 127 / max_j |w_ij / u_j|` (shared
//!   by an expert stack's experts): the trainer rounds the same way.
//! * [`snapped`]: the model's tensors as the blob computes them (integer
//!   weights and biases scaled back), under the names and shapes of
//!   `model.safetensors`. Its f64 forward is what the blob approximates only
//!   in its activations.

use std::collections::BTreeMap;
use std::ops::Range;

use anyhow::{anyhow, bail, Result};
use ndarray::Array2;

use super::omg::OmgNet;
use super::{ExpertLayer, GraphOp, NetLayer, Wiring};
use crate::io::tensors::NpArray;
use crate::quantise::Quantised;

/// One weight tensor of `model.safetensors` and the graph node holding it.
struct Place {
    node: usize,
    layer: usize,
    /// `name.w` / `name.b` (linear) or `experts.w{l}` / `experts.b{l}`.
    weight: String,
    bias: String,
    experts: bool,
    /// The node's rows and columns the tensor fills (`out` holds the
    /// decoder's last layer among the phase and cost rows).
    rows: Range<usize>,
    cols: Vec<usize>,
}

fn places(omg: &OmgNet) -> Result<Vec<Place>> {
    let Wiring::Graph(g) = &omg.net.wiring else {
        bail!("an OMG net is a graph");
    };
    let cfg = &omg.config;
    let np = cfg.slice("phase").len();
    // The decoder's last layer's rows in `out`: the pose's, or a
    // joint-velocity model's D.
    let npose = omg
        .dof
        .as_ref()
        .map_or_else(|| cfg.slice("pose").len(), |d| d.u.len());
    let nh = cfg.sizes.ae_hidden;
    let mut out = Vec::new();
    for (node, n) in g.nodes.iter().enumerate() {
        let GraphOp::Layer { layer, .. } = n.op else {
            continue;
        };
        let Some(NetLayer::Dense(d)) = omg.net.layers.get(layer) else {
            continue;
        };
        let (rows, cols) = (d.w[0].nrows(), d.w[0].ncols());
        let name = n.name.as_str();
        let (stem, idx) = name.split_at(name.len() - 1);
        let place = |weight: String, bias: String, experts, rows, cols| Place {
            node,
            layer,
            weight,
            bias,
            experts,
            rows,
            cols,
        };
        out.push(match (stem, idx) {
            ("gate" | "enc" | "cost" | "dec", _) => {
                let cols = match (name, &cfg.encoder_columns) {
                    ("enc0", Some(c)) => {
                        let lo = c.iter().copied().min().unwrap_or(0);
                        c.iter().map(|&j| j - lo).collect()
                    }
                    _ => (0..cols).collect(),
                };
                place(
                    format!("{stem}.{idx}.w"),
                    format!("{stem}.{idx}.b"),
                    false,
                    0..rows,
                    cols,
                )
            }
            ("moe", _) => place(
                format!("experts.w{idx}"),
                format!("experts.b{idx}"),
                true,
                0..rows,
                (0..cols).collect(),
            ),
            ("ou", "t") => place(
                "dec.2.w".into(),
                "dec.2.b".into(),
                false,
                np..np + npose,
                (2 * np..2 * np + nh).collect(),
            ),
            _ => bail!("OMG graph node {name:?} has no tensor in model.safetensors"),
        });
    }
    Ok(out)
}

/// Per weight tensor, the integer units per real unit of each of its input
/// columns in the blob `q` was quantised for.
pub fn grid(omg: &OmgNet, q: &Quantised) -> Result<BTreeMap<String, Vec<f64>>> {
    places(omg)?
        .into_iter()
        .map(|p| {
            let u = q
                .in_scales
                .get(p.node)
                .filter(|u| !u.is_empty())
                .ok_or_else(|| {
                    anyhow!("node {} has no input scales (not a graph export?)", p.node)
                })?;
            let cols = p
                .cols
                .iter()
                .map(|&j| {
                    u.get(j)
                        .copied()
                        .ok_or_else(|| anyhow!("{}: column {j}", p.weight))
                })
                .collect::<Result<Vec<f64>>>()?;
            Ok((p.weight, cols))
        })
        .collect()
}

/// `arrays` (the model's tensors) with every dense weight and bias replaced
/// by its value in the blob `q` was quantised for.
pub fn snapped(
    omg: &OmgNet,
    q: &Quantised,
    arrays: &BTreeMap<String, NpArray>,
) -> Result<BTreeMap<String, NpArray>> {
    let mut out = arrays.clone();
    for p in places(omg)? {
        let Some(NetLayer::Dense(d)) = q.dequantised.get(p.layer) else {
            bail!("{}: the quantiser returned no dense layer", p.weight);
        };
        let (w, b) = tensors(d, &p)?;
        for (name, new) in [(&p.weight, w), (&p.bias, b)] {
            let old = out
                .get_mut(name)
                .ok_or_else(|| anyhow!("tensor {name:?} is missing"))?;
            if old.shape != new.shape {
                bail!(
                    "tensor {name:?}: shape {:?}, expected {:?}",
                    old.shape,
                    new.shape
                );
            }
            *old = new;
        }
    }
    Ok(out)
}

/// The tensor pair of `p` from its node's layer `d`.
fn tensors(d: &ExpertLayer, p: &Place) -> Result<(NpArray, NpArray)> {
    let k = d.w.len();
    let (nr, nc) = (p.rows.len(), p.cols.len());
    let pick = |w: &Array2<f64>, i: usize, j: usize| w[(p.rows.start + i, p.cols[j])];
    if p.experts {
        // (k, in, out) and (k, out)
        let w = (0..k)
            .flat_map(|e| (0..nc).flat_map(move |j| (0..nr).map(move |i| (e, i, j))))
            .map(|(e, i, j)| pick(&d.w[e], i, j))
            .collect();
        let b = (0..k)
            .flat_map(|e| (0..nr).map(move |i| d.b[e][p.rows.start + i]))
            .collect();
        Ok((
            NpArray::new(vec![k as u64, nc as u64, nr as u64], w)?,
            NpArray::new(vec![k as u64, nr as u64], b)?,
        ))
    } else {
        let w = (0..nr)
            .flat_map(|i| (0..nc).map(move |j| (i, j)))
            .map(|(i, j)| pick(&d.w[0], i, j))
            .collect();
        let b = (0..nr).map(|i| d.b[0][p.rows.start + i]).collect();
        Ok((
            NpArray::new(vec![nr as u64, nc as u64], w)?,
            NpArray::new(vec![nr as u64], b)?,
        ))
    }
}

/// `arrays` as a safetensors file, every tensor float32 (a snapped weight
/// is an integer times a power of two over a row scale: float32 keeps it to
/// within 2^-24 of itself, which rounds back to the same integer).
pub fn to_safetensors(arrays: &BTreeMap<String, NpArray>) -> Result<Vec<u8>> {
    let list: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
        .iter()
        .map(|(n, a)| {
            let data = a.data.iter().map(|&v| v as f32).collect();
            (n.as_str(), a.shape.clone(), data)
        })
        .collect();
    crate::io::tensors::safetensors_bytes(&list)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::omg::{
        net_from_omg,
        tests::{tiny, tiny_dof},
        HEADROOM,
    };
    use crate::quantise::{quantise_net, QuantOptions};

    fn quantised(
        cfg: &crate::net::omg::OmgConfig,
        a: &BTreeMap<String, NpArray>,
    ) -> (OmgNet, Quantised) {
        let omg = net_from_omg(cfg, a).unwrap();
        let opts = QuantOptions {
            headroom: HEADROOM,
            ..QuantOptions::default()
        };
        let q = quantise_net(&omg.net, &opts).unwrap();
        (omg, q)
    }

    fn largest_move(a: &BTreeMap<String, NpArray>, b: &BTreeMap<String, NpArray>) -> f64 {
        a.iter()
            .flat_map(|(n, x)| x.data.iter().zip(&b[n].data).map(|(u, v)| (u - v).abs()))
            .fold(0.0, f64::max)
    }

    /// An absolute and a joint-velocity model (whose `dec.2` fills `out`'s
    /// D middle rows).
    #[test]
    fn snapping_reaches_a_model_whose_blob_holds_its_weights_exactly() {
        for (cfg, arrays) in [tiny(5), tiny_dof(5)] {
            snaps_to_a_fixed_point(&cfg, arrays);
        }
    }

    fn snaps_to_a_fixed_point(
        cfg: &crate::net::omg::OmgConfig,
        mut arrays: BTreeMap<String, NpArray>,
    ) {
        let cfg = cfg.clone();
        let std = arrays["norm.std"].clone();
        let mut moves = Vec::new();
        for _ in 0..6 {
            let (omg, q) = quantised(&cfg, &arrays);
            let next = snapped(&omg, &q, &arrays).unwrap();
            moves.push(largest_move(&arrays, &next));
            arrays = next;
            if moves.last() < Some(&1e-12) {
                break;
            }
        }
        assert!(
            moves[0] > 1e-4,
            "the random model is not on the grid: {moves:?}"
        );
        assert!(
            *moves.last().unwrap() < 1e-12,
            "no fixed point in 6 snaps: {moves:?}"
        );
        // At the fixed point every weight is an integer step of its row, the
        // row's largest at +-127, and the normalisation untouched.
        let (omg, q) = quantised(&cfg, &arrays);
        let g = grid(&omg, &q).unwrap();
        assert_eq!(g.len(), 4 * 3 + 3, "every MLP layer and expert stack");
        for (name, u) in &g {
            assert!(
                u.iter().all(|&v| v > 0.0 && v.log2().fract() == 0.0),
                "{name}: {u:?}"
            );
            let t = &arrays[name];
            let shape: Vec<usize> = t.shape.iter().map(|&d| d as usize).collect();
            // (row, column) of every element, rows shared across experts
            let at = |idx: usize| -> (usize, usize) {
                match shape[..] {
                    [_, i, o] => (idx % o, (idx / o) % i),
                    [_, i] => (idx / i, idx % i),
                    _ => unreachable!(),
                }
            };
            let rows = if shape.len() == 3 { shape[2] } else { shape[0] };
            let mut most = vec![0.0f64; rows];
            for (k, &w) in t.data.iter().enumerate() {
                let (r, c) = at(k);
                most[r] = most[r].max((w / u[c]).abs());
            }
            for (k, &w) in t.data.iter().enumerate() {
                let (r, c) = at(k);
                let steps = w / u[c] * 127.0 / most[r];
                assert!(
                    (steps - steps.round()).abs() < 1e-9,
                    "{name}[{k}] = {steps} steps"
                );
            }
        }
        assert_eq!(arrays["norm.std"], std);
    }

    #[test]
    fn snapped_tensors_survive_float32_storage() {
        let (cfg, arrays) = tiny(6);
        let (omg, q) = quantised(&cfg, &arrays);
        let s = snapped(&omg, &q, &arrays).unwrap();
        let bytes = to_safetensors(&s).unwrap();
        let back = crate::io::tensors::parse_safetensors(&bytes).unwrap();
        assert_eq!(
            back.keys().collect::<Vec<_>>(),
            s.keys().collect::<Vec<_>>()
        );
        for (n, a) in &s {
            assert_eq!(back[n].shape, a.shape, "{n}");
            for (x, y) in a.data.iter().zip(&back[n].data) {
                assert!((x - y).abs() <= x.abs() * 6e-8, "{n}: {x} stored as {y}");
            }
        }
    }
}
