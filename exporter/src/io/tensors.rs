//! Arrays by name, in the two container formats trained weights come in:
//! NumPy `.npz` (float32/float64 `.npy` members) and `.safetensors` (F32,
//! F64, F16, BF16). Every value is widened to f64 and must be finite; sizes
//! from the file's headers are checked before anything is allocated. This
//! layer knows nothing of networks: the importers give the names meaning.

#![deny(clippy::arithmetic_side_effects)]

use crate::io::sizes::element_count;
use anyhow::{anyhow, bail, Context, Result};
use half::{bf16, f16};
use npyz::WriterBuilder;
use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;
use std::io::{Cursor, Read, Write};
use std::path::Path;

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
        let n = crate::io::sizes::nonempty(&shape)?;
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
    crate::io::atomic::note_input(path);
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
    crate::io::sizes::nonempty(header.shape())?;
    let need = crate::io::sizes::bytes_of(header.shape(), width)?;
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
    crate::io::atomic::write_atomic(path, &npz_bytes(arrays)?)
}

/// The bytes of the `.npz` [`write_npz`] writes, for a command that writes
/// it together with other files ([`crate::io::atomic::write_together`]).
pub fn npz_bytes(arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<Vec<u8>> {
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
    Ok(zip.finish()?.into_inner())
}

/// Reads every float array of a `.safetensors` file.
pub fn read_safetensors(path: &Path) -> Result<BTreeMap<String, NpArray>> {
    let bytes = crate::io::atomic::read_input(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    parse_safetensors(&bytes).with_context(|| format!("{}", path.display()))
}

/// Every float tensor of `.safetensors` bytes, as f64. The container (an
/// 8-byte header length, the JSON header, the data; offsets in bounds,
/// contiguous and not overlapping, sizes that fit) is checked by the
/// `safetensors` crate; here only the dtypes and the values.
pub fn parse_safetensors(bytes: &[u8]) -> Result<BTreeMap<String, NpArray>> {
    let st = SafeTensors::deserialize(bytes).map_err(|e| {
        let why = safetensors_diagnosis(bytes).unwrap_or_else(|| e.to_string());
        anyhow!("not a valid safetensors file: {why}")
    })?;
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

/// Bits per element of a `.safetensors` dtype name, as the format defines
/// them (`None`: a name the format does not have).
fn dtype_bits(dtype: &str) -> Option<usize> {
    Some(match dtype {
        "F64" | "I64" | "U64" | "C64" => 64,
        "F32" | "I32" | "U32" => 32,
        "F16" | "BF16" | "I16" | "U16" => 16,
        "F8_E5M2" | "F8_E4M3" | "F8_E8M0" | "I8" | "U8" | "BOOL" => 8,
        "F6_E2M3" | "F6_E3M2" => 6,
        "F4" => 4,
        _ => return None,
    })
}

/// Why the `safetensors` library refused `bytes`, naming the tensor: its
/// own errors for a shape whose size overflows, a shape that does not fit
/// its offsets or data that does not end where the file does name none.
/// The checks are the library's (tensors in offset order, each starting
/// where the one before ended, holding exactly its shape's bytes, the last
/// ending at the end of the file); `None` if none fails here (the library's
/// message is then used as it is).
fn safetensors_diagnosis(bytes: &[u8]) -> Option<String> {
    let len = u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?);
    let end = 8usize.checked_add(usize::try_from(len).ok()?)?;
    let header: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(bytes.get(8..end)?).ok()?;
    let data_len = bytes.len().saturating_sub(end);
    let mut tensors: Vec<(&str, &serde_json::Value, [u64; 2])> = header
        .iter()
        .filter(|(name, _)| *name != "__metadata__")
        .filter_map(|(name, t)| {
            let offs = t.get("data_offsets")?.as_array()?;
            Some((
                name.as_str(),
                t,
                [offs.first()?.as_u64()?, offs.get(1)?.as_u64()?],
            ))
        })
        .collect();
    tensors.sort_by_key(|(_, _, [s, e])| (*s, *e));
    let mut at = 0u64;
    let mut previous: Option<&str> = None;
    for (name, t, [s, e]) in &tensors {
        if *s != at || e < s {
            let after = previous.map_or("the start of the data".to_string(), |p| {
                format!("the end of tensor {p}")
            });
            return Some(format!(
                "tensor {name}: data_offsets [{s}, {e}] do not start at {after} ({at})"
            ));
        }
        at = *e;
        previous = Some(name);
        let dtype = t.get("dtype")?.as_str()?;
        let shape: Vec<u64> = t
            .get("shape")?
            .as_array()?
            .iter()
            .map(serde_json::Value::as_u64)
            .collect::<Option<_>>()?;
        let bits = element_count(&shape).and_then(|n| n.checked_mul(dtype_bits(dtype)?));
        let Some(bits) = bits else {
            return Some(format!(
                "tensor {name}: shape {shape:?} of {dtype} declares more bytes than fit in memory"
            ));
        };
        let need = bits.div_ceil(8);
        let have = e.saturating_sub(*s);
        if u64::try_from(need).ok() != Some(have) {
            return Some(format!(
                "tensor {name}: data_offsets [{s}, {e}] hold {have} bytes, but shape {shape:?} \
                 of {dtype} needs {need}"
            ));
        }
    }
    if u64::try_from(data_len).ok() != Some(at) {
        let last = previous.map_or(String::new(), |p| format!(" (tensor {p})"));
        return Some(format!(
            "the tensors' data ends at byte {at}{last}, but the file has {data_len} data bytes"
        ));
    }
    None
}

/// Writes f32 arrays as a `.safetensors` file (the layout
/// `safetensors.torch.save_file` writes), atomically.
pub fn write_safetensors(path: &Path, arrays: &[(&str, Vec<u64>, Vec<f32>)]) -> Result<()> {
    crate::io::atomic::write_atomic(path, &safetensors_bytes(arrays)?)
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
        _ => write_npz(path, arrays),
    }
}

/// Reads `.npz` or `.safetensors` (by extension).
pub fn read_arrays(path: &Path) -> Result<BTreeMap<String, NpArray>> {
    match path.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => read_safetensors(path),
        _ => read_npz(path),
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::*;

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
        for (bytes, says) in [
            (
                overlap,
                "tensor b: data_offsets [4, 12] do not start at the end of tensor a (8)",
            ),
            (
                huge,
                "tensor a: shape [4294967296, 4294967296, 16] of F32 declares more bytes \
                 than fit in memory",
            ),
            (
                short,
                "tensor a: data_offsets [0, 8] hold 8 bytes, but shape [3] of F32 needs 12",
            ),
            (
                past,
                "the tensors' data ends at byte 8 (tensor a), but the file has 4 data bytes",
            ),
        ] {
            let e = parse_safetensors(&bytes).unwrap_err().to_string();
            assert_eq!(e, format!("not a valid safetensors file: {says}"));
        }
    }
}
