//! Reading and writing the PFNN demo's weight directory.
//!
//! The format is the one the public PFNN demo loads: one headerless file of
//! little-endian `f32` per tensor, matrices row-major (`out x in`), one file
//! per phase table:
//!
//! | file | elements |
//! |---|---|
//! | `Xmean.bin`, `Xstd.bin` | input |
//! | `Ymean.bin`, `Ystd.bin` | output |
//! | `W0_NNN.bin` / `W1_NNN.bin` / `W2_NNN.bin` | hidden x input / hidden x hidden / output x hidden |
//! | `b0_NNN.bin` / `b1_NNN.bin` / `b2_NNN.bin` | hidden / hidden / output |
//!
//! Because nothing in the files states their shape, every file is checked
//! against the byte size the expected dimensions imply before it is parsed,
//! and every value is checked to be finite: a truncated copy or a diverged
//! training run is reported by file name instead of surfacing later as a
//! garbage animation.

#![deny(clippy::arithmetic_side_effects)]

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use ndarray::{Array1, Array2};

use crate::error::ImportError;

/// Input width of the published PFNN (trajectory, gaits, joints, terrain).
pub const INPUT_DIM: usize = 342;
/// Hidden width of both hidden layers of the published PFNN.
pub const HIDDEN_DIM: usize = 512;
/// Output width of the published PFNN.
pub const OUTPUT_DIM: usize = 311;
/// Number of precomputed phase tables the published PFNN ships.
pub const TABLES: usize = 50;

/// Shape of a PFNN-style network: three layers, `tables` phase tables each.
///
/// The loader is generic over it so that the project's small synthetic
/// models use exactly the same code path as the real 115 MB network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PfnnDims {
    pub input: usize,
    pub hidden: usize,
    pub output: usize,
    pub tables: usize,
}

impl PfnnDims {
    /// The published PFNN: 342 -> 512 -> 512 -> 311, 50 tables.
    pub const PFNN: Self = Self {
        input: INPUT_DIM,
        hidden: HIDDEN_DIM,
        output: OUTPUT_DIM,
        tables: TABLES,
    };

    /// `(out, in)` of the weight matrix of each of the three layers.
    pub fn layer_shapes(&self) -> [(usize, usize); 3] {
        [
            (self.hidden, self.input),
            (self.hidden, self.hidden),
            (self.output, self.hidden),
        ]
    }

    /// Number of files in a directory of this shape (drives progress bars).
    pub fn file_count(&self) -> usize {
        self.tables.saturating_mul(6).saturating_add(4)
    }
}

impl Default for PfnnDims {
    fn default() -> Self {
        Self::PFNN
    }
}

/// One layer's weights and biases at every phase table.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerTables {
    /// One matrix per table, `out x in`.
    pub w: Vec<Array2<f32>>,
    /// One bias per table, `out`.
    pub b: Vec<Array1<f32>>,
}

impl LayerTables {
    /// Number of phase tables.
    pub fn tables(&self) -> usize {
        self.w.len()
    }

    /// `(out, in)` of the weight matrices; `(0, 0)` if there are no tables.
    pub fn shape(&self) -> (usize, usize) {
        self.w.first().map_or((0, 0), |w| w.dim())
    }
}

/// A whole PFNN as the demo stores it: normalisation statistics plus the
/// three layers at every phase table.
#[derive(Clone, Debug, PartialEq)]
pub struct PfnnTables {
    pub xmean: Array1<f32>,
    pub xstd: Array1<f32>,
    pub ymean: Array1<f32>,
    pub ystd: Array1<f32>,
    pub layers: [LayerTables; 3],
}

impl PfnnTables {
    /// The dimensions, read off the arrays.
    pub fn dims(&self) -> PfnnDims {
        let (hidden, input) = self.layers[0].shape();
        PfnnDims {
            input,
            hidden,
            output: self.layers[2].shape().0,
            tables: self.layers[0].tables(),
        }
    }
}

