//! Small charts written straight to PNG (no plotting dependency): a title, axes with ticks,
//! numeric labels and axis names in a built-in 3×5 pixel font (capitals, digits and a little
//! punctuation), and a legend of coloured swatches with the series' names. A line chart (one
//! polyline with markers per series) and a scatter chart (sized, labelled markers). Enough
//! for the benchmark figures.

use std::path::Path;

use anyhow::{Context, Result};

pub struct Series {
    pub name: String,
    pub rgb: [u8; 3],
    pub points: Vec<(f64, f64)>,
}

const W: usize = 720;
const H: usize = 460;
const LEFT: usize = 70;
const RIGHT: usize = 20;
const TOP: usize = 64;
const BOTTOM: usize = 50;

/// 3×5 glyphs, rows top to bottom, bits left to right.
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        'x' => [0, 5, 2, 5, 0],
        'A' => [2, 5, 7, 5, 5],
        'B' => [6, 5, 6, 5, 6],
        'C' => [3, 4, 4, 4, 3],
        'D' => [6, 5, 5, 5, 6],
        'E' => [7, 4, 6, 4, 7],
        'F' => [7, 4, 6, 4, 4],
        'G' => [3, 4, 5, 5, 3],
        'H' => [5, 5, 7, 5, 5],
        'I' => [7, 2, 2, 2, 7],
        'J' => [1, 1, 1, 5, 2],
        'K' => [5, 5, 6, 5, 5],
        'L' => [4, 4, 4, 4, 7],
        'M' => [5, 7, 7, 5, 5],
        'N' => [6, 5, 5, 5, 5],
        'O' => [2, 5, 5, 5, 2],
        'P' => [6, 5, 6, 4, 4],
        'Q' => [2, 5, 5, 6, 3],
        'R' => [6, 5, 6, 5, 5],
        'S' => [3, 4, 2, 1, 6],
        'T' => [7, 2, 2, 2, 2],
        'U' => [5, 5, 5, 5, 7],
        'V' => [5, 5, 5, 5, 2],
        'W' => [5, 5, 7, 7, 5],
        'X' => [5, 5, 2, 5, 5],
        'Y' => [5, 5, 2, 2, 2],
        'Z' => [7, 1, 2, 4, 7],
        ' ' => [0; 5],
        '(' => [1, 2, 2, 2, 1],
        ')' => [4, 2, 2, 2, 4],
        '/' => [1, 1, 2, 4, 4],
        ':' => [0, 2, 0, 2, 0],
        '%' => [5, 1, 2, 4, 5],
        ',' => [0, 0, 0, 2, 4],
        _ => return None,
    })
}

struct Canvas(Vec<u8>);

impl Canvas {
    fn put(&mut self, x: i64, y: i64, rgb: [u8; 3]) {
        if (0..W as i64).contains(&x) && (0..H as i64).contains(&y) {
            let i = 3 * (y as usize * W + x as usize);
            self.0[i..i + 3].copy_from_slice(&rgb);
        }
    }
    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, rgb: [u8; 3]) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.put(xx, yy, rgb);
            }
        }
    }
    /// Thick line by stamping squares along it.
    fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), rgb: [u8; 3], thick: i64) {
        let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
        for i in 0..=n {
            let t = i as f64 / n as f64;
            let (x, y) = (x0 + t * (x1 - x0), y0 + t * (y1 - y0));
            self.rect(x.round() as i64 - thick / 2, y.round() as i64 - thick / 2, thick, thick, rgb);
        }
    }
    /// Text in the 3×5 font at `scale` (letters as capitals, but `x` between digits);
    /// characters without a glyph leave a gap.
    fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, rgb: [u8; 3]) {
        for (k, c) in s.chars().enumerate() {
            if let Some(g) = glyph(c).or_else(|| glyph(c.to_ascii_uppercase())) {
                for (row, bits) in g.iter().enumerate() {
                    for col in 0..3 {
                        if bits >> (2 - col) & 1 == 1 {
                            self.rect(x + (k as i64 * 4 + col) * scale, y + row as i64 * scale, scale, scale, rgb);
                        }
                    }
                }
            }
        }
    }
}

fn label(v: f64) -> String {
    if v.abs() >= 100.0 || v == v.round() { format!("{v:.0}") } else { format!("{v:.1}") }
}

/// Words on a chart.
pub struct Labels<'a> {
    pub title: &'a str,
    pub x: &'a str,
    pub y: &'a str,
}

/// Width in pixels of `s` in the 3×5 font at `scale`.
fn text_width(s: &str, scale: i64) -> i64 {
    4 * scale * s.chars().count() as i64 - scale
}

/// Axis ranges (in log-10 units on a log axis) and the plot area's mapping.
struct Axes {
    x: (f64, f64),
    y: (f64, f64),
    log_x: bool,
    log_y: bool,
}

