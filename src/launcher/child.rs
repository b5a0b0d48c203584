//! One supervised child process: spawn, readiness, exit, restart back-off.
//!
//! Children run `shoal service NAME ...` (the same binary), in their own process group (so a
//! terminal Ctrl-C reaches the launcher first, which then stops them in order) and with
//! `PR_SET_PDEATHSIG = SIGKILL` (a child never outlives a killed launcher). Their stdout is
//! read by a thread that watches for the readiness line and copies the rest, with stderr, to
//! `OUT/logs/NAME.log`.
use std::io::{BufRead, BufReader, Write};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

/// Back-off before the first restart (and after a kill the launcher injected itself).
pub const FIRST_BACKOFF: Duration = Duration::from_millis(100);

/// A process that ran this long after being ready resets the restart back-off.
pub const STABLE_AFTER: Duration = Duration::from_secs(5);

/// What is known of a child's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Spawned, readiness line not seen yet.
    Starting,
    /// Ready for data.
    Running,
    /// Exited with success after its input ended (or was stopped by the launcher).
    Done,
    /// Crashed; to be restarted at the given time.
    WaitingRestart(Instant),
    /// Failed for good (configuration error or too many restarts).
    Failed,
}

/// A supervised service process.
pub struct Supervised {
    /// Service name in reports, e.g. `tracker:0`.
    pub name: String,
    /// Arguments after `shoal service`.
    pub args: Vec<String>,
    /// Extra environment.
    pub env: Vec<(String, String)>,
    /// Log file.
    pub log: PathBuf,
    /// Status file the service keeps.
    pub status: PathBuf,
    /// Current process, if any.
    pub child: Option<Child>,
    /// Readiness notifications of the current process.
    ready_rx: Option<Receiver<()>>,
    /// Life phase.
    pub phase: Phase,
    /// Restarts so far.
    pub restarts: u32,
    /// When the current process was spawned.
    pub spawned_at: Instant,
    /// When a crash was last seen (for recovery times).
    pub crashed_at: Option<Instant>,
    /// Recovery times (crash seen → ready again), seconds.
    pub recoveries_s: Vec<f64>,
    /// When the current process printed its readiness line.
    pub ready_at: Option<Instant>,
    /// True for services that end by themselves at the end of their input.
    pub ends_by_itself: bool,
    /// Crashes in a row, each within [`STABLE_AFTER`] of its start being ready (sets the
    /// back-off; a process that ran longer resets it).
    pub quick_crashes: u32,
    /// The current process was SIGKILLed by the launcher's own fault injection (`--kill`,
    /// `--chaos`): its death is not a crash of the service and does not raise the back-off.
    pub kill_injected: bool,
    /// CPU time (user + system, s) of this service's processes that were reaped, summed over
    /// all its starts (from `wait4`'s resource usage of each process).
    pub cpu_s: f64,
    /// Per restart: when the new process was spawned and the status counters it resumed from
    /// (the file the dead process left, read just before the new one started).
    pub restart_snapshots: Vec<(Instant, std::collections::BTreeMap<String, u64>)>,
}

/// How a child ended.
pub fn describe_exit(st: &ExitStatus) -> String {
    match (st.code(), st.signal()) {
        (Some(c), _) => format!("exit code {c}"),
        (None, Some(s)) => format!("killed by signal {s}"),
        _ => "unknown exit".to_string(),
    }
}

impl Supervised {
    /// A service to supervise (not started yet).
    pub fn new(name: &str, args: Vec<String>, out: &Path, ends_by_itself: bool) -> Self {
        let file = name.replace(':', "_c");
        Self {
            name: name.to_string(),
            args,
            env: Vec::new(),
            log: out.join("logs").join(format!("{file}.log")),
            status: out.join("status").join(format!("{file}.json")),
            child: None,
            ready_rx: None,
            phase: Phase::Starting,
            restarts: 0,
            spawned_at: Instant::now(),
            crashed_at: None,
            recoveries_s: Vec::new(),
            ready_at: None,
            ends_by_itself,
            quick_crashes: 0,
            kill_injected: false,
            cpu_s: 0.0,
            restart_snapshots: Vec::new(),
        }
    }

