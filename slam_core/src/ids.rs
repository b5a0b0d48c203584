//! Identifiers of clients, sessions, keyframes, map points and server maps: the bit packing
//! of every composite id in one place.
//!
//! | id | bits (high → low) | made by |
//! |---|---|---|
//! | [`SessionId`] (`u32`) | start 16 · VO session 16 | the tracker, per VO session of each start |
//! | [`ClientKeyframeId`] (`u64`) | 0 · start 12 · counter 28 (< 2^40) | the tracker's VO |
//! | [`ClientPointId`] (`u64`) | counter from 0; in a resumed session start 24 · counter 40 | the tracker's VO |
//! | [`KeyframeId`] (`u64`, server) | client 24 · client keyframe id 40 | the server |
//! | [`MapPointId`] (`u64`, server) | client 24 · counter 40 | the server, per client's handler |
//! | [`MapId`] (`u64`) | client 32 · index 32 | the server, per client |
//!
//! "Start" is the count of lives of the tracker process (1 for the first): a restarted
//! tracker opens new sessions and numbers its keyframes from a new range, so ids stay
//! unique per client across restarts. A visual-inertial tracker that resumes its killed
//! predecessor's session (issue 17) keeps that session's id, continues its keyframe
//! numbering (everything the predecessor sent is older than what it spooled) and numbers its
//! new map points from its own start's range ([`ClientPointId::first_of_start`]).
//!
//! On the wire and in the algorithm's maps the ids stay plain integers (`#[repr(C)]` shared
//! memory types, [`crate::vo::KfId`] / [`crate::vo::PointId`] keys); these types are
//! `#[repr(transparent)]` over them and convert with `from_raw` / `raw` (and `From`) at the
//! boundary. [`MapId`] is used as the type of server map ids throughout the server code.
use core::fmt;

/// `From` conversions between an id newtype and its raw integer (the wire and the journal
/// carry the raw value).
macro_rules! raw_conversions {
    ($id:ident, $raw:ty) => {
        impl From<$raw> for $id {
            fn from(v: $raw) -> Self {
                Self(v)
            }
        }

        impl From<$id> for $raw {
            fn from(v: $id) -> Self {
                v.0
            }
        }
    };
}

/// A client (agent, camera) index.
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ClientId(u32);

impl ClientId {
    /// Client `index`.
    pub const fn new(index: u32) -> Self {
        Self(index)
    }

    /// The index as on the wire.
    pub const fn raw(self) -> u32 {
        self.0
    }

    /// The index, for indexing per-client tables.
    pub const fn index(self) -> usize {
        self.0 as usize
    }
}

/// The bare index (file names such as `trajectory_c{client}.txt` print it so).
impl fmt::Display for ClientId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(&self.0, f)
    }
}

raw_conversions!(ClientId, u32);

/// Bits of the VO session counter in a [`SessionId`].
const SESSION_VO_BITS: u32 = 16;
/// Mask of the VO session counter in a [`SessionId`].
const SESSION_VO_MASK: u32 = (1 << SESSION_VO_BITS) - 1;

/// A client's VO session as on the wire (`MsgMeta::session_id`): the tracker start in the
/// high 16 bits, the VO's own session counter (from 1 in each start) in the low 16 (a
/// restarted tracker's sessions are new ones).
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SessionId(u32);

impl SessionId {
    /// VO session `vo_session` (its low 16 bits) of tracker start `start` (its low 16
    /// bits).
    pub const fn new(start: u32, vo_session: u32) -> Self {
        Self((start << SESSION_VO_BITS) | (vo_session & SESSION_VO_MASK))
    }

    /// A session id as on the wire.
    pub const fn from_raw(v: u32) -> Self {
        Self(v)
    }

    /// As on the wire.
    pub const fn raw(self) -> u32 {
        self.0
    }

    /// The tracker start.
    pub const fn start(self) -> u32 {
        self.0 >> SESSION_VO_BITS
    }

    /// The VO session within the start.
    pub const fn vo_session(self) -> u32 {
        self.0 & SESSION_VO_MASK
    }

    /// The same VO session of start `start + by` (a remote client's run on its server,
    /// `bridge::run_ids`); `None` when that start is not in 1..2^16.
    pub fn shift_start(self, by: i64) -> Option<Self> {
        let start = u32::try_from(i64::from(self.start()) + by).ok()?;
        (start > 0 && start <= SESSION_VO_MASK).then(|| Self::new(start, self.vo_session()))
    }
}

/// `s{start}.{vo_session}`.
impl fmt::Display for SessionId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "s{}.{}", self.start(), self.vo_session())
    }
}

raw_conversions!(SessionId, u32);

/// The first client id of loaded maps (the top half of the 24-bit client field of server
/// keyframe and point ids): a saved map's clients are renamed from it on when it is loaded
/// (`map_store::remap`), so that its ids never collide with the live run's; live clients
/// are numbered from 0 and never reach it.
pub const SAVED_CLIENT_BASE: u32 = 1 << 23;

