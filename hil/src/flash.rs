//! Emulated node flash: one small file per node holding its installed table, and a key slot.
//!
//! Contract: the table file is `node<N>.flash` in the flash directory, little-endian:
//!
//! | bytes | format 2 (written) | format 1 (still read) |
//! |---|---|---|
//! | 0..4 | magic `EXOF` | magic `EXOF` |
//! | 4 | version 2 | version 1 |
//! | 5 | node id | node id |
//! | 6..10 | boot counter | boot counter |
//! | 10..14 | freshness counter of the table | the 24 table bytes ([`Table::to_bytes`]) … |
//! | 14..38 | the 24 table bytes | … then two spare bytes (34..36) |
//! | 38..40 | two spare bytes | CRC-32 of bytes 0..36 (36..40) |
//! | 40..44 | CRC-32 of bytes 0..40 | |
//!
//! so the table and the counter that authorised it change in one write (a format-1 image reads
//! with counter 0). Writes go to a temporary file that is fsynced and renamed over the old one,
//! so a crash leaves either the old or the new content, never a mix. A file whose CRC, magic or
//! length is wrong reads as corrupt and the node then holds no table (as a real node with a
//! blank sector would).
//!
//! The key slot is `node<N>.key`: the node's 16-byte AES-128 key, raw, mode 0600, written by
//! provisioning ([`provision`], `exocal-hil --keys`), never over CAN.
//!
//! The counter record is `node<N>.ctr`, kept apart from the table image so that a corrupt or
//! lost image never takes the freshness counter back (a recorded transfer would then install
//! again): magic `EXOC`, version 1, node id, two spare bytes, the counter (u32), CRC-32 of bytes
//! 0..12 — 16 bytes, written (fsync, rename) before the table image at every commit
//! ([`NodeFlash`]'s [`TableStorage::store_counter`]), created by [`provision`]. A node boots
//! with its key only if it reads both its key slot and its counter record, its counter the
//! higher of the record and the image's ([`Provisioning::boot`]); a node that has either but
//! cannot read both boots without a key and installs nothing until it is provisioned again (fail
//! closed), and so does a node that was never provisioned. Provisioning again never takes a
//! counter back: over a record that does not read, it keys only a node given a new key
//! ([`provision`], [`Provisioned::locked`]).

use exocal_dbc::auth::{Key, KeySet, KEY_LEN};
use exocal_dbc::table::crc32;
use exocal_dbc::transfer::{NodeTransfer, StorageError, TableStorage};
use exocal_dbc::{NodeId, Table};
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 4] = b"EXOF";
const VERSION: u8 = 2;
/// Size of a flash file (format 2).
pub const FILE_LEN: usize = 44;
/// Size of a format-1 flash file.
const V1_LEN: usize = 40;
const COUNTER_MAGIC: &[u8; 4] = b"EXOC";
/// Size of a counter record.
pub const COUNTER_LEN: usize = 16;

/// The content of a flash file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FlashImage {
    /// Boots since flashing (wrapping).
    pub boot_count: u32,
    /// Installed table.
    pub table: Table,
    /// The freshness counter the table was committed with (0 for a factory table or a
    /// format-1 image).
    pub counter: u32,
}

/// Why a flash file could not be read.
#[derive(Debug)]
pub enum FlashError {
    /// I/O error.
    Io(PathBuf, std::io::Error),
    /// Wrong length, magic, version, node or CRC.
    Corrupt(PathBuf, &'static str),
}

impl std::fmt::Display for FlashError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FlashError::Io(p, e) => write!(f, "flash {}: {e}", p.display()),
            FlashError::Corrupt(p, why) => write!(f, "flash {} is corrupt: {why}", p.display()),
        }
    }
}

impl std::error::Error for FlashError {}

/// The flash file path of `node` in `dir`.
pub fn path(dir: &Path, node: NodeId) -> PathBuf {
    dir.join(format!("node{}.flash", node.raw()))
}

