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
use half::{bf16, f16};
use ndarray::{Array1, Array2};
use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;
use std::path::Path;

use crate::net::{Adapter, CpLayer, DiagLayer, Net, NetLayer};
use crate::net::{ExpertLayer, GatingMode};
use crate::npz::{read_npz, NpArray};

/// Reads every float array of a `.safetensors` file.
pub fn read_safetensors(path: &Path) -> Result<BTreeMap<String, NpArray>> {
    let bytes = crate::atomic::read_input(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    parse_safetensors(&bytes).with_context(|| format!("{}", path.display()))
}

/// Every float tensor of `.safetensors` bytes, as f64. The container (an
/// 8-byte header length, the JSON header, the data; offsets in bounds,
/// contiguous and not overlapping, sizes that fit) is checked by the
/// `safetensors` crate; here only the dtypes and the values.
pub fn parse_safetensors(bytes: &[u8]) -> Result<BTreeMap<String, NpArray>> {
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| anyhow!("not a valid safetensors file: {e}"))?;
    let mut out = BTreeMap::new();
    for (name, view) in st.tensors() {
        let (width, conv): (usize, fn(&[u8]) -> f64) = match view.dtype() {
            Dtype::F64 => (8, |b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8]))),
            Dtype::F32 => (4, |b| {
                f64::from(f32::from_le_bytes(b.try_into().unwrap_or([0; 4])))
            }),
            Dtype::F16 => (2, |b| {
                f16::from_le_bytes(b.try_into().unwrap_or([0; 2])).to_f64()
            }),
            Dtype::BF16 => (2, |b| {
                bf16::from_le_bytes(b.try_into().unwrap_or([0; 2])).to_f64()
            }),
            other => bail!("tensor {name} has dtype {other:?}, expected F64, F32, F16 or BF16"),
        };
        let values: Vec<f64> = view.data().chunks_exact(width).map(conv).collect();
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            bail!("tensor {name} has a non-finite value at index {k}");
        }
        let shape = view
            .shape()
            .iter()
            .map(|&d| u64::try_from(d))
            .collect::<Result<Vec<u64>, _>>()?;
        out.insert(
            name.clone(),
            NpArray::new(shape, values).with_context(|| format!("tensor {name}"))?,
        );
    }
    Ok(out)
}

/// Writes f32 arrays as a `.safetensors` file (the layout
/// `safetensors.torch.save_file` writes), atomically.
pub fn write_safetensors(path: &Path, arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<()> {
    crate::atomic::write_atomic(path, &safetensors_bytes(arrays)?)
}

/// f32 arrays as the bytes of a `.safetensors` file.
pub fn safetensors_bytes(arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<Vec<u8>> {
    let bytes: Vec<(String, Vec<u8>, Vec<usize>)> = arrays
        .iter()
        .map(|(name, shape, data)| {
            (
                name.to_string(),
                data.iter().flat_map(|v| v.to_le_bytes()).collect(),
                shape.iter().map(|&d| d as usize).collect(),
            )
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(name, data, shape)| {
            safetensors::tensor::TensorView::new(Dtype::F32, shape.clone(), data)
                .map(|v| (name.clone(), v))
                .map_err(|e| anyhow!("tensor {name}: {e}"))
        })
        .collect::<Result<Vec<_>>>()?;
    safetensors::serialize(views, None).map_err(|e| anyhow!("{e}"))
}

/// Writes `.npz` or `.safetensors` (by extension).
pub fn write_arrays(path: &Path, arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<()> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => write_safetensors(path, arrays),
        _ => crate::npz::write_npz(path, arrays),
    }
}

/// Reads `.npz` or `.safetensors` (by extension).
pub fn read_arrays(path: &Path) -> Result<BTreeMap<String, NpArray>> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => read_safetensors(path),
        _ => read_npz(path),
    }
}

