//! The session's records built from the daemon's types: each thing a session logs is one
//! [`Record`] (defined in `exocal_log::record`), handed by the [`crate::shell::tee::Recorder`]
//! to every observer of the session's data — the MCAP log ([`exocal_log::write::SessionLog`])
//! and, when enabled, the live view ([`crate::live::LiveView`]). Here: the arm's frames, the
//! URDF, the raw frame's record, the calibration record with its push.
//!
//! Contract:
//! - a record carries its log time (host wall-clock ns, the session clock) and borrows its data;
//!   observers encode it as they need (the log in the schema of `exocal-log`, the live view the
//!   same messages over the Foxglove WebSocket protocol);
//! - the log's errors are the session's ([`crate::shell::tee::Recorder::record`] returns them);
//!   the live view never fails a session (a client that cannot keep up misses messages, nothing else);
//! - the arm's frames ([`arm_transforms`]) follow the URDF the report exports
//!   (`base_link → link1 … linkN → tool0`, `exocal_report::export::urdf`), so the transforms and a
//!   URDF of the same table describe one tree.

use exocal_bus::Frame;
use exocal_log::{proto, CanFrameRecord, CollectionEnd};

pub use exocal_log::record::{Link, Record, Transform, BASE_FRAME, TOOL_FRAME};

use crate::config::MAX_JOINTS;
use crate::push::{Holds, PushReport};
use exocal_session::arm::narrow;
use exocal_session::ingest::ClockReport;
use exocal_session::pipeline::{NodeRow, Outcome};
use exocal_session::Session;

/// Whoever takes a session's records besides its log (the live view; in a demo, the emulated
/// wearer's ear): called with each record and its log time, it never fails the session.
pub trait Observer {
    /// Takes `record`, logged at `log_ns`.
    fn observe(&self, log_ns: u64, record: &Record<'_>);
}

/// The robot name of the suit's URDF.
pub const ROBOT_NAME: &str = "exocal_suit";

/// The URDF of the arm of `table`'s first `joints` rows with the joints' `limits` (rad), as
/// `--export-urdf` writes it; an error naming the parameter when the table has a non-finite
/// value (nothing to draw).
pub fn urdf(
    table: &calib_core::DhTable<MAX_JOINTS>,
    limits: &[(f64, f64); MAX_JOINTS],
    joints: usize,
) -> Result<String, exocal_report::export::ExportError> {
    exocal_session::with_joints!(joints, |N| exocal_report::export::urdf(
        ROBOT_NAME,
        &table.first::<N>(),
        &narrow(limits)
    ))
}

/// The record of a collection's end (`exocald offline` honours it: a replay calibrates on the
/// first `frames` frames of /can/rx, as the session did): the frames `session` received (as
/// logged: with the stream gate, not only those ingest took yet), its counters and its gate's,
/// the frames the receiver dropped, and the bus time the window closed.
pub fn collection_end(session: &Session, dropped: u64, window_end_ns: u64) -> CollectionEnd {
    let s = session.stats();
    CollectionEnd {
        frames: session.frames_received(),
        window_end_ns,
        unknown: s.unknown,
        malformed: s.malformed,
        invalid_angles: s.invalid_angles,
        dropped,
        stream: session.gate().map(stream_verification),
    }
}

/// The `/collection` record of what the stream gate passed and dropped.
pub fn stream_verification(gate: &exocal_session::gate::StreamGate) -> proto::StreamVerification {
    let g = gate.stats();
    proto::StreamVerification {
        verified_spans: g.verified_spans,
        verified_frames: g.verified_frames,
        dropped_spans: g.dropped_spans,
        dropped_frames: g.dropped_frames,
        dropped_s: g.dropped_s,
        bad_mac: g.bad_mac,
        deficit: g.deficit,
        no_digest: g.no_digest,
        stale: g.stale,
        second_sender: g.second_sender.to_vec(),
        start_frames: g.start_frames,
        rejects: gate
            .rejects()
            .iter()
            .map(|r| proto::RejectRun {
                node: u32::from(r.node),
                first: r.first,
                count: r.count,
                stale: r.stale,
            })
            .collect(),
        rejects_truncated: g.rejects_truncated,
        empty_rejects: g.empty_rejects,
    }
}

/// A bus time as the log's nanoseconds (saturating).
pub fn ns(t: std::time::Duration) -> u64 {
    t.as_nanos().min(u128::from(u64::MAX)) as u64
}

/// The raw frame `frame` seen at `t` (host time; on SocketCAN also the kernel's timestamp).
pub fn frame_record(frame: &Frame, t: std::time::Duration) -> CanFrameRecord {
    use exocal_bus::embedded_can::Frame as _;
    let ns = ns(t);
    CanFrameRecord {
        id: frame.raw_id(),
        extended: frame.is_extended(),
        remote: frame.is_remote_frame(),
        dlc: frame.dlc() as u8,
        data: frame.data().to_vec(),
        host_ns: ns,
        kernel_ns: Some(ns),
    }
}

fn quat_wxyz(r: &nalgebra::Matrix3<f64>) -> [f64; 4] {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix(r));
    [q.w, q.i, q.j, q.k]
}

