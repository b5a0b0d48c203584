//! The one error type of `slam_core`.

/// Errors of the pure algorithms.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// Not enough data (points, poses, matches) for the requested estimate.
    #[error("not enough data: {0}")]
    NotEnoughData(String),
    /// A numerical method did not converge or met a degenerate configuration.
    #[error("degenerate or non-convergent: {0}")]
    Degenerate(String),
    /// An argument is outside its valid domain.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// A text input (e.g. a g2o pose-graph file) has a malformed line (1-based number).
    #[error("line {line}: {msg}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        msg: String,
    },
    /// A session cannot be resumed from what was stored of it (e.g. a killed tracker's
    /// keyframe spool, [`crate::vo::resume`]): why.
    #[error("cannot resume the session: {0}")]
    Resume(String),
    /// A binary input (e.g. a vocabulary file) is malformed.
    #[error("malformed data: {0}")]
    Format(String),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
}
