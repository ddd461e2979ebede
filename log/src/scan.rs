//! A bounded scan of an MCAP file, record by record.
//!
//! Contract:
//! - [`scan`] reads the data section from a [`Read`] (a file, a byte slice) one record at a
//!   time: opcode, length, body. Every length — of a record, a string, a map, a chunk's
//!   compressed and decompressed data — is checked against the input left and against
//!   [`MAX_RECORD_BYTES`], [`MAX_CHUNK_BYTES`] before anything is allocated for it, so the scan
//!   holds at most one record and one decompressed chunk, whatever the file's size or claims;
//! - every record is parsed here, its lengths checked field by field; a chunk is decompressed
//!   (none, zstd or lz4) into at most the size it declares, its CRC checked, and every record
//!   in it parsed before any is handed out: a chunk is handed out whole or not at all;
//! - ids must agree: a schema id 0 or one redefined differently, a channel redefined
//!   differently or of a schema never defined, a message on a channel never defined are
//!   damage (a writer would refuse them; a reader could not decode them);
//! - the scan stops at the data end (checking the data section's CRC when it has one), at the
//!   first record cut short or at the first damaged one, and says which ([`End`]); [`Scan`]
//!   counts what was handed out before. It then reads on to the end of the input, without
//!   keeping it and at most [`MAX_DRAIN_BYTES`] further, to tell whether the file was finished
//!   ([`Scan::finished`]: it ends with the MCAP magic; an input longer than that is taken as
//!   unfinished, so an endless or huge input, `/dev/zero` or a sparse file, ends the scan in
//!   bounded time). An input without the MCAP magic is not read past it;
//! - nothing here panics on any input, and only the caller's callback can fail the scan.

use std::collections::{HashMap, HashSet};
use std::fmt;
use std::io::Read;

use mcap::records::op;

/// Most bytes read past the point where a scan stopped, looking for the file's end magic. A
/// session log is tens of MB (about 6 MB a minute); a file whose end lies further than this past
/// its damage is taken as unfinished.
pub const MAX_DRAIN_BYTES: u64 = 1 << 30;

/// Longest record outside a chunk, and longest record inside one (bytes). Session logs hold
/// protobuf schemas of a few kB and messages of a few hundred bytes.
pub const MAX_RECORD_BYTES: u64 = 16 << 20;
/// Most decompressed bytes of one chunk; also the most compressed bytes of one (plus
/// [`MAX_CHUNK_HEADER_BYTES`]). The daemon closes its chunks at 1 MiB.
pub const MAX_CHUNK_BYTES: u64 = 16 << 20;
/// Longest chunk header (its compression name included).
pub const MAX_CHUNK_HEADER_BYTES: u64 = 4 << 10;

/// Largest zstd window a chunk may ask the decoder for (2^24 = [`MAX_CHUNK_BYTES`]).
const ZSTD_WINDOW_LOG_MAX: u32 = 24;

/// Opcode and length of a record: 1 + 8 bytes.
const RECORD_HEADER: u64 = 9;

/// A record of the data section, parsed; strings and bytes borrowed from the scan's buffers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum McapRecord<'a> {
    /// The file's header.
    Header {
        /// Profile.
        profile: &'a str,
        /// Writing library.
        library: &'a str,
    },
    /// A schema.
    Schema {
        /// Id (never 0).
        id: u16,
        /// Name.
        name: &'a str,
        /// Encoding.
        encoding: &'a str,
        /// Schema data.
        data: &'a [u8],
    },
    /// A channel.
    Channel {
        /// Id.
        id: u16,
        /// Its schema's id (0: none).
        schema_id: u16,
        /// Topic.
        topic: &'a str,
        /// Message encoding.
        encoding: &'a str,
        /// Metadata, in file order (keys distinct).
        metadata: Vec<(&'a str, &'a str)>,
    },
    /// A message.
    Message {
        /// Its channel's id.
        channel_id: u16,
        /// Sequence number.
        sequence: u32,
        /// Log time (ns).
        log_time: u64,
        /// Publish time (ns).
        publish_time: u64,
        /// The message.
        data: &'a [u8],
    },
    /// An attachment (its CRC checked when it has one).
    Attachment {
        /// Log time (ns).
        log_time: u64,
        /// Creation time (ns).
        create_time: u64,
        /// Name.
        name: &'a str,
        /// Media type.
        media_type: &'a str,
        /// Content.
        data: &'a [u8],
    },
    /// A metadata record.
    Metadata {
        /// Name.
        name: &'a str,
        /// Key-value pairs, in file order (keys distinct).
        metadata: Vec<(&'a str, &'a str)>,
    },
}

