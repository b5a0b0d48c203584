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
//!
//! A journal file starts with a header: `"SHOALJNL" | JOURNAL_VERSION u32 | SCHEMA_VERSION u32`
//! ([`JOURNAL_VERSION`], [`shm_schema::SCHEMA_VERSION`]: the payloads are the messages'
//! fields). A journal without it, or of another version, is refused with a
//! [`VersionError`] naming the file ([`Journal::open`], [`read_journal`]) instead of being
//! misread. Spool files start with their own header, `"SHOALSPL" | JOURNAL_VERSION u32 |
//! SCHEMA_VERSION u32` ([`spool_file_header`], [`parse_spool`]; since journal version 3,
//! issue 19: a spool file of an older tracker, without it, is refused the same way), then
//! hold one keyframe entry followed by a [`Entry::MapPoints`] entry with the positions of the
//! points it observes (issue 17); that kind appears in spool files only.
//!
//! Journal version 3 (schema version 4, issue 19): a keyframe entry carries the header's IMU
//! fields and the IMU segment's records after the keypoints ([`Entry::Keyframe::imu`]).
use std::io::Write;
use std::path::{Path, PathBuf};

use shm_schema::{
    CorrectionHeader, CorrectionRecord, ImuCalib, ImuRecord, Intrinsics, KeyframeHeader,
    KeypointRecord, MsgMeta, Pose, SCHEMA_VERSION,
};

/// Version of the journal format (header, framing and payload encodings). Bump on any change
/// of them.
pub const JOURNAL_VERSION: u32 = 3;
/// First bytes of a journal file.
const FILE_MAGIC: [u8; 8] = *b"SHOALJNL";
/// First bytes of a spool file.
const SPOOL_MAGIC: [u8; 8] = *b"SHOALSPL";
/// Bytes of the file header (magic, journal version, schema version).
pub const FILE_HEAD: usize = 16;

/// Start of every entry ("SHJL").
const MAGIC: u32 = 0x4C4A_4853;
/// Entry kind: a keyframe message.
const KIND_KEYFRAME: u8 = 1;
/// Entry kind: an idle marker.
const KIND_IDLE: u8 = 2;
/// Entry kind: a loop correction as received from the loop closer.
const KIND_CORRECTION: u8 = 3;
/// Entry kind: the map points of a spooled keyframe (spool files only).
const KIND_MAP_POINTS: u8 = 4;
/// Bytes before the payload.
const HEAD: usize = 12;
/// Largest payload accepted when reading (a corrupt length must not allocate gigabytes).
const MAX_PAYLOAD: usize = 64 << 20;

/// A client map point as the tracker spools it beside a keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpooledPoint {
    /// Client map-point id (a keypoint record's `map_point_id`).
    pub id: u64,
    /// Position in the client map's world when the keyframe was spooled, m.
    pub p_w: [f64; 3],
}

