//! Pictures of reaching rollouts, drawn with `plotters`: a PNG with a front
//! view (x horizontal, y up, root space) and a side view (z forward
//! horizontal, y up) of the first rollout's skeleton at a few frames, both
//! hands' paths of every rollout and the hand targets with their reach
//! radius ([`draw`], which `host-sim render` and `host-sim demo` call); and
//! an animated GIF of the same two views frame by frame ([`draw_gif`],
//! `host-sim render --gif`).
//!
//! Text is set in DejaVu Sans, compiled into the binary
//! (`host-sim/assets/DejaVuSans.ttf`, from Debian's `fonts-dejavu-core`
//! 2.37; licence in `assets/DejaVuSans-LICENSE.txt`) and handed to plotters'
//! `ab_glyph` renderer, so no system font and no fontconfig is ever looked
//! up: the pictures come out the same on a machine with no fonts at all.
//! Both views keep 1 m the same length on both axes and in both panels.

use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use anyhow::{anyhow, bail, Context, Result};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use plotters::style::FontStyle;

use super::record::OmgRecord;
use super::CONTACT_RADIUS_M;
use crate::render::canvas::Rgb;

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

/// The embedded font (DejaVu Sans 2.37, Bitstream Vera licence).
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
/// The family the font is registered as (plotters' default for axis labels).
const FAMILY: &str = "sans-serif";

/// Size of [`draw`]'s PNG, pixels.
pub const PNG_SIZE: (u32, u32) = (1200, 800);
/// Size of [`draw_gif`]'s frames, pixels.
pub const GIF_SIZE: (u32, u32) = (900, 480);

const TARGET: RGBColor = RGBColor(30, 150, 60);
const INK: RGBColor = RGBColor(20, 20, 20);
const MUTED: RGBColor = RGBColor(95, 95, 95);
const GRID_BOLD: RGBColor = RGBColor(222, 222, 222);
const GRID_LIGHT: RGBColor = RGBColor(242, 242, 242);
const FRAME_LINE: RGBColor = RGBColor(190, 190, 190);

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Registers the embedded font with plotters (once per process).
fn font() -> Result<()> {
    static OK: OnceLock<bool> = OnceLock::new();
    let ok =
        *OK.get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        bail!("the embedded font (DejaVuSans.ttf) does not parse")
    }
}

/// A plotters error as an `anyhow` one.
fn pe<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("drawing failed: {e}")
}

fn rgb(c: Rgb) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

/// `c` moved towards white by `f` (0: `c`, 1: white).
fn lighter(c: RGBColor, f: f64) -> RGBColor {
    let m = |v: u8| (f64::from(v) + (255.0 - f64::from(v)) * f).round() as u8;
    RGBColor(m(c.0), m(c.1), m(c.2))
}

/// A view: a point in root space to the panel's (horizontal, up).
type View = fn([f64; 3]) -> (f64, f64);

/// Front view: (x, y); side view: (z, y).
const VIEWS: [View; 2] = [|p| (p[0], p[1]), |p| (p[2], p[1])];

/// The hands drawn: key joints 0 (left) and 1 (right), as far as they exist.
fn hands(r: &OmgRecord) -> usize {
    r.key_joints.len().min(2)
}

/// Frame `t` of `r`, or its last one if it is shorter.
fn at(r: &OmgRecord, t: usize) -> usize {
    t.min(r.len().saturating_sub(1))
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|d| (a[d] - b[d]).powi(2)).sum::<f64>().sqrt()
}

/// Axis-aligned bounds of everything drawn over the whole rollout.
#[derive(Clone, Copy, Debug)]
struct Bounds {
    lo: [f64; 3],
    hi: [f64; 3],
}