fn encode(node: NodeId, image: &FlashImage) -> [u8; FILE_LEN] {
    let mut out = [0u8; FILE_LEN];
    out[..4].copy_from_slice(MAGIC);
    out[4] = VERSION;
    out[5] = node.raw();
    out[6..10].copy_from_slice(&image.boot_count.to_le_bytes());
    out[10..14].copy_from_slice(&image.counter.to_le_bytes());
    out[14..38].copy_from_slice(&image.table.to_bytes());
    // Two spare bytes before the CRC keep it 4-byte aligned for a real flash layout.
    let crc = crc32(&out[..FILE_LEN - 4]);
    out[FILE_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
    out
}

fn le32(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// Reads a node's flash file: `Ok(None)` if it does not exist.
pub fn read(dir: &Path, node: NodeId) -> Result<Option<FlashImage>, FlashError> {
    let p = path(dir, node);
    let bytes = match std::fs::read(&p) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(FlashError::Io(p, e)),
    };
    let corrupt = |why| FlashError::Corrupt(p.clone(), why);
    let b = bytes.as_slice();
    // (length, where the table starts, where the counter is) of each format.
    let (len, table_at, counter_at) = match b.get(4) {
        Some(1) => (V1_LEN, 10, None),
        Some(2) => (FILE_LEN, 14, Some(10)),
        _ => return Err(corrupt("bad magic or version")),
    };
    if b.len() != len {
        return Err(corrupt("wrong length"));
    }
    if &b[..4] != MAGIC {
        return Err(corrupt("bad magic or version"));
    }
    if b[5] != node.raw() {
        return Err(corrupt("written by another node"));
    }
    if le32(&b[len - 4..]) != crc32(&b[..len - 4]) {
        return Err(corrupt("CRC mismatch"));
    }
    let table = Table::from_bytes(b[table_at..table_at + 24].try_into().expect("24 bytes"))
        .map_err(|_| corrupt("table out of range"))?;
    Ok(Some(FlashImage {
        boot_count: le32(&b[6..10]),
        table,
        counter: counter_at.map_or(0, |at| le32(&b[at..at + 4])),
    }))
}

/// The key slot path of `node` in `dir`.
pub fn key_path(dir: &Path, node: NodeId) -> PathBuf {
    dir.join(format!("node{}.key", node.raw()))
}

/// Reads a node's key slot: `Ok(None)` if it is empty (no file).
pub fn read_key(dir: &Path, node: NodeId) -> Result<Option<Key>, FlashError> {
    let p = key_path(dir, node);
    match std::fs::read(&p) {
        Ok(b) => <[u8; KEY_LEN]>::try_from(b.as_slice())
            .map(|k| Some(Key::new(k)))
            .map_err(|_| FlashError::Corrupt(p, "a key slot holds 16 bytes")),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(FlashError::Io(p, e)),
    }
}

/// Writes a node's key slot (mode 0600, atomically).
pub fn write_key(dir: &Path, node: NodeId, key: &Key) -> std::io::Result<()> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::create_dir_all(dir)?;
    let p = key_path(dir, node);
    let tmp = p.with_extension("key.tmp");
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(&tmp)?;
    f.write_all(key.bytes())?;
    f.sync_all()?;
    std::fs::rename(&tmp, &p)
}

/// What [`provision`] did: the nodes it keyed, and those it left locked.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Provisioned {
    /// Nodes whose key slot and counter record it wrote.
    pub keyed: Vec<NodeId>,
    /// Nodes left as they were, locked (they boot keyless and install nothing): their counter
    /// record does not read while their key slot holds the key given (or does not read either),
    /// and a counter started again under the same key would let every recorded `CommitAuth`
    /// install again. Provision them with a new key. With why.
    pub locked: Vec<(NodeId, String)>,
}