/// Bytes of one [`SpooledPoint`] in an entry.
const SPOOLED_POINT_BYTES: usize = 32;

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
        /// The IMU segment's records (`header.n_imu` of them as sent; none for a
        /// monocular client).
        imu: Vec<ImuRecord>,
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
    /// The map points a spooled keyframe observes, after its keyframe entry (spool files
    /// only: a successor rebuilds its predecessor's client map from them).
    MapPoints {
        /// Id and position of each point.
        points: Vec<SpooledPoint>,
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

fn encode_imu_calib(e: &mut Enc, c: &ImuCalib) {
    encode_pose(e, &c.pose_bc);
    e.i64(c.t_d_ns);
    e.f64s(&[
        c.gyro_noise_density,
        c.accel_noise_density,
        c.gyro_bias_rw,
        c.accel_bias_rw,
    ]);
    for m in [&c.t_a, &c.t_g, &c.t_s] {
        e.f64s(m);
    }
}

fn decode_imu_calib(d: &mut Dec) -> Option<ImuCalib> {
    let pose_bc = decode_pose(d)?;
    let t_d_ns = d.i64()?;
    let [gyro_noise_density, accel_noise_density, gyro_bias_rw, accel_bias_rw] = d.f64s()?;
    Some(ImuCalib {
        pose_bc,
        t_d_ns,
        gyro_noise_density,
        accel_noise_density,
        gyro_bias_rw,
        accel_bias_rw,
        t_a: d.f64s()?,
        t_g: d.f64s()?,
        t_s: d.f64s()?,
    })
}

/// Bytes of one [`ImuRecord`] in an entry.
const IMU_RECORD_BYTES: usize = 64;

fn encode_imu_records(e: &mut Enc, imu: &[ImuRecord]) {
    e.u32(imu.len() as u32);
    for r in imu {
        e.i64(r.t_ns);
        e.f64s(&r.gyro);
        e.f64s(&r.accel);
        e.u64(r.reserved);
    }
}

fn decode_imu_records(d: &mut Dec) -> Option<Vec<ImuRecord>> {
    let n = d.u32()? as usize;
    if n > d.0.len() / IMU_RECORD_BYTES {
        return None;
    }
    (0..n)
        .map(|_| {
            Some(ImuRecord {
                t_ns: d.i64()?,
                gyro: d.f64s()?,
                accel: d.f64s()?,
                reserved: d.u64()?,
            })
        })
        .collect()
}

fn encode_keyframe(
    client: u32,
    h: &KeyframeHeader,
    records: &[KeypointRecord],
    imu: &[ImuRecord],
) -> Vec<u8> {
    let mut e = Enc(Vec::with_capacity(640 + 64 * (records.len() + imu.len())));
    e.u32(client);
    encode_meta(&mut e, &h.meta);
    e.u64(h.keyframe_id);
    e.i64(h.t_ns);
    e.f64s(&h.pose_ck.t);
    e.f64s(&h.pose_ck.q);
    e.f64s(&h.intrinsics.pinhole);
    e.f64s(&h.intrinsics.distortion);
    for v in [h.width, h.height, h.n_keypoints, h.inertial] {
        e.u32(v);
    }
    e.f64s(&h.velocity_w);
    e.f64s(&h.gyro_bias);
    e.f64s(&h.accel_bias);
    e.u32(h.n_imu);
    e.u32(h.has_imu);
    e.i64(h.imu_t0_ns);
    e.i64(h.imu_t1_ns);
    encode_imu_calib(&mut e, &h.imu_calib);
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
    encode_imu_records(&mut e, imu);
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
        inertial: d.u32()?,
        velocity_w: d.f64s()?,
        gyro_bias: d.f64s()?,
        accel_bias: d.f64s()?,
        n_imu: d.u32()?,
        has_imu: d.u32()?,
        imu_t0_ns: d.i64()?,
        imu_t1_ns: d.i64()?,
        imu_calib: decode_imu_calib(&mut d)?,
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
    let imu = decode_imu_records(&mut d)?;
    Some(Entry::Keyframe {
        client,
        header,
        records,
        imu,
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

fn encode_map_points(points: &[SpooledPoint]) -> Vec<u8> {
    let mut e = Enc(Vec::with_capacity(4 + SPOOLED_POINT_BYTES * points.len()));
    e.u32(points.len() as u32);
    for p in points {
        e.u64(p.id);
        e.f64s(&p.p_w);
    }
    e.0
}

fn decode_map_points(p: &[u8]) -> Option<Entry> {
    let mut d = Dec(p);
    let n = d.u32()? as usize;
    if n > d.0.len() / SPOOLED_POINT_BYTES {
        return None;
    }
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        points.push(SpooledPoint {
            id: d.u64()?,
            p_w: d.f64s()?,
        });
    }
    Some(Entry::MapPoints { points })
}

fn encode(entry: &Entry) -> (u8, Vec<u8>) {
    match entry {
        Entry::Keyframe {
            client,
            header,
            records,
            imu,
        } => (
            KIND_KEYFRAME,
            encode_keyframe(*client, header, records, imu),
        ),
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
        Entry::MapPoints { points } => (KIND_MAP_POINTS, encode_map_points(points)),
    }
}

fn decode(kind: u8, p: &[u8]) -> Option<Entry> {
    match kind {
        KIND_KEYFRAME => decode_keyframe(p),
        KIND_CORRECTION => decode_correction(p),
        KIND_MAP_POINTS => decode_map_points(p),
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

/// The header a file of `kind` written by this binary starts with.
fn header_of(kind: FileKind) -> [u8; FILE_HEAD] {
    let mut h = [0u8; FILE_HEAD];
    h[..8].copy_from_slice(kind.magic());
    h[8..12].copy_from_slice(&JOURNAL_VERSION.to_le_bytes());
    h[12..].copy_from_slice(&SCHEMA_VERSION.to_le_bytes());
    h
}

/// The header a journal of this binary starts with.
fn file_header() -> [u8; FILE_HEAD] {
    header_of(FileKind::Journal)
}

/// The header a spool file of this binary starts with (its entries follow, framed as in a
/// journal: [`encode_entry`]).
pub fn spool_file_header() -> [u8; FILE_HEAD] {
    header_of(FileKind::Spool)
}

/// The two kinds of files of framed entries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    /// The mapper's journal.
    Journal,
    /// A tracker's spool file (one keyframe).
    Spool,
}

impl FileKind {
    fn magic(self) -> &'static [u8; 8] {
        match self {
            Self::Journal => &FILE_MAGIC,
            Self::Spool => &SPOOL_MAGIC,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Journal => "journal",
            Self::Spool => "spool file",
        }
    }
}

/// A journal or spool file this binary does not read: no header, or one of another version.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VersionError {
    /// The file.
    pub path: PathBuf,
    /// Journal or spool file.
    pub kind: FileKind,
    /// (journal version, schema version) of the file's header; `None` when it has none.
    pub found: Option<(u32, u32)>,
}

impl std::fmt::Display for VersionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = self.kind.name();
        write!(f, "{kind} {}: ", self.path.display())?;
        match self.found {
            None => write!(
                f,
                "no {kind} header (written by an older binary, or not a {kind})"
            )?,
            Some((j, s)) => write!(f, "journal version {j} of schema version {s}")?,
        }
        write!(
            f,
            "; this binary reads journal version {JOURNAL_VERSION} of schema version {SCHEMA_VERSION}"
        )
    }
}