/// File name of layer `layer`'s weight matrix at table `table`, e.g. `W1_007.bin`.
pub fn weight_file_name(layer: usize, table: usize) -> String {
    format!("W{layer}_{table:03}.bin")
}

/// File name of layer `layer`'s bias at table `table`, e.g. `b2_049.bin`.
pub fn bias_file_name(layer: usize, table: usize) -> String {
    format!("b{layer}_{table:03}.bin")
}

/// Reads a directory's dimensions off its file sizes: inputs from
/// `Xmean.bin`, outputs from `Ymean.bin`, hidden width from `b0_000.bin`,
/// and the table count from the run of `W0_000.bin`, `W0_001.bin`, ...
/// The loader then checks every file against them, so a directory whose
/// files disagree is still refused, naming the first file that does not fit.
pub fn infer_dims(dir: &Path) -> Result<PfnnDims, ImportError> {
    check_is_dir(dir)?;
    let count = |name: &str| -> Result<usize, ImportError> {
        let path = dir.join(name);
        let len = fs::metadata(&path)
            .map_err(|e| ImportError::from_io(path.clone(), e))?
            .len();
        if len == 0 || len % 4 != 0 {
            return Err(ImportError::WrongSize {
                path,
                expected: len.next_multiple_of(4).max(4),
                found: len,
            });
        }
        Ok((len / 4) as usize)
    };
    let input = count("Xmean.bin")?;
    let output = count("Ymean.bin")?;
    let hidden = count(&bias_file_name(0, 0))?;
    let tables = (0..)
        .take_while(|&t| dir.join(weight_file_name(0, t)).is_file())
        .count();
    Ok(PfnnDims {
        input,
        hidden,
        output,
        tables,
    })
}

/// Loads a PFNN-format directory of any size, its dimensions read off
/// the files by [`infer_dims`].
pub fn load_pfnn_dir_auto(
    dir: &Path,
    progress: Option<&mut dyn FnMut(usize, usize)>,
) -> Result<PfnnTables, ImportError> {
    load_pfnn_dir_dims(dir, infer_dims(dir)?, progress)
}

/// Loads the published PFNN (342/512/311, 50 tables) from `dir`.
pub fn load_pfnn_dir(dir: &Path) -> Result<PfnnTables, ImportError> {
    load_pfnn_dir_dims(dir, PfnnDims::PFNN, None)
}

