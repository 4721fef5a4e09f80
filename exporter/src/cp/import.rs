//! Trained CP factors (and dense or diagonal layers beside them) from
//! NumPy `.npz` or `.safetensors` files.
//!
//! Whole models (a PFNN-shaped network, every layer dense, CP or diagonal):
//!
//! | name | shape | meaning |
//! |---|---|---|
//! | `Xmean`, `Xstd` | (in,) | input normalisation |
//! | `Ymean`, `Ystd` | (out,) | output de-normalisation |
//! | `A{l}` | (out_l, R_l) | CP factor A of layer l |
//! | `B{l}` | (in_l, R_l) | CP factor B of layer l |
//! | `D{l}` | (K, R_l) | cores: row k is `d_k` of expert k |
//! | `W{l}` | (K, out_l, in_l) | dense layer l instead of `A/B/D` |
//! | `w{l}` | (K, n_l) | diagonal layer l (`in_l == out_l == n_l`) instead |
//! | `b{l}` | (K, out_l) | biases of layer l (every form) |
//!
//! with `l = 0, 1, 2, ...` consecutive; ELU follows every layer but the last.
//!
//! Adapters (one style; the layer it sits beside is given separately):
//!
//! | name | shape | form |
//! |---|---|---|
//! | `A`, `B`, `D` | (out, R), (in, R), (K, R) | CP: `W_res(p) = A diag(d(p)) B^T` |
//! | `W` | (K, out, in) | full |
//! | `w` | (K, n) | diagonal |
//! | `bias` | (K, out) | the adapter's bias `b_res` (optional, zero if absent) |
//!
//! `K` is the number of experts of the base gating (4 control points for
//! cubic gating), or 1 for an adapter that does not depend on the phase.
//! Arrays may be float32 or float64 (`.safetensors`: F32, F64, F16, BF16),
//! C order. Every value must be finite.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{anyhow, bail, Context, Result};
use ndarray::{Array1, Array2};
use std::collections::BTreeMap;
use std::path::Path;

use crate::io::tensors::NpArray;
use crate::net::{Adapter, CpLayer, DiagLayer, Net, NetLayer};
use crate::net::{ExpertLayer, GatingMode};

pub use crate::io::tensors::{
    parse_safetensors, read_arrays, read_safetensors, safetensors_bytes, write_arrays,
    write_safetensors,
};

fn matrix(a: &NpArray, name: &str) -> Result<Array2<f64>> {
    match crate::io::sizes::dims::<2>(&a.shape) {
        Some([r, c]) => Array2::from_shape_vec((r, c), a.data.clone())
            .map_err(|e| anyhow!("array {name} of shape {:?}: {e}", a.shape)),
        None => bail!(
            "array {name} has shape {:?}, expected 2 dimensions",
            a.shape
        ),
    }
}

fn vector(a: &NpArray, name: &str) -> Result<Array1<f64>> {
    match a.shape[..] {
        [_] => Ok(Array1::from(a.data.clone())),
        _ => bail!("{name} has shape {:?}, expected a vector", a.shape),
    }
}

fn get<'a>(arrays: &'a BTreeMap<String, NpArray>, name: &str) -> Result<&'a NpArray> {
    arrays
        .get(name)
        .ok_or_else(|| anyhow!("missing array {name}"))
}

/// `(K, out)` rows as vectors.
fn rows(m: &Array2<f64>) -> Vec<Array1<f64>> {
    m.rows().into_iter().map(|r| r.to_owned()).collect()
}

fn dense(w: &NpArray, name: &str) -> Result<Vec<Array2<f64>>> {
    let Some([k, r, c]) = crate::io::sizes::dims::<3>(&w.shape) else {
        bail!(
            "array {name} has shape {:?}, expected (K, out, in)",
            w.shape
        );
    };
    let per = crate::io::sizes::mul(r, c, name)?;
    if k == 0 || per == 0 || crate::io::sizes::element_count(&w.shape) != Some(w.data.len()) {
        bail!(
            "array {name} of shape {:?} is empty or does not hold its elements",
            w.shape
        );
    }
    w.data
        .chunks_exact(per)
        .map(|ws| Ok(Array2::from_shape_vec((r, c), ws.to_vec())?))
        .collect()
}

