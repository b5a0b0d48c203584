//! The global BA of a group's maps on a thread of its own (seed §3.4.2, §5.4: after a loop,
//! a merge or a revisit; issue 19: "off the handler threads"), so the handlers go on with
//! their clients' keyframes while it solves. The handlers only ask for it
//! ([`slam_core::server::KeyframeHandler::take_global_ba`]); [`GlobalBaRunner`] copies the
//! problem out of the map ([`GlobalBa::prepare`]), solves it on its thread and, when the
//! solution is back, writes it into the map as the map is then, carrying the correction over
//! to what entered the map meanwhile ([`GlobalBa::apply`]).
//!
//! One global BA per group at a time; a request for a map while one runs is remembered and
//! started afterwards. A solution is dropped, never applied, when its map was corrected (a
//! merge or a pose graph: [`super::Group::generations`]) or merged away while it solved: the
//! correction asked for a new global BA, which starts next.
//!
//! **Lock-step** (`wait`): the handler thread waits for the solution and applies it at once,
//! at the same point of the keyframe stream on every run, so a lock-step run stays
//! reproducible (and a journal replay takes the same schedule).
use std::collections::BTreeSet;
use std::thread::JoinHandle;
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender};
use slam_core::imu::window::ViParams;
use slam_core::server::{GlobalBa, GlobalBaApplied, MapId, ServerFeedback};
use slam_core::vo::vi_window::ViMappingParams;

use super::{Group, MapFigures, MapSize};

/// A solved (or failed) problem coming back from the thread.
#[derive(Debug)]
pub struct Solved {
    gba: GlobalBa,
    /// The map's generation when the problem was built.
    generation: u64,
    ok: bool,
    solve_ms: f64,
}

/// What became of one global BA.
#[derive(Debug)]
pub struct GlobalBaOutcome {
    /// The map.
    pub map: MapId,
    /// Visual-inertial (a metric, gravity-aligned map) or visual.
    pub inertial: bool,
    /// Keyframes in the problem.
    pub keyframes: usize,
    /// What was written back; `None` when dropped or not solved.
    pub applied: Option<GlobalBaApplied>,
    /// Why it was not applied.
    pub dropped: Option<&'static str>,
    /// Time on the global BA thread, ms.
    pub solve_ms: f64,
    /// Time to write it back on the handler thread, ms.
    pub apply_ms: f64,
    /// The handler thread waited for it (lock-step).
    pub waited: bool,
    /// Feedback of the map's clients (their server poses moved); empty when it waited (the
    /// keyframe or correction it ran within sends theirs).
    pub feedback: Vec<ServerFeedback>,
    /// Figures of the map's clients.
    pub figures: Vec<(u32, MapFigures)>,
    /// Sizes of the group's maps.
    pub maps: Vec<MapSize>,
}

/// The global BA thread of a group and what it is doing (module docs).
#[derive(Debug)]
pub struct GlobalBaRunner {
    tx: Option<Sender<(GlobalBa, u64)>>,
    done: Receiver<Solved>,
    thread: Option<JoinHandle<()>>,
    /// The map whose problem is on the thread.
    in_flight: Option<MapId>,
    /// Maps asked for while one ran.
    again: BTreeSet<MapId>,
    wait: bool,
    vi: ViMappingParams,
}

impl GlobalBaRunner {
    /// Starts the thread (`name`: the group's thread name); `wait` for lock-step.
    pub fn spawn(name: &str, vi: ViMappingParams, wait: bool) -> std::io::Result<Self> {
        let (tx, rx) = crossbeam_channel::unbounded::<(GlobalBa, u64)>();
        let (done_tx, done) = crossbeam_channel::unbounded();
        let solver = vi.solver;
        let thread = std::thread::Builder::new()
            .name(format!("{name}_gba"))
            .spawn(move || solve_loop(&rx, &done_tx, &solver))?;
        Ok(Self {
            tx: Some(tx),
            done,
            thread: Some(thread),
            in_flight: None,
            again: BTreeSet::new(),
            wait,
            vi,
        })
    }

    /// Where solutions come back (to wait on beside the group's jobs).
    pub fn done(&self) -> &Receiver<Solved> {
        &self.done
    }