/// The arm's frames at joint readings `q` for `table`, in the exported URDF's convention
/// (`calib_core::DhTable::links`: link `i` turns about its z axis by `q[i-1]` plus the row's θ
/// offset at the previous row's `Tz(d) Tx(a) Rx(α)`; [`TOOL_FRAME`] sits at the last row's).
/// Composed, they are the table's forward kinematics. The arm is `table`'s first `joints` rows.
pub fn arm_transforms(
    table: &calib_core::DhTable<MAX_JOINTS>,
    q: &[f64; MAX_JOINTS],
    joints: usize,
) -> Vec<Link> {
    let name = |i: usize| match i {
        0 => BASE_FRAME.to_string(),
        i if i > joints => TOOL_FRAME.to_string(),
        i => format!("link{i}"),
    };
    let (links, tool): (Vec<calib_core::Frame>, _) = exocal_session::with_joints!(joints, |N| {
        let (links, tool) = table.first::<N>().links(&narrow(q));
        (links.to_vec(), tool)
    });
    (links.iter().chain([&tool]))
        .enumerate()
        .map(|(i, frame)| Link {
            parent: name(i),
            child: name(i + 1),
            transform: Transform {
                translation: [frame.p.x, frame.p.y, frame.p.z],
                rotation_wxyz: quat_wxyz(&frame.r),
            },
        })
        .collect()
}

fn dh_row(r: &NodeRow) -> proto::DhRow {
    proto::DhRow {
        a: r.a,
        alpha: r.alpha,
        d: r.d,
        theta_offset: r.theta_offset,
        tau: r.tau,
        sigma: r.sigma,
    }
}

