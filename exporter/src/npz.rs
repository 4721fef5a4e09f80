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
use npyz::WriterBuilder;
use std::collections::BTreeMap;
use std::io::{Cursor, Read, Write};
use std::path::Path;

use crate::net::{ExpertLayer, GatingMode, Net, NetLayer};

/// One array: shape and values (widened to f64).
#[derive(Clone, Debug, PartialEq)]
pub struct NpArray {
    /// Shape.
    pub shape: Vec<u64>,
    /// Values, C order.
    pub data: Vec<f64>,
}

impl NpArray {
    /// An array whose `data` holds exactly the element count of `shape`
    /// (checked: a count that overflows is an error, not an empty array).
    pub fn new(shape: Vec<u64>, data: Vec<f64>) -> Result<Self> {
        let n = crate::sizes::nonempty(&shape)?;
        if n != data.len() {
            bail!(
                "shape {shape:?} declares {n} elements, the data has {}",
                data.len()
            );
        }
        Ok(Self { shape, data })
    }
}

/// Reads every float array of an `.npz` file.
pub fn read_npz(path: &Path) -> Result<BTreeMap<String, NpArray>> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    crate::atomic::note_input(path);
    read_npz_from(std::io::BufReader::new(file), path)
}

/// Reads every float array of an in-memory `.npz`; `path` names it in errors.
pub fn read_npz_from(
    reader: impl Read + std::io::Seek,
    path: &Path,
) -> Result<BTreeMap<String, NpArray>> {
    let mut zip = zip::ZipArchive::new(reader)
        .with_context(|| format!("{} is not an .npz (zip) file", path.display()))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut entry = zip
            .by_index(i)
            .with_context(|| format!("{}: zip entry {i}", path.display()))?;
        let Some(name) = npyz::npz::array_name_from_file_name(entry.name()).map(str::to_owned)
        else {
            continue;
        };
        let what = || format!("{}: array {name}", path.display());
        let mut bytes = Vec::new();
        entry.read_to_end(&mut bytes).with_context(what)?;
        let (header, data) = parse_npy(&bytes).with_context(what)?;
        let shape = header.shape().to_vec();
        let data: Vec<f64> = match header.dtype() {
            npyz::DType::Plain(t)
                if t.type_char() == npyz::TypeChar::Float && t.size_field() == 4 =>
            {
                npyz::NpyFile::with_header(header, data)
                    .into_vec::<f32>()
                    .with_context(what)?
                    .into_iter()
                    .map(f64::from)
                    .collect()
            }
            npyz::DType::Plain(t)
                if t.type_char() == npyz::TypeChar::Float && t.size_field() == 8 =>
            {
                npyz::NpyFile::with_header(header, data)
                    .into_vec::<f64>()
                    .with_context(what)?
            }
            other => bail!(
                "{}: array {name} has dtype {}, expected float32 or float64",
                path.display(),
                other.descr()
            ),
        };
        if let Some(k) = data.iter().position(|v| !v.is_finite()) {
            bail!(
                "{}: array {name} has a non-finite value at index {k}",
                path.display()
            );
        }
        let array = NpArray::new(shape, data).with_context(what)?;
        out.insert(name, array);
    }
    Ok(out)
}

/// Splits one `.npy` held in memory into its header and its data bytes,
/// after checking what the header declares against what is there: C
/// order, an element count and byte count that fit (checked, never
/// wrapped), and exactly that many data bytes (fewer is a truncated file,
/// more a damaged one). Errors do not name the file; callers add it.
pub fn parse_npy(bytes: &[u8]) -> Result<(npyz::NpyHeader, &[u8])> {
    check_npy_header(bytes)?;
    let mut rest = bytes;
    let header = npyz::NpyHeader::from_reader(&mut rest)
        .map_err(|e| anyhow!("not a .npy array (bad header: {e})"))?;
    if header.order() != npyz::Order::C {
        bail!("Fortran-ordered; save it in C order");
    }
    let dtype = header.dtype();
    let width = dtype
        .num_bytes()
        .ok_or_else(|| anyhow!("dtype {} is too large", dtype.descr()))?;
    crate::sizes::nonempty(header.shape())?;
    let need = crate::sizes::bytes_of(header.shape(), width)?;
    match rest.len().cmp(&need) {
        std::cmp::Ordering::Less => bail!(
            "truncated: shape {:?} of {} needs {need} data bytes, the file has {}",
            header.shape(),
            dtype.descr(),
            rest.len()
        ),
        std::cmp::Ordering::Greater => bail!(
            "{} bytes after the data of shape {:?} of {} ({need} bytes)",
            rest.len().saturating_sub(need),
            header.shape(),
            dtype.descr()
        ),
        std::cmp::Ordering::Equal => Ok((header, rest)),
    }
}