/// How the data section ends.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum End {
    /// The data section is whole: its data-end record was reached.
    Complete,
    /// The input does not start with the MCAP magic.
    NotMcap,
    /// The input stops inside the record that starts at byte `at` (`opcode`, when its first
    /// byte is there): `have` of its `need` bytes are there. `need` is `None` when the record's
    /// 9-byte opcode and length are cut, or its length is beyond any the scan reads (the
    /// writer's placeholder for the chunk it had open). `have == 0`: the input stops between
    /// two records, before the data end.
    Cut {
        /// Byte offset where the cut record starts.
        at: u64,
        /// Its opcode, when its first byte is there.
        opcode: Option<u8>,
        /// Bytes of it in the input.
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

/// What a scan handed out, and where it stopped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Scan {
    /// Messages handed out.
    pub messages: u64,
    /// Whole chunks handed out.
    pub chunks: u64,
    /// Earliest and latest log time of the messages handed out (ns), if any.
    pub log_times: Option<(u64, u64)>,
    /// Bytes of the input read as whole records (where what was handed out ends).
    pub kept_bytes: u64,
    /// Size of the input: what was read of it (not past its first bytes for an input that is
    /// not MCAP, at most [`MAX_DRAIN_BYTES`] past where the scan stopped otherwise).
    pub file_bytes: u64,
    /// Whether the input ends with the MCAP magic (a writer finished it).
    pub finished: bool,
    /// How the data section ends.
    pub end: End,
}

impl Scan {
    /// Seconds between the first and the last message handed out.
    pub fn span_s(&self) -> f64 {
        self.log_times
            .map_or(0.0, |(a, b)| b.saturating_sub(a) as f64 * 1e-9)
    }

    /// Whether every record of the data section was handed out.
    pub fn is_complete(&self) -> bool {
        self.end == End::Complete
    }
}

/// The record kind, for messages.
pub fn record_name(opcode: u8) -> String {
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
            End::NotMcap => f.write_str("not an MCAP file (no MCAP magic at its start)"),
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

impl fmt::Display for Scan {
    /// One sentence: what was read, and where the input stops.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} messages ({:.1} s of session) in {} complete chunks, the first {} of {} bytes; {}",
            self.messages,
            self.span_s(),
            self.chunks,
            self.kept_bytes,
            self.file_bytes,
            self.end
        )
    }
}

/// The fields of a record body, read in order, every length checked against what is left.
struct Fields<'a> {
    body: &'a [u8],
    pos: usize,
}

impl<'a> Fields<'a> {
    fn new(body: &'a [u8]) -> Self {
        Fields { body, pos: 0 }
    }

    fn left(&self) -> usize {
        self.body.len() - self.pos
    }

    fn take(&mut self, n: u64, what: &str) -> Result<&'a [u8], String> {
        let left = self.left();
        match usize::try_from(n) {
            Ok(n) if n <= left => {
                let out = &self.body[self.pos..self.pos + n];
                self.pos += n;
                Ok(out)
            }
            _ => Err(format!(
                "{what}: {n} bytes declared, {left} left in the record"
            )),
        }
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], String> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N as u64, what)?);
        Ok(out)
    }

    fn u16(&mut self, what: &str) -> Result<u16, String> {
        self.array(what).map(u16::from_le_bytes)
    }

    fn u32(&mut self, what: &str) -> Result<u32, String> {
        self.array(what).map(u32::from_le_bytes)
    }

    fn u64(&mut self, what: &str) -> Result<u64, String> {
        self.array(what).map(u64::from_le_bytes)
    }

    fn bytes32(&mut self, what: &str) -> Result<&'a [u8], String> {
        let n = self.u32(what)?;
        self.take(u64::from(n), what)
    }

    fn bytes64(&mut self, what: &str) -> Result<&'a [u8], String> {
        let n = self.u64(what)?;
        self.take(n, what)
    }

    fn string(&mut self, what: &str) -> Result<&'a str, String> {
        let bytes = self.bytes32(what)?;
        std::str::from_utf8(bytes).map_err(|e| format!("{what}: not UTF-8 ({e})"))
    }

    /// A string-to-string map: its length in bytes, then key and value strings. Keys are
    /// checked distinct through a set, in time linear in the map: a record of
    /// [`MAX_RECORD_BYTES`] holds over a million short keys, ~10^12 comparisons had each key
    /// been compared with every earlier one.
    fn map(&mut self, what: &str) -> Result<Vec<(&'a str, &'a str)>, String> {
        let mut inner = Fields::new(self.bytes32(what)?);
        let mut out: Vec<(&str, &str)> = Vec::new();
        let mut seen: HashSet<&str> = HashSet::new();
        while inner.left() > 0 {
            let k = inner.string(what)?;
            let v = inner.string(what)?;
            if !seen.insert(k) {
                return Err(format!("{what}: key {k:?} twice"));
            }
            out.push((k, v));
        }
        Ok(out)
    }

    fn rest(&mut self) -> &'a [u8] {
        let out = &self.body[self.pos..];
        self.pos = self.body.len();
        out
    }
}

