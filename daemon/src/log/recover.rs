//! Recovery of a session log cut short (`kill -9`, power loss, OOM kill).
//!
//! The daemon closes, flushes and syncs a chunk at least every `output.flush_interval_s`
//! ([`crate::log::mcaplog`]), so a killed session's file is a run of complete records followed by
//! the chunk that was open: its length field never written, its compressed stream unfinished,
//! and no summary or footer. Readers that start from the footer refuse it.
//!
//! Contract:
//! - works on MCAP records only — header, schemas, channels, messages, chunks, attachments,
//!   metadata — and never decodes a message, so it does not depend on the log's message
//!   encoding;
//! - scans from the start magic, one record at a time, and keeps every record up to the first
//!   one that is cut short or damaged (a bad CRC, a chunk that does not decompress, a tail of
//!   zeroes) or up to the data end; a chunk is kept whole or not at all;
//! - [`recover`] copies what it kept into a new, complete MCAP (summary, chunk and message
//!   indexes, statistics, footer) with the same schema and channel ids, sequence numbers and
//!   times, and returns a [`Recovery`]: how many messages, over which log times, from how many
//!   chunks, and where the input ends ([`End`]);
//! - nothing here panics on any input.

use std::collections::BTreeMap;
use std::fmt;
use std::io::{Cursor, Seek, Write};

use mcap::records::{op, Record};

/// How the input ends.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum End {
    /// The data section is whole: its data-end record was reached (the summary after it is
    /// rebuilt, read or not).
    Complete,
    /// The file stops inside the record that starts at byte `at` (`opcode`, when its first byte
    /// is there): `have` of its `need` bytes are there. `need` is `None` when the record's
    /// 9-byte opcode and length are cut, or its length is the writer's placeholder for the chunk
    /// it had open. `have == 0`: the file stops between two records, before the data end.
    Cut {
        /// Byte offset where the cut record starts.
        at: u64,
        /// Its opcode, when its first byte is there.
        opcode: Option<u8>,
        /// Bytes of it in the file.
        have: u64,
        /// Its full length in bytes, when known.
        need: Option<u64>,
    },
    /// The record at byte `at` is whole but unreadable: the reason.
    Damaged {
        /// Byte offset where the record starts.
        at: u64,
        /// Its opcode.
        opcode: u8,
        /// Why it is unreadable.
        why: String,
    },
}

/// What a scan kept.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Recovery {
    /// Messages kept.
    pub messages: u64,
    /// Complete chunks kept.
    pub chunks: u64,
    /// Earliest and latest log time of the messages kept (ns), if any.
    pub log_times: Option<(u64, u64)>,
    /// Bytes of the input read as whole records (where the kept part ends).
    pub kept_bytes: u64,
    /// Size of the input.
    pub file_bytes: u64,
    /// How the input ends.
    pub end: End,
}

impl Recovery {
    /// Seconds between the first and the last message kept.
    pub fn span_s(&self) -> f64 {
        self.log_times
            .map_or(0.0, |(a, b)| b.saturating_sub(a) as f64 * 1e-9)
    }

    /// Whether every message of the input was kept.
    pub fn is_complete(&self) -> bool {
        self.end == End::Complete
    }
}

/// The record kind, for messages.
fn record_name(opcode: u8) -> String {
    match opcode {
        op::HEADER => "header".into(),
        op::FOOTER => "footer".into(),
        op::SCHEMA => "schema".into(),
        op::CHANNEL => "channel".into(),
        op::MESSAGE => "message".into(),
        op::CHUNK => "chunk".into(),
        op::MESSAGE_INDEX => "message index".into(),
        op::CHUNK_INDEX => "chunk index".into(),
        op::ATTACHMENT => "attachment".into(),
        op::ATTACHMENT_INDEX => "attachment index".into(),
        op::STATISTICS => "statistics".into(),
        op::METADATA => "metadata".into(),
        op::METADATA_INDEX => "metadata index".into(),
        op::SUMMARY_OFFSET => "summary offset".into(),
        op::DATA_END => "data end".into(),
        other => format!("record with opcode {other:#04x}"),
    }
}

