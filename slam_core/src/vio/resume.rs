//! A visual-inertial session resumed from stored keyframes (issue 17: the successor of a
//! SIGKILLed tracker continues its predecessor's session instead of initialising again).
//!
//! The VO is given the session's map, rebuilt from the store ([`crate::vo::restore_map`],
//! [`VoTracker::resume_session`]): metric and gravity-aligned, as the predecessor's
//! initialisation left it. [`VioTracker::resume`] then starts the client as initialised:
//! - the coupler runs no initialisation; the refinements the predecessor had not done yet
//!   run over the successor's own keyframes ([`InertialCoupler::mark_resumed`]: the first
//!   once they span 5 s; a refinement moves the whole session's world, the predecessor's
//!   poses included, as any refinement does);
//! - the navigator starts at the newest keyframe's stored state (its pose, velocity and
//!   biases, at its time), as if the client had coasted since then: when the IMU covers
//!   the gap the first frame is predicted and searched around its prediction (the rejoin
//!   window of a dropout), else vision relocalises it against the map and the navigator
//!   re-anchors there ([`Navigator::reset_to`]), keeping the stored velocity with its
//!   uncertainty grown by [`super::NavParams::unmodelled_accel`] times the gap, so the
//!   first visual positions correct it (over a long gap they decide it);
//! - the stored biases are the client's biases from then on (keyframes carry them on).
//!
//! [`VioStatus::Resumed`] says so until the session ends (a new VO session initialises
//! afresh); [`Resumed::anchored_t_ns`] is the first frame vision posed.
//!
//! [`InertialCoupler::mark_resumed`]: crate::imu::coupler::InertialCoupler::mark_resumed
use nalgebra::Isometry3;

use super::{navigator, Navigator, VioParams, VioStatus, VioTracker};
use crate::vo::{KeyframeInertial, KfId, VoTracker};
use crate::CoreError;

/// Where a resumed session started ([`VioStatus::Resumed`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resumed {
    /// The stored keyframe whose inertial state the client started from (the newest).
    pub keyframe_id: KfId,
    /// Its time, IMU clock, ns.
    pub keyframe_t_ns: i64,
    /// IMU time of the first frame vision posed after the resume, once there is one.
    pub anchored_t_ns: Option<i64>,
    /// Refinements of the initialisation: the predecessor's and this client's since.
    pub refinements: usize,
}

impl VioTracker {
    /// A client continuing the session `vo` holds (a map rebuilt from a store and taken
    /// with [`VoTracker::resume_session`]; module docs), whose initialisation was refined
    /// `refinements_done` times (2 or more: no refinement runs). Refused when the map's
    /// newest keyframe has no inertial state (the session was not initialised inertially).
    pub fn resume(
        vo: VoTracker,
        params: VioParams,
        refinements_done: usize,
    ) -> Result<Self, CoreError> {
        let newest = vo.with_map(|m| {
            m.keyframes
                .values()
                .next_back()
                .map(|kf| (kf.id, kf.t_ns, kf.t_cw, kf.inertial))
        });
        let Some((id, t_cam_ns, t_cw, inertial)) = newest else {
            return Err(CoreError::Resume("the VO holds no keyframe".into()));
        };
        let Some(inertial) = inertial else {
            return Err(CoreError::Resume(format!(
                "keyframe {id}, the newest, has no inertial state: the session was not initialised inertially"
            )));
        };
        let mut v = Self::new(vo, params);
        v.start_resumed(id, t_cam_ns + params.coupler.t_d_ns, &t_cw, inertial);
        v.coupler.mark_resumed(refinements_done);
        if let Some(r) = v.resumed.as_mut() {
            r.refinements = refinements_done.min(2);
        }
        Ok(v)
    }

    /// The client's state at stored keyframe `id` (IMU time `t_ns`, pose `t_cw`).
    fn start_resumed(
        &mut self,
        id: KfId,
        t_ns: i64,
        t_cw: &Isometry3<f64>,
        inertial: KeyframeInertial,
    ) {
        let p = self.params;
        self.biases = inertial.biases;
        let state = navigator::nav_from_camera(t_cw, &p.t_bc, inertial.v_wb, inertial.biases);
        self.nav = Some(Navigator::new(state, t_ns, p.t_bc, p.preint, p.nav));
        self.orientation = Some((t_ns, state.r));
        self.last_visual_ns = Some(t_ns);
        // As after a dropout: the first frame is searched around the IMU's prediction.
        self.coasting = true;
        self.resumed = Some(Resumed {
            keyframe_id: id,
            keyframe_t_ns: t_ns,
            anchored_t_ns: None,
            refinements: 0,
        });
    }

    /// The session was resumed, and from where (`None` for a session this client
    /// initialised itself).
    pub fn resumed(&self) -> Option<&Resumed> {
        self.resumed.as_ref()
    }

    /// Vision posed the frame at IMU time `t_ns`: the first such frame of a resumed session
    /// is where it re-anchored.
    pub(super) fn note_visual_pose(&mut self, t_ns: i64) {
        if let Some(r) = self.resumed.as_mut() {
            r.anchored_t_ns.get_or_insert(t_ns);
        }
    }

    /// A refinement of a resumed session's initialisation was applied: `true` (counted),
    /// `false` when the session was not resumed.
    pub(super) fn note_resumed_refinement(&mut self) -> bool {
        self.resumed.as_mut().map(|r| r.refinements += 1).is_some()
    }

    /// The status of a resumed session, if this is one.
    pub(super) fn resumed_status(&self) -> Option<VioStatus> {
        self.resumed.map(|r| VioStatus::Resumed {
            from: r,
            coasting: self.coasting,
        })
    }
}

#[cfg(test)]
mod tests;
