//! The report opens in a real browser (headless Chromium) with every plot present and drawn,
//! on a session whose nominal table is far off (a large nominal error beside a small calibrated
//! one, a log-likelihood in the hundreds of thousands): every axis's tick labels differ from
//! their neighbours, and each residual histogram's bins cover both series (its caption says to
//! what value; the test checks it against the samples), or show the overflow explicitly.
//!
//! Needs Debian's `chromium` (`apt-get install -y chromium`) or `EXOCAL_CHROMIUM=/path/to/it`;
//! without it the test fails, saying so (it never passes silently).

use std::path::PathBuf;
use std::process::Command;

use calib_core::{DhTable, DriftEmOptions, JointRanges, LsOptions, ScenarioConfig};
use exocal_report::html::{render, residuals, FIGURES};
use exocal_report::{Quality, ReportInput, StreamQuality, TimedSample, VerdictSummary};

fn chromium() -> PathBuf {
    if let Some(p) = std::env::var_os("EXOCAL_CHROMIUM") {
        return p.into();
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser"] {
            let p = dir.join(name);
            if p.is_file() {
                return p;
            }
        }
    }
    panic!(
        "headless Chromium is required for this test: install it with `apt-get install -y chromium` \
         (Debian) or set EXOCAL_CHROMIUM to the browser's path"
    );
}

/// Samples in the test's session (a minute at 100 Hz, as a live session has).
const SAMPLES: usize = 6000;

/// A simulated session calibrated for real (EM capped to keep the test fast) from a nominal
/// table 3 cm and 2° off on every row, so the nominal error is large.
fn input() -> ReportInput {
    let cfg = ScenarioConfig::paper();
    let all: Vec<TimedSample> = TimedSample::simulated(cfg, 11, SAMPLES);
    let (fit, held) = all.split_at(SAMPLES * 4 / 5);
    let mut nominal = DhTable::paper_nominal();
    for row in &mut nominal.rows {
        row.a += 0.03;
        row.theta_offset += 2f64.to_radians();
    }
    let samples: Vec<_> = fit.iter().map(|s| s.sample).collect();
    let em = DriftEmOptions {
        max_iterations: 8,
        ..DriftEmOptions::new(cfg.drift.dt)
    };
    let calibration = exocal_session::pipeline::ls_then_em::<7, 28>(
        &nominal,
        &samples,
        &LsOptions::new(),
        &em,
        true,
    )
    .unwrap();
    assert!(
        calibration.em.is_ok(),
        "{:?}",
        calibration.em.as_ref().err()
    );
    let stream = |name: &str| StreamQuality {
        name: name.into(),
        samples: SAMPLES,
        rate_hz: 100.0,
        loss: Some(0.0),
        excluded: 0,
        jumps: 0,
        skew_ppm: Some(12.5),
        jitter_us: Some(80.0),
    };
    ReportInput {
        title: "browser test <&> report".into(),
        source: "calib-core scenario, seed 11".into(),
        nominal,
        calibration,
        judged: None,
        fit: fit.to_vec(),
        held_out: held.to_vec(),
        quality: Quality {
            duration_s: SAMPLES as f64 * cfg.drift.dt,
            grid_hz: 100.0,
            gaps: 0,
            counters: vec![("frames received".into(), 3200), ("unknown".into(), 0)],
            streams: vec![stream("Joint1"), stream("EndEffector")],
            joint_ranges: JointRanges::<7>::paper().limits.to_vec(),
            excitation_required: Some(0.5),
            receiver_stalls: 0,
            longest_stall_ms: None,
        },
        verdict: Some(VerdictSummary {
            onto_bounds: Vec::new(),
            accepted: false,
            reasons: vec!["a test reason".into()],
        }),
        at_rest: None,
        push: None,
    }
}

/// The text of `<figure … id="{id}"> … </figure>` in `dom`.
fn figure<'a>(dom: &'a str, id: &str) -> &'a str {
    let start = dom
        .find(&format!("id=\"{id}\""))
        .unwrap_or_else(|| panic!("figure {id} is missing from the browser's DOM"));
    let end = dom[start..].find("</figure>").expect("unclosed figure") + start;
    &dom[start..end]
}

