//! SVG charts (plotters' SVG backend), returned as strings to inline in the HTML report.
//!
//! Contract: every function returns a complete `<svg>` element, or a [`PlotError`] naming the
//! chart when there is nothing to draw (no finite point) or plotters fails. Long series are
//! decimated to at most [`MAX_POINTS`] points per line (evenly, endpoints kept), which keeps a
//! one-minute session's report small without visible change.

use std::fmt;
use std::ops::Range;

use plotters::chart::MeshStyle;
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;

/// Most points drawn per line.
pub const MAX_POINTS: usize = 1500;

/// Fonts of the charts (the browser picks the family; plotters only estimates sizes).
const FONT: &str = "sans-serif";

/// Colours: actual, nominal, calibrated, then the joints (Tableau 10).
pub const ACTUAL: RGBColor = RGBColor(40, 40, 40);
/// Colour of the nominal table's series.
pub const NOMINAL: RGBColor = RGBColor(214, 39, 40);
/// Colour of the calibrated table's series.
pub const CALIBRATED: RGBColor = RGBColor(31, 119, 180);
/// One colour per joint, joint 1 first.
pub const JOINT_COLOURS: [RGBColor; 7] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
];

/// A chart could not be drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotError {
    /// The chart's title.
    pub chart: String,
    /// What went wrong.
    pub what: String,
}

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "chart \"{}\": {}", self.chart, self.what)
    }
}

impl std::error::Error for PlotError {}

/// One line of a chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend entry.
    pub name: String,
    /// Line colour.
    pub colour: RGBColor,
    /// `(x, y)` points, in drawing order.
    pub points: Vec<(f64, f64)>,
    /// Draw a marker at every point (short series such as the likelihood).
    pub markers: bool,
}

/// One panel of a line chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Chart title.
    pub title: String,
    /// Label of the x axis.
    pub x_label: String,
    /// Label of the y axis.
    pub y_label: String,
    /// The overlaid series.
    pub series: Vec<Series>,
    /// Shade x ≥ this value (the held-out slice), if any.
    pub shade_from: Option<f64>,
}

fn err(chart: &str, what: impl ToString) -> PlotError {
    PlotError {
        chart: chart.to_string(),
        what: what.to_string(),
    }
}

/// Evenly decimated `points` (at most `max`, first and last kept).
pub fn decimate(points: &[(f64, f64)], max: usize) -> Vec<(f64, f64)> {
    if points.len() <= max || max < 2 {
        return points.to_vec();
    }
    let last = points.len() - 1;
    (0..max).map(|i| points[i * last / (max - 1)]).collect()
}

/// Bounds of the finite values, padded by 5 % (a flat series gets a unit-wide range).
fn padded(values: impl Iterator<Item = f64>) -> Option<Range<f64>> {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        return None;
    }
    let pad = if hi > lo { 0.05 * (hi - lo) } else { 0.5 };
    Some(lo - pad..hi + pad)
}

/// Exponents of an axis over `range`: of its tick step (the step is 1, 2 or 5 × 10^exponent,
/// as plotters places the [`AXIS_LABELS`] ticks) and of its largest magnitude.
fn exponents(range: &Range<f64>) -> (i32, i32) {
    use plotters::coord::ranged1d::Ranged;
    let coord: plotters::coord::types::RangedCoordf64 = range.clone().into();
    let ticks = coord.key_points(AXIS_LABELS);
    let step = match ticks.as_slice() {
        [a, b, ..] if b > a => (b - a).log10().floor() as i32,
        _ => {
            let span = (range.end - range.start).abs();
            if span > 0.0 && span.is_finite() {
                (span / AXIS_LABELS as f64).log10().floor() as i32
            } else {
                0
            }
        }
    };
    let magnitude = range.start.abs().max(range.end.abs());
    let mag = if magnitude > 0.0 && magnitude.is_finite() {
        magnitude.log10().floor() as i32
    } else {
        0
    };
    (step, mag)
}