/// Like [`load_pfnn_dir`], calling `progress(done, total)` with the number of
/// files read so far (first with `done = 0`), for a progress bar: reading
/// 304 files / 115 MB from a slow disk takes long enough to want one.
pub fn load_pfnn_dir_with_progress(
    dir: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<PfnnTables, ImportError> {
    load_pfnn_dir_dims(dir, PfnnDims::PFNN, Some(progress))
}

/// Loads a PFNN-format directory of arbitrary dimensions.
///
/// Stops at the first bad file, in a fixed order (statistics first, then
/// table by table), so the same broken directory always gives the same error.
pub fn load_pfnn_dir_dims(
    dir: &Path,
    dims: PfnnDims,
    mut progress: Option<&mut dyn FnMut(usize, usize)>,
) -> Result<PfnnTables, ImportError> {
    check_is_dir(dir)?;
    let total = dims.file_count();
    let mut done = 0;
    let mut tick = |done: &mut usize| {
        if let Some(cb) = progress.as_mut() {
            cb(*done, total);
        }
        *done = done.saturating_add(1);
    };
    tick(&mut done);

    let mut stat = |name: &str, len: usize| -> Result<Array1<f32>, ImportError> {
        let v = read_f32_file(&dir.join(name), len)?;
        tick(&mut done);
        Ok(Array1::from(v))
    };
    let xmean = stat("Xmean.bin", dims.input)?;
    let xstd = stat("Xstd.bin", dims.input)?;
    let ymean = stat("Ymean.bin", dims.output)?;
    let ystd = stat("Ystd.bin", dims.output)?;
    reject_zero(&xstd, &dir.join("Xstd.bin"))?;

    let shapes = dims.layer_shapes();
    let mut layers: [LayerTables; 3] = std::array::from_fn(|_| LayerTables {
        w: Vec::with_capacity(dims.tables),
        b: Vec::with_capacity(dims.tables),
    });
    for t in 0..dims.tables {
        for (l, &(rows, cols)) in shapes.iter().enumerate() {
            let w = read_matrix(&dir.join(weight_file_name(l, t)), rows, cols)?;
            layers[l].w.push(w);
            tick(&mut done);
        }
        for (l, &(rows, _)) in shapes.iter().enumerate() {
            let b = read_f32_file(&dir.join(bias_file_name(l, t)), rows)?;
            layers[l].b.push(Array1::from(b));
            tick(&mut done);
        }
    }
    Ok(PfnnTables {
        xmean,
        xstd,
        ymean,
        ystd,
        layers,
    })
}

/// Writes `tables` in the demo format into `dir` (created if needed).
///
/// Fails with `InvalidInput`, before writing anything, if the arrays do not
/// describe one consistent network: a directory the loader would reject
/// should never be produced.
pub fn write_pfnn_dir(tables: &PfnnTables, dir: &Path) -> io::Result<()> {
    check_consistent(tables).map_err(|msg| io::Error::new(io::ErrorKind::InvalidInput, msg))?;
    fs::create_dir_all(dir)?;
    write_f32_file(&dir.join("Xmean.bin"), tables.xmean.iter())?;
    write_f32_file(&dir.join("Xstd.bin"), tables.xstd.iter())?;
    write_f32_file(&dir.join("Ymean.bin"), tables.ymean.iter())?;
    write_f32_file(&dir.join("Ystd.bin"), tables.ystd.iter())?;
    for (l, layer) in tables.layers.iter().enumerate() {
        for (t, (w, b)) in layer.w.iter().zip(&layer.b).enumerate() {
            // `iter()` walks in logical row-major order whatever the memory
            // layout, which is what the format requires.
            write_f32_file(&dir.join(weight_file_name(l, t)), w.iter())?;
            write_f32_file(&dir.join(bias_file_name(l, t)), b.iter())?;
        }
    }
    Ok(())
}

fn check_is_dir(dir: &Path) -> Result<(), ImportError> {
    let meta = fs::metadata(dir).map_err(|e| ImportError::from_io(dir.to_path_buf(), e))?;
    if meta.is_dir() {
        Ok(())
    } else {
        Err(ImportError::NotADirectory {
            path: dir.to_path_buf(),
        })
    }
}

/// Reads exactly `len` finite little-endian `f32` from `path`.
fn read_f32_file(path: &Path, len: usize) -> Result<Vec<f32>, ImportError> {
    let expected = u64::try_from(len)
        .ok()
        .and_then(|n| n.checked_mul(4))
        .ok_or_else(|| ImportError::SizeOverflow {
            path: path.to_path_buf(),
            what: format!("{len} float32"),
        })?;
    // Check the size before reading, so a wrong (possibly huge) file is
    // rejected without loading it.
    let meta = fs::metadata(path).map_err(|e| ImportError::from_io(path.to_path_buf(), e))?;
    check_size(path, expected, meta.len())?;
    let bytes = crate::io::atomic::read_input(path)
        .map_err(|e| ImportError::from_io(path.to_path_buf(), e))?;
    // Again after reading: the file may have changed in between.
    check_size(path, expected, bytes.len() as u64)?;
    let values: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if let Some(index) = values.iter().position(|v| !v.is_finite()) {
        return Err(ImportError::NonFinite {
            path: path.to_path_buf(),
            index,
            value: values[index],
        });
    }
    Ok(values)
}

fn read_matrix(path: &Path, rows: usize, cols: usize) -> Result<Array2<f32>, ImportError> {
    let len = rows
        .checked_mul(cols)
        .ok_or_else(|| ImportError::SizeOverflow {
            path: path.to_path_buf(),
            what: format!("a {rows} x {cols} matrix"),
        })?;
    let values = read_f32_file(path, len)?;
    // Cannot fail: read_f32_file returned exactly rows * cols values.
    Ok(Array2::from_shape_vec((rows, cols), values).unwrap_or_else(|_| unreachable!()))
}

fn check_size(path: &Path, expected: u64, found: u64) -> Result<(), ImportError> {
    if expected == found {
        Ok(())
    } else {
        Err(ImportError::WrongSize {
            path: path.to_path_buf(),
            expected,
            found,
        })
    }
}

fn reject_zero(std: &Array1<f32>, path: &Path) -> Result<(), ImportError> {
    match std.iter().position(|&s| s == 0.0) {
        Some(index) => Err(ImportError::ZeroStd {
            path: path.to_path_buf(),
            index,
        }),
        None => Ok(()),
    }
}

fn write_f32_file<'a>(path: &PathBuf, values: impl Iterator<Item = &'a f32>) -> io::Result<()> {
    let bytes: Vec<u8> = values.flat_map(|v| v.to_le_bytes()).collect();
    fs::write(path, bytes)
}

