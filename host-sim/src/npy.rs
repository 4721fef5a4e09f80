//! `.npy` reading and writing for the command-line contract (float32
//! matrices and vectors, int16 golden outputs). Writes go through a
//! temporary file and a rename, so a failed run leaves nothing behind.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{bail, Context, Result};
use npyz::WriterBuilder;
use std::path::Path;

/// A row-major matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct Matrix<T> {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// `rows * cols` values.
    pub data: Vec<T>,
}

impl<T: Copy> Matrix<T> {
    /// Row `i`.
    pub fn row(&self, i: usize) -> &[T] {
        self.iter_rows().nth(i).unwrap_or(&[])
    }

    /// Iterator over rows.
    pub fn iter_rows(&self) -> impl Iterator<Item = &[T]> {
        self.data.chunks_exact(self.cols.max(1)).take(self.rows)
    }
}

/// Reads an `.npy` array of `T` (every header check of
/// [`exporter::npz::parse_npy`]); returns its shape and data.
pub fn read_any<T: npyz::Deserialize>(path: &Path) -> Result<(Vec<u64>, Vec<T>)> {
    let bytes = exporter::atomic::read_input(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    let what = || path.display().to_string();
    let (header, data) = exporter::npz::parse_npy(&bytes).with_context(what)?;
    let shape = header.shape().to_vec();
    let descr = header.dtype().descr();
    let data = npyz::NpyFile::with_header(header, data)
        .into_vec::<T>()
        .with_context(|| format!("{}: wrong element type {descr}", path.display()))?;
    Ok((shape, data))
}

/// Reads a 2-D matrix of `T`; with `cols`, its width must be that. The
/// reader ([`exporter::npz::parse_npy`]) has checked that the data holds
/// exactly `rows * cols` elements.
fn read_matrix<T: npyz::Deserialize>(
    path: &Path,
    cols: Option<usize>,
    dtype: &str,
) -> Result<Matrix<T>> {
    let (shape, data) = read_any::<T>(path)?;
    match exporter::sizes::dims::<2>(&shape) {
        Some([r, c]) if cols.is_none_or(|want| want == c) => Ok(Matrix {
            rows: r,
            cols: c,
            data,
        }),
        _ => {
            let width = cols.map_or("M".to_string(), |c| c.to_string());
            bail!(
                "{}: shape {:?}, expected (N, {width}) {dtype}",
                path.display(),
                shape
            )
        }
    }
}

/// Reads an `(N, cols)` float32 matrix.
pub fn read_matrix_f32(path: &Path, cols: usize) -> Result<Matrix<f32>> {
    read_matrix(path, Some(cols), "float32")
}

/// Reads an `(N, M)` float32 matrix of any width.
pub fn read_matrix_f32_any(path: &Path) -> Result<Matrix<f32>> {
    read_matrix(path, None, "float32")
}

/// Reads an `(N, M)` int16 matrix.
pub fn read_matrix_i16(path: &Path) -> Result<Matrix<i16>> {
    read_matrix(path, None, "int16")
}

/// Reads a float32 array of any shape: (shape, values in C order).
pub fn read_array_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
    let (shape, data) = read_any::<f32>(path)?;
    Ok((shape.iter().map(|&d| d as usize).collect(), data))
}

/// Reads an `(N,)` float32 vector.
pub fn read_vector_f32(path: &Path) -> Result<Vec<f32>> {
    let (shape, data) = read_any::<f32>(path)?;
    match shape[..] {
        [_] => Ok(data),
        _ => bail!(
            "{}: shape {:?}, expected (N,) float32",
            path.display(),
            shape
        ),
    }
}

fn write_npy<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    path: &Path,
    shape: &[u64],
    data: &[T],
) -> Result<()> {
    write_atomic(path, &npy_bytes(shape, data)?)
}

/// The `.npy` bytes of an array of `shape`.
pub(crate) fn npy_bytes<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    shape: &[u64],
    data: &[T],
) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    {
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(&mut bytes)
            .begin_nd()?;
        w.extend(data.iter().copied())?;
        w.finish()?;
    }
    Ok(bytes)
}

/// The `.npy` bytes of a vector ([`write_vector`] writes them).
pub fn vector_bytes<T: npyz::Serialize + npyz::AutoSerialize + Copy>(v: &[T]) -> Result<Vec<u8>> {
    npy_bytes(&[v.len() as u64], v)
}

/// The `.npy` bytes of a matrix ([`write_matrix`] writes them).
pub fn matrix_bytes<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    m: &Matrix<T>,
) -> Result<Vec<u8>> {
    npy_bytes(&[m.rows as u64, m.cols as u64], &m.data)
}

/// Writes a matrix as `.npy`.
pub fn write_matrix<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    path: &Path,
    m: &Matrix<T>,
) -> Result<()> {
    write_npy(path, &[m.rows as u64, m.cols as u64], &m.data)
}

/// Writes a vector as `.npy`.
pub fn write_vector<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    path: &Path,
    v: &[T],
) -> Result<()> {
    write_npy(path, &[v.len() as u64], v)
}

/// Writes `bytes` to a temporary file beside `path`, then renames it.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    exporter::atomic::write_atomic(path, bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Found by the `weights` fuzz target (`fuzz/README.md`): a 228-byte
    /// `.npy` whose header nests `{` deep kept npyz's header parser busy
    /// for minutes; host-sim's readers refuse it at once.
    #[test]
    fn deeply_nested_npy_headers_are_refused_at_once() {
        let mut h = format!(
            "{{'descr': '<f4', 'fortran_order': {} False, 'shape': (2, 1), }}",
            "{".repeat(14)
        );
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b.extend([0u8; 8]);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("nested.npy");
        std::fs::write(&p, &b).unwrap();
        let t = std::time::Instant::now();
        let e = read_matrix_f32_any(&p).unwrap_err();
        assert!(format!("{e:#}").contains("nests brackets 16 deep"), "{e:#}");
        assert!(read_vector_f32(&p).is_err());
        assert!(crate::target::frames::read_npy::<f32>(&p).is_err());
        assert!(t.elapsed().as_secs() < 5);
    }
}
