//! The benchmarks' charts, drawn with `plotters` and written twice: a PNG at the path given
//! and an SVG beside it (same name, `.svg`). A line chart (a polyline with markers per
//! series) and a scatter chart (sized, labelled markers, NEPHELE's Fig. 13 kind of picture).
//! Text is set in DejaVu Sans, built into the binary (`fonts/`, Bitstream Vera licence), so
//! a chart looks the same on a machine without fonts.
//!
//! A log axis is drawn as a linear axis over log₁₀ of the values, its ticks labelled with the
//! values themselves.

use std::{path::Path, sync::Once};

use anyhow::{Result, anyhow};
use plotters::{coord::Shift, prelude::*};

/// Every chart's size, pixels.
pub const SIZE: (u32, u32) = (720, 460);
const FONT: &str = "sans-serif";
static DEJAVU_SANS: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// One polyline of a line chart.
pub struct Series {
    pub name: String,
    pub rgb: [u8; 3],
    pub points: Vec<(f64, f64)>,
}

/// Words on a chart.
pub struct Labels<'a> {
    pub title: &'a str,
    pub x: &'a str,
    pub y: &'a str,
}

/// One marker of a scatter chart: a disc of `radius_px` with a short label to its right.
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

/// Draws `series` (y on a log-10 axis when `log_y`) to `path` (PNG) and its `.svg` twin.
pub fn line_chart(path: &Path, labels: &Labels<'_>, series: &[Series], log_y: bool) -> Result<()> {
    both(path, |root| draw_lines(root, labels, series, log_y), |root| draw_lines(root, labels, series, log_y))
}

/// Draws labelled markers (x on a log-10 axis when `log_x`) to `path` (PNG) and its `.svg`.
pub fn scatter_chart(path: &Path, labels: &Labels<'_>, series: &[DotSeries], log_x: bool) -> Result<()> {
    both(path, |root| draw_dots(root, labels, series, log_x), |root| draw_dots(root, labels, series, log_x))
}

fn draw_lines<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, labels: &Labels<'_>, series: &[Series], log_y: bool) -> Result<()> {
    let ty = |v: f64| if log_y { v.max(1e-12).log10() } else { v };
    let xs = series.iter().flat_map(|s| s.points.iter().map(|p| p.0));
    let ys = series.iter().flat_map(|s| s.points.iter().map(|p| ty(p.1)));
    let mut chart = frame(root, labels, range(xs), range(ys), false, log_y)?;
    for s in series {
        let colour = rgb(s.rgb);
        let points: Vec<(f64, f64)> = s.points.iter().map(|&(x, y)| (x, ty(y))).collect();
        chart
            .draw_series(LineSeries::new(points.clone(), colour.stroke_width(2)))
            .map_err(drawing)?
            .label(s.name.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
        chart.draw_series(points.iter().map(|&p| Circle::new(p, 3, colour.filled()))).map_err(drawing)?;
    }
    legend(&mut chart, SeriesLabelPosition::UpperRight)
}

fn draw_dots<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, labels: &Labels<'_>, series: &[DotSeries], log_x: bool) -> Result<()> {
    let tx = |v: f64| if log_x { v.max(1e-12).log10() } else { v };
    let xs = series.iter().flat_map(|s| s.dots.iter().map(|d| tx(d.x)));
    let (y_lo, y_hi) = range(series.iter().flat_map(|s| s.dots.iter().map(|d| d.y)));
    // Room below the lowest marker for the legend (lower right: slow and poor is the
    // emptiest corner of a speed/accuracy chart).
    let ys = (y_lo - 0.25 * (y_hi - y_lo), y_hi);
    let mut chart = frame(root, labels, range(xs), ys, log_x, false)?;
    let offsets = label_offsets(&chart, series, tx);
    for (s, offsets) in series.iter().zip(offsets) {
        let colour = rgb(s.rgb);
        let marker = |(d, dy): (&Dot, i32)| {
            let r = marker_radius(d);
            EmptyElement::at((tx(d.x), d.y)) + Circle::new((0, 0), r, colour.mix(0.75).filled()) + Text::new(d.label.clone(), (r + 3, dy), (FONT, 11).into_font())
        };
        chart
            .draw_series(s.dots.iter().zip(offsets).map(marker))
            .map_err(drawing)?
            .label(s.name.as_str())
            .legend(move |(x, y)| Circle::new((x + 8, y), 5, colour.filled()));
    }
    legend(&mut chart, SeriesLabelPosition::LowerRight)
}

fn marker_radius(d: &Dot) -> i32 {
    i32::try_from(d.radius_px.clamp(1, 60)).unwrap_or(1)
}