fn matrix(a: &NpArray, name: &str) -> Result<Array2<f64>> {
    match crate::sizes::dims::<2>(&a.shape) {
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
    let Some([k, r, c]) = crate::sizes::dims::<3>(&w.shape) else {
        bail!(
            "array {name} has shape {:?}, expected (K, out, in)",
            w.shape
        );
    };
    let per = crate::sizes::mul(r, c, name)?;
    if k == 0 || per == 0 || crate::sizes::element_count(&w.shape) != Some(w.data.len()) {
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
    crate::npz::write_npz(path, &refs)
}

/// Writes an adapter in the layout above (float32).
pub fn write_adapter(adapter: &Adapter, path: &Path) -> Result<()> {
    let mut arrays: Arrays = Vec::new();
    layer_arrays(&adapter.op, "", "bias", &mut arrays);
    let refs: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
        .iter()
        .map(|(n, s, d)| (n.as_str(), s.clone(), d.clone()))
        .collect();
    crate::npz::write_npz(path, &refs)
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
    fn safetensors_are_read_with_every_float_dtype() {
        let mut header = serde_json::json!({
            "__metadata__": {"format": "pt"},
            "A": {"dtype": "F32", "shape": [2, 1], "data_offsets": [0, 8]},
            "D": {"dtype": "BF16", "shape": [1, 1], "data_offsets": [8, 10]},
            "h": {"dtype": "F16", "shape": [2], "data_offsets": [10, 14]},
            "x": {"dtype": "F64", "shape": [1], "data_offsets": [14, 22]},
        })
        .to_string()
        .into_bytes();
        while !header.len().is_multiple_of(8) {
            header.push(b' ');
        }
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend(&header);
        bytes.extend(1.5f32.to_le_bytes());
        bytes.extend((-2.0f32).to_le_bytes());
        bytes.extend(((0.75f32.to_bits() >> 16) as u16).to_le_bytes());
        bytes.extend(0x3C00u16.to_le_bytes()); // 1.0 in f16
        bytes.extend(0xC100u16.to_le_bytes()); // -2.5 in f16
        bytes.extend(0.1f64.to_le_bytes());
        let a = parse_safetensors(&bytes).unwrap();
        assert_eq!(a["A"].data, vec![1.5, -2.0]);
        assert_eq!(a["A"].shape, vec![2, 1]);
        assert_eq!(a["D"].data, vec![0.75]);
        assert_eq!(a["h"].data, vec![1.0, -2.5]);
        assert_eq!(a["x"].data, vec![0.1]);
        assert!(parse_safetensors(&bytes[..20]).is_err());
    }

    /// A safetensors file of the tensors `(name, shape, data_offsets)` over
    /// `data_len` bytes of F32 zeros.
    fn safetensors_bytes(tensors: &[(&str, Vec<u64>, [u64; 2])], data_len: usize) -> Vec<u8> {
        let mut map = serde_json::Map::new();
        for (n, shape, offs) in tensors {
            map.insert(
                n.to_string(),
                serde_json::json!({"dtype": "F32", "shape": shape, "data_offsets": offs}),
            );
        }
        let mut header = serde_json::Value::Object(map).to_string().into_bytes();
        while !header.len().is_multiple_of(8) {
            header.push(b' ');
        }
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend(&header);
        bytes.resize(bytes.len() + data_len, 0);
        bytes
    }

    #[test]
    fn malformed_safetensors_containers_are_refused() {
        let ok = safetensors_bytes(&[("a", vec![2], [0, 8]), ("b", vec![2], [8, 16])], 16);
        assert_eq!(parse_safetensors(&ok).unwrap().len(), 2);
        // Overlapping tensors (the format forbids them).
        let overlap = safetensors_bytes(&[("a", vec![2], [0, 8]), ("b", vec![2], [4, 12])], 16);
        // A shape whose element count overflows 64 bits.
        let huge = safetensors_bytes(&[("a", vec![1 << 32, 1 << 32, 16], [0, 8])], 8);
        // A shape that does not match its bytes, and offsets past the end.
        let short = safetensors_bytes(&[("a", vec![3], [0, 8])], 8);
        let past = safetensors_bytes(&[("a", vec![2], [0, 8])], 4);
        for (what, bytes) in [
            ("overlap", overlap),
            ("huge", huge),
            ("short", short),
            ("past", past),
        ] {
            let e = parse_safetensors(&bytes).unwrap_err().to_string();
            assert!(e.contains("not a valid safetensors file"), "{what}: {e}");
        }
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
