//! Damaged and oversized inputs to `exocald offline` and `exocald recover`:
//! one test per class of the bad-input campaign (`fuzz/campaign.py`), each driving the binary
//! and asserting exit 65 (or, for `recover` and a log merely cut short, what it must do
//! instead) and the message naming what is wrong. The same inputs seed the fuzz corpus
//! (`write_fuzz_seeds`: `EXOCAL_FUZZ_CORPUS=$PWD/fuzz/corpus cargo test -p exocald
//! --test damaged_inputs write_fuzz_seeds`).
//!
//! Memory is asserted through the limits rather than RSS: an input beyond one session under
//! the configuration is refused at its first line or frame beyond it, and a record, chunk or
//! string longer than the input or the limits is refused before anything is allocated for it
//! (exocal-log's `scan` tests; the campaign's peak RSS is in docs/reliability.md).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use exocal_dbc::message::{JointState, Message};
use exocal_dbc::pose::Pose;
use exocal_dbc::{Frame, NodeId, Received};
use exocal_log::{CollectionEnd, Topic};
use exocald::cmd::offline::{self, Format};
use exocald::config::{Config, DEFAULT_TOML};
use exocald::exit::DaemonError;
use exocald::log::records::frame_record;
use prost::Message as _;

/// Receive time of the first frame: 2023-11-14.
const T0_S: u64 = 1_700_000_000;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocald-damaged-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `seconds` of the suit at 100 Hz as the bus delivers it: every joint's state and the
/// end effector's pose (four pages), the joints sweeping part of their range.
fn suit_frames(seconds: f64) -> Vec<Received> {
    let mut out = Vec::new();
    let at = |k: u64, i: u64| Duration::new(T0_S, 0) + Duration::from_micros(k * 10_000 + i * 50);
    for k in 0..(seconds * 100.0) as u64 {
        let node_us = (k * 10_000) as u32;
        for j in 0..7u8 {
            let m = Message::JointState(JointState {
                node: NodeId::new(j + 1).unwrap(),
                timestamp_us: node_us,
                angle: 0.5 * ((k as f64) * 0.02 + f64::from(j)).sin(),
                rate: 0.0,
            });
            out.push(Received {
                frame: m.to_frame::<Frame>().unwrap(),
                timestamp: at(k, u64::from(j)),
            });
        }
        let pose = Pose {
            seq: (k % 64) as u8,
            timestamp_us: node_us,
            position: [0.3, 0.1, -0.2],
            quat: [1.0, 0.0, 0.0, 0.0],
        };
        for (i, page) in pose.pages().into_iter().enumerate() {
            out.push(Received {
                frame: Message::EePose(page).to_frame::<Frame>().unwrap(),
                timestamp: at(k, 7 + i as u64),
            });
        }
    }
    out
}

/// A finished session log of `frames` on `/can/rx` as the daemon encodes them (zstd chunks of
/// `per_chunk` frames; schemas named but empty, which no reader of ours looks into: the seeds
/// stay small), with the collection end record after `end` frames if given.
fn session_log(frames: &[Received], per_chunk: usize, end: Option<usize>) -> Vec<u8> {
    session_log_chunked(frames, per_chunk, end, true)
}

/// [`session_log`], with its records in zstd chunks or (`chunked` false) written plain into the
/// data section, as a writer without chunks does.
fn session_log_chunked(
    frames: &[Received],
    per_chunk: usize,
    end: Option<usize>,
    chunked: bool,
) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(None)
            .use_chunks(chunked);
        let mut w = mcap::Writer::with_options(&mut buf, options).unwrap();
        let mut channel = |t: Topic| {
            let schema = w.add_schema(t.schema().name, "protobuf", b"").unwrap();
            w.add_channel(schema, t.name(), "protobuf", &Default::default())
                .unwrap()
        };
        let (rx, collection) = (channel(Topic::CanRx), channel(Topic::Collection));
        for (i, f) in frames.iter().enumerate() {
            let ns = f.timestamp.as_nanos() as u64;
            let record = frame_record(&f.frame, f.timestamp);
            let header = |ch, seq| mcap::records::MessageHeader {
                channel_id: ch,
                sequence: seq,
                log_time: ns,
                publish_time: ns,
            };
            // One frame per message (a batch of one), so that damage names its frame.
            let batch = exocal_log::can_batch(std::slice::from_ref(&record));
            w.write_to_known_channel(&header(rx, i as u32), &batch.encode_to_vec())
                .unwrap();
            if end == Some(i + 1) {
                let body = CollectionEnd {
                    frames: i as u64 + 1,
                    window_end_ns: ns,
                    ..CollectionEnd::default()
                };
                w.write_to_known_channel(&header(collection, 0), &body.encode_to_vec())
                    .unwrap();
            }
            if (i + 1) % per_chunk == 0 {
                w.flush().unwrap();
            }
        }
        w.finish().unwrap();
    }
    buf.into_inner()
}

