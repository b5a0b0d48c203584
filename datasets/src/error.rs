//! The one error type of `datasets`.
use std::path::PathBuf;

/// Errors while opening or reading a dataset. Every variant names the file (and the line
/// where there is one), so a user can find the bad input.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// The dataset folder or a required file does not exist.
    #[error("{path}: not found ({what})")]
    NotFound {
        /// The missing path.
        path: PathBuf,
        /// What was expected there.
        what: String,
    },
    /// The folder matches no known dataset format.
    #[error("{path}: unknown dataset format ({detail})")]
    UnknownFormat {
        /// The folder.
        path: PathBuf,
        /// What was looked for.
        detail: String,
    },
    /// A file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The IO error.
        #[source]
        source: std::io::Error,
    },
    /// A line of a text file could not be parsed. Line numbers are 1-based (0: the file as
    /// a whole, shown without a line).
    #[error("{}{}: {detail}", path.display(), at_line(*line))]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number (0 when the error is not tied to a line).
        line: usize,
        /// What is wrong.
        detail: String,
    },
    /// An image could not be decoded, or has an unexpected size or format.
    #[error("{path}: bad image: {detail}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
    },
    /// Parameters of a generator or tool are invalid (e.g. a zero image size for the simulator).
    #[error("invalid configuration: {detail}")]
    InvalidConfig {
        /// What is wrong.
        detail: String,
    },
}

/// `:line` for a 1-based line, nothing for 0 (not tied to a line).
fn at_line(line: usize) -> String {
    if line == 0 {
        String::new()
    } else {
        format!(":{line}")
    }
}