/// Bits of the client's own keyframe id in a server [`KeyframeId`] (and of the counter in
/// a [`MapPointId`]).
const CLIENT_KF_BITS: u32 = 40;
/// Bits of the per-start counter in a [`ClientKeyframeId`].
const START_KF_BITS: u32 = 28;

/// A client's keyframe id (the VO's, on the wire as `KeyframeHeader::keyframe_id`): unique
/// per client across sessions and tracker restarts. Start `s` numbers its keyframes from
/// `s << 28` (2^28 keyframes per start, 4096 starts within [`ClientKeyframeId::MAX`]).
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ClientKeyframeId(u64);

impl ClientKeyframeId {
    /// Largest client keyframe id a server [`KeyframeId`] holds (40 bits).
    pub const MAX: u64 = (1 << CLIENT_KF_BITS) - 1;

    /// The first keyframe id of tracker start `start`.
    pub const fn first_of_start(start: u32) -> Self {
        Self((start as u64) << START_KF_BITS)
    }

    /// A client keyframe id as on the wire.
    pub const fn from_raw(v: u64) -> Self {
        Self(v)
    }

    /// As on the wire.
    pub const fn raw(self) -> u64 {
        self.0
    }

    /// The tracker start that made it.
    pub const fn start(self) -> u32 {
        (self.0 >> START_KF_BITS) as u32
    }

    /// The same keyframe of start `start + by` (a remote client's run on its server,
    /// `bridge::run_ids`); `None` when that start is not in 1..4096.
    pub fn shift_start(self, by: i64) -> Option<Self> {
        let start = u64::try_from(i64::from(self.start()) + by).ok()?;
        let counter = self.0 & ((1 << START_KF_BITS) - 1);
        let id = (start << START_KF_BITS) | counter;
        (start > 0 && id <= Self::MAX).then_some(Self(id))
    }

    /// Its number within the start.
    pub const fn counter(self) -> u64 {
        self.0 & ((1 << START_KF_BITS) - 1)
    }
}

/// `s{start}.k{counter}`.
impl fmt::Display for ClientKeyframeId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "s{}.k{}", self.start(), self.counter())
    }
}

raw_conversions!(ClientKeyframeId, u64);

/// A client's map-point id (the VO's, on the wire as `KeypointRecord::map_point_id`). The
/// server keys client points by session, so a new session numbers them from 0; a session
/// resumed by a restarted tracker numbers its new points from [`ClientPointId::first_of_start`]
/// of its own start: its predecessor may have sent points it never spooled, and every id a
/// start gives is below the next start's range (2^40 points per start).
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ClientPointId(u64);

impl ClientPointId {
    /// The first point id tracker start `start` gives in a resumed session.
    pub const fn first_of_start(start: u32) -> Self {
        Self((start as u64) << CLIENT_KF_BITS)
    }

    /// As on the wire.
    pub const fn raw(self) -> u64 {
        self.0
    }
}

raw_conversions!(ClientPointId, u64);

/// A server keyframe id: the client in the bits above 40, the client's own keyframe id
/// below; unique across clients, so that maps of several clients can be merged.
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct KeyframeId(u64);

impl KeyframeId {
    /// Client `client`'s keyframe `client_kf` (its low 40 bits, see
    /// [`ClientKeyframeId::MAX`]).
    pub const fn new(client: ClientId, client_kf: u64) -> Self {
        Self(((client.0 as u64) << CLIENT_KF_BITS) | (client_kf & ClientKeyframeId::MAX))
    }

    /// A server keyframe id as on the wire.
    pub const fn from_raw(v: u64) -> Self {
        Self(v)
    }

    /// As on the wire.
    pub const fn raw(self) -> u64 {
        self.0
    }

    /// The client that made the keyframe.
    pub const fn client(self) -> ClientId {
        ClientId((self.0 >> CLIENT_KF_BITS) as u32)
    }

    /// The client's own keyframe id.
    pub const fn client_kf(self) -> u64 {
        self.0 & ClientKeyframeId::MAX
    }
}

/// `c{client}.k{client keyframe id}`.
impl fmt::Display for KeyframeId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "c{}.k{}", self.client(), self.client_kf())
    }
}

raw_conversions!(KeyframeId, u64);

/// A server map-point id: the client whose handler created the point in the bits above 40,
/// that handler's counter below (a point keeps its id when maps merge).
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct MapPointId(u64);

impl MapPointId {
    /// The first point id of client `client`'s handler.
    pub const fn first_of_client(client: ClientId) -> Self {
        Self((client.0 as u64) << CLIENT_KF_BITS)
    }

    /// A server point id as on the wire.
    pub const fn from_raw(v: u64) -> Self {
        Self(v)
    }

    /// As on the wire.
    pub const fn raw(self) -> u64 {
        self.0
    }

    /// The client whose handler created the point.
    pub const fn client(self) -> ClientId {
        ClientId((self.0 >> CLIENT_KF_BITS) as u32)
    }

