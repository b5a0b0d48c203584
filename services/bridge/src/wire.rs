//! What crosses the network (issue 22): zenoh key expressions and payloads.
//!
//! - `shoal/hello` (the server's queryable): a client asks for its slot with its name and
//!   schema version ([`hello`]); the server answers with the slot, the same for the same
//!   name across reconnects and server restarts, or a refusal with its reason ([`Welcome`]).
//! - `shoal/kf/{name}`: a keyframe message, client → server, as one journal entry
//!   ([`shoal_runtime::journal::encode_entry`]: framed and checksummed, the mapper journal's
//!   and the tracker spool's own encoding).
//! - `shoal/fb/{name}`: the mapper's acknowledgement and pose feedback, server → client
//!   ([`encode_feedback`], little-endian, with the schema version).
//!
//! Times: a message's `publish_mono_ns` is on the monotonic clock of the host that sent
//! it, which means nothing on the other; each bridge stamps what it publishes into its
//! host's shared memory with its own clock.
//!
//! Nothing here acknowledges: the end-to-end acknowledgement is the mapper's feedback, and a
//! keyframe it has not acknowledged is sent again by the tracker (`RESEND_AFTER_NS`), so a
//! keyframe lost on the way (a cut connection, a restarted server) comes again.
use shm_schema::{
    Feedback, ImuRecord, KeyframeHeader, KeyframeRecord, KeypointRecord, MsgMeta, Pose,
    SCHEMA_VERSION,
};
use shoal_runtime::journal::{encode_entry, parse, Entry};

/// The server's queryable of slots.
pub const HELLO_KEY: &str = "shoal/hello";

/// Key of client `name`'s keyframes (by name, not slot: with `--auth` the server's access
/// control lets a client publish only under its own name, [`crate::auth`]).
pub fn keyframe_key(name: &str) -> String {
    format!("{KEYFRAMES}/{name}")
}

/// Key of client `name`'s feedback.
pub fn feedback_key(name: &str) -> String {
    format!("{FEEDBACK}/{name}")
}

/// Prefix of the keyframe keys.
pub const KEYFRAMES: &str = "shoal/kf";

/// Prefix of the feedback keys.
pub const FEEDBACK: &str = "shoal/fb";

/// Every client's keyframes (the server's subscription).
pub const ALL_KEYFRAMES: &str = "shoal/kf/*";

/// The client name of a keyframe or feedback key.
pub fn name_of(key: &str) -> Option<&str> {
    let name = key.rsplit_once('/')?.1;
    valid_name(name).then_some(name)
}

/// A client name: non-empty, one key-expression chunk (no `/`, wildcards or verbatim
/// markers), no spaces (the slot table is `SLOT NAME` lines) and no `:` (the credentials
/// file is `NAME:PASSWORD` lines).
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && !name.contains(['/', '*', '$', '#', '?', ':', '@'])
        && !name.chars().any(char::is_whitespace)
}

/// A client's request for a slot: `shoal-hello {schema version} {name} {run}` (`run`: the
/// launcher's id of this run of the client, [`crate::run_ids`]).
pub fn hello(name: &str, run: u64) -> Vec<u8> {
    format!("shoal-hello {SCHEMA_VERSION} {name} {run}").into_bytes()
}

/// What a client says in its hello.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Hello {
    pub version: u32,
    pub name: String,
    pub run: u64,
}

/// A hello's schema version, name and run, or why it is not one.
pub fn parse_hello(bytes: &[u8]) -> Result<Hello, String> {
    let text = std::str::from_utf8(bytes).map_err(|_| "a hello that is not text".to_string())?;
    let parts: Vec<&str> = text.split(' ').collect();
    let ["shoal-hello", v, rest @ ..] = parts.as_slice() else {
        return Err(format!("not a shoal hello: {text:?}"));
    };
    let version = v
        .parse()
        .map_err(|_| format!("bad schema version in {text:?}"))?;
    // The schema version first: another version's hello may be laid out otherwise.
    if version != SCHEMA_VERSION {
        return Ok(Hello {
            version,
            name: rest.first().unwrap_or(&"").to_string(),
            run: 0,
        });
    }
    let [name, run] = rest else {
        return Err(format!("expected `shoal-hello VERSION NAME RUN`: {text:?}"));
    };
    if !valid_name(name) {
        return Err(format!("bad client name {name:?}"));
    }
    let run = run.parse().map_err(|_| format!("bad run id in {text:?}"))?;
    Ok(Hello {
        version,
        name: name.to_string(),
        run,
    })
}

