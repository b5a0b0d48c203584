//! The client side: the tracker's keyframes to the server, its feedback back.
use std::time::{Duration, Instant};

use shm_schema::topics;
use shoal_runtime::{ErrorKind, ServiceStart};
use zenoh::Wait;

use crate::wire::{self, Welcome};
use crate::{zenoh_config, BridgeCounters, Params, SERVICE_NAME};

/// How long a hello waits for the server's answer.
const HELLO_TIMEOUT: Duration = Duration::from_secs(2);
/// How often a client without a server tries again.
const RETRY: Duration = Duration::from_millis(500);

/// How often a client asks its session whether the server is reachable.
const LIVENESS_PERIOD: Duration = Duration::from_millis(250);

/// A session to the server, with the client's slot. zenoh reconnects a client session by
/// itself when it loses its router (a cut connection, a partition once the lease expired, a
/// restarted server); the declared publisher and subscriber come back with it.
struct Link {
    session: zenoh::Session,
    slot: u32,
    /// This run's start base on the server ([`crate::run_ids`]).
    start_base: u32,
    /// The session had a router when last asked ([`LIVENESS_PERIOD`]).
    up: bool,
    /// When it was last asked.
    asked: Instant,
    keyframes: zenoh::pubsub::Publisher<'static>,
    feedback: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
}

/// Opens a session to the server of `params` and asks for the slot of its client (its
/// name, its run); `Ok(None)` while no server answers, an error when the server refuses the
/// client (for good).
fn connect(
    params: &Params,
    auth: Option<&crate::auth::Credential>,
) -> anyhow::Result<Option<Link>> {
    let (endpoint, name) = (params.endpoint.as_str(), params.name.as_str());
    let mut config = zenoh_config("client", endpoint, false)?;
    if let Some(cred) = auth {
        crate::auth::client_config(&mut config, cred)?;
    }
    if let Some(ca) = &params.tls_ca {
        crate::tls::client_config(&mut config, ca)?;
    }
    let Ok(session) = zenoh::open(config).wait() else {
        return Ok(None);
    };
    let replies = session
        .get(wire::HELLO_KEY)
        .payload(wire::hello(name, params.run))
        .timeout(HELLO_TIMEOUT)
        .wait()
        .map_err(|e| anyhow::anyhow!("hello to {endpoint}: {e}"))?;
    let Ok(reply) = replies.recv() else {
        return Ok(None);
    };
    let sample = match reply.result() {
        Ok(s) => s,
        Err(e) => anyhow::bail!("{endpoint}: the server's hello failed: {e:?}"),
    };
    let (slot, start_base) = match Welcome::decode(&sample.payload().to_bytes()) {
        Ok(Welcome::Slot { slot, start_base }) => (slot, start_base),
        Ok(Welcome::Refused(why)) => {
            return Err(crate::Refused(format!("{endpoint} refused client {name:?}: {why}")).into())
        }
        Err(e) => anyhow::bail!("{endpoint}: {e}"),
    };
    let keyframes = (session.declare_publisher(wire::keyframe_key(name)))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let feedback = (session.declare_subscriber(wire::feedback_key(name)))
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(Some(Link {
        session,
        slot,
        start_base,
        up: true,
        asked: Instant::now(),
        keyframes,
        feedback,
    }))
}

type KeyframeSub = iceoryx2::port::subscriber::Subscriber<
    topics::Ipc,
    [shm_schema::KeyframeRecord],
    shm_schema::KeyframeHeader,
>;
type FeedbackPub = iceoryx2::port::publisher::Publisher<topics::Ipc, shm_schema::Feedback, ()>;

/// The client side's state: its counters and errors, the round trips.
struct Client {
    counters: BridgeCounters,
    trips: crate::RoundTrips,
    status: shoal_runtime::Status,
    /// Its credential (`--auth`).
    auth: Option<crate::auth::Credential>,
    /// Since when no session opens (`None`: one is open).
    failing_since: Option<Instant>,
    /// The server's absence was written in the errors.
    noted: bool,
}