/// Tick labels of an axis spanning `range`, with as many digits as the ticks need to differ:
/// plotters puts at most [`AXIS_LABELS`] labels on an axis, at multiples of a step of 1, 2 or
/// 5 × 10^k, so showing the digits down to 10^k tells every two ticks apart (1.6e5 ± 20 reads
/// 159990, 159995, …, never "1.6e5" five times). Magnitudes from 1e-3 to below 1e6 are written out, others in
/// scientific notation with the mantissa digits the step needs. [`axis_labels`] adds an
/// offset when that would take more than [`MAX_DIGITS`] digits.
pub fn tick_labels(range: &Range<f64>) -> impl Fn(&f64) -> String {
    let (step, mag) = exponents(range);
    let scientific = !(-3..6).contains(&mag);
    move |v: &f64| {
        // Below a thousandth of a step is the rounding of a range computation, not a value.
        if v.abs() < 10f64.powi(step) * 1e-3 {
            return "0".into();
        }
        if scientific {
            let digits = (mag - step).clamp(0, 15) as usize;
            format!("{v:.digits$e}")
        } else {
            let decimals = (-step).clamp(0, 15) as usize;
            format!("{v:.decimals$}")
        }
    }
}

/// An axis's tick label formatter.
pub type TickLabels = Box<dyn Fn(&f64) -> String>;

/// Most significant digits a tick label shows.
pub const MAX_DIGITS: i32 = 6;

/// The tick labels and the description of an axis over `range` described as `desc`: the labels
/// of [`tick_labels`], or, when they would need more than [`MAX_DIGITS`] digits (a narrow
/// range far from zero: 1e9 + 0…7), the labels of the values minus an offset that the
/// description names (`"time (s) − 1e9"`).
pub fn axis_labels(range: &Range<f64>, desc: &str) -> (TickLabels, String) {
    let (step, mag) = exponents(range);
    let span = (range.end - range.start).abs();
    if mag - step < MAX_DIGITS || !(span > 0.0 && span.is_finite()) {
        return (Box::new(tick_labels(range)), desc.to_string());
    }
    // The start rounded down to a power of ten above the span: labels of a few digits.
    let q = 10f64.powi(span.log10().floor() as i32 + 1);
    let offset = (range.start.min(range.end) / q).floor() * q;
    let f = tick_labels(&(range.start - offset..range.end - offset));
    let desc = if offset < 0.0 {
        format!("{desc} + {:e}", -offset)
    } else {
        format!("{desc} − {offset:e}")
    };
    (Box::new(move |v: &f64| f(&(v - offset))), desc)
}

/// Text for HTML: `&`, `<`, `>` and `"` escaped.
pub fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// How a legend entry's swatch looks: a line, or a filled area (bars, a shaded span).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Swatch {
    /// A line of the series' colour.
    Line,
    /// A filled box of the series' colour.
    Area,
}

/// A chart's legend as HTML, placed after its SVG: beside the data, never over it.
/// Entries repeat across stacked panels; each is listed once.
pub fn legend(entries: &[(String, RGBColor, Swatch)]) -> String {
    let mut seen: Vec<&(String, RGBColor, Swatch)> = Vec::new();
    let mut out = String::from("<div class=\"legend\">");
    for e in entries {
        if seen.contains(&e) {
            continue;
        }
        seen.push(e);
        let (name, RGBColor(r, g, b), swatch) = e;
        let class = match swatch {
            Swatch::Line => "line",
            Swatch::Area => "area",
        };
        out.push_str(&format!(
            "<span class=\"key\"><i class=\"{class}\" style=\"background:#{r:02x}{g:02x}{b:02x}\"></i>{}</span>",
            esc(name)
        ));
    }
    out.push_str("</div>");
    out
}

/// Labels per axis plotters draws at most (its default for both axes).
pub const AXIS_LABELS: usize = 10;