/// Parses the body of a record of kind `opcode`; `None` for the kinds the scan skips (indexes,
/// statistics, the footer, summary offsets, unknown opcodes).
fn parse(opcode: u8, body: &[u8]) -> Result<Option<McapRecord<'_>>, String> {
    let mut f = Fields::new(body);
    let record = match opcode {
        op::HEADER => McapRecord::Header {
            profile: f.string("profile")?,
            library: f.string("library")?,
        },
        op::SCHEMA => McapRecord::Schema {
            id: f.u16("schema id")?,
            name: f.string("schema name")?,
            encoding: f.string("schema encoding")?,
            data: f.bytes32("schema data")?,
        },
        op::CHANNEL => McapRecord::Channel {
            id: f.u16("channel id")?,
            schema_id: f.u16("schema id")?,
            topic: f.string("topic")?,
            encoding: f.string("message encoding")?,
            metadata: f.map("channel metadata")?,
        },
        op::MESSAGE => McapRecord::Message {
            channel_id: f.u16("channel id")?,
            sequence: f.u32("sequence")?,
            log_time: f.u64("log time")?,
            publish_time: f.u64("publish time")?,
            data: f.rest(),
        },
        op::ATTACHMENT => {
            let record = McapRecord::Attachment {
                log_time: f.u64("log time")?,
                create_time: f.u64("create time")?,
                name: f.string("name")?,
                media_type: f.string("media type")?,
                data: f.bytes64("attachment data")?,
            };
            let covered = f.pos;
            let saved = f.u32("attachment CRC")?;
            let computed = crc32fast::hash(&body[..covered]);
            if saved != 0 && saved != computed {
                return Err(crc_mismatch(saved, computed));
            }
            record
        }
        op::METADATA => McapRecord::Metadata {
            name: f.string("name")?,
            metadata: f.map("metadata")?,
        },
        _ => return Ok(None),
    };
    Ok(Some(record))
}

fn crc_mismatch(saved: u32, computed: u32) -> String {
    format!("CRC mismatch: {saved:#010x} saved, {computed:#010x} computed")
}

/// A chunk's records, decompressed, CRC-checked and parsed into `buf` and the returned list.
fn chunk<'b>(body: &[u8], buf: &'b mut Vec<u8>) -> Result<Vec<McapRecord<'b>>, String> {
    let mut f = Fields::new(body);
    let _start = f.u64("message start time")?;
    let _end = f.u64("message end time")?;
    let size = f.u64("uncompressed size")?;
    let crc = f.u32("uncompressed CRC")?;
    let compression = f.string("compression")?;
    let data = f.bytes64("compressed records")?;
    if size > MAX_CHUNK_BYTES {
        return Err(format!(
            "{size} bytes once decompressed, more than the {MAX_CHUNK_BYTES} a chunk may hold"
        ));
    }
    // `size` is at most MAX_CHUNK_BYTES: it fits a usize, and the buffer is bounded by it.
    let size = size as usize;
    buf.clear();
    match compression {
        "" => buf.extend_from_slice(data),
        "zstd" => {
            buf.reserve(size);
            zstd::stream::read::Decoder::with_buffer(data)
                .and_then(|mut d| {
                    d.window_log_max(ZSTD_WINDOW_LOG_MAX)?;
                    d.take(size as u64 + 1).read_to_end(buf)
                })
                .map_err(|e| format!("zstd: {e}"))?;
        }
        "lz4" => {
            buf.reserve(size);
            lz4::Decoder::new(data)
                .and_then(|d| d.take(size as u64 + 1).read_to_end(buf))
                .map_err(|e| format!("lz4: {e}"))?;
        }
        other => return Err(format!("compression {other:?} unknown")),
    }
    if buf.len() > size {
        return Err(format!(
            "decompresses to more than the {size} bytes declared"
        ));
    }
    if buf.len() < size {
        return Err(format!(
            "decompresses to {} bytes, {size} declared",
            buf.len()
        ));
    }
    let computed = crc32fast::hash(buf);
    if crc != 0 && crc != computed {
        return Err(crc_mismatch(crc, computed));
    }
    let mut records = Vec::new();
    let mut rest = Fields::new(buf.as_slice());
    while rest.left() > 0 {
        let opcode = rest.array::<1>("record opcode")?[0];
        let len = rest.u64("record length")?;
        let inner = rest.take(len, &format!("a {} inside", record_name(opcode)))?;
        match opcode {
            op::SCHEMA | op::CHANNEL | op::MESSAGE => {}
            other => return Err(format!("a {} inside", record_name(other))),
        }
        if let Some(r) =
            parse(opcode, inner).map_err(|e| format!("the {} inside: {e}", record_name(opcode)))?
        {
            records.push(r);
        }
    }
    Ok(records)
}

/// What a schema or channel id was defined as: the CRC of its record body.
#[derive(Default)]
struct Ids {
    schemas: HashMap<u16, u32>,
    channels: HashMap<u16, u32>,
}