/// Provisions the key slot and the counter record of every joint node `keys` has a key for (a
/// factory step: the nodes read both at boot). The counter never goes down: it keeps the
/// highest of what its record held and the table image's counter that still reads. Where the
/// record is missing or corrupt, only a node never provisioned (no key slot, no record) or
/// given a key other than the one its slot holds is keyed again (an old `CommitAuth` does not
/// verify under a new key); any other node stays locked ([`Provisioned::locked`]): fail closed.
pub fn provision(dir: &Path, keys: &KeySet) -> std::io::Result<Provisioned> {
    let mut done = Provisioned::default();
    for node in NodeId::ALL {
        let Some(key) = keys.node(node) else { continue };
        let image = read(dir, node).ok().flatten().map_or(0, |i| i.counter);
        let counter = match (read_key(dir, node), read_counter(dir, node)) {
            (_, Ok(Some(record))) => Ok(record.max(image)),
            (Ok(None), Ok(None)) => Ok(image),
            (Ok(Some(old)), _) if old.bytes() != key.bytes() => Ok(image),
            (Ok(Some(_)), Ok(None)) => Err("its counter record is missing".to_string()),
            (_, Err(e)) => Err(e.to_string()),
            (Err(e), Ok(None)) => Err(e.to_string()),
        };
        match counter {
            Ok(counter) => {
                write_key(dir, node, key)?;
                write_counter(dir, node, counter)?;
                done.keyed.push(node);
            }
            Err(why) => done.locked.push((node, why)),
        }
    }
    Ok(done)
}

/// The counter record path of `node` in `dir`.
pub fn counter_path(dir: &Path, node: NodeId) -> PathBuf {
    dir.join(format!("node{}.ctr", node.raw()))
}

/// Reads a node's counter record: `Ok(None)` if there is none.
pub fn read_counter(dir: &Path, node: NodeId) -> Result<Option<u32>, FlashError> {
    let p = counter_path(dir, node);
    let b = match std::fs::read(&p) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(FlashError::Io(p, e)),
    };
    let corrupt = |why| Err(FlashError::Corrupt(p.clone(), why));
    if b.len() != COUNTER_LEN {
        return corrupt("wrong length");
    }
    if &b[..4] != COUNTER_MAGIC || b[4] != 1 {
        return corrupt("bad magic or version");
    }
    if b[5] != node.raw() {
        return corrupt("written by another node");
    }
    if le32(&b[12..]) != crc32(&b[..12]) {
        return corrupt("CRC mismatch");
    }
    Ok(Some(le32(&b[8..12])))
}

/// Writes a node's counter record atomically (temporary file, fsync, rename).
pub fn write_counter(dir: &Path, node: NodeId, counter: u32) -> std::io::Result<()> {
    let mut out = [0u8; COUNTER_LEN];
    out[..4].copy_from_slice(COUNTER_MAGIC);
    out[4] = 1;
    out[5] = node.raw();
    out[8..12].copy_from_slice(&counter.to_le_bytes());
    let crc = crc32(&out[..12]);
    out[12..].copy_from_slice(&crc.to_le_bytes());
    std::fs::create_dir_all(dir)?;
    let p = counter_path(dir, node);
    let tmp = p.with_extension("ctr.tmp");
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(&out)?;
    f.sync_all()?;
    std::fs::rename(&tmp, &p)
}

/// What a node finds at boot besides its table: its key slot and its counter record.
#[derive(Debug)]
pub struct Provisioning {
    /// The key slot (`Ok(None)`: empty).
    pub key: Result<Option<Key>, FlashError>,
    /// The counter record (`Ok(None)`: none).
    pub counter: Result<Option<u32>, FlashError>,
}

impl Provisioning {
    /// Reads `node`'s key slot and counter record in `dir`.
    pub fn read(dir: &Path, node: NodeId) -> Provisioning {
        Provisioning {
            key: read_key(dir, node),
            counter: read_counter(dir, node),
        }
    }

    /// Whether the node was ever provisioned (it has a key slot or a counter record, readable
    /// or not).
    pub fn provisioned(&self) -> bool {
        !matches!((&self.key, &self.counter), (Ok(None), Ok(None)))
    }

    /// The node's transfer state machine as it boots holding `image`: keyed with the higher of
    /// the record's and the image's counter if the key slot and the counter record both read,
    /// else without a key (it installs nothing: fail closed).
    pub fn boot(self, node: NodeId, image: Option<&FlashImage>) -> NodeTransfer {
        let transfer = NodeTransfer::new(node, image.map(|i| i.table));
        match (self.key, self.counter) {
            (Ok(Some(key)), Ok(Some(counter))) => {
                transfer.with_key(key, counter.max(image.map_or(0, |i| i.counter)))
            }
            _ => transfer,
        }
    }
}

