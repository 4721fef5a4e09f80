//! NumPy `.npz` archives: generic array I/O and the PFNN-shaped layout
//! phasegate uses for float models that are not in the demo's directory
//! format (its own default model, models trained elsewhere).
//!
//! Layout (names as `numpy.savez(path, Xmean=..., W0=..., ...)` writes them):
//!
//! | array | shape | meaning |
//! |---|---|---|
//! | `Xmean`, `Xstd` | (in,) | input normalisation |
//! | `Ymean`, `Ystd` | (out,) | output de-normalisation |
//! | `W0`, `W1`, `W2` | (K, rows, cols) | expert weights (control points for cubic) |
//! | `b0`, `b1`, `b2` | (K, rows) | expert biases |
//!
//! float32 or float64; the gating (and so what the K experts mean) is given
//! by the caller.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{anyhow, bail, Context, Result};
use ndarray::{Array1, Array2};
use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::Path;

use crate::net::{ExpertLayer, GatingMode, Net, NetLayer};

pub use crate::io::tensors::{
    check_npy_header, npz_bytes, parse_npy, read_npz, read_npz_from, write_npz, NpArray,
    MAX_NPY_HEADER_DEPTH,
};

fn take<'a>(arrays: &'a BTreeMap<String, NpArray>, name: &str, path: &Path) -> Result<&'a NpArray> {
    arrays
        .get(name)
        .ok_or_else(|| anyhow!("{}: missing array {name}", path.display()))
}

fn vector(a: &NpArray, name: &str) -> Result<Array1<f64>> {
    match a.shape[..] {
        [_] => Ok(Array1::from(a.data.clone())),
        _ => bail!("array {name} has shape {:?}, expected a vector", a.shape),
    }
}

/// Reads a PFNN-shaped float network from the layout above.
pub fn pfnn_from_npz(path: &Path, mode: GatingMode) -> Result<Net> {
    pfnn_from_arrays(&read_npz(path)?, path, mode)
}

/// [`pfnn_from_npz`] for an `.npz` already in memory.
pub fn pfnn_from_npz_bytes(bytes: &[u8], name: &Path, mode: GatingMode) -> Result<Net> {
    pfnn_from_arrays(&read_npz_from(Cursor::new(bytes), name)?, name, mode)
}

fn pfnn_from_arrays(
    arrays: &BTreeMap<String, NpArray>,
    path: &Path,
    mode: GatingMode,
) -> Result<Net> {
    let v = |n: &str| -> Result<Array1<f64>> {
        vector(take(arrays, n, path)?, n).with_context(|| path.display().to_string())
    };
    let (xmean, xstd, ymean, ystd) = (v("Xmean")?, v("Xstd")?, v("Ymean")?, v("Ystd")?);
    for (name, std) in [("Xstd", &xstd), ("Ystd", &ystd)] {
        if let Some(i) = std.iter().position(|&s| s <= 0.0) {
            bail!(
                "{}: array {name}: entry {i} is not positive",
                path.display()
            );
        }
    }
    let mut layers = Vec::new();
    let mut width = xmean.len();
    for l in 0..3 {
        let (wn, bn) = (format!("W{l}"), format!("b{l}"));
        let (w, b) = (take(arrays, &wn, path)?, take(arrays, &bn, path)?);
        let Some([k, rows, cols]) = crate::io::sizes::dims::<3>(&w.shape) else {
            bail!(
                "{}: array {wn} has shape {:?}, expected (K, rows, cols)",
                path.display(),
                w.shape
            );
        };
        let per =
            crate::io::sizes::mul(rows, cols, &wn).with_context(|| path.display().to_string())?;
        if crate::io::sizes::dims::<2>(&b.shape) != Some([k, rows])
            || cols != width
            || k == 0
            || per == 0
        {
            bail!(
                "{}: arrays {wn} {:?} / {bn} {:?} do not fit a layer with {width} inputs",
                path.display(),
                w.shape,
                b.shape
            );
        }
        if crate::io::sizes::element_count(&w.shape) != Some(w.data.len())
            || crate::io::sizes::element_count(&b.shape) != Some(b.data.len())
        {
            bail!(
                "{}: arrays {wn} / {bn} do not hold their shapes' elements",
                path.display()
            );
        }
        let mut layer = ExpertLayer {
            w: Vec::new(),
            b: Vec::new(),
        };
        for (ws, bs) in w.data.chunks_exact(per).zip(b.data.chunks_exact(rows)) {
            layer
                .w
                .push(Array2::from_shape_vec((rows, cols), ws.to_vec())?);
            layer.b.push(Array1::from(bs.to_vec()));
        }
        layers.push(layer);
        width = rows;
    }
    if width != ymean.len() || xstd.len() != xmean.len() || ystd.len() != ymean.len() {
        bail!(
            "{}: output width {width} does not match Ymean/Ystd",
            path.display()
        );
    }
    let layers: [ExpertLayer; 3] = layers
        .try_into()
        .map_err(|_| anyhow!("three layers expected"))?;
    if layers.iter().any(|l| l.experts() != layers[0].experts()) {
        bail!("{}: layers have different expert counts", path.display());
    }
    if mode == GatingMode::Cubic && layers[0].experts() != 4 {
        bail!(
            "{}: cubic gating needs 4 control points, the file has {}",
            path.display(),
            layers[0].experts()
        );
    }
    Ok(Net {
        mode,
        xmean,
        xstd,
        ymean,
        ystd,
        layers: layers.into_iter().map(NetLayer::Dense).collect(),
        wiring: crate::net::Wiring::Chain,
    })
}