impl Axes {
    /// Ranges over `points` (non-finite and, on a log axis, non-positive values left out):
    /// a log axis spans whole decades; a linear y axis starts at 0 when `y_from_zero`, else
    /// gets a 5% margin.
    fn fit(points: impl Iterator<Item = (f64, f64)>, log_x: bool, log_y: bool, y_from_zero: bool) -> Self {
        let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for (x, y) in points.filter(|p| p.0.is_finite() && p.1.is_finite() && (!log_x || p.0 > 0.0) && (!log_y || p.1 > 0.0)) {
            let (x, y) = (if log_x { x.log10() } else { x }, if log_y { y.log10() } else { y });
            (x_lo, x_hi, y_lo, y_hi) = (x_lo.min(x), x_hi.max(x), y_lo.min(y), y_hi.max(y));
        }
        if x_lo > x_hi {
            (x_lo, x_hi, y_lo, y_hi) = (0.0, 1.0, 0.0, 1.0);
        }
        let decades = |lo: f64, hi: f64| (lo.floor(), hi.ceil().max(lo.floor() + 1.0));
        if log_y {
            (y_lo, y_hi) = decades(y_lo, y_hi);
        } else if y_from_zero {
            y_lo = y_lo.min(0.0);
            y_hi = if y_hi > y_lo { y_hi * 1.05 } else { y_lo + 1.0 };
        } else {
            let pad = ((y_hi - y_lo) * 0.05).max(0.5);
            (y_lo, y_hi) = ((y_lo - pad).floor(), (y_hi + pad).ceil());
        }
        if log_x {
            (x_lo, x_hi) = decades(x_lo, x_hi);
        } else if x_hi <= x_lo {
            x_hi = x_lo + 1.0;
        }
        Self { x: (x_lo, x_hi), y: (y_lo, y_hi), log_x, log_y }
    }

    fn keeps(&self, (x, y): (f64, f64)) -> bool {
        x.is_finite() && y.is_finite() && (!self.log_x || x > 0.0) && (!self.log_y || y > 0.0)
    }

    fn to_px(&self, x: f64, y: f64) -> (f64, f64) {
        let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
        let (x, y) = (if self.log_x { x.log10() } else { x }, if self.log_y { y.log10() } else { y });
        (LEFT as f64 + (x - self.x.0) / (self.x.1 - self.x.0) * pw, TOP as f64 + (1.0 - (y - self.y.0) / (self.y.1 - self.y.0)) * ph)
    }

    /// Tick values: each decade on a log axis, six even steps on a linear one.
    fn ticks(lo: f64, hi: f64, log: bool) -> Vec<f64> {
        if log { (lo as i64..=hi as i64).map(|e| 10f64.powi(e as i32)).collect() } else { (0..=5).map(|i| lo + (hi - lo) * i as f64 / 5.0).collect() }
    }

    /// Grid lines, tick labels and the two axes.
    fn draw(&self, c: &mut Canvas) {
        let (grey, ink) = ([200, 200, 200], [40, 40, 40]);
        let lo = |(lo, _): (f64, f64), log: bool| if log { 10f64.powf(lo) } else { lo };
        for x in Self::ticks(self.x.0, self.x.1, self.log_x) {
            let (px, _) = self.to_px(x, lo(self.y, self.log_y));
            c.line((px, TOP as f64), (px, (H - BOTTOM) as f64), grey, 1);
            let text = label(x);
            let width = 8 * text.len() as i64;
            c.text((px as i64 - width / 2).min((W - 2) as i64 - width), (H - BOTTOM + 8) as i64, &text, 2, ink);
        }
        for y in Self::ticks(self.y.0, self.y.1, self.log_y) {
            let (_, py) = self.to_px(lo(self.x, self.log_x), y);
            c.line((LEFT as f64, py), ((W - RIGHT) as f64, py), grey, 1);
            let text = label(y);
            c.text(LEFT as i64 - 8 - 8 * text.len() as i64, py as i64 - 5, &text, 2, ink);
        }
        c.line((LEFT as f64, TOP as f64), (LEFT as f64, (H - BOTTOM) as f64), ink, 2);
        c.line((LEFT as f64, (H - BOTTOM) as f64), ((W - RIGHT) as f64, (H - BOTTOM) as f64), ink, 2);
    }
}

/// Title, legend (swatch and name per entry), axis names; then writes the PNG.
fn finish(mut c: Canvas, path: &Path, labels: &Labels<'_>, legend: &[(&str, [u8; 3])]) -> Result<()> {
    let ink = [40, 40, 40];
    c.text(LEFT as i64, 8, labels.title, 2, ink);
    let mut x = LEFT as i64;
    for (name, rgb) in legend {
        c.rect(x, 30, 28, 10, *rgb);
        c.text(x + 36, 30, name, 2, ink);
        x += 36 + text_width(name, 2) + 24;
    }
    c.text(8, TOP as i64 - 16, labels.y, 2, ink);
    c.text(LEFT as i64 + (W - LEFT - RIGHT) as i64 / 2 - text_width(labels.x, 2) / 2, (H - 18) as i64, labels.x, 2, ink);
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), W as u32, H as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.write_header().and_then(|mut w| w.write_image_data(&c.0)).with_context(|| format!("writing {}", path.display()))
}