impl std::error::Error for VersionError {}

/// The versions in the header of journal bytes; `Err(None)` without a header, `Err(found)`
/// for another version.
fn check_header(bytes: &[u8], kind: FileKind) -> Result<(), Option<(u32, u32)>> {
    let head = bytes.get(..FILE_HEAD).ok_or(None)?;
    if head[..8] != *kind.magic() {
        return Err(None);
    }
    let word = |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
    let found = (word(8), word(12));
    if found != (JOURNAL_VERSION, SCHEMA_VERSION) {
        return Err(Some(found));
    }
    Ok(())
}

/// Parses the bytes of a journal file (header, then entries); `good_len` counts the header.
/// Errors, naming `path`, when the header is missing or of another version.
pub fn parse_journal(path: &Path, bytes: &[u8]) -> Result<Contents, VersionError> {
    parse_with_header(path, bytes, FileKind::Journal)
}

/// Parses the bytes of a spool file (header, then entries); errors, naming `path`, when
/// the header is missing (a spool file of a tracker before journal version 3) or of another
/// version.
pub fn parse_spool(path: &Path, bytes: &[u8]) -> Result<Contents, VersionError> {
    parse_with_header(path, bytes, FileKind::Spool)
}

fn parse_with_header(path: &Path, bytes: &[u8], kind: FileKind) -> Result<Contents, VersionError> {
    check_header(bytes, kind).map_err(|found| VersionError {
        path: path.to_path_buf(),
        kind,
        found,
    })?;
    Ok(parse_from(bytes, FILE_HEAD))
}

/// Why a journal file could not be read.
#[derive(Debug)]
pub enum ReadError {
    /// Reading the file failed.
    Io(PathBuf, std::io::Error),
    /// Not a journal of this version.
    Version(VersionError),
}