/// The calibration result as logged: the outcome, the clock fits and grid figures, and the
/// push report once there is one.
pub fn calibration_record(
    outcome: &Outcome,
    clocks: &[ClockReport],
    aligned_samples: usize,
    gaps: usize,
    push: Option<&PushReport>,
) -> proto::Calibration {
    let v = &outcome.verdict;
    proto::Calibration {
        before: outcome.before.iter().map(dh_row).collect(),
        after: outcome.node_rows.iter().map(dh_row).collect(),
        refused: v.reasons.iter().map(ToString::to_string).collect(),
        fit_samples: outcome.fit_samples as u64,
        heldout_samples: outcome.heldout_samples as u64,
        condition_number: v.condition_number,
        expected_position_mm: v.expected.map(|e| e.position_mm),
        expected_rotation_mrad: v.expected.map(|e| e.rotation_mrad),
        heldout_nominal: v.nominal.mean_error,
        heldout_calibrated: v.candidate.mean_error,
        heldout_t: v.heldout_t,
        ls_iterations: outcome.ls.iterations as u64,
        em_iterations: outcome.em.as_ref().map_or(0, |e| e.iterations as u64),
        em_converged: outcome.em.as_ref().is_some_and(|e| e.converged),
        em_error: outcome.em_error.map_or_else(String::new, |e| e.to_string()),
        clocks: clocks
            .iter()
            .map(|c| proto::ClockFit {
                node: c.node.clone(),
                samples: c.samples as u64,
                unmapped: c.unmapped as u64,
                jumps: c.jumps as u64,
                skew_ppm: c.skew_ppm,
                residual_rms_us: c.residual_rms_us,
                outliers: c.outliers as u64,
            })
            .collect(),
        aligned_samples: aligned_samples as u64,
        gaps: gaps as u64,
        drift: outcome
            .em
            .as_ref()
            .and_then(|em| em.drift_95.clone())
            .map_or_else(Vec::new, |d| {
                d.iter()
                    .map(|d| proto::DriftFit {
                        tau_s: d.tau_s,
                        tau_low_s: d.tau_95_s[0],
                        tau_high_s: d.tau_95_s[1],
                        sigma_mrad: d.sigma_mrad,
                        sigma_low_mrad: d.sigma_95_mrad[0],
                        sigma_high_mrad: d.sigma_95_mrad[1],
                    })
                    .collect()
            }),
        reading_drift_rms_mrad: outcome.reading_drift_rms.iter().map(|r| r * 1e3).collect(),
        drift_model: outcome.em.as_ref().map_or_else(Vec::new, |em| {
            em.models.iter().map(ToString::to_string).collect()
        }),
        discounted: outcome.em.as_ref().map_or(0, |em| em.discounted as u64),
        discounted_s: outcome.em.as_ref().map_or_else(Vec::new, |em| {
            em.discounted_s.iter().flatten().copied().collect()
        }),
        drift_consistency: outcome
            .em
            .as_ref()
            .map_or_else(Vec::new, |em| em.consistency.to_vec()),
        onto_bounds: outcome
            .onto_bounds
            .iter()
            .map(ToString::to_string)
            .collect(),
        push: push.map_or_else(Vec::new, push_records),
    }
}