/// Writes a node's flash file atomically.
pub fn write(dir: &Path, node: NodeId, image: &FlashImage) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let p = path(dir, node);
    let tmp = p.with_extension("flash.tmp");
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(&encode(node, image))?;
    f.sync_all()?;
    std::fs::rename(&tmp, &p)
}

/// A node's flash as the transfer state machine's [`TableStorage`].
#[derive(Debug)]
pub struct NodeFlash {
    dir: PathBuf,
    node: NodeId,
    boot_count: u32,
    /// Makes every write fail (fault injection).
    pub fail_writes: bool,
}

impl NodeFlash {
    /// Flash of `node` in `dir`.
    pub fn new(dir: &Path, node: NodeId, boot_count: u32) -> Self {
        NodeFlash {
            dir: dir.to_path_buf(),
            node,
            boot_count,
            fail_writes: false,
        }
    }
}

impl TableStorage for NodeFlash {
    fn store_counter(&mut self, counter: u32) -> Result<(), StorageError> {
        if self.fail_writes {
            return Err(StorageError);
        }
        write_counter(&self.dir, self.node, counter).map_err(|_| StorageError)
    }

    fn store(&mut self, table: &Table, counter: u32) -> Result<(), StorageError> {
        if self.fail_writes {
            return Err(StorageError);
        }
        write(
            &self.dir,
            self.node,
            &FlashImage {
                boot_count: self.boot_count,
                table: *table,
                counter,
            },
        )
        .map_err(|_| StorageError)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("exocal-hil-flash-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn round_trip_and_corruption_is_detected() {
        let d = dir("rt");
        let node = NodeId::JOINTS[1];
        assert!(read(&d, node).unwrap().is_none());
        let image = FlashImage {
            boot_count: 3,
            table: Table::from_si(0.04, 1.0, 0.0, 0.5, 1.0, 1.0).unwrap(),
            counter: 0x0102_0304,
        };
        write(&d, node, &image).unwrap();
        assert_eq!(read(&d, node).unwrap(), Some(image));
        let mut bytes = std::fs::read(path(&d, node)).unwrap();
        bytes[12] ^= 1;
        std::fs::write(path(&d, node), &bytes).unwrap();
        assert!(matches!(
            read(&d, node),
            Err(FlashError::Corrupt(_, "CRC mismatch"))
        ));
        std::fs::write(path(&d, node), &bytes[..10]).unwrap();
        assert!(matches!(
            read(&d, node),
            Err(FlashError::Corrupt(_, "wrong length"))
        ));
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn storage_writes_and_can_be_made_to_fail() {
        let d = dir("st");
        let node = NodeId::JOINTS[0];
        let t = Table::from_si(0.1, 0.2, 0.3, 0.4, 0.5, 0.6).unwrap();
        let mut f = NodeFlash::new(&d, node, 7);
        f.store(&t, 9).unwrap();
        assert_eq!(
            read(&d, node)
                .unwrap()
                .map(|i| (i.boot_count, i.table, i.counter)),
            Some((7, t, 9))
        );
        f.fail_writes = true;
        assert_eq!(
            f.store(&Table::from_si(0.2, 0.2, 0.3, 0.4, 0.5, 0.6).unwrap(), 10),
            Err(StorageError)
        );
        assert_eq!(read(&d, node).unwrap().map(|i| i.table), Some(t));
        let _ = std::fs::remove_dir_all(&d);
    }

    /// A format-1 image (as written before authentication) still reads, with counter 0; the
    /// next write is format 2.
    #[test]
    fn a_format_1_image_still_reads() {
        let d = dir("v1");
        let node = NodeId::JOINTS[4];
        let t = Table::from_si(0.04, 1.0, 0.0, 0.5, 1.0, 1.0).unwrap();
        let mut v1 = [0u8; V1_LEN];
        v1[..4].copy_from_slice(MAGIC);
        v1[4] = 1;
        v1[5] = node.raw();
        v1[6..10].copy_from_slice(&5u32.to_le_bytes());
        v1[10..34].copy_from_slice(&t.to_bytes());
        let crc = crc32(&v1[..V1_LEN - 4]);
        v1[V1_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(path(&d, node), v1).unwrap();
        let image = read(&d, node).unwrap().unwrap();
        assert_eq!((image.boot_count, image.table, image.counter), (5, t, 0));
        NodeFlash::new(&d, node, 6).store(&t, 1).unwrap();
        assert_eq!(std::fs::read(path(&d, node)).unwrap().len(), FILE_LEN);
        assert_eq!(read(&d, node).unwrap().unwrap().counter, 1);
        // A format-1 length with a format-2 version byte is corrupt.
        v1[4] = 2;
        std::fs::write(path(&d, node), v1).unwrap();
        assert!(matches!(
            read(&d, node),
            Err(FlashError::Corrupt(_, "wrong length"))
        ));
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn key_slots_are_provisioned_private_and_read_back() {
        use std::os::unix::fs::PermissionsExt;
        let d = dir("keys");
        let keys = KeySet::derived(11);
        assert_eq!(read_key(&d, NodeId::JOINTS[0]).unwrap(), None);
        assert_eq!(provision(&d, &keys).unwrap().keyed, NodeId::ALL.to_vec());
        for node in NodeId::ALL {
            assert_eq!(read_key(&d, node).unwrap().as_ref(), keys.node(node));
            let mode = std::fs::metadata(key_path(&d, node))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
        std::fs::write(key_path(&d, NodeId::JOINTS[1]), [0u8; 3]).unwrap();
        assert!(matches!(
            read_key(&d, NodeId::JOINTS[1]),
            Err(FlashError::Corrupt(..))
        ));
        let _ = std::fs::remove_dir_all(&d);
    }
    /// The counter record reads back, detects corruption, and provisioning creates it without
    /// ever lowering it (the table image's counter counts too).
    #[test]
    fn counter_records_round_trip_and_provisioning_never_lowers_them() {
        let d = dir("ctr");
        let node = NodeId::JOINTS[3];
        assert_eq!(read_counter(&d, node).unwrap(), None);
        write_counter(&d, node, 0x0102_0304).unwrap();
        assert_eq!(read_counter(&d, node).unwrap(), Some(0x0102_0304));
        let mut b = std::fs::read(counter_path(&d, node)).unwrap();
        b[8] ^= 1;
        std::fs::write(counter_path(&d, node), &b).unwrap();
        assert!(matches!(
            read_counter(&d, node),
            Err(FlashError::Corrupt(_, "CRC mismatch"))
        ));
        let keys = KeySet::derived(12);
        write_counter(&d, node, 40).unwrap();
        let t = Table::from_si(0.04, 1.0, 0.0, 0.5, 1.0, 1.0).unwrap();
        let image = |counter| FlashImage {
            boot_count: 1,
            table: t,
            counter,
        };
        write(&d, node, &image(55)).unwrap();
        provision(&d, &keys).unwrap();
        assert_eq!(read_counter(&d, node).unwrap(), Some(55));
        write(&d, node, &image(3)).unwrap();
        provision(&d, &keys).unwrap();
        assert_eq!(read_counter(&d, node).unwrap(), Some(55));
        assert_eq!(read_counter(&d, NodeId::JOINTS[0]).unwrap(), Some(0));
        // A provisioned node boots keyed with the higher counter; without its record, keyless.
        let booted = Provisioning::read(&d, node).boot(node, Some(&image(3)));
        assert!(booted.is_keyed());
        assert_eq!(booted.counter(), 55);
        std::fs::remove_file(counter_path(&d, node)).unwrap();
        let p = Provisioning::read(&d, node);
        assert!(p.provisioned());
        assert!(!p.boot(node, Some(&image(3))).is_keyed());
        let fresh = Provisioning::read(&d.join("none"), node);
        assert!(!fresh.provisioned());
        let _ = std::fs::remove_dir_all(&d);
    }
}
