//! The command-line tools on hostile files (issue 14, item 2): every file
//! the `exporter` and `host-sim` can be handed that is damaged, lies about
//! its sizes or holds the wrong thing gets one line on stderr naming the
//! file (and the array, where there is one), a non-zero exit that is not a
//! panic (101), and no output file. One test per class.
//!
//! The binaries are the ones `cargo test --workspace` builds beside this
//! test (`target/<profile>/exporter`, `.../host-sim`).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let dir = exe.parent().unwrap().parent().unwrap();
    let p = dir.join(name);
    assert!(
        p.is_file(),
        "{} not built: run `cargo test --workspace` (it builds the binaries) or `cargo build -p {name}`",
        p.display()
    );
    p
}

fn run(tool: &str, args: &[&Path]) -> Output {
    Command::new(bin(tool)).args(args).output().unwrap()
}

fn p(s: &str) -> &Path {
    Path::new(s)
}

/// Non-zero exit, not a panic, one stderr line containing every `needle`,
/// `out` not created and no temporary file left beside it.
fn refused(o: &Output, needles: &[&str], out: &Path) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success(), "exit 0; stderr: {err}");
    assert_ne!(o.status.code(), Some(101), "panicked: {err}");
    assert!(o.status.code().is_some(), "killed by a signal: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err}");
    for n in needles {
        assert!(err.contains(n), "{n:?} missing from: {err}");
    }
    assert!(!out.exists(), "{} was written", out.display());
    println!("refused: {}", err.trim_end());
    if let Some(dir) = out.parent().filter(|d| d.is_dir()) {
        for e in std::fs::read_dir(dir).unwrap() {
            let name = e.unwrap().file_name();
            assert!(
                !name.to_string_lossy().ends_with(".tmp"),
                "left {name:?} behind"
            );
        }
    }
    err
}

// ---- file builders -------------------------------------------------------

/// A `.npy` with a hand-written header (`shape` as Python text) and `data`.
fn npy(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut h =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}").into_bytes();
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(b' ');
    }
    h.push(b'\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend(u16::try_from(h.len()).unwrap().to_le_bytes());
    out.extend(h);
    out.extend(data);
    out
}

fn npy_f32(shape: &[usize], v: &[f32]) -> Vec<u8> {
    let s: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape = if s.len() == 1 {
        format!("({},)", s[0])
    } else {
        format!("({})", s.join(", "))
    };
    npy(
        "<f4",
        &shape,
        &v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<_>>(),
    )
}

/// A stored (uncompressed) `.npz` of `(name, .npy bytes)`.
fn npz(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    use std::io::Write;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts =
        zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, bytes) in entries {
        zip.start_file(format!("{name}.npy"), opts).unwrap();
        zip.write_all(bytes).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

/// The arrays of a small PFNN-shaped `.npz` (4 -> 6 -> 6 -> 3, K = 4).
fn pfnn_arrays() -> Vec<(String, Vec<usize>, Vec<f32>)> {
    let mut seed = 7u32;
    let mut rnd = move |n: usize| -> Vec<f32> {
        (0..n)
            .map(|_| {
                seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
            })
            .collect()
    };
    let mut a = vec![
        ("Xmean".to_string(), vec![4], rnd(4)),
        ("Xstd".to_string(), vec![4], vec![1.0; 4]),
        ("Ymean".to_string(), vec![3], rnd(3)),
        ("Ystd".to_string(), vec![3], vec![2.0; 3]),
    ];
    for (l, (r, c)) in [(6, 4), (6, 6), (3, 6)].into_iter().enumerate() {
        a.push((format!("W{l}"), vec![4, r, c], rnd(4 * r * c)));
        a.push((format!("b{l}"), vec![4, r], rnd(4 * r)));
    }
    a
}

fn pfnn_npz(arrays: &[(String, Vec<usize>, Vec<f32>)]) -> Vec<u8> {
    npz(&arrays
        .iter()
        .map(|(n, s, v)| (n.clone(), npy_f32(s, v)))
        .collect::<Vec<_>>())
}

/// A `.safetensors` file: `(name, dtype, shape, [begin, end])` over `data`.
fn safetensors(tensors: &[(&str, &str, Vec<u64>, [u64; 2])], data: &[u8]) -> Vec<u8> {
    let mut map = serde_json::Map::new();
    for (n, dt, shape, offs) in tensors {
        map.insert(
            n.to_string(),
            serde_json::json!({"dtype": dt, "shape": shape, "data_offsets": offs}),
        );
    }
    let mut header = serde_json::Value::Object(map).to_string().into_bytes();
    while !header.len().is_multiple_of(8) {
        header.push(b' ');
    }
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend(header);
    out.extend(data);
    out
}

const GRAPH: &str = r#"{"format": "phasegate-graph", "version": 1, "input_dim": 4,
  "nodes": [{"name": "fc", "op": "dense", "inputs": ["input"]}], "output": "fc"}"#;

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

