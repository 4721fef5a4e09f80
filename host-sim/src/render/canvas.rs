//! A small RGB raster: anti-aliasing-free lines, discs, text and PNG output.
//! Enough for skeleton snapshots and error plots, with no font or GUI deps.

use anyhow::{Context, Result};
use std::path::Path;

use super::font::{glyph, ADVANCE, HEIGHT};

/// An RGB colour.
pub type Rgb = [u8; 3];

/// White.
pub const WHITE: Rgb = [255, 255, 255];
/// Black.
pub const BLACK: Rgb = [20, 20, 20];
/// Light grey for grids.
pub const GRID: Rgb = [225, 225, 225];
/// Mid grey for axes and the ground.
pub const GREY: Rgb = [140, 140, 140];
/// First rollout.
pub const BLUE: Rgb = [30, 90, 200];
/// Second rollout.
pub const ORANGE: Rgb = [225, 100, 20];
/// A third series in plots.
pub const GREEN: Rgb = [30, 150, 60];

/// An image being drawn.
pub struct Canvas {
    width: usize,
    height: usize,
    px: Vec<Rgb>,
}

impl Canvas {
    /// A `width x height` canvas filled with `bg`.
    pub fn new(width: usize, height: usize, bg: Rgb) -> Self {
        Canvas {
            width,
            height,
            px: vec![bg; width * height],
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Sets one pixel (ignored outside the canvas).
    pub fn set(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            self.px[y as usize * self.width + x as usize] = c;
        }
    }

    /// A filled disc.
    pub fn disc(&mut self, cx: f64, cy: f64, r: f64, c: Rgb) {
        let r2 = r * r;
        for y in (cy - r).floor() as i64..=(cy + r).ceil() as i64 {
            for x in (cx - r).floor() as i64..=(cx + r).ceil() as i64 {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                if dx * dx + dy * dy <= r2 {
                    self.set(x, y, c);
                }
            }
        }
    }

    /// A line `width` pixels wide (a disc stamped every half pixel).
    pub fn line(&mut self, a: (f64, f64), b: (f64, f64), width: f64, c: Rgb) {
        if !(a.0.is_finite() && a.1.is_finite() && b.0.is_finite() && b.1.is_finite()) {
            return;
        }
        let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
        let steps = (len * 2.0).ceil().clamp(1.0, 1e5) as usize;
        let r = (width / 2.0).max(0.5);
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            if r <= 0.5 {
                self.set(x.round() as i64, y.round() as i64, c);
            } else {
                self.disc(x, y, r, c);
            }
        }
    }

    /// A polyline.
    pub fn polyline(&mut self, pts: &[(f64, f64)], width: f64, c: Rgb) {
        for w in pts.windows(2) {
            self.line(w[0], w[1], width, c);
        }
    }

    /// Outline of a rectangle.
    pub fn rect(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, c: Rgb) {
        self.polyline(&[(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)], 1.0, c);
    }

    /// Text with its top-left corner at `(x, y)`, each font pixel `scale`
    /// pixels wide.
    pub fn text(&mut self, x: f64, y: f64, s: &str, scale: usize, c: Rgb) {
        let (x0, y0) = (x.round() as i64, y.round() as i64);
        let sc = scale.max(1) as i64;
        for (i, ch) in s.chars().enumerate() {
            let gx = x0 + (i * ADVANCE) as i64 * sc;
            for (row, bits) in glyph(ch).iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        for dy in 0..sc {
                            for dx in 0..sc {
                                self.set(gx + col * sc + dx, y0 + row as i64 * sc + dy, c);
                            }
                        }
                    }
                }
            }
        }
    }

    /// Width of `s` drawn at `scale`, pixels.
    pub fn text_width(s: &str, scale: usize) -> f64 {
        (s.chars().count() * ADVANCE * scale.max(1)) as f64
    }

    /// Height of a line of text at `scale`, pixels.
    pub fn text_height(scale: usize) -> f64 {
        (HEIGHT * scale.max(1)) as f64
    }

    /// Writes an 8-bit RGB PNG.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        exporter::atomic::write_atomic(path, &self.png_bytes()?)
            .with_context(|| format!("writing {}", path.display()))
    }

    /// The 8-bit RGB PNG [`Canvas::save_png`] writes.
    pub fn png_bytes(&self) -> Result<Vec<u8>> {
        let mut bytes = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut bytes, self.width as u32, self.height as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header()?;
            let data: Vec<u8> = self.px.iter().flatten().copied().collect();
            w.write_image_data(&data)?;
        }
        Ok(bytes)
    }
}

