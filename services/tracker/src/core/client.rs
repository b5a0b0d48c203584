//! The client the tracker runs (`tracker.mode`, issue 17): the monocular VO of seed ch. 3,
//! or the visual-inertial client of ch. 5 around it ([`slam_core::vio::VioTracker`]), and
//! what a frame gave, whichever it is ([`ClientOutput`]). The visual-inertial client also
//! reports its state ([`VioReport`]), including why it is disabled (no camera-IMU
//! extrinsics, a calibration it cannot use) or not initialised yet.
use nalgebra::{Isometry3, UnitQuaternion};
use shm_schema::PoseSource;
use slam_core::imu::ImuMeasurement;
use slam_core::vio::{ImuSampleError, VioStatus, VioTracker, WorldMove};
use slam_core::vo::{VoFrame, VoOutput, VoState, VoTracker};

use super::{StaticReport, VioReport};

/// The monocular VO, or the visual-inertial client around it.
pub enum Client {
    /// Monocular (seed ch. 3).
    Mono(Box<VoTracker>),
    /// Visual-inertial (seed ch. 5).
    Vio(Box<VioTracker>),
}

/// What one frame gave.
pub struct ClientOutput {
    /// The VO's output (keyframes evicted, backfilled poses, stage times); every pose in it
    /// is in the world after [`ClientOutput::world_move`].
    pub vo: VoOutput,
    /// The frame's pose, world to camera (vision's, or the IMU's through a dropout).
    pub t_cw: Option<Isometry3<f64>>,
    /// Where it came from.
    pub source: PoseSource,
    /// The camera orientation `R_wc` when only that is known.
    pub r_wc: Option<UnitQuaternion<f64>>,
    /// The world of the VO session moved with this frame (before its poses).
    pub world_move: Option<WorldMove>,
    /// The client's world was anchored to the server map by this rigid move before the
    /// frame ([`VioTracker::request_anchor`]).
    pub anchor: Option<Isometry3<f64>>,
    /// The poses are metric and gravity-aligned (initialised inertially).
    pub metric: bool,
    /// The metric body state (pose, velocity, biases) once initialised.
    pub nav: Option<slam_core::imu::NavState>,
}

impl Client {
    /// The VO.
    pub fn vo(&self) -> &VoTracker {
        match self {
            Self::Mono(v) => v,
            Self::Vio(v) => v.vo(),
        }
    }

    /// The VO, mutable.
    pub fn vo_mut(&mut self) -> &mut VoTracker {
        match self {
            Self::Mono(v) => v,
            Self::Vio(v) => v.vo_mut(),
        }
    }

    /// The visual-inertial client, if this is one.
    pub fn vio(&self) -> Option<&VioTracker> {
        match self {
            Self::Mono(_) => None,
            Self::Vio(v) => Some(v),
        }
    }

    /// One IMU sample (the visual-inertial client keeps it); its complaint, if any.
    pub fn on_imu(&mut self, m: ImuMeasurement) -> Result<(), ImuSampleError> {
        match self {
            Self::Mono(_) => Ok(()),
            Self::Vio(v) => v.on_imu(m),
        }
    }

    /// Tracks one frame.
    pub fn process(&mut self, frame: &VoFrame<'_>) -> Result<ClientOutput, slam_core::CoreError> {
        match self {
            Self::Mono(v) => {
                let vo = v.process(frame)?;
                let tracking = vo.state == VoState::Tracking;
                Ok(ClientOutput {
                    t_cw: vo.t_cw.filter(|_| tracking),
                    source: if tracking {
                        PoseSource::Visual
                    } else {
                        PoseSource::None
                    },
                    r_wc: None,
                    world_move: None,
                    anchor: None,
                    metric: false,
                    nav: None,
                    vo,
                })
            }
            Self::Vio(v) => {
                let o = v.process(frame)?;
                let metric = v.status().is_metric();
                Ok(ClientOutput {
                    t_cw: o.t_cw,
                    source: wire_source(o.source),
                    r_wc: o.r_wc,
                    world_move: o.world_move,
                    anchor: o.anchor,
                    metric,
                    nav: o.nav,
                    vo: o.vo,
                })
            }
        }
    }
}

/// The wire's name of a visual-inertial pose source.
fn wire_source(s: slam_core::vio::PoseSource) -> PoseSource {
    use slam_core::vio::PoseSource as S;
    match s {
        S::Visual => PoseSource::Visual,
        S::VisualInertial => PoseSource::VisualInertial,
        S::Inertial => PoseSource::Inertial,
        S::OrientationOnly => PoseSource::OrientationOnly,
        S::None => PoseSource::None,
    }
}

/// The visual-inertial client's report from its status (`first_frame_ns`: the IMU time of
/// the client's first frame, for the time it took to initialise).
pub fn vio_report(v: &VioTracker, first_frame_ns: Option<i64>) -> VioReport {
    let m = v.vo().local_mapping_stats();
    let mut r = VioReport {
        attempts: v.coupler().attempts() as u64,
        vi_windows: m.vi_windows as u64,
        vi_windows_skipped: m.vi_skipped as u64,
        vi_windows_failed: m.vi_failed as u64,
        vi_window_ms_mean: (m.vi_windows > 0).then(|| m.vi_ms_total / m.vi_windows as f64),
        vi_window_ms_max: (m.vi_windows > 0).then_some(m.vi_ms_max),
        static_init: v.static_init().map(|(s, up_w)| StaticReport {
            t_ns: s.t1_ns,
            window_s: (s.t1_ns - s.t0_ns) as f64 * 1e-9,
            gyro_bias: s.gyro_bias.into(),
            up_b: s.up_b.into(),
            up_w: up_w.map(Into::into),
            accel_norm: s.accel_norm,
            gyro_std: s.gyro_std,
            accel_std: s.accel_std,
        }),
        refinements_skipped: v.refinements_skipped() as u64,
        ..VioReport::default()
    };
    match v.status() {
        VioStatus::Collecting => {
            r.status = "collecting".into();
            let rest = if r.static_init.is_some() {
                "found at rest (static_init: gyro bias and gravity; scale and velocity need motion); "
            } else {
                ""
            };
            r.reason = Some(format!(
                "{rest}{:.2} s of keyframes so far; an attempt needs {} keyframes over {:.1} s",
                v.coupler().span_s(),
                v.params().coupler.min_keyframes,
                v.params().coupler.min_span_s
            ));
        }
        VioStatus::Refused(e) => {
            r.status = "refused".into();
            r.reason = Some(e.to_string());
        }
        VioStatus::Initialised {
            t_ns,
            scale,
            scale_sigma,
            refinements,
            ..
        } => {
            r.status = "initialised".into();
            r.initialised_t_ns = Some(t_ns);
            r.initialised_after_s = first_frame_ns.map(|t0| (t_ns - t0) as f64 * 1e-9);
            r.scale = Some(scale);
            r.scale_sigma_percent = Some(scale_sigma * 100.0);
            r.refinements = refinements as u64;
        }
        // Initialised by a predecessor: the tracker core adds what it knows of that.
        VioStatus::Resumed { .. } => r.status = "initialised".into(),
    }
    r
}

/// The report of a visual-inertial client that could not run, and why.
pub fn vio_disabled(reason: &str) -> VioReport {
    VioReport {
        status: "disabled".into(),
        reason: Some(reason.to_string()),
        ..VioReport::default()
    }
}