struct Dir(tempfile::TempDir);

impl Dir {
    fn new() -> Self {
        Dir(tempfile::tempdir().unwrap())
    }
    fn file(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.0.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
    fn path(&self, name: &str) -> PathBuf {
        self.0.path().join(name)
    }
}

fn export_npz(weights: &Path, out: &Path) -> Output {
    run(
        "exporter",
        &[
            p("npz"),
            p("--weights"),
            weights,
            p("--gating"),
            p("cubic"),
            p("-o"),
            out,
        ],
    )
}

fn export_graph(json: &Path, weights: &Path, out: &Path) -> Output {
    run(
        "exporter",
        &[
            p("graph"),
            p("--graph"),
            json,
            p("--weights"),
            weights,
            p("-o"),
            out,
        ],
    )
}

fn compare(a: &Path, b: &Path) -> Output {
    run("host-sim", &[p("compare"), a, b])
}

/// The valid starting point works, so each refusal below is the damage's.
#[test]
fn the_undamaged_files_export() {
    let d = Dir::new();
    let w = d.file("m.npz", &pfnn_npz(&pfnn_arrays()));
    let out = d.path("m.blob");
    let o = export_npz(&w, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.is_file());
    let json = d.file("g.json", GRAPH.as_bytes());
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[
                ("fc.weight", "F32", vec![3, 4], [0, 48]),
                ("fc.bias", "F32", vec![3], [48, 60]),
            ],
            &f32_bytes(&[0.25; 15]),
        ),
    );
    let out = d.path("g.blob");
    let o = export_graph(&json, &st, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

// ---- declared sizes that overflow ----------------------------------------

/// A `.npz` array whose header shape has 2^64 elements (was read as an
/// empty array, then a slice index panicked).
#[test]
fn npz_shape_whose_element_count_overflows() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    a.retain(|(n, ..)| n != "W1");
    let mut entries: Vec<(String, Vec<u8>)> = a
        .iter()
        .map(|(n, s, v)| (n.clone(), npy_f32(s, v)))
        .collect();
    entries.push(("W1".into(), npy("<f4", "(4, 4294967296, 4294967296)", &[])));
    let w = d.file("m.npz", &npz(&entries));
    let out = d.path("m.blob");
    refused(
        &export_npz(&w, &out),
        &["m.npz", "array W1", "overflows"],
        &out,
    );
}

/// An array with no elements but a huge dimension (`(2^62, 0)`): nothing
/// overflows, but a consumer would loop or allocate for 2^62 rows.
#[test]
fn npz_empty_array_with_a_huge_dimension() {
    let d = Dir::new();
    let mut entries = pfnn_npz_entries();
    entries[2] = ("Ymean".into(), npy("<f4", "(4611686018427387904, 0)", &[]));
    let w = d.file("m.npz", &npz(&entries));
    let out = d.path("m.blob");
    refused(
        &export_npz(&w, &out),
        &["m.npz", "array Ymean", "no elements"],
        &out,
    );
}

/// The same in a `.safetensors` header.
#[test]
fn safetensors_shape_whose_element_count_overflows() {
    let d = Dir::new();
    let json = d.file("g.json", GRAPH.as_bytes());
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[("fc.weight", "F32", vec![1 << 32, 1 << 32, 16], [0, 8])],
            &[0; 8],
        ),
    );
    let out = d.path("g.blob");
    // The library's message names no tensor; ours does.
    refused(
        &export_graph(&json, &st, &out),
        &[
            "g.safetensors: not a valid safetensors file: tensor fc.weight: shape \
             [4294967296, 4294967296, 16] of F32 declares more bytes than fit in memory",
        ],
        &out,
    );
}

