//! Why a saved-map file was refused.
use std::path::PathBuf;

/// A saved-map file that cannot be written or read; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum MapFileError {
    /// Reading or writing failed (missing file, permissions, full disk).
    #[error("map file {path}: {what}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What was being done.
        what: &'static str,
        /// The system's error.
        source: std::io::Error,
    },
    /// The file does not start with the magic bytes: not a shoal map.
    #[error("map file {path}: not a shoal map file (no {magic:?} magic at its start)")]
    NotAMap {
        /// The file.
        path: PathBuf,
        /// The expected magic, as text.
        magic: String,
    },
    /// The file is of another format version.
    #[error("map file {path}: format version {found} (written by shoal {writer}), this shoal reads version {expected} only")]
    Version {
        /// The file.
        path: PathBuf,
        /// Version in the file.
        found: u32,
        /// Version this build reads.
        expected: u32,
        /// The shoal version that wrote it, when the header is readable ("unknown" else).
        writer: String,
    },
    /// The file is shorter than its header says (an interrupted copy or write).
    #[error("map file {path}: truncated: {found} bytes, its header says {expected}")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Bytes the header announces (header and payload).
        expected: u64,
        /// Bytes present.
        found: u64,
    },
    /// The file is longer than its header says.
    #[error("map file {path}: {extra} bytes after the payload its header announces")]
    TrailingBytes {
        /// The file.
        path: PathBuf,
        /// Bytes past the end.
        extra: u64,
    },
    /// The file's CRC-32 differs from the header's: the file is corrupted.
    #[error("map file {path}: corrupted: checksum {found:#010x}, header says {expected:#010x}")]
    Checksum {
        /// The file.
        path: PathBuf,
        /// CRC in the header.
        expected: u32,
        /// CRC of the payload read.
        found: u32,
    },
    /// The header is malformed (a shoal version string that is not UTF-8 or too long).
    #[error("map file {path}: malformed header: {detail}")]
    Header {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// The maps could not be encoded (a writer's bug: every saved type encodes).
    #[error("map file {path}: the maps do not encode: {detail}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's message.
        detail: String,
    },
    /// The payload passed the checksum but does not decode as maps.
    #[error("map file {path}: payload does not decode: {detail}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// The decoder's message.
        detail: String,
    },
    /// The payload decodes but is inconsistent ([`crate::MapFile::validate`]).
    #[error("map file {path}: inconsistent maps: {detail}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is inconsistent.
        detail: String,
    },
}
