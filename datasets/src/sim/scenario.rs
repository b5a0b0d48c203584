//! Scenarios: which agents fly which analytic paths through the room, and their defaults.
//!
//! All paths are ellipses around the room centre with the camera looking outwards at the
//! walls and panels (1.5-5 m away), moving sideways (good parallax for monocular start-up).
//! Lap period 32 s (about 1 m/s on the 6 m x 4 m ellipse, 31.7 m per lap).

use std::f64::consts::{PI, TAU};
use std::fmt;
use std::str::FromStr;

use super::trajectory::{euroc_t_bs, AnalyticTrajectory, Signal, Sine};

/// Lap period of the default ellipse, seconds.
pub const LAP_S: f64 = 32.0;

/// A simulated scenario.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Scenario {
    /// One camera, two laps of the same closed path (a loop revisited once), global shutter.
    Loop,
    /// Two cameras on overlapping paths in the same world frame (one lap each).
    TwoAgents,
    /// Four hand-held cameras with IMUs on overlapping paths in the same world frame (one
    /// lap each; issue 19, visual-inertial clients on one server): the two `two-agents`
    /// paths and two more ellipses of other sizes, heights and phases, each with the
    /// `blackout` scenario's hand-held bounce and sways ([`add_hand_held_bounce`]), which
    /// excite the accelerometer enough for an inertial initialisation within seconds.
    FourAgents,
    /// One lap with fast yaw swings (up to ~2.8 rad/s) and shaking; rolling shutter 30 ms.
    FastRs,
    /// EuRoC-like drone flight (752x480 at 20 Hz, 200 Hz IMU with the ADIS16448 noise, global
    /// shutter): two faster laps (20 s) of a smaller ellipse with height changes and large
    /// roll, pitch and yaw swings (aggressive 6-DoF motion).
    Drone,
    /// The `loop` scene and path with 2 s of blank (black) frames in the middle of the stream
    /// (camera blackout; the IMU keeps running), carried by hand: a 1.6 Hz ±3 cm bounce and
    /// ±2 cm sways ([`add_hand_held_bounce`]; the `loop` path alone accelerates about as
    /// little as an accelerometer's bias, so no inertial initialisation could find its scale
    /// before the gap).
    Blackout,
    /// Hand-held phone while walking: one 24 s lap of the `loop` ellipse at walking pace
    /// (mean 1.33 m/s; 0.7-1.9 m/s within a stride) with a 1.9 Hz step bounce (±2 cm), a 0.95 Hz sway
    /// (±3 cm), and hand rotation jitter (peak body rate ~0.6 rad/s); 30 Hz rolling shutter
    /// (t_r 25 ms), a phone-grade 200 Hz IMU with biases and non-ideal `T_g`, `T_s`, `T_a`,
    /// and a camera-IMU offset t_d of 40 ms (the defaults of [`super::SimParams::new`]).
    Phone,
    /// Camera-IMU calibration motion after the seed's Fig. 4.4 (issue 18): the rig turns about
    /// a point near the room centre ([`calib_trajectory`]) with body rates up to 2.3-2.5 rad/s
    /// about every axis, roll and pitch swinging ±0.6 rad (attitude to gravity varied over
    /// 87°), accelerations up to 2.6-4.6 m/s² per axis, the room's six faces and its panels all around as landmarks; the
    /// `phone` camera and IMU (30 Hz, t_r 25 ms, t_d 40 ms, non-ideal `T_g`, `T_s`, `T_a`),
    /// 120 s.
    Calib,
}

/// Duration of the `calib` scenario, seconds.
pub const CALIB_S: f64 = 120.0;

/// Lap period of the `drone` scenario, seconds.
pub const DRONE_LAP_S: f64 = 20.0;

/// Lap period of the `phone` scenario (the `loop` ellipse at walking pace), seconds.
pub const PHONE_LAP_S: f64 = 24.0;

/// Step frequency of the `phone` scenario's walker, Hz.
pub const PHONE_STEP_HZ: f64 = 1.9;

/// Length of the `blackout` scenario's blank stretch, seconds.
pub const BLACKOUT_S: f64 = 2.0;

