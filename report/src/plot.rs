//! SVG charts (plotters' SVG backend), returned as strings to inline in the HTML report.
//!
//! Contract: every function returns a complete `<svg>` element, or a [`PlotError`] naming the
//! chart when there is nothing to draw (no finite point) or plotters fails. Long series are
//! decimated to at most [`MAX_POINTS`] points per line (evenly, endpoints kept), which keeps a
//! one-minute session's report small without visible change.

use std::fmt;
use std::ops::Range;

use plotters::coord::Shift;
use plotters::prelude::*;

/// Most points drawn per line.
pub const MAX_POINTS: usize = 1500;

/// Fonts of the charts (the browser picks the family; plotters only estimates sizes).
const FONT: &str = "sans-serif";

/// Colours: actual, nominal, calibrated, then the joints (Tableau 10).
pub const ACTUAL: RGBColor = RGBColor(40, 40, 40);
pub const NOMINAL: RGBColor = RGBColor(214, 39, 40);
pub const CALIBRATED: RGBColor = RGBColor(31, 119, 180);
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
    pub name: String,
    pub colour: RGBColor,
    pub points: Vec<(f64, f64)>,
    /// Draw a marker at every point (short series such as the likelihood).
    pub markers: bool,
}

/// One panel of a line chart.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
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

/// Short tick labels for any magnitude.
fn tick(v: &f64) -> String {
    let a = v.abs();
    // Below 1e-12 is rounding noise of a range computation, not a value.
    if a < 1e-12 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

fn draw_panel(area: &DrawingArea<SVGBackend<'_>, Shift>, panel: &Panel) -> Result<(), PlotError> {
    let e = |what: &dyn fmt::Display| err(&panel.title, what);
    let xs = padded(
        panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.0)),
    )
    .ok_or_else(|| e(&"no finite point to draw"))?;
    let ys = padded(
        panel
            .series
            .iter()
            .flat_map(|s| s.points.iter().map(|p| p.1)),
    )
    .ok_or_else(|| e(&"no finite point to draw"))?;
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
    let mut chart = ChartBuilder::on(area)
        .margin(8)
        .caption(&panel.title, (FONT, 17))
        .x_label_area_size(38)
        .y_label_area_size(62)
        .build_cartesian_2d(xs.clone(), ys.clone())
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .x_label_formatter(&tick)
        .y_label_formatter(&tick)
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .light_line_style(RGBColor(238, 238, 238))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(|x| e(&x))?;
    if let Some(from) = panel.shade_from.filter(|f| xs.contains(f)) {
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(from, ys.start), (xs.end, ys.end)],
                RGBColor(255, 200, 80).mix(0.15).filled(),
            )))
            .map_err(|x| e(&x))?
            .label("held out")
            .legend(|(x, y)| {
                Rectangle::new(
                    [(x, y - 5), (x + 18, y + 5)],
                    RGBColor(255, 200, 80).mix(0.4).filled(),
                )
            });
    }
    for s in &panel.series {
        let colour = s.colour;
        let pts: Vec<(f64, f64)> = decimate(&s.points, MAX_POINTS)
            .into_iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .collect();
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
            .map_err(|x| e(&x))?
            .label(s.name.as_str())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(3))
            });
        if s.markers {
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                .map_err(|x| e(&x))?;
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(190, 190, 190))
        .draw()
        .map_err(|x| e(&x))?;
    Ok(())
}

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
    Ok(svg)
}

/// One overlaid histogram series.
#[derive(Debug, Clone, PartialEq)]
pub struct Distribution {
    pub name: String,
    pub colour: RGBColor,
    pub values: Vec<f64>,
}

/// Overlaid histograms of `series` on shared bins (`bins` between 0 and the 99th percentile of
/// all values, the rest in the last bin).
pub fn histogram(
    title: &str,
    x_label: &str,
    series: &[Distribution],
    bins: usize,
    size: (u32, u32),
) -> Result<String, PlotError> {
    let mut all: Vec<f64> = series
        .iter()
        .flat_map(|s| s.values.iter().copied())
        .filter(|v| v.is_finite())
        .collect();
    if all.is_empty() || bins == 0 {
        return Err(err(title, "no finite value to draw"));
    }
    all.sort_by(f64::total_cmp);
    let lo = all[0].min(0.0);
    let hi = all[((all.len() - 1) as f64 * 0.99) as usize].max(lo + f64::EPSILON);
    let width = (hi - lo) / bins as f64;
    let counts: Vec<Vec<f64>> = series
        .iter()
        .map(|s| {
            let mut c = vec![0.0; bins];
            let n = s.values.iter().filter(|v| v.is_finite()).count().max(1) as f64;
            for v in s.values.iter().filter(|v| v.is_finite()) {
                let b = (((v - lo) / width) as usize).min(bins - 1);
                c[b] += 100.0 / n;
            }
            c
        })
        .collect();
    let top = counts.iter().flatten().fold(0.0f64, |m, &c| m.max(c)) * 1.1;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(|x| err(title, x))?;
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .caption(title, (FONT, 17))
            .x_label_area_size(38)
            .y_label_area_size(62)
            .build_cartesian_2d(lo..hi, 0.0..top.max(1.0))
            .map_err(|x| err(title, x))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc("share of samples (%)")
            .x_label_formatter(&tick)
            .y_label_formatter(&tick)
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 14))
            .light_line_style(RGBColor(238, 238, 238))
            .bold_line_style(RGBColor(215, 215, 215))
            .draw()
            .map_err(|x| err(title, x))?;
        for (s, c) in series.iter().zip(&counts) {
            let colour = s.colour;
            chart
                .draw_series(
                    c.iter()
                        .enumerate()
                        .filter(|(_, &h)| h > 0.0)
                        .map(|(b, &h)| {
                            let x0 = lo + b as f64 * width;
                            Rectangle::new([(x0, 0.0), (x0 + width, h)], colour.mix(0.35).filled())
                        }),
                )
                .map_err(|x| err(title, x))?
                .label(s.name.as_str())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 18, y + 5)], colour.mix(0.6).filled())
                });
            // The outline, as a step line.
            let steps: Vec<(f64, f64)> = c
                .iter()
                .enumerate()
                .flat_map(|(b, &h)| {
                    let x0 = lo + b as f64 * width;
                    [(x0, h), (x0 + width, h)]
                })
                .collect();
            chart
                .draw_series(LineSeries::new(steps, colour.stroke_width(2)))
                .map_err(|x| err(title, x))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font((FONT, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(190, 190, 190))
            .draw()
            .map_err(|x| err(title, x))?;
        root.present().map_err(|x| err(title, x))?;
    }
    Ok(svg)
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
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .caption(title, (FONT, 17))
            .x_label_area_size(38)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..100.0, 0.0..n as f64)
            .map_err(|x| err(title, x))?;
        let names = labels.to_vec();
        chart
            .configure_mesh()
            .disable_y_mesh()
            .x_desc("share of the joint's range visited (%)")
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
            })
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 14))
            .light_line_style(RGBColor(238, 238, 238))
            .bold_line_style(RGBColor(215, 215, 215))
            .draw()
            .map_err(|x| err(title, x))?;
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
                .map_err(|x| err(title, x))?
                .label("required")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], ACTUAL.stroke_width(2))
                });
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .label_font((FONT, 13))
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(190, 190, 190))
                .draw()
                .map_err(|x| err(title, x))?;
        }
        root.present().map_err(|x| err(title, x))?;
    }
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
        let svg = histogram("h", "x", &[d], 20, (500, 300)).unwrap();
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
}
