//! Journals of the services (design: faults). The tracker's keyframe spool writes one
//! keyframe entry per file ([`encode_entry`], read back by [`parse`]); the mapper keeps an
//! append-only [`Journal`].
//!
//! The mapper's append-only journal: every keyframe the mapper applies is
//! written whole (header + keypoint records) before it is acknowledged, and after each
//! handled keyframe whose handler then ran its idle step (local BA + culling) a small idle
//! marker is written. A restarted mapper replays the keyframes in journal order through
//! fresh handlers, running the idle step exactly after the keyframes that have a marker, so
//! it rebuilds the same maps (the handler is deterministic for a given call schedule).
//!
//! Framing, little endian: `MAGIC u32 | kind u8 | 0 u8 ×3 | len u32 | payload | FNV-1a 64 of
//! (kind, len, payload)`. A torn or corrupt tail (a crash in the middle of a write) is
//! reported and cut off before new entries are appended; nothing after it is read.
use std::io::Write;
use std::path::{Path, PathBuf};

use shm_schema::{
    CorrectionHeader, CorrectionRecord, Intrinsics, KeyframeHeader, KeypointRecord, MsgMeta, Pose,
};

/// Start of every entry ("SHJL").
const MAGIC: u32 = 0x4C4A_4853;
/// Entry kind: a keyframe message.
const KIND_KEYFRAME: u8 = 1;
/// Entry kind: an idle marker.
const KIND_IDLE: u8 = 2;
/// Entry kind: a loop correction as received from the loop closer.
const KIND_CORRECTION: u8 = 3;
/// Bytes before the payload.
const HEAD: usize = 12;
/// Largest payload accepted when reading (a corrupt length must not allocate gigabytes).
const MAX_PAYLOAD: usize = 64 << 20;

/// One journal entry.
#[derive(Debug, Clone, PartialEq)]
pub enum Entry {
    /// A keyframe message of `client`, as received.
    Keyframe {
        /// Client index.
        client: u32,
        /// Message header (boxed: it is large beside the idle marker).
        header: Box<KeyframeHeader>,
        /// Keypoint records.
        records: Vec<KeypointRecord>,
    },
    /// The handler of `client` ran its idle step right after handling keyframe `kf_id` of
    /// `session`.
    Idle {
        /// Client index.
        client: u32,
        /// VO session of the keyframe.
        session: u32,
        /// Client keyframe id.
        kf_id: u64,
    },
    /// A loop correction (merge or pose graph) as received, applied after the entries
    /// before it.
    Correction {
        /// Message header.
        header: Box<CorrectionHeader>,
        /// Records.
        records: Vec<CorrectionRecord>,
    },
}

/// What [`read`] found.
#[derive(Debug, Default)]
pub struct Contents {
    /// The good entries, in order.
    pub entries: Vec<Entry>,
    /// Length of the good prefix of the file, bytes.
    pub good_len: u64,
    /// Why reading stopped before the end of the file (torn or corrupt tail).
    pub problem: Option<String>,
}

