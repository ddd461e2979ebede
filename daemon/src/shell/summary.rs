//! The session summary as `exocald` prints it on stdout: what the user reads after a session
//! (log path, frames, clocks, expected table error, verdict, push), one line per fact. Used by
//! every subcommand that runs a session and by the serve loop; it imports nothing of theirs.

use crate::exit::DaemonError;
use crate::shell::runner::{SessionError, SessionSummary};

/// Prints what a session did, to stdout (one line per fact).
pub fn print_summary(summary: &SessionSummary) {
    println!("log: {}", summary.log_path.display());
    let f = &summary.frames;
    println!(
        "frames: {} received, {} unknown, {} malformed, {} invalid angles",
        f.received, f.unknown, f.malformed, f.invalid_angles
    );
    if let Some(g) = &summary.stream {
        println!(
            "streams: {} spans verified ({} frames), {} dropped unverified ({} frames, {:.1} s), \
             {} frames from before the nonce{}",
            g.verified_spans,
            g.verified_frames,
            g.dropped_spans,
            g.dropped_frames,
            g.dropped_s,
            g.start_frames,
            g.second_senders()
                .map(|(n, c)| format!("; a second sender on {n}'s identifiers ({c} spans)"))
                .chain((g.foreign_nonces > 0).then(|| format!(
                    "; {} StreamNonce frames from another sender on the bus (forged or replayed)",
                    g.foreign_nonces
                )))
                .chain((g.empty_rejects > 0).then(|| format!(
                    "; {} digests over no frames that did not verify (forged, or a keyless node)",
                    g.empty_rejects
                )))
                .chain((g.reboots > 0).then(|| format!(
                    "; {} new boot counts in heartbeats (reboots, or spoofed)",
                    g.reboots
                )))
                .collect::<String>()
        );
    }
    println!(
        "aligned samples: {} ({} grid points excluded as gaps)",
        summary.aligned_samples, summary.gaps
    );
    if summary.stalls.count > 0 {
        println!("clocks: {}", summary.stalls);
    }
    for c in &summary.clocks {
        println!(
            "clock {}: skew {} ppm, {} jump(s), {} samples excluded",
            c.node,
            c.skew_ppm
                .map_or_else(|| "?".into(), |s| format!("{s:+.1}")),
            c.jumps,
            c.unmapped
        );
    }
    if let Some(o) = &summary.outcome {
        let v = &o.verdict;
        if let Some(e) = v.expected {
            println!("expected table error: {e}");
        }
        if o.reading_drift_rms.iter().any(|&r| r > 0.0) {
            let mrad: Vec<String> = o
                .reading_drift_rms
                .iter()
                .map(|r| format!("{:.2}", r * 1e3))
                .collect();
            println!(
                "rough drift taken out of the readings, RMS per joint: {} mrad",
                mrad.join(" ")
            );
        }
        if let Some(em) = &o.em {
            if let Some(drift) = em.drift_95 {
                for (j, d) in drift.iter().enumerate() {
                    println!("drift joint {}: {d} (95%)", j + 1);
                }
            }
            for (j, m) in em.models.iter().enumerate() {
                println!("drift model joint {}: {m}", j + 1);
            }
            if let Some(line) = rate_bias_line(em) {
                println!("{line}");
            }
            println!("{}", discounted_line(em));
            if let Some(line) = ls_kept_line(em) {
                println!("{line}");
            }
        }
        println!(
            "held-out mean pose error: nominal {:.4e}, calibrated {:.4e} ({:.1}% better); condition number {:.3e}",
            v.nominal.mean_error,
            v.candidate.mean_error,
            v.improvement * 100.0,
            v.condition_number
        );
        let removed = if v.nominal.mean_position_m > 0.0 {
            (1.0 - v.candidate.mean_position_m / v.nominal.mean_position_m) * 100.0
        } else {
            0.0
        };
        println!(
            "held-out mean position error: {:.2} → {:.2} mm ({removed:.0}% removed), rotation {:.1} → {:.1} mrad (the report's cards)",
            v.nominal.mean_position_m * 1e3,
            v.candidate.mean_position_m * 1e3,
            v.nominal.mean_rotation_rad * 1e3,
            v.candidate.mean_rotation_rad * 1e3
        );
        for moved in &o.onto_bounds {
            println!("{}", moved.line());
        }
        for reason in &v.reasons {
            println!("refused: {reason}");
        }
    }
    if let Some(p) = &summary.push {
        for line in p.lines() {
            println!("push {line}");
        }
    }
    if let Some(l) = &summary.latency {
        if l.simulated {
            println!(
                "end of collection to every table verified: {:.3} s ({:.3} s computing on this \
                 machine + {:.3} s of emulated bus and nodes)",
                l.total().as_secs_f64(),
                l.real.as_secs_f64(),
                l.session.as_secs_f64()
            );
        } else {
            println!(
                "end of collection to every table verified: {:.3} s",
                l.total().as_secs_f64()
            );
        }
    }
    if let Some(r) = &summary.report_path {
        println!("report: {}", r.display());
    }
}

