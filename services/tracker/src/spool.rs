//! The tracker's keyframe spool (design: faults; issue 6, "lose no keyframe").
//!
//! A keyframe is sent to the mapper only when it leaves the client's VO window (seed §3.3:
//! the oldest of N keyframes), so a SIGKILLed tracker used to take up to N keyframes with it.
//! The spool keeps them on disk: every keyframe the VO creates is written to
//! `DIR/{session:08x}_{id:016x}.kf` (one [`shoal_runtime::journal`] entry, written to a
//! temporary file and renamed, so a kill leaves the whole file or none) and deleted when it
//! is sent (from then on the outbox and the mapper's acknowledgement take over). What is left
//! in the folder after a kill is exactly the dead process's window: its successor sends
//! those keyframes first, as keyframes of the dead session, so the mapper appends them to
//! that session's map, and only then starts its own session.
//!
//! Spooled keyframes carry the pose and map points they had when they were created (local
//! BA refines the window afterwards; that refinement dies with the process), and, in a
//! second entry of the file ([`Entry::MapPoints`]), the world positions of those points:
//! with them a visual-inertial successor rebuilds the dead process's client map and resumes
//! its session (`core/resume.rs`, issue 17). A file without that second entry is recovered
//! and sent, and its session is not resumed.
//!
//! A file starts with a header naming its version
//! ([`shoal_runtime::journal::spool_file_header`]); since issue 19 the keyframe entry carries
//! the IMU segment of the message, and a file of an older tracker (no header, or another
//! version) is refused with both versions named, deleted, and counted as a spool error.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use shm_schema::{ImuRecord, KeyframeHeader, KeypointRecord};
use shoal_runtime::journal::{encode_entry, parse_spool, spool_file_header, Entry, SpooledPoint};

use crate::outbox::KeyframeMsg;

/// A keyframe recovered from the spool.
pub struct Recovered {
    /// Message header (session and keyframe id of the dead process).
    pub header: KeyframeHeader,
    /// Keypoint records.
    pub records: Vec<KeypointRecord>,
    /// The IMU segment's records (empty for a monocular client).
    pub imu: Vec<ImuRecord>,
    /// Positions of the points it observed when spooled (`None`: a file of an older
    /// tracker, written without them).
    pub points: Option<Vec<SpooledPoint>>,
}

/// A keyframe to spool: its message as it would be sent now and the positions of the map
/// points it observes.
#[derive(Debug, Clone)]
pub struct SpoolEntry {
    /// The keyframe message.
    pub msg: KeyframeMsg,
    /// Id and world position of each map point the keyframe observes.
    pub points: Vec<SpooledPoint>,
}

/// What [`Spool::recover`] found.
#[derive(Default)]
pub struct Recovery {
    /// Keyframes in (session, id) order.
    pub keyframes: Vec<Recovered>,
    /// Files that could not be used (torn, corrupt, unreadable), with the reason.
    pub errors: Vec<String>,
}

/// Keyframes created and not yet sent, on disk.
pub struct Spool {
    dir: PathBuf,
    /// (session, id) of the files this process knows of.
    files: BTreeSet<(u32, u64)>,
    /// Those of keyframes sent and kept until acknowledged ([`Spool::sent_keep`]).
    sent_kept: BTreeSet<(u32, u64)>,
    /// A file stays until its keyframe is acknowledged, not only until it is sent
    /// (`tracker.spool_until_ack`, [`Spool::until_acked`]).
    until_ack: bool,
    /// Keyframes written.
    pub written: u64,
    /// Bytes written.
    pub bytes_written: u64,
}