impl Scenario {
    /// All scenarios.
    pub const ALL: [Scenario; 8] = [
        Scenario::Loop,
        Scenario::TwoAgents,
        Scenario::FourAgents,
        Scenario::FastRs,
        Scenario::Drone,
        Scenario::Blackout,
        Scenario::Phone,
        Scenario::Calib,
    ];

    /// The name used on the command line (`loop`, `two-agents`, `fast-rs`, `drone`,
    /// `blackout`, `phone`, `calib`).
    pub fn name(self) -> &'static str {
        match self {
            Scenario::Loop => "loop",
            Scenario::TwoAgents => "two-agents",
            Scenario::FourAgents => "four-agents",
            Scenario::FastRs => "fast-rs",
            Scenario::Drone => "drone",
            Scenario::Blackout => "blackout",
            Scenario::Phone => "phone",
            Scenario::Calib => "calib",
        }
    }

    /// Number of agents (cameras) of the scenario.
    pub fn n_agents(self) -> usize {
        match self {
            Scenario::TwoAgents => 2,
            Scenario::FourAgents => 4,
            Scenario::Loop
            | Scenario::FastRs
            | Scenario::Drone
            | Scenario::Blackout
            | Scenario::Phone
            | Scenario::Calib => 1,
        }
    }

    /// Default duration of the camera stream, seconds.
    pub fn default_duration_s(self) -> f64 {
        match self {
            Scenario::Loop | Scenario::Blackout => 2.0 * LAP_S,
            Scenario::TwoAgents | Scenario::FourAgents | Scenario::FastRs => LAP_S,
            Scenario::Drone => 2.0 * DRONE_LAP_S,
            Scenario::Phone => PHONE_LAP_S,
            Scenario::Calib => CALIB_S,
        }
    }

    /// Default rolling-shutter readout time, ms (0 = global shutter).
    pub fn default_readout_ms(self) -> f64 {
        match self {
            Scenario::FastRs => 30.0,
            Scenario::Phone | Scenario::Calib => 25.0,
            Scenario::Loop
            | Scenario::TwoAgents
            | Scenario::FourAgents
            | Scenario::Drone
            | Scenario::Blackout => 0.0,
        }
    }

    /// Frames `[first, end)` rendered blank (all black) out of `n_frames` at `rate_hz`: the
    /// middle [`BLACKOUT_S`] of the `blackout` stream, empty for the other scenarios.
    pub fn blank_frames(self, n_frames: usize, rate_hz: f64) -> std::ops::Range<usize> {
        if self != Scenario::Blackout {
            return 0..0;
        }
        let n_blank = ((BLACKOUT_S * rate_hz).round() as usize).min(n_frames);
        let first = (n_frames - n_blank) / 2;
        first..first + n_blank
    }

    /// The analytic trajectory of `agent` (0-based; `None` if the scenario has no such agent).
    pub fn trajectory(self, agent: usize) -> Option<AnalyticTrajectory> {
        let w = TAU / LAP_S;
        let ellipse = |a: f64, b: f64, phase: f64| {
            [
                Signal::new(
                    0.0,
                    0.0,
                    vec![Sine {
                        amp: a,
                        omega: w,
                        phase: phase + 0.5 * PI,
                    }],
                ),
                Signal::new(
                    0.0,
                    0.0,
                    vec![Sine {
                        amp: b,
                        omega: w,
                        phase,
                    }],
                ),
            ]
        };
        let traj = match (self, agent) {
            (Scenario::Blackout, 0) => {
                let mut t = Scenario::Loop.trajectory(0)?;
                add_hand_held_bounce(&mut t);
                t
            }
            (Scenario::FourAgents, 0 | 1) => {
                let mut t = Scenario::TwoAgents.trajectory(agent)?;
                add_hand_held_bounce(&mut t);
                t
            }
            (Scenario::FourAgents, 2 | 3) => {
                let (a, b, phase, z) = if agent == 2 {
                    (5.7, 3.8, 0.5 * PI, 1.45)
                } else {
                    (5.0, 3.2, 1.5 * PI, 1.6)
                };
                let [x, y] = ellipse(a, b, phase);
                let mut t = AnalyticTrajectory {
                    pos: [
                        x,
                        y,
                        Signal::new(z, 0.0, vec![Sine::with_period(0.12, 9.7, 0.3)]),
                    ],
                    yaw: Signal::new(phase, w, vec![Sine::with_period(0.15, 6.9, 0.2)]),
                    pitch: Signal::new(0.06, 0.0, vec![Sine::with_period(0.04, 8.1, 0.1)]),
                    roll: Signal::new(0.0, 0.0, vec![Sine::with_period(0.03, 5.9, 0.6)]),
                    t_bs: euroc_t_bs(),
                };
                add_hand_held_bounce(&mut t);
                t
            }
            (Scenario::Loop, 0) | (Scenario::TwoAgents, 0) => {
                let [x, y] = ellipse(6.0, 4.0, 0.0);
                AnalyticTrajectory {
                    pos: [
                        x,
                        y,
                        Signal::new(1.5, 0.0, vec![Sine::with_period(0.15, 11.3, 0.0)]),
                    ],
                    yaw: Signal::new(0.0, w, vec![Sine::with_period(0.15, 7.7, 0.4)]),
                    pitch: Signal::new(0.05, 0.0, vec![Sine::with_period(0.05, 9.1, 0.0)]),
                    roll: Signal::new(0.0, 0.0, vec![Sine::with_period(0.03, 5.3, 1.0)]),
                    t_bs: euroc_t_bs(),
                }
            }
            (Scenario::TwoAgents, 1) => {
                let [x, y] = ellipse(5.4, 3.5, PI);
                AnalyticTrajectory {
                    pos: [
                        x,
                        y,
                        Signal::new(1.3, 0.0, vec![Sine::with_period(0.1, 8.3, 1.0)]),
                    ],
                    yaw: Signal::new(PI, w, vec![Sine::with_period(0.2, 6.1, 0.0)]),
                    pitch: Signal::new(0.08, 0.0, vec![Sine::with_period(0.04, 7.3, 0.5)]),
                    roll: Signal::new(0.0, 0.0, vec![Sine::with_period(0.03, 4.7, 0.0)]),
                    t_bs: euroc_t_bs(),
                }
            }
            (Scenario::FastRs, 0) => {
                let [mut x, mut y] = ellipse(6.0, 4.0, 0.0);
                // Hand shake: a few mm at 3-4 Hz.
                x.sines.push(Sine::with_period(0.003, 1.0 / 3.7, 0.0));
                y.sines.push(Sine::with_period(0.003, 1.0 / 3.1, 1.0));
                let z = Signal::new(
                    1.5,
                    0.0,
                    vec![
                        Sine::with_period(0.1, 9.0, 0.0),
                        Sine::with_period(0.003, 1.0 / 4.3, 2.0),
                    ],
                );
                AnalyticTrajectory {
                    pos: [x, y, z],
                    // Yaw swings of +-0.45 rad at 0.8 Hz (2.26 rad/s peak) plus a 6 Hz shake.
                    yaw: Signal::new(
                        0.0,
                        w,
                        vec![
                            Sine::with_period(0.45, 1.25, 0.0),
                            Sine::with_period(0.01, 1.0 / 6.0, 0.3),
                        ],
                    ),
                    pitch: Signal::new(0.05, 0.0, vec![Sine::with_period(0.04, 1.0 / 3.1, 0.0)]),
                    roll: Signal::new(0.0, 0.0, vec![Sine::with_period(0.04, 1.0 / 4.3, 0.5)]),
                    t_bs: euroc_t_bs(),
                }
            }
            (Scenario::Drone, 0) => {
                let wd = TAU / DRONE_LAP_S;
                let p = |period: f64| TAU / period;
                let sine = |amp: f64, period: f64, phase: f64| Sine {
                    amp,
                    omega: p(period),
                    phase,
                };
                // A 4.5 m x 3 m ellipse in 20 s (~1.2 m/s) with 2-4 Hz wobble, ±0.45 m of
                // height; yaw follows the lap with ±0.5 rad swings (peak rate ~1.9 rad/s),
                // roll and pitch swing ±0.25-0.3 rad as a drone banking and braking.
                AnalyticTrajectory {
                    pos: [
                        Signal::new(
                            0.0,
                            0.0,
                            vec![
                                Sine {
                                    amp: 4.5,
                                    omega: wd,
                                    phase: 0.5 * PI,
                                },
                                sine(0.02, 0.37, 0.0),
                            ],
                        ),
                        Signal::new(
                            0.0,
                            0.0,
                            vec![
                                Sine {
                                    amp: 3.0,
                                    omega: wd,
                                    phase: 0.0,
                                },
                                sine(0.02, 0.29, 1.0),
                            ],
                        ),
                        Signal::new(1.4, 0.0, vec![sine(0.35, 6.7, 0.0), sine(0.1, 1.9, 0.5)]),
                    ],
                    yaw: Signal::new(0.0, wd, vec![sine(0.4, 2.9, 0.0), sine(0.1, 1.1, 0.7)]),
                    pitch: Signal::new(0.05, 0.0, vec![sine(0.2, 3.3, 0.2), sine(0.05, 0.9, 0.0)]),
                    roll: Signal::new(0.0, 0.0, vec![sine(0.25, 2.3, 0.4), sine(0.05, 0.7, 1.3)]),
                    t_bs: euroc_t_bs(),
                }
            }
            (Scenario::Phone, 0) => phone_trajectory(),
            (Scenario::Calib, 0) => calib_trajectory(),
            _ => return None,
        };
        Some(traj)
    }
}