/// The SVG text elements of `fig`: (x, y, text-anchor, content).
fn texts(fig: &str) -> Vec<(String, String, String, String)> {
    let attr = |tag: &str, name: &str| {
        tag.split(&format!(" {name}=\""))
            .nth(1)
            .map_or(String::new(), |v| v[..v.find('"').unwrap_or(0)].to_string())
    };
    fig.split("<text")
        .skip(1)
        .map(|t| {
            let (tag, rest) = t.split_once('>').unwrap_or((t, ""));
            let content = rest[..rest.find("</text>").unwrap_or(rest.len())].trim();
            (
                attr(tag, "x"),
                attr(tag, "y"),
                attr(tag, "text-anchor"),
                content.to_string(),
            )
        })
        .collect()
}

/// The tick labels of each axis of `fig`: runs of numbers, in document order, in a row (same
/// y: an x axis) or right-aligned in a column (same x: a y axis), of at least three. (Stacked
/// panels put their axes at the same place: each panel's labels are one run.)
fn axes(fig: &str) -> Vec<Vec<String>> {
    let mut runs: Vec<((bool, String), Vec<String>)> = Vec::new();
    for (x, y, anchor, text) in texts(fig) {
        if text.parse::<f64>().is_err() {
            runs.push(((false, String::new()), Vec::new()));
            continue;
        }
        let key = if anchor == "end" {
            (true, x)
        } else {
            (false, y)
        };
        match runs.last_mut() {
            Some((k, labels)) if *k == key => labels.push(text),
            _ => runs.push((key, vec![text])),
        }
    }
    runs.into_iter()
        .map(|(_, labels)| labels)
        .filter(|l| l.len() >= 3)
        .collect()
}

/// The upper end of a histogram's bins, as its caption states it; `None` for an overflow bar.
fn bins_upper_end(fig: &str) -> Option<f64> {
    let caption = &fig[fig.find("<figcaption>").expect("a caption")..];
    let (_, rest) = caption
        .split_once("Bins from ")
        .expect("the caption states the bins");
    let hi = rest.split(" to ").nth(1).expect("bins' upper end");
    let (hi, tail) = hi.split_once(' ').unwrap();
    if tail.contains("every sample of both series") {
        Some(hi.parse().unwrap())
    } else {
        assert!(tail.contains("&gt;"), "{caption}");
        None
    }
}

/// Points drawn by the figure's polylines.
fn polyline_points(fig: &str) -> usize {
    fig.split("<polyline")
        .skip(1)
        .map(|p| {
            let attr = p.split("points=\"").nth(1).unwrap_or("");
            attr[..attr.find('"').unwrap_or(0)]
                .split_whitespace()
                .count()
        })
        .sum()
}

/// A script run at load: every legend (`div.legend`, HTML after its chart) is marked
/// `data-overlap="1"` if the browser lays it out over its chart's SVG, else `"0"`.
const LAYOUT_CHECK: &str = "<script>for (const l of document.querySelectorAll('div.legend')) {\
  const svg = l.previousElementSibling; const a = l.getBoundingClientRect();\
  const b = svg.getBoundingClientRect();\
  const over = a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom;\
  l.setAttribute('data-overlap', over ? '1' : '0'); }</script>";

