//! Fault injection: a kill schedule (`--kill SERVICE@SECONDS` or `--kill SERVICE@fFRAMES`,
//! repeatable; the second form fires once the recorder has poses of FRAMES distinct frames of
//! the service's client, a fixed point in the data of a lock-step replay) and chaos
//! (`--chaos SEED:PERIOD`: a random running service every PERIOD seconds on average,
//! exponential gaps, reproducible from SEED). Kills are SIGKILL of the real child process;
//! the supervisor then restarts the service like after any crash. Each kill is recorded
//! with its time, the frame count, the recovery time (kill → the restarted service's
//! readiness line) and the counters the restarted process resumed from; the report's
//! `faults_summary` gives kills per service and recovery p50 / max.
use std::collections::BTreeMap;
use std::str::FromStr;
use std::time::Instant;

use serde::Serialize;
use slam_core::ransac::SplitMix64;

use super::child::{Phase, Supervised};

/// When a scheduled kill is due.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum KillAt {
    /// Seconds after the services are all ready.
    Seconds(f64),
    /// Once the recorder has a pose of this many distinct frames of the service's client
    /// (client 0 for the host-wide mapper and loop closer): a point in the data, the same
    /// in every run of a lock-step replay whatever the machine's speed.
    Frame(u64),
}

/// One scheduled kill: `SERVICE@SECONDS` or `SERVICE@fFRAMES`, e.g. `tracker:0@3.5`,
/// `mapper@10`, `mapper@f200`.
#[derive(Debug, Clone, PartialEq)]
pub struct KillSpec {
    /// Service name as in reports (`tracker:0`, `camera_ingest:1`, `mapper`, ...).
    pub service: String,
    /// When.
    pub at: KillAt,
    /// The entry as given on the command line (`mapper@f200`), quoted in the report.
    pub text: String,
}

impl KillSpec {
    /// The client whose frames a [`KillAt::Frame`] counts: the service's own client index
    /// (`tracker:1` → 1), 0 for host-wide services.
    pub fn client(&self) -> usize {
        client_of(&self.service)
    }
}

/// Client index of a service name (`tracker:1` → 1), 0 for host-wide services.
pub fn client_of(service: &str) -> usize {
    service
        .rsplit_once(':')
        .and_then(|(_, c)| c.parse().ok())
        .unwrap_or(0)
}

impl FromStr for KillSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (service, at) = s.rsplit_once('@').ok_or_else(|| {
            format!("'{s}': expected SERVICE@SECONDS or SERVICE@fFRAMES, e.g. tracker:0@3.5")
        })?;
        if service.is_empty() {
            return Err(format!("'{s}': no service name before '@'"));
        }
        let at = if let Some(n) = at.strip_prefix('f') {
            KillAt::Frame(
                n.parse()
                    .map_err(|_| format!("'{s}': '{n}' is not a number of frames"))?,
            )
        } else {
            let at_s: f64 = at
                .parse()
                .map_err(|_| format!("'{s}': '{at}' is not a number of seconds"))?;
            if !at_s.is_finite() || at_s < 0.0 {
                return Err(format!("'{s}': expected SERVICE@SECONDS with SECONDS >= 0"));
            }
            KillAt::Seconds(at_s)
        };
        Ok(Self {
            service: service.to_string(),
            at,
            text: s.to_string(),
        })
    }
}

impl std::fmt::Display for KillSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.at {
            KillAt::Seconds(t) => write!(f, "{}@{t}", self.service),
            KillAt::Frame(n) => write!(f, "{}@f{n}", self.service),
        }
    }
}

/// Chaos: `SEED:PERIOD`.
#[derive(Debug, Clone, PartialEq)]
pub struct ChaosSpec {
    /// Seed of the choice of victims and of the gaps.
    pub seed: u64,
    /// Mean gap between kills, seconds.
    pub period_s: f64,
    /// The entry as given on the command line (`7:2.0`), quoted in the report.
    pub text: String,
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
        Ok(Self {
            seed,
            period_s,
            text: s.to_string(),
        })
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
    /// Distinct frames of the service's client (client 0 for host-wide services) with a
    /// pose at the time of the kill.
    pub at_frame: u64,
    /// Process id killed.
    pub pid: u32,
    /// Kill → ready again, seconds (`None`: not back before the run ended).
    pub recovery_s: Option<f64>,
    /// The status counters the restarted process resumed from (what the killed one last
    /// wrote): the restarted process's own work is its final counters minus these.
    pub counters_at_restart: Option<std::collections::BTreeMap<String, u64>>,
    #[serde(skip)]
    killed_at: Option<Instant>,
}