/// Maps data coordinates to pixels inside a panel, same scale on both axes
/// when asked (for views of space), y up.
#[derive(Clone, Copy, Debug)]
pub struct Frame2 {
    /// Panel left, top, right, bottom in pixels.
    pub px: (f64, f64, f64, f64),
    /// Data x range.
    pub x: (f64, f64),
    /// Data y range.
    pub y: (f64, f64),
}

impl Frame2 {
    /// A frame showing `x` and `y` ranges in the panel; with `equal`, the
    /// ranges are widened so one data unit has the same size on both axes.
    pub fn new(px: (f64, f64, f64, f64), x: (f64, f64), y: (f64, f64), equal: bool) -> Self {
        let widen = |r: (f64, f64)| {
            if r.1 - r.0 > 1e-9 {
                r
            } else {
                (r.0 - 1.0, r.1 + 1.0)
            }
        };
        let (mut x, mut y) = (widen(x), widen(y));
        if equal {
            let (pw, ph) = (px.2 - px.0, px.3 - px.1);
            let s = ((x.1 - x.0) / pw).max((y.1 - y.0) / ph);
            let (cx, cy) = ((x.0 + x.1) / 2.0, (y.0 + y.1) / 2.0);
            x = (cx - s * pw / 2.0, cx + s * pw / 2.0);
            y = (cy - s * ph / 2.0, cy + s * ph / 2.0);
        }
        Frame2 { px, x, y }
    }

    /// Pixel of a data point.
    pub fn map(&self, x: f64, y: f64) -> (f64, f64) {
        let (l, t, r, b) = self.px;
        (
            l + (x - self.x.0) / (self.x.1 - self.x.0) * (r - l),
            b - (y - self.y.0) / (self.y.1 - self.y.0) * (b - t),
        )
    }
}

/// About `n` round tick values covering `[lo, hi]`.
pub fn ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    let span = (hi - lo).abs().max(1e-12);
    let raw = span / n.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let start = (lo / step).ceil() as i64;
    let end = (hi / step).floor() as i64;
    (start..=end).map(|i| i as f64 * step).collect()
}

/// A tick label with as few digits as the step needs.
pub fn tick_label(v: f64, step: f64) -> String {
    let digits = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    format!("{v:.digits$}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round() {
        assert_eq!(ticks(0.0, 10.0, 5), vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        assert_eq!(ticks(0.0, 0.9, 4), vec![0.0, 0.5]);
        assert_eq!(ticks(-3.0, 3.0, 3), vec![-2.0, 0.0, 2.0]);
        assert_eq!(tick_label(0.2, 0.2), "0.2");
        assert_eq!(tick_label(600.0, 100.0), "600");
    }

    #[test]
    fn frames_map_corners_and_keep_aspect() {
        let f = Frame2::new((0.0, 0.0, 200.0, 100.0), (0.0, 10.0), (0.0, 10.0), true);
        let (x0, y0) = f.map(0.0, 0.0);
        let (x1, y1) = f.map(10.0, 10.0);
        assert!(((x1 - x0) - (y0 - y1)).abs() < 1e-9);
        let mut c = Canvas::new(20, 10, WHITE);
        c.line((-5.0, 5.0), (50.0, 5.0), 3.0, BLACK);
        c.text(0.0, 0.0, "Az09.:-", 1, BLACK);
        assert_eq!(c.px[5 * 20 + 10], BLACK);
    }
}