fn bounds(layers: &[Layer<'_>]) -> Result<Bounds> {
    let mut b = Bounds {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };
    let mut grow = |p: [f64; 3], r: f64| {
        if p.iter().all(|v| v.is_finite()) {
            for (d, &v) in p.iter().enumerate() {
                b.lo[d] = b.lo[d].min(v - r);
                b.hi[d] = b.hi[d].max(v + r);
            }
        }
    };
    for l in layers {
        for frame in &l.record.positions {
            frame.iter().for_each(|&p| grow(p, 0.0));
        }
        for frame in &l.record.targets {
            frame
                .iter()
                .take(2)
                .for_each(|&p| grow(p, CONTACT_RADIUS_M));
        }
    }
    if !(0..3).all(|d| b.lo[d] <= b.hi[d]) {
        bail!("the rollout has no finite joint position to draw");
    }
    Ok(b)
}

/// Sizes of one kind of picture: fonts, margins, axis areas (pixels).
#[derive(Clone, Copy, Debug)]
struct Style {
    size: (u32, u32),
    /// Height of the title band.
    title_h: u32,
    title_font: u32,
    /// Height above each panel's plotting area (the panel's own title).
    panel_title_h: u32,
    panel_font: u32,
    tick_font: u32,
    desc_font: u32,
    legend_font: u32,
    /// Width of the y tick label area, height of the x one.
    y_label_w: u32,
    x_label_h: u32,
    /// Left and right margin of each panel; bottom margin of both.
    margin: (u32, u32, u32),
    /// Bounds of the legend column's width.
    legend_w: (u32, u32),
    /// Metres of room added around the data on every side.
    pad_m: f64,
}

const PNG_STYLE: Style = Style {
    size: PNG_SIZE,
    title_h: 46,
    title_font: 24,
    panel_title_h: 30,
    panel_font: 17,
    tick_font: 14,
    desc_font: 15,
    legend_font: 15,
    y_label_w: 62,
    x_label_h: 50,
    margin: (6, 18, 8),
    legend_w: (220, 430),
    pad_m: 0.06,
};

const GIF_STYLE: Style = Style {
    size: GIF_SIZE,
    title_h: 32,
    title_font: 18,
    panel_title_h: 24,
    panel_font: 15,
    tick_font: 13,
    desc_font: 14,
    legend_font: 14,
    y_label_w: 50,
    x_label_h: 40,
    margin: (4, 12, 6),
    legend_w: (200, 330),
    pad_m: 0.04,
};

/// Where the two panels go: the width of each panel's area and the data
/// ranges that give both the same metres per pixel on both axes.
#[derive(Clone, Debug)]
struct Views {
    /// Width of the front panel's area, of the side panel's area.
    widths: (u32, u32),
    x: Range<f64>,
    z: Range<f64>,
    y: Range<f64>,
}

impl Views {
    /// The views of `b` in `width` x `height` pixels (both panels with their
    /// label areas and margins) for `st`.
    fn new(b: &Bounds, st: &Style, width: u32, height: u32) -> Views {
        let over_w = f64::from(st.y_label_w + st.margin.0 + st.margin.1);
        let over_h = f64::from(st.panel_title_h + st.x_label_h + st.margin.2);
        let span = |d: usize| (b.hi[d] - b.lo[d] + 2.0 * st.pad_m).max(0.1);
        let (wx, wz, hy) = (span(0), span(2), span(1));
        let plot_w = (f64::from(width) - 2.0 * over_w).max(20.0);
        let plot_h = (f64::from(height) - over_h).max(20.0);
        // Pixels per metre: the tighter of the two directions.
        let s = (plot_w / (wx + wz)).min(plot_h / hy);
        // Spare width is shared equally (in metres) by the two panels.
        let spare = (plot_w - s * (wx + wz)) / 2.0;
        let (pw_x, pw_z) = (s * wx + spare, s * wz + spare);
        let centred = |d: usize, px: f64| {
            let c = (b.lo[d] + b.hi[d]) / 2.0;
            // plotters maps a range onto `px - 1` pixel steps.
            let half = (px - 1.0).max(1.0) / s / 2.0;
            c - half..c + half
        };
        let front_w = (pw_x + over_w).round() as u32;
        Views {
            widths: (front_w, width.saturating_sub(front_w)),
            x: centred(0, pw_x.round()),
            z: centred(2, pw_z.round()),
            y: centred(1, plot_h.round()),
        }
    }

    /// Pixel columns of the front and side plotting areas (for tests).
    #[cfg(test)]
    fn plot_columns(&self, st: &Style) -> [Range<u32>; 2] {
        let l = st.margin.0 + st.y_label_w;
        let (a, b) = self.widths;
        [l..a - st.margin.1, a + l..a + b - st.margin.1]
    }
}

/// Tick labels for the ticks plotters puts on `range` (at most `n`), all
/// with as many decimals as the finest of them needs.
fn tick_format(range: Range<f64>, n: usize) -> impl Fn(&f64) -> String {
    let ticks = RangedCoordf64::from(range).key_points(n);
    let decimals = (0..4)
        .find(|&d| {
            let k = 10f64.powi(d);
            ticks.iter().all(|v| ((v * k).round() - v * k).abs() < 1e-6)
        })
        .unwrap_or(4) as usize;
    move |v: &f64| {
        let s = format!("{v:.decimals$}");
        // "-0.0" is "0.0".
        match s.strip_prefix('-') {
            Some(t) if t.chars().all(|c| c == '0' || c == '.') => t.to_string(),
            _ => s,
        }
    }
}

/// One panel: its title above, axes with tick labels in metres and axis
/// titles, over `x` by `y`.
fn panel<'a, 'b>(
    area: &'a Area<'b>,
    st: &Style,
    title: &str,
    xdesc: &str,
    x: Range<f64>,
    y: Range<f64>,
) -> Result<Chart<'a, 'b>> {
    let (xr, yr) = (x.clone(), y.clone());
    let mut chart = ChartBuilder::on(area)
        .margin_top(st.panel_title_h)
        .margin_left(st.margin.0)
        .margin_right(st.margin.1)
        .margin_bottom(st.margin.2)
        .x_label_area_size(st.x_label_h)
        .y_label_area_size(st.y_label_w)
        .build_cartesian_2d(x, y)
        .map_err(pe)?;
    let (pw, ph) = chart.plotting_area().dim_in_pixel();
    let (nx, ny) = ((pw / 55).max(2) as usize, (ph / 45).max(2) as usize);
    let (fx, fy) = (tick_format(xr, nx), tick_format(yr, ny));
    chart
        .configure_mesh()
        .x_labels(nx)
        .y_labels(ny)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .bold_line_style(GRID_BOLD)
        .light_line_style(GRID_LIGHT)
        .max_light_lines(1)
        .axis_style(FRAME_LINE)
        .label_style((FAMILY, st.tick_font).into_font().color(&MUTED))
        .axis_desc_style((FAMILY, st.desc_font).into_font().color(&INK))
        .x_desc(xdesc)
        .y_desc("y (m, up)")
        .draw()
        .map_err(pe)?;
    // The panel's title, centred over its plotting area.
    let (px0, _) = chart.plotting_area().get_base_pixel();
    let (ax0, _) = area.get_base_pixel();
    let style = TextStyle::from((FAMILY, st.panel_font).into_font())
        .color(&INK)
        .pos(Pos::new(HPos::Center, VPos::Bottom));
    area.draw_text(
        title,
        &style,
        (px0 - ax0 + pw as i32 / 2, st.panel_title_h as i32 - 7),
    )
    .map_err(pe)?;
    Ok(chart)
}

/// A polyline in data coordinates.
fn polyline(chart: &mut Chart<'_, '_>, pts: Vec<(f64, f64)>, style: ShapeStyle) -> Result<()> {
    chart
        .draw_series(std::iter::once(PathElement::new(pts, style)))
        .map_err(pe)?;
    Ok(())
}

/// The reach circle of a target at `c` (radius [`CONTACT_RADIUS_M`]), in
/// data coordinates.
fn circle_points(c: (f64, f64)) -> Vec<(f64, f64)> {
    (0..=72)
        .map(|i| {
            let a = f64::from(i) / 72.0 * std::f64::consts::TAU;
            (
                c.0 + CONTACT_RADIUS_M * a.cos(),
                c.1 + CONTACT_RADIUS_M * a.sin(),
            )
        })
        .collect()
}

/// Bones of `frame` (joint to parent) in `view`.
fn bones(
    chart: &mut Chart<'_, '_>,
    r: &OmgRecord,
    frame: &[[f64; 3]],
    view: View,
    style: ShapeStyle,
) -> Result<()> {
    let segs = r.parents.iter().enumerate().filter_map(|(j, &p)| {
        let p = usize::try_from(p).ok()?;
        let (a, b) = (frame.get(j)?, frame.get(p)?);
        Some(PathElement::new(vec![view(*a), view(*b)], style))
    });
    chart.draw_series(segs).map_err(pe)?;
    Ok(())
}

/// What a legend entry shows before its text.
#[derive(Clone, Copy, Debug)]
enum Swatch {
    /// A line of this colour and width.
    Line(RGBColor, u32),
    /// Grey lines from light to dark.
    Ramp,
    /// A target: a dot and its reach circle.
    Target,
    /// A target filled in this colour.
    Reached(RGBColor),
}

/// One legend entry: its swatch, its text, and an optional second line.
struct Entry {
    swatch: Swatch,
    text: String,
    note: Option<String>,
}

fn entry(swatch: Swatch, text: impl Into<String>, note: Option<String>) -> Entry {
    Entry {
        swatch,
        text: text.into(),
        note,
    }
}

/// Width of `s` in the embedded font at `size` pixels.
fn text_w(s: &str, size: u32) -> Result<u32> {
    let (w, _) = FontDesc::new(FontFamily::Name(FAMILY), f64::from(size), FontStyle::Normal)
        .box_size(s)
        .map_err(pe)?;
    Ok(w)
}

/// `s`, shortened with an ellipsis to fit `max` pixels at `size`.
fn fit(s: &str, size: u32, max: u32) -> Result<String> {
    if text_w(s, size)? <= max {
        return Ok(s.to_string());
    }
    let mut chars: Vec<char> = s.chars().collect();
    while !chars.is_empty() {
        chars.pop();
        let t: String = chars.iter().collect::<String>() + "…";
        if text_w(&t, size)? <= max {
            return Ok(t);
        }
    }
    Ok("…".into())
}

const SWATCH_W: i32 = 34;
const LEGEND_PAD: i32 = 10;

/// The legend column's width for `entries` and `extra` lines (within
/// `st.legend_w`).
fn legend_width(st: &Style, entries: &[Entry], extra: &[&str]) -> Result<u32> {
    let mut w = 0;
    for e in entries {
        w = w.max(text_w(&e.text, st.legend_font)?);
        if let Some(n) = &e.note {
            w = w.max(text_w(n, st.legend_font - 2)?);
        }
    }
    w += SWATCH_W as u32 + 8;
    for t in extra {
        w = w.max(text_w(t, st.legend_font)?);
    }
    Ok((w + 2 * LEGEND_PAD as u32 + 4).clamp(st.legend_w.0, st.legend_w.1))
}

/// Draws a boxed legend of `entries` at `(x, y)`, `w` wide, under an
/// optional `head` line.
fn legend(
    area: &Area<'_>,
    st: &Style,
    (x, y): (i32, i32),
    w: u32,
    head: Option<&str>,
    entries: &[Entry],
) -> Result<()> {
    let f = st.legend_font as i32;
    let font = TextStyle::from((FAMILY, st.legend_font).into_font()).color(&INK);
    let note_font = TextStyle::from((FAMILY, st.legend_font - 2).into_font()).color(&MUTED);
    let line_h = f + 7;
    let note_h = f + 2;
    let rows: i32 = entries
        .iter()
        .map(|e| line_h + if e.note.is_some() { note_h } else { 0 })
        .sum::<i32>()
        + if head.is_some() { line_h + 4 } else { 0 };
    let (x1, y1) = (x + w as i32, y + rows + 2 * LEGEND_PAD - 4);
    area.draw(&Rectangle::new([(x, y), (x1, y1)], WHITE.filled()))
        .map_err(pe)?;
    area.draw(&Rectangle::new([(x, y), (x1, y1)], FRAME_LINE))
        .map_err(pe)?;
    let text_x = x + LEGEND_PAD + SWATCH_W + 8;
    let text_width = (x1 - LEGEND_PAD - text_x).max(10) as u32;
    let mut cy = y + LEGEND_PAD;
    if let Some(h) = head {
        let h = fit(h, st.legend_font, w - 2 * LEGEND_PAD as u32)?;
        area.draw_text(&h, &font, (x + LEGEND_PAD, cy))
            .map_err(pe)?;
        cy += line_h + 4;
    }
    for e in entries {
        let (sx0, sx1, sy) = (x + LEGEND_PAD, x + LEGEND_PAD + SWATCH_W, cy + f / 2);
        match e.swatch {
            Swatch::Line(c, width) => {
                area.draw(&PathElement::new(
                    vec![(sx0, sy), (sx1, sy)],
                    c.stroke_width(width),
                ))
                .map_err(pe)?;
            }
            Swatch::Ramp => {
                for i in 0..4 {
                    let g = (200 - 50 * i) as u8;
                    let (a, b) = (sx0 + i * SWATCH_W / 4, sx0 + (i + 1) * SWATCH_W / 4);
                    area.draw(&PathElement::new(
                        vec![(a, sy + 4 - 3 * i), (b, sy + 1 - 3 * i)],
                        RGBColor(g, g, g).stroke_width(2),
                    ))
                    .map_err(pe)?;
                }
            }
            Swatch::Target => {
                let c = ((sx0 + sx1) / 2, sy);
                area.draw(&Circle::new(c, f / 2 + 1, TARGET.stroke_width(1)))
                    .map_err(pe)?;
                area.draw(&Circle::new(c, 3, TARGET.filled())).map_err(pe)?;
            }
            Swatch::Reached(col) => {
                let c = ((sx0 + sx1) / 2, sy);
                area.draw(&Circle::new(c, f / 2 + 1, col.mix(0.3).filled()))
                    .map_err(pe)?;
                area.draw(&Circle::new(c, f / 2 + 1, TARGET.stroke_width(1)))
                    .map_err(pe)?;
            }
        }
        let t = fit(&e.text, st.legend_font, text_width)?;
        area.draw_text(&t, &font, (text_x, cy)).map_err(pe)?;
        cy += line_h;
        if let Some(n) = &e.note {
            let n = fit(n, st.legend_font - 2, text_width)?;
            area.draw_text(&n, &note_font, (text_x, cy - 4))
                .map_err(pe)?;
            cy += note_h;
        }
    }
    Ok(())
}

/// The title, left in the title band (shortened to fit).
fn title_text(root: &Area<'_>, st: &Style, title: &str, max: u32) -> Result<()> {
    let font = TextStyle::from((FAMILY, st.title_font).into_font()).color(&INK);
    let t = fit(title, st.title_font, max)?;
    let y = (st.title_h as i32 - st.title_font as i32) / 2;
    root.draw_text(&t, &font, (16, y)).map_err(pe)?;
    Ok(())
}

/// Creates the parent directory of `path` (if it has one).
fn parent_dir(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).with_context(|| {
                format!(
                    "cannot write {}: cannot create {}",
                    path.display(),
                    dir.display()
                )
            })?;
        }
    }
    Ok(())
}