/// Adds the `blackout` scenario's hand-held motion to `t`: a vertical bounce of ±3 cm at
/// 1.6 Hz (peak 3.0 m/s²) and horizontal sways of ±2 cm at 0.9 Hz and 0.7 Hz (0.6 and
/// 0.4 m/s²), all sinusoids so the IMU stays exact.
fn add_hand_held_bounce(t: &mut AnalyticTrajectory) {
    let hz = |f: f64| Sine {
        amp: 0.0,
        omega: TAU * f,
        phase: 0.0,
    };
    t.pos[2].sines.push(Sine {
        amp: 0.03,
        ..hz(1.6)
    });
    t.pos[0].sines.push(Sine {
        amp: 0.02,
        phase: 0.5,
        ..hz(0.9)
    });
    t.pos[1].sines.push(Sine {
        amp: 0.02,
        phase: 1.3,
        ..hz(0.7)
    });
}

/// The `phone` walk: the `loop` ellipse (6 m x 4 m) in [`PHONE_LAP_S`], the phone held at
/// 1.35 m and looking outwards 0.35 rad ahead of the side direction, 0.1 rad down.
///
/// The ellipse alone gives 1.05-1.57 m/s (mean 1.32 m/s); with the gait the horizontal
/// speed ranges 0.7-1.9 m/s. Gait (steps at [`PHONE_STEP_HZ`]): vertical bounce ±2 cm at the step frequency (peak
/// 2.9 m/s²), lateral sway ±3 cm at half of it, a ±1.5 cm surge at the step frequency.
/// Hand: pitch ±0.03 rad at the step frequency, roll ±0.04 rad at half of it, yaw ±0.08 rad
/// at 0.6 Hz, and a ±0.004 rad tremor at 4.7 Hz on each angle (peak body rate ~0.6 rad/s,
/// a few to tens of deg/s). All sinusoids, so the IMU is exact.
fn phone_trajectory() -> AnalyticTrajectory {
    let w = TAU / PHONE_LAP_S;
    let step = TAU * PHONE_STEP_HZ;
    let sine = |amp: f64, omega: f64, phase: f64| Sine { amp, omega, phase };
    let hz = |f: f64| TAU * f;
    AnalyticTrajectory {
        pos: [
            Signal::new(
                0.0,
                0.0,
                vec![
                    sine(6.0, w, 0.5 * PI),
                    sine(0.03, 0.5 * step, 0.0),
                    sine(0.015, step, 0.4),
                ],
            ),
            Signal::new(
                0.0,
                0.0,
                vec![
                    sine(4.0, w, 0.0),
                    sine(0.03, 0.5 * step, 1.2),
                    sine(0.015, step, 2.0),
                ],
            ),
            Signal::new(
                1.35,
                0.0,
                vec![sine(0.02, step, 0.0), sine(0.05, hz(0.13), 0.3)],
            ),
        ],
        yaw: Signal::new(
            0.35,
            w,
            vec![sine(0.08, hz(0.6), 0.0), sine(0.004, hz(4.7), 0.9)],
        ),
        pitch: Signal::new(
            0.1,
            0.0,
            vec![
                sine(0.03, step, 0.6),
                sine(0.05, hz(0.17), 0.0),
                sine(0.004, hz(4.7), 2.1),
            ],
        ),
        roll: Signal::new(
            0.0,
            0.0,
            vec![sine(0.04, 0.5 * step, 0.3), sine(0.004, hz(4.7), 0.2)],
        ),
        t_bs: euroc_t_bs(),
    }
}