/// A chart on `area` over `xs` × `ys`, captioned `title`, with `y_area` pixels for the y
/// labels (and the charts' margin and x label area).
fn chart<'c, 'b>(
    area: &DrawingArea<SVGBackend<'b>, Shift>,
    title: &str,
    y_area: u32,
    xs: Range<f64>,
    ys: Range<f64>,
) -> Result<ChartContext<'c, SVGBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>, PlotError>
{
    ChartBuilder::on(area)
        .margin(8)
        .caption(title, (FONT, 17))
        .x_label_area_size(38)
        .y_label_area_size(y_area)
        .build_cartesian_2d(xs, ys)
        .map_err(|x| err(title, x))
}

/// Draws `mesh` in the charts' style (label fonts, light grey grid lines); a failure names
/// the chart `title`.
fn draw_mesh(
    mesh: &mut MeshStyle<'_, '_, RangedCoordf64, RangedCoordf64, SVGBackend<'_>>,
    title: &str,
) -> Result<(), PlotError> {
    mesh.label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .light_line_style(RGBColor(238, 238, 238))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(|x| err(title, x))
}

fn draw_panel(area: &DrawingArea<SVGBackend<'_>, Shift>, panel: &Panel) -> Result<(), PlotError> {
    let e = |what: &dyn fmt::Display| err(&panel.title, what);
    // The padded range of one coordinate over every series' points.
    let range = |coord: fn(&(f64, f64)) -> f64| {
        padded(panel.series.iter().flat_map(|s| s.points.iter().map(coord)))
            .ok_or_else(|| e(&"no finite point to draw"))
    };
    let xs = range(|p| p.0)?;
    let ys = range(|p| p.1)?;
    // The x axis spans the data exactly (time starts where the session starts).
    let xs = {
        let pad = (xs.end - xs.start) / 1.1 * 0.05;
        let (lo, hi) = (xs.start + pad, xs.end - pad);
        if hi > lo {
            lo..hi
        } else {
            xs
        }
    };
    // A label per 30 px of height at most: a short panel (one of seven joints) stays legible.
    let y_labels = (area.dim_in_pixel().1 as usize / 30).clamp(3, AXIS_LABELS);
    let mut chart = chart(area, &panel.title, 62, xs.clone(), ys.clone())?;
    let (x_ticks, x_desc) = axis_labels(&xs, &panel.x_label);
    let (y_ticks, y_desc) = axis_labels(&ys, &panel.y_label);
    draw_mesh(
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc(y_desc)
            .x_labels(AXIS_LABELS)
            .y_labels(y_labels)
            .x_label_formatter(&x_ticks)
            .y_label_formatter(&y_ticks),
        &panel.title,
    )?;
    if let Some(from) = panel.shade_from.filter(|f| xs.contains(f)) {
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(from, ys.start), (xs.end, ys.end)],
                HELD_OUT_SHADE.mix(0.15).filled(),
            )))
            .map_err(|x| e(&x))?;
    }
    for s in &panel.series {
        let colour = s.colour;
        let pts: Vec<(f64, f64)> = decimate(&s.points, MAX_POINTS)
            .into_iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
            .map_err(|x| e(&x))?;
        if s.markers {
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                .map_err(|x| e(&x))?;
        }
    }
    Ok(())
}

/// The colour of the held-out span's shading, and of its legend swatch.
const HELD_OUT_SHADE: RGBColor = RGBColor(255, 200, 80);