/// A `--kill` entry, or `--chaos`, that killed nothing: the run ended before it was due,
/// or its service was not running then, or does not exist.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct UnfiredFault {
    /// The option as given: `--kill mapper@f99999`, `--chaos 7:100`.
    pub spec: String,
    /// Why it killed nothing.
    pub reason: String,
}

/// Executes the kill schedule and chaos during a run.
#[derive(Debug)]
pub struct FaultInjector {
    /// Scheduled kills not done yet.
    schedule: Vec<KillSpec>,
    chaos: Option<(SplitMix64, f64, f64)>,
    /// `--chaos` as given.
    chaos_text: Option<String>,
    /// Kills so far.
    pub events: Vec<FaultEvent>,
    /// Scheduled kills that were due but found no running process of their service.
    pub skipped: Vec<UnfiredFault>,
}

impl FaultInjector {
    /// A schedule (any order) and optional chaos.
    pub fn new(schedule: Vec<KillSpec>, chaos: Option<ChaosSpec>) -> Self {
        let chaos_text = chaos.as_ref().map(|c| format!("--chaos {}", c.text));
        let chaos = chaos.map(|c| {
            let mut rng = SplitMix64::new(c.seed);
            let first = exp_gap(&mut rng, c.period_s);
            (rng, c.period_s, first)
        });
        Self {
            schedule,
            chaos,
            chaos_text,
            events: Vec::new(),
            skipped: Vec::new(),
        }
    }

    /// True when nothing is scheduled.
    pub fn is_empty(&self) -> bool {
        self.schedule.is_empty() && self.chaos.is_none()
    }