impl fmt::Display for Scenario {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Scenario {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Scenario::ALL
            .into_iter()
            .find(|sc| sc.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| {
                format!(
                    "unknown scenario `{s}` (expected one of: loop, two-agents, four-agents, \
                     fast-rs, drone, blackout, phone, calib)"
                )
            })
    }
}

/// The `calib` motion (seed Fig. 4.4, `VI_NOTES.md` §3 "Simulation": rates ≥ 1 rad/s,
/// ≥ 1 m/s²): a rig held at 1.5 m near the room centre, moving ±0.3-0.4 m at 0.3-1.2 Hz
/// (peak accelerations 2.6-4.6 m/s² per world axis), its yaw sweeping round the room once
/// every 18 s with ±0.6 rad swings, pitch and roll ±0.55-0.6 rad (the attitude to gravity
/// varies, as `T_a` needs) with faster ±0.1 rad swings: peak body rates 2.3-2.5 rad/s about
/// every body axis (`tests::calib_excites_every_axis`).
/// All sinusoids, so the IMU is exact.
pub fn calib_trajectory() -> AnalyticTrajectory {
    let sine = Sine::with_period;
    AnalyticTrajectory {
        pos: [
            Signal::new(0.3, 0.0, vec![sine(0.35, 2.3, 0.0), sine(0.04, 0.9, 1.0)]),
            Signal::new(-0.2, 0.0, vec![sine(0.3, 2.9, 1.0), sine(0.04, 1.1, 0.3)]),
            Signal::new(1.5, 0.0, vec![sine(0.25, 3.7, 0.5), sine(0.03, 0.8, 2.0)]),
        ],
        yaw: Signal::new(
            0.0,
            TAU / 18.0,
            vec![sine(0.6, 2.6, 0.0), sine(0.06, 0.9, 0.4)],
        ),
        pitch: Signal::new(0.0, 0.0, vec![sine(0.45, 3.1, 0.7), sine(0.1, 1.3, 0.0)]),
        roll: Signal::new(0.0, 0.0, vec![sine(0.5, 2.7, 1.9), sine(0.1, 1.1, 0.2)]),
        t_bs: euroc_t_bs(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn names_round_trip() {
        for s in Scenario::ALL {
            assert_eq!(s.name().parse::<Scenario>(), Ok(s));
            for a in 0..s.n_agents() {
                assert!(s.trajectory(a).is_some());
            }
            assert!(s.trajectory(s.n_agents()).is_none());
        }
        assert!("nope".parse::<Scenario>().is_err());
    }

    /// The `calib` motion excites what calibration needs (`VI_NOTES.md` §3 "Observability"):
    /// every body axis turns faster than 1 rad/s, every world axis accelerates more than
    /// 1 m/s², gravity's direction in the body frame varies by more than 60°, and the rig
    /// stays within 1 m of the room centre (far from the panels).
    #[test]
    fn calib_excites_every_axis() {
        let tr = Scenario::Calib.trajectory(0).expect("agent 0");
        let (mut w_peak, mut a_peak) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
        let (mut g_dirs, mut far) = (Vec::new(), 0.0f64);
        for i in 0..24_000 {
            let s = tr.body_state(f64::from(i) * 0.005);
            w_peak = w_peak.zip_map(&s.omega_b, |p, w| p.max(w.abs()));
            a_peak = a_peak.zip_map(&s.a_w, |p, a| p.max(a.abs()));
            g_dirs.push(s.q_wb.inverse() * Vector3::z());
            far = far.max((s.p_wb - Vector3::new(0.0, 0.0, 1.5)).norm());
        }
        let spread = g_dirs
            .iter()
            .step_by(50)
            .flat_map(|a| g_dirs.iter().step_by(50).map(move |b| a.angle(b)))
            .fold(0.0, f64::max);
        eprintln!("peak rates {w_peak:.2?} rad/s, accelerations {a_peak:.2?} m/s², gravity spread {:.0}°, farthest {far:.2} m", spread.to_degrees());
        assert!(
            w_peak.min() > 1.0 && a_peak.min() > 1.0,
            "{w_peak} {a_peak}"
        );
        assert!(spread > 60f64.to_radians() && far < 1.0);
    }

    #[test]
    fn fast_rs_rotates_fast_and_loop_gently() {
        let peak = |sc: Scenario| {
            let tr = sc.trajectory(0).expect("agent 0");
            (0..6400)
                .map(|i| tr.body_state(f64::from(i) * 0.005).omega_b.norm())
                .fold(0.0, f64::max)
        };
        let fast = peak(Scenario::FastRs);
        assert!((2.0..3.2).contains(&fast), "fast-rs peak {fast}");
        assert!(peak(Scenario::Loop) < 0.6);
        let drone = peak(Scenario::Drone);
        assert!((1.0..3.5).contains(&drone), "drone peak {drone}");
    }

    #[test]
    fn drone_moves_in_six_dof_and_blackout_is_the_hand_held_loop_with_a_gap() {
        let tr = Scenario::Drone.trajectory(0).expect("drone");
        let (mut roll, mut pitch, mut z, mut acc) = (0.0f64, 0.0f64, (f64::MAX, f64::MIN), 0.0f64);
        for i in 0..8000 {
            let t = f64::from(i) * 0.005;
            roll = roll.max(tr.roll.value(t).abs());
            pitch = pitch.max(tr.pitch.value(t).abs());
            let s = tr.body_state(t);
            z = (z.0.min(s.p_wb.z), z.1.max(s.p_wb.z));
            acc = acc.max(s.a_w.norm());
        }
        assert!(
            roll > 0.25 && pitch > 0.2 && z.1 - z.0 > 0.7 && acc > 2.0,
            "{roll} {pitch} {z:?} {acc}"
        );
        // `blackout`: the loop path within a few cm, but with accelerations an inertial
        // initialisation can use (the loop's stay near the accelerometer bias's size).
        let (lp, bo) = (
            Scenario::Loop.trajectory(0).expect("loop"),
            Scenario::Blackout.trajectory(0).expect("blackout"),
        );
        let (mut dist, mut acc_loop, mut acc_bo) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..6400 {
            let t = f64::from(i) * 0.01;
            let (a, b) = (lp.body_state(t), bo.body_state(t));
            dist = dist.max((a.p_wb - b.p_wb).norm());
            acc_loop = acc_loop.max(a.a_w.norm());
            acc_bo = acc_bo.max(b.a_w.norm());
        }
        assert!(dist < 0.05, "blackout {dist} m off the loop path");
        assert!(acc_loop < 0.5 && acc_bo > 2.5, "{acc_loop} {acc_bo}");
        assert_eq!(Scenario::Blackout.blank_frames(1280, 20.0), 620..660);
        assert_eq!(Scenario::Loop.blank_frames(1280, 20.0), 0..0);
        assert_eq!(Scenario::Blackout.blank_frames(10, 20.0), 0..10);
    }

    /// `phone`: walking pace, a step bounce of a few cm at ~2 Hz, body rates of a few to
    /// tens of deg/s (never the fast-rs swings).
    #[test]
    fn phone_walks_with_a_bouncing_jittering_hand() {
        let tr = Scenario::Phone.trajectory(0).expect("phone");
        let (mut speed, mut rate, mut z) = ((f64::MAX, 0.0f64), 0.0f64, (f64::MAX, f64::MIN));
        let mut mean_speed = 0.0;
        let n = 4800;
        for i in 0..n {
            let s = tr.body_state(f64::from(i) * 0.005);
            let v = s.v_w.xy().norm();
            speed = (speed.0.min(v), speed.1.max(v));
            mean_speed += v / f64::from(n);
            rate = rate.max(s.omega_b.norm());
            z = (z.0.min(s.p_wb.z), z.1.max(s.p_wb.z));
        }
        assert!(
            (1.2..1.5).contains(&mean_speed) && speed.0 > 0.6 && speed.1 < 2.0,
            "speed {mean_speed} {speed:?}"
        );
        assert!((0.3..1.0).contains(&rate), "peak rate {rate}");
        assert!((0.08..0.2).contains(&(z.1 - z.0)), "height range {z:?}");
        assert_eq!(Scenario::Phone.default_readout_ms(), 25.0);
    }
}