    /// Its number among that handler's points.
    pub const fn counter(self) -> u64 {
        self.0 & ((1 << CLIENT_KF_BITS) - 1)
    }
}

/// `c{client}.p{counter}`.
impl fmt::Display for MapPointId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "c{}.p{}", self.client(), self.counter())
    }
}

raw_conversions!(MapPointId, u64);

/// Bits of the per-client index in a [`MapId`].
const MAP_INDEX_BITS: u32 = 32;

/// A server map id: the client that created the map in the high 32 bits, which of its maps
/// it is (from 0) in the low 32. A map merged into another keeps its id in the poses
/// reported before the merge.
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct MapId(u64);

impl MapId {
    /// Client `client`'s `index`-th server map.
    pub const fn new(client: ClientId, index: u32) -> Self {
        Self(((client.0 as u64) << MAP_INDEX_BITS) | index as u64)
    }

    /// A map id as on the wire.
    pub const fn from_raw(v: u64) -> Self {
        Self(v)
    }

    /// As on the wire.
    pub const fn raw(self) -> u64 {
        self.0
    }

    /// The client that created the map.
    pub const fn client(self) -> ClientId {
        ClientId((self.0 >> MAP_INDEX_BITS) as u32)
    }

    /// Which of its client's maps it is.
    pub const fn index(self) -> u32 {
        self.0 as u32
    }
}

/// `c{client}.m{index}`.
impl fmt::Display for MapId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "c{}.m{}", self.client(), self.index())
    }
}

/// The raw id in hexadecimal (`{:#x}`: `0x100000000` is client 1's first map), as the
/// services' messages print map ids.
impl fmt::LowerHex for MapId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::LowerHex::fmt(&self.0, f)
    }
}

raw_conversions!(MapId, u64);

/// A feature track's id: the image front end's ([`crate::features::tracks`]) or a
/// calibration target corner's (`tag · 4 + corner`), as the calibration filter
/// ([`crate::calib`]) receives its observations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct TrackId(pub u64);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packings_round_trip() {
        let c = ClientId::new(3);
        let m = MapId::new(c, 7);
        assert_eq!(m.raw(), (3 << 32) | 7);
        assert_eq!((m.client(), m.index()), (c, 7));
        assert_eq!(format!("{m:#x}"), "0x300000007");
        assert_eq!(m.to_string(), "c3.m7");

        let s = SessionId::new(2, 5);
        assert_eq!(s.raw(), 0x0002_0005);
        assert_eq!((s.start(), s.vo_session()), (2, 5));
        assert_eq!(SessionId::new(1, 0x1_0003).vo_session(), 3);

        let first = ClientKeyframeId::first_of_start(3);
        assert_eq!(first.raw(), 3 << 28);
        let k = ClientKeyframeId::from_raw(first.raw() + 9);
        assert_eq!((k.start(), k.counter()), (3, 9));

        let s = KeyframeId::new(c, k.raw());
        assert_eq!(s.raw(), (3 << 40) | k.raw());
        assert_eq!((s.client(), s.client_kf()), (c, k.raw()));
        assert_eq!(KeyframeId::new(c, u64::MAX).client(), c);
        assert_eq!(s.to_string(), format!("c3.k{}", k.raw()));

        let p = MapPointId::first_of_client(c);
        assert_eq!(p.raw(), 3 << 40);
        let p = MapPointId::from_raw(p.raw() + 11);
        assert_eq!((p.client(), p.counter()), (c, 11));
        assert_eq!(u64::from(p), p.raw());
    }

    #[test]
    fn ordering_is_that_of_the_raw_ids() {
        let a = MapId::new(ClientId::new(0), 5);
        let b = MapId::new(ClientId::new(1), 0);
        assert!(a < b && a.raw() < b.raw());
        let a = KeyframeId::new(ClientId::new(1), 5);
        let b = KeyframeId::new(ClientId::new(1), 6);
        assert!(a < b);
    }

    #[test]
    fn starts_shift_and_keep_the_rest() {
        let s = SessionId::new(2, 7).shift_start(5).unwrap();
        assert_eq!((s.start(), s.vo_session()), (7, 7));
        assert_eq!(s.shift_start(-5), Some(SessionId::new(2, 7)));
        assert_eq!(
            SessionId::new(2, 7).shift_start(-2),
            None,
            "start 0 is no start"
        );
        assert_eq!(SessionId::new(0xFFFF, 1).shift_start(1), None);
        let k = ClientKeyframeId::from_raw(ClientKeyframeId::first_of_start(3).raw() + 9);
        let moved = k.shift_start(10).unwrap();
        assert_eq!((moved.start(), moved.counter()), (13, 9));
        assert_eq!(moved.shift_start(-10), Some(k));
        assert_eq!(k.shift_start(-3), None);
        assert_eq!(k.shift_start(4093), None, "beyond 4096 starts");
        assert_eq!(k.shift_start(4092).unwrap().start(), 4095);
    }
}