    /// Kills what is due at `elapsed_s` with `frames[c]` distinct frames of client `c`
    /// posed so far, and notes recoveries.
    pub fn step(&mut self, services: &mut [Supervised], elapsed_s: f64, frames: &[u64]) {
        let frames_of = |c: usize| frames.get(c).copied().unwrap_or(0);
        let due = |k: &KillSpec| match k.at {
            KillAt::Seconds(t) => t <= elapsed_s,
            KillAt::Frame(n) => frames_of(k.client()) >= n,
        };
        let (mut now, later): (Vec<KillSpec>, Vec<KillSpec>) = std::mem::take(&mut self.schedule)
            .into_iter()
            .partition(due);
        self.schedule = later;
        // Several due at once (e.g. a slow start): in the order they were meant for.
        now.sort_by(|a, b| match (a.at, b.at) {
            (KillAt::Seconds(x), KillAt::Seconds(y)) => x.total_cmp(&y),
            (KillAt::Frame(x), KillAt::Frame(y)) => x.cmp(&y),
            (KillAt::Seconds(_), KillAt::Frame(_)) => std::cmp::Ordering::Less,
            (KillAt::Frame(_), KillAt::Seconds(_)) => std::cmp::Ordering::Greater,
        });
        for k in now {
            match services.iter_mut().find(|s| s.name == k.service) {
                Some(sv) if sv.phase == Phase::Running && sv.child.is_some() => {
                    let f = frames_of(client_of(&sv.name));
                    self.kill(sv, "schedule", elapsed_s, f);
                }
                Some(sv) => self.skipped.push(UnfiredFault {
                    spec: format!("--kill {}", k.text),
                    reason: format!(
                        "due at {elapsed_s:.1} s, {} was not running ({:?})",
                        sv.name, sv.phase
                    ),
                }),
                None => self.skipped.push(UnfiredFault {
                    spec: format!("--kill {}", k.text),
                    reason: format!(
                        "no such service (names: {})",
                        services
                            .iter()
                            .map(|s| s.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                }),
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
            let f = frames_of(client_of(&services[i].name));
            self.kill(&mut services[i], "chaos", elapsed_s, f);
        }
        self.note_recoveries(services);
    }

    /// Fills the recovery times of kills whose service has become ready again, and the
    /// counters its restarted process resumed from.
    pub fn note_recoveries(&mut self, services: &[Supervised]) {
        for ev in self.events.iter_mut().filter(|e| e.recovery_s.is_none()) {
            let Some(killed) = ev.killed_at else { continue };
            if let Some(sv) = services.iter().find(|s| s.name == ev.service) {
                if let Some(ready) = sv.ready_at.filter(|r| *r > killed) {
                    ev.recovery_s = Some(ready.duration_since(killed).as_secs_f64());
                }
                if ev.counters_at_restart.is_none() {
                    ev.counters_at_restart = sv
                        .restart_snapshots
                        .iter()
                        .find(|(at, _)| *at > killed)
                        .map(|(_, c)| c.clone());
                }
            }
        }
    }

    /// Everything that killed nothing, at the end of a run that lasted `elapsed_s` after
    /// start-up with `frames[c]` distinct frames of client `c` posed: the scheduled kills
    /// never due (the run ended first), those due when their service was not running or
    /// that name no service, and `--chaos` when it killed nothing.
    pub fn unfired(&self, elapsed_s: f64, frames: &[u64]) -> Vec<UnfiredFault> {
        let mut out = self.skipped.clone();
        for k in &self.schedule {
            let now = match k.at {
                KillAt::Seconds(_) => format!("it lasted {elapsed_s:.1} s after start-up"),
                KillAt::Frame(_) => format!(
                    "client {} had {} frames posed",
                    k.client(),
                    frames.get(k.client()).copied().unwrap_or(0)
                ),
            };
            out.push(UnfiredFault {
                spec: format!("--kill {}", k.text),
                reason: format!("the run ended before it was due ({now})"),
            });
        }
        let chaos_kills = self.events.iter().filter(|e| e.cause == "chaos").count();
        if let (Some(text), Some((_, _, next)), 0) = (&self.chaos_text, &self.chaos, chaos_kills) {
            out.push(UnfiredFault {
                spec: text.clone(),
                reason: format!(
                    "killed nothing: the run lasted {elapsed_s:.1} s after start-up, the next \
                     kill was due at {next:.1} s"
                ),
            });
        }
        out
    }

    fn kill(&mut self, sv: &mut Supervised, cause: &'static str, at_s: f64, at_frame: u64) {
        let pid = sv.pid().unwrap_or(0);
        tracing::warn!("fault injection ({cause}): SIGKILL {} (pid {pid})", sv.name);
        sv.signal(libc::SIGKILL);
        sv.kill_injected = true;
        self.events.push(FaultEvent {
            service: sv.name.clone(),
            cause,
            at_s,
            at_frame,
            pid,
            recovery_s: None,
            counters_at_restart: None,
            killed_at: Some(Instant::now()),
        });
    }
}

/// Summary of the kills of a run: how many per service, recovery-time percentiles.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FaultsSummary {
    /// Kills injected.
    pub kills: usize,
    /// Kills whose service was ready again before the run ended.
    pub recovered: usize,
    /// Recovery time (kill → ready again), all kills: median, s.
    pub recovery_p50_s: Option<f64>,
    /// Recovery time, all kills: largest, s.
    pub recovery_max_s: Option<f64>,
    /// Per service (`tracker:0`, `mapper`, ...): kills and recovery p50 / max.
    pub per_service: BTreeMap<String, ServiceFaults>,
    /// `--kill` entries and `--chaos` that killed nothing (listed in `faults_unfired`).
    pub unfired: usize,
}

/// Kills of one service.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ServiceFaults {
    /// Kills injected.
    pub kills: usize,
    /// Recovery time median, s.
    pub recovery_p50_s: Option<f64>,
    /// Recovery time largest, s.
    pub recovery_max_s: Option<f64>,
}

/// Median (lower of the two middle values for an even count) and maximum.
fn p50_max(mut v: Vec<f64>) -> (Option<f64>, Option<f64>) {
    if v.is_empty() {
        return (None, None);
    }
    v.sort_by(f64::total_cmp);
    (Some(v[(v.len() - 1) / 2]), v.last().copied())
}

impl FaultsSummary {
    /// Summarises `events`.
    pub fn of(events: &[FaultEvent]) -> Self {
        let rec: Vec<f64> = events.iter().filter_map(|e| e.recovery_s).collect();
        let (p50, max) = p50_max(rec.clone());
        let mut per_service: BTreeMap<String, ServiceFaults> = BTreeMap::new();
        for e in events {
            per_service.entry(e.service.clone()).or_default().kills += 1;
        }
        for (name, sf) in per_service.iter_mut() {
            let r = events
                .iter()
                .filter(|e| &e.service == name)
                .filter_map(|e| e.recovery_s)
                .collect();
            (sf.recovery_p50_s, sf.recovery_max_s) = p50_max(r);
        }
        Self {
            kills: events.len(),
            recovered: rec.len(),
            recovery_p50_s: p50,
            recovery_max_s: max,
            per_service,
            unfired: 0,
        }
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
        assert_eq!(k.at, KillAt::Seconds(3.5));
        assert_eq!(k.client(), 0);
        assert_eq!(
            "mapper@10".parse::<KillSpec>().unwrap().at,
            KillAt::Seconds(10.0)
        );
        let f: KillSpec = "tracker:1@f150".parse().unwrap();
        assert_eq!((f.at, f.client()), (KillAt::Frame(150), 1));
        assert_eq!(f.to_string(), "tracker:1@f150");
        assert!("mapper@fx".parse::<KillSpec>().is_err());
        assert!("@3".parse::<KillSpec>().is_err());
        assert!("mapper".parse::<KillSpec>().is_err());
        assert!("mapper@x".parse::<KillSpec>().is_err());
        assert!("mapper@-1".parse::<KillSpec>().is_err());
        let c: ChaosSpec = "7:2.5".parse().unwrap();
        assert_eq!((c.seed, c.period_s), (7, 2.5));
        assert!("7".parse::<ChaosSpec>().is_err());
        assert!("7:0".parse::<ChaosSpec>().is_err());
    }