impl fmt::Display for End {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            End::Complete => f.write_str("the data section is complete"),
            End::Cut { at, have: 0, .. } => write!(
                f,
                "the file ends at byte {at}, between two records, before the data end"
            ),
            End::Cut {
                at,
                opcode,
                have,
                need,
            } => {
                let name = opcode.map_or_else(|| "record".into(), record_name);
                match need {
                    Some(need) => write!(
                        f,
                        "the file ends inside the {name} that starts at byte {at} ({have} of its \
                         {need} bytes were written)"
                    ),
                    None => write!(
                        f,
                        "the file ends inside the {name} that starts at byte {at} ({have} bytes \
                         written, its length never was: the record the writer had open)"
                    ),
                }
            }
            End::Damaged { at, opcode, why } => write!(
                f,
                "the {} at byte {at} is damaged ({why})",
                record_name(*opcode)
            ),
        }
    }
}

impl fmt::Display for Recovery {
    /// One sentence: what was kept, and where the input stops.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "recovered {} messages ({:.1} s of session) from {} complete chunks, the first {} of \
             {} bytes; {}",
            self.messages,
            self.span_s(),
            self.chunks,
            self.kept_bytes,
            self.file_bytes,
            self.end
        )
    }
}

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

/// Opcode and length of a record header: 1 + 8 bytes.
const RECORD_HEADER: usize = 9;

