//! The report: one self-contained HTML file (inline CSS and SVG, no script, no external
//! resource), readable offline and printable.
//!
//! Contract: [`render`] never fails. A chart that cannot be drawn (no EM, no held-out slice,
//! nothing finite) is replaced by a visible note saying why, so a broken run still leaves a
//! report. Every chart sits in a `<figure class="plot" id="fig-…">` (ids in [`FIGURES`]), which
//! is what the browser test looks for.
//!
//! Errors shown are the paper's pose error in the model's tool frame: position error in mm and
//! rotation error in mrad; "calibrated" is the static calibrated table (what is pushed), without
//! the per-sample drift estimate.

use std::fmt::Write as _;

use calib_core::drift_conf::Z_95;
use calib_core::{pose_error, DhTable, TableError};

use crate::input::{
    excitation, param_name, param_value, AtRest, Calibration, EmDetail, NodePush, Quality,
    ReportInput, SessionInput, TimedSample, MAX_JOINTS, MAX_PARAMS,
};
use crate::plot::{
    bars, esc, histogram, line_panels, Binning, Distribution, Panel, PlotError, Series, ACTUAL,
    CALIBRATED, JOINT_COLOURS, NOMINAL,
};

/// The figure ids, in page order.
pub const FIGURES: [&str; 7] = [
    "fig-trajectory-time",
    "fig-trajectory-plane",
    "fig-residual-position",
    "fig-residual-rotation",
    "fig-likelihood",
    "fig-drift",
    "fig-excitation",
];

const WIDE: u32 = 1040;
const HALF: u32 = 515;

