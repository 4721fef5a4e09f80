//! Pictures of rollouts: skeleton snapshots (`host-sim render`) and error
//! curves (`host-sim plot-errors`), as PNG.

pub mod canvas;
mod font;

use anyhow::{bail, Context, Result};
use phasegate_controller::layout::{JOINTS, PARENTS};
use std::path::PathBuf;

use crate::rollout::compare::{compare, root_relative};
use crate::rollout::Rollout;
use canvas::{
    tick_label, ticks, Canvas, Frame2, Rgb, BLACK, BLUE, GREEN, GREY, GRID, ORANGE, WHITE,
};

/// Joints of the character's left side (drawn lighter in side views).
fn is_left(j: usize) -> bool {
    (1..=5).contains(&j) || (17..=23).contains(&j)
}

fn lighten(c: Rgb) -> Rgb {
    c.map(|v| ((u16::from(v) + 2 * 255) / 3) as u8)
}

/// `n` frame indices spread over `len` frames, first and last included.
pub fn snapshot_frames(len: usize, n: usize) -> Vec<usize> {
    match (len, n) {
        (0, _) | (_, 0) => Vec::new(),
        (1, _) | (_, 1) => vec![len - 1],
        _ => (0..n)
            .map(|i| ((i * (len - 1)) as f64 / (n - 1) as f64).round() as usize)
            .collect(),
    }
}

/// `host-sim render`.
#[derive(Debug, clap::Args)]
pub struct RenderArgs {
    /// The rollout (.npz), drawn in blue.
    pub a: PathBuf,
    /// A second rollout of the same script, overlaid in orange.
    pub b: Option<PathBuf>,
    /// Where to write the PNG.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Number of snapshots.
    #[arg(long, default_value_t = 10, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
    pub snapshots: usize,
    /// OMG rollouts: also write an animated GIF of the rollout here (one
    /// GIF frame every 3 rollout frames).
    #[arg(long, value_name = "PATH")]
    pub gif: Option<PathBuf>,
}