    /// Takes the handlers' pending requests and starts a global BA of the first map asked
    /// for when none runs. With `wait`, solves and applies it at once and returns what
    /// became of it.
    pub fn request(&mut self, g: &mut Group) -> Vec<GlobalBaOutcome> {
        for cs in g.clients.values_mut() {
            if cs.h.take_global_ba() {
                self.again.extend(cs.h.current_map_id());
            }
        }
        let mut outcomes = Vec::new();
        while self.in_flight.is_none() {
            let Some(map) = self.again.pop_first() else {
                break;
            };
            self.start(g, map);
            if self.wait && self.in_flight.is_some() {
                match self.done.recv() {
                    Ok(s) => outcomes.push(self.finish(g, s)),
                    Err(_) => self.in_flight = None,
                }
            }
        }
        outcomes
    }

    /// Copies map `map`'s problem out and sends it to the thread.
    fn start(&mut self, g: &Group, map: MapId) {
        let Some(m) = g.maps.get(&map) else {
            return;
        };
        let Some(gba) = GlobalBa::prepare(m, &self.vi) else {
            return;
        };
        let generation = g.generations.get(&map).copied().unwrap_or(0);
        if self
            .tx
            .as_ref()
            .is_some_and(|tx| tx.send((gba, generation)).is_ok())
        {
            self.in_flight = Some(map);
        }
    }

    /// A solution came back: applied unless stale (module docs); then the next request
    /// starts (in lock-step, the caller's [`Self::request`] loop starts it).
    pub fn finish(&mut self, g: &mut Group, s: Solved) -> GlobalBaOutcome {
        self.in_flight = None;
        let t0 = Instant::now();
        let (map, inertial, keyframes) = (s.gba.map, s.gba.is_inertial(), s.gba.keyframes());
        let current = g.generations.get(&map).copied().unwrap_or(0) == s.generation;
        let dropped = match (s.ok, g.maps.contains_key(&map), current) {
            (false, _, _) => Some("not solved"),
            (_, false, _) => Some("map merged away"),
            (_, _, false) => Some("map corrected meanwhile"),
            _ => None,
        };
        let applied = dropped
            .is_none()
            .then(|| g.maps.get_mut(&map).and_then(|m| s.gba.apply(m)))
            .flatten();
        let clients: Vec<u32> = g
            .clients
            .iter()
            .filter(|(_, cs)| cs.h.current_map_id() == Some(map))
            .map(|(c, _)| *c)
            .collect();
        if let Some(a) = &applied {
            for c in &clients {
                if let Some(cs) = g.clients.get_mut(c) {
                    cs.h.after_global_ba(a);
                }
            }
        }
        let apply_ms = t0.elapsed().as_secs_f64() * 1e3;
        if !self.wait {
            if let Some(next) = self.again.pop_first() {
                self.start(g, next);
            }
        }
        GlobalBaOutcome {
            map,
            inertial,
            keyframes,
            dropped,
            solve_ms: s.solve_ms,
            apply_ms,
            waited: self.wait,
            feedback: if self.wait || applied.is_none() {
                Vec::new()
            } else {
                clients
                    .iter()
                    .filter_map(|c| g.clients.get(c))
                    .filter_map(|cs| cs.h.feedback(&g.maps))
                    .collect()
            },
            figures: clients.iter().map(|c| (*c, g.figures(*c))).collect(),
            maps: g.sizes(),
            applied,
        }
    }

    /// Ends the thread (a problem on it is solved and dropped).
    pub fn stop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for GlobalBaRunner {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The thread: solves each problem it gets and sends it back, until its queue closes.
fn solve_loop(rx: &Receiver<(GlobalBa, u64)>, done: &Sender<Solved>, params: &ViParams) {
    while let Ok((mut gba, generation)) = rx.recv() {
        let t0 = Instant::now();
        let ok = gba.solve(params);
        let solved = Solved {
            gba,
            generation,
            ok,
            solve_ms: t0.elapsed().as_secs_f64() * 1e3,
        };
        if done.send(solved).is_err() {
            break;
        }
    }
}
