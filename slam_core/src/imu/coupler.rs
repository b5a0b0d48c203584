//! When to initialise: the inertial initialisation ([`super::init`]) driven by a running
//! monocular VO (issue 17; seed ch. 5; `VI_NOTES.md` §4). Plain data in, events out, no
//! threads or clocks: the tracker feeds it IMU samples and keyframe poses, asks it after
//! each keyframe, and applies what it returns to its map.
//!
//! - IMU samples arrive in time order (a sample not after the last one is refused and
//!   counted by the caller); keyframe poses arrive as the VO makes them and again whenever
//!   its local BA moves them (the latest pose of a keyframe wins), keyed by their camera
//!   time; the IMU clock is `t_imu = t_cam + t_d` (`VI_NOTES.md` §1).
//! - An attempt runs when at least [`CouplerParams::min_keyframes`] keyframes span at least
//!   [`CouplerParams::min_span_s`] and a keyframe came since the last attempt. It uses the
//!   keyframes from the first one of the VO session (at most
//!   [`CouplerParams::max_keyframes`], evenly thinned), so a motion that was too gentle at
//!   first becomes informative as it goes on; a refused attempt says why
//!   ([`CouplerStatus::Refused`]).
//! - After the first success the VO's world is expected to be moved into the metric,
//!   gravity-aligned frame ([`InertialCoupler::transform_world`] does the same to the stored
//!   poses); the initialisation is then refined once or twice, when the span reaches
//!   [`CouplerParams::refine_at_s`] (ORB-SLAM3 refines at 5 s and 15 s): the result is again
//!   a similarity to apply, now close to identity.
use std::collections::BTreeMap;

use nalgebra::{Isometry3, Translation3};

use super::init::{initialize, InertialInit, InitError, InitParams};
use super::preint::{ImuMeasurement, Preintegrated, PreintegrationParams};
use super::ImuBiases;

/// Settings of [`InertialCoupler`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CouplerParams {
    /// Settings of each attempt.
    pub init: InitParams,
    /// Fewest keyframes for an attempt.
    pub min_keyframes: usize,
    /// Shortest span of the keyframes for an attempt, s.
    pub min_span_s: f64,
    /// Most keyframes in one attempt (evenly thinned beyond).
    pub max_keyframes: usize,
    /// Spans (from the session's first keyframe) at which the initialisation is refined, s.
    pub refine_at_s: [f64; 2],
    /// Camera-IMU time offset `t_d`: `t_imu = t_cam + t_d`, ns.
    pub t_d_ns: i64,
}

impl Default for CouplerParams {
    fn default() -> Self {
        Self {
            init: InitParams::default(),
            min_keyframes: 8,
            min_span_s: 1.0,
            max_keyframes: 30,
            refine_at_s: [5.0, 15.0],
            t_d_ns: 0,
        }
    }
}

/// Where the coupler stands.
#[derive(Debug, Clone, PartialEq)]
pub enum CouplerStatus {
    /// Too few keyframes or too short a span for an attempt yet.
    Collecting,
    /// The last attempt was refused, and why.
    Refused(InitError),
    /// Initialised; refinements done since.
    Initialised {
        /// Refinements done (0-2).
        refinements: usize,
    },
}

/// What an attempt gave, to apply to the VO's map.
#[derive(Debug, Clone, PartialEq)]
pub enum CouplerEvent {
    /// The first initialisation of this session.
    Initialised(InertialInit),
    /// A refinement (a similarity close to identity when the world was transformed).
    Refined(InertialInit),
}

/// The inertial initialisation of one VO session (module docs).
#[derive(Debug, Clone)]
pub struct InertialCoupler {
    params: CouplerParams,
    preint: PreintegrationParams,
    t_bc: Isometry3<f64>,
    /// IMU samples since a little before the session's first keyframe, time order.
    imu: Vec<ImuMeasurement>,
    /// Keyframe poses `T_wc` by camera time.
    keyframes: BTreeMap<i64, Isometry3<f64>>,
    /// Keyframes when the last attempt ran.
    attempted_at: usize,
    status: CouplerStatus,
    /// Attempts run (for reports).
    attempts: usize,
}