/// Panels stacked vertically in one SVG of `width` × `panel_height · panels`.
pub fn line_panels(panels: &[Panel], width: u32, panel_height: u32) -> Result<String, PlotError> {
    let name = panels.first().map_or("", |p| p.title.as_str());
    if panels.is_empty() {
        return Err(err(name, "no panel"));
    }
    let mut svg = String::new();
    {
        let height = panel_height * panels.len() as u32;
        let root = SVGBackend::with_string(&mut svg, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| err(name, x))?;
        let areas = root.split_evenly((panels.len(), 1));
        for (area, panel) in areas.iter().zip(panels) {
            draw_panel(area, panel)?;
        }
        root.present().map_err(|x| err(name, x))?;
    }
    let mut keys: Vec<(String, RGBColor, Swatch)> = Vec::new();
    for p in panels {
        keys.extend(
            p.series
                .iter()
                .map(|s| (s.name.clone(), s.colour, Swatch::Line)),
        );
        if p.shade_from.is_some() {
            keys.push(("held out".into(), HELD_OUT_SHADE, Swatch::Area));
        }
    }
    // A series drawn in several panels is named once.
    let mut seen = std::collections::HashSet::new();
    keys.retain(|k| seen.insert(k.0.clone()));
    svg.push_str(&legend(&keys));
    Ok(svg)
}

/// One overlaid histogram series.
#[derive(Debug, Clone, PartialEq)]
pub struct Distribution {
    /// Legend entry.
    pub name: String,
    /// Bar colour.
    pub colour: RGBColor,
    /// The values to bin.
    pub values: Vec<f64>,
}

/// Where a histogram's bins lie: `bins` bins of `width` from `lo` to `hi`, and, when
/// `overflow`, one more bar right of `hi` holding every value above it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Binning {
    /// Left edge of the first bin.
    pub lo: f64,
    /// Right edge of the last regular bin.
    pub hi: f64,
    /// Width of a bin.
    pub width: f64,
    /// Number of regular bins.
    pub bins: usize,
    /// Whether a last bar holds every value above `hi`.
    pub overflow: bool,
}

/// A value this many times the largest series' 99th percentile is an outlier: the bins then end
/// at that percentile and an explicit overflow bar holds the rest.
pub const OUTLIER_FACTOR: f64 = 2.0;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The bins of `series` (see [`histogram`]); `None` if there is no finite value.
pub fn binning(series: &[Distribution], bins: usize) -> Option<Binning> {
    let sorted: Vec<Vec<f64>> = series
        .iter()
        .map(|s| {
            let mut v: Vec<f64> = s.values.iter().copied().filter(|v| v.is_finite()).collect();
            v.sort_by(f64::total_cmp);
            v
        })
        .filter(|v| !v.is_empty())
        .collect();
    if sorted.is_empty() || bins == 0 {
        return None;
    }
    let lo = sorted.iter().map(|v| v[0]).fold(0.0f64, f64::min);
    let max = sorted.iter().map(|v| v[v.len() - 1]).fold(lo, f64::max);
    let p99 = sorted
        .iter()
        .map(|v| percentile(v, 0.99))
        .fold(lo, f64::max);
    let overflow = max - lo > OUTLIER_FACTOR * (p99 - lo);
    let hi = if overflow { p99 } else { max }.max(lo + f64::EPSILON);
    Some(Binning {
        lo,
        hi,
        width: (hi - lo) / bins as f64,
        bins,
        overflow,
    })
}