/// A CP layer from `A`, `B`, `D` and a `(K, out)` bias (zero when `None`).
fn cp_layer(
    a: &NpArray,
    b: &NpArray,
    d: &NpArray,
    bias: Option<&NpArray>,
    names: [&str; 4],
) -> Result<CpLayer> {
    let (a, b, d) = (
        matrix(a, names[0])?,
        matrix(b, names[1])?,
        matrix(d, names[2])?,
    );
    let rank = a.ncols();
    if b.ncols() != rank || d.ncols() != rank || rank == 0 {
        bail!(
            "{}/{}/{} ranks differ: {} / {} / {}",
            names[0],
            names[1],
            names[2],
            rank,
            b.ncols(),
            d.ncols()
        );
    }
    let (k, out) = (d.nrows(), a.nrows());
    let bias = match bias {
        Some(x) => {
            let m = matrix(x, names[3])?;
            if m.dim() != (k, out) {
                bail!(
                    "{} has shape {:?}, expected ({k}, {out})",
                    names[3],
                    m.dim()
                );
            }
            rows(&m)
        }
        None => vec![Array1::zeros(out); k],
    };
    Ok(CpLayer { a, b, d, bias })
}

/// Reads a whole network in the layout above.
pub fn read_cp_net(path: &Path, mode: GatingMode) -> Result<Net> {
    let arrays = read_arrays(path)?;
    net_from_arrays(&arrays, mode).with_context(|| path.display().to_string())
}

/// [`read_cp_net`] for arrays already read.
pub fn net_from_arrays(arrays: &BTreeMap<String, NpArray>, mode: GatingMode) -> Result<Net> {
    let v = |n: &str| vector(get(arrays, n)?, n);
    let (xmean, xstd, ymean, ystd) = (v("Xmean")?, v("Xstd")?, v("Ymean")?, v("Ystd")?);
    if let Some(i) = xstd.iter().chain(&ystd).position(|&s| s <= 0.0) {
        bail!("Xstd/Ystd entry {i} is not positive");
    }
    let mut layers = Vec::new();
    let mut width = xmean.len();
    for l in 0.. {
        let (an, bn, dn, wn, gn, biasn) = (
            format!("A{l}"),
            format!("B{l}"),
            format!("D{l}"),
            format!("W{l}"),
            format!("w{l}"),
            format!("b{l}"),
        );
        let layer = if let Some(w) = arrays.get(&wn) {
            let w = dense(w, &wn)?;
            let bias = matrix(get(arrays, &biasn)?, &biasn)?;
            NetLayer::Dense(ExpertLayer { w, b: rows(&bias) })
        } else if let Some(w) = arrays.get(&gn) {
            let w = rows(&matrix(w, &gn)?);
            let b = rows(&matrix(get(arrays, &biasn)?, &biasn)?);
            let n = w.first().map_or(0, Array1::len);
            if b.len() != w.len() || b.iter().any(|r| r.len() != n) {
                bail!("{biasn} must have shape ({}, {n}) like {gn}", w.len());
            }
            NetLayer::Diagonal(DiagLayer { w, b })
        } else if arrays.contains_key(&an) {
            NetLayer::Cp(cp_layer(
                get(arrays, &an)?,
                get(arrays, &bn)?,
                get(arrays, &dn)?,
                Some(get(arrays, &biasn)?),
                [&an, &bn, &dn, &biasn],
            )?)
        } else {
            break;
        };
        if layer.in_dim() != width {
            bail!(
                "layer {l} takes {} inputs, the previous layer gives {width}",
                layer.in_dim()
            );
        }
        width = layer.out_dim();
        layers.push(layer);
    }
    if layers.is_empty() {
        bail!("no layers (expected A0/B0/D0/b0 or W0/b0)");
    }
    if width != ymean.len() || xstd.len() != xmean.len() || ystd.len() != ymean.len() {
        bail!("output width {width} does not match Ymean/Ystd");
    }
    let k = layers[0].experts();
    if layers.iter().any(|l| l.experts() != k) {
        bail!("layers have different expert counts");
    }
    if mode == GatingMode::Cubic && k != 4 {
        bail!("cubic gating needs 4 control points, the file has {k}");
    }
    Ok(Net {
        mode,
        xmean,
        xstd,
        ymean,
        ystd,
        layers,
        wiring: crate::net::Wiring::Chain,
    })
}

/// Reads one adapter (layout above) for base layer `layer`.
pub fn read_adapter(path: &Path, layer: usize) -> Result<Adapter> {
    let arrays = read_arrays(path)?;
    adapter_from_arrays(&arrays, layer).with_context(|| path.display().to_string())
}