/// `host-sim render`: side views of the skeleton at regular frames (each in
/// its own root frame, facing right) above a top view of the world with the
/// root paths and the same snapshots.
pub fn render_cmd(args: &RenderArgs) -> Result<()> {
    if crate::omg_rollout::record::OmgRecord::is_record(&args.a)? {
        return render_omg(args);
    }
    if let Some(gif) = &args.gif {
        bail!(
            "--gif {}: only OMG reaching rollouts have a GIF",
            gif.display()
        );
    }
    let a = Rollout::read(&args.a)?;
    let b = args.b.as_ref().map(|p| Rollout::read(p)).transpose()?;
    if let Some(b) = &b {
        if b.len() != a.len() {
            bail!("the rollouts have {} and {} frames", a.len(), b.len());
        }
    }
    if a.is_empty() {
        bail!("{} has no frames", args.a.display());
    }
    let names = [
        args.a.display().to_string(),
        args.b
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_default(),
    ];
    let c = render(&a, b.as_ref(), &names, args.snapshots.clamp(1, 40));
    c.save_png(&args.out)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// Draws the picture `render_cmd` writes.
pub fn render(a: &Rollout, b: Option<&Rollout>, names: &[String; 2], snapshots: usize) -> Canvas {
    let (w, h) = (1600.0, 1120.0);
    let mut c = Canvas::new(w as usize, h as usize, WHITE);
    let frames = snapshot_frames(a.len(), snapshots);
    // A thick, B thin on top of it: where they agree, both stay visible.
    let runs: Vec<(&Rollout, Rgb, f64)> = std::iter::once((a, BLUE, 4.0))
        .chain(b.map(|b| (b, ORANGE, 1.5)))
        .collect();

    c.text(20.0, 14.0, &format!("A (blue): {}", names[0]), 2, BLUE);
    if b.is_some() {
        c.text(20.0, 36.0, &format!("B (orange): {}", names[1]), 2, ORANGE);
    }
    let info = format!("{} frames at {} fps", a.len(), a.frame_rate);
    c.text(
        w - 20.0 - Canvas::text_width(&info, 2),
        14.0,
        &info,
        2,
        BLACK,
    );

    // Side views: one slot per snapshot, root-relative, facing right.
    let (top, bottom) = (90.0, 500.0);
    c.text(
        20.0,
        top - 26.0,
        "side view, each pose in its own root frame (facing right; left limbs lighter)",
        2,
        BLACK,
    );
    let rel = |r: &Rollout, f: usize| root_relative(&r.poses[f]);
    let mut ymax: f64 = 1.0;
    let mut zext: f64 = 1.0;
    for &(r, _, _) in &runs {
        for &f in &frames {
            for p in rel(r, f) {
                ymax = ymax.max(p[1]);
                zext = zext.max(p[2].abs());
            }
        }
    }
    let slot = (w - 40.0) / frames.len().max(1) as f64;
    let scale = ((bottom - top - 30.0) / (ymax + 5.0)).min((slot - 10.0) / (2.0 * zext + 10.0));
    for (k, &f) in frames.iter().enumerate() {
        let cx = 20.0 + slot * (k as f64 + 0.5);
        let ground = bottom - 20.0;
        c.line(
            (cx - slot / 2.0 + 6.0, ground),
            (cx + slot / 2.0 - 6.0, ground),
            1.0,
            GREY,
        );
        let map = |p: [f64; 3]| (cx + p[2] * scale, ground - p[1] * scale);
        for &(r, col, width) in &runs {
            let joints = rel(r, f);
            draw_bones(&mut c, &joints, map, col, width);
        }
        let label = format!("frame {f}");
        c.text(
            cx - Canvas::text_width(&label, 2) / 2.0,
            ground + 6.0,
            &label,
            2,
            BLACK,
        );
    }

    // Top view of the world.
    let panel = (60.0, 560.0, w - 40.0, h - 40.0);
    c.text(20.0, panel.1 - 30.0, "top view of the world (+z up, +x to the left, so turns look as they are): root paths and the same snapshots", 2, BLACK);
    let (mut xr, mut zr) = (
        (f64::INFINITY, f64::NEG_INFINITY),
        (f64::INFINITY, f64::NEG_INFINITY),
    );
    for &(r, _, _) in &runs {
        for p in &r.poses {
            for j in p.joint_positions.iter().chain([&p.root_position]) {
                xr = (xr.0.min(-j[0]), xr.1.max(-j[0]));
                zr = (zr.0.min(j[2]), zr.1.max(j[2]));
            }
        }
    }
    let pad = 20.0;
    let fr = Frame2::new(
        panel,
        (xr.0 - pad, xr.1 + pad),
        (zr.0 - pad, zr.1 + pad),
        true,
    );
    grid(&mut c, &fr, "x (units)", "z (units)", true);
    for &(r, col, width) in &runs {
        let path: Vec<(f64, f64)> = r
            .poses
            .iter()
            .map(|p| fr.map(-p.root_position[0], p.root_position[2]))
            .collect();
        c.polyline(&path, width / 2.0 + 0.5, lighten(col));
        for &f in &frames {
            let p = &r.poses[f];
            draw_bones(
                &mut c,
                &p.joint_positions,
                |j| fr.map(-j[0], j[2]),
                col,
                width / 2.0 + 0.5,
            );
            let root = p.root_position;
            let tip = [
                root[0] + 25.0 * p.facing[0],
                0.0,
                root[2] + 25.0 * p.facing[1],
            ];
            c.line(
                fr.map(-root[0], root[2]),
                fr.map(-tip[0], tip[2]),
                2.0,
                BLACK,
            );
        }
        if let Some(p) = r.poses.first() {
            let (x, y) = fr.map(-p.root_position[0], p.root_position[2]);
            c.disc(x, y, 5.0, col);
        }
    }
    c.rect(panel.0, panel.1, panel.2, panel.3, GREY);
    c
}

fn draw_bones(
    c: &mut Canvas,
    joints: &[[f64; 3]; JOINTS],
    map: impl Fn([f64; 3]) -> (f64, f64),
    col: Rgb,
    width: f64,
) {
    // Left side first, so the right side is drawn over it.
    for left in [true, false] {
        for (j, &p) in PARENTS.iter().enumerate() {
            let Ok(p) = usize::try_from(p) else { continue };
            if is_left(j) == left {
                let shade = if left { lighten(col) } else { col };
                c.line(map(joints[p]), map(joints[j]), width, shade);
            }
        }
    }
    let head = map(joints[16]);
    c.disc(head.0, head.1, width + 1.0, col);
}

/// Grid lines and tick labels of a frame; axis titles under and beside it.
/// With `negate_x` the frame's x is minus the data's (the top view draws +x
/// to the left) and the labels show the data's value.
pub(crate) fn grid(c: &mut Canvas, fr: &Frame2, xlabel: &str, ylabel: &str, negate_x: bool) {
    let (l, t, r, b) = fr.px;
    let xt = ticks(fr.x.0, fr.x.1, 8);
    let yt = ticks(fr.y.0, fr.y.1, 5);
    let xs = xt.get(1).zip(xt.first()).map_or(1.0, |(a, b)| a - b);
    let ys = yt.get(1).zip(yt.first()).map_or(1.0, |(a, b)| a - b);
    for &v in &xt {
        let (x, _) = fr.map(v, fr.y.0);
        c.line((x, t), (x, b), 1.0, GRID);
        let s = tick_label(if negate_x { -v } else { v }, xs);
        c.text(x - Canvas::text_width(&s, 1) / 2.0, b + 4.0, &s, 1, GREY);
    }
    for &v in &yt {
        let (_, y) = fr.map(fr.x.0, v);
        c.line((l, y), (r, y), 1.0, GRID);
        let s = tick_label(v, ys);
        c.text(l - Canvas::text_width(&s, 1) - 4.0, y - 3.0, &s, 1, GREY);
    }
    if !xlabel.is_empty() {
        c.text(
            (l + r) / 2.0 - Canvas::text_width(xlabel, 1) / 2.0,
            b + 16.0,
            xlabel,
            1,
            BLACK,
        );
    }
    if !ylabel.is_empty() {
        c.text(l, t - 12.0, ylabel, 1, BLACK);
    }
}

/// `host-sim plot-errors`.
#[derive(Debug, clap::Args)]
pub struct PlotErrorsArgs {
    /// Reference rollout (.npz).
    pub a: PathBuf,
    /// Rollout compared with it (.npz).
    pub b: PathBuf,
    /// Where to write the PNG.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

/// `host-sim plot-errors`: root-relative joint error (mean, p99, max), root
/// drift, heading drift and phase error against frame number.
pub fn plot_errors_cmd(args: &PlotErrorsArgs) -> Result<()> {
    let (a, b) = (Rollout::read(&args.a)?, Rollout::read(&args.b)?);
    let cmp =
        compare(&a, &b).with_context(|| format!("{} vs {}", args.a.display(), args.b.display()))?;
    let title = format!("{}  vs  {}", args.b.display(), args.a.display());
    let c = plot_errors(&cmp, &title);
    c.save_png(&args.out)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// Draws the picture `plot_errors_cmd` writes.
pub fn plot_errors(cmp: &crate::rollout::Comparison, title: &str) -> Canvas {
    let (w, h) = (1400.0, 1000.0);
    let mut c = Canvas::new(w as usize, h as usize, WHITE);
    c.text(20.0, 14.0, title, 2, BLACK);
    let n = cmp.frames.len();
    let fr = &cmp.frames;
    type Series<'a> = (&'a str, Rgb, Vec<f64>);
    let panels: [(&str, Vec<Series>); 3] = [
        (
            "root-relative joint position error (units)",
            vec![
                ("max", ORANGE, fr.iter().map(|f| f.joint_max).collect()),
                ("p99", GREEN, fr.iter().map(|f| f.joint_p99).collect()),
                ("mean", BLUE, fr.iter().map(|f| f.joint_mean).collect()),
            ],
        ),
        (
            "root position drift (units)",
            vec![("drift", BLUE, fr.iter().map(|f| f.root_drift).collect())],
        ),
        (
            "heading drift and phase error (rad)",
            vec![
                ("phase", ORANGE, fr.iter().map(|f| f.phase_error).collect()),
                (
                    "heading",
                    BLUE,
                    fr.iter().map(|f| f.heading_drift).collect(),
                ),
            ],
        ),
    ];
    let (top, bottom, left, right) = (60.0, h - 30.0, 90.0, w - 30.0);
    let ph = (bottom - top) / 3.0;
    for (i, (name, series)) in panels.iter().enumerate() {
        let pt = top + ph * i as f64 + 24.0;
        let pb = top + ph * (i + 1) as f64 - 24.0;
        let ymax = series
            .iter()
            .flat_map(|s| s.2.iter().copied())
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        let ymax = if ymax > 0.0 { ymax * 1.08 } else { 1e-6 };
        let fr2 = Frame2::new(
            (left, pt, right, pb),
            (0.0, n.max(2) as f64 - 1.0),
            (0.0, ymax),
            false,
        );
        grid(&mut c, &fr2, if i == 2 { "frame" } else { "" }, name, false);
        for (_, col, v) in series {
            let pts: Vec<(f64, f64)> = v
                .iter()
                .enumerate()
                .map(|(k, &y)| fr2.map(k as f64, y))
                .collect();
            c.polyline(&pts, 1.5, *col);
        }
        // Legend, top right.
        let mut x = right - 10.0;
        for (name, col, _) in series.iter() {
            x -= Canvas::text_width(name, 2) + 30.0;
            c.line((x, pt + 10.0), (x + 20.0, pt + 10.0), 3.0, *col);
            c.text(x + 24.0, pt + 3.0, name, 2, *col);
        }
        c.rect(left, pt, right, pb, GREY);
    }
    c
}

/// `host-sim render` of OMG reaching rollouts: the front and side views of
/// [`crate::omg_rollout::picture`], and with `--gif` its animation.
fn render_omg(args: &RenderArgs) -> Result<()> {
    use crate::omg_rollout::picture::{gif_bytes, png_bytes, Layer};
    use crate::omg_rollout::record::OmgRecord;
    let a = OmgRecord::read(&args.a)?;
    let b = args.b.as_ref().map(|p| OmgRecord::read(p)).transpose()?;
    if a.is_empty() {
        bail!("{} has no frames", args.a.display());
    }
    if let Some(b) = &b {
        crate::omg_rollout::compare(&a, b).with_context(|| {
            format!(
                "{} vs {}",
                args.a.display(),
                args.b.as_deref().unwrap_or(&args.a).display()
            )
        })?;
    }
    let name = |p: &std::path::Path| {
        p.file_name().map_or_else(
            || p.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        )
    };
    let mut layers = vec![Layer {
        record: &a,
        label: name(&args.a),
        colour: canvas::BLUE,
        width: 1.5,
    }];
    if let (Some(b), Some(path)) = (&b, &args.b) {
        layers.push(Layer {
            record: b,
            label: name(path),
            colour: canvas::ORANGE,
            width: 4.0,
        });
    }
    // The picture and the animation together, or neither.
    let mut outputs = exporter::atomic::Outputs::new();
    for p in std::iter::once(&args.out).chain(&args.gif) {
        if let Some(d) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            outputs.dir(d);
        }
    }
    let title = "OMG reaching rollout: front and side views";
    outputs.add(
        &args.out,
        png_bytes(&layers, title, args.snapshots.clamp(1, 40), &args.out)?,
    );
    if let Some(gif) = &args.gif {
        outputs.add(gif, gif_bytes(&layers, "OMG reaching rollout", gif, 3)?);
    }
    outputs.commit()?;
    for p in std::iter::once(&args.out).chain(&args.gif) {
        println!("wrote {}", p.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn snapshots_cover_first_and_last() {
        assert_eq!(snapshot_frames(600, 3), vec![0, 300, 599]);
        assert_eq!(snapshot_frames(5, 1), vec![4]);
        assert!(snapshot_frames(0, 4).is_empty());
    }
}
