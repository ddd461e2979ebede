//! The report opens in a real browser (headless Chromium) with every plot present and drawn.
//!
//! Needs Debian's `chromium` (`apt-get install -y chromium`) or `EXOCAL_CHROMIUM=/path/to/it`;
//! without it the test fails, saying so (it never passes silently).

use std::path::PathBuf;
use std::process::Command;

use calib_core::{DhTable, DriftEmOptions, JointRanges, LsOptions, Scenario, ScenarioConfig};
use exocal_report::html::{render, FIGURES};
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

/// A short simulated session, calibrated for real (EM capped to keep the test fast).
fn input() -> ReportInput {
    let cfg = ScenarioConfig::paper();
    let all: Vec<TimedSample> = Scenario::new(cfg, 11)
        .take(400)
        .enumerate()
        .map(|(i, s)| TimedSample {
            t: i as f64 * cfg.drift.dt,
            sample: s.sample,
        })
        .collect();
    let (fit, held) = all.split_at(320);
    let nominal = DhTable::paper_nominal();
    let samples: Vec<_> = fit.iter().map(|s| s.sample).collect();
    let em = DriftEmOptions {
        max_iterations: 8,
        ..DriftEmOptions::new(cfg.drift.dt)
    };
    let calibration =
        exocald::pipeline::ls_then_em(&nominal, &samples, &LsOptions::new(), &em).unwrap();
    assert!(
        calibration.em.is_ok(),
        "{:?}",
        calibration.em.as_ref().err()
    );
    let stream = |name: &str| StreamQuality {
        name: name.into(),
        samples: 400,
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
            duration_s: 4.0,
            grid_hz: 100.0,
            gaps: 0,
            counters: vec![("frames received".into(), 3200), ("unknown".into(), 0)],
            streams: vec![stream("Joint1"), stream("EndEffector")],
            joint_ranges: JointRanges::<7>::paper().limits,
            excitation_required: Some(0.5),
            receiver_stalls: 0,
            longest_stall_ms: None,
        },
        verdict: Some(VerdictSummary {
            accepted: false,
            reasons: vec!["a test reason".into()],
        }),
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

#[test]
fn the_report_renders_in_headless_chromium_with_every_plot_drawn() {
    let browser = chromium();
    let html = render(&input());
    let dir = std::env::temp_dir().join(format!("exocal-report-browser-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let page = dir.join("report.html");
    std::fs::write(&page, &html).unwrap();
    let profile = dir.join("profile");
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
    let dom = String::from_utf8(out.stdout).unwrap();
    assert!(
        dom.contains("browser test &lt;&amp;&gt; report"),
        "title not escaped/rendered"
    );
    assert!(dom.contains("a test reason"));
    assert!(
        dom.contains("expected table error (1σ, Cramér-Rao bound)"),
        "the expected accuracy is not stated"
    );
    assert!(!dom.contains("class=\"missing\""), "a plot was not drawn");
    for id in FIGURES {
        let fig = figure(&dom, id);
        assert!(fig.contains("<svg"), "{id}: no <svg> in the browser's DOM");
        let points = polyline_points(fig);
        let rects = fig.matches("<rect").count();
        match id {
            // Three series × three axes of 400 samples; two planes of three series.
            "fig-trajectory-time" | "fig-trajectory-plane" => {
                assert!(points >= 2 * 3 * 400, "{id}: {points} points")
            }
            "fig-drift" => assert!(points >= 7 * 320, "{id}: {points} points"),
            "fig-likelihood" => assert!(points >= 3, "{id}: {points} points"),
            // Bars: at least a few non-empty bins per distribution, one bar per joint.
            "fig-residual-position" | "fig-residual-rotation" => {
                assert!(rects >= 6, "{id}: {rects} bars")
            }
            "fig-excitation" => assert!(rects >= 7, "{id}: {rects} bars"),
            other => panic!("untested figure {other}"),
        }
    }
    // Nothing external: the file is self-contained.
    assert!(!html.contains("src=\"http") && !html.contains("href=\"http"));
    let _ = std::fs::remove_dir_all(&dir);
}