/// [`read_adapter`] for arrays already read.
pub fn adapter_from_arrays(arrays: &BTreeMap<String, NpArray>, layer: usize) -> Result<Adapter> {
    let bias = arrays.get("bias");
    let op = if let Some(a) = arrays.get("A") {
        NetLayer::Cp(cp_layer(
            a,
            get(arrays, "B")?,
            get(arrays, "D")?,
            bias,
            ["A", "B", "D", "bias"],
        )?)
    } else if let Some(w) = arrays.get("W") {
        let w = dense(w, "W")?;
        let (k, out) = (w.len(), w.first().map_or(0, |m| m.nrows()));
        let b = match bias {
            Some(b) => rows(&matrix(b, "bias")?),
            None => vec![Array1::zeros(out); k],
        };
        if b.len() != k || b.iter().any(|r| r.len() != out) {
            bail!("bias must have shape ({k}, {out})");
        }
        NetLayer::Dense(ExpertLayer { w, b })
    } else if let Some(w) = arrays.get("w") {
        let w = rows(&matrix(w, "w")?);
        let (k, n) = (w.len(), w.first().map_or(0, Array1::len));
        let b = match bias {
            Some(b) => rows(&matrix(b, "bias")?),
            None => vec![Array1::zeros(n); k],
        };
        if b.len() != k || b.iter().any(|r| r.len() != n) {
            bail!("bias must have shape ({k}, {n})");
        }
        NetLayer::Diagonal(DiagLayer { w, b })
    } else {
        bail!("no adapter weights: expected A/B/D (CP), W (full) or w (diagonal)");
    };
    Ok(Adapter { layer, op })
}

fn f32s(v: impl IntoIterator<Item = f64>) -> Vec<f32> {
    v.into_iter().map(|x| x as f32).collect()
}

type Arrays = Vec<(String, Vec<u64>, Vec<f32>)>;

fn layer_arrays(op: &NetLayer, suffix: &str, bias_name: &str, out: &mut Arrays) {
    let mat = |m: &Array2<f64>| {
        (
            vec![m.nrows() as u64, m.ncols() as u64],
            f32s(m.iter().copied()),
        )
    };
    let stack = |v: &[Array1<f64>]| {
        (
            vec![v.len() as u64, v.first().map_or(0, |r| r.len()) as u64],
            f32s(v.iter().flatten().copied()),
        )
    };
    // One matrix per expert, `(experts, rows, cols)`.
    let per_expert = |v: &[Array2<f64>]| {
        let (r, c) = v.first().map_or((0, 0), Array2::dim);
        (
            vec![v.len() as u64, r as u64, c as u64],
            f32s(v.iter().flatten().copied()),
        )
    };
    match op {
        NetLayer::Cp(l) => {
            for (n, m) in [("A", &l.a), ("B", &l.b), ("D", &l.d)] {
                let (s, d) = mat(m);
                out.push((format!("{n}{suffix}"), s, d));
            }
            let (s, d) = stack(&l.bias);
            out.push((bias_name.to_string(), s, d));
        }
        NetLayer::Dense(l) => {
            let (s, d) = per_expert(&l.w);
            out.push((format!("W{suffix}"), s, d));
            let (s, d) = stack(&l.b);
            out.push((bias_name.to_string(), s, d));
        }
        NetLayer::Diagonal(l) => {
            let (s, d) = stack(&l.w);
            out.push((format!("w{suffix}"), s, d));
            let (s, d) = stack(&l.b);
            out.push((bias_name.to_string(), s, d));
        }
        NetLayer::Rbf(l) => {
            let (s, d) = per_expert(&l.centres);
            out.push((format!("centres{suffix}"), s, d));
            let (s, d) = stack(&l.sigma);
            out.push((format!("sigma{suffix}"), s, d));
            let (s, d) = stack(&l.b);
            out.push((bias_name.to_string(), s, d));
        }
        NetLayer::Dec(l) => {
            let (s, d) = per_expert(&l.centres);
            out.push((format!("centres{suffix}"), s, d));
            let (s, d) = stack(&l.b);
            out.push((bias_name.to_string(), s, d));
        }
    }
}

/// Writes a network in the layout above (float32).
pub fn write_cp_net(net: &Net, path: &Path) -> Result<()> {
    crate::io::atomic::write_atomic(path, &cp_net_bytes(net)?)
}