/// Prints the summary of a session result and returns its error.
pub fn finish(result: Result<SessionSummary, SessionError>) -> Result<(), DaemonError> {
    match result {
        Ok(summary) => {
            print_summary(&summary);
            Ok(())
        }
        Err(SessionError { error, summary }) => {
            if let Some(s) = summary {
                print_summary(&s);
            }
            Err(error)
        }
    }
}

/// Without the sensors' spec (issue 30): what a rate bias too small for the session to show
/// would add to the table error, or that the data chose the rate bias themselves. `None` when
/// the spec is configured.
pub fn rate_bias_line(em: &exocal_session::pipeline::EmSummary) -> Option<String> {
    if em.models.iter().any(|m| m.by_spec) {
        return None;
    }
    Some(match &em.unmodelled_rate_bias {
        Some(u) => format!(
            "sensors' rate bias: not configured ([sensors]): one of {} °/s, too small for this \
             session to show, would add ±{:.2} mm, ±{:.2} mrad (1σ) to the table error; set it \
             from the IMUs' spec",
            u.rate_deg_s, u.position_mm, u.rotation_mrad
        ),
        None => {
            "sensors' rate bias: not configured ([sensors]); this session's data chose it (drift \
                 models above)"
                .to_string()
        }
    })
}

/// Where LS's table is the result because the EM's disagrees with it beyond LS's own error
/// (the EM's drift model does not hold for the session); `None` where they agree.
pub fn ls_kept_line(em: &exocal_session::pipeline::EmSummary) -> Option<String> {
    let v = em.versus_ls.filter(|v| v.ls_kept)?;
    Some(format!(
        "our EM's table disagrees with LS's: they differ by {:.2} mm, {:.2} mrad where LS alone \
         is expected within ±{:.2} mm, ±{:.2} mrad (statistic {:.1} > {}): the EM's drift model \
         does not hold for this session, so LS's table is the result, stated by LS's own \
         expected error",
        v.difference_mm,
        v.difference_mrad,
        v.ls_expected_mm,
        v.ls_expected_mrad,
        v.statistic,
        calib_core::MAX_EM_LS_STATISTIC
    ))
}

/// The reference samples the EM discounted as glitches, and when: `reference glitches
/// discounted: none`, or `… 12 samples at 3.10–3.14 s, 17.20 s`.
pub fn discounted_line(em: &exocal_session::pipeline::EmSummary) -> String {
    if em.discounted == 0 {
        return "reference glitches discounted: none".to_string();
    }
    let at: Vec<String> = em
        .discounted_s
        .iter()
        .map(|&[a, b]| {
            if a == b {
                format!("{a:.2} s")
            } else {
                format!("{a:.2}–{b:.2} s")
            }
        })
        .collect();
    let more = if at.len() < em.discounted
        && em.discounted_s.len() >= calib_core::drift_em::MAX_DISCOUNTED_RUNS
    {
        ", …"
    } else {
        ""
    };
    format!(
        "reference glitches discounted: {} sample(s) at {}{more}",
        em.discounted,
        at.join(", ")
    )
}
