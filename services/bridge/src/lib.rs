//! The bridge service (issue 22): carries a client's keyframes from its host's shared
//! memory to a server on another host, and the server's feedback back, over zenoh
//! ([`wire`]). One runs beside each remote client's tracker (`--side client`: its keyframes
//! topic out, its feedback topic in) and one beside the server's mapper (`--side server`:
//! every slot's keyframes in, their feedback out), so neither the tracker nor the mapper
//! knows the other is remote.
//!
//! Nothing is acknowledged here: the mapper's feedback crosses back and is the end-to-end
//! acknowledgement; a keyframe the network lost is sent again by its tracker. A client's
//! bridge never blocks its tracker: it drops what it cannot send (counted) while the server
//! is away.
pub mod auth;
pub mod client;
pub mod run_ids;
pub mod server;
pub mod slots;
pub mod tls;
pub mod wire;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// The service's name in reports.
pub const SERVICE_NAME: &str = "bridge";

/// Which end of the connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Side {
    /// Beside a client's tracker: connects to the server.
    Client,
    /// Beside the server's mapper: listens for clients.
    Server,
}

/// Command line of the bridge service.
#[derive(Debug, Clone, clap::Parser)]
#[command(name = "bridge", about = "shoal bridge service (zenoh)")]
pub struct Params {
    /// Which end.
    #[arg(long, value_enum)]
    pub side: Side,
    /// The zenoh endpoint (`tcp/HOST:PORT`): the server listens on it, a client connects to
    /// it.
    #[arg(long)]
    pub endpoint: String,
    /// Client: its name, which keeps its slot on the server across reconnects.
    #[arg(long, default_value = "client")]
    pub name: String,
    /// Client: the local client index (its tracker's).
    #[arg(long, default_value_t = 0)]
    pub client: u32,
    /// Client: this run's id (the launcher's, the same for every start of the bridge in
    /// the run): the server keeps the ids of the client's runs apart by it ([`run_ids`]).
    #[arg(long, default_value_t = 0)]
    pub run: u64,
    /// Server: how many clients it takes (the mapper's `--clients`).
    #[arg(long, default_value_t = 4)]
    pub capacity: u32,
    /// Server: the most keyframes per second it forwards to the mapper, all clients
    /// together (0: no limit); beyond it a keyframe is refused and counted, and its tracker
    /// sends it again later, rather than the server falling behind ([`RateLimit`]).
    #[arg(long, default_value_t = 0.0)]
    pub max_keyframe_rate: f64,
    /// Only known clients ([`auth`]): server: their `NAME:PASSWORD` lines; client: its one
    /// `NAME:PASSWORD` line (its name is the server's).
    #[arg(long)]
    pub auth: Option<PathBuf>,
    /// Server: its TLS certificate (chain, PEM; with `--tls-key`, for a `tls/` endpoint).
    #[arg(long)]
    pub tls_cert: Option<PathBuf>,
    /// Server: its TLS private key (PEM).
    #[arg(long)]
    pub tls_key: Option<PathBuf>,
    /// Client: the CA certificate (PEM) the server's TLS certificate must chain to.
    #[arg(long)]
    pub tls_ca: Option<PathBuf>,
    /// Server: the file of the clients' slots (kept across restarts).
    #[arg(long)]
    pub clients_file: Option<PathBuf>,
    /// Status file (JSON).
    #[arg(long)]
    pub status: Option<PathBuf>,
    /// iceoryx2 resource prefix (default: $SHOAL_IPC_PREFIX or "shoal_").
    #[arg(long)]
    pub ipc_prefix: Option<String>,
}