impl InertialCoupler {
    /// A coupler for a camera at `t_bc` in the body frame (metric), preintegrating with
    /// `preint`.
    pub fn new(params: CouplerParams, preint: PreintegrationParams, t_bc: Isometry3<f64>) -> Self {
        Self {
            params,
            preint,
            t_bc,
            imu: Vec::new(),
            keyframes: BTreeMap::new(),
            attempted_at: 0,
            status: CouplerStatus::Collecting,
            attempts: 0,
        }
    }

    /// Takes an IMU sample; `false` (not taken) when it is not after the last one. Once
    /// both refinements are done nothing is stored any more (the buffers stay bounded).
    pub fn on_imu(&mut self, m: ImuMeasurement) -> bool {
        if self.imu.last().is_some_and(|l| l.t_ns >= m.t_ns) {
            return false;
        }
        if !self.finished() {
            self.imu.push(m);
        }
        true
    }

    /// Sets (or moves) the pose `t_wc` of the keyframe at camera time `t_cam_ns` (ignored
    /// once both refinements are done, and before the first IMU sample: no preintegration
    /// reaches it).
    pub fn set_keyframe(&mut self, t_cam_ns: i64, t_wc: Isometry3<f64>) {
        let covered = self
            .imu
            .first()
            .is_some_and(|m| m.t_ns <= t_cam_ns + self.params.t_d_ns);
        if !self.finished() && covered {
            self.keyframes.insert(t_cam_ns, t_wc);
        }
    }

    /// Initialised and refined twice: no attempt is due any more.
    fn finished(&self) -> bool {
        matches!(self.status, CouplerStatus::Initialised { refinements } if refinements >= 2)
    }

    /// Forgets the keyframe at `t_cam_ns` (culled by the VO).
    pub fn remove_keyframe(&mut self, t_cam_ns: i64) {
        self.keyframes.remove(&t_cam_ns);
    }

    /// Starts over for a new VO session (a new map, in a new frame).
    pub fn reset(&mut self) {
        self.imu.clear();
        self.keyframes.clear();
        self.attempted_at = 0;
        self.status = CouplerStatus::Collecting;
    }

    /// A session resumed from stored keyframes (`crate::vio`, issue 17): its world was made
    /// metric and gravity-aligned by a predecessor's initialisation, refined
    /// `refinements_done` times. No initialisation runs; the refinements left continue over
    /// the successor's own keyframes and IMU samples (its span counted from its first
    /// keyframe after its first sample: the predecessor's samples are gone).
    pub fn mark_resumed(&mut self, refinements_done: usize) {
        self.imu.clear();
        self.keyframes.clear();
        self.attempted_at = 0;
        self.status = CouplerStatus::Initialised {
            refinements: refinements_done.min(2),
        };
    }

    /// Where the coupler stands.
    pub fn status(&self) -> &CouplerStatus {
        &self.status
    }

    /// Attempts run so far in this session.
    pub fn attempts(&self) -> usize {
        self.attempts
    }

    /// Span of the stored keyframes, s.
    pub fn span_s(&self) -> f64 {
        match (
            self.keyframes.keys().next(),
            self.keyframes.keys().next_back(),
        ) {
            (Some(a), Some(b)) => (b - a) as f64 * 1e-9,
            _ => 0.0,
        }
    }

    /// Moves the stored poses as the caller moved its world (e.g. with an initialisation's
    /// `s = scale`, `R = R_gw`, or an anchor to the server map): `x_new = s R x + t`
    /// (positions), `R_new = R R_old` (orientations).
    pub fn transform_world(&mut self, m: &crate::lie::Sim3) {
        for t_wc in self.keyframes.values_mut() {
            let p = m.transform_point(&t_wc.translation.vector);
            *t_wc = Isometry3::from_parts(Translation3::from(p), m.r * t_wc.rotation);
        }
    }

    /// Runs an attempt when one is due (module docs); the event to apply, if any.
    pub fn step(&mut self) -> Option<CouplerEvent> {
        let due = match self.status {
            CouplerStatus::Initialised { refinements } => {
                refinements < 2 && self.span_s() >= self.params.refine_at_s[refinements]
            }
            _ => {
                self.keyframes.len() >= self.params.min_keyframes
                    && self.span_s() >= self.params.min_span_s
                    && self.keyframes.len() > self.attempted_at
            }
        };
        if !due {
            return None;
        }
        self.attempted_at = self.keyframes.len();
        self.attempts += 1;
        let result = self.attempt();
        match (&self.status, result) {
            (CouplerStatus::Initialised { refinements }, Ok(init)) => {
                self.status = CouplerStatus::Initialised {
                    refinements: refinements + 1,
                };
                Some(CouplerEvent::Refined(init))
            }
            (CouplerStatus::Initialised { refinements }, Err(_)) => {
                // A refinement that fails keeps the initialisation; it is not retried.
                self.status = CouplerStatus::Initialised {
                    refinements: refinements + 1,
                };
                None
            }
            (_, Ok(init)) => {
                self.status = CouplerStatus::Initialised { refinements: 0 };
                Some(CouplerEvent::Initialised(init))
            }
            (_, Err(e)) => {
                self.status = CouplerStatus::Refused(e);
                None
            }
        }
    }