/// Deepest bracket nesting accepted in an `.npy` header. A plain array's
/// header (`{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }`)
/// nests 2 deep; the header parser npyz uses (py_literal) takes time
/// exponential in the depth (found by the `weights` fuzz target: a 228-byte
/// `.npy` whose header opened 60 `{` did not parse in minutes).
pub const MAX_NPY_HEADER_DEPTH: usize = 4;

/// Refuses an `.npy` whose header nests brackets deeper than
/// [`MAX_NPY_HEADER_DEPTH`], before npyz parses it. Bytes that are not an
/// `.npy` pass (npyz refuses them).
pub fn check_npy_header(bytes: &[u8]) -> Result<()> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Ok(());
    }
    let (len, start): (usize, usize) = if bytes[6] == 1 {
        (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10)
    } else if bytes.len() >= 12 {
        let n = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        (usize::try_from(n).unwrap_or(usize::MAX), 12)
    } else {
        return Ok(());
    };
    let header = &bytes[start..start.saturating_add(len).min(bytes.len())];
    let (mut depth, mut deepest) = (0usize, 0usize);
    for &b in header {
        match b {
            b'(' | b'[' | b'{' => {
                depth = depth.saturating_add(1);
                deepest = deepest.max(depth);
            }
            b')' | b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    if deepest > MAX_NPY_HEADER_DEPTH {
        bail!(
            "the .npy header nests brackets {deepest} deep (at most {MAX_NPY_HEADER_DEPTH} accepted)"
        );
    }
    check_header_numbers(header)
}

/// Refuses a header whose integers could overflow npyz's own size
/// arithmetic, which multiplies the dimensions (and, for the strides, the
/// trailing ones) unchecked: a panic under debug assertions and a wrapped,
/// small count in release (found by the `weights` fuzz target, F2).
/// Conservative on purpose: the product of every nonzero integer in the
/// header, whatever key it sits under or however the key is spelt, must
/// fit in 64 bits, and every integer must be written in plain decimal
/// (NumPy writes nothing else; a literal npyz would read differently, such
/// as `0x10` or `1_0`, is refused rather than guessed at).
fn check_header_numbers(header: &[u8]) -> Result<()> {
    let word = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let mut product: u64 = 1;
    let mut i = 0usize;
    while let Some(&b) = header.get(i) {
        let after_word = i
            .checked_sub(1)
            .and_then(|p| header.get(p))
            .is_some_and(|&p| word(p));
        if !b.is_ascii_digit() || after_word {
            i = i.saturating_add(1);
            continue;
        }
        let len = header[i..]
            .iter()
            .take_while(|d| d.is_ascii_digit())
            .count();
        let end = i.saturating_add(len);
        let digits = &header[i..end];
        // Python 2's NumPy wrote long dimensions as `3L`.
        let next = match header.get(end) {
            Some(b'L') => end.checked_add(1).and_then(|e| header.get(e)),
            other => other,
        };
        if next.is_some_and(|&n| word(n)) {
            let token = header[i..].iter().take_while(|&&t| word(t)).count();
            bail!(
                "the .npy header holds a number that is not a plain decimal integer: {}",
                String::from_utf8_lossy(&header[i..i.saturating_add(token)])
            );
        }
        let value = std::str::from_utf8(digits)
            .ok()
            .and_then(|d| d.parse::<u64>().ok());
        product = match value {
            Some(0) => product,
            Some(v) => product.checked_mul(v).ok_or_else(overflow)?,
            None => return Err(overflow()),
        };
        i = end;
    }
    Ok(())
}

fn overflow() -> anyhow::Error {
    anyhow!("the .npy header declares sizes whose product overflows 64 bits")
}

/// Writes float32 arrays to an `.npz` (stored, uncompressed), atomically.
pub fn write_npz(path: &Path, arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<()> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::FileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .last_modified_time(zip::DateTime::default());
    for (name, shape, data) in arrays {
        zip.start_file(npyz::npz::file_name_from_array_name(name), options)?;
        let mut bytes = Vec::new();
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(&mut bytes)
            .begin_nd()?;
        w.extend(data.iter().copied())?;
        w.finish()?;
        zip.write_all(&bytes)?;
    }
    let bytes = zip.finish()?.into_inner();
    crate::atomic::write_atomic(path, &bytes)
}

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
        let Some([k, rows, cols]) = crate::sizes::dims::<3>(&w.shape) else {
            bail!(
                "{}: array {wn} has shape {:?}, expected (K, rows, cols)",
                path.display(),
                w.shape
            );
        };
        let per = crate::sizes::mul(rows, cols, &wn).with_context(|| path.display().to_string())?;
        if crate::sizes::dims::<2>(&b.shape) != Some([k, rows])
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
        if crate::sizes::element_count(&w.shape) != Some(w.data.len())
            || crate::sizes::element_count(&b.shape) != Some(b.data.len())
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
    /// A version-1 `.npy` with the header dict `dict` and 8 data bytes.
    fn npy_with_header(dict: &str) -> Vec<u8> {
        let mut h = dict.to_owned();
        while !(10 + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b.extend([0u8; 8]);
        b
    }

    /// Found by the `weights` fuzz target (`fuzz/README.md`): an `.npy`
    /// header that nests 14 `{` deep made npyz's header parser run for
    /// minutes (exponential in the depth); it is refused at once.
    #[test]
    fn deeply_nested_npy_headers_are_refused_at_once() {
        let npy = |nest: usize| {
            npy_with_header(&format!(
                "{{'descr': '<f4', 'fortran_order': {} False, 'shape': (2,), }}",
                "{".repeat(nest)
            ))
        };
        let t = std::time::Instant::now();
        let e = check_npy_header(&npy(14)).unwrap_err().to_string();
        assert!(e.contains("nests brackets 16 deep"), "{e}");
        // Inside an .npz too.
        let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
        zip.start_file("W0.npy", zip::write::FileOptions::default())
            .unwrap();
        zip.write_all(&npy(14)).unwrap();
        let bytes = zip.finish().unwrap().into_inner();
        let e = read_npz_from(Cursor::new(bytes), Path::new("x.npz")).unwrap_err();
        assert!(format!("{e:#}").contains("nests brackets"), "{e:#}");
        assert!(t.elapsed().as_secs() < 5);
        // Plain headers pass.
        check_npy_header(&npy(0)).unwrap();
    }

    /// F2 of the `weights` fuzz target (`fuzz/README.md`): npyz multiplies
    /// the declared dimensions unchecked, so this header panicked inside
    /// `NpyHeader::from_reader` under debug assertions (and wrapped in
    /// release). It is refused before npyz sees it, whichever way it is
    /// spelt.
    #[test]
    fn shapes_whose_product_overflows_are_refused_before_npyz() {
        let npy = |shape: &str| {
            npy_with_header(&format!(
                "{{'descr': '<f4', 'fortran_order': False, {shape}, }}"
            ))
        };
        for shape in [
            "'shape': (4294967296, 4294967296, 16)",
            "\"shape\": (4294967296, 4294967296, 16)",
            "'shape': (0, 4294967296, 4294967296)",
            "'shape': (99999999999999999999999,)",
            "'shape': (4294967296L, 4294967296L, 16L)",
        ] {
            let e = parse_npy(&npy(shape)).err().expect("refused").to_string();
            assert!(e.contains("overflows 64 bits"), "{shape}: {e}");
        }
        for shape in [
            "'shape': (0x10, 2)",
            "'shape': (1_0, 2)",
            "'shape': (2, 1e3)",
        ] {
            let e = parse_npy(&npy(shape)).err().expect("refused").to_string();
            assert!(e.contains("not a plain decimal"), "{shape}: {e}");
        }
        // A plain header with its descr's digits passes the check.
        check_npy_header(&npy("'shape': (2,)")).unwrap();
        check_npy_header(&npy("'shape': (3L, 4L)")).unwrap();
    }

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
