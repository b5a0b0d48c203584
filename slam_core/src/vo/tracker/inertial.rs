//! What the VO does for a visual-inertial client ([`crate::vio`]): the IMU samples cut into
//! each keyframe's segment ([`crate::vo::keyframe_imu`]), and the report of the newest
//! keyframe local mapping finished ([`super::VoOutput::mapped`]).
use super::{MappedKeyframe, VoTracker};
use crate::imu::ImuMeasurement;
use crate::vo::keyframe_imu::{ImuCalibration, KeyframeImu, KeyframeImuSource};

impl VoTracker {
    /// From now on every keyframe carries the IMU samples since the previous keyframe of
    /// its session ([`crate::vo::Keyframe::imu`]), given with [`VoTracker::push_imu`]; local
    /// mapping then runs the visual-inertial window on keyframes with an inertial state.
    /// On a VO that continues a session ([`VoTracker::resume_session`]) the next keyframe's
    /// segment starts at the map's newest keyframe, as it would have in the session's
    /// first process: the session's keyframes stay linked across the restart.
    pub fn enable_keyframe_imu(&mut self, calib: ImuCalibration) {
        let mut source = KeyframeImuSource::new(calib);
        if let Some(t_ns) = self.with_map(|m| m.keyframes.values().next_back().map(|k| k.t_ns)) {
            source.continue_after(t_ns);
        }
        self.imu_source = Some(source);
    }

    /// One IMU sample, in time order (checked by the caller; a sample not after the last
    /// one is ignored). Nothing without [`VoTracker::enable_keyframe_imu`].
    pub fn push_imu(&mut self, m: ImuMeasurement) {
        if let Some(s) = self.imu_source.as_mut() {
            s.push(m);
        }
    }

    /// The IMU segment of a keyframe made now at camera time `t_ns` (keyframes are made in
    /// time order).
    pub(super) fn keyframe_imu(&mut self, t_ns: i64) -> Option<KeyframeImu> {
        self.imu_source.as_mut().map(|s| s.segment(t_ns))
    }

    /// The newest keyframe made by an earlier frame, once local mapping has finished it
    /// (inline: at once; a runner: when idle, which a synchronised run waits for), so that
    /// inline and threaded mapping report it with the same frame.
    pub(super) fn report_mapped_keyframe(&mut self) -> Option<MappedKeyframe> {
        let id = self.unreported_kf?;
        if !self.mapping.as_ref().is_none_or(|m| m.idle()) {
            return None;
        }
        self.unreported_kf = None;
        let kf = self.map.keyframes.get(&id)?;
        Some(MappedKeyframe {
            id,
            t_ns: kf.t_ns,
            t_cw: kf.t_cw,
            inertial: kf.inertial,
        })
    }
}