/// Counters of a bridge (the status file's `counters`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct BridgeCounters {
    /// Keyframe messages sent on (client: to the server; server: to the mapper).
    pub keyframes_forwarded: u64,
    /// Keyframe bytes sent on.
    pub keyframe_bytes: u64,
    /// Client: keyframes dropped while no server was reachable (the tracker sends them
    /// again).
    pub keyframes_unsent: u64,
    /// Keyframes that could not be decoded or came for no known slot (dropped).
    pub keyframes_refused: u64,
    /// Server: keyframes refused beyond `--max-keyframe-rate` (their trackers send them
    /// again).
    pub keyframes_over_rate: u64,
    /// Feedback messages sent on (server: to the client; client: to the tracker).
    pub feedback_forwarded: u64,
    /// Feedback messages that could not be decoded (dropped).
    pub feedback_refused: u64,
    /// Client: feedback for an earlier run of the client (ids below this run's start
    /// base, [`run_ids`]; not passed to the tracker).
    pub feedback_other_runs: u64,
    /// Server: hellos answered with a slot; client: 1 once it has its slot.
    pub hellos: u64,
    /// Server: hellos refused (full, another schema version, a bad or unknown name).
    pub hellos_refused: u64,
    /// Server with `--auth`: connections zenoh refused for their credentials (none, an
    /// unknown name, a wrong password).
    pub auth_refused: u64,
    /// Client: its slot on the server (gauge).
    pub slot: Option<u64>,
    /// Client: this run's start base on the server ([`run_ids`]; gauge; 0 for a name's
    /// first run).
    pub start_base: Option<u64>,
    /// Client: times it reached its server: the first connection, and each time the server
    /// came back after a loss.
    pub connects: u64,
    /// Client: times its session lost the server (a cut, a partition, a server restart).
    pub link_losses: u64,
    /// Client: keyframes whose round trip was timed (sent here → the mapper's
    /// acknowledgement back here; a re-sent keyframe from its last sending).
    pub roundtrips: u64,
    /// Client: median round trip, µs.
    pub roundtrip_us_p50: Option<u64>,
    /// Client: 99th percentile round trip, µs.
    pub roundtrip_us_p99: Option<u64>,
}

/// Round trips of keyframes: when each was sent, and the times of those acknowledged.
#[derive(Debug, Default)]
pub struct RoundTrips {
    sent: std::collections::BTreeMap<(u32, u64), std::time::Instant>,
    us: Vec<u64>,
}

impl RoundTrips {
    /// Keyframe `(session, id)` goes out now.
    pub fn sent(&mut self, key: (u32, u64)) {
        self.sent.insert(key, std::time::Instant::now());
        if self.sent.len() > 4096 {
            // Never acknowledged in ten minutes (its tracker gave up, or was restarted).
            let old = std::time::Duration::from_secs(600);
            self.sent.retain(|_, t| t.elapsed() < old);
        }
    }

    /// The mapper acknowledged keyframe `(session, id)` (acknowledgements are one per
    /// keyframe, in the order the mapper applied them, not cumulative).
    pub fn acked(&mut self, key: (u32, u64)) {
        if let Some(t) = self.sent.remove(&key) {
            self.us.push(t.elapsed().as_micros() as u64);
        }
    }

    /// Puts the count and percentiles in `c`.
    pub fn put(&self, c: &mut BridgeCounters) {
        let mut v = self.us.clone();
        v.sort_unstable();
        let at = |q: f64| {
            v.get(((v.len() as f64 - 1.0) * q).round() as usize)
                .copied()
        };
        c.roundtrips = v.len() as u64;
        c.roundtrip_us_p50 = at(0.5);
        c.roundtrip_us_p99 = at(0.99);
    }
}

/// Seconds' worth of keyframes a [`RateLimit`] lets through at once.
const BURST_S: f64 = 10.0;

/// A token bucket: at most `rate` keyframes a second on average, bursts of [`BURST_S`]
/// seconds' worth (the end of a stream sends a client's whole window at once; a reconnected
/// client re-sends what was lost): the limit is for a server that would fall behind for
/// good, not for a moment.
#[derive(Debug, Clone)]
pub struct RateLimit {
    rate: f64,
    tokens: f64,
    at: std::time::Instant,
}

