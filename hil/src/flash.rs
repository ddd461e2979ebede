//! Emulated node flash: one small file per node holding its installed table.
//!
//! Contract: the file is `node<N>.flash` in the flash directory: the magic `EXOF`, format
//! version 1, the node id, a boot counter, the 24 table bytes of [`Table::to_bytes`], two
//! spare bytes, and a CRC-32 over everything before it (40 bytes in all, little-endian). Writes go to a temporary file that is
//! fsynced and renamed over the old one, so a crash leaves either the old or the new content,
//! never a mix. A file whose CRC or magic is wrong reads as corrupt and the node then holds no
//! table (as a real node with a blank sector would).

use exocal_dbc::table::crc32;
use exocal_dbc::transfer::{StorageError, TableStorage};
use exocal_dbc::{NodeId, Table};
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 4] = b"EXOF";
const VERSION: u8 = 1;
/// Size of a flash file.
pub const FILE_LEN: usize = 40;

/// The content of a flash file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FlashImage {
    /// Boots since flashing (wrapping).
    pub boot_count: u32,
    /// Installed table.
    pub table: Table,
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
    out[10..34].copy_from_slice(&image.table.to_bytes());
    // Two spare bytes before the CRC keep it 4-byte aligned for a real flash layout.
    let crc = crc32(&out[..FILE_LEN - 4]);
    out[FILE_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
    out
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
    let b: [u8; FILE_LEN] = bytes
        .as_slice()
        .try_into()
        .map_err(|_| corrupt("wrong length"))?;
    if &b[..4] != MAGIC || b[4] != VERSION {
        return Err(corrupt("bad magic or version"));
    }
    if b[5] != node.raw() {
        return Err(corrupt("written by another node"));
    }
    let crc = u32::from_le_bytes([b[36], b[37], b[38], b[39]]);
    if crc != crc32(&b[..FILE_LEN - 4]) {
        return Err(corrupt("CRC mismatch"));
    }
    let table = Table::from_bytes(b[10..34].try_into().expect("24 bytes"))
        .map_err(|_| corrupt("table out of range"))?;
    Ok(Some(FlashImage {
        boot_count: u32::from_le_bytes([b[6], b[7], b[8], b[9]]),
        table,
    }))
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
    fn store(&mut self, table: &Table) -> Result<(), StorageError> {
        if self.fail_writes {
            return Err(StorageError);
        }
        write(
            &self.dir,
            self.node,
            &FlashImage {
                boot_count: self.boot_count,
                table: *table,
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
        f.store(&t).unwrap();
        assert_eq!(
            read(&d, node).unwrap().map(|i| (i.boot_count, i.table)),
            Some((7, t))
        );
        f.fail_writes = true;
        assert_eq!(
            f.store(&Table::from_si(0.2, 0.2, 0.3, 0.4, 0.5, 0.6).unwrap()),
            Err(StorageError)
        );
        assert_eq!(read(&d, node).unwrap().map(|i| i.table), Some(t));
        let _ = std::fs::remove_dir_all(&d);
    }
}