/// The small log of the tests: 2 s of the suit, chunks of 200 frames, collection ended.
fn small_log() -> Vec<u8> {
    let frames = suit_frames(2.0);
    session_log(&frames, 200, Some(frames.len()))
}

/// Start and length of each chunk record of a finished file.
fn chunks(bytes: &[u8]) -> Vec<(usize, usize)> {
    let summary = mcap::Summary::read(bytes).unwrap().unwrap();
    summary
        .chunk_indexes
        .iter()
        .map(|c| (c.chunk_start_offset as usize, c.chunk_length as usize))
        .collect()
}

/// The default configuration, with `edits` (`from`, `to`) applied, in `dir`.
fn config(dir: &Path, edits: &[(&str, &str)]) -> PathBuf {
    let mut text = DEFAULT_TOML.to_string();
    for (from, to) in edits {
        assert!(text.contains(from), "{from}");
        text = text.replace(from, to);
    }
    let p = dir.join("exocald.toml");
    std::fs::write(&p, text).unwrap();
    p
}

/// Runs `exocald --config CONFIG args…` in `dir`: exit status, stdout, stderr.
fn exocald(dir: &Path, config: &Path, args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_exocald"))
        .arg("--config")
        .arg(config)
        .args(args)
        .current_dir(dir)
        .output()
        .expect("run exocald");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `exocald offline` on `bytes` written to `dir/name`: exit status and stderr.
fn offline_on(dir: &Path, name: &str, bytes: &[u8], config: &Path) -> (i32, String) {
    let input = dir.join(name);
    std::fs::write(&input, bytes).unwrap();
    let report = dir.join("report.html");
    let (code, _, err) = exocald(
        dir,
        config,
        &[
            "offline",
            "-i",
            input.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ],
    );
    (code, err)
}

/// Asserts exit 65 with a `bad input` message containing every one of `what`.
fn refused(case: &str, (code, err): (i32, String), what: &[&str]) {
    assert_eq!(code, 65, "{case}: {err}");
    assert!(err.contains("bad input"), "{case}: {err}");
    for w in what {
        assert!(err.contains(w), "{case}: no {w:?} in: {err}");
    }
    assert!(!err.contains("panicked"), "{case}: {err}");
}

/// The damaged-log classes of the campaign, as (name, bytes, what the message must name).
fn damaged_logs() -> Vec<(&'static str, Vec<u8>, Vec<String>)> {
    let log = small_log();
    let c = chunks(&log);
    let (start, len) = c[1];
    let mut out = Vec::new();
    // A single bit flip inside a chunk's compressed records.
    let mut b = log.clone();
    b[start + len - 7] ^= 0x04;
    out.push((
        "flip",
        b,
        vec![format!("the chunk at byte {start} is damaged")],
    ));
    // A chunk that says it decompresses to 1 TB (the mcap crate allocated it: abort).
    let mut b = log.clone();
    b[start + 25..start + 33].copy_from_slice(&(1u64 << 40).to_le_bytes());
    out.push((
        "terabyte-chunk",
        b,
        vec!["1099511627776 bytes once decompressed, more than the 16777216".into()],
    ));
    // A record length far beyond the file, in a finished file.
    let mut b = log.clone();
    b[start + 1..start + 9].copy_from_slice(&(1u64 << 62).to_le_bytes());
    out.push((
        "record-length",
        b,
        vec![format!(
            "the file ends inside the chunk that starts at byte {start}"
        )],
    ));
    // A channel topic whose length says 4 GB (in a log without chunks: in a chunk, its CRC
    // notices first).
    let frames = suit_frames(0.2);
    let mut b = session_log_chunked(&frames, 200, Some(frames.len()), false);
    let topic = b
        .windows(7)
        .position(|w| w == b"/can/rx")
        .expect("the channel");
    b[topic - 4..topic].copy_from_slice(&u32::MAX.to_le_bytes());
    out.push((
        "string-length",
        b,
        vec!["topic: 4294967295 bytes declared".into()],
    ));
    // Bytes inserted inside a chunk.
    let mut b = log.clone();
    let at = start + len / 2;
    b.splice(at..at, [0xA5, 0x5A, 0x00]);
    out.push((
        "insertion",
        b,
        vec![format!("the chunk at byte {start} is damaged")],
    ));
    out
}

#[test]
fn damaged_session_logs_are_exit_65_naming_the_record() {
    let dir = temp_dir("logs");
    let cfg = config(&dir, &[]);
    // The intact log reads, and is too short for a session (66): what follows is refused for
    // its damage, not its content.
    let (code, err) = offline_on(&dir, "intact.mcap", &small_log(), &cfg);
    assert_eq!(code, 66, "{err}");
    for (name, bytes, what) in damaged_logs() {
        let what: Vec<&str> = what.iter().map(String::as_str).collect();
        refused(
            name,
            offline_on(&dir, &format!("{name}.mcap"), &bytes, &cfg),
            &what,
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A log cut short (a killed daemon's) is not damage: it is read up to the cut, with a
/// warning saying how much and where.
#[test]
fn a_log_cut_short_is_read_up_to_its_cut() {
    let dir = temp_dir("cut");
    let cfg = config(&dir, &[]);
    let log = small_log();
    let (start, len) = chunks(&log)[3];
    let (code, err) = offline_on(&dir, "cut.mcap", &log[..start + len / 2], &cfg);
    assert_eq!(code, 66, "{err}");
    assert!(err.contains("was cut short"), "{err}");
    assert!(
        err.contains(&format!(
            "recovered 600 messages (0.5 s of session) in 3 complete chunks, the first {start}"
        )),
        "{err}"
    );
    // A log cut before its first chunk ends (the campaign's 34 KB were a daemon's header,
    // schemas and first, unfinished chunk): no frame, refused.
    let first = chunks(&log)[0];
    let (code, err) = offline_on(&dir, "head.mcap", &log[..first.0 + first.1 - 1], &cfg);
    refused("head", (code, err), &["no message on /can/rx"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// More frames than one session can hold, or frames further apart: refused at that frame
/// (a 2-s window, plus 1 s: at most 63,830 frames within 3 s).
#[test]
fn a_log_beyond_one_session_is_exit_65_at_its_first_frame_beyond() {
    let dir = temp_dir("beyond");
    let cfg = config(
        &dir,
        &[
            ("min_duration_s = 20.0", "min_duration_s = 1.0"),
            ("max_duration_s = 180.0", "max_duration_s = 2.0"),
            ("min_samples = 1000", "min_samples = 100"),
        ],
    );
    let one = suit_frames(0.01)[0];
    let many = vec![one; 63_831];
    refused(
        "count",
        offline_on(&dir, "many.mcap", &session_log(&many, 10_000, None), &cfg),
        &[
            "message 63830 on /can/rx: more than 63830 frames",
            "session.max_duration_s",
        ],
    );
    let mut far = suit_frames(0.5);
    let last = far.len() - 1;
    far[last].timestamp += Duration::from_secs(1_000);
    refused(
        "span",
        offline_on(&dir, "far.mcap", &session_log(&far, 100, None), &cfg),
        &[
            &format!("message {last} on /can/rx: this frame is 1000.49"),
            "spans more than the longest session this configuration collects (3 s",
        ],
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A candump log whose first lines are at time 0, and one line of a megabyte: refused at that
/// line (unchecked, the first would size the alignment grid at 1.4 TB).
#[test]
fn a_candump_log_beyond_one_session_is_exit_65_naming_the_line() {
    let dir = temp_dir("candump");
    let cfg = config(&dir, &[]);
    let frames = suit_frames(1.0);
    let mut text = exocal_session::formats::candump_text(&frames, "can0");
    let zero = text
        .lines()
        .take(100)
        .map(|l| format!("(0.000000){}\n", &l[l.find(')').unwrap() + 1..]))
        .collect::<String>();
    let rest: String = text.lines().skip(100).map(|l| format!("{l}\n")).collect();
    let time0 = format!("{zero}{rest}");
    refused(
        "time 0",
        offline_on(&dir, "time0.log", time0.as_bytes(), &cfg),
        &[
            "candump log, line 101: this frame is 1700000000",
            "session.max_duration_s",
        ],
    );
    text.insert_str(text.find('\n').unwrap() + 1, &"A".repeat(1 << 20));
    refused(
        "long line",
        offline_on(&dir, "long.log", text.as_bytes(), &cfg),
        &["candump log, line 2: longer than 4096 bytes"],
    );
    let mut bytes = time0.into_bytes();
    bytes[30] = 0xFF;
    refused(
        "not UTF-8",
        offline_on(&dir, "binary.log", &bytes, &cfg),
        &["candump log, line 1: not UTF-8 text"],
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// CSV samples beyond one session: more rows than the grid holds (18,101 at 100 Hz over
/// 181 s), or a longer span. The campaign's 200,000 rows took 573 MiB and 75 s.
#[test]
fn csv_samples_beyond_one_session_are_exit_65_naming_the_line() {
    let dir = temp_dir("csv");
    let cfg = config(&dir, &[]);
    let csv = |n: usize, hz: f64| {
        let mut s = format!("{}\n", exocal_session::formats::CSV_HEADER);
        for k in 0..n {
            s.push_str(&format!(
                "{},0.1,0.2,0.3,0.4,0.1,0.2,0.3,0.3,0.1,-0.2,1,0,0,0\n",
                k as f64 / hz
            ));
        }
        s
    };
    refused(
        "rows",
        offline_on(&dir, "rows.csv", csv(20_000, 1_000.0).as_bytes(), &cfg),
        &[
            "CSV samples, line 18103: more than 18101 samples",
            "session.grid_hz = 100 Hz",
        ],
    );
    refused(
        "span",
        offline_on(&dir, "span.csv", csv(2_000, 10.0).as_bytes(), &cfg),
        &[
            "CSV samples, line 1813: this sample is 181.1",
            "spans more than",
        ],
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `recover` writes OUT only when it has a complete file: what is not MCAP (65) and an OUT it
/// cannot write (74) leave neither OUT nor its temporary file; a damaged log is recovered up
/// to its damage.
#[test]
fn recover_leaves_no_output_when_it_fails() {
    let dir = temp_dir("recover");
    let cfg = config(&dir, &[]);
    let listing = |d: &Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    let text = dir.join("text.mcap");
    std::fs::write(&text, "hello").unwrap();
    let before = listing(&dir);
    let out = dir.join("out.mcap");
    let (code, _, err) = exocald(
        &dir,
        &cfg,
        &["recover", text.to_str().unwrap(), out.to_str().unwrap()],
    );
    assert_eq!(code, 65, "{err}");
    assert!(err.contains("not an MCAP file"), "{err}");
    assert_eq!(listing(&dir), before, "recover left files behind");

    let (name, damaged, _) = damaged_logs().swap_remove(0);
    let input = dir.join(format!("{name}.mcap"));
    std::fs::write(&input, &damaged).unwrap();
    let nowhere = dir.join("missing").join("out.mcap");
    let (code, _, err) = exocald(
        &dir,
        &cfg,
        &[
            "recover",
            input.to_str().unwrap(),
            nowhere.to_str().unwrap(),
        ],
    );
    assert_eq!(code, 74, "{err}");
    assert!(!dir.join("missing").exists());

    let (code, said, err) = exocald(
        &dir,
        &cfg,
        &["recover", input.to_str().unwrap(), out.to_str().unwrap()],
    );
    assert_eq!(code, 0, "{err}");
    assert!(said.contains("recovered 200 messages"), "{said}");
    assert!(said.contains("is damaged"), "{said}");
    let whole = std::fs::read(&out).unwrap();
    let stats = mcap::Summary::read(&whole).unwrap().unwrap().stats.unwrap();
    assert_eq!(stats.message_count, 200);
    assert!(!listing(&dir).iter().any(|f| f.ends_with(".partial")));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Every 211th single-bit flip of the small log (211 is prime: every bit position is hit) through the offline reading (in process): a
/// recording, or bad input naming what is wrong — never a panic, never another error.
#[test]
fn bit_flips_of_a_log_read_or_are_bad_input() {
    let log = small_log();
    let rules = Config::default_config().calibration;
    let path = Path::new("flipped.mcap");
    let (mut read, mut bad) = (0, 0);
    let mut b = log.clone();
    for i in (0..log.len() * 8).step_by(211) {
        b[i / 8] ^= 1 << (i % 8);
        match offline::read_input(path, b.as_slice(), Format::Mcap, &rules) {
            Ok(_) => read += 1,
            Err(DaemonError::Input(what)) => {
                assert!(what.starts_with("flipped.mcap: MCAP log: "), "{what}");
                bad += 1;
            }
            Err(e) => panic!("bit {i}: {e}"),
        }
        b[i / 8] ^= 1 << (i % 8);
    }
    // Flips in the summary and footer change nothing read; every other is noticed.
    assert!(read > 0 && bad > read, "{read} read, {bad} refused");
}

/// Writes the damaged inputs above as the fuzz targets' seeds (see fuzz/README.md): into
/// `$EXOCAL_FUZZ_CORPUS/<target>/` when that is set, else into a temporary directory, where the
/// test checks that every reader's target got its seeds.
#[test]
fn write_fuzz_seeds() {
    let root = std::env::var_os("EXOCAL_FUZZ_CORPUS")
        .map_or_else(|| temp_dir("fuzz-corpus"), PathBuf::from);
    let put = |target: &str, name: &str, bytes: &[u8]| {
        let d = root.join(target);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join(name), bytes).unwrap();
    };
    let log = small_log();
    let (start, len) = chunks(&log)[3];
    let first = chunks(&log)[0];
    let mut logs = vec![
        ("intact", log.clone()),
        ("cut", log[..start + len / 2].to_vec()),
        ("head", log[..first.0 + first.1 - 1].to_vec()),
    ];
    logs.extend(damaged_logs().into_iter().map(|(n, b, _)| (n, b)));
    for (name, bytes) in &logs {
        put("offline_mcap", &format!("{name}.mcap"), bytes);
        put("recover", &format!("{name}.mcap"), bytes);
    }
    let frames = suit_frames(0.3);
    let text = exocal_session::formats::candump_text(&frames, "can0");
    put("offline_candump", "intact.log", text.as_bytes());
    let zero: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| match i {
            0..=9 => format!("(0.000000){}\n", &l[l.find(')').unwrap() + 1..]),
            _ => format!("{l}\n"),
        })
        .collect();
    put("offline_candump", "time0.log", zero.as_bytes());
    let mut csv = format!("{}\n", exocal_session::formats::CSV_HEADER);
    for k in 0..30 {
        csv.push_str(&format!(
            "{},0.1,0.2,0.3,0.4,0.1,0.2,{},0.3,0.1,-0.2,1,0,0,0\n",
            f64::from(k) * 0.01,
            f64::from(k) * 0.02
        ));
    }
    put("offline_csv", "intact.csv", csv.as_bytes());
    let far = csv.replace("\n0.29,", "\n1000.29,");
    put("offline_csv", "span.csv", far.as_bytes());
    for (target, at_least) in [
        ("offline_mcap", 4),
        ("recover", 4),
        ("offline_candump", 2),
        ("offline_csv", 2),
    ] {
        let n = std::fs::read_dir(root.join(target)).map_or(0, Iterator::count);
        assert!(n >= at_least, "{target}: {n} seeds");
    }
}
