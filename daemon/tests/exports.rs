//! The exports and readers agree with the daemon's own code: the TOML export loads with the
//! daemon's configuration parser, and the log crate's MCAP reader reads the daemon's
//! session-log writer.

use calib_core::DhTable;
use exocal_bus::embedded_can::Frame as _;
use exocal_log::read::read_mcap_session;
use exocal_log::write::{CanFrameRecord, CollectionEnd, Level, SessionLog};
use exocald::config::{with_nominal, Config, CALIBRATED_NOTE, DEFAULT_TOML};
use exocald::log::records::Record;

#[test]
fn the_exported_configuration_loads_in_the_daemon_with_the_calibrated_table() {
    let calibrated = DhTable::<7>::paper_actual();
    let text = with_nominal(DEFAULT_TOML, &calibrated.rows).unwrap();
    let loaded = Config::parse(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    let default = Config::parse(DEFAULT_TOML).unwrap();
    for (row, want) in loaded.calibration.nominal.rows.iter().zip(&calibrated.rows) {
        assert!((row.a - want.a).abs() < 1e-15, "{row:?} vs {want:?}");
        assert!((row.d - want.d).abs() < 1e-15);
        assert!((row.alpha - want.alpha).abs() < 1e-12);
        assert!((row.theta_offset - want.theta_offset).abs() < 1e-12);
    }
    // Only the nominal table changed.
    assert_ne!(loaded.calibration.nominal, default.calibration.nominal);
    let mut same = loaded.clone();
    same.calibration.nominal = default.calibration.nominal;
    assert_eq!(same, default);
    // The comments of the shipped file survive, but the one that says the table is the
    // paper's Table 1 (untrue above a calibrated table) becomes the calibrated note.
    assert!(text.contains("# Anatomical bounds"));
    assert!(!text.contains("# The paper's Table 1") && text.contains(CALIBRATED_NOTE));
}

#[test]
fn the_mcap_reader_reads_the_frames_the_daemon_logged() {
    let mut buf = std::io::Cursor::new(Vec::new());
    let mut log = SessionLog::new(&mut buf, 500_000_000).unwrap();
    let mut sent = Vec::new();
    for i in 0..300u64 {
        let record = CanFrameRecord {
            id: 0x100 + (i % 7) as u32,
            extended: false,
            remote: false,
            dlc: 8,
            data: (0..8).map(|b| (i as u8).wrapping_mul(b)).collect(),
            host_ns: 1_700_000_000_000_000_000 + i * 1_234_567,
            kernel_ns: (i % 2 == 0).then_some(1_700_000_000_000_000_000 + i * 1_234_567 - 5),
        };
        let sent_frame = Record::Frame {
            sent: i % 50 == 49,
            frame: &record,
        };
        log.write_record(record.host_ns, &sent_frame).unwrap();
        if i == 200 {
            // Prose is for people; the replay reads the structured record only.
            let msg = "collection done: 999 frames (0 unknown, 0 malformed)";
            let event = Record::Event {
                level: Level::Info,
                message: msg,
            };
            log.write_record(record.host_ns, &event).unwrap();
            let end = CollectionEnd {
                frames: 200,
                window_end_ns: record.host_ns,
                unknown: 0,
                malformed: 0,
                invalid_angles: 0,
                dropped: 0,
                stream: None,
            };
            log.write_record(end.window_end_ns, &Record::CollectionEnd(&end))
                .unwrap();
        }
        if i % 50 != 49 {
            sent.push(record);
        }
    }
    log.finish().unwrap();
    let session = read_mcap_session(buf.get_ref().as_slice(), exocal_log::read::admit_all).unwrap();
    assert_eq!(
        session.collection_end.unwrap().as_nanos() as u64,
        1_700_000_000_000_000_000 + 200 * 1_234_567
    );
    assert_eq!(session.collection_frames, Some(200));
    let frames = session.frames;
    assert_eq!(frames.len(), sent.len());
    for (f, r) in frames.iter().zip(&sent) {
        assert_eq!(f.frame.raw_id(), r.id);
        assert_eq!(f.frame.data(), &r.data[..]);
        assert_eq!(
            f.timestamp.as_nanos() as u64,
            r.kernel_ns.unwrap_or(r.host_ns)
        );
    }
}