/// Vertical pixel offsets of the markers' labels (per series, per dot): each label right of
/// its marker, moved up or down in line steps until it overlaps no label placed before it.
fn label_offsets<DB: DrawingBackend>(chart: &Chart<'_, DB>, series: &[DotSeries], tx: impl Fn(f64) -> f64) -> Vec<Vec<i32>> {
    const LINE: i32 = 12;
    const CHAR_PX: i32 = 7;
    let mut placed: Vec<(i32, i32, i32, i32)> = Vec::new();
    let overlaps = |a: &(i32, i32, i32, i32), b: &(i32, i32, i32, i32)| a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3;
    series
        .iter()
        .map(|s| {
            s.dots
                .iter()
                .map(|d| {
                    let (px, py) = chart.backend_coord(&(tx(d.x), d.y));
                    let left = px + marker_radius(d) + 3;
                    let width = CHAR_PX * d.label.chars().count() as i32;
                    let rect = |dy: i32| (left, py + dy, left + width, py + dy + LINE);
                    let dy = (0..12)
                        .map(|k| -6 + if k % 2 == 0 { k / 2 * LINE } else { -(k + 1) / 2 * LINE })
                        .find(|&dy| !placed.iter().any(|p| overlaps(p, &rect(dy))))
                        .unwrap_or(-6);
                    placed.push(rect(dy));
                    dy
                })
                .collect()
        })
        .collect()
}

type Chart<'a, DB> = ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>>;

/// The title, axes, ticks and axis names over `x` × `y` (log-10 units on a log axis).
fn frame<'a, DB: DrawingBackend>(root: &'a DrawingArea<DB, Shift>, labels: &Labels<'_>, x: (f64, f64), y: (f64, f64), log_x: bool, log_y: bool) -> Result<Chart<'a, DB>> {
    root.fill(&WHITE).map_err(drawing)?;
    let mut chart = ChartBuilder::on(root)
        .caption(labels.title, (FONT, 17))
        .margin(14)
        .x_label_area_size(46)
        .y_label_area_size(64)
        .build_cartesian_2d(x.0..x.1, y.0..y.1)
        .map_err(drawing)?;
    let tick = |log: bool| move |v: &f64| number(if log { 10f64.powf(*v) } else { *v });
    chart
        .configure_mesh()
        .x_desc(labels.x)
        .y_desc(labels.y)
        .x_label_formatter(&tick(log_x))
        .y_label_formatter(&tick(log_y))
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 14))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(drawing)?;
    Ok(chart)
}

fn legend<'a, DB: DrawingBackend + 'a>(chart: &mut Chart<'a, DB>, at: SeriesLabelPosition) -> Result<()> {
    chart
        .configure_series_labels()
        .position(at)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 13))
        .draw()
        .map_err(drawing)
}

/// Draws with `png` on a PNG at `path` and with `svg` (the same drawing) on an SVG beside it.
fn both(
    path: &Path,
    png: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<()>,
    svg: impl FnOnce(&DrawingArea<SVGBackend<'_>, Shift>) -> Result<()>,
) -> Result<()> {
    register_font();
    let root = BitMapBackend::new(path, SIZE).into_drawing_area();
    png(&root)?;
    root.present().map_err(|e| anyhow!("writing {}: {e:?}", path.display()))?;
    let svg_path = path.with_extension("svg");
    let root = SVGBackend::new(&svg_path, SIZE).into_drawing_area();
    svg(&root)?;
    root.present().map_err(|e| anyhow!("writing {}: {e:?}", svg_path.display()))?;
    Ok(())
}

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is ours and valid; were it not, text would fall back to nothing, not fail.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, DEJAVU_SANS);
    });
}

/// The data's range padded by 6% on each side (a unit around a single value).
fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if hi > lo { 0.06 * (hi - lo) } else { 0.5 };
    (lo - pad, hi + pad)
}

/// A tick label: whole numbers plain, others to three significant digits.
fn number(v: f64) -> String {
    if v.abs() >= 100.0 || v == v.round() {
        format!("{v:.0}")
    } else if v.abs() >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

fn rgb([r, g, b]: [u8; 3]) -> RGBColor {
    RGBColor(r, g, b)
}

fn drawing<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing a chart: {e:?}")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both charts write a PNG of [`SIZE`] with ink in it, and an SVG with its text.
    #[test]
    fn charts_write_png_and_svg() {
        let dir = std::env::temp_dir().join(format!("nephele-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let labels = Labels { title: "a title", x: "x axis", y: "y axis" };
        let line = dir.join("line.png");
        line_chart(&line, &labels, &[Series { name: "one".into(), rgb: [214, 39, 40], points: vec![(1.0, 10.0), (2.0, 100.0), (3.0, 30.0)] }], true).unwrap();
        let scatter = dir.join("scatter.png");
        let dots = vec![Dot { x: 5.0, y: 30.0, radius_px: 6, label: "A".into() }, Dot { x: 50.0, y: 33.0, radius_px: 3, label: "B".into() }];
        scatter_chart(&scatter, &labels, &[DotSeries { name: "dots".into(), rgb: [31, 119, 180], dots }], true).unwrap();
        for png in [&line, &scatter] {
            let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(png).unwrap()));
            let mut reader = decoder.read_info().unwrap();
            let mut buf = vec![0; reader.output_buffer_size().unwrap()];
            let info = reader.next_frame(&mut buf).unwrap();
            assert_eq!((info.width, info.height), SIZE);
            let dark = buf.chunks_exact(3).filter(|p| p.iter().all(|&c| c < 100)).count();
            assert!(dark > 500, "{}: {dark} dark pixels (axes, text)", png.display());
            let svg = std::fs::read_to_string(png.with_extension("svg")).unwrap();
            assert!(svg.contains("a title") && svg.contains("x axis"), "{svg}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