/// `html` (with [`LAYOUT_CHECK`]) as headless Chromium's DOM after loading it.
fn dump_dom(dir: &std::path::Path, name: &str, html: &str) -> String {
    let browser = chromium();
    std::fs::create_dir_all(dir).unwrap();
    let page = dir.join(format!("{name}.html"));
    std::fs::write(
        &page,
        html.replace("</body>", &format!("{LAYOUT_CHECK}</body>")),
    )
    .unwrap();
    let profile = dir.join(format!("profile-{name}"));
    let out = Command::new(&browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--no-first-run",
            "--disable-component-update",
            "--disable-sync",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("--dump-dom")
        .arg(format!("file://{}", page.display()))
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", browser.display()));
    assert!(
        out.status.success(),
        "chromium failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// A pushed table's report says so and lists every node's outcome; a node left on
/// its old table is named in the banner and marked in the table.
#[test]
fn the_report_shows_the_push_per_node() {
    let mut input = input();
    input.verdict = Some(VerdictSummary {
        onto_bounds: Vec::new(),
        accepted: true,
        reasons: Vec::new(),
    });
    let row = |n: u32, holds: &str| exocal_report::NodePush {
        node: format!("Joint{n}"),
        new_crc: 0x1234_5678 + n,
        held_crc: Some(if holds == "new" {
            0x1234_5678 + n
        } else {
            0xdead_beef
        }),
        holds: holds.into(),
        attempts: 1,
        error: if holds == "new" {
            String::new()
        } else {
            "CRC mismatch".into()
        },
        authenticated: true,
        verified_crc: None,
        counter: None,
    };
    let dir = std::env::temp_dir().join(format!("exocal-report-push-{}", std::process::id()));
    // The daemon writes the report before the push and adds the outcome after it, without
    // rendering again: the same document as a render with the outcome.
    let before = render(&input);
    for holds in ["new", "old"] {
        let push: Vec<_> = (1..=7)
            .map(|n| row(n, if n == 3 { holds } else { "new" }))
            .collect();
        input.push = Some(push.clone());
        assert!(exocal_report::html::with_push(&before, &push) == Some(render(&input)));
    }
    assert_eq!(exocal_report::html::with_push(&render(&input), &[]), None);
    input.push = Some((1..=7).map(|n| row(n, "new")).collect());
    let dom = dump_dom(&dir, "all-new", &render(&input));
    assert!(
        dom.contains("Validated and pushed: every node (7) holds"),
        "banner"
    );
    assert!(dom.contains("<h2 id=\"push\">Push</h2>"), "no push section");
    let push = &dom[dom.find("id=\"push\"").unwrap()..];
    let push = &push[..push.find("</table>").unwrap()];
    assert_eq!(push.matches("<td>Joint").count(), 7, "{push}");
    assert!(dom.contains("<code>0x1234567f</code>"), "Joint7's CRC");
    input.push = Some(
        (1..=7)
            .map(|n| row(n, if n == 3 { "old" } else { "new" }))
            .collect(),
    );
    let dom = dump_dom(&dir, "one-old", &render(&input));
    assert!(
        dom.contains("the push did not complete: Joint3 holds the old table"),
        "banner"
    );
    assert!(
        dom.contains("<tr class=\"bad\"><td>Joint3</td><td>old</td>"),
        "Joint3's row"
    );
    input.push = None;
    let dom = dump_dom(&dir, "not-yet", &render(&input));
    assert!(
        dom.contains("the push's outcome is added here after it"),
        "banner"
    );
    assert!(!dom.contains("id=\"push\""));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_report_renders_in_headless_chromium_with_every_plot_drawn() {
    let input = input();
    let html = render(&input);
    let dir = std::env::temp_dir().join(format!("exocal-report-browser-{}", std::process::id()));
    let dom = dump_dom(&dir, "report", &html);
    assert!(
        dom.contains("browser test &lt;&amp;&gt; report"),
        "title not escaped/rendered"
    );
    assert!(dom.contains("a test reason"));
    assert!(
        dom.contains("expected table error (1σ: the Cramér-Rao bound with the drift-model choice)"),
        "the expected accuracy is not stated"
    );
    assert!(!dom.contains("class=\"missing\""), "a plot was not drawn");
    // The parameter table near the top (after the verdict and the key
    // numbers, before the plots), a unit on the drift table's σ, the version in the header.
    let at = |s: &str| dom.find(s).unwrap_or_else(|| panic!("no {s}"));
    assert!(at("<h2>Parameters</h2>") < at("<h2>Error over time</h2>"));
    assert!(at("class=\"cards\"") < at("<h2>Parameters</h2>"));
    assert!(dom.contains("σ (paper, eq. 8, rad/s)"));
    assert!(dom.contains(&format!("· exocal {}", env!("CARGO_PKG_VERSION"))));
    // Legends sit after their charts, never over the data: none inside an SVG (its
    // box would be plotters' grey-bordered rectangle), and the browser lays none over a chart.
    assert!(!dom.contains("#BEBEBE"), "a legend box inside a chart");
    assert_eq!(
        dom.matches("data-overlap=\"0\"").count(),
        dom.matches("<div class=\"legend\"").count(),
        "a legend laid out over its chart"
    );
    assert!(dom.matches("<div class=\"legend\"").count() >= FIGURES.len());
    for id in FIGURES {
        let fig = figure(&dom, id);
        assert!(fig.contains("<svg"), "{id}: no <svg> in the browser's DOM");
        let points = polyline_points(fig);
        let rects = fig.matches("<rect").count();
        match id {
            // Two series (nominal, calibrated) × position and rotation error (decimated to
            // 1,500 points each), each named once in the legend; two planes of three series.
            "fig-trajectory-time" => {
                assert!(points >= 2 * 2 * 1500, "{id}: {points} points");
                let legend = &dom[dom[dom.find(id).unwrap()..]
                    .find("class=\"legend\"")
                    .unwrap()
                    + dom.find(id).unwrap()..];
                let legend = &legend[..legend.find("</div>").unwrap()];
                assert_eq!(legend.matches("nominal").count(), 1, "{legend}");
            }
            "fig-trajectory-plane" => assert!(points >= 2 * 3 * 1500, "{id}: {points} points"),
            // One panel per joint.
            "fig-drift" => {
                assert!(points >= 7 * 1500, "{id}: {points} points");
                assert_eq!(
                    (1..=7)
                        .filter(|j| fig.contains(&format!("joint {j}: τ")))
                        .count(),
                    7
                );
            }
            "fig-likelihood" => assert!(points >= 3, "{id}: {points} points"),
            // Bars: at least a few non-empty bins per distribution, one bar per joint.
            "fig-residual-position" | "fig-residual-rotation" => {
                assert!(rects >= 6, "{id}: {rects} bars")
            }
            "fig-excitation" => assert!(rects >= 7, "{id}: {rects} bars"),
            other => panic!("untested figure {other}"),
        }
        // Every axis: as many distinct labels as ticks.
        let axes = axes(fig);
        assert!(!axes.is_empty(), "{id}: no axis labels found");
        for labels in &axes {
            let mut unique = labels.clone();
            unique.sort();
            unique.dedup();
            assert_eq!(
                unique.len(),
                labels.len(),
                "{id}: repeated tick labels {labels:?}"
            );
        }
        println!("{id}: axes {axes:?}");
    }
    // The log-likelihood of a minute of samples is large: the case the labels must tell apart.
    let em = input.calibration.em.as_ref().unwrap();
    let ll = &em.log_likelihood;
    // Every iteration of every objective has its marker, none dropped.
    assert_eq!(
        figure(&dom, "fig-likelihood").matches("<circle").count(),
        ll.len(),
        "objectives start at {:?}",
        em.objectives
    );
    assert!(ll.iter().all(|l| l.abs() > 1e4), "{ll:?}");
    // The histograms' bins reach the largest error of both series (nominal is far off here).
    let held = residuals(&input.nominal, &input.held_out);
    let calibrated = residuals(&input.calibration.calibrated, &input.held_out);
    for (id, pick) in [
        (
            "fig-residual-position",
            (|r: &(f64, f64)| r.0) as fn(&(f64, f64)) -> f64,
        ),
        ("fig-residual-rotation", |r: &(f64, f64)| r.1),
    ] {
        let max = |v: &[(f64, f64)]| v.iter().map(pick).fold(0.0f64, f64::max);
        let (nominal, calibrated) = (max(&held), max(&calibrated));
        assert!(
            nominal > 5.0 * calibrated,
            "{id}: nominal {nominal}, calibrated {calibrated}"
        );
        match bins_upper_end(figure(&dom, id)) {
            Some(hi) => assert!(
                hi >= nominal * (1.0 - 1e-3),
                "{id}: bins end at {hi}, the largest nominal error is {nominal}"
            ),
            None => assert!(figure(&dom, id).contains("&gt; "), "{id}: no overflow bar"),
        }
    }
    // Nothing external: the file is self-contained.
    assert!(!html.contains("src=\"http") && !html.contains("href=\"http"));
    let _ = std::fs::remove_dir_all(&dir);
}
