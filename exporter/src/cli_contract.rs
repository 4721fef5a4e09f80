//! The command-line tools' output contract, as a check their tests share
//! (`exporter/tests/cli.rs`, `host-sim/tests/cli.rs`): a command with
//! several outputs writes all of them or none ([`crate::io::atomic`]).
//! Test support: it panics on a broken contract.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

/// Runs `<bin> <prefix> <flag> <path>...` with every output good (all
/// written), then with each output in turn made unwritable: below a plain
/// file, an existing directory, one of `inputs`, the same as the next
/// output, and (unless the command `makes_dirs` for its outputs) in a
/// missing directory. Each must fail in one line saying why and leave no
/// output and no temporary in the output directory, and the inputs
/// unchanged.
pub fn written_together_or_not_at_all(
    bin: &Path,
    makes_dirs: bool,
    prefix: &[String],
    outputs: &[(&str, &str)],
    inputs: &[PathBuf],
) {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let before: Vec<Vec<u8>> = inputs.iter().map(|p| std::fs::read(p).unwrap()).collect();
    let run = |paths: &[PathBuf]| {
        let mut args: Vec<String> = prefix.to_vec();
        for ((flag, _), p) in outputs.iter().zip(paths) {
            args.push(flag.to_string());
            args.push(p.display().to_string());
        }
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        Command::new(bin)
            .args(&refs)
            .output()
            .expect("the command runs")
    };
    let good: Vec<PathBuf> = outputs.iter().map(|(_, n)| out.join(n)).collect();
    let o = run(&good);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut written = good.clone();
    written.sort();
    assert_eq!(files_in(&out), written);
    for p in &good {
        std::fs::remove_file(p).unwrap();
    }
    let blocker = out.join("a-directory");
    std::fs::create_dir(&blocker).unwrap();
    let plain = out.join("a-file");
    std::fs::write(&plain, b"x").unwrap();
    let n = outputs.len();
    for k in 0..n {
        let mut cases = vec![
            ("in a file", plain.join(outputs[k].1), "not a directory"),
            ("a directory", blocker.clone(), "is a directory"),
        ];
        if !makes_dirs {
            cases.push((
                "missing directory",
                out.join("no-such-dir").join(outputs[k].1),
                "no such directory",
            ));
        }
        for input in inputs {
            cases.push(("an input", input.clone(), "also an input"));
        }
        if n > 1 {
            cases.push(("named twice", good[(k + 1) % n].clone(), "two outputs"));
        }
        for (why, bad, says) in cases {
            let mut paths = good.clone();
            paths[k] = bad.clone();
            let o = run(&paths);
            let err = stderr(&o);
            let what = format!(
                "{} {} as {why} ({})",
                prefix[0],
                outputs[k].0,
                bad.display()
            );
            assert!(!o.status.success(), "{what}: succeeded");
            assert_eq!(err.trim_end().lines().count(), 1, "{what}: {err}");
            assert!(err.contains(says), "{what}: {err}");
            assert_eq!(
                files_in(&out),
                [blocker.clone(), plain.clone()],
                "{what}: {err}"
            );
            assert_eq!(std::fs::read(&plain).unwrap(), b"x", "{what}: {err}");
        }
    }
    for (p, b) in inputs.iter().zip(&before) {
        assert_eq!(&std::fs::read(p).unwrap(), b, "{} changed", p.display());
    }
}
