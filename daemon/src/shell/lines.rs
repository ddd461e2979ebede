//! What a session says in its log (and, for warnings, on the console) at the end of each step,
//! as lines: one function per step, each a renderer of what the step produced. The loop writes
//! them; nothing here decides anything.

use exocal_log::write::Level;
use exocal_session::collect::Collected;
use exocal_session::gate::GateStats;
use exocal_session::ingest::FrameStats;
use exocal_session::pipeline::Outcome;

/// A clock fit whose residual exceeds this (µs RMS) is reported as unreliable. Receive jitter
/// averages out in the fit (an in-process bus whose hil sends frames in ~10 ms batches sees ~5 ms
/// RMS and still aligns well); tens of ms mean the timestamps cannot be trusted.
pub const CLOCK_RESIDUAL_WARN_US: f64 = 20_000.0;

/// A line and how much it matters.
pub type Line = (Level, String);

/// The end of the collection: the frame counters (`dropped`: frames the receiver lost), the
/// stream gate's account when the streams were authenticated, and every babbling node.
pub fn collection_end(s: &FrameStats, gate: Option<&GateStats>, dropped: u64) -> Vec<Line> {
    let mut lines = vec![(
        Level::Info,
        format!(
            "collection done: {} frames ({} unknown, {} malformed, {} invalid angles, {} dropped \
             by the receiver)",
            s.received, s.unknown, s.malformed, s.invalid_angles, dropped
        ),
    )];
    if let Some(g) = gate {
        lines.push((Level::Info, stream_verification(g)));
        for (node, spans) in g.second_senders() {
            let line = format!(
                "a second sender on {node}'s identifiers: {spans} spans held more frames than \
                 its digests cover (dropped)"
            );
            lines.push((Level::Warning, line));
        }
    }
    for (node, repeats) in s.babbling() {
        let line = format!("{node} is babbling: {repeats} frames repeated verbatim");
        lines.push((Level::Warning, line));
    }
    lines
}

/// The stream gate's account of a collection, in a line.
fn stream_verification(g: &GateStats) -> String {
    format!(
        "stream verification: {} spans verified ({} frames); {} spans dropped unverified ({} \
         frames, {:.1} s: {} bad MAC, {} frames lost, {} without a digest); {} replayed digests \
         ignored; {} frames from before the nonce dropped; {} new boot counts, {} StreamNonce \
         frames from another sender, {} new nonces sent{}",
        g.verified_spans,
        g.verified_frames,
        g.dropped_spans,
        g.dropped_frames,
        g.dropped_s,
        g.bad_mac,
        g.deficit,
        g.no_digest,
        g.stale,
        g.start_frames,
        g.reboots,
        g.foreign_nonces,
        g.renonces,
        if g.renonces_capped {
            " (the limit: more were wanted)"
        } else {
            ""
        }
    )
}

/// The alignment: receiver stalls, clocks whose timestamps cannot be trusted or that jumped,
/// and the grid (`grid_hz`) the samples are on.
pub fn aligned(collected: &Collected, grid_hz: f64) -> Vec<Line> {
    let mut lines = Vec::new();
    let stalls = collected.stalls;
    if stalls.count > 0 {
        let line = format!(
            "{stalls}: every node's frames arrived late together while their clocks ran on; \
             their samples are kept on the nodes' clocks (not clock jumps)"
        );
        lines.push((Level::Warning, line));
    }
    for c in &collected.clocks {
        if let Some(r) = c.residual_rms_us.filter(|&r| r > CLOCK_RESIDUAL_WARN_US) {
            let line = format!(
                "{}: receive-time residual {r:.0} µs RMS: timestamps are unreliable (a lagging \
                 sender or a loaded receiver); expect a poor alignment",
                c.node
            );
            lines.push((Level::Warning, line));
        }
        if c.jumps > 0 || c.unmapped > 0 {
            let line = format!(
                "{}: {} clock jump(s)/reboot(s), {} samples excluded",
                c.node, c.jumps, c.unmapped
            );
            lines.push((Level::Warning, line));
        }
    }
    let line = format!(
        "aligned {} samples on a {} Hz grid, {} grid points excluded as gaps",
        collected.samples.len(),
        grid_hz,
        collected.gaps
    );
    lines.push((Level::Info, line));
    lines
}