/// Position (mm) and rotation (mrad) error of `table` on each sample.
pub fn residuals(table: &DhTable<MAX_JOINTS>, samples: &[TimedSample]) -> Vec<(f64, f64)> {
    samples
        .iter()
        .map(|s| {
            let e = pose_error(&table.fk(&s.sample.joints), &s.sample.pose);
            (
                e.fixed_rows::<3>(0).norm() * 1e3,
                e.fixed_rows::<3>(3).norm() * 1e3,
            )
        })
        .collect()
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

fn figure(out: &mut String, id: &str, caption: &str, svg: Result<String, PlotError>) {
    let _ = write!(out, "<figure class=\"plot\" id=\"{id}\">");
    match svg {
        Ok(svg) => out.push_str(&svg),
        Err(e) => {
            let _ = write!(
                out,
                "<div class=\"missing\">Not drawn: {}</div>",
                esc(&e.to_string())
            );
        }
    }
    let _ = writeln!(out, "<figcaption>{caption}</figcaption></figure>");
}

/// The table the held-out slice judges: fitted without it.
fn held_out_table(input: &ReportInput) -> &DhTable<MAX_JOINTS> {
    input
        .judged
        .as_ref()
        .unwrap_or(&input.calibration.calibrated)
}

/// `x` to four significant digits.
fn sig4(x: f64) -> String {
    if x == 0.0 {
        return "0".into();
    }
    if !x.is_finite() {
        return format!("{x}");
    }
    let mag = x.abs().log10().floor() as i32;
    let decimals = (3 - mag).clamp(0, 12) as usize;
    format!("{x:.decimals$}")
}

/// What a histogram's bins cover, for its caption.
fn bins_caption(b: &Binning, unit: &str) -> String {
    let (lo, hi) = (sig4(b.lo), sig4(b.hi));
    if b.overflow {
        format!(
            "Bins from {lo} to {hi} {unit}; the bar marked \"&gt;\" holds every sample beyond \
             (outliers)."
        )
    } else {
        format!("Bins from {lo} to {hi} {unit}: every sample of both series.")
    }
}

fn all_samples(input: &ReportInput) -> Vec<TimedSample> {
    input.fit.iter().chain(&input.held_out).copied().collect()
}

/// The pose error over time of the nominal table and of the table the held-out slice judged
/// (fitted without it), position and rotation: where each is off, and whether the calibrated
/// one stays better on the slice it never saw.
fn error_over_time(input: &ReportInput) -> Result<String, PlotError> {
    let all = all_samples(input);
    let shade = input.held_out.first().map(|s| s.t);
    let nominal = residuals(&input.nominal, &all);
    let calibrated = residuals(held_out_table(input), &all);
    let panel = |title: &str, unit: &str, pick: fn(&(f64, f64)) -> f64| Panel {
        title: title.into(),
        x_label: "time (s)".into(),
        y_label: unit.into(),
        series: [
            ("nominal", NOMINAL, &nominal),
            ("calibrated", CALIBRATED, &calibrated),
        ]
        .iter()
        .map(|(name, colour, errors)| Series {
            name: (*name).into(),
            colour: *colour,
            points: all
                .iter()
                .zip(errors.iter())
                .map(|(s, e)| (s.t, pick(e)))
                .collect(),
            markers: false,
        })
        .collect(),
        shade_from: shade,
    };
    line_panels(
        &[
            panel("end-effector position error", "‖Δp‖ (mm)", |e| e.0),
            panel("end-effector rotation error", "‖Δφ‖ (mrad)", |e| e.1),
        ],
        WIDE,
        240,
    )
}

/// The trajectories on two planes of the base frame: measured, nominal and calibrated.
fn trajectories(input: &ReportInput) -> Result<String, PlotError> {
    let all = all_samples(input);
    let fk = |table: &DhTable<MAX_JOINTS>| -> Vec<(f64, [f64; 3])> {
        all.iter()
            .map(|s| {
                let p = table.fk(&s.sample.joints).p * 1e3;
                (s.t, [p.x, p.y, p.z])
            })
            .collect()
    };
    let actual: Vec<(f64, [f64; 3])> = all
        .iter()
        .map(|s| {
            let p = s.sample.pose.p * 1e3;
            (s.t, [p.x, p.y, p.z])
        })
        .collect();
    let nominal = fk(&input.nominal);
    let calibrated = fk(&input.calibration.calibrated);
    let lines = [
        ("actual (measured)", ACTUAL, &actual),
        ("nominal model", NOMINAL, &nominal),
        ("calibrated model", CALIBRATED, &calibrated),
    ];
    let plane = |a: usize, b: usize, title: &str, xl: &str, yl: &str| Panel {
        title: title.into(),
        x_label: xl.into(),
        y_label: yl.into(),
        series: lines
            .iter()
            .map(|(label, colour, pts)| Series {
                name: (*label).into(),
                colour: *colour,
                points: pts.iter().map(|(_, p)| (p[a], p[b])).collect(),
                markers: false,
            })
            .collect(),
        shade_from: None,
    };
    let top = plane(0, 1, "top view (x–y)", "x (mm)", "y (mm)");
    let side = plane(0, 2, "side view (x–z)", "x (mm)", "z (mm)");
    line_panels(&[top], HALF, 420).and_then(|a| {
        line_panels(&[side], HALF, 420).map(|b| format!("<div class=\"pair\">{a}{b}</div>"))
    })
}

/// A histogram, drawn, and its bins.
type Histogram = Result<(String, Binning), PlotError>;

fn residual_charts(input: &ReportInput) -> (Histogram, Histogram, &'static str) {
    let (samples, which) = if input.held_out.is_empty() {
        (&input.fit, "fitted samples (no held-out slice)")
    } else {
        (&input.held_out, "held-out slice")
    };
    let before = residuals(&input.nominal, samples);
    let after = residuals(held_out_table(input), samples);
    let dist = |pick: fn(&(f64, f64)) -> f64| {
        vec![
            Distribution {
                name: "nominal".into(),
                colour: NOMINAL,
                values: before.iter().map(pick).collect(),
            },
            Distribution {
                name: "calibrated".into(),
                colour: CALIBRATED,
                values: after.iter().map(pick).collect(),
            },
        ]
    };
    (
        histogram(
            "position error",
            "‖Δp‖ (mm)",
            &dist(|r| r.0),
            40,
            (HALF, 330),
        ),
        histogram(
            "rotation error",
            "‖Δφ‖ (mrad)",
            &dist(|r| r.1),
            40,
            (HALF, 330),
        ),
        which,
    )
}

fn em_charts(input: &ReportInput) -> (Result<String, PlotError>, Result<String, PlotError>) {
    let em = match &input.calibration.em {
        Ok(em) => em,
        Err(e) => {
            let no = |chart: &str| {
                Err(PlotError {
                    chart: chart.into(),
                    what: format!("the EM failed: {e}"),
                })
            };
            return (no("log-likelihood"), no("drift"));
        }
    };
    // One series per objective (finer samples, the rate bias's prior refitted): likelihoods
    // compare only within one, so each shows its gain since its own first iterate.
    let mut starts = vec![0];
    starts.extend(em.objectives.iter().copied());
    starts.push(em.log_likelihood.len());
    let last = starts.len() - 2;
    let ll = Panel {
        title: "EM log-likelihood gain per iteration".into(),
        x_label: "iteration".into(),
        y_label: "log-likelihood − its objective's first".into(),
        series: starts
            .windows(2)
            .enumerate()
            .map(|(k, w)| {
                let part = &em.log_likelihood[w[0]..w[1]];
                Series {
                    name: if k == last {
                        "final objective".into()
                    } else {
                        format!("objective {}", k + 1)
                    },
                    colour: if k == last {
                        CALIBRATED
                    } else {
                        JOINT_COLOURS[(k + 1) % JOINT_COLOURS.len()]
                    },
                    points: part
                        .iter()
                        .enumerate()
                        .map(|(i, &l)| ((w[0] + i + 1) as f64, l - part[0]))
                        .collect(),
                    markers: true,
                }
            })
            .filter(|s| !s.points.is_empty())
            .collect(),
        shade_from: None,
    };
    // The drift series covers the samples the EM ran on: the fitted ones, or every one.
    let times: Vec<f64> = input
        .fit
        .iter()
        .chain(&input.held_out)
        .map(|s| s.t)
        .collect();
    // One panel per joint: seven drifts on one axis hide each other.
    let drift: Vec<Panel> = (0..em.drift.len())
        .map(|j| Panel {
            title: format!("joint {}: τ {:.2} s", j + 1, em.drift[j].tau),
            x_label: "time (s)".into(),
            y_label: "drift (mrad)".into(),
            series: vec![Series {
                name: format!("joint {}", j + 1),
                colour: JOINT_COLOURS[j],
                points: times
                    .iter()
                    .zip(&em.drift_series)
                    .map(|(&t, d)| (t, d[j] * 1e3))
                    .collect(),
                markers: false,
            }],
            shade_from: None,
        })
        .collect();
    (
        line_panels(&[ll], HALF, 330),
        line_panels(&drift, WIDE, 190),
    )
}

/// Value and standard deviation in display units: mm for lengths, degrees for angles.
fn display(index: usize, v: f64) -> f64 {
    if index < 2 * MAX_JOINTS {
        v * 1e3
    } else {
        v.to_degrees()
    }
}

fn parameter_table(out: &mut String, nominal: &DhTable<MAX_JOINTS>, c: &Calibration) {
    out.push_str(
        "<table class=\"params\"><thead><tr><th>parameter</th><th>unit</th><th>nominal</th>\
         <th>least squares</th><th>± σ (LS)</th><th>calibrated</th><th>± σ (EM, CRB)</th>\
         <th>change</th></tr></thead><tbody>\n",
    );
    let em_std = c.em.as_ref().ok().map(|em| em.std_errors);
    for p in (0..MAX_PARAMS).filter(|p| p % MAX_JOINTS < c.joints) {
        let unit = if p < 2 * MAX_JOINTS { "mm" } else { "°" };
        let nom = display(p, param_value(nominal, p));
        let ls = display(p, param_value(&c.ls.table, p));
        let cal = display(p, param_value(&c.calibrated, p));
        let ls_sd = display(p, c.ls.std_errors[p]);
        let em_sd = em_std.map_or("—".to_string(), |s| format!("{:.3}", display(p, s[p])));
        let change = cal - nom;
        let strong = match em_std {
            Some(s) if change.abs() > 3.0 * display(p, s[p]) => " class=\"sig\"",
            _ => "",
        };
        let _ = writeln!(
            out,
            "<tr><td>{}</td><td>{unit}</td><td>{nom:.3}</td><td>{ls:.3}</td><td>{ls_sd:.3}</td>\
             <td><b>{cal:.3}</b></td><td>{em_sd}</td><td{strong}>{change:+.3}</td></tr>",
            param_name(p)
        );
    }
    out.push_str("</tbody></table>\n");
}

fn correlation_table(out: &mut String, c: &Calibration) {
    if c.correlations.is_empty() {
        out.push_str("<p class=\"note\">No correlations: no parameter is identifiable.</p>");
        return;
    }
    out.push_str(
        "<table class=\"corr\"><thead><tr><th>pair</th><th>r</th><th></th></tr></thead><tbody>\n",
    );
    for k in &c.correlations {
        let w = (k.r.abs() * 100.0).round();
        let colour = if k.r >= 0.0 { "#1f77b4" } else { "#d62728" };
        let _ = writeln!(
            out,
            "<tr><td>{} – {}</td><td>{:+.3}</td><td><span class=\"bar\" style=\"width:{w}px;background:{colour}\"></span></td></tr>",
            param_name(k.first),
            param_name(k.second),
            k.r
        );
    }
    out.push_str("</tbody></table>\n");
}

/// The data-quality table, stream table and excitation chart of `all` (`split`: how many were
/// fitted and held out, when a calibration ran); returns the chart for the caller to place.
fn quality_section(
    out: &mut String,
    q: &Quality,
    all: &[TimedSample],
    split: Option<(usize, usize)>,
) -> Result<String, PlotError> {
    out.push_str("<div class=\"pair\"><table class=\"kv\"><tbody>\n");
    let _ = writeln!(
        out,
        "<tr><th>session length</th><td>{:.1} s</td></tr>",
        q.duration_s
    );
    let _ = writeln!(
        out,
        "<tr><th>grid rate</th><td>{:.1} Hz</td></tr>",
        q.grid_hz
    );
    let _ = match split {
        Some((fitted, held)) => writeln!(
            out,
            "<tr><th>aligned samples</th><td>{} ({fitted} fitted, {held} held out)</td></tr>",
            all.len(),
        ),
        None => writeln!(
            out,
            "<tr><th>aligned samples</th><td>{}</td></tr>",
            all.len()
        ),
    };
    let _ = writeln!(
        out,
        "<tr><th>grid points excluded as gaps</th><td>{}</td></tr>",
        q.gaps
    );
    if q.receiver_stalls > 0 {
        let longest = q
            .longest_stall_ms
            .map_or(String::new(), |ms| format!(" (longest {ms:.0} ms)"));
        let _ = writeln!(
            out,
            "<tr><th>receiver stalls</th><td>{}{longest}</td></tr>",
            q.receiver_stalls
        );
    }
    for (k, v) in &q.counters {
        let _ = writeln!(out, "<tr><th>{}</th><td>{v}</td></tr>", esc(k));
    }
    out.push_str("</tbody></table>\n");
    let exc = excitation(all, &q.joint_ranges);
    let labels: Vec<String> = (1..=exc.len()).map(|j| format!("joint {j}")).collect();
    let chart = bars(
        "excitation",
        &labels,
        &exc,
        q.excitation_required,
        (HALF, 300),
    );
    out.push_str("</div>\n");
    if !q.streams.is_empty() {
        out.push_str(
            "<table class=\"streams\"><thead><tr><th>stream</th><th>samples</th><th>rate</th>\
             <th>loss</th><th>excluded</th><th>clock jumps</th><th>skew</th><th>clock jitter</th>\
             </tr></thead><tbody>\n",
        );
        for s in &q.streams {
            let opt = |v: Option<f64>, unit: &str, digits: usize| {
                v.map_or("—".into(), |v| format!("{v:.digits$} {unit}"))
            };
            let _ = writeln!(
                out,
                "<tr><td>{}</td><td>{}</td><td>{:.1} Hz</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                esc(&s.name),
                s.samples,
                s.rate_hz,
                opt(s.loss.map(|l| l * 100.0), "%", 2),
                s.excluded,
                s.jumps,
                opt(s.skew_ppm, "ppm", 1),
                opt(s.jitter_us, "µs", 0),
            );
        }
        out.push_str("</tbody></table>\n");
    }
    chart
}

const STYLE: &str = "
:root { --ink:#1d2330; --muted:#5b6475; --line:#dfe3ea; --ok:#2c9c2c; --bad:#d62728; --blue:#1f77b4; }
* { box-sizing: border-box; }
body { margin:0; font:15px/1.5 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif; color:var(--ink); background:#f4f6f9; }
main { max-width:1100px; margin:0 auto; padding:24px 28px 60px; background:#fff; box-shadow:0 0 24px rgba(0,0,0,.06); }
h1 { font-size:26px; margin:0 0 4px; }
h2 { font-size:19px; margin:36px 0 10px; padding-bottom:6px; border-bottom:2px solid var(--line); }
.sub { color:var(--muted); margin:0 0 16px; }
.verdict { padding:12px 16px; border-radius:8px; margin:12px 0 18px; font-weight:600; }
.verdict.ok { background:#e8f6e8; color:#1d6b1d; border:1px solid #b9e2b9; }
.verdict.bad { background:#fdecec; color:#8d1a1a; border:1px solid #f3bcbc; }
.verdict.none { background:#eef1f5; color:var(--muted); border:1px solid var(--line); }
.verdict ul { margin:6px 0 0; font-weight:400; }
.cards { display:grid; grid-template-columns:repeat(auto-fill,minmax(200px,1fr)); gap:12px; }
.card { border:1px solid var(--line); border-radius:8px; padding:10px 14px; }
.card .v { font-size:22px; font-weight:650; }
.card .k { color:var(--muted); font-size:13px; }
figure.plot { margin:14px 0; }
figure.plot svg { display:block; max-width:100%; height:auto; }
figcaption { color:var(--muted); font-size:13px; margin-top:4px; }
.pair { display:flex; gap:10px; flex-wrap:wrap; align-items:flex-start; }
.missing { padding:30px; border:2px dashed var(--bad); color:var(--bad); border-radius:8px; }
table { border-collapse:collapse; font-size:13.5px; margin:8px 0; }
caption { text-align:left; font-weight:600; margin-bottom:4px; }
th, td { padding:4px 10px; border-bottom:1px solid var(--line); text-align:right; }
th:first-child, td:first-child { text-align:left; }
thead th { background:#f7f8fa; }
table.kv th { text-align:left; font-weight:500; color:var(--muted); }
td.sig { color:var(--blue); font-weight:650; }
table.push tr.bad td { color:var(--bad); font-weight:650; }
.bar { display:inline-block; height:10px; border-radius:2px; }
.note { color:var(--muted); font-size:13px; }
.legend { display:flex; flex-wrap:wrap; gap:4px 14px; font-size:13px; margin:2px 0 0 62px; }
.legend .key { display:inline-flex; align-items:center; gap:6px; }
.legend i { display:inline-block; width:18px; }
.legend i.line { height:3px; }
.legend i.area { height:10px; opacity:0.6; }
footer { margin-top:40px; color:var(--muted); font-size:12.5px; }
@media print { body { background:#fff; } main { box-shadow:none; } }
";

/// The document's head, its title as the headline, and where the data came from.
fn page_head(out: &mut String, title: &str, source: &str) {
    let _ = write!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>{}</title><style>{STYLE}</style></head><body><main>\n",
        esc(title)
    );
    let _ = writeln!(
        out,
        "<h1>{}</h1><p class=\"sub\">{} · exocal {}</p>",
        esc(title),
        esc(source),
        env!("CARGO_PKG_VERSION")
    );
}

const EXCITATION_CAPTION: &str = "Share of each joint's anatomical range the session visited \
     (excitation); the line is what the session rules require.";

/// The report of a session that ended without a calibration: the reasons, then the same data
/// quality section as [`render`]'s (session length, streams, excitation), so the user sees what
/// the motion lacked.
pub fn render_session(input: &SessionInput) -> String {
    let mut out = String::with_capacity(1 << 16);
    page_head(&mut out, &input.title, &input.source);
    out.push_str(if input.interrupted {
        "<div class=\"verdict bad\">Stopped before calibrating (SIGTERM or SIGINT): nothing is \
         pushed. The log holds every frame received; <code>exocald offline</code> on it calibrates \
         what was collected.<ul>"
    } else {
        "<div class=\"verdict bad\">Not calibrated: the session does not meet the session rules; \
         nothing is pushed.<ul>"
    });
    for r in &input.reasons {
        let _ = write!(out, "<li>{}</li>", esc(r));
    }
    out.push_str("</ul></div>\n<h2>Data quality</h2>\n");
    let exc = quality_section(&mut out, &input.quality, &input.samples, None);
    figure(&mut out, FIGURES[6], EXCITATION_CAPTION, exc);
    let _ = writeln!(
        out,
        "<footer>Generated by exocal-report {}.</footer>",
        env!("CARGO_PKG_VERSION")
    );
    out.push_str("</main></body></html>\n");
    out
}

/// The report as one HTML document (see the module docs).
pub fn render(input: &ReportInput) -> String {
    let c = &input.calibration;
    let mut out = String::with_capacity(1 << 20);
    page_head(&mut out, &input.title, &input.source);
    match (&input.verdict, &input.push) {
        (Some(v), push) if v.accepted => push_banner(&mut out, push.as_deref()),
        (Some(v), _) => {
            out.push_str("<div class=\"verdict bad\">Refused: the table is not pushed.<ul>");
            for r in &v.reasons {
                let _ = write!(out, "<li>{}</li>", esc(r));
            }
            out.push_str("</ul></div>\n");
        }
        (None, _) => {
            out.push_str("<div class=\"verdict none\">Not validated (offline analysis).</div>\n")
        }
    }
    for moved in input.verdict.iter().flat_map(|v| &v.onto_bounds) {
        let _ = writeln!(
            out,
            "<p class=\"note\">Onto its bound: {} (the expected table error includes the move).</p>",
            esc(moved)
        );
    }

    // Key numbers.
    let eval = if input.held_out.is_empty() {
        &input.fit
    } else {
        &input.held_out
    };
    let before = residuals(&input.nominal, eval);
    let after = residuals(held_out_table(input), eval);
    let (pb, pa) = (
        mean(before.iter().map(|r| r.0)),
        mean(after.iter().map(|r| r.0)),
    );
    let (rb, ra) = (
        mean(before.iter().map(|r| r.1)),
        mean(after.iter().map(|r| r.1)),
    );
    let slice = if input.held_out.is_empty() {
        "fitted"
    } else {
        "held-out"
    };
    let card = |out: &mut String, v: String, k: String| {
        let _ = write!(
            out,
            "<div class=\"card\"><div class=\"v\">{v}</div><div class=\"k\">{k}</div></div>"
        );
    };
    out.push_str("<div class=\"cards\">");
    card(
        &mut out,
        format!("{pb:.2} → {pa:.2} mm"),
        format!("mean position error, {slice}"),
    );
    card(
        &mut out,
        format!("{rb:.1} → {ra:.1} mrad"),
        format!("mean rotation error, {slice}"),
    );
    card(
        &mut out,
        format!("{:.0} %", 100.0 * (1.0 - pa / pb)),
        "position error removed".into(),
    );
    if let Some(e) = c.stated {
        let how = match &c.em {
            Ok(_) => "expected table error (1σ: the Cramér-Rao bound with the drift-model choice)",
            Err(_) => {
                "expected table error (1σ, least squares with white residuals: the EM failed)"
            }
        };
        card(
            &mut out,
            format!(
                "±{:.2} mm, ±{:.2} mrad",
                e.position_m * 1e3,
                e.rotation_rad * 1e3
            ),
            how.into(),
        );
    }
    card(
        &mut out,
        format!("{:.1}", c.ls.condition),
        format!("condition number (rank {}/{})", c.ls.rank, 4 * c.joints),
    );
    card(
        &mut out,
        format!("{} / {}", input.fit.len(), input.held_out.len()),
        "samples fitted / held out".into(),
    );
    match &c.em {
        Ok(em) => card(
            &mut out,
            format!(
                "{} iterates{}",
                em.log_likelihood.len(),
                if em.converged { "" } else { " (limit)" }
            ),
            format!(
                "EM: accepted iterates (of {} maps: accelerated steps, refits and the robust \
                 pass included)",
                em.iterations
            ),
        ),
        Err(_) => card(&mut out, "failed".into(), "EM (LS table used)".into()),
    }
    out.push_str("</div>\n");
    let _ = writeln!(
        out,
        "<p class=\"note\">The figure to judge the table by is the expected table error: how far \
         the calibrated arm's pose is expected to be from the true arm's on fresh poses (1σ, \
         RMS over the workspace). The {slice} errors above are measured against the reference and \
         include that slice's own drift and reference noise; the console's \"held-out mean \
         error\" line gives the same figures.</p>"
    );

    // The table itself right after the verdict and the key numbers: what was pushed, what
    // changed and by how much.
    out.push_str("<h2>Parameters</h2>\n");
    out.push_str(
        "<p class=\"note\">Standard D-H parameters per joint. σ (LS) is the white-noise standard \
         deviation from the least-squares information matrix; σ (EM, CRB) the Cramér–Rao bound \
         under the fitted drift model. Changes larger than 3σ (EM) are highlighted.</p>\n",
    );
    parameter_table(&mut out, &input.nominal, c);
    out.push_str("<h3>Strongest correlations</h3>\n");
    correlation_table(&mut out, c);
    match &input.push {
        Some(push) => push_table(&mut out, push),
        None => out.push_str(PUSH_MARK),
    }

    out.push_str("<h2>Error over time</h2>\n");
    figure(
        &mut out,
        FIGURES[0],
        "The end effector's pose error, measured against the nominal and the calibrated models' \
         forward kinematics of the same joint readings, sample by sample (cf. the paper's Figs. 3, \
         4 and 7). The calibrated table here is the one fitted without the shaded held-out slice, \
         which judged it.",
        error_over_time(input),
    );
    figure(
        &mut out,
        FIGURES[1],
        "The measured trajectory and the two models' on two planes of the base frame.",
        trajectories(input),
    );

    let (pos, rot, which) = residual_charts(input);
    let _ = writeln!(out, "<h2>Residuals before and after ({which})</h2>");
    out.push_str("<div class=\"pair\">");
    let caption = |what: &str, unit: &str, h: &Histogram| match h {
        Ok((_, b)) => format!("{what} {}", bins_caption(b, unit)),
        Err(_) => what.to_string(),
    };
    figure(
        &mut out,
        FIGURES[2],
        &caption(
            "Position error per sample (pose error in the model's tool frame).",
            "mm",
            &pos,
        ),
        pos.map(|(svg, _)| svg),
    );
    figure(
        &mut out,
        FIGURES[3],
        &caption(
            "Rotation error per sample (rotation-vector norm).",
            "mrad",
            &rot,
        ),
        rot.map(|(svg, _)| svg),
    );
    out.push_str("</div>\n");

    out.push_str("<h2>Drift EM</h2>\n");
    let (ll, drift) = em_charts(input);
    out.push_str("<div class=\"pair\">");
    figure(
        &mut out,
        FIGURES[4],
        "Log-likelihood at each EM iteration (cf. the paper's Figs. 5 and 8), as its gain since the \
         first iterate of its objective: the EM's objective changes when it moves to finer samples \
         or refits the rate bias's prior, and likelihoods compare only within one. Within one it \
         never decreases.",
        ll,
    );
    if let Ok(em) = &c.em {
        drift_table(&mut out, em);
    }
    out.push_str("</div>\n");
    if let Ok(em) = &c.em {
        ls_against_em(&mut out, em);
    }
    if let Some(r) = &input.at_rest {
        at_rest(&mut out, r);
    }
    figure(
        &mut out,
        FIGURES[5],
        "Each joint's smoothed drift estimate over the samples the EM ran on (Gauss–Markov \
         model, Kalman filter and RTS smoother), one panel per joint, each on its own scale.",
        drift,
    );

    out.push_str("<h2>Data quality</h2>\n");
    let exc = quality_section(
        &mut out,
        &input.quality,
        &all_samples(input),
        Some((input.fit.len(), input.held_out.len())),
    );
    figure(&mut out, FIGURES[6], EXCITATION_CAPTION, exc);
    let _ =
        writeln!(
        out,
        "<footer>LS: {} iterations, RMS residual {:.3e}. {}Generated by exocal-report {}.</footer>",
        c.ls.iterations,
        c.ls.rms,
        match &c.em {
            Ok(em) => format!(
                "EM: {} accepted iterates ({} maps) over {} objective(s), final objective's log-likelihood {:.1} → {:.1}. ",
                em.log_likelihood.len(),
                em.iterations,
                em.objectives.len() + 1,
                em.last_objective().first().copied().unwrap_or(f64::NAN),
                em.last_objective().last().copied().unwrap_or(f64::NAN)
            ),
            Err(e) => format!("EM failed ({}); the LS table is the result. ", esc(&e.to_string())),
        },
        env!("CARGO_PKG_VERSION")
    );
    out.push_str("</main></body></html>\n");
    out
}

/// Marks where [`with_push`] puts the push's outcome in a report rendered before the push.
const PUSH_MARK: &str = "<!-- exocal: the push's outcome -->\n";

/// The banner of a validated table: pushed (every node holds it), pushed in part (naming the
/// nodes that do not), or not yet pushed.
fn push_banner(out: &mut String, push: Option<&[NodePush]>) {
    out.push_str("<div class=\"verdict");
    match push {
        Some(push) if push.iter().all(|n| n.holds == "new") => {
            let _ = write!(
                out,
                " ok\">Validated and pushed: every node ({}) holds the calibrated table, its CRC \
                 read back (<a href=\"#push\">push</a>).",
                push.len()
            );
        }
        Some(push) => {
            let short: Vec<String> = push
                .iter()
                .filter(|n| n.holds != "new")
                .map(|n| format!("{} holds the {} table", esc(&n.node), esc(&n.holds)))
                .collect();
            let _ = write!(
                out,
                " bad\">Validated, but the push did not complete: {} (<a href=\"#push\">push</a>).",
                short.join("; ")
            );
        }
        None => out.push_str(
            " ok\">Validated: the calibrated table may be pushed (not pushed when this report was \
             written: the push's outcome is added here after it; a dry run and an offline run \
             push nothing).",
        ),
    }
    out.push_str("</div>\n");
}

/// `html`, a validated table's report rendered before the push ([`render`] without
/// `push`), with the push's outcome: its banner replaced and the push table added. Nothing is
/// re-rendered (the plots stay as they are), so this is cheap on a slow controller. `None`
/// when `html` is not such a report.
pub fn with_push(html: &str, push: &[NodePush]) -> Option<String> {
    let mut before = String::new();
    push_banner(&mut before, None);
    let at = html.find(&before)?;
    let mark = html.find(PUSH_MARK)?;
    let mut after = String::new();
    push_banner(&mut after, Some(push));
    let mut table = String::new();
    push_table(&mut table, push);
    Some(format!(
        "{}{after}{}{table}{}",
        &html[..at],
        &html[at + before.len()..mark],
        &html[mark + PUSH_MARK.len()..]
    ))
}

/// The push's outcome per node: which table it holds (new, old, unknown), the CRC sent and the
/// CRC it reported, whether that answer was authenticated, the attempts and the last failure.
fn push_table(out: &mut String, push: &[NodePush]) {
    out.push_str(
        "<h2 id=\"push\">Push</h2>\n<p class=\"note\">Per node, after the push: the table it \
         holds (<b>new</b>: committed and its CRC read back identical; <b>old</b>: its previous \
         table; <b>unknown</b>: no answer settles it), the CRC sent and the CRC it reported \
         (authenticated: in an answer carrying the node's MAC over the daemon's nonce).</p>\n\
         <table class=\"push\"><tr><th>node</th><th>holds</th><th>CRC sent</th>\
         <th>CRC held</th><th>authenticated</th><th>attempts</th><th>last failure</th></tr>\n",
    );
    for n in push {
        let held = n
            .held_crc
            .map_or_else(|| "none".to_string(), |c| format!("{c:#010x}"));
        let class = if n.holds == "new" {
            ""
        } else {
            " class=\"bad\""
        };
        let _ = writeln!(
            out,
            "<tr{class}><td>{}</td><td>{}</td><td><code>{:#010x}</code></td>\
             <td><code>{held}</code></td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&n.node),
            esc(&n.holds),
            n.new_crc,
            if n.authenticated { "yes" } else { "no" },
            n.attempts,
            esc(&n.error)
        );
    }
    out.push_str("</table>\n");
}

/// The unaided joints' gyro bias measured at rest: per joint, the bias and its standard error,
/// and how long the suit was still; or that it never was, and what that leaves in the table.
fn at_rest(out: &mut String, r: &AtRest) {
    out.push_str("<h3>Gyro bias at rest</h3>\n");
    if r.runs == 0 {
        let _ = writeln!(out, "<p class=\"note\">{}.</p>", esc(&r.to_string()));
        return;
    }
    let _ = writeln!(
        out,
        "<p class=\"note\">The suit was still for {:.1} s ({} run{}): there the unaided joints' \
         gyros read their bias alone. It was taken out of their readings before least squares \
         and the EM, and what is left of it (its standard error) is the rate-bias spec the \
         stated error allows for.</p>",
        r.still_s,
        r.runs,
        if r.runs == 1 { "" } else { "s" }
    );
    out.push_str(
        "<table class=\"at-rest\"><thead><tr><th>joint</th><th>bias (°/s)</th>\
         <th>standard error (°/s)</th></tr></thead><tbody>",
    );
    for j in (0..r.joints.len()).filter(|&j| r.joints[j]) {
        let _ = write!(
            out,
            "<tr><td>{}</td><td>{:+.4}</td><td>{:.4}</td></tr>",
            j + 1,
            r.bias_deg_s[j],
            r.se_deg_s[j]
        );
    }
    out.push_str("</tbody></table>\n");
}

/// Each joint's fitted τ and σ, with their 95% intervals when the EM gave their confidence.
fn drift_table(out: &mut String, em: &EmDetail) {
    let ci = em.drift_confidence.is_some();
    out.push_str("<table class=\"drift\"><thead><tr><th>joint</th><th>τ (s)</th>");
    if ci {
        out.push_str("<th>τ 95%</th>");
    }
    out.push_str("<th>σ (mrad, stationary)</th>");
    if ci {
        out.push_str("<th>σ 95%</th>");
    }
    out.push_str("<th>σ (paper, eq. 8, rad/s)</th><th>model (and why)</th></tr></thead><tbody>");
    let range = |(lo, hi): (f64, f64), scale: f64, p: usize| {
        if hi.is_finite() {
            format!("{:.p$}–{:.p$}", lo * scale, hi * scale)
        } else {
            "unbounded".to_string()
        }
    };
    for (j, d) in em.drift.iter().enumerate() {
        let _ = write!(out, "<tr><td>{}</td><td>{:.3}</td>", j + 1, d.tau);
        let c = em.drift_confidence.as_ref().map(|c| c[j]);
        if let Some(c) = c {
            let _ = write!(out, "<td>{}</td>", range(c.tau_interval(Z_95), 1.0, 3));
        }
        let _ = write!(out, "<td>{:.2}</td>", d.stationary_sigma * 1e3);
        if let Some(c) = c {
            let _ = write!(out, "<td>{}</td>", range(c.sigma_interval(Z_95), 1e3, 2));
        }
        let _ = write!(
            out,
            "<td>{:.3}</td><td>{}</td></tr>",
            d.paper_sigma,
            esc(&em.models[j].to_string())
        );
    }
    out.push_str("</tbody></table>");
    let d = &em.discounted;
    let glitches = if d.count == 0 {
        "none".to_string()
    } else {
        format!(
            "{} of {} samples in {} run(s) (Student-t ν {:.1})",
            d.count,
            d.samples,
            d.runs.len(),
            d.dof
        )
    };
    let _ = write!(
        out,
        "<p class=\"note\">Each joint keeps the paper's Gauss-Markov drift unless the data (BIC) or \
         the sensors' spec (<code>[sensors]</code>) support a rate bias on top. Reference poses \
         discounted as glitches (heavy-tailed model): {glitches}. Consistency (long-run variance \
         of each joint's normalised drift innovations, 1 under the model): {}.</p>",
        em.consistency
            .iter()
            .map(|c| format!("{:.2}", c.long_run))
            .collect::<Vec<_>>()
            .join(" ")
    );
    if ci {
        out.push_str(
            "<p class=\"note\">95% intervals from the curvature of the likelihood (calib-core's \
             <code>drift_confidence</code>). Checked by Monte Carlo on sessions of 120 τ, they \
             cover the truth about 90% of the time (τ 91%, σ 89%: calib-core/README.md, \
             <code>drift-coverage</code>); on sessions shorter than about 100 τ they are \
             optimistic.</p>",
        );
    }
}

/// This session's LS against our EM: the accuracy each table is expected to have (1σ) under the
/// drift and noise the EM fitted, and how far apart the two tables are.
fn ls_against_em(out: &mut String, em: &EmDetail) {
    let fmt = |e: TableError| {
        format!(
            "±{:.2} mm, ±{:.2} mrad",
            e.position_m * 1e3,
            e.rotation_rad * 1e3
        )
    };
    out.push_str(
        "<table class=\"drift\"><caption>LS against our EM</caption><thead><tr><th>this session</th><th>expected table error (1σ)</th></tr></thead><tbody>",
    );
    let versus = em.versus_ls;
    let kept = em.ls_kept();
    let _ = write!(
        out,
        "<tr><td>LS alone (weighs the drift as white noise){}</td><td>{}</td></tr>",
        if kept { ", pushed" } else { "" },
        versus.map_or(
            "— (normal equations too ill-conditioned)".to_string(),
            |v| fmt(v.ls_expected)
        )
    );
    let _ = write!(
        out,
        "<tr><td>our EM{} (stated: its Cramér-Rao bound with the drift-model choice)</td><td>{}</td></tr>",
        if kept { ", not pushed: its table disagrees with LS's" } else { ", pushed" },
        fmt(em.stated_error)
    );
    if em.allowance.position_m > 0.0 {
        let _ = write!(
            out,
            "<tr><td>what a rate bias of {} °/s, too small for the session to show, would add \
             (the sensors' spec, <code>[sensors]</code>, is not configured)</td><td>{}</td></tr>",
            exocal_session::rules::UNCONFIGURED_RATE_BIAS_DEG_S,
            fmt(em.allowance)
        );
    }
    let apart = versus.map_or(String::new(), |v| {
        format!(
            "; the LS table's FK differs from the EM table's by {:.2} mm, {:.2} mrad RMS there \
             ({:.1} times what the EM's model lets it be, squared: {}; above {} the EM's model \
             does not hold for the session and LS's table is the one pushed)",
            v.difference.position_m * 1e3,
            v.difference.rotation_rad * 1e3,
            v.statistic,
            if kept { "disagreeing" } else { "agreeing" },
            calib_core::MAX_EM_LS_STATISTIC
        )
    });
    let _ = write!(
        out,
        "</tbody></table><p class=\"note\">Both under the drift (τ, σ per joint) and pose noise the EM fitted, over poses spread over the joint ranges{apart}. \
         The calibrate-many-sessions view of the same comparison (LS, our EM and the bound against known true tables) is calib-core's sweep.</p>"
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::{JointRanges, ScenarioConfig};

    #[test]
    fn a_session_without_a_calibration_reports_why_and_its_data() {
        let cfg = ScenarioConfig::paper();
        let samples: Vec<TimedSample> = TimedSample::simulated(cfg, 3, 300);
        let html = render_session(&SessionInput {
            title: "offline <short>".into(),
            source: "offline: short.csv (CSV)".into(),
            reasons: vec!["the recording is 3.0 s long, session.min_duration_s is 60 s".into()],
            interrupted: false,
            samples,
            quality: Quality {
                duration_s: 3.0,
                grid_hz: 100.0,
                gaps: 0,
                counters: Vec::new(),
                streams: Vec::new(),
                joint_ranges: JointRanges::<MAX_JOINTS>::paper().limits.to_vec(),
                excitation_required: Some(0.5),
                receiver_stalls: 0,
                longest_stall_ms: None,
            },
        });
        assert!(html.contains("offline &lt;short&gt;"), "title not escaped");
        assert!(html.contains("Not calibrated"));
        assert!(
            html.contains("<li>the recording is 3.0 s long, session.min_duration_s is 60 s</li>")
        );
        assert!(html.contains("<tr><th>aligned samples</th><td>300</td></tr>"));
        let at = html
            .find("id=\"fig-excitation\"")
            .expect("the excitation figure");
        assert!(html[at..].contains("<svg"), "excitation not drawn");
        assert!(!html.contains("class=\"missing\""));
    }

    #[test]
    fn receiver_stalls_are_one_row_only_when_there_were_some() {
        let q = |receiver_stalls, longest_stall_ms| Quality {
            duration_s: 1.0,
            grid_hz: 100.0,
            joint_ranges: JointRanges::<MAX_JOINTS>::paper().limits.to_vec(),
            receiver_stalls,
            longest_stall_ms,
            ..Quality::default()
        };
        let row = |q: &Quality| {
            let mut out = String::new();
            quality_section(&mut out, q, &[], None).unwrap();
            out.lines()
                .find(|l| l.contains("receiver stalls"))
                .map(str::to_string)
        };
        assert_eq!(
            row(&q(2, Some(412.4))).as_deref(),
            Some("<tr><th>receiver stalls</th><td>2 (longest 412 ms)</td></tr>")
        );
        assert_eq!(row(&q(0, None)), None);
    }

    #[test]
    fn the_gyro_at_rest_shows_each_unaided_joints_bias_or_that_the_suit_was_never_still() {
        let nan = f64::NAN;
        let mut r = AtRest {
            still_s: 4.56,
            runs: 2,
            joints: vec![true, false, true, false, false, false, false],
            bias_deg_s: vec![0.0251, nan, -0.0183, nan, nan, nan, nan],
            se_deg_s: vec![0.0041, nan, 0.0052, nan, nan, nan, nan],
        };
        let mut out = String::new();
        at_rest(&mut out, &r);
        assert!(out.contains("still for 4.6 s (2 runs)"), "{out}");
        let rows: Vec<&str> = out.matches("<tr><td>").collect();
        assert_eq!(rows.len(), 2, "a row per unaided joint: {out}");
        assert!(out.contains("<tr><td>1</td><td>+0.0251</td><td>0.0041</td></tr>"));
        assert!(out.contains("<tr><td>3</td><td>-0.0183</td><td>0.0052</td></tr>"));
        r.runs = 0;
        let mut out = String::new();
        at_rest(&mut out, &r);
        assert!(out.contains("never still for"), "{out}");
        assert!(out.contains("joints 1, 3 not measured"), "{out}");
        assert!(!out.contains("<table"));
    }
}