/// Overlaid histograms of `series` on shared bins, in % of each series. The bins cover every
/// value of every series, from 0 (or the least value, if negative) to the largest; only when
/// that largest is an outlier (over [`OUTLIER_FACTOR`] × the largest series' 99th percentile)
/// do they end at that percentile, and a separate bar marked "> hi" right of them holds every
/// value beyond. Returns the SVG and the [`Binning`] (for the caption).
pub fn histogram(
    title: &str,
    x_label: &str,
    series: &[Distribution],
    bins: usize,
    size: (u32, u32),
) -> Result<(String, Binning), PlotError> {
    let b = binning(series, bins).ok_or_else(|| err(title, "no finite value to draw"))?;
    let Binning { lo, hi, width, .. } = b;
    // Bin k of `bins`; index `bins` is the overflow bar.
    let counts: Vec<Vec<f64>> = series
        .iter()
        .map(|s| {
            let mut c = vec![0.0; bins + 1];
            let n = s.values.iter().filter(|v| v.is_finite()).count().max(1) as f64;
            for v in s.values.iter().filter(|v| v.is_finite()) {
                let k = if *v > hi {
                    bins
                } else {
                    (((v - lo) / width) as usize).min(bins - 1)
                };
                c[k] += 100.0 / n;
            }
            c
        })
        .collect();
    // Bar k spans [x0, x0 + width); the overflow bar stands half a bin apart.
    let x0 = |k: usize| {
        if k == bins {
            hi + 0.5 * width
        } else {
            lo + k as f64 * width
        }
    };
    // A bin and a half of room right of the last bar (or of the overflow bar).
    let xs = lo..hi + if b.overflow { 3.0 * width } else { 1.5 * width };
    let top = counts.iter().flatten().fold(0.0f64, |m, &c| m.max(c)) * 1.1;
    let ys = 0.0..top.max(1.0);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(|x| err(title, x))?;
        let mut chart = chart(&root, title, 62, xs.clone(), ys.clone())?;
        let (x_ticks, x_desc) = axis_labels(&xs, x_label);
        draw_mesh(
            chart
                .configure_mesh()
                .x_desc(x_desc)
                .y_desc("share of samples (%)")
                .x_labels(AXIS_LABELS)
                .y_labels(AXIS_LABELS)
                .x_label_formatter(&x_ticks)
                .y_label_formatter(&tick_labels(&ys)),
            title,
        )?;
        for (s, c) in series.iter().zip(&counts) {
            let colour = s.colour;
            chart
                .draw_series(
                    c.iter()
                        .enumerate()
                        .filter(|(_, &h)| h > 0.0)
                        .map(|(k, &h)| {
                            Rectangle::new(
                                [(x0(k), 0.0), (x0(k) + width, h)],
                                colour.mix(0.35).filled(),
                            )
                        }),
                )
                .map_err(|x| err(title, x))?;
            // The outline of the bins, as a step line.
            let steps: Vec<(f64, f64)> = c[..bins]
                .iter()
                .enumerate()
                .flat_map(|(k, &h)| [(x0(k), h), (x0(k) + width, h)])
                .collect();
            chart
                .draw_series(LineSeries::new(steps, colour.stroke_width(2)))
                .map_err(|x| err(title, x))?;
        }
        if b.overflow {
            let label = format!("> {}", tick_labels(&xs)(&hi));
            let h = counts.iter().map(|c| c[bins]).fold(0.0f64, f64::max);
            chart
                .draw_series(std::iter::once(Text::new(
                    label,
                    (x0(bins), (h + 0.04 * ys.end).min(0.97 * ys.end)),
                    (FONT, 12).into_font().color(&ACTUAL),
                )))
                .map_err(|x| err(title, x))?;
        }
        root.present().map_err(|x| err(title, x))?;
    }
    let keys: Vec<_> = series
        .iter()
        .map(|s| (s.name.clone(), s.colour, Swatch::Area))
        .collect();
    svg.push_str(&legend(&keys));
    Ok((svg, b))
}