impl std::fmt::Display for ReadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReadError::Io(p, e) => write!(f, "reading the journal {}: {e}", p.display()),
            ReadError::Version(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for ReadError {}

/// Reads and parses the journal file at `path` ([`parse_journal`]).
pub fn read_journal(path: &Path) -> Result<Contents, ReadError> {
    let bytes = std::fs::read(path).map_err(|e| ReadError::Io(path.to_path_buf(), e))?;
    parse_journal(path, &bytes).map_err(ReadError::Version)
}

/// Parses framed entries without a file header (a spool file): the good entries and where
/// the good prefix ends.
pub fn parse(bytes: &[u8]) -> Contents {
    parse_from(bytes, 0)
}

/// The entries of `bytes` from offset `at` on; `good_len` and the problem's byte offset are
/// file offsets.
fn parse_from(bytes: &[u8], mut at: usize) -> Contents {
    let mut c = Contents {
        good_len: at as u64,
        ..Contents::default()
    };
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

/// Why [`Journal::open`] failed.
#[derive(Debug)]
pub enum OpenError {
    /// Reading, cutting or creating the file failed.
    Io(std::io::Error),
    /// The file is not a journal of this version (nothing was changed in it).
    Version(VersionError),
}

impl std::fmt::Display for OpenError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OpenError::Io(e) => e.fmt(f),
            OpenError::Version(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for OpenError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            OpenError::Io(e) => Some(e),
            OpenError::Version(e) => Some(e),
        }
    }
}

impl From<std::io::Error> for OpenError {
    fn from(e: std::io::Error) -> Self {
        OpenError::Io(e)
    }
}

