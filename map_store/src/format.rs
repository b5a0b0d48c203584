//! The file layout, its atomic write and its checked read.
//!
//! | bytes | field |
//! |---|---|
//! | 0..8 | magic `SHOALMAP` |
//! | 8..12 | format version, `u32` little-endian ([`FORMAT_VERSION`]) |
//! | 12..16 | vocabulary identity ([`crate::vocabulary_id`]) of the BoW vectors |
//! | 16..24 | payload length in bytes, `u64` LE |
//! | 24..28 | CRC-32 (IEEE) of every other byte of the file (header and payload), `u32` LE |
//! | 28..30 | length `n` of the shoal version string, `u16` LE |
//! | 30..30+n | the shoal version that wrote the file (UTF-8) |
//! | then | the payload: a [`MapFile`] encoded with postcard 1.x |
//!
//! The version comes right after the magic and is checked before anything else, so that
//! a later version may change everything after it.
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::{MapFile, MapFileError};

/// The magic bytes a map file starts with.
pub const MAGIC: [u8; 8] = *b"SHOALMAP";

/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;

/// Bytes of the header before the version string.
const FIXED_LEN: usize = 30;

/// What the header says about a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    /// Format version.
    pub format_version: u32,
    /// Identity of the vocabulary of the stored BoW vectors.
    pub vocabulary_id: u32,
    /// Payload bytes.
    pub payload_len: u64,
    /// CRC-32 of the file but this field.
    pub crc: u32,
    /// Version of the shoal that wrote it.
    pub shoal_version: String,
}

impl Header {
    /// Bytes of the whole header (where the payload starts).
    pub fn byte_len(&self) -> usize {
        FIXED_LEN + self.shoal_version.len()
    }
}

/// The bytes of a map file holding `file`, its BoW vectors made with vocabulary
/// `vocabulary_id`, written by shoal `shoal_version`.
pub fn encode(
    file: &MapFile,
    vocabulary_id: u32,
    shoal_version: &str,
) -> Result<Vec<u8>, postcard::Error> {
    let payload = postcard::to_stdvec(file)?;
    Ok(with_header(&payload, vocabulary_id, shoal_version))
}

/// The header (module docs) and `payload`.
pub(crate) fn with_header(payload: &[u8], vocabulary_id: u32, shoal_version: &str) -> Vec<u8> {
    let version = &shoal_version.as_bytes()[..shoal_version.len().min(u16::MAX as usize)];
    let mut out = Vec::with_capacity(FIXED_LEN + version.len() + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&vocabulary_id.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(&(version.len() as u16).to_le_bytes());
    out.extend_from_slice(version);
    out.extend_from_slice(payload);
    let crc = file_crc(&out);
    out[24..28].copy_from_slice(&crc.to_le_bytes());
    out
}

/// Writes `file` to `path` atomically: a temporary file in the same folder, written and
/// fsynced, renamed over `path`, the folder fsynced. On any failure the temporary file is
/// removed and `path` is left as it was. Returns the bytes written.
pub fn write(
    path: &Path,
    file: &MapFile,
    vocabulary_id: u32,
    shoal_version: &str,
) -> Result<u64, MapFileError> {
    let bytes = encode(file, vocabulary_id, shoal_version).map_err(|e| MapFileError::Encode {
        path: path.to_path_buf(),
        detail: e.to_string(),
    })?;
    write_atomic(path, &bytes)?;
    Ok(bytes.len() as u64)
}

/// `bytes` to `path` through a temporary file in the same folder (see [`write`]).
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), MapFileError> {
    let io = |what, source| MapFileError::Io {
        path: path.to_path_buf(),
        what,
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map_or_else(|| "map".into(), |n| n.to_string_lossy().into_owned());
    let tmp = dir.join(format!(".{name}.tmp.{}", std::process::id()));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp).map_err(|e| io("creating a temporary file", e))?;
        f.write_all(bytes).map_err(|e| io("writing", e))?;
        f.sync_all().map_err(|e| io("syncing", e))?;
        std::fs::rename(&tmp, path).map_err(|e| io("renaming the temporary file", e))
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
        return result;
    }
    // The rename is durable once the folder is synced (best effort: not every file system
    // lets a folder be opened for it).
    if let Ok(d) = std::fs::File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Reads, checks and decodes the map file at `path` (module docs for the order of checks).