/// Distinct positions among `pts` (within a micrometre), in order.
fn distinct(pts: impl IntoIterator<Item = [f64; 3]>) -> Vec<[f64; 3]> {
    let mut seen: Vec<[f64; 3]> = Vec::new();
    for p in pts {
        if p.iter().all(|v| v.is_finite())
            && !seen
                .iter()
                .any(|q| (0..3).all(|d| (q[d] - p[d]).abs() < 1e-6))
        {
            seen.push(p);
        }
    }
    seen
}

/// The two panels (front, side) of `views`, on their areas.
fn charts<'a, 'b>(
    front: &'a Area<'b>,
    side: &'a Area<'b>,
    st: &Style,
    views: &Views,
) -> Result<[Chart<'a, 'b>; 2]> {
    Ok([
        panel(
            front,
            st,
            "front view",
            "x (m, root space)",
            views.x.clone(),
            views.y.clone(),
        )?,
        panel(
            side,
            st,
            "side view",
            "z (m, forward)",
            views.z.clone(),
            views.y.clone(),
        )?,
    ])
}

/// Where everything of a picture goes.
struct Layout {
    entries: Vec<Entry>,
    /// Width of the legend column.
    legend_w: u32,
    /// Width of the panels' part (left of the legend).
    body_w: u32,
    views: Views,
}

