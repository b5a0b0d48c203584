//! The kinds of error a service or the launcher counts: one list of their names, which are
//! the `kind` of an [`crate::ErrorRecord`], the keys of a status file's `error_counts` and
//! the `kind` part of report.json's `error_counts` keys (`service/kind`).
use std::fmt;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

macro_rules! error_kinds {
    ($($(#[doc = $doc:literal])* $variant:ident = $name:literal,)*) => {
        /// What went wrong, by kind (its name in files: [`ErrorKind::as_str`]).
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum ErrorKind {
            $($(#[doc = $doc])* $variant,)*
        }

        impl ErrorKind {
            /// Every kind.
            pub const ALL: &'static [ErrorKind] = &[$(ErrorKind::$variant,)*];

            /// The kind's name in status files and report.json.
            pub fn as_str(self) -> &'static str {
                match self {
                    $(ErrorKind::$variant => $name,)*
                }
            }
        }
    };
}

error_kinds! {
    // Bad input (the dataset readers' skipped lines and files, the camera ingest's images).
    /// An image that does not decode (camera ingest).
    CorruptImage = "corrupt_image",
    /// A line of a dataset file that does not parse (e.g. a truncated IMU line).
    MalformedLine = "malformed_line",
    /// A timestamp not after the previous one (dataset file, or an IMU sample at the tracker).
    NonMonotonic = "non_monotonic",
    /// An image a dataset's index names that does not exist.
    MissingImage = "missing_image",
    /// A file the dataset layout has but this dataset lacks (e.g. no IMU data).
    MissingFile = "missing_file",
    /// A pose without a valid time (KITTI).
    MissingTime = "missing_time",
    /// Times and poses of different counts (KITTI).
    LengthMismatch = "length_mismatch",
    /// A recorded message (MCAP / ROS 2 bag) that does not decode or has an unknown
    /// encoding: skipped.
    BadMessage = "bad_message",
    /// A recording cut short or with a damaged chunk: the rest of it is used.
    TruncatedFile = "truncated_file",
    // Messages.
    /// A message of another schema version (a foreign publisher on the same services).
    SchemaVersion = "schema_version",
    /// A frame whose payload does not match its header (tracker).
    BadFrame = "bad_frame",
    /// A keyframe message that does not convert (mapper, loop closer).
    BadKeyframe = "bad_keyframe",
    /// A correction message that does not decode (mapper).
    BadCorrection = "bad_correction",
    /// A keyframe message's IMU segment that does not hold (times, values, borders, record
    /// count): the keyframe is used without it, visual-only (mapper, issue 19).
    BadImuSegment = "bad_imu_segment",
    /// An IMU segment longer than `shm_schema::topics::MAX_IMU_RECORDS`, cut to that many
    /// samples in its keyframe message (tracker, issue 19).
    ImuSegmentCut = "imu_segment_cut",
    // The services' own work.
    /// Lock-step: no consumer acknowledged a frame in time (camera ingest).
    AckTimeout = "ack_timeout",
    /// The tracker's visual odometry failed on a frame.
    Vo = "vo",
    /// The calibration filter refused a frame (tracker, `calib` mode).
    Calib = "calib",
    /// IMU samples missing over a stretch longer than the visual-inertial client bridges
    /// (tracker): it tracks monocularly over it.
    ImuGap = "imu_gap",
    /// An IMU sample with a non-finite or saturated value (tracker): not used.
    ImuSaturated = "imu_saturated",
    /// An IMU calibration (`imu0/sensor.yaml`, `[tracker.imu]`) that does not read or holds
    /// impossible values: the defaults are used, or the client runs monocular.
    ImuCalibration = "imu_calibration",
    /// The tracker's keyframe spool could not be written or read.
    Spool = "spool",
    /// A visual-inertial tracker's successor could not resume its killed predecessor's
    /// session from the keyframe spool (the reason named): it sent the spooled keyframes
    /// and started a new session.
    VioResume = "vio_resume",
    /// A mapper handler refused a keyframe, or its thread panicked.
    Handler = "handler",
    /// The mapper journal is damaged or holds what cannot be replayed.
    Journal = "journal",
    /// A saved-map file could not be read or written (`--load-map`, `--save-map`).
    MapFile = "map_file",
    /// A correction that could not be applied (mapper) or sent (loop closer).
    Correction = "correction",
    /// A loop the loop closer found and could not verify or optimise.
    Loop = "loop",
    /// A message from a remote host that does not decode, or a client the server refused
    /// (bridge, issue 22).
    Remote = "remote",
    /// The crash-recovery state a killed predecessor left is of another format or
    /// unreadable: the service started afresh ([`crate::Status::take_resume`]).
    ResumeState = "resume_state",
    // The launcher's (service `launcher`).
    /// A `--kill` or `--chaos` that killed nothing.
    KillUnfired = "kill_unfired",
    /// A dataset that could not be opened.
    Dataset = "dataset",
    /// `--max-seconds` stopped the run.
    Timeout = "timeout",
    /// A service exited with a configuration error (not restarted).
    Config = "config",
    /// A service that kept crashing: the launcher stopped restarting it.
    GaveUp = "gave_up",
}

impl From<datasets::IssueKind> for ErrorKind {
    fn from(k: datasets::IssueKind) -> Self {
        use datasets::IssueKind as I;
        match k {
            I::MalformedLine => Self::MalformedLine,
            I::NonMonotonic => Self::NonMonotonic,
            I::MissingImage => Self::MissingImage,
            I::MissingFile => Self::MissingFile,
            I::MissingTime => Self::MissingTime,
            I::LengthMismatch => Self::LengthMismatch,
            I::BadMessage => Self::BadMessage,
            I::TruncatedFile => Self::TruncatedFile,
        }
    }
}

impl fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ErrorKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .iter()
            .copied()
            .find(|k| k.as_str() == s)
            .ok_or_else(|| format!("unknown error kind '{s}'"))
    }
}

/// By name, so that a status file's `error_counts` stay in alphabetical order.
impl Ord for ErrorKind {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.as_str().cmp(other.as_str())
    }
}

impl PartialOrd for ErrorKind {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Serialize for ErrorKind {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for ErrorKind {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = std::borrow::Cow::<'de, str>::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The names are distinct, round-trip through serde and parse back.
    #[test]
    fn names_are_distinct_and_round_trip() {
        let mut names: Vec<&str> = ErrorKind::ALL.iter().map(|k| k.as_str()).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), ErrorKind::ALL.len());
        for &k in ErrorKind::ALL {
            let json = serde_json::to_string(&k).unwrap();
            assert_eq!(json, format!("\"{k}\""));
            assert_eq!(serde_json::from_str::<ErrorKind>(&json).unwrap(), k);
        }
        let counts = std::collections::BTreeMap::from([(ErrorKind::Vo, 1), (ErrorKind::Spool, 2)]);
        let json = serde_json::to_string(&counts).unwrap();
        assert_eq!(json, r#"{"spool":2,"vo":1}"#);
        assert!(serde_json::from_str::<ErrorKind>("\"kill_skipped\"").is_err());
    }

    /// Every reader problem has an error kind of the same name.
    #[test]
    fn dataset_issue_kinds_keep_their_names() {
        for &i in datasets::IssueKind::ALL {
            assert_eq!(ErrorKind::from(i).as_str(), i.as_str());
        }
    }
}
