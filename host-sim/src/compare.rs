//! Error statistics between two output matrices, per PFNN output group,
//! in output units.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{bail, Result};
use serde::Serialize;

use crate::npy::Matrix;

/// Named column ranges of the PFNN output vector (see shared/pfnn/README.md).
pub const PFNN_GROUPS: [(&str, usize, usize); 7] = [
    ("root motion", 0, 3),
    ("phase", 3, 4),
    ("contacts", 4, 8),
    ("trajectory", 8, 32),
    ("joint positions", 32, 125),
    ("joint velocities", 125, 218),
    ("joint rotations", 218, 311),
];

/// Max and RMS absolute difference of one group.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct GroupError {
    /// Group name.
    pub group: String,
    /// Columns `[start, end)`.
    pub columns: (usize, usize),
    /// Largest absolute difference.
    pub max_abs: f64,
    /// Root mean square difference.
    pub rms: f64,
}

/// Per-group and overall errors.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Comparison {
    /// Rows compared.
    pub rows: usize,
    /// Groups (PFNN groups for 311-wide outputs).
    pub groups: Vec<GroupError>,
    /// All columns.
    pub overall: GroupError,
}

fn group_error(
    a: &Matrix<f32>,
    b: &Matrix<f32>,
    name: &str,
    start: usize,
    end: usize,
) -> GroupError {
    let (mut max, mut sq, mut n) = (0.0f64, 0.0f64, 0usize);
    for (ra, rb) in a.iter_rows().zip(b.iter_rows()) {
        for (&x, &y) in ra[start..end].iter().zip(&rb[start..end]) {
            let d = (f64::from(x) - f64::from(y)).abs();
            // NaN on either side is an infinite error, never a silent pass.
            let d = if d.is_nan() { f64::INFINITY } else { d };
            max = max.max(d);
            sq += d * d;
            n = n.saturating_add(1);
        }
    }
    GroupError {
        group: name.to_string(),
        columns: (start, end),
        max_abs: max,
        rms: if n == 0 { 0.0 } else { (sq / n as f64).sqrt() },
    }
}

/// Compares `a` with `b` (same shape).
pub fn compare(a: &Matrix<f32>, b: &Matrix<f32>) -> Result<Comparison> {
    if (a.rows, a.cols) != (b.rows, b.cols) {
        bail!(
            "shapes differ: ({}, {}) vs ({}, {})",
            a.rows,
            a.cols,
            b.rows,
            b.cols
        );
    }
    if a.rows == 0 || a.cols == 0 {
        bail!(
            "nothing to compare: both arrays are ({}, {})",
            a.rows,
            a.cols
        );
    }
    let groups = if a.cols == 311 {
        PFNN_GROUPS
            .iter()
            .map(|&(n, s, e)| group_error(a, b, n, s, e))
            .collect()
    } else {
        Vec::new()
    };
    Ok(Comparison {
        rows: a.rows,
        groups,
        overall: group_error(a, b, "overall", 0, a.cols),
    })
}

impl Comparison {
    /// A readable table.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{:<18} {:>10} {:>12} {:>12}\n",
            "group", "columns", "max abs", "rms"
        );
        for g in self.groups.iter().chain(std::iter::once(&self.overall)) {
            s += &format!(
                "{:<18} {:>10} {:>12.6} {:>12.6}\n",
                g.group,
                format!("{}..{}", g.columns.0, g.columns.1),
                g.max_abs,
                g.rms
            );
        }
        s
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::*;

    #[test]
    fn groups_and_nan() {
        let a = Matrix {
            rows: 1,
            cols: 311,
            data: vec![0.0f32; 311],
        };
        let mut b = a.clone();
        b.data[3] = 2.0;
        b.data[100] = -1.0;
        let c = compare(&a, &b).unwrap();
        assert_eq!(c.groups[1].max_abs, 2.0);
        assert_eq!(c.groups[4].max_abs, 1.0);
        assert_eq!(c.groups[0].max_abs, 0.0);
        assert_eq!(c.overall.max_abs, 2.0);
        b.data[0] = f32::NAN;
        assert!(compare(&a, &b).unwrap().overall.max_abs.is_infinite());
    }
}