/// Describes the first inconsistency between the arrays of `t`, if any.
fn check_consistent(t: &PfnnTables) -> Result<(), String> {
    let dims = t.dims();
    let expect = |what: &str, found: usize, want: usize| {
        if found == want {
            Ok(())
        } else {
            Err(format!("{what} has {found} elements, expected {want}"))
        }
    };
    expect("Xmean", t.xmean.len(), dims.input)?;
    expect("Xstd", t.xstd.len(), dims.input)?;
    expect("Ymean", t.ymean.len(), dims.output)?;
    expect("Ystd", t.ystd.len(), dims.output)?;
    for (l, (layer, &(rows, cols))) in t.layers.iter().zip(&dims.layer_shapes()).enumerate() {
        expect(
            &format!("layer {l} weight tables"),
            layer.w.len(),
            dims.tables,
        )?;
        expect(
            &format!("layer {l} bias tables"),
            layer.b.len(),
            dims.tables,
        )?;
        for (i, (w, b)) in layer.w.iter().zip(&layer.b).enumerate() {
            if w.dim() != (rows, cols) {
                return Err(format!(
                    "W{l}_{i:03} is {:?}, expected {:?}",
                    w.dim(),
                    (rows, cols)
                ));
            }
            expect(&format!("b{l}_{i:03}"), b.len(), rows)?;
        }
    }
    Ok(())
}

/// Helpers shared by the unit tests of this crate.
#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
pub(crate) mod fixtures {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The real PFNN weights, if this checkout has them: `$PHASEGATE_PFNN_DIR`
    /// if set (then it must be valid), else `../shared/pfnn/network` beside
    /// the repository. `None` means tests on real data should skip.
    pub(crate) fn real_pfnn_dir() -> Option<PathBuf> {
        if let Some(dir) = std::env::var_os("PHASEGATE_PFNN_DIR") {
            return Some(PathBuf::from(dir));
        }
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/pfnn/network");
        if dir.is_dir() {
            Some(dir)
        } else {
            // Straight to stderr: the harness would swallow println! of a passing test.
            let _ = std::io::Write::write_all(
                &mut std::io::stderr(),
                b"skipped: ../shared/pfnn not found\n",
            );
            None
        }
    }