/// The push outcome as logged: per node, the CRC sent, what it holds, and the CRC it proved
/// holding in an answer whose MAC verified (what `exocald nodes` compares with).
pub fn push_records(p: &PushReport) -> Vec<proto::NodePush> {
    p.nodes
        .iter()
        .map(|n| proto::NodePush {
            node: n.node.clone(),
            new_crc: n.new_crc,
            held_crc: n.held_crc,
            holds: match n.holds {
                Holds::New => "new",
                Holds::Old => "old",
                Holds::Unknown => "unknown",
            }
            .to_string(),
            attempts: n.attempts,
            error: n.error.clone().unwrap_or_default(),
            authenticated: n.authenticated,
            verified_crc: n.verified_crc,
            counter: n.counter,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

    fn iso(t: &Transform) -> Isometry3<f64> {
        let [w, x, y, z] = t.rotation_wxyz;
        Isometry3::from_parts(
            Translation3::new(t.translation[0], t.translation[1], t.translation[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }

    #[test]
    fn the_calibration_record_and_the_report_carry_what_the_pipeline_found() {
        use calib_core::{Outliers, Scenario, ScenarioConfig};
        use exocal_session::align::AlignedSample;
        use exocal_session::Settings;
        // A 30 s paper session with 2 % reference glitches, the drift in the reading.
        let mut cfg = ScenarioConfig::paper();
        cfg.outliers = Outliers {
            probability: 0.02,
            burst: 1,
            position: 0.03,
            rotation: 0.03,
        };
        let samples: Vec<AlignedSample> = Scenario::new(cfg, 5)
            .take(3000)
            .enumerate()
            .map(|(i, s)| {
                let q = s.sample.joints;
                let read = calib_core::Sample {
                    joints: std::array::from_fn(|j| q[j] - s.drift[j]),
                    pose: s.sample.pose,
                };
                AlignedSample::of(i as f64 * cfg.drift.dt, &read)
            })
            .collect();
        let mut settings = Settings::suit_default();
        settings.window.min_samples = 500;
        let c = exocal_session::pipeline::run(&samples, &settings).unwrap();
        let record = calibration_record(&c.outcome, &[], 0, 0, None);
        let em = c.outcome.em.as_ref().unwrap();
        // The rough drift taken out of the readings, in mrad.
        let rms = c
            .outcome
            .reading_drift_rms
            .iter()
            .map(|r| r * 1e3)
            .collect::<Vec<_>>();
        assert!(rms.iter().all(|&r| r > 0.0), "{rms:?}");
        assert_eq!(record.reading_drift_rms_mrad, rms.to_vec());
        // Each joint's drift with its interval, its model and why.
        let drift = em.drift_95.clone().unwrap();
        assert_eq!(record.drift.len(), MAX_JOINTS);
        assert_eq!(record.drift[2].tau_high_s, drift[2].tau_95_s[1]);
        assert_eq!(record.drift_model.len(), MAX_JOINTS);
        assert!(
            record.drift_model[0].starts_with("Gauss-Markov"),
            "{:?}",
            record.drift_model
        );
        // The glitches discounted, counted and timed.
        assert!(record.discounted > 20, "{}", record.discounted);
        assert_eq!(record.discounted, em.discounted as u64);
        assert_eq!(record.discounted_s.len(), 2 * em.discounted_s.len());
        assert_eq!(record.drift_consistency.len(), MAX_JOINTS);
        // A parameter moved onto its bound is in the record, worded as the summary words it.
        assert!(record.onto_bounds.is_empty());
        let mut moved = c.outcome.clone();
        moved.onto_bounds.push(exocal_session::validate::OntoBound {
            violation: calib_core::BoundViolation {
                kind: calib_core::ParamKind::A,
                joint: 3,
                value: 0.2672,
                min: 0.211,
                max: 0.267,
            },
            to: 0.267,
            sigmas: 0.13,
        });
        let record = calibration_record(&moved, &[], 0, 0, None);
        assert_eq!(
            record.onto_bounds,
            ["joint 4: a = 0.2672 m outside [0.211, 0.267] by 0.13σ, moved onto it (0.2670 m)"]
        );
        // The report shows them too.
        let html = exocal_report::html::render(&crate::shell::html_report::report_input(
            "t".into(),
            "s".into(),
            &settings,
            &c,
            exocal_session::detail::Quality::default(),
            None,
        ));
        let [lo, hi] = drift[0].tau_95_s;
        assert!(
            html.contains(&format!("<td>{lo:.3}–{hi:.3}</td>")),
            "τ interval"
        );
        assert!(html.contains("model (and why)"), "no model column");
        assert!(
            html.contains(&format!(
                "{} of {} samples",
                em.discounted,
                c.outcome.fit_samples + c.outcome.heldout_samples
            )),
            "no glitch count"
        );
    }

    #[test]
    fn the_arm_frames_compose_to_the_tables_forward_kinematics() {
        let table = calib_core::DhTable::<MAX_JOINTS>::paper_nominal();
        let q = [0.3, -0.7, 0.2, 1.1, -0.1, 0.25, 0.6];
        let links = arm_transforms(&table, &q, MAX_JOINTS);
        assert_eq!(links.len(), MAX_JOINTS + 1);
        assert_eq!(links[0].parent, "base_link");
        assert_eq!(links[1].parent, "link1");
        assert_eq!(links[MAX_JOINTS].child, "tool0");
        for w in links.windows(2) {
            assert_eq!(w[0].child, w[1].parent);
        }
        let chain = links
            .iter()
            .fold(Isometry3::identity(), |acc, l| acc * iso(&l.transform));
        let fk = table.fk(&q);
        assert!((chain.translation.vector - fk.p).norm() < 1e-12);
        assert!((chain.rotation.to_rotation_matrix().matrix() - fk.r).norm() < 1e-12);
    }
}