/// After this long without a session the client says so in its errors (once).
const UNREACHABLE_NOTE: Duration = Duration::from_secs(10);

impl Client {
    /// Asks the session whether it has its server now and then; counts the losses and the
    /// reconnections.
    fn liveness(&mut self, link: &mut Link, name: &str) {
        if link.asked.elapsed() < LIVENESS_PERIOD {
            return;
        }
        link.asked = Instant::now();
        let up = (link.session.info().routers_zid().wait()).next().is_some();
        match (link.up, up) {
            (true, false) => {
                self.counters.link_losses += 1;
                eprintln!("[bridge:{name}] lost the server; zenoh reconnects");
            }
            (false, true) => {
                self.counters.connects += 1;
                eprintln!("[bridge:{name}] the server is back");
            }
            _ => {}
        }
        link.up = up;
    }

    /// The tracker's keyframes to the server (dropped, and counted, without one: the
    /// tracker sends them again); whether there were any.
    fn keyframes_out(&mut self, sub: &KeyframeSub, link: Option<&Link>) -> anyhow::Result<bool> {
        let mut busy = false;
        while let Some(s) = sub.receive()? {
            busy = true;
            let h = *s.user_header();
            let Some(l) = link.filter(|l| l.up) else {
                self.counters.keyframes_unsent += 1;
                continue;
            };
            let mut on_server = h;
            let bytes = crate::run_ids::keyframe_to_server(&mut on_server, l.start_base)
                .and_then(|()| wire::encode_keyframe(&on_server, s.payload()));
            let bytes = match bytes {
                Ok(b) => b,
                Err(e) => {
                    self.counters.keyframes_refused += 1;
                    self.status
                        .error(ErrorKind::Remote, format!("keyframe: {e}"));
                    continue;
                }
            };
            self.counters.keyframe_bytes += bytes.len() as u64;
            match l.keyframes.put(bytes).wait() {
                Ok(()) => {
                    self.counters.keyframes_forwarded += 1;
                    self.trips.sent((h.meta.session_id, h.keyframe_id));
                }
                Err(_) => self.counters.keyframes_unsent += 1,
            }
        }
        Ok(busy)
    }

    /// The server's feedback to the tracker (as local client `c`); whether there was any.
    fn feedback_in(
        &mut self,
        link: &Link,
        c: u32,
        publisher: &FeedbackPub,
    ) -> anyhow::Result<bool> {
        let mut busy = false;
        while let Ok(Some(s)) = link.feedback.try_recv() {
            busy = true;
            let mine =
                |mut f| crate::run_ids::feedback_from_server(&mut f, link.start_base).then_some(f);
            match wire::decode_feedback(&s.payload().to_bytes(), c).map(mine) {
                // An earlier run's (its ids are below this run's base): not this tracker's.
                Ok(None) => self.counters.feedback_other_runs += 1,
                Ok(Some(mut f)) => {
                    // Published on this host now: the server's clock is not this one.
                    f.meta.publish_mono_ns = shm_schema::time::monotonic_ns();
                    self.trips.acked((f.acked_session_id, f.acked_keyframe_id));
                    publisher.send_copy(f)?;
                    self.counters.feedback_forwarded += 1;
                }
                Err(e) => {
                    self.counters.feedback_refused += 1;
                    self.status
                        .error(ErrorKind::Remote, format!("feedback: {e}"));
                }
            }
        }
        Ok(busy)
    }