/// The `.npz` bytes [`write_cp_net`] writes.
pub fn cp_net_bytes(net: &Net) -> Result<Vec<u8>> {
    let v = |a: &Array1<f64>| (vec![a.len() as u64], f32s(a.iter().copied()));
    let mut arrays: Arrays = Vec::new();
    for (n, a) in [
        ("Xmean", &net.xmean),
        ("Xstd", &net.xstd),
        ("Ymean", &net.ymean),
        ("Ystd", &net.ystd),
    ] {
        let (s, d) = v(a);
        arrays.push((n.to_string(), s, d));
    }
    for (l, layer) in net.layers.iter().enumerate() {
        layer_arrays(layer, &l.to_string(), &format!("b{l}"), &mut arrays);
    }
    let refs: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
        .iter()
        .map(|(n, s, d)| (n.as_str(), s.clone(), d.clone()))
        .collect();
    crate::io::tensors::npz_bytes(&refs)
}

/// Writes an adapter in the layout above (float32).
pub fn write_adapter(adapter: &Adapter, path: &Path) -> Result<()> {
    crate::io::atomic::write_atomic(path, &adapter_bytes(adapter)?)
}

/// The `.npz` bytes [`write_adapter`] writes.
pub fn adapter_bytes(adapter: &Adapter) -> Result<Vec<u8>> {
    let mut arrays: Arrays = Vec::new();
    layer_arrays(&adapter.op, "", "bias", &mut arrays);
    let refs: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
        .iter()
        .map(|(n, s, d)| (n.as_str(), s.clone(), d.clone()))
        .collect();
    crate::io::tensors::npz_bytes(&refs)
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::*;

    fn tiny_net() -> Net {
        let cp = |out: usize, inp: usize, r: usize| {
            NetLayer::Cp(CpLayer {
                a: Array2::from_shape_fn((out, r), |(i, j)| (i * r + j) as f64 * 0.125 - 0.5),
                b: Array2::from_shape_fn((inp, r), |(i, j)| (i + j) as f64 * 0.25 - 0.75),
                d: Array2::from_shape_fn((4, r), |(k, j)| (k + 2 * j) as f64 * 0.5),
                bias: (0..4)
                    .map(|k| Array1::from_elem(out, k as f64 * 0.5))
                    .collect(),
            })
        };
        Net {
            mode: GatingMode::Cubic,
            xmean: Array1::from(vec![0.5, -1.0, 2.0]),
            xstd: Array1::from(vec![1.0, 2.0, 0.25]),
            ymean: Array1::from(vec![3.0, 4.0]),
            ystd: Array1::from(vec![0.5, 8.0]),
            layers: vec![
                cp(5, 3, 2),
                NetLayer::Diagonal(DiagLayer {
                    w: (0..4)
                        .map(|k| Array1::from_shape_fn(5, |i| (k + i) as f64 * 0.25 - 0.5))
                        .collect(),
                    b: (0..4)
                        .map(|k| Array1::from_shape_fn(5, |i| (k * i) as f64 * 0.5))
                        .collect(),
                }),
                NetLayer::Dense(ExpertLayer {
                    w: (0..4)
                        .map(|k| {
                            Array2::from_shape_fn((5, 5), |(i, j)| (k + i * j) as f64 * 0.0625)
                        })
                        .collect(),
                    b: (0..4).map(|_| Array1::zeros(5)).collect(),
                }),
                cp(2, 5, 3),
            ],
            wiring: crate::net::Wiring::Chain,
        }
    }

    #[test]
    fn npz_round_trip_of_mixed_networks_and_adapters() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("cp.npz");
        let net = tiny_net();
        write_cp_net(&net, &p).unwrap();
        assert_eq!(read_cp_net(&p, GatingMode::Cubic).unwrap(), net);
        let ad = Adapter {
            layer: 1,
            op: net.layers[0].clone(),
        };
        let q = dir.path().join("ad.npz");
        write_adapter(&ad, &q).unwrap();
        assert_eq!(read_adapter(&q, 1).unwrap(), ad);
    }

    #[test]
    fn errors_name_the_array() {
        let mut arrays = BTreeMap::new();
        arrays.insert(
            "A".to_string(),
            NpArray {
                shape: vec![3, 2],
                data: vec![0.0; 6],
            },
        );
        let e = format!("{:#}", adapter_from_arrays(&arrays, 1).unwrap_err());
        assert!(e.contains("missing array B"), "{e}");
        arrays.insert(
            "B".to_string(),
            NpArray {
                shape: vec![4, 3],
                data: vec![0.0; 12],
            },
        );
        arrays.insert(
            "D".to_string(),
            NpArray {
                shape: vec![4, 2],
                data: vec![0.0; 8],
            },
        );
        let e = format!("{:#}", adapter_from_arrays(&arrays, 1).unwrap_err());
        assert!(e.contains("ranks differ"), "{e}");
    }
}