impl RateLimit {
    /// A full bucket for `rate` keyframes a second (0 or less: no limit).
    pub fn new(rate: f64) -> Self {
        Self {
            rate,
            tokens: Self::burst_of(rate),
            at: std::time::Instant::now(),
        }
    }

    fn burst_of(rate: f64) -> f64 {
        (BURST_S * rate).max(1.0)
    }

    /// Whether one more keyframe may pass at `now` (and takes its token).
    pub fn admit(&mut self, now: std::time::Instant) -> bool {
        if self.rate <= 0.0 {
            return true;
        }
        let dt = now.saturating_duration_since(self.at).as_secs_f64();
        self.at = now;
        self.tokens = (self.tokens + dt * self.rate).min(Self::burst_of(self.rate));
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            return true;
        }
        false
    }
}

/// The server refused the client (full, another schema version, a bad name): for good, so
/// the launcher does not restart the bridge.
#[derive(Debug)]
pub struct Refused(pub String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Refused {}

/// Runs the service; returns the process exit code.
pub fn main_with(params: Params) -> i32 {
    let result = match params.side {
        Side::Client => client::run(&params),
        Side::Server => server::run(&params),
    };
    if let Err(e) = &result {
        if e.downcast_ref::<Refused>().is_some() {
            eprintln!("[{SERVICE_NAME}] {e:#}");
            return shoal_runtime::EXIT_CONFIG;
        }
    }
    shoal_runtime::exit_code(SERVICE_NAME, result)
}

/// How often a bridge writes its status file.
pub(crate) const STATUS_PERIOD: std::time::Duration = std::time::Duration::from_millis(200);

/// Waits up to a millisecond for shared-memory events when the last pass did nothing (not
/// at all when it did); false once SIGINT/SIGTERM came.
pub(crate) fn keep_going(node: &iceoryx2::node::Node<shm_schema::topics::Ipc>, busy: bool) -> bool {
    let pause = if busy {
        std::time::Duration::ZERO
    } else {
        std::time::Duration::from_millis(1)
    };
    node.wait(pause).is_ok()
}

/// A zenoh configuration: `mode`, with `endpoint` to listen on (server) or connect to
/// (client), no multicast scouting (only the given endpoint is used).
pub fn zenoh_config(mode: &str, endpoint: &str, listen: bool) -> anyhow::Result<zenoh::Config> {
    let mut c = zenoh::Config::default();
    set_config(&mut c, "mode", &format!("{mode:?}"))?;
    set_config(&mut c, "scouting/multicast/enabled", "false")?;
    let key = if listen {
        "listen/endpoints"
    } else {
        "connect/endpoints"
    };
    set_config(&mut c, key, &format!("[{endpoint:?}]"))?;
    Ok(c)
}

/// Sets one key of a zenoh configuration (`value` in JSON5); an error names the key, not
/// the value (it may be a password).
pub(crate) fn set_config(c: &mut zenoh::Config, key: &str, value: &str) -> anyhow::Result<()> {
    c.insert_json5(key, value)
        .map_err(|e| anyhow::anyhow!("zenoh configuration {key}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::RateLimit;
    use std::time::{Duration, Instant};

    /// A burst of ten seconds' worth passes, then one keyframe per `1/rate`; no limit at 0.
    #[test]
    fn rate_limit() {
        let t0 = Instant::now();
        let mut r = RateLimit::new(5.0);
        let burst = (0..100).filter(|_| r.admit(t0)).count();
        assert_eq!(burst, 50);
        let mut passed = 0;
        for i in 1..=100 {
            passed += r.admit(t0 + Duration::from_millis(10 * i)) as usize;
        }
        assert_eq!(passed, 5, "one second at 5 a second");
        let mut free = RateLimit::new(0.0);
        assert!((0..1000).all(|_| free.admit(t0)));
    }
}
