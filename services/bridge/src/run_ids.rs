//! A remote client's runs on one server (issue 22). Every run of a client numbers its
//! tracker starts from 1, so its sessions and keyframe ids repeat those of its earlier runs
//! ([`slam_core::ids`]), and the server's mapper would take a new run's keyframes for
//! re-sends of the old ones (acknowledged, never applied). So the server gives each run of a
//! name (the launcher's run id, in the hello) a **start base** past every start it has seen
//! of that name ([`crate::slots`]), the same across the run's reconnects and the server's
//! restarts, and the client's bridge adds it to the tracker start in every session and
//! keyframe id it sends, and takes it off those of the feedback it receives. The tracker and
//! the mapper never see the other's numbering; the first run's base is 0 (no change).
use shm_schema::{Feedback, KeyframeHeader};
use slam_core::ids::{ClientKeyframeId, SessionId};

/// A keyframe's ids as the server numbers them (start + `base`), or why they cannot be.
pub fn keyframe_to_server(h: &mut KeyframeHeader, base: u32) -> Result<(), String> {
    let by = i64::from(base);
    let session = SessionId::from_raw(h.meta.session_id);
    let kf = ClientKeyframeId::from_raw(h.keyframe_id);
    match (session.shift_start(by), kf.shift_start(by)) {
        (Some(s), Some(k)) => {
            h.meta.session_id = s.raw();
            h.keyframe_id = k.raw();
            Ok(())
        }
        _ => Err(format!(
            "keyframe {} of session {session} is beyond the ids this server has left for \
             this client's runs (start base {base}): give the client a new name",
            h.keyframe_id
        )),
    }
}

/// A feedback's ids as the client numbers them (start − `base`); `false` when they belong
/// to another run of the client (below its base), which the tracker must not see. An id 0
/// (none) stays 0.
pub fn feedback_from_server(f: &mut Feedback, base: u32) -> bool {
    let by = -i64::from(base);
    let session = |raw: u32| match raw {
        0 => Some(0),
        r => SessionId::from_raw(r).shift_start(by).map(SessionId::raw),
    };
    let kf = match f.acked_keyframe_id {
        0 => Some(0),
        k => ClientKeyframeId::from_raw(k)
            .shift_start(by)
            .map(ClientKeyframeId::raw),
    };
    match (session(f.meta.session_id), session(f.acked_session_id), kf) {
        (Some(s), Some(a), Some(k)) => {
            (f.meta.session_id, f.acked_session_id, f.acked_keyframe_id) = (s, a, k);
            true
        }
        _ => false,
    }
}

/// The server's start of a keyframe it received (the newest start its ids may carry).
pub fn server_start(h: &KeyframeHeader) -> u32 {
    ClientKeyframeId::from_raw(h.keyframe_id)
        .start()
        .max(SessionId::from_raw(h.meta.session_id).start())
}

#[cfg(test)]
mod tests {
    use super::*;
    use shm_schema::MsgMeta;

    /// A keyframe's ids go out shifted by the base, its acknowledgement comes back as the
    /// tracker numbered it; feedback of an earlier run (below the base) is kept from it.
    #[test]
    fn ids_cross_shifted_and_come_back() {
        let session = SessionId::new(1, 2).raw();
        let kf = ClientKeyframeId::first_of_start(1).raw() + 5;
        let mut h = KeyframeHeader {
            meta: MsgMeta::new(0, session, 1, 0),
            keyframe_id: kf,
            ..Default::default()
        };
        keyframe_to_server(&mut h, 3).unwrap();
        assert_eq!(SessionId::from_raw(h.meta.session_id), SessionId::new(4, 2));
        assert_eq!(h.keyframe_id, ClientKeyframeId::first_of_start(4).raw() + 5);
        assert_eq!(server_start(&h), 4);
        let mut f = Feedback {
            meta: MsgMeta::new(0, h.meta.session_id, 1, 0),
            acked_keyframe_id: h.keyframe_id,
            acked_session_id: h.meta.session_id,
            ..Default::default()
        };
        assert!(feedback_from_server(&mut f, 3));
        assert_eq!((f.meta.session_id, f.acked_session_id), (session, session));
        assert_eq!(f.acked_keyframe_id, kf);
        // The same feedback reaching a later run (base 4): not its own.
        let mut old = f;
        assert!(!feedback_from_server(&mut old, 4));
        let mut none = Feedback::default();
        assert!(feedback_from_server(&mut none, 3), "ids 0 stay 0");
        let mut h = KeyframeHeader {
            meta: MsgMeta::new(0, session, 1, 0),
            keyframe_id: kf,
            ..Default::default()
        };
        let err = keyframe_to_server(&mut h, 4095).unwrap_err();
        assert!(err.contains("new name"), "{err}");
    }
}