/// The same in a `.npy` handed to `host-sim compare` (which exited 0,
/// comparing nothing).
#[test]
fn npy_shape_whose_element_count_overflows() {
    let d = Dir::new();
    let a = d.file("a.npy", &npy("<f4", "(4294967296, 4294967296)", &[]));
    let b = d.file("b.npy", &npy("<f4", "(4294967296, 4294967296)", &[]));
    refused(&compare(&a, &b), &["a.npy", "overflows"], &d.path("none"));
}

// ---- truncated data ------------------------------------------------------

#[test]
fn npz_array_shorter_than_its_header() {
    let d = Dir::new();
    let mut a = pfnn_npz_entries();
    let n = a[0].1.len() - 4;
    a[0].1.truncate(n); // Xmean loses its last float
    let w = d.file("m.npz", &npz(&a));
    let out = d.path("m.blob");
    refused(
        &export_npz(&w, &out),
        &["m.npz", "array Xmean", "truncated"],
        &out,
    );
}

#[test]
fn npy_shorter_than_its_header() {
    let d = Dir::new();
    let full = npy_f32(&[2, 3], &[1.0; 6]);
    let a = d.file("a.npy", &full[..full.len() - 4]);
    let b = d.file("b.npy", &npy_f32(&[2, 3], &[1.0; 6]));
    refused(&compare(&a, &b), &["a.npy", "truncated"], &d.path("none"));
}

/// A damaged zip entry (its CRC no longer matches): the zip crate's
/// "Invalid checksum" now names the file and the array.
#[test]
fn npz_entry_with_a_bad_checksum() {
    let d = Dir::new();
    let mut bytes = pfnn_npz(&pfnn_arrays());
    // A byte of Xstd's stored .npy (its header padding), past the local
    // zip header's file name.
    let at = bytes.windows(8).position(|w| w == b"Xstd.npy").unwrap() + 8 + 60;
    bytes[at] ^= 0x40;
    let w = d.file("m.npz", &bytes);
    let out = d.path("m.blob");
    refused(&export_npz(&w, &out), &["m.npz", "array Xstd"], &out);
}

#[test]
fn pfnn_bin_file_truncated() {
    let d = Dir::new();
    let dir = d.path("net");
    write_small_pfnn_dir(&dir);
    let f = dir.join("W1_007.bin");
    let len = std::fs::metadata(&f).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&f)
        .unwrap()
        .set_len(len - 3)
        .unwrap();
    let out = d.path("m.blob");
    let o = run(
        "exporter",
        &[
            p("pfnn"),
            p("--weights"),
            &dir,
            p("--gating"),
            p("cubic"),
            p("-o"),
            &out,
        ],
    );
    refused(&o, &["W1_007.bin", "wrong size"], &out);
}

// ---- wrong dtypes and shapes ---------------------------------------------

#[test]
fn npz_array_of_the_wrong_dtype() {
    let d = Dir::new();
    let mut a = pfnn_npz_entries();
    a[1] = ("Xstd".into(), npy("<i4", "(4,)", &[1; 16]));
    let w = d.file("m.npz", &npz(&a));
    let out = d.path("m.blob");
    refused(
        &export_npz(&w, &out),
        &["m.npz", "array Xstd", "dtype"],
        &out,
    );
}

#[test]
fn npz_array_of_the_wrong_shape() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    let w0 = a.iter_mut().find(|(n, ..)| n == "W0").unwrap();
    w0.1 = vec![24, 4]; // (K*rows, cols): 2-D instead of (K, rows, cols)
    let w = d.file("m.npz", &pfnn_npz(&a));
    let out = d.path("m.blob");
    refused(&export_npz(&w, &out), &["m.npz", "W0", "shape"], &out);
}

// ---- NaN and infinity ------------------------------------------------------

