//! Replays files (a fuzz corpus, a crash artifact) through a fuzz target's
//! code on stable Rust, and says how far they got: for `model` and
//! `styled`, how many loaded and how many frames ran.
//!
//!     cargo run --release -p phasegate-tests --example fuzz_replay -- TARGET PATH...
//!
//! A PATH that is a directory stands for the files in it.

use phasegate_tests::fuzz;
use std::path::PathBuf;

fn main() {
    let mut args = std::env::args().skip(1);
    let target = args.next().expect("usage: fuzz_replay TARGET PATH...");
    let run: fn(&[u8]) -> usize = match target.as_str() {
        "model" => fuzz::exercise_model,
        "styled" => fuzz::exercise_styled,
        "rig" => fuzz::exercise_rig,
        "controller" => fuzz::exercise_controller,
        "reach" => fuzz::exercise_reach,
        "weights" => fuzz::exercise_weights,
        "configs" => fuzz::exercise_configs,
        "pfnn_dir" => fuzz::exercise_pfnn_dir,
        "omg_model" => fuzz::exercise_omg_model,
        "self_test" => fuzz::exercise_self_test,
        other => panic!("unknown target {other}"),
    };
    let mut files: Vec<PathBuf> = Vec::new();
    for a in args {
        let p = PathBuf::from(a);
        if p.is_dir() {
            let mut v: Vec<PathBuf> = std::fs::read_dir(&p)
                .expect("directory")
                .map(|e| e.expect("entry").path())
                .collect();
            v.sort();
            files.extend(v);
        } else {
            files.push(p);
        }
    }
    let (mut nonzero, mut total) = (0, 0);
    for f in &files {
        let bytes = std::fs::read(f).expect("file");
        let n = run(&bytes);
        nonzero += usize::from(n > 0);
        total += n;
    }
    println!(
        "{target}: {} files, {nonzero} got through (frames or parsed files: {total})",
        files.len()
    );
}
