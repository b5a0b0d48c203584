//! Fault injection: a kill schedule (`--kill SERVICE@SECONDS`, repeatable) and chaos
//! (`--chaos SEED:PERIOD`: a random running service every PERIOD seconds on average,
//! exponential gaps, reproducible from SEED). Kills are SIGKILL of the real child process;
//! the supervisor then restarts the service like after any crash. Each kill is recorded
//! with its time and the recovery time (kill → the restarted service's readiness line).
use std::str::FromStr;
use std::time::Instant;

use serde::Serialize;
use slam_core::ransac::SplitMix64;

use super::child::{Phase, Supervised};

/// One scheduled kill: `SERVICE@SECONDS`, e.g. `tracker:0@3.5`, `mapper@10`.
#[derive(Debug, Clone, PartialEq)]
pub struct KillSpec {
    /// Service name as in reports (`tracker:0`, `camera_ingest:1`, `mapper`, ...).
    pub service: String,
    /// Seconds after the services are all ready.
    pub at_s: f64,
}

impl FromStr for KillSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (service, at) = s
            .rsplit_once('@')
            .ok_or_else(|| format!("'{s}': expected SERVICE@SECONDS, e.g. tracker:0@3.5"))?;
        let at_s: f64 = at
            .parse()
            .map_err(|_| format!("'{s}': '{at}' is not a number of seconds"))?;
        if service.is_empty() || !at_s.is_finite() || at_s < 0.0 {
            return Err(format!("'{s}': expected SERVICE@SECONDS with SECONDS >= 0"));
        }
        Ok(Self {
            service: service.to_string(),
            at_s,
        })
    }
}

/// Chaos: `SEED:PERIOD`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChaosSpec {
    /// Seed of the choice of victims and of the gaps.
    pub seed: u64,
    /// Mean gap between kills, seconds.
    pub period_s: f64,
}

impl FromStr for ChaosSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (seed, period) = s
            .split_once(':')
            .ok_or_else(|| format!("'{s}': expected SEED:PERIOD, e.g. 7:2.0"))?;
        let seed = seed
            .parse()
            .map_err(|_| format!("'{s}': seed '{seed}' is not an integer"))?;
        let period_s: f64 = period
            .parse()
            .map_err(|_| format!("'{s}': period '{period}' is not a number"))?;
        if !period_s.is_finite() || period_s <= 0.0 {
            return Err(format!("'{s}': the period must be > 0 seconds"));
        }
        Ok(Self { seed, period_s })
    }
}

/// One kill that happened, for the report's `faults` section.
#[derive(Debug, Clone, Serialize)]
pub struct FaultEvent {
    /// The service killed.
    pub service: String,
    /// `schedule` or `chaos`.
    pub cause: &'static str,
    /// Seconds after the services were all ready.
    pub at_s: f64,
    /// Process id killed.
    pub pid: u32,
    /// Kill → ready again, seconds (`None`: not back before the run ended).
    pub recovery_s: Option<f64>,
    #[serde(skip)]
    killed_at: Option<Instant>,
}

/// Executes the kill schedule and chaos during a run.
#[derive(Debug)]
pub struct FaultInjector {
    schedule: Vec<KillSpec>,
    chaos: Option<(SplitMix64, f64, f64)>,
    /// Kills so far.
    pub events: Vec<FaultEvent>,
    /// Problems (a scheduled service that does not exist or was not running).
    pub skipped: Vec<String>,
}

impl FaultInjector {
    /// A schedule (any order) and optional chaos.
    pub fn new(mut schedule: Vec<KillSpec>, chaos: Option<ChaosSpec>) -> Self {
        schedule.sort_by(|a, b| b.at_s.total_cmp(&a.at_s));
        let chaos = chaos.map(|c| {
            let mut rng = SplitMix64::new(c.seed);
            let first = exp_gap(&mut rng, c.period_s);
            (rng, c.period_s, first)
        });
        Self {
            schedule,
            chaos,
            events: Vec::new(),
            skipped: Vec::new(),
        }
    }

