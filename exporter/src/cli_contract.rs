//! The command-line tools' output contract, as a check their tests share
//! (`exporter/tests/cli.rs`, `host-sim/tests/cli.rs`): a command with
//! several outputs writes all of them or none ([`crate::io::atomic`]), and
//! a count at its largest accepted value runs under a memory cap.
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

/// The address-space cap of [`runs_under_a_memory_cap`]: 4 GiB, above
/// the largest accepted work run to the end (the heaviest,
/// `host-sim accuracy --calibration-tours 436` at the PFNN's widths,
/// peaks at 3.78 GB resident and finishes under this cap;
/// `docs/input-files.md`, "Bounds").
pub const MEMORY_CAP: u64 = 1 << 32;

/// How a run under the memory cap ended.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub enum CappedRun {
    /// It finished, successfully, before the deadline.
    Finished,
    /// It was still running at the deadline, and an interrupt ended it
    /// with exit 130 and no output.
    Interrupted,
}

/// What [`runs_under_a_memory_cap`] saw.
#[derive(Clone, Copy, Debug)]
pub struct CapReport {
    /// How it ended.
    pub outcome: CappedRun,
    /// The largest resident memory seen (`VmHWM`, sampled every 20 ms), MiB.
    pub peak_rss_mib: u64,
    /// Wall time, seconds.
    pub seconds: f64,
}

fn peak_rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Runs `<bin> <args>` from `cwd` under an address-space cap of
/// [`MEMORY_CAP`] (`prlimit --as`, which execs the tool: the pid is the
/// tool's) in its own process group, for at most `deadline`. It must
/// either finish successfully, or still be running at the deadline, and
/// then end on an interrupt (SIGINT to the group, as Ctrl-C in a
/// terminal) with exit 130, leaving `out_dir` (where every output of
/// `args` goes) empty. A count that sizes an allocation up front fails
/// at once under the cap (an allocation failure aborts, exit 134), as does
/// memory that grows past it before the deadline: both fail this check.
/// A run that ends with exit 1 and `verdict` in its error (a measuring
/// command's own judgement of the model, such as "bars missed") finished
/// its work and counts as finished. `None` when `prlimit` (util-linux) is not installed.
#[cfg(unix)]
pub fn runs_under_a_memory_cap(
    bin: &Path,
    cwd: &Path,
    args: &[String],
    out_dir: &Path,
    deadline: std::time::Duration,
    verdict: Option<&str>,
) -> Option<CapReport> {
    use std::os::unix::process::CommandExt;
    Command::new("prlimit").arg("--version").output().ok()?;
    let logs = tempfile::tempdir().unwrap();
    let (out_log, err_log) = (logs.path().join("stdout"), logs.path().join("stderr"));
    let what = format!("{} {}", bin.display(), args.join(" "));
    let start = std::time::Instant::now();
    let mut child = Command::new("prlimit")
        .arg(format!("--as={MEMORY_CAP}"))
        .arg(bin)
        .args(args)
        .current_dir(cwd)
        .stdout(std::fs::File::create(&out_log).unwrap())
        .stderr(std::fs::File::create(&err_log).unwrap())
        .process_group(0)
        .spawn()
        .expect("prlimit runs");
    let pid = child.id();
    let mut peak = 0;
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        peak = peak.max(peak_rss_kib(pid).unwrap_or(0));
        if start.elapsed() >= deadline {
            break None;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let err = || std::fs::read_to_string(&err_log).unwrap_or_default();
    let outcome = match status {
        Some(s) => {
            let judged = s.code() == Some(1) && verdict.is_some_and(|v| err().contains(v));
            assert!(
                s.success() || judged,
                "{what}: {s} under a {MEMORY_CAP}-byte cap: {}",
                err()
            );
            CappedRun::Finished
        }
        None => {
            let k = Command::new("kill")
                .args(["-INT", "--", &format!("-{pid}")])
                .status()
                .unwrap();
            assert!(k.success(), "{what}: cannot interrupt");
            let s = child.wait().unwrap();
            assert_eq!(
                s.code(),
                Some(130),
                "{what}: {s} on an interrupt: {}",
                err()
            );
            assert_eq!(
                files_in(out_dir),
                Vec::<PathBuf>::new(),
                "{what}: left output"
            );
            CappedRun::Interrupted
        }
    };
    Some(CapReport {
        outcome,
        peak_rss_mib: peak / 1024,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Runs each of `cases` through [`runs_under_a_memory_cap`] from `cwd`,
/// `{out}` in its arguments standing for a fresh empty output directory,
/// and prints one line per run (outcome, time, peak memory, command).
/// `check` then sees the report, the arguments as run and the output
/// directory. Returns `false`, having run nothing, when `prlimit` is not
/// installed (and says so).
#[cfg(unix)]
pub fn each_under_a_memory_cap(
    bin: &Path,
    cwd: &Path,
    cases: &[Vec<&str>],
    deadline: std::time::Duration,
    verdict: Option<&str>,
    mut check: impl FnMut(&CapReport, &[String], &Path),
) -> bool {
    let name = bin.file_name().map(|n| n.to_string_lossy().into_owned());
    for case in cases {
        let out = tempfile::tempdir().unwrap();
        let o = out.path().display().to_string();
        let args: Vec<String> = case.iter().map(|a| a.replace("{out}", &o)).collect();
        let Some(r) = runs_under_a_memory_cap(bin, cwd, &args, out.path(), deadline, verdict)
        else {
            eprintln!("prlimit (util-linux) is not installed: memory-cap test skipped");
            return false;
        };
        eprintln!(
            "{:?} after {:.1} s, peak {} MiB: {} {}",
            r.outcome,
            r.seconds,
            r.peak_rss_mib,
            name.as_deref().unwrap_or(""),
            args.join(" ")
        );
        check(&r, &args, out.path());
    }
    true
}