#[test]
fn npz_array_with_nan() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    a.iter_mut().find(|(n, ..)| n == "W1").unwrap().2[5] = f32::NAN;
    let w = d.file("m.npz", &pfnn_npz(&a));
    let out = d.path("m.blob");
    refused(
        &export_npz(&w, &out),
        &["m.npz", "array W1", "non-finite"],
        &out,
    );
}

#[test]
fn safetensors_tensor_with_infinity() {
    let d = Dir::new();
    let json = d.file("g.json", GRAPH.as_bytes());
    let mut w = [0.25f32; 15];
    w[2] = f32::INFINITY;
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[
                ("fc.weight", "F32", vec![3, 4], [0, 48]),
                ("fc.bias", "F32", vec![3], [48, 60]),
            ],
            &f32_bytes(&w),
        ),
    );
    let out = d.path("g.blob");
    refused(
        &export_graph(&json, &st, &out),
        &["g.safetensors", "fc.weight", "non-finite"],
        &out,
    );
}

// ---- overlapping or out-of-range tensor offsets ----------------------------

#[test]
fn safetensors_tensors_that_overlap() {
    let d = Dir::new();
    let json = d.file("g.json", GRAPH.as_bytes());
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[
                ("fc.weight", "F32", vec![3, 4], [0, 48]),
                ("fc.bias", "F32", vec![3], [36, 48]),
            ],
            &f32_bytes(&[0.25; 12]),
        ),
    );
    let out = d.path("g.blob");
    refused(
        &export_graph(&json, &st, &out),
        &[
            "g.safetensors: not a valid safetensors file: tensor fc.bias: data_offsets [36, 48] \
           do not start at the end of tensor fc.weight (48)",
        ],
        &out,
    );
}

#[test]
fn safetensors_offsets_past_the_data() {
    let d = Dir::new();
    let json = d.file("g.json", GRAPH.as_bytes());
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[
                ("fc.weight", "F32", vec![3, 4], [0, 48]),
                ("fc.bias", "F32", vec![3], [48, 60]),
            ],
            &f32_bytes(&[0.25; 13]),
        ),
    );
    let out = d.path("g.blob");
    refused(
        &export_graph(&json, &st, &out),
        &[
            "g.safetensors: not a valid safetensors file: the tensors' data ends at byte 60 \
           (tensor fc.bias), but the file has 52 data bytes",
        ],
        &out,
    );
}

// ---- missing arrays and files ----------------------------------------------

#[test]
fn npz_without_a_required_array() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    a.retain(|(n, ..)| n != "b2");
    let w = d.file("m.npz", &pfnn_npz(&a));
    let out = d.path("m.blob");
    refused(&export_npz(&w, &out), &["m.npz", "missing array b2"], &out);
}

#[test]
fn input_file_that_does_not_exist() {
    let d = Dir::new();
    let out = d.path("m.blob");
    refused(
        &export_npz(&d.path("nowhere.npz"), &out),
        &["nowhere.npz"],
        &out,
    );
}

// ---- inconsistent configs --------------------------------------------------

/// Layer widths that do not chain.
#[test]
fn npz_layers_that_do_not_chain() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    let w1 = a.iter_mut().find(|(n, ..)| n == "W1").unwrap();
    w1.1 = vec![4, 6, 5];
    w1.2.truncate(4 * 6 * 5);
    let w = d.file("m.npz", &pfnn_npz(&a));
    let out = d.path("m.blob");
    refused(&export_npz(&w, &out), &["m.npz", "W1"], &out);
}

/// A graph description whose node does not fit its weights.
#[test]
fn graph_description_that_does_not_fit_its_weights() {
    let d = Dir::new();
    let json = d.file("g.json", GRAPH.as_bytes());
    let st = d.file(
        "g.safetensors",
        &safetensors(
            &[("fc.weight", "F32", vec![3, 5], [0, 60])],
            &f32_bytes(&[0.25; 15]),
        ),
    );
    let out = d.path("g.blob");
    let err = refused(
        &export_graph(&json, &st, &out),
        &[
            "node 0 (\"fc\"): array \"fc.weight\" has 5 inputs, but the node's input slices \
             give 4 (the weights of ",
            "g.json)",
        ],
        &out,
    );
    assert!(
        err.starts_with(&format!("error: {}: ", st.display())),
        "the weights file first: {err}"
    );
    // A description error names the description.
    let bad = d.file(
        "bad.json",
        GRAPH
            .replace("\"op\": \"dense\"", "\"op\": \"dense\", \"gate\": \"nope\"")
            .as_bytes(),
    );
    let err = refused(&export_graph(&bad, &st, &out), &["gate \"nope\""], &out);
    assert!(
        err.starts_with(&format!("error: {}: ", bad.display())),
        "the description first: {err}"
    );
}