    #[test]
    fn summary_percentiles() {
        let ev = |service: &str, r: Option<f64>| FaultEvent {
            service: service.into(),
            cause: "chaos",
            at_s: 0.0,
            at_frame: 0,
            pid: 1,
            recovery_s: r,
            counters_at_restart: None,
            killed_at: None,
        };
        let s = FaultsSummary::of(&[
            ev("mapper", Some(0.3)),
            ev("tracker:0", Some(0.1)),
            ev("mapper", Some(0.5)),
            ev("mapper", None),
        ]);
        assert_eq!((s.kills, s.recovered), (4, 3));
        assert_eq!((s.recovery_p50_s, s.recovery_max_s), (Some(0.3), Some(0.5)));
        let m = &s.per_service["mapper"];
        assert_eq!(
            (m.kills, m.recovery_p50_s, m.recovery_max_s),
            (3, Some(0.3), Some(0.5))
        );
        assert_eq!(s.per_service["tracker:0"].kills, 1);
    }

    #[test]
    fn kills_never_due_are_reported_as_given() {
        let kills = ["mapper@f99999", "tracker:0@1000.50", "trackr:1@0"]
            .map(|k| k.parse::<KillSpec>().unwrap());
        let chaos = "7:1000.0".parse::<ChaosSpec>().ok();
        let mut inj = FaultInjector::new(kills.to_vec(), chaos);
        inj.step(&mut [], 2.0, &[100]);
        let unfired = inj.unfired(2.5, &[100]);
        let specs: Vec<&str> = unfired.iter().map(|u| u.spec.as_str()).collect();
        assert_eq!(
            specs,
            [
                "--kill trackr:1@0",
                "--kill mapper@f99999",
                "--kill tracker:0@1000.50",
                "--chaos 7:1000.0"
            ]
        );
        assert!(unfired[0].reason.contains("no such service"), "{unfired:?}");
        assert!(
            unfired[1].reason.contains("client 0 had 100 frames posed"),
            "{unfired:?}"
        );
        assert!(unfired[2].reason.contains("2.5 s"), "{unfired:?}");
        assert!(unfired[3].reason.contains("killed nothing"), "{unfired:?}");
        // Nothing scheduled: nothing unfired.
        assert!(FaultInjector::new(Vec::new(), None)
            .unfired(1.0, &[])
            .is_empty());
    }

    #[test]
    fn chaos_gaps_average_the_period() {
        let mut rng = SplitMix64::new(3);
        let n = 20_000;
        let mean: f64 = (0..n).map(|_| exp_gap(&mut rng, 2.0)).sum::<f64>() / n as f64;
        assert!((mean - 2.0).abs() < 0.06, "{mean}");
    }
}