    /// A small PFNN-shaped network of independent uniform random values.
    pub(crate) fn random_tables(dims: PfnnDims, seed: u64) -> PfnnTables {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut vec = |n: usize, lo: f32, hi: f32| -> Array1<f32> {
            (0..n).map(|_| rng.gen_range(lo..hi)).collect()
        };
        let xmean = vec(dims.input, -2.0, 2.0);
        let xstd = vec(dims.input, 0.5, 3.0);
        let ymean = vec(dims.output, -2.0, 2.0);
        let ystd = vec(dims.output, 0.5, 3.0);
        let mut layer = |rows: usize, cols: usize| {
            let w = (0..dims.tables)
                .map(|_| {
                    let v = vec(rows * cols, -0.5, 0.5).to_vec();
                    Array2::from_shape_vec((rows, cols), v).expect("shape")
                })
                .collect();
            let b = (0..dims.tables).map(|_| vec(rows, -0.5, 0.5)).collect();
            LayerTables { w, b }
        };
        let [s0, s1, s2] = dims.layer_shapes();
        let layers = [layer(s0.0, s0.1), layer(s1.0, s1.1), layer(s2.0, s2.1)];
        PfnnTables {
            xmean,
            xstd,
            ymean,
            ystd,
            layers,
        }
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::fixtures::*;
    use super::*;

    const TINY: PfnnDims = PfnnDims {
        input: 5,
        hidden: 4,
        output: 3,
        tables: 6,
    };

    fn tiny_dir() -> (tempfile::TempDir, PfnnTables) {
        let tmp = tempfile::tempdir().expect("tempdir");
        let t = random_tables(TINY, 7);
        write_pfnn_dir(&t, tmp.path()).expect("write");
        (tmp, t)
    }

    fn load_tiny(dir: &Path) -> Result<PfnnTables, ImportError> {
        load_pfnn_dir_dims(dir, TINY, None)
    }

    fn overwrite_f32(path: &Path, index: usize, value: f32) {
        let mut bytes = fs::read(path).expect("read");
        bytes[index * 4..index * 4 + 4].copy_from_slice(&value.to_le_bytes());
        fs::write(path, bytes).expect("write");
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let (tmp, t) = tiny_dir();
        let back = load_tiny(tmp.path()).expect("load");
        assert_eq!(back, t);
        assert_eq!(back.dims(), TINY);
        assert_eq!(
            fs::read_dir(tmp.path()).expect("ls").count(),
            TINY.file_count()
        );
    }

    #[test]
    fn files_are_row_major_little_endian() {
        let (tmp, t) = tiny_dir();
        let bytes = fs::read(tmp.path().join("W0_002.bin")).expect("read");
        let w = &t.layers[0].w[2];
        // Element (1, 3) sits at 1 * cols + 3.
        let at = (w.ncols() + 3) * 4;
        let v = f32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
        assert_eq!(v, w[[1, 3]]);
    }

    #[test]
    fn progress_counts_every_file() {
        let (tmp, _) = tiny_dir();
        let mut calls = Vec::new();
        let mut cb = |done: usize, total: usize| calls.push((done, total));
        load_pfnn_dir_dims(tmp.path(), TINY, Some(&mut cb)).expect("load");
        let total = TINY.file_count();
        let expected: Vec<_> = (0..=total).map(|d| (d, total)).collect();
        assert_eq!(calls, expected);
    }

    #[test]
    fn missing_file_is_named() {
        let (tmp, _) = tiny_dir();
        fs::remove_file(tmp.path().join("b1_004.bin")).expect("rm");
        let e = load_tiny(tmp.path()).unwrap_err();
        assert!(matches!(e, ImportError::MissingFile { .. }), "{e:?}");
        assert!(e.to_string().contains("b1_004.bin: not found"), "{e}");
    }

    #[test]
    fn truncated_file_reports_both_sizes() {
        let (tmp, _) = tiny_dir();
        let path = tmp.path().join("W2_005.bin");
        let bytes = fs::read(&path).expect("read");
        fs::write(&path, &bytes[..bytes.len() - 3]).expect("write");
        let e = load_tiny(tmp.path()).unwrap_err();
        match &e {
            ImportError::WrongSize {
                expected, found, ..
            } => assert_eq!((*expected, *found), (48, 45)),
            other => panic!("wrong variant: {other:?}"),
        }
        assert!(e.to_string().contains("W2_005.bin: wrong size"), "{e}");
    }

    #[test]
    fn oversized_file_is_rejected() {
        let (tmp, _) = tiny_dir();
        let path = tmp.path().join("Ymean.bin");
        let mut bytes = fs::read(&path).expect("read");
        bytes.extend_from_slice(&[0; 4]);
        fs::write(&path, bytes).expect("write");
        let e = load_tiny(tmp.path()).unwrap_err();
        assert!(matches!(e, ImportError::WrongSize { .. }), "{e:?}");
        assert!(e.to_string().contains("Ymean.bin"), "{e}");
    }

    #[test]
    fn nan_is_reported_with_its_index() {
        let (tmp, _) = tiny_dir();
        overwrite_f32(&tmp.path().join("W1_003.bin"), 9, f32::NAN);
        let e = load_tiny(tmp.path()).unwrap_err();
        assert!(
            matches!(e, ImportError::NonFinite { index: 9, .. }),
            "{e:?}"
        );
        let msg = e.to_string();
        assert!(
            msg.contains("W1_003.bin") && msg.contains("index 9"),
            "{msg}"
        );
    }

    #[test]
    fn infinity_is_reported() {
        let (tmp, _) = tiny_dir();
        overwrite_f32(&tmp.path().join("Xmean.bin"), 4, f32::NEG_INFINITY);
        let e = load_tiny(tmp.path()).unwrap_err();
        assert!(
            matches!(e, ImportError::NonFinite { index: 4, value, .. } if value == f32::NEG_INFINITY),
            "{e:?}"
        );
        assert!(e.to_string().contains("Xmean.bin"), "{e}");
    }

    #[test]
    fn zero_input_std_is_rejected() {
        let (tmp, _) = tiny_dir();
        overwrite_f32(&tmp.path().join("Xstd.bin"), 2, 0.0);
        let e = load_tiny(tmp.path()).unwrap_err();
        assert!(matches!(e, ImportError::ZeroStd { index: 2, .. }), "{e:?}");
        assert!(e.to_string().contains("Xstd.bin"), "{e}");
    }

    #[test]
    fn directory_errors() {
        let (tmp, _) = tiny_dir();
        let file = tmp.path().join("Xmean.bin");
        let e = load_tiny(&file).unwrap_err();
        assert!(matches!(e, ImportError::NotADirectory { .. }), "{e:?}");
        assert!(e.to_string().ends_with("Xmean.bin: not a directory"), "{e}");

        let gone = tmp.path().join("nope");
        let e = load_tiny(&gone).unwrap_err();
        assert!(matches!(e, ImportError::MissingFile { .. }), "{e:?}");
    }

    #[test]
    fn wrong_dimensions_fail_on_the_first_file() {
        let (tmp, _) = tiny_dir();
        let e = load_pfnn_dir(tmp.path()).unwrap_err();
        match e {
            ImportError::WrongSize {
                path,
                expected,
                found,
            } => {
                assert!(path.ends_with("Xmean.bin"));
                assert_eq!((expected, found), (342 * 4, 5 * 4));
            }
            other => panic!("wrong variant: {other:?}"),
        }
    }

    #[test]
    fn writer_refuses_inconsistent_tables() {
        let mut t = random_tables(TINY, 1);
        t.layers[1].b.pop();
        let tmp = tempfile::tempdir().expect("tempdir");
        let e = write_pfnn_dir(&t, &tmp.path().join("out")).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
        assert!(e.to_string().contains("layer 1 bias tables"), "{e}");
        assert!(!tmp.path().join("out").exists());
    }

    #[test]
    fn file_names_match_the_demo() {
        assert_eq!(weight_file_name(0, 0), "W0_000.bin");
        assert_eq!(bias_file_name(2, 49), "b2_049.bin");
        assert_eq!(PfnnDims::PFNN.file_count(), 304);
    }

    #[test]
    fn real_pfnn_loads() {
        let Some(dir) = real_pfnn_dir() else { return };
        let t = load_pfnn_dir(&dir).expect("real PFNN should load");
        assert_eq!(t.dims(), PfnnDims::PFNN);
        assert_eq!(t.layers[1].w[49].dim(), (512, 512));
    }
}