impl Layout {
    fn new(b: &Bounds, st: &Style, entries: Vec<Entry>, extra: &[&str]) -> Result<Layout> {
        let legend_w = legend_width(st, &entries, extra)?;
        let body_w = st.size.0 - legend_w - 16;
        let views = Views::new(b, st, body_w, st.size.1 - st.title_h);
        Ok(Layout {
            entries,
            legend_w,
            body_w,
            views,
        })
    }

    /// Top left corner of the legend.
    fn legend_at(&self, st: &Style) -> (i32, i32) {
        (
            (self.body_w + 8) as i32,
            (st.title_h + st.panel_title_h) as i32,
        )
    }
}

/// The layout of [`draw`]'s picture.
fn png_layout(layers: &[Layer<'_>], first: &Layer<'_>, snapshots: usize) -> Result<Layout> {
    let mut entries: Vec<Entry> = layers
        .iter()
        .map(|l| {
            entry(
                Swatch::Line(rgb(l.colour), line_width(l.width)),
                format!("hand paths: {}", l.label),
                None,
            )
        })
        .collect();
    entries.push(entry(
        Swatch::Target,
        "hand targets",
        Some(format!("circle: {CONTACT_RADIUS_M} m reach radius")),
    ));
    entries.push(entry(
        Swatch::Ramp,
        format!("skeleton: {}", first.label),
        Some(format!("{snapshots} frames, lighter = earlier")),
    ));
    Layout::new(&bounds(layers)?, &PNG_STYLE, entries, &[])
}

/// A layer's line width in whole pixels.
fn line_width(w: f64) -> u32 {
    if w.is_finite() {
        (w.round() as u32).clamp(1, 5)
    } else {
        1
    }
}

/// Draws `layers` (at least one) under `title` to the PNG `path` (its
/// directory is created if missing; written atomically): the front and the
/// side view with the first layer's skeleton at `snapshots` frames (lighter
/// when earlier), both hands' paths of every layer (wider layers first)
/// and each distinct hand target once with its reach radius, a legend in a
/// column on the right.
pub fn draw(layers: &[Layer<'_>], title: &str, snapshots: usize, path: &Path) -> Result<()> {
    let bytes = png_bytes(layers, title, snapshots, path)?;
    parent_dir(path)?;
    exporter::atomic::write_atomic(path, &bytes)
}

/// The PNG [`draw`] writes to `path` (named in errors only), as bytes, for
/// a command that writes it together with other files.
pub fn png_bytes(
    layers: &[Layer<'_>],
    title: &str,
    snapshots: usize,
    path: &Path,
) -> Result<Vec<u8>> {
    let Some(first) = layers.first() else {
        bail!("cannot draw {}: no rollout to draw", path.display());
    };
    font()?;
    let st = PNG_STYLE;
    let (w, h) = st.size;
    let rec = first.record;
    let snaps = crate::render::snapshot_frames(rec.len(), snapshots);
    let lay = png_layout(layers, first, snaps.len())?;
    let mut buf = vec![255u8; 3 * (w * h) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        title_text(&root, &st, title, w - 32)?;
        let body = root.margin(st.title_h, 0, 0, 0);
        let (front, rest) = body.split_horizontally(lay.views.widths.0);
        let (side, _) = rest.split_horizontally(lay.views.widths.1);
        let mut charts = charts(&front, &side, &st, &lay.views)?;
        let mut order: Vec<&Layer<'_>> = layers.iter().collect();
        order.sort_by(|a, b| b.width.total_cmp(&a.width));
        let targets = distinct(rec.targets.iter().flat_map(|f| f.iter().take(2).copied()));
        for (chart, view) in charts.iter_mut().zip(VIEWS) {
            // The first rollout's skeleton at a few frames, darker when later.
            for (i, &t) in snaps.iter().enumerate() {
                let g = (200.0 - 160.0 * i as f64 / (snaps.len().max(2) - 1) as f64) as u8;
                let style = RGBColor(g, g, g).stroke_width(2);
                bones(chart, rec, &rec.positions[t], view, style)?;
            }
            for l in &order {
                let style = rgb(l.colour).stroke_width(line_width(l.width));
                for k in 0..hands(l.record) {
                    let pts = (0..l.record.len())
                        .map(|t| view(l.record.key_position(t, k)))
                        .collect();
                    polyline(chart, pts, style)?;
                }
            }
            // Each distinct hand target once, with its reach radius.
            for &p in &targets {
                let c = view(p);
                polyline(chart, circle_points(c), TARGET.stroke_width(1))?;
                chart
                    .draw_series(std::iter::once(Circle::new(c, 4, TARGET.filled())))
                    .map_err(pe)?;
            }
        }
        drop(charts);
        legend(
            &root,
            &st,
            lay.legend_at(&st),
            lay.legend_w,
            None,
            &lay.entries,
        )?;
        root.present().map_err(pe)?;
    }
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(png::Compression::Best);
        enc.set_adaptive_filter(png::AdaptiveFilterType::Adaptive);
        let mut wr = enc.write_header()?;
        wr.write_image_data(&buf)?;
    }
    Ok(bytes)
}

/// The widest of the per-layer lines [`draw_gif`] writes under a label.
const GIF_NOTE_WIDEST: &str = "to targets: left 0.000 m, right 0.000 m";

/// The layout of [`draw_gif`]'s frames.
fn gif_layout(layers: &[Layer<'_>], first: &Layer<'_>) -> Result<Layout> {
    let mut entries: Vec<Entry> = layers
        .iter()
        .map(|l| {
            // The widest note sizes the legend; each frame writes its own.
            let note = Some(GIF_NOTE_WIDEST.to_string());
            entry(Swatch::Line(rgb(l.colour), 3), l.label.clone(), note)
        })
        .collect();
    entries.push(entry(
        Swatch::Target,
        "hand targets now",
        Some(format!("circle: {CONTACT_RADIUS_M} m reach radius")),
    ));
    entries.push(entry(
        Swatch::Reached(rgb(first.colour)),
        "reached",
        Some(format!("a hand within {CONTACT_RADIUS_M} m, in its colour")),
    ));
    Layout::new(
        &bounds(layers)?,
        &GIF_STYLE,
        entries,
        &["frame 00000 of 00000   t = 000.00 s"],
    )
}

/// Frames per second of `r` (60 if it states none that makes sense).
fn fps(r: &OmgRecord) -> f64 {
    if r.frame_rate.is_finite() && r.frame_rate > 0.0 {
        r.frame_rate
    } else {
        60.0
    }
}

/// The GIF frame delay of one frame every `every` frames at `fps`, ms.
fn gif_delay_ms(every: usize, fps: f64) -> u32 {
    (1000.0 * every as f64 / fps).round() as u32
}

/// Draws `layers` (at least one) under `title` as an animated GIF to `path`
/// (its directory is created if missing; written to a temporary file in it
/// and renamed): one GIF frame every `every` rollout frames, played at the
/// rollout's speed, each with the front and the side view over fixed axes:
/// every layer's skeleton at that frame (the first one bold, the others
/// thin over it), each hand's trail so far, the current hand targets with their
/// reach circle (filled in a layer's colour while that layer's hand is
/// within it), the frame number and time.
pub fn draw_gif(layers: &[Layer<'_>], title: &str, path: &Path, every: usize) -> Result<()> {
    let bytes = gif_bytes(layers, title, path, every)?;
    parent_dir(path)?;
    exporter::atomic::write_atomic(path, &bytes)
}

/// The GIF [`draw_gif`] writes to `path` (named in errors only), as bytes.
pub fn gif_bytes(layers: &[Layer<'_>], title: &str, path: &Path, every: usize) -> Result<Vec<u8>> {
    let Some(first) = layers.first() else {
        bail!("cannot draw {}: no rollout to draw", path.display());
    };
    if every == 0 {
        bail!(
            "cannot draw {}: one GIF frame every 0 frames",
            path.display()
        );
    }
    let n = layers.iter().map(|l| l.record.len()).max().unwrap_or(0);
    if layers.iter().any(|l| l.record.is_empty()) {
        bail!("cannot draw {}: a rollout has no frames", path.display());
    }
    font()?;
    let st = GIF_STYLE;
    let (w, h) = st.size;
    let fps = fps(first.record);
    let mut lay = gif_layout(layers, first)?;
    // plotters' GIF backend writes to a path: a temporary file of the
    // system's, removed when dropped, so an error leaves nothing behind.
    let tmp = tempfile::Builder::new()
        .prefix(".phasegate-")
        .suffix(".tmp.gif")
        .tempfile()
        .with_context(|| format!("cannot draw {}: no temporary file", path.display()))?;
    {
        let root = BitMapBackend::gif(tmp.path(), (w, h), gif_delay_ms(every, fps))
            .map_err(|e| anyhow!("cannot write {}: {e}", path.display()))?
            .into_drawing_area();
        let mut order: Vec<&Layer<'_>> = layers.iter().collect();
        order.sort_by(|a, b| b.width.total_cmp(&a.width));
        for t in (0..n).step_by(every) {
            root.fill(&WHITE).map_err(pe)?;
            title_text(&root, &st, title, w - 32)?;
            let body = root.margin(st.title_h, 0, 0, 0);
            let (front, rest) = body.split_horizontally(lay.views.widths.0);
            let (side, _) = rest.split_horizontally(lay.views.widths.1);
            let mut charts = charts(&front, &side, &st, &lay.views)?;
            let lead = first.record;
            let targets = distinct(lead.targets[at(lead, t)].iter().take(2).copied());
            for (chart, view) in charts.iter_mut().zip(VIEWS) {
                // Targets under everything, filled where a layer's hand is in reach.
                for &p in &targets {
                    let c = view(p);
                    for l in layers {
                        let r = l.record;
                        let tt = at(r, t);
                        let reached = (0..hands(r)).any(|k| {
                            let tk = r.targets[tt][k];
                            dist(tk, p) < 1e-6 && dist(r.key_position(tt, k), tk) < CONTACT_RADIUS_M
                        });
                        if reached {
                            let fill = rgb(l.colour).mix(0.3).filled();
                            chart
                                .draw_series(std::iter::once(Polygon::new(circle_points(c), fill)))
                                .map_err(pe)?;
                        }
                    }
                    polyline(chart, circle_points(c), TARGET.stroke_width(2))?;
                    chart
                        .draw_series(std::iter::once(Circle::new(c, 3, TARGET.filled())))
                        .map_err(pe)?;
                }
                // Trails so far, wider layers first.
                for l in &order {
                    let r = l.record;
                    let width = line_width(l.width).min(4);
                    let style = lighter(rgb(l.colour), 0.35).stroke_width(width);
                    for k in 0..hands(r) {
                        let pts = (0..=at(r, t)).map(|s| view(r.key_position(s, k))).collect();
                        polyline(chart, pts, style)?;
                    }
                }
                // Skeletons and hands: the first bold, the others thin on
                // top of it (so both show where they agree).
                for (i, l) in layers.iter().enumerate() {
                    let r = l.record;
                    let col = rgb(l.colour);
                    let (width, dot) = if i == 0 { (3, 4) } else { (1, 3) };
                    bones(
                        chart,
                        r,
                        &r.positions[at(r, t)],
                        view,
                        col.stroke_width(width),
                    )?;
                    let dots = (0..hands(r))
                        .map(|k| Circle::new(view(r.key_position(at(r, t), k)), dot, col.filled()));
                    chart.draw_series(dots).map_err(pe)?;
                }
            }
            drop(charts);
            for (e, l) in lay.entries.iter_mut().zip(layers) {
                let r = l.record;
                let tt = at(r, t);
                let d: Vec<String> = (0..hands(r))
                    .map(|k| {
                        let m = dist(r.key_position(tt, k), r.targets[tt][k]);
                        format!("{} {m:.3} m", ["left", "right"][k])
                    })
                    .collect();
                e.note = Some(format!("to targets: {}", d.join(", ")));
            }
            let head = format!("frame {t} of {}   t = {:.2} s", n - 1, t as f64 / fps);
            legend(
                &root,
                &st,
                lay.legend_at(&st),
                lay.legend_w,
                Some(&head),
                &lay.entries,
            )?;
            root.present()
                .map_err(|e| anyhow!("cannot write {}: {e}", path.display()))?;
        }
    }
    std::fs::read(tmp.path()).with_context(|| format!("cannot draw {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::canvas::{BLUE, ORANGE};

    const N: usize = 10;

    /// Five joints (root, spine, left hand, right hand, head) whose hands
    /// sweep towards two targets, the left one reached at the end; `dx`
    /// shifts the hands.
    fn record(dx: f64) -> OmgRecord {
        let positions = (0..N)
            .map(|t| {
                let s = t as f64 / (N - 1) as f64;
                vec![
                    [0.0, 1.0, 0.0],
                    [0.0, 1.5, 0.0],
                    [-0.5 + 0.2 * s + dx, 1.0 + 0.2 * s, 0.1 + 0.2 * s],
                    [0.2 + dx, 1.2 - 0.3 * s, 0.3 * s],
                    [0.0, 1.8, 0.05],
                ]
            })
            .collect();
        let targets = (0..N)
            .map(|t| {
                if t < N / 2 {
                    vec![[-0.4, 1.3, 0.2], [0.3, 1.0, 0.2]]
                } else {
                    vec![[-0.3, 1.2, 0.3], [0.4, 0.8, 0.4]]
                }
            })
            .collect();
        OmgRecord {
            frames: vec![Vec::new(); N],
            positions,
            targets,
            axes: vec![vec![[0.0; 6]; 2]; N],
            key_joints: vec![2, 3],
            parents: vec![-1, 0, 1, 1, 1],
            frame_rate: 60.0,
        }
    }

    fn layers<'a>(a: &'a OmgRecord, b: &'a OmgRecord) -> Vec<Layer<'a>> {
        vec![
            Layer {
                record: a,
                label: "fixed".into(),
                colour: BLUE,
                width: 1.5,
            },
            Layer {
                record: b,
                label: "float".into(),
                colour: ORANGE,
                width: 4.0,
            },
        ]
    }

    /// An RGB(A) image.
    struct Img {
        w: usize,
        px: Vec<[u8; 3]>,
    }

    impl Img {
        /// Pixels in columns `xs` and rows `ys` for which `f` holds.
        fn count(&self, xs: Range<u32>, ys: Range<u32>, f: impl Fn([u8; 3]) -> bool) -> usize {
            ys.flat_map(|y| xs.clone().map(move |x| (x, y)))
                .filter(|&(x, y)| f(self.px[y as usize * self.w + x as usize]))
                .count()
        }
    }

    fn read_png(path: &Path) -> (u32, u32, Img) {
        let d = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut r = d.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        let px = buf[..info.buffer_size()]
            .chunks(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let w = info.width as usize;
        (info.width, info.height, Img { w, px })
    }

    /// The frames of a GIF (RGB) and their delays (centiseconds).
    fn read_gif(path: &Path) -> (u32, u32, Vec<(Img, u16)>) {
        let mut o = gif::DecodeOptions::new();
        o.set_color_output(gif::ColorOutput::RGBA);
        let mut d = o.read_info(std::fs::File::open(path).unwrap()).unwrap();
        let (w, h) = (u32::from(d.width()), u32::from(d.height()));
        let mut frames = Vec::new();
        while let Some(f) = d.read_next_frame().unwrap() {
            // plotters writes whole frames.
            assert_eq!((u32::from(f.width), u32::from(f.height)), (w, h));
            let px = f.buffer.chunks(4).map(|c| [c[0], c[1], c[2]]).collect();
            frames.push((Img { w: w as usize, px }, f.delay));
        }
        (w, h, frames)
    }

    fn dark(p: [u8; 3]) -> bool {
        p.iter().all(|&v| v < 110)
    }

    /// No temporary file is left in `dir`.
    fn no_temporaries(dir: &Path) {
        for e in std::fs::read_dir(dir).unwrap() {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            assert!(!name.contains(".tmp"), "left behind: {name}");
        }
    }

    #[test]
    fn png_has_both_views_every_layer_targets_and_text() {
        let (a, b) = (record(0.0), record(0.05));
        let layers = layers(&a, &b);
        let dir = tempfile::tempdir().unwrap();
        // A missing directory is created (`host-sim demo` relies on it).
        let path = dir.path().join("new/reach.png");
        draw(&layers, "synthetic reach", 4, &path).unwrap();
        let (w, h, img) = read_png(&path);
        assert_eq!((w, h), PNG_SIZE);
        let st = PNG_STYLE;
        let lay = png_layout(&layers, &layers[0], 4).unwrap();
        let rows = st.title_h + st.panel_title_h..h - st.x_label_h - st.margin.2;
        for cols in lay.views.plot_columns(&st) {
            let at = |f: &dyn Fn([u8; 3]) -> bool| img.count(cols.clone(), rows.clone(), f);
            assert!(
                at(&|p| p != [255; 3]) > 2000,
                "panel {cols:?} is nearly blank"
            );
            for c in [BLUE, ORANGE] {
                assert!(at(&|p| p == c) > 30, "colour {c:?} missing in {cols:?}");
            }
            let target = [TARGET.0, TARGET.1, TARGET.2];
            assert!(at(&|p| p == target) > 100, "targets missing in {cols:?}");
            // The skeleton: greys from light (earlier) to dark (later).
            let grey = |lo: u8, hi: u8| {
                move |p: [u8; 3]| p[0] == p[1] && p[1] == p[2] && (lo..=hi).contains(&p[0])
            };
            assert!(
                at(&grey(150, 200)) > 50 && at(&grey(40, 90)) > 50,
                "skeleton in {cols:?}"
            );
        }
        // Text: the title band and the legend column are not blank.
        assert!(img.count(0..w, 0..st.title_h, dark) > 300, "no title text");
        let (lx, ly) = lay.legend_at(&st);
        let legend_cols = lx as u32..(lx as u32 + lay.legend_w).min(w);
        assert!(img.count(legend_cols.clone(), ly as u32..h, dark) > 500);
        for c in [BLUE, ORANGE] {
            assert!(img.count(legend_cols.clone(), ly as u32..h, |p| p == c) > 20);
        }
        // Equal aspect: the same pixels per metre on both axes and panels.
        let v = &lay.views;
        let [fc, sc] = v.plot_columns(&st);
        let ph = f64::from(rows.end - rows.start);
        let sy = (ph - 1.0) / (v.y.end - v.y.start);
        let sx = f64::from(fc.end - fc.start - 1) / (v.x.end - v.x.start);
        let sz = f64::from(sc.end - sc.start - 1) / (v.z.end - v.z.start);
        assert!(
            (sx / sy - 1.0).abs() < 0.01 && (sz / sy - 1.0).abs() < 0.01,
            "{sx} {sy} {sz}"
        );
        no_temporaries(&dir.path().join("new"));
    }

    #[test]
    fn gif_has_one_frame_every_n_at_the_rollout_speed() {
        let (a, b) = (record(0.0), record(0.05));
        let layers = layers(&a, &b);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("reach.gif");
        draw_gif(&layers, "synthetic reach", &path, 3).unwrap();
        let (w, h, frames) = read_gif(&path);
        assert_eq!((w, h), GIF_SIZE);
        // Frames 0, 3, 6, 9 of 10; 3 frames at 60 fps = 50 ms.
        assert_eq!(frames.len(), N.div_ceil(3));
        assert!(frames.iter().all(|(_, d)| *d == 5), "delays");
        let st = GIF_STYLE;
        let lay = gif_layout(&layers, &layers[0]).unwrap();
        let rows = st.title_h + st.panel_title_h..h - st.x_label_h - st.margin.2;
        for (img, _) in &frames {
            assert!(img.count(0..w, 0..st.title_h, dark) > 150, "no title text");
            for cols in lay.views.plot_columns(&st) {
                // The bold skeleton of the first layer (colours of a GIF
                // frame are quantised: near its colour).
                let near = |p: [u8; 3]| {
                    p.iter()
                        .zip(BLUE)
                        .all(|(&v, c)| (i32::from(v) - i32::from(c)).abs() < 24)
                };
                let n = img.count(cols.clone(), rows.clone(), near);
                assert!(n > 500, "first skeleton missing in {cols:?}: {n} pixels");
            }
        }
        // The frame counter changes.
        assert_ne!(frames[0].0.px, frames[1].0.px);
        // Every 4th frame of 10: frames 0, 4, 8.
        draw_gif(&layers, "synthetic reach", &path, 4).unwrap();
        assert_eq!(read_gif(&path).2.len(), 3);
        no_temporaries(dir.path());
    }

    #[test]
    fn nothing_to_draw_or_nowhere_to_write_fails_and_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("r.png");
        let gif = dir.path().join("r.gif");
        let e = draw(&[], "t", 3, &png).unwrap_err().to_string();
        assert!(e.contains("no rollout") && e.contains("r.png"), "{e}");
        let e = draw_gif(&[], "t", &gif, 3).unwrap_err().to_string();
        assert!(e.contains("no rollout") && e.contains("r.gif"), "{e}");
        let a = record(0.0);
        let one = [Layer {
            record: &a,
            label: "a".into(),
            colour: BLUE,
            width: 2.0,
        }];
        let e = draw_gif(&one, "t", &gif, 0).unwrap_err().to_string();
        assert!(e.contains("every 0"), "{e}");
        assert!(!png.exists() && !gif.exists());
        // A directory that cannot exist: its would-be parent is a file.
        let file = dir.path().join("plain-file");
        std::fs::write(&file, b"x").unwrap();
        for p in [file.join("r.png"), file.join("r.gif")] {
            let r = if p.extension().is_some_and(|e| e == "png") {
                draw(&one, "t", 3, &p)
            } else {
                draw_gif(&one, "t", &p, 3)
            };
            let e = format!("{:#}", r.unwrap_err());
            assert!(e.contains(&p.display().to_string()), "{e}");
        }
        // An unwritable destination (a directory of that name): the GIF's
        // temporary file is removed.
        let taken = dir.path().join("taken.gif");
        std::fs::create_dir(&taken).unwrap();
        let e = format!("{:#}", draw_gif(&one, "t", &taken, 3).unwrap_err());
        assert!(e.contains("taken.gif"), "{e}");
        no_temporaries(dir.path());
    }

    #[test]
    fn tick_labels_and_frame_delays() {
        let f = tick_format(-0.5..1.7, 8);
        let l = |v: f64| f(&v);
        assert_eq!(
            (l(0.4), l(-0.0), l(-0.2)),
            ("0.4".into(), "0.0".into(), "-0.2".into())
        );
        // Ticks 0.5 apart need one decimal, 0.01 apart two.
        assert_eq!(tick_format(0.0..1.0, 5)(&0.5), "0.5");
        assert_eq!(tick_format(0.0..0.1, 12)(&0.05), "0.05");
        assert_eq!(tick_format(0.0..0.1, 12)(&0.1), "0.10");
        assert_eq!(gif_delay_ms(3, 60.0), 50);
        assert_eq!(gif_delay_ms(1, 30.0), 33);
        let mut r = record(0.0);
        r.frame_rate = 0.0;
        assert_eq!(fps(&r), 60.0);
    }
}