pub fn read(path: &Path) -> Result<(Header, MapFile), MapFileError> {
    let bytes = std::fs::read(path).map_err(|source| MapFileError::Io {
        path: path.to_path_buf(),
        what: "reading",
        source,
    })?;
    read_bytes(&bytes, path)
}

/// Checks and decodes the bytes of a map file (`path` names it in errors).
pub fn read_bytes(bytes: &[u8], path: &Path) -> Result<(Header, MapFile), MapFileError> {
    let header = read_header(bytes, path)?;
    let payload = &bytes[header.byte_len()..];
    let decode = |detail: String| MapFileError::Decode {
        path: path.to_path_buf(),
        detail,
    };
    let (file, rest): (MapFile, _) =
        postcard::take_from_bytes(payload).map_err(|e| decode(e.to_string()))?;
    if !rest.is_empty() {
        // A payload of another layout under the same version (or a writer's bug).
        return Err(decode(format!("{} bytes left after the maps", rest.len())));
    }
    file.validate().map_err(|detail| MapFileError::Invalid {
        path: path.to_path_buf(),
        detail,
    })?;
    Ok((header, file))
}

/// CRC-32 of a whole file but its CRC field (bytes 24..28).
fn file_crc(bytes: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[..24]);
    h.update(&bytes[28..]);
    h.finalize()
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    let mut a = [0; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

/// The header of `bytes` after the checks of magic, version, length and checksum.
pub fn read_header(bytes: &[u8], path: &Path) -> Result<Header, MapFileError> {
    let path = path.to_path_buf();
    let truncated = |expected: u64| MapFileError::Truncated {
        path: path.clone(),
        expected,
        found: bytes.len() as u64,
    };
    if bytes.len() < MAGIC.len() || bytes[..MAGIC.len()] != MAGIC {
        return Err(MapFileError::NotAMap {
            path,
            magic: String::from_utf8_lossy(&MAGIC).into_owned(),
        });
    }
    if bytes.len() < 12 {
        return Err(truncated(FIXED_LEN as u64));
    }
    let format_version = u32_at(bytes, 8);
    let writer = || {
        let n = bytes
            .get(28..30)
            .map(|b| u16::from_le_bytes([b[0], b[1]]) as usize)?;
        let s = bytes.get(FIXED_LEN..FIXED_LEN + n)?;
        std::str::from_utf8(s).ok().map(str::to_owned)
    };
    if format_version != FORMAT_VERSION {
        return Err(MapFileError::Version {
            path,
            found: format_version,
            expected: FORMAT_VERSION,
            writer: writer().unwrap_or_else(|| "unknown".into()),
        });
    }
    if bytes.len() < FIXED_LEN {
        return Err(truncated(FIXED_LEN as u64));
    }
    let mut len8 = [0; 8];
    len8.copy_from_slice(&bytes[16..24]);
    let payload_len = u64::from_le_bytes(len8);
    let version_len = u16::from_le_bytes([bytes[28], bytes[29]]) as usize;
    let header_len = (FIXED_LEN + version_len) as u64;
    let expected = header_len.saturating_add(payload_len);
    let found = bytes.len() as u64;
    if found < expected {
        return Err(truncated(expected));
    }
    if found > expected {
        return Err(MapFileError::TrailingBytes {
            path,
            extra: found - expected,
        });
    }
    let (crc_header, crc_payload) = (u32_at(bytes, 24), file_crc(bytes));
    if crc_header != crc_payload {
        return Err(MapFileError::Checksum {
            path,
            expected: crc_header,
            found: crc_payload,
        });
    }
    let shoal_version = writer().ok_or_else(|| MapFileError::Header {
        path: path.clone(),
        detail: "the shoal version string is not UTF-8".into(),
    })?;
    Ok(Header {
        format_version,
        vocabulary_id: u32_at(bytes, 12),
        payload_len,
        crc: crc_header,
        shoal_version,
    })
}
