//! Progress displays for the command-line tools (`exporter`, `host-sim`):
//! on stderr when stdout is a terminal, hidden otherwise, so that logs,
//! pipes and tests see only the results.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::time::Duration;

/// stderr when stdout is a terminal, else nowhere.
fn target() -> ProgressDrawTarget {
    if std::io::stdout().is_terminal() {
        ProgressDrawTarget::stderr()
    } else {
        ProgressDrawTarget::hidden()
    }
}

/// A spinner with `msg` and the time elapsed, for work of unknown length.
pub fn spinner(msg: &str) -> ProgressBar {
    let pb = ProgressBar::with_draw_target(None, target());
    pb.set_style(
        ProgressStyle::with_template("{spinner} {msg} [{elapsed}]")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    pb.set_message(msg.to_string());
    pb.enable_steady_tick(Duration::from_millis(120));
    pb
}

/// Runs `work` under a [`spinner`] showing `msg`, cleared when it ends
/// (whatever it returns).
pub fn during<T>(msg: &str, work: impl FnOnce() -> T) -> T {
    let pb = spinner(msg);
    let out = work();
    pb.finish_and_clear();
    out
}

/// A bar of `len` `unit` (for instance "scripts"), with `msg` before it.
pub fn bar(len: u64, msg: &str, unit: &str) -> ProgressBar {
    let pb = ProgressBar::with_draw_target(Some(len), target());
    let template = format!("{{msg}} {{bar:30}} {{pos}}/{{len}} {unit} [{{elapsed}}]");
    pb.set_style(
        ProgressStyle::with_template(&template).unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb.set_message(msg.to_string());
    pb
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Under the test harness stdout is captured: nothing is drawn, and
    /// the bars still count.
    #[test]
    fn hidden_without_a_terminal_and_still_counting() {
        let b = bar(3, "recording", "scripts");
        b.inc(2);
        assert_eq!((b.position(), b.length()), (2, Some(3)));
        if !std::io::stdout().is_terminal() {
            assert!(b.is_hidden());
            assert!(spinner("exporting").is_hidden());
        }
        assert_eq!(during("adding", || 2 + 2), 4);
    }
}
