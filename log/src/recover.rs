//! Recovery of a session log cut short (`kill -9`, power loss, OOM kill).
//!
//! The daemon closes, flushes and syncs a chunk at least every `output.flush_interval_s`
//! ([`crate::write`]), so a killed session's file is a run of complete records followed by
//! the chunk that was open: its length field never written, its compressed stream unfinished,
//! and no summary or footer. Readers that start from the footer refuse it.
//!
//! Contract:
//! - works on MCAP records only — header, schemas, channels, messages, chunks, attachments,
//!   metadata — and never decodes a message, so it does not depend on the log's message
//!   encoding;
//! - reads the input through the bounded scan ([`crate::scan`]: one record at a time,
//!   every length, chunk size and CRC checked, a chunk kept whole or not at all) and keeps
//!   every record up to the first one that is cut short or damaged (a bad CRC, a chunk that
//!   does not decompress, ids that disagree, a tail of zeroes) or up to the data end;
//! - [`recover`] copies what it kept into a new, complete MCAP (summary, chunk and message
//!   indexes, statistics, footer) with the same schema and channel ids, sequence numbers and
//!   times, and returns a [`Recovery`]: how many messages, over which log times, from how many
//!   chunks, and where the input ends ([`End`]);
//! - nothing here panics on any input, and its memory is one chunk plus the writer's.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::fmt;
use std::io::{Cursor, Read, Seek, Write};

pub use crate::scan::End;
use crate::scan::{self, McapRecord};

/// What a recovery kept: [`crate::scan::Scan`].
pub type Recovery = scan::Scan;

/// Why nothing could be recovered.
#[derive(Debug)]
pub enum RecoverError {
    /// The input does not start with the MCAP magic.
    NotMcap,
    /// Writing the recovered file failed.
    Write(mcap::McapError),
}

impl fmt::Display for RecoverError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RecoverError::NotMcap => f.write_str("not an MCAP file (no MCAP magic at its start)"),
            RecoverError::Write(e) => write!(f, "writing the recovered MCAP: {e}"),
        }
    }
}

impl std::error::Error for RecoverError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            RecoverError::NotMcap => None,
            RecoverError::Write(e) => Some(e),
        }
    }
}

impl From<mcap::McapError> for RecoverError {
    fn from(e: mcap::McapError) -> Self {
        RecoverError::Write(e)
    }
}