/// The server's answer to a hello.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Welcome {
    /// The client's slot, and its run's start base ([`crate::run_ids`]).
    Slot { slot: u32, start_base: u32 },
    /// Refused, and why.
    Refused(String),
}

impl Welcome {
    /// Its payload.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Self::Slot { slot, start_base } => format!("slot {slot} {start_base}").into_bytes(),
            Self::Refused(why) => format!("refused {why}").into_bytes(),
        }
    }

    /// From a payload.
    pub fn decode(bytes: &[u8]) -> Result<Self, String> {
        let text = String::from_utf8_lossy(bytes);
        if let Some(s) = text.strip_prefix("slot ") {
            let mut n = s.split(' ').map(str::parse::<u32>);
            return match (n.next(), n.next(), n.next()) {
                (Some(Ok(slot)), Some(Ok(start_base)), None) => Ok(Self::Slot { slot, start_base }),
                _ => Err(format!("bad slot {s:?}")),
            };
        }
        match text.strip_prefix("refused ") {
            Some(why) => Ok(Self::Refused(why.to_string())),
            None => Err(format!("not a shoal welcome: {text:?}")),
        }
    }
}

/// A keyframe message as a journal entry (its client index as given).
pub fn encode_keyframe(h: &KeyframeHeader, payload: &[KeyframeRecord]) -> Result<Vec<u8>, String> {
    let records = h.keypoints(payload).map_err(|e| e.to_string())?.to_vec();
    let imu = h.imu_records(payload).map_err(|e| e.to_string())?.to_vec();
    Ok(encode_entry(&Entry::Keyframe {
        client: h.meta.client_id,
        header: Box::new(*h),
        records,
        imu,
    }))
}

/// A keyframe message back from its entry: header, keypoints, IMU records.
pub type KeyframeParts = (KeyframeHeader, Vec<KeypointRecord>, Vec<ImuRecord>);

/// Decodes a keyframe entry; an error says why it is not one (torn, corrupt, another
/// entry, another schema).
pub fn decode_keyframe(bytes: &[u8]) -> Result<KeyframeParts, String> {
    let c = parse(bytes);
    if let Some(p) = c.problem {
        return Err(p);
    }
    match c.entries.into_iter().next() {
        Some(Entry::Keyframe {
            header,
            records,
            imu,
            ..
        }) => {
            header.meta.check().map_err(|e| e.to_string())?;
            Ok((*header, records, imu))
        }
        _ => Err("not a keyframe entry".into()),
    }
}

/// Bytes of an encoded [`Feedback`].
pub const FEEDBACK_BYTES: usize = 4 + 8 * 3 + 4 * 2 + 8 * 7 + 8 + 8 + 4 * 4 + 8 + 8;

/// A feedback message, little-endian: schema version, then every field.
pub fn encode_feedback(f: &Feedback) -> Vec<u8> {
    let mut b = Vec::with_capacity(FEEDBACK_BYTES);
    b.extend(SCHEMA_VERSION.to_le_bytes());
    let m = &f.meta;
    for v in [m.seq, m.publish_mono_ns as u64, f.acked_keyframe_id] {
        b.extend(v.to_le_bytes());
    }
    b.extend(m.session_id.to_le_bytes());
    b.extend(m.flags.to_le_bytes());
    for v in f.server_pose.q.iter().chain(&f.server_pose.t) {
        b.extend(v.to_le_bytes());
    }
    b.extend(f.scale_ratio.to_le_bytes());
    b.extend(f.server_map_id.to_le_bytes());
    for v in [m.client_id, f.acked_session_id, f.has_pose, 0] {
        b.extend(v.to_le_bytes());
    }
    b.extend(0u64.to_le_bytes());
    b.extend(0u64.to_le_bytes());
    b
}