impl Spool {
    /// Opens (creates) the spool folder.
    pub fn open(dir: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            files: BTreeSet::new(),
            sent_kept: BTreeSet::new(),
            until_ack: false,
            written: 0,
            bytes_written: 0,
        })
    }

    /// Keeps each file until its keyframe is acknowledged ([`Spool::acked`]), at most
    /// [`crate::config::SPOOL_MAX_FILES`] of them (`tracker.spool_until_ack`).
    pub fn until_acked(mut self) -> Self {
        self.until_ack = true;
        self
    }

    fn path(&self, session: u32, id: u64) -> PathBuf {
        self.dir.join(format!("{session:08x}_{id:016x}.kf"))
    }

    /// Reads every spooled keyframe left by earlier processes. Unusable files are reported
    /// and deleted; the usable ones stay until [`Spool::sent`] is called for them.
    pub fn recover(&mut self, client: u32) -> Recovery {
        let mut out = Recovery::default();
        let entries = match std::fs::read_dir(&self.dir) {
            Ok(e) => e,
            Err(e) => {
                out.errors
                    .push(format!("spool {}: {e}", self.dir.display()));
                return out;
            }
        };
        let mut names: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
        names.sort();
        for path in names {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
            let Some(name) = name else { continue };
            if !name.ends_with(".kf") {
                // A temporary file of a write cut short by the kill.
                let _ = std::fs::remove_file(&path);
                continue;
            }
            let bytes = match std::fs::read(&path) {
                Ok(b) => b,
                Err(e) => {
                    out.errors
                        .push(format!("spool file {}: {e}", path.display()));
                    continue;
                }
            };
            let contents = match parse_spool(&path, &bytes) {
                Ok(c) => c,
                Err(e) => {
                    out.errors.push(e.to_string());
                    let _ = std::fs::remove_file(&path);
                    continue;
                }
            };
            let mut entries = contents.entries.into_iter();
            match (entries.next(), entries.next(), entries.next()) {
                (
                    Some(Entry::Keyframe {
                        client: c,
                        header,
                        records,
                        imu,
                    }),
                    points,
                    None,
                ) if c == client
                    && contents.problem.is_none()
                    && matches!(points, None | Some(Entry::MapPoints { .. })) =>
                {
                    self.files
                        .insert((header.meta.session_id, header.keyframe_id));
                    out.keyframes.push(Recovered {
                        header: *header,
                        records,
                        imu,
                        points: match points {
                            Some(Entry::MapPoints { points }) => Some(points),
                            _ => None,
                        },
                    });
                }
                _ => {
                    out.errors.push(format!(
                        "spool file {}: not a keyframe of client {client}{}",
                        path.display(),
                        contents
                            .problem
                            .map(|p| format!(" ({p})"))
                            .unwrap_or_default()
                    ));
                    let _ = std::fs::remove_file(&path);
                }
            }
        }
        out.keyframes
            .sort_by_key(|k| (k.header.meta.session_id, k.header.keyframe_id));
        out
    }

    /// Writes a keyframe just created (its message as it would be sent now, IMU segment
    /// included) and the positions of its map points, in one file.
    pub fn write(
        &mut self,
        client: u32,
        msg: &KeyframeMsg,
        points: &[SpooledPoint],
    ) -> std::io::Result<()> {
        if self.until_ack && self.files.len() >= crate::config::SPOOL_MAX_FILES {
            return Err(std::io::Error::other(format!(
                "the spool holds {} unacknowledged keyframes, its most; this one is kept in \
                 memory only",
                self.files.len()
            )));
        }
        let header = &msg.header;
        let key = (header.meta.session_id, header.keyframe_id);
        let mut bytes = spool_file_header().to_vec();
        bytes.extend(encode_entry(&Entry::Keyframe {
            client,
            header: Box::new(*header),
            records: msg.records.to_vec(),
            imu: msg.imu.to_vec(),
        }));
        bytes.extend(encode_entry(&Entry::MapPoints {
            points: points.to_vec(),
        }));
        let path = self.path(key.0, key.1);
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, &bytes)?;
        std::fs::rename(&tmp, &path)?;
        self.files.insert(key);
        self.written += 1;
        self.bytes_written += bytes.len() as u64;
        Ok(())
    }

    /// Keyframe `id` of `session` was sent: its file goes (or stays until acknowledged,
    /// [`Spool::sent_keep`]), with those of older keyframes of the session (keyframes leave
    /// the window oldest first, so an older one still here was culled by local mapping and
    /// will never be sent). Returns the files removed.
    pub fn sent(&mut self, session: u32, id: u64) -> usize {
        if self.until_ack {
            return self.sent_keep(session, id);
        }
        let gone: Vec<(u32, u64)> = self
            .files
            .range((session, 0)..=(session, id))
            .copied()
            .collect();
        for (s, k) in &gone {
            let _ = std::fs::remove_file(self.path(*s, *k));
            self.files.remove(&(*s, *k));
        }
        gone.len()
    }

    /// Keyframe `id` of `session` was sent, and its file stays until the mapper
    /// acknowledges it (`tracker.spool_until_ack`, [`Spool::acked`]); the files of older
    /// keyframes of the session never sent go (culled, as in [`Spool::sent`]). Returns the
    /// files removed.
    pub fn sent_keep(&mut self, session: u32, id: u64) -> usize {
        let culled: Vec<(u32, u64)> = (self.files.range((session, 0)..(session, id)))
            .filter(|k| !self.sent_kept.contains(k))
            .copied()
            .collect();
        for k in &culled {
            let _ = std::fs::remove_file(self.path(k.0, k.1));
            self.files.remove(k);
        }
        if self.files.contains(&(session, id)) {
            self.sent_kept.insert((session, id));
        }
        culled.len()
    }

    /// Drops keyframe `(session, id)`'s file once the mapper acknowledged it
    /// (`tracker.spool_until_ack`; without it the file went when the keyframe was sent);
    /// whether there was one.
    pub fn acked(&mut self, session: u32, id: u64) -> bool {
        if !self.sent_kept.remove(&(session, id)) {
            return false;
        }
        let had = self.files.remove(&(session, id));
        if had {
            let _ = std::fs::remove_file(self.path(session, id));
        }
        had
    }

    /// Keyframes on disk.
    pub fn len(&self) -> usize {
        self.files.len()
    }

    /// Whether no keyframe is on disk.
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shm_schema::MsgMeta;

    /// Keyframe `id`'s message, with a two-sample IMU segment from the previous one.
    fn message(session: u32, id: u64) -> KeyframeMsg {
        let t_ns = id as i64 * 1000;
        let imu: Vec<ImuRecord> = [t_ns - 1000, t_ns]
            .iter()
            .map(|&t| ImuRecord {
                t_ns: t,
                gyro: [0.1, 0.0, id as f64],
                ..ImuRecord::default()
            })
            .collect();
        let header = KeyframeHeader {
            meta: MsgMeta::new(3, session, 0, 0),
            keyframe_id: id,
            t_ns,
            n_keypoints: 2,
            n_imu: 2,
            has_imu: 1,
            imu_t0_ns: t_ns - 1000,
            imu_t1_ns: t_ns,
            ..KeyframeHeader::default()
        };
        let records = vec![
            KeypointRecord {
                u: id as f32,
                map_point_id: 7,
                ..KeypointRecord::default()
            };
            2
        ];
        KeyframeMsg {
            header,
            records: records.into(),
            imu: imu.into(),
            imu_cut: 0,
        }
    }

    /// Kept until acknowledged (`tracker.spool_until_ack`): a successor recovers the
    /// unsent keyframes and the sent, unacknowledged ones, not the culled nor the
    /// acknowledged ones.
    #[test]
    fn kept_until_acknowledged() {
        let dir = std::env::temp_dir().join(format!("shoal_spool_ack_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut s = Spool::open(&dir).expect("spool").until_acked();
        for id in 1..=8 {
            s.write(3, &message(65537, id), &[]).expect("write");
        }
        // 1 culled; 2, 3 and 5 sent (4 culled); 3 acknowledged; the network is down.
        assert_eq!(s.sent_keep(65537, 2), 1);
        assert_eq!(s.sent_keep(65537, 3), 0);
        assert_eq!(s.sent_keep(65537, 5), 1);
        assert!(s.acked(65537, 3));
        assert!(!s.acked(65537, 3), "acknowledged twice");
        assert_eq!(s.len(), 5);
        drop(s);
        let rec = Spool::open(&dir).expect("spool").recover(3);
        let ids: Vec<u64> = rec.keyframes.iter().map(|k| k.header.keyframe_id).collect();
        assert_eq!(ids, vec![2, 5, 6, 7, 8]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_successor_recovers_exactly_the_unsent_keyframes() {
        let dir = std::env::temp_dir().join(format!("shoal_spool_test_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut s = Spool::open(&dir).expect("spool");
        let points = [SpooledPoint {
            id: 7,
            p_w: [1.0, 2.0, 3.0],
        }];
        for id in 1..=6 {
            s.write(3, &message(65537, id), &points).expect("write");
        }
        // Keyframe 3 leaves the window (1 and 2 were culled), then the process dies.
        assert_eq!(s.sent(65537, 3), 3);
        std::fs::write(dir.join("00010001_0000000000000007.tmp"), b"torn").expect("tmp");
        std::fs::write(dir.join("00010001_0000000000000008.kf"), b"garbage").expect("bad");
        drop(s);
        let mut next = Spool::open(&dir).expect("spool");
        let rec = next.recover(3);
        let ids: Vec<u64> = rec.keyframes.iter().map(|k| k.header.keyframe_id).collect();
        assert_eq!(ids, vec![4, 5, 6]);
        assert_eq!(rec.keyframes[0].records[0].u, 4.0);
        assert_eq!(rec.keyframes[0].records[1].map_point_id, 7);
        assert_eq!(rec.keyframes[0].imu, message(65537, 4).imu.to_vec());
        assert_eq!(rec.keyframes[0].header, message(65537, 4).header);
        assert_eq!(rec.keyframes[0].points.as_deref(), Some(&points[..]));
        assert_eq!(rec.errors.len(), 1, "{:?}", rec.errors);
        assert!(
            rec.errors[0].contains("0000000000000008.kf"),
            "{:?}",
            rec.errors
        );
        assert_eq!(next.len(), 3);
        assert_eq!(next.sent(65537, 6), 3);
        assert!(next.is_empty());
        let left = std::fs::read_dir(&dir).expect("dir").count();
        assert_eq!(left, 0, "the temporary and the corrupt file are gone too");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A file without the map points entry is recovered without point positions; one with
    /// a foreign entry after the keyframe is refused as corrupt; a file of a tracker before
    /// issue 19 (no spool header), or one cut inside its IMU records, is refused, named,
    /// and deleted.
    #[test]
    fn older_torn_and_foreign_spool_files() {
        let dir = std::env::temp_dir().join(format!("shoal_spool_old_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut s = Spool::open(&dir).expect("spool");
        let m = message(65537, 2);
        let entry = Entry::Keyframe {
            client: 3,
            header: Box::new(m.header),
            records: m.records.to_vec(),
            imu: m.imu.to_vec(),
        };
        let mut alone = spool_file_header().to_vec();
        alone.extend(encode_entry(&entry));
        std::fs::write(s.path(65537, 2), &alone).expect("file");
        let mut foreign = alone.clone();
        foreign.extend(encode_entry(&entry));
        std::fs::write(s.path(65537, 3), foreign).expect("foreign file");
        std::fs::write(s.path(65537, 4), encode_entry(&entry)).expect("pre-v3 file");
        std::fs::write(s.path(65537, 5), &alone[..alone.len() - 30]).expect("torn file");
        let rec = s.recover(3);
        assert_eq!(rec.keyframes.len(), 1);
        assert_eq!(rec.keyframes[0].header.keyframe_id, 2);
        assert_eq!(rec.keyframes[0].imu.len(), 2);
        assert!(rec.keyframes[0].points.is_none());
        assert_eq!(rec.errors.len(), 3, "{:?}", rec.errors);
        assert!(rec
            .errors
            .iter()
            .any(|e| e.contains("0000000000000004.kf") && e.contains("no spool file header")));
        assert!(rec.errors.iter().any(|e| e.contains("0000000000000005.kf")));
        assert_eq!(std::fs::read_dir(&dir).expect("dir").count(), 1);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