    /// One initialisation over the (thinned) stored keyframes.
    fn attempt(&self) -> Result<InertialInit, InitError> {
        let all: Vec<(i64, Isometry3<f64>)> =
            self.keyframes.iter().map(|(&t, p)| (t, *p)).collect();
        let picked = thin(&all, self.params.max_keyframes);
        let t_d = self.params.t_d_ns;
        let mut poses = Vec::with_capacity(picked.len());
        let mut preints = Vec::with_capacity(picked.len());
        for (k, &(t, t_wc)) in picked.iter().enumerate() {
            poses.push(t_wc);
            if let Some(&(t_next, _)) = picked.get(k + 1) {
                let pre = Preintegrated::from_window(
                    &self.imu,
                    t + t_d,
                    t_next + t_d,
                    ImuBiases::default(),
                    self.preint,
                )
                .ok_or_else(|| {
                    InitError::Alignment(format!(
                        "no IMU samples bracket the keyframes at {t} and {t_next} ns"
                    ))
                })?;
                preints.push(pre);
            }
        }
        initialize(&poses, &preints, &self.t_bc, &self.params.init)
    }
}

/// At most `n` (≥ 2) of `all`, evenly spread, the first and last included.
fn thin<T: Copy>(all: &[T], n: usize) -> Vec<T> {
    let n = n.max(2);
    if all.len() <= n {
        return all.to_vec();
    }
    (0..n)
        .map(|i| all[(i * (all.len() - 1) + (n - 1) / 2) / (n - 1)])
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thinning_keeps_both_ends_and_spreads_evenly() {
        let all: Vec<usize> = (0..100).collect();
        let t = thin(&all, 5);
        assert_eq!(t.len(), 5);
        assert_eq!((t[0], t[4]), (0, 99));
        assert!(
            t.windows(2).all(|w| (20..=30).contains(&(w[1] - w[0]))),
            "{t:?}"
        );
        assert_eq!(thin(&all[..3], 5), vec![0, 1, 2]);
    }

    #[test]
    fn nothing_is_stored_once_refined_twice() {
        let params =
            PreintegrationParams::new(&Default::default(), &Default::default()).expect("params");
        let mut c = InertialCoupler::new(CouplerParams::default(), params, Isometry3::identity());
        c.status = CouplerStatus::Initialised { refinements: 2 };
        let m = ImuMeasurement {
            t_ns: 1,
            gyro: Default::default(),
            accel: Default::default(),
        };
        assert!(c.on_imu(m));
        c.set_keyframe(5, Isometry3::identity());
        assert!(c.imu.is_empty() && c.keyframes.is_empty());
        assert_eq!(c.step(), None);
    }

    #[test]
    fn samples_out_of_order_are_refused_and_no_attempt_runs_early() {
        let params =
            PreintegrationParams::new(&Default::default(), &Default::default()).expect("params");
        let mut c = InertialCoupler::new(CouplerParams::default(), params, Isometry3::identity());
        let m = |t_ns| ImuMeasurement {
            t_ns,
            gyro: Default::default(),
            accel: Default::default(),
        };
        assert!(c.on_imu(m(10)));
        assert!(!c.on_imu(m(10)));
        assert!(!c.on_imu(m(5)));
        for k in 0..7 {
            c.set_keyframe(k * 300_000_000, Isometry3::identity());
        }
        assert_eq!(c.step(), None);
        assert_eq!(c.status(), &CouplerStatus::Collecting);
        assert_eq!(c.attempts(), 0);
        assert!(
            (c.span_s() - 1.5).abs() < 1e-9,
            "the keyframe before the first sample is not kept: span {}",
            c.span_s()
        );
    }
}