/// Finite statistics that would give an absurd output stage (an output
/// std of 1e30): refused by the exporter, naming the file and the output,
/// instead of writing a blob whose outputs overflow f32.
#[test]
fn npz_statistics_that_give_an_absurd_output_stage() {
    let d = Dir::new();
    let mut a = pfnn_arrays();
    a.iter_mut().find(|(n, ..)| n == "Ystd").unwrap().2[2] = 1e30;
    let w = d.file("m.npz", &pfnn_npz(&a));
    let out = d.path("m.blob");
    refused(&export_npz(&w, &out), &["m.npz", "output 2", "2^40"], &out);
}

// ---- outputs -----------------------------------------------------------------

#[test]
fn output_directory_that_does_not_exist() {
    let d = Dir::new();
    let w = d.file("m.npz", &pfnn_npz(&pfnn_arrays()));
    let out = d.path("no/such/dir/m.blob");
    refused(&export_npz(&w, &out), &["m.blob"], &out);
}

/// An output directory that cannot be written (here a path through a
/// regular file, which even root cannot create files in).
#[test]
fn output_directory_that_cannot_be_written() {
    let d = Dir::new();
    let w = d.file("m.npz", &pfnn_npz(&pfnn_arrays()));
    d.file("plain", b"x");
    let out = d.path("plain/m.blob");
    refused(&export_npz(&w, &out), &["m.blob"], &out);
}

/// `-o` naming the input: refused before anything is written, the input
/// unchanged (it was replaced by the blob).
#[test]
fn output_path_equal_to_an_input() {
    let d = Dir::new();
    let bytes = pfnn_npz(&pfnn_arrays());
    let w = d.file("m.npz", &bytes);
    let o = export_npz(&w, &w);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success() && o.status.code() != Some(101), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("m.npz") && err.contains("also an input"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(&w).unwrap(),
        bytes,
        "the input was overwritten"
    );
    // host-sim too: eval's output over its own inputs.
    let x = d.file("x.npy", &npy_f32(&[2, 342], &[0.5; 684]));
    let ph = d.file("p.npy", &npy_f32(&[2], &[0.0, 1.0]));
    let before = std::fs::read(&x).unwrap();
    let blob = Path::new(env!("CARGO_MANIFEST_DIR")).join("golden/default/model.blob");
    let o = run(
        "host-sim",
        &[
            p("eval"),
            p("--model"),
            &blob,
            p("--inputs"),
            &x,
            p("--phases"),
            &ph,
            p("--out"),
            &x,
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success() && o.status.code() != Some(101), "{err}");
    assert!(
        err.contains("x.npy") && err.contains("also an input"),
        "{err}"
    );
    assert_eq!(std::fs::read(&x).unwrap(), before);
}

// ---- blobs -------------------------------------------------------------------

/// A blob that passes every other check but whose output stage has a
/// finite, absurd scale (1e30: `q * scale` overflows f32): refused by the
/// loader, so neither `exporter inspect` nor `host-sim eval` accepts it.
#[test]
fn blob_with_an_absurd_output_scale() {
    let d = Dir::new();
    let good =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("golden/default/model.blob"))
            .unwrap();
    let model = phasegate::Model::from_bytes(&good).unwrap();
    let mut header = model.header().decoded();
    let mut payload = good[good.len() - header.payload_len as usize..].to_vec();
    let at = header.output_stage.offset as usize;
    payload[at..at + 4].copy_from_slice(&1e30f32.to_le_bytes());
    header.payload_crc = phasegate::blob::crc32(&payload);
    let bad = exporter::encode::frame(&header, &payload);
    assert_eq!(
        phasegate::Model::from_bytes(&bad).unwrap_err(),
        phasegate::Error::UnsupportedParameter {
            layer: phasegate::STAGE
        }
    );
    let blob = d.file("absurd.blob", &bad);
    refused(
        &run("exporter", &[p("inspect"), &blob]),
        &["absurd.blob", "output stage"],
        &d.path("none"),
    );
    let x = d.file("x.npy", &npy_f32(&[1, 342], &[0.5; 342]));
    let ph = d.file("p.npy", &npy_f32(&[1], &[0.0]));
    let out = d.path("y.npy");
    let o = run(
        "host-sim",
        &[
            p("eval"),
            p("--model"),
            &blob,
            p("--inputs"),
            &x,
            p("--phases"),
            &ph,
            p("--out"),
            &out,
        ],
    );
    refused(&o, &["absurd.blob", "output stage"], &out);
}

