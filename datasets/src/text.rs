//! Private helpers for the lenient text readers: file reading with clear errors, line
//! splitting, number parsing and the monotonic-timestamp guard.

use std::path::Path;

use crate::{DatasetError, InputIssue, IssueKind};

/// Reads a whole text file; a missing file is [`DatasetError::NotFound`] with `what`.
pub(crate) fn read_text(path: &Path, what: &str) -> Result<String, DatasetError> {
    match std::fs::read(path) {
        // Lossy: a stray non-UTF-8 byte only spoils its own line, which is then skipped.
        Ok(bytes) => Ok(String::from_utf8_lossy(&bytes).into_owned()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(DatasetError::NotFound {
            path: path.to_path_buf(),
            what: what.to_string(),
        }),
        Err(source) => Err(DatasetError::Io {
            path: path.to_path_buf(),
            source,
        }),
    }
}

/// An [`InputIssue`].
pub(crate) fn issue(
    path: &Path,
    line: usize,
    kind: IssueKind,
    detail: impl Into<String>,
) -> InputIssue {
    InputIssue {
        path: path.to_path_buf(),
        line,
        kind,
        detail: detail.into(),
    }
}

/// Non-empty, non-comment (`#`) lines with their 1-based line numbers, trimmed.
pub(crate) fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Splits a CSV line on commas (trimmed fields) or a whitespace-separated line.
pub(crate) fn fields(line: &str, comma: bool) -> Vec<&str> {
    if comma {
        line.split(',').map(str::trim).collect()
    } else {
        line.split_whitespace().collect()
    }
}

/// Parses finite floats; `None` if any field is not a finite number.
pub(crate) fn parse_f64s(fields: &[&str]) -> Option<Vec<f64>> {
    fields
        .iter()
        .map(|f| f.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect()
}

/// Parses an integer; also accepts an integral float text like `1.0e7` (exactly integral).
pub(crate) fn parse_i64(s: &str) -> Option<i64> {
    let s = s.trim();
    s.parse::<i64>().ok().or_else(|| {
        let v = s.parse::<f64>().ok()?;
        (v.is_finite() && v.fract() == 0.0 && v.abs() < 9.0e18).then_some(v as i64)
    })
}

/// True when the first field of `line` is not a number: a header row.
pub(crate) fn is_header(line: &str) -> bool {
    let first = line.split([',', ' ', '\t']).next().unwrap_or("").trim();
    first.parse::<f64>().is_err()
}

/// Rejects timestamps that are not strictly increasing, recording a `non_monotonic` issue.
#[derive(Default)]
pub(crate) struct Monotonic {
    last: Option<i64>,
}

impl Monotonic {
    /// True when `t` is after every accepted stamp; otherwise records the issue.
    pub(crate) fn accept(
        &mut self,
        t: i64,
        path: &Path,
        line: usize,
        issues: &mut Vec<InputIssue>,
    ) -> bool {
        if let Some(last) = self.last {
            if t <= last {
                let what = if t == last { "duplicate" } else { "earlier" };
                issues.push(issue(
                    path,
                    line,
                    IssueKind::NonMonotonic,
                    format!(
                        "timestamp {t} is {what} than the previous accepted {last}; line skipped"
                    ),
                ));
                return false;
            }
        }
        self.last = Some(t);
        true
    }
}