    /// A server that stays out of reach is named in the errors once, with the likely reasons.
    fn note_unreachable(&mut self, params: &Params) {
        let since = *self.failing_since.get_or_insert_with(Instant::now);
        if !self.noted && self.counters.connects == 0 && since.elapsed() >= UNREACHABLE_NOTE {
            self.noted = true;
            let mut why = vec!["no server answers".to_string()];
            if let Some(c) = &self.auth {
                why.push(format!(
                    "it refused the credential of {:?} (--auth)",
                    c.name
                ));
            }
            if let Some(ca) = &params.tls_ca {
                let ca = ca.display();
                why.push(format!(
                    "its TLS certificate is not one {ca} vouches for (--tls-ca)"
                ));
            }
            let why = match why.len() {
                1 => format!("{} there (the client goes on and keeps trying)", why[0]),
                _ => why.join(", or "),
            };
            let s = UNREACHABLE_NOTE.as_secs();
            let text = format!("no session to {} for {s} s: {why}", params.endpoint);
            eprintln!("[bridge:{}] {text}", params.client);
            self.status.error(ErrorKind::Remote, text);
        }
    }

    /// Writes the status file.
    fn write(&mut self, file: &mut shoal_runtime::StatusFile) {
        self.trips.put(&mut self.counters);
        self.status.put_counters(&self.counters);
        let _ = file.write(&self.status);
    }

    /// Tries to connect (a refusal is final: written and returned); the link, if any.
    fn connect(
        &mut self,
        params: &Params,
        file: &mut shoal_runtime::StatusFile,
    ) -> anyhow::Result<Option<Link>> {
        let link = match connect(params, self.auth.as_ref()) {
            Ok(l) => l,
            Err(e) => {
                self.status.error(ErrorKind::Remote, format!("{e:#}"));
                self.write(file);
                return Err(e);
            }
        };
        if link.is_none() {
            self.note_unreachable(params);
        }
        if let Some(l) = &link {
            self.failing_since = None;
            self.counters.connects += 1;
            self.counters.hellos = 1;
            self.counters.slot = Some(u64::from(l.slot));
            self.counters.start_base = Some(u64::from(l.start_base));
            eprintln!(
                "[bridge:{}] connected to {} as slot {} (run {}, start base {})",
                params.client, params.endpoint, l.slot, params.run, l.start_base
            );
        }
        Ok(link)
    }
}

/// Runs the client side until SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<()> {
    let c = params.client;
    let mut start = ServiceStart::open(
        &format!("{SERVICE_NAME}:{c}"),
        &format!("bridge_c{c}"),
        params.status.clone(),
        params.ipc_prefix.clone(),
    )?;
    let node = &start.node;
    let keyframes = topics::keyframe_subscriber(&topics::keyframes_service(node, c)?)?;
    let feedback = topics::publisher(&topics::feedback_service(node, c)?)?;
    let auth = params.auth.as_deref().map(crate::auth::client_credential);
    let mut me = Client {
        counters: start.status.counters_as(),
        trips: crate::RoundTrips::default(),
        status: std::mem::take(&mut start.status),
        auth: auth.transpose()?,
        failing_since: None,
        noted: false,
    };
    if let Some(c) = me.auth.as_ref().filter(|c| c.name != params.name) {
        anyhow::bail!(
            "--name {:?} but the credential is {:?}'s: a client's name is its user",
            params.name,
            c.name
        );
    }
    shoal_runtime::signal_ready();
    let (mut link, mut next_try, mut written) = (None::<Link>, Instant::now(), Instant::now());
    loop {
        if link.is_none() && Instant::now() >= next_try {
            link = me.connect(params, &mut start.file)?;
            next_try = Instant::now() + RETRY;
        }
        if let Some(l) = &mut link {
            me.liveness(l, &params.name);
        }
        let mut busy = me.keyframes_out(&keyframes, link.as_ref())?;
        if let Some(l) = &link {
            busy |= me.feedback_in(l, c, &feedback)?;
        }
        if written.elapsed() >= crate::STATUS_PERIOD {
            written = Instant::now();
            me.write(&mut start.file);
        }
        if !crate::keep_going(node, busy) {
            break;
        }
    }
    me.write(&mut start.file);
    if let Some(l) = link {
        let _ = l.session.close().wait();
    }
    Ok(())
}