/// The output-stage bounds are exact: `|scale| <= 2^24`, `|offset| <= 2^39`
/// load, the next f32 above either does not; the input stage needs only
/// finite values (it saturates to i16).
#[test]
fn output_stage_bounds_are_exact() {
    let good =
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("golden/default/model.blob"))
            .unwrap();
    let patched = |stage_of: fn(&phasegate::blob::Header) -> u32, field: usize, v: f32| {
        let model = phasegate::Model::from_bytes(&good).unwrap();
        let mut header = model.header().decoded();
        let mut payload = good[good.len() - header.payload_len as usize..].to_vec();
        let at = stage_of(&header) as usize + 4 * field;
        payload[at..at + 4].copy_from_slice(&v.to_le_bytes());
        header.payload_crc = phasegate::blob::crc32(&payload);
        let blob = exporter::encode::frame(&header, &payload);
        phasegate::Model::from_bytes(&blob).map(|_| ())
    };
    let out = |h: &phasegate::blob::Header| h.output_stage.offset;
    let inp = |h: &phasegate::blob::Header| h.input_stage.offset;
    let up = |v: f32| f32::from_bits(v.to_bits() + 1);
    let (s, o) = (
        phasegate::blob::MAX_OUTPUT_SCALE,
        phasegate::blob::MAX_OUTPUT_OFFSET,
    );
    let refused = Err(phasegate::Error::UnsupportedParameter {
        layer: phasegate::STAGE,
    });
    assert_eq!(patched(out, 0, s), Ok(()));
    assert_eq!(patched(out, 0, -s), Ok(()));
    assert_eq!(patched(out, 0, up(s)), refused);
    assert_eq!(patched(out, 1, o), Ok(()));
    assert_eq!(patched(out, 1, -up(o)), refused);
    assert_eq!(patched(out, 1, f32::NAN), refused);
    assert_eq!(patched(inp, 1, 1e30), Ok(()));
    assert_eq!(patched(inp, 0, f32::INFINITY), refused);
}

// ---- helpers used above ------------------------------------------------------

fn pfnn_npz_entries() -> Vec<(String, Vec<u8>)> {
    pfnn_arrays()
        .iter()
        .map(|(n, s, v)| (n.clone(), npy_f32(s, v)))
        .collect()
}

fn write_small_pfnn_dir(dir: &Path) {
    use exporter::pfnn_dir::{write_pfnn_dir, LayerTables, PfnnTables};
    use ndarray::{Array1, Array2};
    let layers = [(6usize, 4usize), (6, 6), (3, 6)].map(|(r, c)| LayerTables {
        w: (0..50)
            .map(|t| Array2::from_shape_fn((r, c), |(i, j)| ((t + i * c + j) % 7) as f32 * 0.1))
            .collect(),
        b: (0..50).map(|_| Array1::from_elem(r, 0.1f32)).collect(),
    });
    let tables = PfnnTables {
        xmean: Array1::zeros(4),
        xstd: Array1::from_elem(4, 1.0),
        ymean: Array1::zeros(3),
        ystd: Array1::from_elem(3, 1.0),
        layers,
    };
    write_pfnn_dir(&tables, dir).unwrap();
}