/// Writes a float network in the layout above (float32).
pub fn pfnn_to_npz(net: &Net, path: &Path) -> Result<()> {
    let f = |a: &Array1<f64>| a.iter().map(|&v| v as f32).collect::<Vec<f32>>();
    let mut arrays = vec![
        ("Xmean", vec![net.xmean.len() as u64], f(&net.xmean)),
        ("Xstd", vec![net.xstd.len() as u64], f(&net.xstd)),
        ("Ymean", vec![net.ymean.len() as u64], f(&net.ymean)),
        ("Ystd", vec![net.ystd.len() as u64], f(&net.ystd)),
    ];
    const W: [&str; 3] = ["W0", "W1", "W2"];
    const B: [&str; 3] = ["b0", "b1", "b2"];
    if net.layers.len() != 3 {
        bail!(
            "the PFNN .npz layout holds three layers, the network has {}",
            net.layers.len()
        );
    }
    for (l, layer) in net.layers.iter().enumerate() {
        let layer = layer.as_dense().ok_or_else(|| {
            anyhow!("layer {l} is not dense: the PFNN .npz layout holds dense layers")
        })?;
        let (rows, cols) = layer.dim();
        let k = layer.experts() as u64;
        let w: Vec<f32> = layer
            .w
            .iter()
            .flat_map(|m| m.iter().map(|&v| v as f32).collect::<Vec<_>>())
            .collect();
        let b: Vec<f32> = layer.b.iter().flat_map(f).collect();
        arrays.push((W[l], vec![k, rows as u64, cols as u64], w));
        arrays.push((B[l], vec![k, rows as u64], b));
    }
    write_npz(path, &arrays)
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {

    use super::*;

    fn tiny() -> Net {
        let layer = |r: usize, c: usize| ExpertLayer {
            w: (0..4)
                .map(|k| {
                    Array2::from_shape_fn((r, c), |(i, j)| (k * 7 + i * 3 + j) as f64 * 0.25 - 1.0)
                })
                .collect(),
            b: (0..4)
                .map(|k| Array1::from_shape_fn(r, |i| (k + i) as f64 * 0.5))
                .collect(),
        };
        Net {
            mode: GatingMode::Cubic,
            xmean: Array1::from(vec![0.5, -1.0, 2.0]),
            xstd: Array1::from(vec![1.0, 2.0, 0.25]),
            ymean: Array1::from(vec![3.0, 4.0]),
            ystd: Array1::from(vec![0.5, 8.0]),
            layers: vec![layer(5, 3), layer(5, 5), layer(2, 5)]
                .into_iter()
                .map(NetLayer::Dense)
                .collect(),
            wiring: crate::net::Wiring::Chain,
        }
    }

    #[test]
    fn npz_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.npz");
        let net = tiny();
        pfnn_to_npz(&net, &p).unwrap();
        let back = pfnn_from_npz(&p, GatingMode::Cubic).unwrap();
        assert_eq!(back, net);
        assert!(pfnn_from_npz(&p, GatingMode::Cubic).is_ok());
    }

    #[test]
    fn npz_errors_name_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.npz");
        write_npz(&p, &[("Xmean", vec![2], vec![0.0, 1.0])]).unwrap();
        let e = format!("{:#}", pfnn_from_npz(&p, GatingMode::Cubic).unwrap_err());
        assert!(e.contains("missing array Xstd"), "{e}");
        write_npz(&p, &[("Xmean", vec![2], vec![0.0, f32::NAN])]).unwrap();
        let e = format!("{:#}", read_npz(&p).unwrap_err());
        assert!(e.contains("non-finite"), "{e}");
        std::fs::write(&p, b"not a zip").unwrap();
        assert!(read_npz(&p).is_err());
    }
}