/// Horizontal bars (value in [0, 1] per label) with a vertical "required" line.
pub fn bars(
    title: &str,
    labels: &[String],
    values: &[f64],
    required: Option<f64>,
    size: (u32, u32),
) -> Result<String, PlotError> {
    if labels.is_empty() || labels.len() != values.len() {
        return Err(err(
            title,
            "labels and values differ in length or are empty",
        ));
    }
    let n = labels.len();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(|x| err(title, x))?;
        let mut chart = chart(&root, title, 70, 0.0..100.0, 0.0..n as f64)?;
        let names = labels.to_vec();
        draw_mesh(
            chart
                .configure_mesh()
                .disable_y_mesh()
                .x_desc("share of the joint's range visited (%)")
                .x_labels(AXIS_LABELS)
                .x_label_formatter(&tick_labels(&(0.0..100.0)))
                .y_labels(n * 2 + 1)
                .y_label_formatter(&|y: &f64| {
                    let k = y - 0.5;
                    if (k - k.round()).abs() < 1e-6 && k >= 0.0 {
                        names
                            .get(n - 1 - k.round() as usize)
                            .cloned()
                            .unwrap_or_default()
                    } else {
                        String::new()
                    }
                }),
            title,
        )?;
        chart
            .draw_series(values.iter().enumerate().map(|(i, &v)| {
                let y = (n - 1 - i) as f64;
                let ok = required.is_none_or(|r| v >= r);
                let c = if ok { RGBColor(44, 160, 44) } else { NOMINAL };
                Rectangle::new(
                    [(0.0, y + 0.2), (100.0 * v.clamp(0.0, 1.0), y + 0.8)],
                    c.mix(0.75).filled(),
                )
            }))
            .map_err(|x| err(title, x))?;
        if let Some(r) = required {
            chart
                .draw_series(LineSeries::new(
                    [(100.0 * r, 0.0), (100.0 * r, n as f64)],
                    ACTUAL.stroke_width(2),
                ))
                .map_err(|x| err(title, x))?;
        }
        root.present().map_err(|x| err(title, x))?;
    }
    let mut keys = vec![
        ("enough".to_string(), RGBColor(44, 160, 44), Swatch::Area),
        ("not enough".to_string(), NOMINAL, Swatch::Area),
    ];
    if required.is_some() {
        keys.push(("required".into(), ACTUAL, Swatch::Line));
    } else {
        keys.truncate(1);
        keys[0].0 = "visited".into();
    }
    svg.push_str(&legend(&keys));
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sine(n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|i| (i as f64 * 0.01, (i as f64 * 0.01).sin()))
            .collect()
    }

    #[test]
    fn decimation_keeps_the_ends_and_the_limit() {
        let p = sine(10_000);
        let d = decimate(&p, 100);
        assert_eq!(d.len(), 100);
        assert_eq!(d[0], p[0]);
        assert_eq!(d[99], p[9_999]);
        assert_eq!(decimate(&p[..5], 100), p[..5].to_vec());
    }

    #[test]
    fn a_line_chart_is_an_svg_with_one_polyline_per_series() {
        let panel = Panel {
            title: "sine".into(),
            x_label: "t (s)".into(),
            y_label: "y".into(),
            series: vec![
                Series {
                    name: "a".into(),
                    colour: ACTUAL,
                    points: sine(3000),
                    markers: false,
                },
                Series {
                    name: "b".into(),
                    colour: NOMINAL,
                    points: sine(50),
                    markers: true,
                },
            ],
            shade_from: Some(20.0),
        };
        let svg = line_panels(&[panel.clone(), panel], 600, 200).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..80]);
        assert!(svg.matches("<polyline").count() >= 4);
        assert!(svg.contains(">sine<") || svg.contains("sine"));
    }

    #[test]
    fn an_empty_chart_is_an_error_naming_it() {
        let panel = Panel {
            title: "nothing".into(),
            x_label: String::new(),
            y_label: String::new(),
            series: vec![Series {
                name: "nan".into(),
                colour: ACTUAL,
                points: vec![(f64::NAN, 1.0)],
                markers: false,
            }],
            shade_from: None,
        };
        let e = line_panels(&[panel], 300, 200).unwrap_err();
        assert_eq!(e.chart, "nothing");
        assert!(e.to_string().contains("no finite point"));
        let h = histogram("h", "x", &[], 10, (300, 200)).unwrap_err();
        assert_eq!(h.chart, "h");
        assert!(bars("b", &["x".into()], &[], None, (300, 200)).is_err());
    }

    #[test]
    fn histograms_and_bars_draw_rectangles() {
        let d = Distribution {
            name: "d".into(),
            colour: CALIBRATED,
            values: (0..500).map(|i| (i % 37) as f64).collect(),
        };
        let (svg, _) = histogram("h", "x", &[d], 20, (500, 300)).unwrap();
        assert!(svg.matches("<rect").count() > 10);
        let svg = bars(
            "b",
            &["j1".into(), "j2".into()],
            &[0.3, 0.9],
            Some(0.5),
            (500, 200),
        )
        .unwrap();
        assert!(svg.matches("<rect").count() >= 3);
    }

    /// The labels plotters puts on an axis over `range`, through [`axis_labels`], and the
    /// axis's description.
    fn axis(range: Range<f64>) -> (Vec<String>, String) {
        use plotters::coord::ranged1d::Ranged;
        let coord: plotters::coord::types::RangedCoordf64 = range.clone().into();
        let (f, desc) = axis_labels(&range, "y");
        (coord.key_points(AXIS_LABELS).iter().map(f).collect(), desc)
    }

    #[test]
    fn neighbouring_ticks_never_read_the_same() {
        let ranges = [
            159_990.0..160_030.0, // the EM log-likelihood of a one-minute session
            -160_004.0..-159_998.5,
            1.6e5 - 0.3..1.6e5 + 0.2,
            1.0e9..1.0e9 + 7.0,
            -2.5e7 - 3.0..-2.5e7,
            0.0..1.0,
            -0.5..312.4,
            0.0..100.0,
            2.0e-7..2.6e-7,
            -3.0e-4..4.0e-4,
            12.0..12.004,
            0.0..5.0e6,
        ];
        for r in ranges {
            let (labels, desc) = axis(r.clone());
            assert!(labels.len() >= 3, "{r:?}: {labels:?}");
            let mut unique = labels.clone();
            unique.sort();
            unique.dedup();
            assert_eq!(unique.len(), labels.len(), "{r:?}: {labels:?}");
            assert!(
                labels.iter().all(|l| l.len() <= 9),
                "{r:?}: {labels:?} ({desc})"
            );
        }
        assert_eq!(axis(159_990.0..160_030.0).0[..2], ["159990", "159995"]);
        assert_eq!(axis(0.0..1.0).0[..3], ["0", "0.2", "0.4"]);
        let (labels, desc) = axis(1.0e9..1.0e9 + 7.0);
        assert_eq!(
            (&labels[..3], desc.as_str()),
            (&["0".to_string(), "1".into(), "2".into()][..], "y − 1e9")
        );
    }

    #[test]
    fn histogram_bins_cover_both_series_or_name_the_overflow() {
        let series = |a: Vec<f64>, b: Vec<f64>| {
            [
                Distribution {
                    name: "nominal".into(),
                    colour: NOMINAL,
                    values: a,
                },
                Distribution {
                    name: "calibrated".into(),
                    colour: CALIBRATED,
                    values: b,
                },
            ]
        };
        // A large nominal error beside a small calibrated one: the bins reach the largest
        // nominal value (bins ending at the 99th percentile of both together would cut off
        // the nominal tail at the chart's edge).
        let nominal: Vec<f64> = (0..1000).map(|i| 200.0 + 0.1 * i as f64).collect();
        let calibrated: Vec<f64> = (0..1000).map(|i| 0.02 * i as f64).collect();
        let b = binning(&series(nominal.clone(), calibrated.clone()), 40).unwrap();
        assert_eq!((b.lo, b.hi, b.overflow), (0.0, 299.9, false));
        let (svg, _) = histogram(
            "h",
            "x",
            &series(nominal.clone(), calibrated.clone()),
            40,
            (500, 300),
        )
        .unwrap();
        assert!(!svg.contains("&gt; "), "no overflow bar");
        // One wild value: the bins end at the 99th percentile, and the bar beyond says so.
        let mut wild = nominal;
        wild.push(5000.0);
        let b = binning(&series(wild.clone(), calibrated), 40).unwrap();
        assert!(b.overflow && (b.hi - 299.0).abs() < 1.0, "{b:?}");
        let (svg, _) = histogram("h", "x", &series(wild, vec![1.0]), 40, (500, 300)).unwrap();
        assert!(svg.contains("&gt; 29"), "overflow bar labelled");
        assert!(binning(&series(vec![f64::NAN], vec![]), 40).is_none());
    }
}