/// Draws the series on shared axes (linear x, log-10 y when `log_y`) and writes a PNG.
pub fn line_chart(path: &Path, labels: &Labels<'_>, series: &[Series], log_y: bool) -> Result<()> {
    let mut c = Canvas(vec![255; W * H * 3]);
    let axes = Axes::fit(series.iter().flat_map(|s| s.points.iter().copied()), false, log_y, true);
    axes.draw(&mut c);
    for s in series {
        let mut prev: Option<(f64, f64)> = None;
        for &(x, y) in s.points.iter().filter(|&&p| axes.keeps(p)) {
            let p = axes.to_px(x, y);
            if let Some(q) = prev {
                c.line(q, p, s.rgb, 3);
            }
            c.rect(p.0 as i64 - 4, p.1 as i64 - 4, 9, 9, s.rgb);
            prev = Some(p);
        }
    }
    let legend: Vec<(&str, [u8; 3])> = series.iter().map(|s| (s.name.as_str(), s.rgb)).collect();
    finish(c, path, labels, &legend)
}

/// One marker of a scatter chart: a filled square of half-width `radius_px` with a short
/// label to its right.
pub struct Dot {
    pub x: f64,
    pub y: f64,
    pub radius_px: i64,
    pub label: String,
}

/// Markers of one colour, named in the legend.
pub struct DotSeries {
    pub name: String,
    pub rgb: [u8; 3],
    pub dots: Vec<Dot>,
}

/// Draws labelled markers (x on a log-10 axis when `log_x`, y linear over the data's range)
/// and writes a PNG: NEPHELE's Fig. 13 kind of picture.
pub fn scatter_chart(path: &Path, labels: &Labels<'_>, series: &[DotSeries], log_x: bool) -> Result<()> {
    let mut c = Canvas(vec![255; W * H * 3]);
    let axes = Axes::fit(series.iter().flat_map(|s| s.dots.iter().map(|d| (d.x, d.y))), log_x, false, false);
    axes.draw(&mut c);
    // Markers first; then each label right of its marker, moved up or down a line at a time
    // until it clears the labels already placed (clustered points stay readable).
    let mut placed: Vec<(i64, i64, &str)> = Vec::new();
    for s in series {
        for d in s.dots.iter().filter(|d| axes.keeps((d.x, d.y))) {
            let (px, py) = axes.to_px(d.x, d.y);
            let r = d.radius_px.clamp(2, 24);
            c.rect(px as i64 - r, py as i64 - r, 2 * r + 1, 2 * r + 1, s.rgb);
            let (x, w) = (px as i64 + r + 4, text_width(&d.label, 2));
            let clear = |y: i64| placed.iter().all(|&(lx, ly, l)| x + w < lx || lx + text_width(l, 2) < x || y + 10 < ly || ly + 10 < y);
            let y = [0, 12, -12, 24, -24, 36, -36].iter().map(|dy| py as i64 - 5 + dy).find(|&y| clear(y)).unwrap_or(py as i64 - 5);
            placed.push((x, y, &d.label));
        }
    }
    for &(x, y, text) in &placed {
        c.text(x, y, text, 2, [40, 40, 40]);
    }
    let legend: Vec<(&str, [u8; 3])> = series.iter().map(|s| (s.name.as_str(), s.rgb)).collect();
    finish(c, path, labels, &legend)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chart_is_a_png_with_the_series_colours() {
        let dir = std::env::temp_dir().join(format!("nephele-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("chart.png");
        let series = [
            Series { name: "a".into(), rgb: [220, 40, 40], points: vec![(1.0, 1000.0), (2.0, 300.0), (3.0, 90.0)] },
            Series { name: "b".into(), rgb: [40, 40, 220], points: vec![(1.0, 20.0), (2.0, 12.0), (3.0, f64::NAN)] },
        ];
        line_chart(&path, &Labels { title: "Title", x: "x axis", y: "y axis (log)" }, &series, true).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (W as u32, H as u32));
        for s in &series {
            let count = buf.chunks_exact(3).filter(|p| p == &s.rgb).count();
            assert!(count > 200, "{}: {count} pixels", s.name);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn scatter_is_a_png_with_sized_markers() {
        let dir = std::env::temp_dir().join(format!("nephele-scatter-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("scatter.png");
        let dot = |x, y, radius_px| Dot { x, y, radius_px, label: "T0.1".into() };
        let series = [
            DotSeries { name: "small".into(), rgb: [220, 40, 40], dots: vec![dot(5.0, 30.0, 3)] },
            DotSeries { name: "big".into(), rgb: [40, 40, 220], dots: vec![dot(200.0, 33.0, 12), dot(f64::NAN, 1.0, 5), dot(-1.0, 2.0, 5)] },
        ];
        scatter_chart(&path, &Labels { title: "PSNR against ms", x: "ms (log)", y: "PSNR dB" }, &series, true).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        let count = |rgb: [u8; 3]| buf.chunks_exact(3).filter(|p| *p == rgb).count();
        // Markers (7² and 25² pixels) plus the legend swatch (28×10); the bad dots are left out.
        assert_eq!(count([220, 40, 40]), 49 + 280);
        assert_eq!(count([40, 40, 220]), 625 + 280);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
