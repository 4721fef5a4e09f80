//! Writes the seed corpus of every target into a directory (default
//! `fuzz/work/seeds`): small valid files generated through the real
//! exporter, plus, with `--large`, the committed golden blobs and weights.
//!
//!     cargo run --release -p phasegate-tests --example write_fuzz_seeds -- [--large] [DIR]

use std::path::PathBuf;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let large = args.iter().any(|a| a == "--large");
    let dir = args
        .iter()
        .find(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("fuzz/work/seeds"));
    let mut total = 0;
    for (target, name, bytes) in phasegate_tests::fuzz::seeds(large) {
        let d = dir.join(target);
        std::fs::create_dir_all(&d).expect("seed dir");
        std::fs::write(d.join(&name), &bytes).expect("seed file");
        println!("{target}/{name}: {} bytes", bytes.len());
        total += bytes.len();
    }
    println!("{total} bytes");
}
