//! A fresh VO continues a session rebuilt from stored keyframes ([`crate::vo::resume`];
//! issue 17, a SIGKILLed tracker's successor): the map becomes this VO's, its keyframe ids
//! continue the session's, and the VO starts lost next to its newest keyframe, so the next
//! frames are tracked by the usual fallbacks of a lost frame (`track.rs`): the search
//! around an outside prediction when there is one ([`super::PoseHint::rejoin_radius`]),
//! the newest keyframe's points matched by descriptors from its pose, then relocalisation
//! over the whole map (`reloc.rs`). A session that stays lost for
//! [`super::VoParams::max_failures`] frames ends as any other (its keyframes evicted to be
//! sent, a new session started).
use super::{lock, LastFrame, VoState, VoTracker};
use crate::vo::map::ClientMap;
use crate::CoreError;

impl VoTracker {
    /// Takes `map` as this VO's session (see the module docs); to be called on a fresh VO,
    /// before its first frame. Its keyframe ids continue after the map's newest (a session
    /// numbers its keyframes in one run, so the server sees them in order); its point ids
    /// continue from the map's counter ([`ClientMap::new`], [`crate::vo::restore_map`]).
    /// Refused when the VO has a map or state already, or `map` has no keyframe.
    pub fn resume_session(&mut self, mut map: ClientMap) -> Result<(), CoreError> {
        if self.state != VoState::NotInitialized || self.last.is_some() || self.init.is_some() {
            return Err(CoreError::Resume("the VO has seen frames already".into()));
        }
        let Some(kf) = map.keyframes.values().next_back() else {
            return Err(CoreError::Resume("the map has no keyframe".into()));
        };
        let newest = kf.id;
        let last = LastFrame {
            t_ns: kf.t_ns,
            t_cw: kf.t_cw,
            features: kf.features.clone(),
            points: kf.points.clone(),
        };
        map.session_id = self.session_id;
        {
            let mut shared = lock(&self.shared);
            if !shared.keyframes.is_empty() {
                return Err(CoreError::Resume("the VO has a map already".into()));
            }
            *shared = map;
        }
        self.next_kf_id = newest + 1;
        self.state = VoState::Lost;
        self.ref_kf = Some(newest);
        self.last = Some(last);
        self.velocity = None;
        self.failures = 0;
        self.frames_since_kf = 0;
        self.reloc_cursor = None;
        Ok(())
    }

    /// Takes `map`, a map of another run made of prior keyframes
    /// ([`crate::vo::prior_client_map`]), as this VO's session: the VO starts lost in it as
    /// after [`VoTracker::resume_session`], but its keyframe ids stay its own (set by
    /// [`VoTracker::start_keyframe_ids_at`], after the map's), and it stays lost, trying to
    /// relocalise every frame, until a frame is posed: a prior that has not matched yet is no
    /// reason to start a new session. From the first pose on, a loss counts as usual.
    pub fn start_in_prior_map(&mut self, map: ClientMap) -> Result<(), CoreError> {
        let own = self.next_kf_id;
        if map.keyframes.keys().any(|&k| k >= own) {
            return Err(CoreError::Resume(format!(
                "a prior keyframe id is not below the VO's own ({own})"
            )));
        }
        self.resume_session(map)?;
        self.next_kf_id = own;
        self.awaiting_prior = true;
        Ok(())
    }

    /// Whether the VO is in a prior map and has not posed a frame in it yet
    /// ([`VoTracker::start_in_prior_map`]).
    pub fn awaiting_prior(&self) -> bool {
        self.awaiting_prior
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Vector3};

    use super::*;
    use crate::camera::PinholeRadtan;
    use crate::features::OrbFeatures;
    use crate::vo::{Keyframe, VoParams};

    fn keyframe(id: u64, x: f64) -> Keyframe {
        Keyframe {
            id,
            t_ns: id as i64 * 1000,
            t_cw: Isometry3::translation(-x, 0.0, 0.0),
            camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
            readout_ns: 0,
            features: OrbFeatures::default(),
            points: vec![],
            inertial: None,
            imu: None,
        }
    }

    /// A resumed VO is lost next to the map's newest keyframe, in the VO's session, and
    /// numbers its keyframes after it; a second resume, or one on an empty map, is refused.
    #[test]
    fn a_resumed_vo_starts_lost_at_the_newest_keyframe() {
        let cam = PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0);
        let mut vo = VoTracker::new(VoParams::default(), cam).expect("vo");
        vo.start_keyframe_ids_at(2 << 28);
        assert!(matches!(
            vo.resume_session(ClientMap::new(9, 0)),
            Err(CoreError::Resume(_))
        ));
        let mut map = ClientMap::new(9, 1 << 40);
        map.insert_keyframe(keyframe(41, 0.0));
        map.insert_keyframe(keyframe(44, 0.5));
        vo.resume_session(map).expect("resumed");
        assert_eq!(vo.state(), VoState::Lost);
        assert_eq!(vo.frames_failed(), 0);
        assert_eq!(vo.with_map(|m| (m.session_id, m.keyframes.len())), (1, 2));
        assert_eq!(vo.next_kf_id, 45, "the session's numbering continues");
        assert_eq!(vo.ref_kf, Some(44));
        let last = vo.last.as_ref().expect("last frame");
        assert_eq!(last.t_cw.translation.vector, Vector3::new(-0.5, 0.0, 0.0));
        let mut again = ClientMap::new(9, 0);
        again.insert_keyframe(keyframe(50, 1.0));
        assert!(vo.resume_session(again).is_err());
    }
}