impl Ids {
    /// Checks `records` (a unit: one record or a chunk's) against the ids defined so far and
    /// in `records` itself; on success, defines theirs.
    fn admit(&mut self, records: &[McapRecord<'_>]) -> Result<(), String> {
        // The unit's own definitions, by id (a chunk may define all 65,535 of each and hold
        // hundreds of thousands of messages: every lookup is by key).
        let mut schemas: HashMap<u16, u32> = HashMap::new();
        let mut channels: HashMap<u16, u32> = HashMap::new();
        let find = |known: &HashMap<u16, u32>, new: &HashMap<u16, u32>, id: u16| {
            known.get(&id).or_else(|| new.get(&id)).copied()
        };
        for r in records {
            match r {
                McapRecord::Schema {
                    id,
                    name,
                    encoding,
                    data,
                } => {
                    let key = digest(&[name.as_bytes(), encoding.as_bytes(), data]);
                    let known = find(&self.schemas, &schemas, *id);
                    if *id == 0 || known.is_some_and(|k| k != key) {
                        return Err(format!("schema {id} redefined or invalid"));
                    }
                    schemas.insert(*id, key);
                }
                McapRecord::Channel {
                    id,
                    schema_id,
                    topic,
                    encoding,
                    metadata,
                } => {
                    let sid = schema_id.to_le_bytes();
                    let mut parts: Vec<&[u8]> = vec![&sid, topic.as_bytes(), encoding.as_bytes()];
                    for (k, v) in metadata {
                        parts.extend([k.as_bytes(), v.as_bytes()]);
                    }
                    let key = digest(&parts);
                    let schema_known =
                        *schema_id == 0 || find(&self.schemas, &schemas, *schema_id).is_some();
                    let known = find(&self.channels, &channels, *id);
                    if !schema_known || known.is_some_and(|k| k != key) {
                        return Err(format!(
                            "channel {id} redefined or of a schema never defined"
                        ));
                    }
                    channels.insert(*id, key);
                }
                McapRecord::Message { channel_id, .. }
                    if find(&self.channels, &channels, *channel_id).is_none() =>
                {
                    return Err(format!("a message on channel {channel_id} never defined"));
                }
                _ => {}
            }
        }
        self.schemas.extend(schemas);
        self.channels.extend(channels);
        Ok(())
    }
}

/// CRC-32 of the parts, each preceded by its length (so that the split is part of the key).
fn digest(parts: &[&[u8]]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for p in parts {
        h.update(&(p.len() as u64).to_le_bytes());
        h.update(p);
    }
    h.finalize()
}

/// The input, read with a running CRC of the data section and a count of the bytes read.
struct Input<R: Read> {
    inner: R,
    pos: u64,
    crc: crc32fast::Hasher,
    /// The last bytes read (up to the magic's length), to tell a finished file.
    tail: Vec<u8>,
}

impl<R: Read> Input<R> {
    /// Reads up to `n` bytes into `buf` (cleared first); fewer only at the end of the input.
    /// An I/O error other than an interruption ends the input there.
    fn read(&mut self, n: u64, buf: &mut Vec<u8>) -> u64 {
        buf.clear();
        let got = (&mut self.inner)
            .take(n)
            .read_to_end(buf)
            .unwrap_or(buf.len());
        self.crc.update(buf);
        self.pos += got as u64;
        self.keep_tail(buf);
        got as u64
    }

    fn keep_tail(&mut self, bytes: &[u8]) {
        let m = mcap::MAGIC.len();
        self.tail
            .extend_from_slice(&bytes[bytes.len().saturating_sub(m)..]);
        let extra = self.tail.len().saturating_sub(m);
        self.tail.drain(..extra);
    }