/// A record that can be copied into the new file.
enum Kept {
    Schema(mcap::records::SchemaHeader, Vec<u8>),
    Channel(mcap::records::Channel),
    Message(mcap::records::MessageHeader, Vec<u8>),
    Attachment(mcap::Attachment<'static>),
    Metadata(mcap::records::Metadata),
}

fn keep(record: Record<'_>) -> Option<Kept> {
    match record {
        Record::Schema { header, data } => Some(Kept::Schema(header, data.into_owned())),
        Record::Channel(c) => Some(Kept::Channel(c)),
        Record::Message { header, data } => Some(Kept::Message(header, data.into_owned())),
        Record::Attachment { header, data, .. } => Some(Kept::Attachment(mcap::Attachment {
            log_time: header.log_time,
            create_time: header.create_time,
            name: header.name,
            media_type: header.media_type,
            data: std::borrow::Cow::Owned(data.into_owned()),
        })),
        Record::Metadata(m) => Some(Kept::Metadata(m)),
        // Indexes, statistics and the footer are rebuilt by the writer.
        _ => None,
    }
}

/// The records inside a chunk, all of them or the reason the chunk is unreadable (the CRC is
/// checked once the last record is out, so nothing is kept before then).
fn chunk_records(header: mcap::records::ChunkHeader, data: &[u8]) -> Result<Vec<Kept>, String> {
    let reader = mcap::read::ChunkReader::new(header, data).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    for record in reader {
        let record = record.map_err(|e| e.to_string())?;
        if let Some(k) = keep(record) {
            out.push(k);
        }
    }
    Ok(out)
}

/// Copies records into the new file, keeping ids, and counts the messages.
/// A schema as the writer compares it: name, encoding, data.
type SchemaKey = (String, String, Vec<u8>);
/// A channel as the writer compares it: schema id, topic, encoding, metadata.
type ChannelKey = (u16, String, String, BTreeMap<String, String>);

struct Copier<W: Write + Seek> {
    writer: mcap::Writer<W>,
    messages: u64,
    log_times: Option<(u64, u64)>,
    /// Schemas and channels copied so far, by id: a record the writer would refuse (an id
    /// redefined differently, a channel of an unknown schema, a message on an unknown channel)
    /// marks its chunk damaged instead of failing the recovery ([`Copier::check`]).
    schemas: BTreeMap<u16, SchemaKey>,
    channels: BTreeMap<u16, ChannelKey>,
}

impl<W: Write + Seek> Copier<W> {
    /// Copies `kept` (checked by [`Copier::check`]: only I/O can fail here).
    fn copy(&mut self, kept: Vec<Kept>) -> Result<(), mcap::McapError> {
        for k in kept {
            match k {
                Kept::Schema(h, data) => {
                    self.writer
                        .add_schema_with_id(h.id, &h.name, &h.encoding, &data)?;
                    self.schemas.insert(h.id, (h.name, h.encoding, data));
                }
                Kept::Channel(c) => {
                    self.writer.add_channel_with_id(
                        c.id,
                        c.schema_id,
                        &c.topic,
                        &c.message_encoding,
                        &c.metadata,
                    )?;
                    self.channels
                        .insert(c.id, (c.schema_id, c.topic, c.message_encoding, c.metadata));
                }
                Kept::Message(header, data) => {
                    self.writer.write_to_known_channel(&header, &data)?;
                    self.messages += 1;
                    let t = header.log_time;
                    self.log_times =
                        Some(self.log_times.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
                }
                Kept::Attachment(a) => self.writer.attach(&a)?,
                Kept::Metadata(m) => self.writer.write_metadata(&m)?,
            }
        }
        Ok(())
    }

    /// Why the writer would refuse a record of `kept`, if it would: a schema id 0 or redefined
    /// differently, a channel redefined differently or of a schema never defined, a message on
    /// a channel never defined (earlier, or in `kept` itself).
    fn check(&self, kept: &[Kept]) -> Result<(), String> {
        let mut schemas: BTreeMap<u16, SchemaKey> = BTreeMap::new();
        let mut channels: BTreeMap<u16, ChannelKey> = BTreeMap::new();
        for k in kept {
            match k {
                Kept::Schema(h, data) => {
                    let key = (h.name.clone(), h.encoding.clone(), data.clone());
                    let known = self.schemas.get(&h.id).or(schemas.get(&h.id));
                    if h.id == 0 || known.is_some_and(|s| *s != key) {
                        return Err(format!("schema {} redefined or invalid", h.id));
                    }
                    schemas.insert(h.id, key);
                }
                Kept::Channel(c) => {
                    let key = (
                        c.schema_id,
                        c.topic.clone(),
                        c.message_encoding.clone(),
                        c.metadata.clone(),
                    );
                    let schema_known = c.schema_id == 0
                        || self.schemas.contains_key(&c.schema_id)
                        || schemas.contains_key(&c.schema_id);
                    let known = self.channels.get(&c.id).or(channels.get(&c.id));
                    if !schema_known || known.is_some_and(|k| *k != key) {
                        return Err(format!(
                            "channel {} redefined or of a schema never defined",
                            c.id
                        ));
                    }
                    channels.insert(c.id, key);
                }
                Kept::Message(h, _)
                    if !self.channels.contains_key(&h.channel_id)
                        && !channels.contains_key(&h.channel_id) =>
                {
                    return Err(format!(
                        "a message on channel {} never defined",
                        h.channel_id
                    ))
                }
                _ => {}
            }
        }
        Ok(())
    }
}

/// Scans `bytes` (see the module docs) and writes what it keeps to `out` as a complete MCAP,
/// its chunks compressed with `compression`. Returns what was kept and the writer.
pub fn recover<W: Write + Seek>(
    bytes: &[u8],
    out: W,
    compression: Option<mcap::Compression>,
) -> Result<(Recovery, W), RecoverError> {
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(RecoverError::NotMcap);
    }
    let mut pos = mcap::MAGIC.len();
    // The header record comes first: its profile and library go to the new file.
    let mut options = mcap::WriteOptions::new()
        .compression(compression)
        .library(concat!("exocald ", env!("CARGO_PKG_VERSION"), " recover"));
    if let Some((op::HEADER, body)) = record_at(bytes, pos) {
        if let Ok(Record::Header(h)) = mcap::parse_record(op::HEADER, body) {
            options = options.profile(h.profile).library(format!(
                "{} (recovered by exocald {})",
                h.library,
                env!("CARGO_PKG_VERSION")
            ));
        }
    }
    let mut copier = Copier {
        writer: mcap::Writer::with_options(out, options)?,
        messages: 0,
        log_times: None,
        schemas: BTreeMap::new(),
        channels: BTreeMap::new(),
    };
    let mut chunks = 0u64;
    let end = loop {
        let at = pos as u64;
        let rest = &bytes[pos..];
        if rest.len() < RECORD_HEADER {
            break End::Cut {
                at,
                opcode: rest.first().copied(),
                have: rest.len() as u64,
                need: None,
            };
        }
        let opcode = rest[0];
        let mut len = [0u8; 8];
        len.copy_from_slice(&rest[1..RECORD_HEADER]);
        let len = u64::from_le_bytes(len);
        let have = (rest.len() - RECORD_HEADER) as u64;
        if opcode == 0 {
            break End::Damaged {
                at,
                opcode,
                why: "opcode 0x00: a tail of zeroes, allocated but never written".into(),
            };
        }
        if len > have {
            break End::Cut {
                at,
                opcode: Some(opcode),
                have: have + RECORD_HEADER as u64,
                // The writer's placeholder for the open chunk is u64::MAX.
                need: len.checked_add(RECORD_HEADER as u64),
            };
        }
        let body = &rest[RECORD_HEADER..RECORD_HEADER + len as usize];
        let damaged = |why: String| End::Damaged { at, opcode, why };
        let record = match mcap::parse_record(opcode, body) {
            Ok(r) => r,
            Err(e) => break damaged(e.to_string()),
        };
        let kept = match record {
            Record::DataEnd(_) => break End::Complete,
            Record::Chunk { header, data } => match chunk_records(header, &data) {
                Ok(kept) => {
                    chunks += 1;
                    kept
                }
                Err(why) => break damaged(why),
            },
            other => keep(other).into_iter().collect(),
        };
        if let Err(why) = copier.check(&kept) {
            break damaged(why);
        }
        copier.copy(kept)?;
        pos += RECORD_HEADER + len as usize;
    };
    let kept_bytes = match &end {
        End::Complete => bytes.len() as u64,
        End::Cut { at, .. } | End::Damaged { at, .. } => *at,
    };
    copier.writer.finish()?;
    let recovery = Recovery {
        messages: copier.messages,
        chunks,
        log_times: copier.log_times,
        kept_bytes,
        file_bytes: bytes.len() as u64,
        end,
    };
    Ok((recovery, copier.writer.into_inner()))
}

/// The opcode and body of the whole record at `pos`, if there is one.
fn record_at(bytes: &[u8], pos: usize) -> Option<(u8, &[u8])> {
    let rest = bytes.get(pos..)?;
    let len = u64::from_le_bytes(rest.get(1..RECORD_HEADER)?.try_into().ok()?);
    let end = RECORD_HEADER.checked_add(usize::try_from(len).ok()?)?;
    Some((rest[0], rest.get(RECORD_HEADER..end)?))
}

/// Whether `bytes` is an MCAP file with its end magic (a finished log; anything else that starts
/// like MCAP is read through [`recover`]).
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
    use crate::log::mcaplog::{CanFrameRecord, Level, SessionLog, Topic};
    use crate::log::records::Record;
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
        let c = chunks(&bytes);
        let (start, len, _) = c[7];
        // What the writer leaves for a chunk it never closed: the length placeholder.
        let mut cut = bytes[..start + len / 2].to_vec();
        cut[start + 1..start + 9].copy_from_slice(&u64::MAX.to_le_bytes());
        let before: usize = c[..7].iter().map(|x| x.2).sum();
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
        let c = chunks(&bytes);
        let (start, len, _) = c[12];
        let before: usize = c[..12].iter().map(|x| x.2).sum();
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
    /// Run: `EXOCAL_PYTHON=<venv>/bin/python cargo test -p exocald -- --ignored python`.
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
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/check_mcap.py");
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
        let counts: BTreeMap<String, u64> = serde_json::from_value(got["counts"].clone()).unwrap();
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