/// The calibration: each parameter moved onto its bound, then the expected table error and the
/// held-out test in a line.
pub fn calibrated(outcome: &Outcome) -> Vec<Line> {
    let mut lines: Vec<Line> = (outcome.onto_bounds.iter())
        .map(|moved| (Level::Info, moved.line()))
        .collect();
    let v = &outcome.verdict;
    let line = format!(
        "expected table error {}; held-out pose error {:.3e} → {:.3e} ({:.1}% better than \
         nominal, paired t {:.1}), condition number {:.3e}",
        v.expected
            .map_or_else(|| "unknown".to_string(), |e| e.to_string()),
        v.nominal.mean_error,
        v.candidate.mean_error,
        v.improvement * 100.0,
        v.heldout_t,
        v.condition_number
    );
    lines.push((Level::Info, line));
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_session::ingest::{ClockReport, StallReport};

    fn clock(node: &str, residual_rms_us: Option<f64>, jumps: usize) -> ClockReport {
        ClockReport {
            node: node.into(),
            samples: 1000,
            unmapped: 3 * jumps,
            jumps,
            skew_ppm: Some(12.0),
            residual_rms_us,
            outliers: 0,
        }
    }

    #[test]
    fn a_collection_says_its_counters_and_with_a_gate_its_account() {
        let s = FrameStats {
            received: 120,
            malformed: 2,
            ..FrameStats::default()
        };
        let plain = collection_end(&s, None, 5);
        assert_eq!(plain.len(), 1);
        assert_eq!(plain[0].0, Level::Info);
        assert!(plain[0]
            .1
            .starts_with("collection done: 120 frames (0 unknown, 2 malformed"));
        assert!(
            plain[0].1.ends_with("5 dropped by the receiver)"),
            "{}",
            plain[0].1
        );
        let g = GateStats {
            verified_spans: 40,
            renonces_capped: true,
            ..GateStats::default()
        };
        let gated = collection_end(&s, Some(&g), 0);
        assert_eq!(gated.len(), 2, "{gated:?}");
        assert!(gated[1]
            .1
            .starts_with("stream verification: 40 spans verified"));
        assert!(gated[1].1.ends_with("(the limit: more were wanted)"));
    }

    #[test]
    fn an_alignment_warns_of_stalls_untrustworthy_clocks_and_jumps_and_says_its_grid() {
        let quiet = Collected {
            clocks: vec![clock("Joint1", Some(900.0), 0)],
            gaps: 4,
            ..Collected::default()
        };
        let lines = aligned(&quiet, 100.0);
        assert_eq!(lines.len(), 1, "{lines:?}");
        assert_eq!(
            lines[0],
            (
                Level::Info,
                "aligned 0 samples on a 100 Hz grid, 4 grid points excluded as gaps".into()
            )
        );
        let troubled = Collected {
            clocks: vec![
                clock("Joint1", Some(CLOCK_RESIDUAL_WARN_US * 2.0), 0),
                clock("Joint2", Some(900.0), 2),
            ],
            stalls: StallReport {
                count: 1,
                longest_ms: Some(250.0),
            },
            ..Collected::default()
        };
        let lines = aligned(&troubled, 100.0);
        let warnings: Vec<&str> = (lines.iter())
            .filter(|(l, _)| *l == Level::Warning)
            .map(|(_, s)| s.as_str())
            .collect();
        assert_eq!(warnings.len(), 3, "{lines:?}");
        assert!(warnings[0].contains("every node's frames arrived late together"));
        assert!(warnings[1].starts_with("Joint1: receive-time residual 40000 µs RMS"));
        assert_eq!(
            warnings[2],
            "Joint2: 2 clock jump(s)/reboot(s), 6 samples excluded"
        );
    }
}
