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
    /// One lap with fast yaw swings (up to ~2.8 rad/s) and shaking; rolling shutter 30 ms.
    FastRs,
}

impl Scenario {
    /// All scenarios.
    pub const ALL: [Scenario; 3] = [Scenario::Loop, Scenario::TwoAgents, Scenario::FastRs];

    /// The name used on the command line (`loop`, `two-agents`, `fast-rs`).
    pub fn name(self) -> &'static str {
        match self {
            Scenario::Loop => "loop",
            Scenario::TwoAgents => "two-agents",
            Scenario::FastRs => "fast-rs",
        }
    }

    /// Number of agents (cameras) of the scenario.
    pub fn n_agents(self) -> usize {
        match self {
            Scenario::TwoAgents => 2,
            Scenario::Loop | Scenario::FastRs => 1,
        }
    }

    /// Default duration of the camera stream, seconds.
    pub fn default_duration_s(self) -> f64 {
        match self {
            Scenario::Loop => 2.0 * LAP_S,
            Scenario::TwoAgents | Scenario::FastRs => LAP_S,
        }
    }

    /// Default rolling-shutter readout time, ms (0 = global shutter).
    pub fn default_readout_ms(self) -> f64 {
        match self {
            Scenario::FastRs => 30.0,
            Scenario::Loop | Scenario::TwoAgents => 0.0,
        }
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
            _ => return None,
        };
        Some(traj)
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
                format!("unknown scenario `{s}` (expected one of: loop, two-agents, fast-rs)")
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
    }
}