    /// Spawns the process.
    pub fn spawn(&mut self, exe: &Path) -> std::io::Result<()> {
        if let Some(dir) = self.log.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)?;
        writeln!(log, "--- start #{} of {} ---", self.restarts + 1, self.name)?;
        self.kill_injected = false;
        let mut cmd = Command::new(exe);
        cmd.arg("service")
            .args(&self.args)
            .arg("--status")
            .arg(&self.status);
        cmd.envs(self.env.iter().map(|(k, v)| (k, v)));
        cmd.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log.try_clone()?);
        cmd.process_group(0);
        // SAFETY: prctl is async-signal-safe; nothing else runs between fork and exec.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        let mut child = cmd.spawn()?;
        let (tx, rx) = channel();
        if let Some(stdout) = child.stdout.take() {
            std::thread::spawn(move || {
                for line in BufReader::new(stdout).lines() {
                    let Ok(line) = line else { break };
                    if line.trim() == shoal_runtime::READY_LINE {
                        let _ = tx.send(());
                    } else {
                        let _ = writeln!(log, "{line}");
                    }
                }
            });
        }
        self.child = Some(child);
        self.ready_rx = Some(rx);
        self.phase = Phase::Starting;
        self.spawned_at = Instant::now();
        Ok(())
    }

    /// Checks for the readiness line; true when the service just became ready.
    pub fn poll_ready(&mut self) -> bool {
        if self.phase != Phase::Starting {
            return false;
        }
        if self
            .ready_rx
            .as_ref()
            .is_some_and(|rx| rx.try_recv().is_ok())
        {
            self.phase = Phase::Running;
            self.ready_at = Some(Instant::now());
            if let Some(t) = self.crashed_at.take() {
                self.recoveries_s.push(t.elapsed().as_secs_f64());
            }
            return true;
        }
        false
    }

    /// Whether exit `st` is the end of the service's work, not a crash: a clean exit of a
    /// service that ends by itself at the end of its input (even during start-up: an IMU
    /// ingest of a dataset without IMU samples signals ready and ends at once).
    pub fn ended_cleanly(&self, st: &ExitStatus) -> bool {
        st.success() && self.ends_by_itself
    }

    /// Reaps the child if it exited (waitpid, so no zombie keeps its PID and locks alive).
    pub fn try_reap(&mut self) -> Option<ExitStatus> {
        self.reap(false)
    }

    /// Reaps the child with `wait4` (blocking or not) and adds its CPU time to `cpu_s`.
    /// `std::process::Child::try_wait` would discard the child's resource usage, which is
    /// only available when the process is reaped.
    fn reap(&mut self, block: bool) -> Option<ExitStatus> {
        let pid = self.child.as_ref()?.id() as libc::pid_t;
        let mut raw = 0;
        // SAFETY: an all-zero rusage is a valid value of this plain C struct.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        let flags = if block { 0 } else { libc::WNOHANG };
        loop {
            // SAFETY: wait4 on our own child's pid with valid out-pointers.
            let r = unsafe { libc::wait4(pid, &mut raw, flags, &mut usage) };
            if r == pid {
                let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
                self.cpu_s += tv(usage.ru_utime) + tv(usage.ru_stime);
                // The process is reaped: dropping the `Child` neither waits nor kills.
                self.child = None;
                return Some(ExitStatus::from_raw(raw));
            }
            if r == -1 && std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted
            {
                continue;
            }
            return None;
        }
    }

    /// CPU time (user + system, s) the running child has used so far (`/proc/PID/stat`),
    /// 0 when there is none or it cannot be read.
    pub fn running_cpu_s(&self) -> f64 {
        let Some(pid) = self.pid() else { return 0.0 };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            return 0.0;
        };
        // Fields after the command name (which may hold spaces) closed by the last ')'.
        let Some((_, rest)) = stat.rsplit_once(')') else {
            return 0.0;
        };
        let f: Vec<&str> = rest.split_whitespace().collect();
        // SAFETY: sysconf has no preconditions.
        let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
        let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
        // utime and stime are fields 14 and 15 of stat(5), 12 and 13 after the name.
        (ticks(11) + ticks(12)) as f64 / hz
    }

    /// Process id of the running child.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// Sends `sig` to the running child.
    pub fn signal(&self, sig: i32) {
        if let Some(pid) = self.pid() {
            // SAFETY: plain kill(2) on our own child's pid.
            unsafe {
                libc::kill(pid as i32, sig);
            }
        }
    }

    /// Back-off before the next restart: 100 ms doubling per crash in a row, at most 3.2 s.
    pub fn backoff(&self) -> Duration {
        FIRST_BACKOFF * (1u32 << self.quick_crashes.min(5))
    }

    /// Notes a crash of the current process; returns the back-off before its restart. A
    /// process that had been ready for [`STABLE_AFTER`] resets the back-off, so a service
    /// that crashes now and then is not restarted ever more slowly. A kill injected by the
    /// launcher itself is no crash of the service: the first back-off, the count of crashes
    /// in a row unchanged (under `--chaos` a service killed every few seconds used to be
    /// restarted after up to 3.2 s).
    pub fn note_crash(&mut self) -> Duration {
        if std::mem::take(&mut self.kill_injected) {
            return FIRST_BACKOFF;
        }
        let stable = self
            .ready_at
            .is_some_and(|r| r > self.spawned_at && r.elapsed() >= STABLE_AFTER);
        if stable {
            self.quick_crashes = 0;
        }
        let b = self.backoff();
        self.quick_crashes += 1;
        b
    }

    /// Waits up to `timeout` for the child to exit, then SIGKILLs and reaps it.
    pub fn stop(&mut self, timeout: Duration) -> Option<ExitStatus> {
        self.signal(libc::SIGTERM);
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Some(st) = self.try_reap() {
                return Some(st);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        self.signal(libc::SIGKILL);
        self.reap(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crashes_in_a_row_double_the_backoff_but_injected_kills_do_not() {
        let dir = std::env::temp_dir();
        let mut sv = Supervised::new("tracker:0", Vec::new(), &dir, false);
        let ms = |d: Duration| d.as_millis();
        assert_eq!(ms(sv.note_crash()), 100);
        assert_eq!(ms(sv.note_crash()), 200);
        assert_eq!(ms(sv.note_crash()), 400);
        // The launcher's own SIGKILL (--kill, --chaos): first back-off, count unchanged.
        sv.kill_injected = true;
        assert_eq!(ms(sv.note_crash()), 100);
        assert_eq!(sv.quick_crashes, 3);
        assert!(!sv.kill_injected, "one kill, one exemption");
        assert_eq!(ms(sv.note_crash()), 800);
        // Ready for longer than STABLE_AFTER: the back-off starts again.
        sv.spawned_at = Instant::now() - STABLE_AFTER * 3;
        sv.ready_at = Some(Instant::now() - STABLE_AFTER * 2);
        assert_eq!(ms(sv.note_crash()), 100);
        sv.spawned_at = Instant::now(); // restarted, not ready yet
        for _ in 0..10 {
            sv.note_crash();
        }
        assert_eq!(ms(sv.backoff()), 3200, "capped");
    }
}