/// A feedback message for client `client` from its encoding.
pub fn decode_feedback(b: &[u8], client: u32) -> Result<Feedback, String> {
    if b.len() != FEEDBACK_BYTES {
        return Err(format!(
            "feedback of {} bytes, expected {FEEDBACK_BYTES}",
            b.len()
        ));
    }
    let u32_at = |i: usize| u32::from_le_bytes(b[i..i + 4].try_into().unwrap());
    let u64_at = |i: usize| u64::from_le_bytes(b[i..i + 8].try_into().unwrap());
    let f64_at = |i: usize| f64::from_le_bytes(b[i..i + 8].try_into().unwrap());
    let version = u32_at(0);
    if version != SCHEMA_VERSION {
        return Err(format!(
            "feedback of schema version {version}, this client speaks {SCHEMA_VERSION}"
        ));
    }
    let mut meta = MsgMeta::new(client, u32_at(28), u64_at(4), u64_at(12) as i64);
    meta.flags = u32_at(32);
    let q = [f64_at(36), f64_at(44), f64_at(52), f64_at(60)];
    let t = [f64_at(68), f64_at(76), f64_at(84)];
    Ok(Feedback {
        meta,
        acked_keyframe_id: u64_at(20),
        server_pose: Pose { q, t },
        scale_ratio: f64_at(92),
        server_map_id: u64_at(100),
        acked_session_id: u32_at(112),
        has_pose: u32_at(116),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A feedback crosses unchanged but for the client index, which the receiver sets.
    #[test]
    fn feedback_round_trip() {
        let mut meta = MsgMeta::new(3, 7, 42, 123_456);
        meta.flags = shm_schema::FLAG_HANDLED;
        let f = Feedback {
            meta,
            acked_keyframe_id: 99,
            acked_session_id: 7,
            has_pose: 1,
            server_pose: Pose {
                q: [0.5, 0.5, 0.5, 0.5],
                t: [1.0, -2.0, 3.5],
            },
            scale_ratio: 1.25,
            server_map_id: 5,
        };
        let b = encode_feedback(&f);
        assert_eq!(b.len(), FEEDBACK_BYTES);
        let back = decode_feedback(&b, 0).unwrap();
        let mut want = f;
        want.meta.client_id = 0;
        assert_eq!(back, want);
        let mut other = b.clone();
        other[0] ^= 1;
        assert!(decode_feedback(&other, 0)
            .unwrap_err()
            .contains("schema version"));
        assert!(decode_feedback(&b[1..], 0).is_err());
    }

    /// A keyframe crosses whole; a damaged one is refused, never read as another.
    #[test]
    fn keyframe_round_trip_and_damage() {
        let mut h = KeyframeHeader {
            meta: MsgMeta::new(1, 2, 3, 4),
            keyframe_id: 17,
            n_keypoints: 2,
            n_imu: 1,
            ..KeyframeHeader::default()
        };
        h.t_ns = 1_000;
        let kp = KeypointRecord {
            u: 10.0,
            v: 20.0,
            map_point_id: 5,
            ..KeypointRecord::default()
        };
        let imu = ImuRecord::default();
        let payload = [kp.into(), kp.into(), imu.into()];
        let b = encode_keyframe(&h, &payload).unwrap();
        let (h2, k2, i2) = decode_keyframe(&b).unwrap();
        assert_eq!((h2, k2, i2), (h, vec![kp, kp], vec![imu]));
        // A flipped byte is refused, or (in the entry head's unused bits) changes nothing.
        let mut refused = 0;
        for i in 0..b.len() {
            let mut bad = b.clone();
            bad[i] ^= 0x40;
            match decode_keyframe(&bad) {
                Err(_) => refused += 1,
                Ok(back) => assert_eq!(back, (h, vec![kp, kp], vec![imu]), "byte {i} flipped"),
            }
        }
        assert!(refused >= b.len() - 3, "{refused} of {} refused", b.len());
        assert!(decode_keyframe(&b[..b.len() - 1]).is_err());
    }

    #[test]
    fn hello_and_welcome() {
        let h = parse_hello(&hello("phone-1", 77)).unwrap();
        assert_eq!(
            (h.version, h.name.as_str(), h.run),
            (SCHEMA_VERSION, "phone-1", 77)
        );
        assert!(parse_hello(b"shoal-hello 4 a/b 1").is_err());
        assert!(parse_hello(b"shoal-hello 4 phone").is_err(), "no run id");
        assert!(parse_hello(b"hello").is_err());
        // Another schema version is read only as far as its version and name (the refusal
        // names them).
        let old = parse_hello(b"shoal-hello 3 phone").unwrap();
        assert_eq!((old.version, old.name.as_str()), (3, "phone"));
        let slot = Welcome::Slot {
            slot: 3,
            start_base: 5,
        };
        for w in [slot, Welcome::Refused("full".into())] {
            assert_eq!(Welcome::decode(&w.encode()).unwrap(), w);
        }
        assert_eq!(name_of(&keyframe_key("phone-1")), Some("phone-1"));
        assert_eq!(name_of("shoal/kf/a b"), None);
        assert!(parse_hello(b"shoal-hello 4 a:b 1").is_err());
    }
}