fn fnv1a(h: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(h, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn checksum(kind: u8, len: u32, payload: &[u8]) -> u64 {
    let h = fnv1a(0xcbf2_9ce4_8422_2325, &[kind]);
    let h = fnv1a(h, &len.to_le_bytes());
    fnv1a(h, payload)
}

/// Little-endian writer of the payload.
#[derive(Default)]
struct Enc(Vec<u8>);

impl Enc {
    fn u32(&mut self, v: u32) {
        self.0.extend(v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend(v.to_le_bytes());
    }
    fn i64(&mut self, v: i64) {
        self.0.extend(v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend(v.to_le_bytes());
    }
    fn f64s(&mut self, v: &[f64]) {
        for x in v {
            self.0.extend(x.to_le_bytes());
        }
    }
}

/// Little-endian reader of a payload.
struct Dec<'a>(&'a [u8]);

impl Dec<'_> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let (a, rest) = self.0.split_at_checked(N)?;
        self.0 = rest;
        a.try_into().ok()
    }
    fn u32(&mut self) -> Option<u32> {
        self.take().map(u32::from_le_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.take().map(u64::from_le_bytes)
    }
    fn i64(&mut self) -> Option<i64> {
        self.take().map(i64::from_le_bytes)
    }
    fn f32(&mut self) -> Option<f32> {
        self.take().map(f32::from_le_bytes)
    }
    fn f64s<const N: usize>(&mut self) -> Option<[f64; N]> {
        let mut out = [0.0; N];
        for x in &mut out {
            *x = self.take().map(f64::from_le_bytes)?;
        }
        Some(out)
    }
}

fn encode_meta(e: &mut Enc, m: &MsgMeta) {
    for v in [m.magic, m.schema_version, m.client_id, m.session_id] {
        e.u32(v);
    }
    e.u64(m.seq);
    e.i64(m.publish_mono_ns);
    e.u32(m.flags);
    e.u32(m.reserved);
}

fn decode_meta(d: &mut Dec) -> Option<MsgMeta> {
    Some(MsgMeta {
        magic: d.u32()?,
        schema_version: d.u32()?,
        client_id: d.u32()?,
        session_id: d.u32()?,
        seq: d.u64()?,
        publish_mono_ns: d.i64()?,
        flags: d.u32()?,
        reserved: d.u32()?,
    })
}

fn encode_keyframe(client: u32, h: &KeyframeHeader, records: &[KeypointRecord]) -> Vec<u8> {
    let mut e = Enc(Vec::with_capacity(256 + 64 * records.len()));
    e.u32(client);
    encode_meta(&mut e, &h.meta);
    e.u64(h.keyframe_id);
    e.i64(h.t_ns);
    e.f64s(&h.pose_ck.t);
    e.f64s(&h.pose_ck.q);
    e.f64s(&h.intrinsics.pinhole);
    e.f64s(&h.intrinsics.distortion);
    for v in [h.width, h.height, h.n_keypoints, h.reserved] {
        e.u32(v);
    }
    e.u32(records.len() as u32);
    for r in records {
        for v in [r.u, r.v, r.angle, r.response] {
            e.f32(v);
        }
        e.u32(r.octave);
        e.u32(r.reserved);
        e.u64(r.map_point_id);
        e.0.extend(r.descriptor);
    }
    e.0
}

fn decode_keyframe(p: &[u8]) -> Option<Entry> {
    let mut d = Dec(p);
    let client = d.u32()?;
    let meta = decode_meta(&mut d)?;
    let header = Box::new(KeyframeHeader {
        meta,
        keyframe_id: d.u64()?,
        t_ns: d.i64()?,
        pose_ck: Pose {
            t: d.f64s()?,
            q: d.f64s()?,
        },
        intrinsics: Intrinsics {
            pinhole: d.f64s()?,
            distortion: d.f64s()?,
        },
        width: d.u32()?,
        height: d.u32()?,
        n_keypoints: d.u32()?,
        reserved: d.u32()?,
    });
    let n = d.u32()? as usize;
    if n > d.0.len() / 64 {
        return None;
    }
    let mut records = Vec::with_capacity(n);
    for _ in 0..n {
        records.push(KeypointRecord {
            u: d.f32()?,
            v: d.f32()?,
            angle: d.f32()?,
            response: d.f32()?,
            octave: d.u32()?,
            reserved: d.u32()?,
            map_point_id: d.u64()?,
            descriptor: d.take()?,
        });
    }
    Some(Entry::Keyframe {
        client,
        header,
        records,
    })
}

fn encode_pose(e: &mut Enc, p: &Pose) {
    e.f64s(&p.t);
    e.f64s(&p.q);
}

fn decode_pose(d: &mut Dec) -> Option<Pose> {
    Some(Pose {
        t: d.f64s::<3>()?,
        q: d.f64s::<4>()?,
    })
}

fn encode_correction(h: &CorrectionHeader, records: &[CorrectionRecord]) -> Vec<u8> {
    let mut e = Enc(Vec::with_capacity(256 + 88 * records.len()));
    encode_meta(&mut e, &h.meta);
    e.u64(h.correction_id);
    e.u32(h.kind);
    e.u32(h.n_records);
    for v in [h.query_kf, h.matched_kf, h.from_map, h.into_map] {
        e.u64(v);
    }
    encode_pose(&mut e, &h.sim3);
    e.f64s(&[h.scale]);
    e.u32(h.inliers);
    e.u32(h.reserved);
    e.u32(records.len() as u32);
    for r in records {
        e.u32(r.kind);
        e.u32(r.reserved);
        e.u64(r.a);
        e.u64(r.b);
        encode_pose(&mut e, &r.delta);
        e.f64s(&[r.scale]);
    }
    e.0
}

fn decode_correction(p: &[u8]) -> Option<Entry> {
    let mut d = Dec(p);
    let meta = decode_meta(&mut d)?;
    let header = Box::new(CorrectionHeader {
        meta,
        correction_id: d.u64()?,
        kind: d.u32()?,
        n_records: d.u32()?,
        query_kf: d.u64()?,
        matched_kf: d.u64()?,
        from_map: d.u64()?,
        into_map: d.u64()?,
        sim3: decode_pose(&mut d)?,
        scale: d.f64s::<1>()?[0],
        inliers: d.u32()?,
        reserved: d.u32()?,
    });
    let n = d.u32()? as usize;
    if n > d.0.len() / 88 + 1 {
        return None;
    }
    let mut records = Vec::with_capacity(n);
    for _ in 0..n {
        records.push(CorrectionRecord {
            kind: d.u32()?,
            reserved: d.u32()?,
            a: d.u64()?,
            b: d.u64()?,
            delta: decode_pose(&mut d)?,
            scale: d.f64s::<1>()?[0],
        });
    }
    Some(Entry::Correction { header, records })
}

fn encode(entry: &Entry) -> (u8, Vec<u8>) {
    match entry {
        Entry::Keyframe {
            client,
            header,
            records,
        } => (KIND_KEYFRAME, encode_keyframe(*client, header, records)),
        Entry::Idle {
            client,
            session,
            kf_id,
        } => {
            let mut e = Enc::default();
            e.u32(*client);
            e.u32(*session);
            e.u64(*kf_id);
            (KIND_IDLE, e.0)
        }
        Entry::Correction { header, records } => {
            (KIND_CORRECTION, encode_correction(header, records))
        }
    }
}

fn decode(kind: u8, p: &[u8]) -> Option<Entry> {
    match kind {
        KIND_KEYFRAME => decode_keyframe(p),
        KIND_CORRECTION => decode_correction(p),
        KIND_IDLE => {
            let mut d = Dec(p);
            Some(Entry::Idle {
                client: d.u32()?,
                session: d.u32()?,
                kf_id: d.u64()?,
            })
        }
        _ => None,
    }
}

/// Parses journal bytes: the good entries and where the good prefix ends.
pub fn parse(bytes: &[u8]) -> Contents {
    let mut c = Contents::default();
    let mut at = 0usize;
    while at < bytes.len() {
        let rest = &bytes[at..];
        let fail = |why: &str| format!("byte {at}: {why}; the journal is cut there");
        if rest.len() < HEAD {
            c.problem = Some(fail("torn entry head"));
            break;
        }
        let mut d = Dec(rest);
        let (magic, kind_word, len) = (d.u32(), d.u32(), d.u32());
        let (Some(magic), Some(kind_word), Some(len)) = (magic, kind_word, len) else {
            c.problem = Some(fail("torn entry head"));
            break;
        };
        if magic != MAGIC {
            c.problem = Some(fail("bad magic"));
            break;
        }
        let kind = (kind_word & 0xff) as u8;
        let len_us = len as usize;
        if len_us > MAX_PAYLOAD {
            c.problem = Some(fail("entry length out of range"));
            break;
        }
        let Some(body) = rest.get(HEAD..HEAD + len_us + 8) else {
            c.problem = Some(fail("torn entry"));
            break;
        };
        let (payload, sum) = body.split_at(len_us);
        let sum_ok = sum
            .try_into()
            .map(u64::from_le_bytes)
            .is_ok_and(|s| s == checksum(kind, len, payload));
        if !sum_ok {
            c.problem = Some(fail("checksum mismatch"));
            break;
        }
        let Some(entry) = decode(kind, payload) else {
            c.problem = Some(fail("undecodable entry"));
            break;
        };
        c.entries.push(entry);
        at += HEAD + len_us + 8;
        c.good_len = at as u64;
    }
    c
}

/// One entry framed as in a journal file (magic, kind, length, payload, checksum).
pub fn encode_entry(entry: &Entry) -> Vec<u8> {
    let (kind, payload) = encode(entry);
    let len = payload.len() as u32;
    let mut buf = Vec::with_capacity(HEAD + payload.len() + 8);
    buf.extend(MAGIC.to_le_bytes());
    buf.extend(u32::from(kind).to_le_bytes());
    buf.extend(len.to_le_bytes());
    buf.extend(&payload);
    buf.extend(checksum(kind, len, &payload).to_le_bytes());
    buf
}

/// The journal file, open for appending.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    file: std::fs::File,
    /// Bytes written by this process.
    pub bytes_written: u64,
}

impl Journal {
    /// Opens (or creates) the journal at `path`: reads what is there, cuts a torn or corrupt
    /// tail off, and positions for appending.
    pub fn open(path: &Path) -> std::io::Result<(Self, Contents)> {
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => return Err(e),
        };
        let contents = parse(&bytes);
        if contents.good_len < bytes.len() as u64 {
            let f = std::fs::OpenOptions::new().write(true).open(path)?;
            f.set_len(contents.good_len)?;
        }
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)?;
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
                bytes_written: 0,
            },
            contents,
        ))
    }

    /// The journal's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends one entry (a single write, flushed to the OS: it survives a crash of the
    /// process; no fsync, so not a power loss).
    pub fn append(&mut self, entry: &Entry) -> std::io::Result<()> {
        let buf = encode_entry(entry);
        self.file.write_all(&buf)?;
        self.file.flush()?;
        self.bytes_written += buf.len() as u64;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keyframe(id: u64) -> Entry {
        let mut header = KeyframeHeader {
            meta: MsgMeta::new(1, 65537, id, 99),
            keyframe_id: id,
            t_ns: 1_000 * id as i64,
            n_keypoints: 2,
            width: 752,
            height: 480,
            ..KeyframeHeader::default()
        };
        header.pose_ck.t = [1.0, 2.0, 3.5];
        header.intrinsics.pinhole = [458.0, 457.0, 367.0, 248.0];
        let mut r = KeypointRecord {
            u: 1.5,
            v: 2.5,
            octave: 3,
            map_point_id: 77,
            ..KeypointRecord::default()
        };
        r.descriptor[5] = 0xab;
        Entry::Keyframe {
            client: 1,
            header: Box::new(header),
            records: vec![r, KeypointRecord::default()],
        }
    }

    #[test]
    fn round_trip_and_torn_tail_is_cut() {
        let dir = std::env::temp_dir().join(format!("shoal_journal_{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("j.bin");
        let _ = std::fs::remove_file(&path);
        let entries = vec![
            keyframe(1),
            Entry::Idle {
                client: 1,
                session: 65537,
                kf_id: 1,
            },
            keyframe(2),
            Entry::Correction {
                header: Box::new(CorrectionHeader {
                    meta: MsgMeta::new(1, 0, 7, 5),
                    correction_id: 7,
                    kind: shm_schema::CORRECTION_POSE_GRAPH,
                    n_records: 2,
                    query_kf: 9,
                    matched_kf: 3,
                    from_map: 1 << 32,
                    into_map: 1 << 32,
                    scale: 1.25,
                    inliers: 88,
                    ..CorrectionHeader::default()
                }),
                records: vec![
                    CorrectionRecord {
                        kind: shm_schema::RECORD_KEYFRAME_DELTA,
                        a: 3,
                        scale: 0.9,
                        ..CorrectionRecord::default()
                    },
                    CorrectionRecord {
                        kind: shm_schema::RECORD_POINT_PAIR,
                        a: 11,
                        b: 12,
                        ..CorrectionRecord::default()
                    },
                ],
            },
        ];
        {
            let (mut j, c) = Journal::open(&path).expect("open");
            assert!(c.entries.is_empty() && c.problem.is_none());
            for e in &entries {
                j.append(e).expect("append");
            }
        }
        let full = std::fs::read(&path).expect("read");
        let c = parse(&full);
        assert_eq!(c.entries, entries);
        assert!(c.problem.is_none());
        // A crash in the middle of the last write: the entries before it survive.
        std::fs::write(&path, &full[..full.len() - 10]).expect("write");
        let (mut j, c) = Journal::open(&path).expect("reopen");
        assert_eq!(c.entries, entries[..3]);
        assert!(c.problem.as_deref().is_some_and(|p| p.contains("torn")));
        // Appending after the cut gives a clean journal again.
        j.append(&entries[3]).expect("append");
        drop(j);
        let c = parse(&std::fs::read(&path).expect("read"));
        assert_eq!(c.entries, entries);
        assert!(c.problem.is_none());
        // A flipped byte inside an entry is caught by the checksum.
        let mut bad = full.clone();
        bad[HEAD + 20] ^= 1;
        let c = parse(&bad);
        assert!(c.entries.is_empty());
        assert!(c.problem.is_some_and(|p| p.contains("checksum")));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