    /// True when nothing is scheduled.
    pub fn is_empty(&self) -> bool {
        self.schedule.is_empty() && self.chaos.is_none()
    }

    /// Kills what is due at `elapsed_s` and notes recoveries.
    pub fn step(&mut self, services: &mut [Supervised], elapsed_s: f64) {
        while self.schedule.last().is_some_and(|k| k.at_s <= elapsed_s) {
            let Some(k) = self.schedule.pop() else { break };
            match services.iter_mut().find(|s| s.name == k.service) {
                Some(sv) if sv.phase == Phase::Running && sv.child.is_some() => {
                    self.kill(sv, "schedule", elapsed_s);
                }
                Some(sv) => self.skipped.push(format!(
                    "{} at {:.1} s: not running ({:?})",
                    k.service, k.at_s, sv.phase
                )),
                None => self.skipped.push(format!(
                    "{} at {:.1} s: no such service (names: {})",
                    k.service,
                    k.at_s,
                    services
                        .iter()
                        .map(|s| s.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                )),
            }
        }
        let mut victim = None;
        if let Some((rng, period, next)) = self.chaos.as_mut() {
            if elapsed_s >= *next {
                *next = elapsed_s + exp_gap(rng, *period);
                let running: Vec<usize> = services
                    .iter()
                    .enumerate()
                    .filter(|(_, s)| s.phase == Phase::Running && s.child.is_some())
                    .map(|(i, _)| i)
                    .collect();
                if !running.is_empty() {
                    victim = Some(running[rng.below(running.len())]);
                }
            }
        }
        if let Some(i) = victim {
            self.kill(&mut services[i], "chaos", elapsed_s);
        }
        self.note_recoveries(services);
    }

    /// Fills the recovery times of kills whose service has become ready again.
    pub fn note_recoveries(&mut self, services: &[Supervised]) {
        for ev in self.events.iter_mut().filter(|e| e.recovery_s.is_none()) {
            let Some(killed) = ev.killed_at else { continue };
            if let Some(sv) = services.iter().find(|s| s.name == ev.service) {
                if let Some(ready) = sv.ready_at.filter(|r| *r > killed) {
                    ev.recovery_s = Some(ready.duration_since(killed).as_secs_f64());
                }
            }
        }
    }

    fn kill(&mut self, sv: &mut Supervised, cause: &'static str, at_s: f64) {
        let pid = sv.pid().unwrap_or(0);
        tracing::warn!("fault injection ({cause}): SIGKILL {} (pid {pid})", sv.name);
        sv.signal(libc::SIGKILL);
        self.events.push(FaultEvent {
            service: sv.name.clone(),
            cause,
            at_s,
            pid,
            recovery_s: None,
            killed_at: Some(Instant::now()),
        });
    }
}

/// Exponential gap with mean `period` (a Poisson process of kills).
fn exp_gap(rng: &mut SplitMix64, period: f64) -> f64 {
    let u = rng.next_f64().clamp(1e-12, 1.0 - 1e-12);
    -period * (1.0 - u).ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_specs() {
        let k: KillSpec = "tracker:0@3.5".parse().unwrap();
        assert_eq!(k.service, "tracker:0");
        assert_eq!(k.at_s, 3.5);
        assert_eq!("mapper@10".parse::<KillSpec>().unwrap().at_s, 10.0);
        assert!("mapper".parse::<KillSpec>().is_err());
        assert!("mapper@x".parse::<KillSpec>().is_err());
        assert!("mapper@-1".parse::<KillSpec>().is_err());
        let c: ChaosSpec = "7:2.5".parse().unwrap();
        assert_eq!((c.seed, c.period_s), (7, 2.5));
        assert!("7".parse::<ChaosSpec>().is_err());
        assert!("7:0".parse::<ChaosSpec>().is_err());
    }

    #[test]
    fn chaos_gaps_average_the_period() {
        let mut rng = SplitMix64::new(3);
        let n = 20_000;
        let mean: f64 = (0..n).map(|_| exp_gap(&mut rng, 2.0)).sum::<f64>() / n as f64;
        assert!((mean - 2.0).abs() < 0.06, "{mean}");
    }
}
