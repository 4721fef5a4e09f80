//! `host-sim target --self-test N`: the boot self-test under QEMU
//! (docs/blob-format.md, "Self-test section"; docs/firmware.md, boot
//! step 3), both ways:
//!
//! - **passing**: the blob with an N-vector self-test
//!   (`exporter::self_test::with_self_test`, or the blob itself when it
//!   has one) boots with the same input image as the main run; the
//!   firmware must log `self-test: N vectors passed`, exit 0, and write
//!   outputs bit for bit the main run's (the section changes no frame);
//! - **corrupted**: the same blob with one stored output changed and the
//!   payload CRC re-sealed (`exporter::self_test::corrupt_expected`), so
//!   that it loads and only the self-test can refuse it: the firmware must
//!   exit with `wire::exit::SELF_TEST_FAILED` and log the vector and
//!   output index.

use std::path::Path;
use std::time::Duration;

use anyhow::{ensure, Context, Result};
use phasegate::Model;

use super::report::INSTRUCTIONS_PER_TICK;
use super::{boot, wire, ElfInfo};

/// What the two boots showed.
#[derive(Clone, Debug)]
pub struct SelfTestCheck {
    /// Vectors in the section.
    pub vectors: u16,
    /// Bytes the section adds to the blob.
    pub section_bytes: usize,
    /// Instructions the firmware's self-test took (SysTick ticks x 40).
    pub instructions: u64,
    /// The passing boot's self-test log line.
    pub passed_line: String,
    /// The vector and output whose stored value was changed.
    pub corrupted: (u16, u16),
    /// The corrupted boot's exit code.
    pub corrupted_exit: i32,
    /// The corrupted boot's log line naming them.
    pub failed_line: String,
}

/// The blob with a self-test of `n` vectors: `blob` itself when it has
/// one already.
pub fn blob_with_self_test(blob: &[u8], n: usize) -> Result<Vec<u8>> {
    let model = Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("{e}"))?;
    if model.self_test().is_some() {
        return Ok(blob.to_vec());
    }
    ensure!(n > 0, "--self-test 0: the check needs at least one vector");
    Ok(exporter::self_test::with_self_test(blob, n)?.0)
}

/// Runs both boots with `elf`; `image` and `outputs` are the main run's
/// input image and its output file's (i16, f32) records, which the
/// passing boot must reproduce.
#[allow(clippy::too_many_arguments)]
pub fn check(
    elf: &ElfInfo,
    elf_path: &Path,
    blob: &[u8],
    n: usize,
    image: &[u8],
    outputs: (&[i16], &[f32]),
    parse: impl Fn(&[u8]) -> Result<(Vec<i16>, Vec<f32>)>,
    timeout: Duration,
) -> Result<SelfTestCheck> {
    let tested = blob_with_self_test(blob, n)?;
    let model = Model::from_bytes(&tested).map_err(|e| anyhow::anyhow!("{e}"))?;
    let vectors = model.self_test().map_or(0, |t| t.count());
    let output_dim = model.output_dim();
    let dir = tempfile::Builder::new()
        .prefix("phasegate-self-test-")
        .tempdir()
        .context("cannot create a temporary directory")?;

    let path = dir.path().join("self-test.blob");
    std::fs::write(&path, &tested).context("cannot write the self-test blob")?;
    let booted = boot(elf, elf_path, Some(&path), None, Some(image), timeout)?;
    let file = booted
        .output_file()
        .context("the blob with a self-test did not run")?;
    let prefix = format!("self-test: {vectors} vectors passed, bit for bit (");
    let passed_line = booted
        .log
        .iter()
        .find(|l| l.contains(&prefix))
        .with_context(|| {
            format!(
                "the firmware did not log {prefix:?}; its log:\n  {}",
                booted.log.join("\n  ")
            )
        })?
        .clone();
    let ticks: u64 = passed_line
        .split(prefix.as_str())
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|t| t.parse().ok())
        .context("no tick count in the self-test line")?;
    let (q, f) = parse(file)?;
    ensure!(
        q == outputs.0
            && f.len() == outputs.1.len()
            && f.iter()
                .zip(outputs.1)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
        "with its self-test section the blob's frames differ from the run without it"
    );

    // The middle vector, the middle output.
    let corrupted = (vectors / 2, (output_dim / 2) as u16);
    let bad = exporter::self_test::corrupt_expected(
        &tested,
        usize::from(corrupted.0),
        usize::from(corrupted.1),
    )?;
    ensure!(
        Model::from_bytes(&bad).is_ok(),
        "the corrupted blob must load (CRC re-sealed)"
    );
    let path = dir.path().join("self-test-corrupted.blob");
    std::fs::write(&path, &bad).context("cannot write the corrupted blob")?;
    let booted = boot(elf, elf_path, Some(&path), None, None, timeout)?;
    let corrupted_exit = booted.run.exit_code;
    let naming = format!(
        "self-test failed: vector {} output {}:",
        corrupted.0, corrupted.1
    );
    let failed_line = booted
        .log
        .iter()
        .find(|l| l.contains(&naming))
        .cloned()
        .unwrap_or_default();
    ensure!(
        corrupted_exit == wire::exit::SELF_TEST_FAILED && !failed_line.is_empty(),
        "the corrupted self-test must exit with {} ({}) and log {naming:?}; it exited with {} ({}), log:\n  {}",
        wire::exit::SELF_TEST_FAILED,
        wire::exit::describe(wire::exit::SELF_TEST_FAILED),
        corrupted_exit,
        wire::exit::describe(corrupted_exit),
        booted.log.join("\n  ")
    );
    ensure!(
        booted.run.output_file.is_none(),
        "the corrupted self-test's firmware wrote outputs: the model ran"
    );
    Ok(SelfTestCheck {
        vectors,
        section_bytes: section_bytes(&model),
        instructions: ticks * INSTRUCTIONS_PER_TICK,
        passed_line,
        corrupted,
        corrupted_exit,
        failed_line,
    })
}

/// Bytes of `model`'s self-test section: from the first record to the
/// end of the payload (footer included).
fn section_bytes(model: &Model<'_>) -> usize {
    let p = model.payload();
    let at = p
        .len()
        .saturating_sub(phasegate::blob::SELF_TEST_FOOTER_LEN);
    p.get(at..at + 4)
        .and_then(|b| b.try_into().ok())
        .map_or(0, |b| {
            p.len().saturating_sub(u32::from_le_bytes(b) as usize)
        })
}

impl SelfTestCheck {
    /// The report's lines.
    pub fn render(&self) -> String {
        format!(
            "self-test: {} vectors ({} B at the end of the payload) passed on the firmware in {} instructions \
             ({} per vector), outputs of the frames unchanged\n  {}\n\
             self-test, corrupted (vector {} output {} changed, CRC re-sealed): exit code {} ({})\n  {}\n",
            self.vectors,
            self.section_bytes,
            self.instructions,
            self.instructions / u64::from(self.vectors.max(1)),
            self.passed_line,
            self.corrupted.0,
            self.corrupted.1,
            self.corrupted_exit,
            wire::exit::describe(self.corrupted_exit),
            self.failed_line
        )
    }
}