    /// Reads the rest of the input without keeping it, at most [`MAX_DRAIN_BYTES`]; returns how
    /// many bytes that was, and whether the input ended within them.
    fn drain(&mut self) -> (u64, bool) {
        let mut chunk = [0u8; 64 << 10];
        let mut total = 0u64;
        let ended = loop {
            if total >= MAX_DRAIN_BYTES {
                break false;
            }
            match self.inner.read(&mut chunk) {
                Ok(0) => break true,
                Ok(n) => {
                    total += n as u64;
                    self.keep_tail(&chunk[..n]);
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(_) => break true,
            }
        };
        self.pos += total;
        if !ended {
            // Whatever its last bytes, this is not where the input ends.
            self.tail.clear();
        }
        (total, ended)
    }
}

/// Scans `input` (see the module docs), handing each whole unit — one record, or every record
/// of a chunk — to `f`. Stops early only if `f` fails.
pub fn scan<R: Read, E>(
    input: R,
    mut f: impl FnMut(&[McapRecord<'_>]) -> Result<(), E>,
) -> Result<Scan, E> {
    let mut input = Input {
        inner: input,
        pos: 0,
        crc: crc32fast::Hasher::new(),
        tail: Vec::new(),
    };
    let mut out = Scan {
        messages: 0,
        chunks: 0,
        log_times: None,
        kept_bytes: 0,
        file_bytes: 0,
        finished: false,
        end: End::NotMcap,
    };
    let mut body = Vec::new();
    let mut decompressed = Vec::new();
    let mut ids = Ids::default();
    let magic = input.read(mcap::MAGIC.len() as u64, &mut body);
    out.end = if magic as usize == mcap::MAGIC.len() && body == mcap::MAGIC {
        loop {
            let at = input.pos;
            out.kept_bytes = at;
            let crc_before = input.crc.clone().finalize();
            let have = input.read(RECORD_HEADER, &mut body);
            if have < RECORD_HEADER {
                break End::Cut {
                    at,
                    opcode: body.first().copied(),
                    have,
                    need: None,
                };
            }
            let opcode = body[0];
            let mut len = [0u8; 8];
            len.copy_from_slice(&body[1..9]);
            let len = u64::from_le_bytes(len);
            if opcode == 0 {
                break End::Damaged {
                    at,
                    opcode,
                    why: "opcode 0x00: a tail of zeroes, allocated but never written".into(),
                };
            }
            let limit = match opcode {
                op::CHUNK => MAX_CHUNK_BYTES + MAX_CHUNK_HEADER_BYTES,
                _ => MAX_RECORD_BYTES,
            };
            if len > limit {
                // Either the writer's placeholder for the chunk it had open (the file ends
                // inside it) or a length no record of ours has.
                let (rest, _) = input.drain();
                break if rest < len {
                    End::Cut {
                        at,
                        opcode: Some(opcode),
                        have: RECORD_HEADER + rest,
                        need: len.checked_add(RECORD_HEADER),
                    }
                } else {
                    End::Damaged {
                        at,
                        opcode,
                        why: format!("{len} bytes long, more than the {limit} a record may be"),
                    }
                };
            }
            let got = input.read(len, &mut body);
            if got < len {
                break End::Cut {
                    at,
                    opcode: Some(opcode),
                    have: RECORD_HEADER + got,
                    need: Some(RECORD_HEADER + len),
                };
            }
            let damaged = |why: String| End::Damaged { at, opcode, why };
            let records = match opcode {
                op::DATA_END => {
                    let saved = match Fields::new(&body).u32("data section CRC") {
                        Ok(crc) => crc,
                        Err(why) => break damaged(why),
                    };
                    if saved != 0 && saved != crc_before {
                        break damaged(format!("data section {}", crc_mismatch(saved, crc_before)));
                    }
                    out.kept_bytes = input.pos;
                    break End::Complete;
                }
                op::CHUNK => match chunk(&body, &mut decompressed) {
                    Ok(records) => records,
                    Err(why) => break damaged(why),
                },
                _ => match parse(opcode, &body) {
                    Ok(record) => record.into_iter().collect(),
                    Err(why) => break damaged(why),
                },
            };
            if let Err(why) = ids.admit(&records) {
                break damaged(why);
            }
            f(&records)?;
            out.chunks += u64::from(opcode == op::CHUNK);
            for r in &records {
                if let McapRecord::Message { log_time: t, .. } = *r {
                    out.messages += 1;
                    out.log_times =
                        Some(out.log_times.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
                }
            }
        }
    } else {
        End::NotMcap
    };
    match out.end {
        // Everything was read up to the end of the input already.
        End::Cut { have, .. } => out.file_bytes = out.kept_bytes + have,
        // Not an MCAP file: nothing past its first bytes tells anything more.
        End::NotMcap => out.file_bytes = input.pos,
        _ => {
            input.drain();
            out.file_bytes = input.pos;
        }
    }
    out.finished = out.file_bytes >= 2 * mcap::MAGIC.len() as u64 && input.tail == mcap::MAGIC;
    Ok(out)
}

/// Bytes from the start of a file that [`header`] looks at.
pub const HEADER_PEEK_BYTES: u64 = 4 << 10;

/// The profile and library of the header record right after the magic, if `prefix` (the
/// start of a file) holds one whole.
pub fn header(prefix: &[u8]) -> Option<(&str, &str)> {
    let mut f = Fields::new(prefix.strip_prefix(mcap::MAGIC)?);
    let opcode = f.array::<1>("opcode").ok()?[0];
    let body = f.bytes64("header").ok()?;
    match (opcode, parse(opcode, body)) {
        (op::HEADER, Ok(Some(McapRecord::Header { profile, library }))) => Some((profile, library)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `/dev/zero`, or a sparse file's hole after a magic: the scan ends in bounded time.
    #[test]
    fn an_endless_input_ends_the_scan() {
        let none = |_: &[McapRecord<'_>]| Ok::<(), ()>(());
        let s = scan(std::io::repeat(0), none).unwrap();
        assert!(matches!(s.end, End::NotMcap));
        assert_eq!(s.file_bytes, mcap::MAGIC.len() as u64);
        let s = scan(mcap::MAGIC.chain(std::io::repeat(0)), none).unwrap();
        assert!(
            matches!(
                s.end,
                End::Damaged {
                    at: 8,
                    opcode: 0,
                    ..
                }
            ),
            "{}",
            s.end
        );
        assert!(!s.finished);
        let stopped = mcap::MAGIC.len() as u64 + RECORD_HEADER;
        assert!(s.file_bytes >= stopped + MAX_DRAIN_BYTES);
        assert!(s.file_bytes <= stopped + MAX_DRAIN_BYTES + (64 << 10));
    }

    /// A finished file of `chunks` chunks (compressed with `compression`) of 3 messages each on
    /// two channels, with a metadata record and an attachment between them.
    fn file(chunks: u64, compression: Option<mcap::Compression>) -> Vec<u8> {
        let mut buf = std::io::Cursor::new(Vec::new());
        {
            let options = mcap::WriteOptions::new()
                .compression(compression)
                .profile("test");
            let mut w = mcap::Writer::with_options(&mut buf, options).unwrap();
            let schema = w.add_schema("s", "jsonschema", b"{}").unwrap();
            let meta = [("k".to_string(), "v".to_string())].into_iter().collect();
            let a = w.add_channel(schema, "/a", "json", &meta).unwrap();
            let b = w.add_channel(0, "/b", "raw", &Default::default()).unwrap();
            for k in 0..chunks {
                for (i, ch) in [a, b, a].into_iter().enumerate() {
                    let t = 1_000 * k + i as u64;
                    let header = mcap::records::MessageHeader {
                        channel_id: ch,
                        sequence: t as u32,
                        log_time: t,
                        publish_time: t,
                    };
                    w.write_to_known_channel(&header, format!("{{\"k\":{t}}}").as_bytes())
                        .unwrap();
                }
                w.flush().unwrap();
            }
            w.write_metadata(&mcap::records::Metadata {
                name: "m".into(),
                metadata: [("x".to_string(), "y".to_string())].into_iter().collect(),
            })
            .unwrap();
            w.attach(&mcap::Attachment {
                log_time: 1,
                create_time: 2,
                name: "a.txt".into(),
                media_type: "text/plain".into(),
                data: std::borrow::Cow::Borrowed(b"hello"),
            })
            .unwrap();
            w.finish().unwrap();
        }
        buf.into_inner()
    }

    /// Every unit handed out: (records per unit, messages' data).
    fn units(bytes: &[u8]) -> (Scan, Vec<usize>, Vec<Vec<u8>>) {
        let (mut sizes, mut data) = (Vec::new(), Vec::new());
        let s = scan(bytes, |records| {
            sizes.push(records.len());
            for r in records {
                if let McapRecord::Message { data: d, .. } = r {
                    data.push(d.to_vec());
                }
            }
            Ok::<(), ()>(())
        })
        .unwrap();
        (s, sizes, data)
    }

    /// Where the data end record starts: a data section's bytes are before it.
    fn data_end(bytes: &[u8]) -> usize {
        let footer = mcap::read::footer(bytes).unwrap();
        let summary = footer.summary_start as usize;
        // The data end record (opcode, length 4, CRC) is the last of the data section.
        summary - 13
    }

    #[test]
    fn a_finished_file_scans_whole_with_every_record_parsed() {
        for compression in [
            None,
            Some(mcap::Compression::Zstd),
            Some(mcap::Compression::Lz4),
        ] {
            let bytes = file(4, compression);
            let (s, sizes, data) = units(&bytes);
            assert_eq!(s.end, End::Complete, "{compression:?}: {s}");
            assert!(s.finished && s.is_complete());
            assert_eq!((s.messages, s.chunks), (12, 4), "{s}");
            assert_eq!(s.log_times, Some((0, 3_002)));
            assert_eq!(s.file_bytes, bytes.len() as u64);
            assert_eq!(data[5], b"{\"k\":1002}");
            // Header, schema and channels before the first message, then one unit per chunk
            // (each whole), the metadata and the attachment.
            assert!(sizes.contains(&3), "{sizes:?}");
        }
        let bytes = file(1, None);
        let mut seen = Vec::new();
        scan(bytes.as_slice(), |records| {
            for r in records {
                match r {
                    McapRecord::Header { profile, .. } => seen.push(format!("header {profile}")),
                    McapRecord::Channel {
                        topic, metadata, ..
                    } => seen.push(format!("channel {topic} {metadata:?}")),
                    McapRecord::Metadata { metadata, .. } => {
                        seen.push(format!("metadata {metadata:?}"))
                    }
                    McapRecord::Attachment { name, data, .. } => {
                        seen.push(format!("attachment {name} {}", data.len()))
                    }
                    _ => {}
                }
            }
            Ok::<(), ()>(())
        })
        .unwrap();
        assert!(seen.contains(&"header test".to_string()), "{seen:?}");
        assert!(
            seen.contains(&"channel /a [(\"k\", \"v\")]".to_string()),
            "{seen:?}"
        );
        assert!(
            seen.contains(&"metadata [(\"x\", \"y\")]".to_string()),
            "{seen:?}"
        );
        assert!(seen.contains(&"attachment a.txt 5".to_string()), "{seen:?}");
    }

    /// Every prefix of a file: never a panic; a chunk is handed out whole or not at all, and
    /// the scan says where the input stops.
    #[test]
    fn every_truncation_keeps_whole_chunks_and_says_where_it_stops() {
        let bytes = file(3, Some(mcap::Compression::Zstd));
        let end = data_end(&bytes);
        for cut in 0..bytes.len() {
            let (s, _, data) = units(&bytes[..cut]);
            assert_eq!(s.file_bytes, cut as u64);
            assert!(!s.finished, "cut at {cut}");
            assert_eq!(data.len() % 3, 0, "cut at {cut}: a chunk in part");
            match cut {
                0..=7 => assert_eq!(s.end, End::NotMcap),
                c if c < end + 13 => assert!(matches!(s.end, End::Cut { .. }), "{c}: {s}"),
                _ => assert_eq!((s.end, s.messages), (End::Complete, 9)),
            }
        }
    }

    /// Every single bit flip in the data section is noticed (the record's own checks, the
    /// chunk CRC or the data section's), never a panic; flips in the summary do not matter.
    #[test]
    fn every_bit_flip_in_the_data_section_is_damage() {
        let bytes = file(2, Some(mcap::Compression::Zstd));
        let end = data_end(&bytes);
        let mut b = bytes.clone();
        for at in 0..bytes.len() {
            for bit in 0..8 {
                b[at] ^= 1 << bit;
                let (s, _, data) = units(&b);
                // The data end's length (bytes end+1..end+9) is the one field whose change
                // alters nothing read: its CRC is read from the same place.
                if at < end + 13 && !(end + 1..end + 9).contains(&at) {
                    assert!(!s.is_complete(), "flip at {at}.{bit} unnoticed: {s}");
                } else {
                    assert_eq!(data.len(), 6, "flip at {at}.{bit}");
                }
                b[at] ^= 1 << bit;
            }
        }
    }

    /// Hand-made records: opcode, length, body.
    fn record(op: u8, body: &[u8]) -> Vec<u8> {
        [
            vec![op],
            (body.len() as u64).to_le_bytes().to_vec(),
            body.to_vec(),
        ]
        .concat()
    }

    fn string(s: &str) -> Vec<u8> {
        [
            (s.len() as u32).to_le_bytes().to_vec(),
            s.as_bytes().to_vec(),
        ]
        .concat()
    }

    fn chunk(size: u64, crc: u32, compression: &str, data: &[u8]) -> Vec<u8> {
        let body = [
            0u64.to_le_bytes().to_vec(),
            1u64.to_le_bytes().to_vec(),
            size.to_le_bytes().to_vec(),
            crc.to_le_bytes().to_vec(),
            string(compression),
            (data.len() as u64).to_le_bytes().to_vec(),
            data.to_vec(),
        ]
        .concat();
        record(op::CHUNK, &body)
    }

    fn end_of(file: &[u8]) -> End {
        units(file).0.end
    }

    /// Lengths beyond the input or the limits are refused before anything is allocated for
    /// them: the 1-TB chunk, the 2^62-byte record, the 4-GB string, the decompression bomb.
    #[test]
    fn declared_lengths_are_checked_before_anything_is_allocated() {
        let magic = mcap::MAGIC.to_vec();
        let why = |e: End| match e {
            End::Damaged { why, .. } => why,
            other => panic!("{other}"),
        };
        let f = [magic.clone(), chunk(1 << 40, 0, "zstd", b"x")].concat();
        assert!(why(end_of(&f)).contains("1099511627776 bytes once decompressed, more than"));
        // A record length far beyond the input: cut short, read without being kept.
        let mut f = [magic.clone(), record(op::SCHEMA, b"")].concat();
        f[9..17].copy_from_slice(&(1u64 << 62).to_le_bytes());
        f.extend_from_slice(&[7u8; 100]);
        let e = end_of(&f);
        assert!(
            matches!(e, End::Cut { at: 8, have: 109, need: Some(n), .. } if n == (1 << 62) + 9),
            "{e}"
        );
        // Longer than a record may be, and there: damaged.
        let big = vec![1u8; MAX_RECORD_BYTES as usize + 1];
        let f = [magic.clone(), record(0x42, &big)].concat();
        assert!(why(end_of(&f)).contains("more than the 16777216 a record may be"));
        // A string claiming 4 GB in a 12-byte channel record.
        let body = [
            1u16.to_le_bytes().to_vec(),
            0u16.to_le_bytes().to_vec(),
            u32::MAX.to_le_bytes().to_vec(),
            b"/a".to_vec(),
        ]
        .concat();
        let f = [magic.clone(), record(op::CHANNEL, &body)].concat();
        assert_eq!(
            why(end_of(&f)),
            "topic: 4294967295 bytes declared, 2 left in the record"
        );
        // A zstd stream that decompresses past what the chunk declares (1 MB of zeroes, 64 B
        // declared), and one that stops short of it.
        let zeroes = zstd::bulk::compress(&vec![0u8; 1 << 20], 3).unwrap();
        let f = [magic.clone(), chunk(64, 0, "zstd", &zeroes)].concat();
        assert!(why(end_of(&f)).contains("decompresses to more than the 64 bytes declared"));
        let f = [magic.clone(), chunk(2 << 20, 0, "zstd", &zeroes)].concat();
        assert!(why(end_of(&f)).contains("decompresses to 1048576 bytes, 2097152 declared"));
        let f = [magic.clone(), chunk(1, 0, "brotli", b"x")].concat();
        assert!(why(end_of(&f)).contains("compression \"brotli\" unknown"));
        // A chunk whose CRC does not match, and one holding a record a chunk may not hold.
        let inner = record(
            op::SCHEMA,
            &[
                1u16.to_le_bytes().to_vec(),
                string("s"),
                string("e"),
                string(""),
            ]
            .concat(),
        );
        let f = [magic.clone(), chunk(inner.len() as u64, 7, "", &inner)].concat();
        assert!(why(end_of(&f)).contains("CRC mismatch: 0x00000007 saved"));
        let inner = record(op::DATA_END, &[0; 4]);
        let f = [magic.clone(), chunk(inner.len() as u64, 0, "", &inner)].concat();
        assert_eq!(why(end_of(&f)), "a data end inside");
        // An attachment shorter than its fields say (the mcap crate's parser panicked on it).
        let f = [magic.clone(), record(op::ATTACHMENT, &[0u8; 3])].concat();
        assert_eq!(
            why(end_of(&f)),
            "log time: 8 bytes declared, 3 left in the record"
        );
    }

    /// A metadata record of 300,000 distinct keys (3.8 MB, well inside a record's limit) is
    /// read quickly: repeated keys are found with a set (comparing each key with every earlier
    /// one is 4.5·10^10 comparisons, minutes unoptimised; with the set, the crate's 13 tests
    /// take about 2 s); the same key twice is damage.
    #[test]
    fn a_map_of_many_keys_reads_and_a_repeated_key_is_damage() {
        let metadata = |keys: &[String]| {
            let map: Vec<u8> = keys
                .iter()
                .flat_map(|k| [string(k), string("")].concat())
                .collect();
            let body = [string("m"), (map.len() as u32).to_le_bytes().to_vec(), map].concat();
            [mcap::MAGIC.to_vec(), record(op::METADATA, &body)].concat()
        };
        let mut keys: Vec<String> = (0..300_000u32).map(|k| format!("{k:x}")).collect();
        let (s, sizes, _) = units(&metadata(&keys));
        assert_eq!(sizes, [1], "{s}");
        keys.push("2a".into());
        match end_of(&metadata(&keys)) {
            End::Damaged { why, .. } => assert_eq!(why, "metadata: key \"2a\" twice"),
            other => panic!("{other}"),
        }
    }

    /// A chunk may define every channel id there is (65,535 channels) and hold 400,000 messages
    /// on the last one: each message's channel is looked up among the chunk's new ids by key,
    /// not by a search through them (4·10^5 × 6.5·10^4 comparisons before: 14 s in an
    /// optimised build, minutes for a file of such chunks); it reads, and a message on a
    /// channel the chunk never defined is damage.
    #[test]
    fn a_chunk_defining_every_channel_id_reads_and_its_messages_are_checked() {
        let channel = |id: u16| {
            let body = [
                id.to_le_bytes().to_vec(),
                0u16.to_le_bytes().to_vec(),
                string("t"),
                string(""),
                0u32.to_le_bytes().to_vec(),
            ]
            .concat();
            record(op::CHANNEL, &body)
        };
        let message = |channel: u16| {
            let body = [channel.to_le_bytes().to_vec(), vec![0; 4 + 8 + 8]].concat();
            record(op::MESSAGE, &body)
        };
        let with_messages_on = |target: u16| {
            let mut data: Vec<u8> = (1..=u16::MAX).flat_map(channel).collect();
            data.extend((0..400_000).flat_map(|_| message(target)));
            [mcap::MAGIC.to_vec(), chunk(data.len() as u64, 0, "", &data)].concat()
        };
        let (s, sizes, _) = units(&with_messages_on(u16::MAX));
        assert_eq!(sizes, [u16::MAX as usize + 400_000], "{s}");
        match end_of(&with_messages_on(0)) {
            End::Damaged { why, .. } => assert!(why.contains("channel 0 never defined"), "{why}"),
            other => panic!("{other}"),
        }
    }

    #[test]
    fn the_callback_can_end_the_scan() {
        let bytes = file(3, None);
        let mut n = 0;
        let r = scan(bytes.as_slice(), |records| {
            n += records.len();
            if n > 5 {
                Err(n)
            } else {
                Ok(())
            }
        });
        assert!(matches!(r, Err(k) if k > 5));
        assert_eq!(header(&bytes).map(|h| h.0), Some("test"));
        assert_eq!(header(b"\x89MCAP0\r\n\x02"), None);
    }
}
