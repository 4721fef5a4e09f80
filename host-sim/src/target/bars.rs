//! Speed bars for `host-sim target --bar SPEC`: the run fails (after its
//! report) when a measured figure is above its bar, so CI holds issue 12's
//! instruction bars the way `host-sim footprint` holds the size budgets.
//!
//! A spec is one of
//! - `per-mac=F`: every layer node at most `F` instructions per MAC;
//! - `nodeN-per-mac=F`: node `N` at most `F` instructions per MAC;
//! - `frame=N`: the inference's median instructions per frame at most `N`.
//!
//! Per-node figures are the firmware's stage profile (mean over the frames,
//! each stage read to one SysTick tick); the frame figure is the median of
//! `run_quantised`.

use std::fmt;
use std::str::FromStr;

use super::layers::StageRow;
use super::TargetReport;

/// One bar.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bar {
    /// Every layer node's instructions per MAC.
    PerMac(f64),
    /// One node's instructions per MAC.
    NodePerMac(u8, f64),
    /// Median inference instructions per frame.
    Frame(u64),
}

impl FromStr for Bar {
    type Err = String;

    fn from_str(s: &str) -> Result<Bar, String> {
        let bad = || format!("bad bar {s:?}: expected per-mac=F, nodeN-per-mac=F or frame=N");
        let (key, value) = s.split_once('=').ok_or_else(bad)?;
        let ratio = || {
            value
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(bad)
        };
        match key {
            "per-mac" => Ok(Bar::PerMac(ratio()?)),
            "frame" => value.parse().map(Bar::Frame).map_err(|_| bad()),
            _ => {
                let node = key
                    .strip_prefix("node")
                    .and_then(|k| k.strip_suffix("-per-mac"))
                    .and_then(|n| n.parse::<u8>().ok())
                    .ok_or_else(bad)?;
                Ok(Bar::NodePerMac(node, ratio()?))
            }
        }
    }
}

impl fmt::Display for Bar {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Bar::PerMac(v) => write!(f, "per-mac={v}"),
            Bar::NodePerMac(n, v) => write!(f, "node{n}-per-mac={v}"),
            Bar::Frame(v) => write!(f, "frame={v}"),
        }
    }
}

/// One judged figure: what was measured against which bar.
#[derive(Clone, Debug, PartialEq)]
pub struct Verdict {
    /// What is judged (`node 1 instructions per MAC`).
    pub what: String,
    /// The figure.
    pub measured: f64,
    /// Its bar.
    pub bar: f64,
}

impl Verdict {
    /// Within its bar.
    pub fn met(&self) -> bool {
        self.measured <= self.bar
    }

    /// One line for the report.
    pub fn line(&self) -> String {
        format!(
            "bar: {} {} <= {}: {}",
            self.what,
            trim(self.measured),
            trim(self.bar),
            if self.met() { "met" } else { "NOT met" }
        )
    }
}

fn trim(v: f64) -> String {
    if v.fract() == 0.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.3}")
    }
}

fn layer_nodes(stages: &[StageRow]) -> impl Iterator<Item = (u8, f64)> + '_ {
    stages
        .iter()
        .filter_map(|s| match (s.stage, s.node, s.per_mac()) {
            ("node", Some(n), Some(r)) => Some((n, r)),
            _ => None,
        })
}

/// Judges `bars` against a run's stages and inference median; a bar that
/// names no layer node of the blob is an error (a typo must not pass).
pub fn judge(bars: &[Bar], stages: &[StageRow], infer_median: u64) -> Result<Vec<Verdict>, String> {
    let mut out = Vec::new();
    for bar in bars {
        match *bar {
            Bar::PerMac(b) => {
                let before = out.len();
                out.extend(layer_nodes(stages).map(|(n, r)| Verdict {
                    what: format!("node {n} instructions per MAC"),
                    measured: r,
                    bar: b,
                }));
                if out.len() == before {
                    return Err(format!("bar {bar}: the blob has no layer node"));
                }
            }
            Bar::NodePerMac(node, b) => {
                let (_, r) = layer_nodes(stages)
                    .find(|(n, _)| *n == node)
                    .ok_or_else(|| {
                        format!("bar {bar}: node {node} is not a layer node of the blob")
                    })?;
                out.push(Verdict {
                    what: format!("node {node} instructions per MAC"),
                    measured: r,
                    bar: b,
                });
            }
            Bar::Frame(b) => out.push(Verdict {
                what: "inference instructions per frame (median)".into(),
                measured: infer_median as f64,
                bar: b as f64,
            }),
        }
    }
    Ok(out)
}

/// Prints one line per judged figure; an error naming every missed bar.
pub fn check(bars: &[Bar], report: &TargetReport) -> anyhow::Result<()> {
    if bars.is_empty() {
        return Ok(());
    }
    let verdicts = judge(bars, &report.stages, report.infer_instructions.median)
        .map_err(anyhow::Error::msg)?;
    for v in &verdicts {
        println!("{}", v.line());
    }
    let missed: Vec<String> = verdicts
        .iter()
        .filter(|v| !v.met())
        .map(Verdict::line)
        .collect();
    if missed.is_empty() {
        Ok(())
    } else {
        anyhow::bail!("{}: {}", report.model.display(), missed.join("; "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stage(stage: &'static str, node: Option<u8>, macs: u64, instructions: f64) -> StageRow {
        StageRow {
            stage,
            node,
            op: String::new(),
            shape: String::new(),
            formats: String::new(),
            experts: 4,
            macs,
            instructions,
            min: instructions as u64,
            max: instructions as u64,
        }
    }

    fn stages() -> Vec<StageRow> {
        vec![
            stage("input", None, 0, 28_000.0),
            stage("prepare", Some(0), 0, 4_000.0),
            stage("node", Some(0), 1_000, 1_900.0),
            stage("node", Some(1), 1_000, 2_100.0),
            stage("node", Some(2), 0, 500.0), // a softmax gate: no MACs
            stage("output", None, 0, 8_000.0),
        ]
    }

    #[test]
    fn specs_parse_and_print_back() {
        for s in ["per-mac=2", "node1-per-mac=1.4", "frame=3600000"] {
            let b: Bar = s.parse().unwrap();
            assert_eq!(b.to_string(), s);
        }
        for s in [
            "per-mac",
            "per-mac=x",
            "per-mac=-1",
            "node-per-mac=1",
            "nodeX-per-mac=1",
            "frame=1.5",
            "speed=1",
        ] {
            assert!(s.parse::<Bar>().is_err(), "{s}");
        }
    }

    #[test]
    fn every_layer_node_is_judged_and_a_miss_is_reported() {
        let v = judge(&[Bar::PerMac(2.0)], &stages(), 0).unwrap();
        assert_eq!(v.len(), 2, "the softmax node has no MACs: not judged");
        assert!(v[0].met() && !v[1].met());
        assert!(v[1].line().ends_with("NOT met"), "{}", v[1].line());
        let v = judge(&[Bar::NodePerMac(0, 1.9), Bar::Frame(100)], &stages(), 100).unwrap();
        assert!(v.iter().all(Verdict::met), "{v:?}");
    }

    #[test]
    fn a_bar_on_a_missing_node_is_an_error() {
        assert!(judge(&[Bar::NodePerMac(2, 1.0)], &stages(), 0).is_err());
        assert!(judge(&[Bar::NodePerMac(7, 1.0)], &stages(), 0).is_err());
        assert!(judge(&[Bar::PerMac(1.0)], &[], 0).is_err());
    }
}