impl Journal {
    /// Opens (or creates, with its header) the journal at `path`: reads what is there, cuts
    /// a torn or corrupt tail off, and positions for appending. A file of another journal
    /// version, or without a header, is an [`OpenError::Version`] and is left as it is
    /// (see [`Journal::set_aside`]). An empty file, or one holding part of this version's
    /// header (a crash while creating it), is a new journal.
    pub fn open(path: &Path) -> Result<(Self, Contents), OpenError> {
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => return Err(e.into()),
        };
        let header = file_header();
        let fresh = bytes.len() < FILE_HEAD && header.starts_with(&bytes);
        let contents = if fresh {
            Contents::default()
        } else {
            parse_journal(path, &bytes).map_err(OpenError::Version)?
        };
        if !fresh && contents.good_len < bytes.len() as u64 {
            let f = std::fs::OpenOptions::new().write(true).open(path)?;
            f.set_len(contents.good_len)?;
        }
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)?;
        let mut bytes_written = 0;
        if fresh {
            file.set_len(0)?;
            file.write_all(&header)?;
            file.flush()?;
            bytes_written = FILE_HEAD as u64;
        }
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
                bytes_written,
            },
            contents,
        ))
    }

    /// Moves the file at `path` out of the way (to `<path>.rejected`, replacing an older
    /// one) so that a new journal can start there; returns where it went.
    pub fn set_aside(path: &Path) -> std::io::Result<PathBuf> {
        let mut name = path.as_os_str().to_owned();
        name.push(".rejected");
        let to = PathBuf::from(name);
        std::fs::rename(path, &to)?;
        Ok(to)
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
        // A visual-inertial keyframe with a three-sample segment (even ids) or a monocular one.
        let imu: Vec<ImuRecord> = (0..3 * (1 - id as i64 % 2))
            .map(|k| ImuRecord {
                t_ns: 1_000 * id as i64 - 10 + 5 * k,
                gyro: [0.1, -0.2, 0.3 * k as f64],
                accel: [0.5, 9.81, -1e-3],
                reserved: 0,
            })
            .collect();
        if !imu.is_empty() {
            header.n_imu = imu.len() as u32;
            header.has_imu = 1;
            header.imu_t0_ns = imu[0].t_ns;
            header.imu_t1_ns = imu[imu.len() - 1].t_ns;
            header.imu_calib.pose_bc.t = [0.01, -0.02, 0.03];
            header.imu_calib.t_d_ns = -1234;
            header.imu_calib.gyro_noise_density = 1.7e-4;
            header.imu_calib.accel_bias_rw = 3e-3;
            header.imu_calib.t_s[4] = 1e-3;
        }
        Entry::Keyframe {
            client: 1,
            header: Box::new(header),
            records: vec![r, KeypointRecord::default()],
            imu,
        }
    }

    /// A keyframe entry with an IMU segment (header fields, calibration, records) reads
    /// back whole, as a monocular one does; cut inside its IMU records, or with a record
    /// count beyond the entry, it is refused (a torn or undecodable entry), never misread.
    #[test]
    fn keyframe_with_imu_segment_round_trips() {
        for id in [2, 3] {
            let bytes = encode_entry(&keyframe(id));
            let c = parse(&bytes);
            assert_eq!(c.entries, vec![keyframe(id)]);
            assert!(c.problem.is_none());
        }
        let bytes = encode_entry(&keyframe(2));
        let c = parse(&bytes[..bytes.len() - 8 - 40]);
        assert!(c.entries.is_empty());
        assert!(c.problem.as_deref().is_some_and(|p| p.contains("torn")));
        // A corrupt IMU record count (re-checksummed: not a torn write) is undecodable.
        let (kind, mut payload) = encode(&keyframe(2));
        let at = payload.len() - 3 * IMU_RECORD_BYTES - 4;
        assert_eq!(payload[at..at + 4], 3u32.to_le_bytes());
        payload[at..at + 4].copy_from_slice(&4u32.to_le_bytes());
        let len = payload.len() as u32;
        let mut framed = Vec::new();
        framed.extend(MAGIC.to_le_bytes());
        framed.extend(u32::from(kind).to_le_bytes());
        framed.extend(len.to_le_bytes());
        framed.extend(&payload);
        framed.extend(checksum(kind, len, &payload).to_le_bytes());
        let c = parse(&framed);
        assert!(c.entries.is_empty());
        assert!(c
            .problem
            .as_deref()
            .is_some_and(|p| p.contains("undecodable")));
    }

    /// A spool file: a keyframe entry and its map points, read back whole; cut short, the
    /// keyframe survives and the cut is reported.
    #[test]
    fn spool_file_with_map_points_round_trips() {
        let points = Entry::MapPoints {
            points: vec![
                SpooledPoint {
                    id: 77,
                    p_w: [0.5, -1.25, 4.0],
                },
                SpooledPoint {
                    id: 1 << 41,
                    p_w: [1e-3, 2.0, -3.0],
                },
            ],
        };
        let path = Path::new("spool/0001_0004.kf");
        let mut bytes = spool_file_header().to_vec();
        bytes.extend(encode_entry(&keyframe(4)));
        let keyframe_len = bytes.len();
        bytes.extend(encode_entry(&points));
        let c = parse_spool(path, &bytes).expect("this version");
        assert_eq!(c.entries, vec![keyframe(4), points]);
        assert!(c.problem.is_none());
        let c = parse_spool(path, &bytes[..bytes.len() - 3]).expect("this version");
        assert_eq!(c.entries, vec![keyframe(4)]);
        assert_eq!(c.good_len, keyframe_len as u64);
        assert!(c.problem.is_some());
        // A spool file of an older tracker (no header) or of another version is refused
        // with both versions named; a journal is not a spool file.
        let e = parse_spool(path, &bytes[FILE_HEAD..]).expect_err("no header");
        assert_eq!((e.kind, e.found), (FileKind::Spool, None));
        assert!(e.to_string().contains("no spool file header"), "{e}");
        let mut old = bytes.clone();
        old[8..12].copy_from_slice(&2u32.to_le_bytes());
        let e = parse_spool(path, &old).expect_err("version 2");
        let text = e.to_string();
        assert!(text.contains("spool file spool/0001_0004.kf"), "{text}");
        assert!(
            text.contains("journal version 2 of schema version"),
            "{text}"
        );
        assert!(
            text.contains(&format!("reads journal version {JOURNAL_VERSION}")),
            "{text}"
        );
        let mut journal = file_header().to_vec();
        journal.extend(&bytes[FILE_HEAD..]);
        assert!(parse_spool(path, &journal).is_err());
    }

    #[test]
    fn round_trip_and_torn_tail_is_cut() {
        let map = slam_core::ids::MapId::new(slam_core::ids::ClientId::new(1), 0);
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
                    from_map: map.raw(),
                    into_map: map.raw(),
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
        assert_eq!(full[..FILE_HEAD], file_header());
        let c = parse_journal(&path, &full).expect("this version");
        assert_eq!(c.good_len, full.len() as u64);
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
        let c = read_journal(&path).expect("read");
        assert_eq!(c.entries, entries);
        assert!(c.problem.is_none());
        // A flipped byte inside an entry is caught by the checksum.
        let mut bad = full.clone();
        bad[FILE_HEAD + HEAD + 20] ^= 1;
        let c = parse_journal(&path, &bad).expect("header intact");
        assert_eq!(c.good_len, FILE_HEAD as u64);
        assert!(c.entries.is_empty());
        assert!(c.problem.is_some_and(|p| p.contains("checksum")));
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn temp_journal(name: &str) -> (PathBuf, PathBuf) {
        let dir = std::env::temp_dir().join(format!("shoal_journal_{name}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("mapper_journal.bin");
        (dir, path)
    }

    /// A journal of another version is refused, untouched, with an error naming the file and
    /// both versions; set aside, a new journal starts in its place.
    #[test]
    fn another_version_is_refused() {
        let (dir, path) = temp_journal("version");
        {
            let (mut j, _) = Journal::open(&path).expect("open");
            j.append(&keyframe(1)).expect("append");
        }
        let mut bytes = std::fs::read(&path).expect("read");
        bytes[8..12].copy_from_slice(&(JOURNAL_VERSION + 1).to_le_bytes());
        std::fs::write(&path, &bytes).expect("write");
        let err = match Journal::open(&path) {
            Err(OpenError::Version(e)) => e,
            other => panic!("expected a version error, got {other:?}"),
        };
        assert_eq!(err.found, Some((JOURNAL_VERSION + 1, SCHEMA_VERSION)));
        let text = err.to_string();
        assert!(text.contains(&path.display().to_string()), "{text}");
        assert!(
            text.contains(&format!("journal version {}", JOURNAL_VERSION + 1)),
            "{text}"
        );
        assert_eq!(std::fs::read(&path).expect("read"), bytes, "left as it was");
        assert!(matches!(read_journal(&path), Err(ReadError::Version(_))));
        // Another schema version is refused the same way.
        let mut other_schema = bytes.clone();
        other_schema[8..12].copy_from_slice(&JOURNAL_VERSION.to_le_bytes());
        other_schema[12..16].copy_from_slice(&(SCHEMA_VERSION + 1).to_le_bytes());
        let e = parse_journal(&path, &other_schema).expect_err("other schema");
        assert_eq!(e.found, Some((JOURNAL_VERSION, SCHEMA_VERSION + 1)));
        // Set aside, the path holds a new, empty journal.
        let aside = Journal::set_aside(&path).expect("rename");
        assert_eq!(std::fs::read(&aside).expect("read"), bytes);
        let (_, c) = Journal::open(&path).expect("fresh");
        assert!(c.entries.is_empty() && c.problem.is_none());
        assert_eq!(std::fs::read(&path).expect("read"), file_header());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A journal without the header (bare entries, as older binaries wrote it) is refused;
    /// an empty file or a torn header (a crash while creating the journal) is a new journal.
    #[test]
    fn missing_header_is_refused_and_a_torn_one_restarts() {
        let (dir, path) = temp_journal("header");
        let bare = encode_entry(&keyframe(1));
        std::fs::write(&path, &bare).expect("write");
        let err = match Journal::open(&path) {
            Err(OpenError::Version(e)) => e,
            other => panic!("expected a version error, got {other:?}"),
        };
        assert_eq!(err.found, None);
        let text = err.to_string();
        assert!(text.contains("no journal header"), "{text}");
        assert!(text.contains(&path.display().to_string()), "{text}");
        assert_eq!(std::fs::read(&path).expect("read"), bare);
        for torn in [0, 5, FILE_HEAD - 1] {
            std::fs::write(&path, &file_header()[..torn]).expect("write");
            let (mut j, c) = Journal::open(&path).expect("a new journal");
            assert!(c.entries.is_empty() && c.problem.is_none());
            j.append(&keyframe(2)).expect("append");
            drop(j);
            let c = read_journal(&path).expect("read");
            assert_eq!(c.entries, vec![keyframe(2)]);
        }
        // Garbage shorter than a header is not taken for a torn one.
        std::fs::write(&path, b"abc").expect("write");
        assert!(matches!(
            Journal::open(&path),
            Err(OpenError::Version(VersionError { found: None, .. }))
        ));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
