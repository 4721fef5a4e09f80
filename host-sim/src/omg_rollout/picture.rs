//! The front view of reaching rollouts (x to the character's left drawn to
//! the right, y up, root space): the first rollout's skeleton at a few
//! frames, both hands' paths of every rollout, and the hand targets with
//! their reach radius. `host-sim render` and `host-sim demo` draw it.

use std::path::Path;

use anyhow::{Context, Result};

use super::record::OmgRecord;
use super::CONTACT_RADIUS_M;
use crate::render::canvas::{Canvas, Frame2, Rgb, BLACK, GREEN, GREY, WHITE};

/// One rollout in the picture: its record, legend label, colour and line
/// width (wider ones are drawn first, so narrower ones show on top).
pub struct Layer<'a> {
    /// The rollout.
    pub record: &'a OmgRecord,
    /// Legend text.
    pub label: String,
    /// Colour of its hand paths.
    pub colour: Rgb,
    /// Line width, pixels.
    pub width: f64,
}

/// Draws `layers` (at least one) under `title` to the PNG `path`.
pub fn draw(layers: &[Layer<'_>], title: &str, snapshots: usize, path: &Path) -> Result<()> {
    let Some(first) = layers.first() else {
        anyhow::bail!("nothing to draw");
    };
    let xy = |p: [f64; 3]| (p[0], p[1]);
    let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
    let mut grow = |p: (f64, f64)| {
        lo = (lo.0.min(p.0), lo.1.min(p.1));
        hi = (hi.0.max(p.0), hi.1.max(p.1));
    };
    for l in layers {
        for frame in &l.record.positions {
            frame.iter().for_each(|&p| grow(xy(p)));
        }
    }
    for frame in &first.record.targets {
        frame.iter().take(2).for_each(|&p| grow(xy(p)));
    }
    let (w, h) = (900usize, 760usize);
    let mut c = Canvas::new(w, h, WHITE);
    let pad = 0.08;
    let fr = Frame2::new(
        (70.0, 60.0, w as f64 - 30.0, h as f64 - 110.0),
        (lo.0 - pad, hi.0 + pad),
        (lo.1 - pad, hi.1 + pad),
        true,
    );
    crate::render::grid(&mut c, &fr, "x (m, root space)", "y (m)", false);
    c.text(70.0, 20.0, title, 2, BLACK);
    let map = |p: [f64; 3]| fr.map(p[0], p[1]);
    // The first rollout's skeleton at a few frames, darker when later.
    let rec = first.record;
    let snaps = crate::render::snapshot_frames(rec.len(), snapshots);
    for (i, &t) in snaps.iter().enumerate() {
        let shade = (200.0 - 160.0 * i as f64 / (snaps.len().max(2) - 1) as f64) as u8;
        let frame = &rec.positions[t];
        for (j, &p) in rec.parents.iter().enumerate() {
            if let Ok(p) = usize::try_from(p) {
                c.line(map(frame[j]), map(frame[p]), 2.0, [shade, shade, shade]);
            }
        }
    }
    let mut order: Vec<&Layer<'_>> = layers.iter().collect();
    order.sort_by(|a, b| b.width.total_cmp(&a.width));
    for l in order {
        for k in 0..l.record.key_joints.len().min(2) {
            let pts: Vec<(f64, f64)> = (0..l.record.len())
                .map(|t| map(l.record.key_position(t, k)))
                .collect();
            c.polyline(&pts, l.width, l.colour);
        }
    }
    // Each distinct hand target once, with its reach radius.
    let mut seen: Vec<[f64; 3]> = Vec::new();
    for frame in &rec.targets {
        for &p in frame.iter().take(2) {
            if seen
                .iter()
                .any(|q| (0..3).all(|d| (q[d] - p[d]).abs() < 1e-6))
            {
                continue;
            }
            seen.push(p);
            let (x, y) = map(p);
            c.disc(x, y, 7.0, GREEN);
            let rad = (fr.map(p[0] + CONTACT_RADIUS_M, p[1]).0 - x).abs();
            for a in 0..64 {
                let t = a as f64 / 64.0 * std::f64::consts::TAU;
                c.disc(x + rad * t.cos(), y + rad * t.sin(), 1.0, GREEN);
            }
        }
    }
    let mut items: Vec<(String, Rgb)> = layers
        .iter()
        .map(|l| (format!("hand paths, {}", l.label), l.colour))
        .collect();
    items.push(("targets and their 0.1 m reach radius".into(), GREEN));
    items.push((
        format!(
            "skeleton ({}) at {} frames, darker = later",
            first.label,
            snaps.len()
        ),
        GREY,
    ));
    let ly = h as f64 - 60.0;
    for (i, (label, col)) in items.iter().enumerate() {
        let x = 70.0 + (i % 2) as f64 * 420.0;
        let y = ly + (i / 2) as f64 * 22.0;
        c.line((x, y + 4.0), (x + 30.0, y + 4.0), 3.0, *col);
        c.text(x + 38.0, y, label, 1, BLACK);
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| format!("{}", dir.display()))?;
        }
    }
    c.save_png(path)
}