fn owned(pairs: &[(&str, &str)]) -> BTreeMap<String, String> {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

/// Copies one unit the scan handed out into `w` (the scan checked its ids: only I/O can fail).
fn copy<W: Write + Seek>(
    w: &mut mcap::Writer<W>,
    records: &[McapRecord<'_>],
) -> Result<(), mcap::McapError> {
    for r in records {
        match r {
            // The new file has its own header (with the input's profile: see `recover`).
            McapRecord::Header { .. } => {}
            McapRecord::Schema {
                id,
                name,
                encoding,
                data,
            } => {
                w.add_schema_with_id(*id, name, encoding, data)?;
            }
            McapRecord::Channel {
                id,
                schema_id,
                topic,
                encoding,
                metadata,
            } => {
                w.add_channel_with_id(*id, *schema_id, topic, encoding, &owned(metadata))?;
            }
            McapRecord::Message {
                channel_id,
                sequence,
                log_time,
                publish_time,
                data,
            } => {
                let header = mcap::records::MessageHeader {
                    channel_id: *channel_id,
                    sequence: *sequence,
                    log_time: *log_time,
                    publish_time: *publish_time,
                };
                w.write_to_known_channel(&header, data)?;
            }
            McapRecord::Attachment {
                log_time,
                create_time,
                name,
                media_type,
                data,
            } => w.attach(&mcap::Attachment {
                log_time: *log_time,
                create_time: *create_time,
                name: name.to_string(),
                media_type: media_type.to_string(),
                data: Cow::Borrowed(data),
            })?,
            McapRecord::Metadata { name, metadata } => {
                w.write_metadata(&mcap::records::Metadata {
                    name: name.to_string(),
                    metadata: owned(metadata),
                })?
            }
        }
    }
    Ok(())
}

/// Scans `input` (see the module docs) and writes what it keeps to `out` as a complete MCAP,
/// its chunks compressed with `compression`. Returns what was kept and the writer.
pub fn recover<R: Read, W: Write + Seek>(
    mut input: R,
    out: W,
    compression: Option<mcap::Compression>,
) -> Result<(Recovery, W), RecoverError> {
    // The magic and the header record come first: the header's profile and library go to the
    // new file. What is read here is scanned again, from the start.
    let mut head = Vec::new();
    let _ = (&mut input)
        .take(scan::HEADER_PEEK_BYTES)
        .read_to_end(&mut head);
    if !head.starts_with(mcap::MAGIC) {
        return Err(RecoverError::NotMcap);
    }
    let mut options = mcap::WriteOptions::new()
        .compression(compression)
        .library(concat!("exocald ", env!("CARGO_PKG_VERSION"), " recover"));
    if let Some((profile, library)) = scan::header(&head) {
        options = options.profile(profile).library(format!(
            "{library} (recovered by exocald {})",
            env!("CARGO_PKG_VERSION")
        ));
    }
    let mut writer = mcap::Writer::with_options(out, options)?;
    let recovery = scan::scan(Cursor::new(&head).chain(input), |records| {
        copy(&mut writer, records)
    })?;
    writer.finish()?;
    Ok((recovery, writer.into_inner()))
}

/// Whether `bytes` is an MCAP file with its end magic (a finished log).
pub fn is_finished(bytes: &[u8]) -> bool {
    bytes.len() >= 2 * mcap::MAGIC.len()
        && bytes.starts_with(mcap::MAGIC)
        && bytes.ends_with(mcap::MAGIC)
}

/// [`recover`] into memory, uncompressed (for a reader that needs a complete file).
pub fn recover_in_memory(bytes: &[u8]) -> Result<(Recovery, Vec<u8>), RecoverError> {
    let (recovery, out) = recover(bytes, Cursor::new(Vec::new()), None)?;
    Ok((recovery, out.into_inner()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use mcap::records::op;

    /// Opcode and length of a record header: 1 + 8 bytes.
    const RECORD_HEADER: usize = 9;
    use crate::record::Record;
    use crate::write::{CanFrameRecord, Level, SessionLog, Topic};
    use std::collections::BTreeMap;

    /// A finished session log of 30 flushed chunks (two message kinds each), its bytes.
    fn session_log(name: &str) -> Vec<u8> {
        let dir =
            std::env::temp_dir().join(format!("exocald-recover-{}-{name}", std::process::id()));
        let t0 = 1_700_000_000_000_000_000u64;
        let (path, mut log) = SessionLog::create_in(&dir, t0, 1_000).unwrap();
        log.tick(0).unwrap();
        for k in 0..30u64 {
            for i in 0..(5 + k % 4) {
                let ns = t0 + k * 100_000_000 + i * 1_000_000;
                let frame = CanFrameRecord {
                    id: 0x101 + (i % 7) as u32,
                    extended: false,
                    remote: false,
                    dlc: 2,
                    data: vec![k as u8, i as u8],
                    host_ns: ns,
                    kernel_ns: Some(ns),
                };
                log.write_record(
                    ns,
                    &Record::Frame {
                        sent: false,
                        frame: &frame,
                    },
                )
                .unwrap();
            }
            let message = format!("chunk {k}");
            log.write_record(
                t0 + k * 100_000_000,
                &Record::Event {
                    level: Level::Info,
                    message: &message,
                },
            )
            .unwrap();
            assert!(log.tick((k + 1) * 2_000).unwrap(), "chunk {k} flushed");
        }
        log.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        bytes
    }

    /// Every message (topic, sequence, log time, data) of a file, in file order; the file
    /// must be whole (the end magic is required).
    fn messages(bytes: &[u8]) -> Vec<(String, u32, u64, Vec<u8>)> {
        mcap::MessageStream::new(bytes)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (
                    m.channel.topic.clone(),
                    m.sequence,
                    m.log_time,
                    m.data.into_owned(),
                )
            })
            .collect()
    }

    /// Start, length and message count of each chunk of a finished file.
    fn chunks(bytes: &[u8]) -> Vec<(usize, usize, usize)> {
        let summary = mcap::Summary::read(bytes).unwrap().unwrap();
        summary
            .chunk_indexes
            .iter()
            .map(|c| {
                let n = summary.stream_chunk(bytes, c).unwrap().count();
                (c.chunk_start_offset as usize, c.chunk_length as usize, n)
            })
            .collect()
    }

    /// Start and length of chunk `i` of a finished file, and the messages before it.
    fn chunk(bytes: &[u8], i: usize) -> (usize, usize, usize) {
        let c = chunks(bytes);
        let (start, len, _) = c[i];
        (start, len, c[..i].iter().map(|x| x.2).sum())
    }

    /// Recovers `cut` and checks the result against the first `expect` messages of `all`: the
    /// same messages, a complete file with every channel and the right statistics.
    fn check(cut: &[u8], all: &[(String, u32, u64, Vec<u8>)], expect: usize) -> Recovery {
        let (r, out) = recover_in_memory(cut).unwrap();
        assert_eq!(r.messages as usize, expect, "{r}");
        assert_eq!(messages(&out), all[..expect], "{r}");
        let summary = mcap::Summary::read(&out).unwrap().expect("a summary");
        assert_eq!(summary.stats.unwrap().message_count as usize, expect);
        if expect > 0 {
            assert_eq!(summary.channels.len(), Topic::ALL.len(), "{r}");
            let (first, last) = r.log_times.unwrap();
            assert_eq!(
                (first, last),
                (all[0].2, all[..expect].iter().map(|m| m.2).max().unwrap())
            );
        }
        assert!(r.kept_bytes <= cut.len() as u64 && r.file_bytes == cut.len() as u64);
        r
    }

    #[test]
    fn a_file_cut_at_every_chunk_boundary_keeps_every_chunk_before_it() {
        let bytes = session_log("boundaries");
        let all = messages(&bytes);
        let chunks = chunks(&bytes);
        assert!(chunks.len() >= 30, "{} chunks", chunks.len());
        let mut before = 0;
        for (i, &(start, len, n)) in chunks.iter().enumerate() {
            // At the chunk's start (after the previous chunk's message indexes), and at its end
            // (before its own message indexes).
            let r = check(&bytes[..start], &all, before);
            assert_eq!(r.chunks as usize, i);
            assert_eq!(r.kept_bytes as usize, start);
            assert!(matches!(r.end, End::Cut { have: 0, .. }), "{r}");
            assert!(r.to_string().contains("between two records"), "{r}");
            let r = check(&bytes[..start + len], &all, before + n);
            assert_eq!(r.chunks as usize, i + 1);
            before += n;
        }
        assert_eq!(before, all.len());
        // Whole data section, summary or footer cut anywhere: nothing lost.
        let summary_start = mcap::read::footer(&bytes).unwrap().summary_start as usize;
        for cut in [bytes.len() - 1, bytes.len() - 30, summary_start] {
            let r = check(&bytes[..cut], &all, all.len());
            assert_eq!(r.end, End::Complete, "cut at {cut}: {r}");
        }
    }

    #[test]
    fn a_file_cut_inside_a_chunk_keeps_the_chunks_before_it() {
        let bytes = session_log("middle");
        let all = messages(&bytes);
        let mut before = 0;
        for &(start, len, n) in &chunks(&bytes) {
            for inside in [1, 9, len / 2, len - 1] {
                let r = check(&bytes[..start + inside], &all, before);
                assert_eq!(r.kept_bytes as usize, start);
                let End::Cut {
                    at, opcode, have, ..
                } = r.end
                else {
                    panic!("{r}")
                };
                assert_eq!((at as usize, have as usize), (start, inside));
                if inside >= RECORD_HEADER {
                    assert_eq!(opcode, Some(op::CHUNK));
                    assert!(
                        r.to_string()
                            .contains(&format!("chunk that starts at byte {start}")),
                        "{r}"
                    );
                }
            }
            before += n;
        }
    }

    #[test]
    fn the_open_chunk_of_a_killed_writer_is_dropped_and_named() {
        let bytes = session_log("open");
        let all = messages(&bytes);
        let (start, len, before) = chunk(&bytes, 7);
        // What the writer leaves for a chunk it never closed: the length placeholder.
        let mut cut = bytes[..start + len / 2].to_vec();
        cut[start + 1..start + 9].copy_from_slice(&u64::MAX.to_le_bytes());
        let r = check(&cut, &all, before);
        assert!(matches!(r.end, End::Cut { need: None, .. }), "{r}");
        assert!(
            r.to_string().contains("the record the writer had open"),
            "{r}"
        );
    }

    #[test]
    fn a_damaged_chunk_or_a_tail_of_zeroes_stops_the_scan_there() {
        let bytes = session_log("damaged");
        let all = messages(&bytes);
        let (start, len, before) = chunk(&bytes, 12);
        let mut bad = bytes.clone();
        bad[start + len - 3] ^= 0x5a;
        let r = check(&bad, &all, before);
        assert!(
            matches!(r.end, End::Damaged { at, opcode: op::CHUNK, .. } if at as usize == start),
            "{r}"
        );
        let mut zeroes = bytes[..start].to_vec();
        zeroes.resize(start + 4096, 0);
        let r = check(&zeroes, &all, before);
        assert!(r.to_string().contains("tail of zeroes"), "{r}");
    }

    #[test]
    fn what_is_not_mcap_is_refused_and_tiny_files_recover_empty() {
        assert!(matches!(
            recover_in_memory(b"hello"),
            Err(RecoverError::NotMcap)
        ));
        let (r, out) = recover_in_memory(mcap::MAGIC).unwrap();
        assert_eq!((r.messages, r.chunks), (0, 0));
        assert!(mcap::Summary::read(&out).unwrap().is_some());
        assert!(!is_finished(mcap::MAGIC));
        assert!(is_finished(&session_log("finished")));
    }

    /// Cross-check with another implementation: Python's `mcap` opens the recovered file by its
    /// summary (indexed read, every CRC validated) and counts what the Rust side kept.
    /// Run: `EXOCAL_PYTHON=<venv>/bin/python cargo test -p exocal-log -- --ignored python`.
    #[test]
    #[ignore = "needs the project venv (EXOCAL_PYTHON): `cargo xtask test` runs it"]
    fn python_mcap_reader_opens_a_recovered_file() {
        let python = std::env::var("EXOCAL_PYTHON").unwrap_or_else(|_| "python3".into());
        let bytes = session_log("python");
        let (start, len, _) = chunks(&bytes)[20];
        let (r, out) = recover_in_memory(&bytes[..start + len / 2]).unwrap();
        let path =
            std::env::temp_dir().join(format!("exocald-recovered-{}.mcap", std::process::id()));
        std::fs::write(&path, &out).unwrap();
        // The daemon's tool (its README documents it for users), run on what this crate wrote.
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/../daemon/tools/check_mcap.py");
        let run = std::process::Command::new(&python)
            .arg(script)
            .arg(&path)
            .output()
            .unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
        std::fs::remove_file(&path).unwrap();
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let got: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
        let counts: BTreeMap<String, u64> =
            serde_json::from_value(got["messages"].clone()).unwrap();
        assert_eq!(counts.values().sum::<u64>(), r.messages);
        assert_eq!(counts.len(), Topic::ALL.len(), "{counts:?}");
    }

    /// Hand-made records of an unchunked file: opcode, length, body.
    fn record(op: u8, body: &[u8]) -> Vec<u8> {
        let mut r = vec![op];
        r.extend_from_slice(&(body.len() as u64).to_le_bytes());
        r.extend_from_slice(body);
        r
    }

    fn string(s: &str) -> Vec<u8> {
        let mut b = (s.len() as u32).to_le_bytes().to_vec();
        b.extend_from_slice(s.as_bytes());
        b
    }

    fn schema(id: u16, name: &str) -> Vec<u8> {
        let body = [
            id.to_le_bytes().to_vec(),
            string(name),
            string("jsonschema"),
            string("{}"),
        ]
        .concat();
        record(op::SCHEMA, &body)
    }

    fn channel(id: u16, schema: u16) -> Vec<u8> {
        let body = [
            id.to_le_bytes().to_vec(),
            schema.to_le_bytes().to_vec(),
            string("/t"),
            string("json"),
            0u32.to_le_bytes().to_vec(),
        ]
        .concat();
        record(op::CHANNEL, &body)
    }

    fn message(channel: u16, t: u64) -> Vec<u8> {
        let body = [
            channel.to_le_bytes().to_vec(),
            1u32.to_le_bytes().to_vec(),
            t.to_le_bytes().to_vec(),
            t.to_le_bytes().to_vec(),
            b"{}".to_vec(),
        ]
        .concat();
        record(op::MESSAGE, &body)
    }

    #[test]
    fn records_the_writer_would_refuse_are_damage_not_a_failure() {
        let head = [
            mcap::MAGIC.to_vec(),
            record(op::HEADER, &[string(""), string("hand")].concat()),
            schema(1, "a"),
            channel(1, 1),
            message(1, 5),
        ]
        .concat();
        let (r, out) = recover_in_memory(&head).unwrap();
        assert_eq!((r.messages, r.chunks, r.log_times), (1, 0, Some((5, 5))));
        assert_eq!(messages(&out).len(), 1);
        for (bad, why) in [
            (schema(1, "b"), "schema 1 redefined"),
            (schema(0, "a"), "schema 0 redefined or invalid"),
            (
                channel(2, 7),
                "channel 2 redefined or of a schema never defined",
            ),
            (message(9, 6), "a message on channel 9 never defined"),
        ] {
            let file = [head.clone(), bad, message(1, 7)].concat();
            let (r, out) = recover_in_memory(&file).unwrap();
            assert_eq!(r.messages, 1, "{r}");
            assert!(
                matches!(r.end, End::Damaged { at, .. } if at as usize == head.len()),
                "{r}"
            );
            assert!(r.to_string().contains(why), "{r}");
            assert!(mcap::Summary::read(&out).unwrap().is_some());
        }
    }
}
