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

/// A session to the server, with the client's slot.
struct Link {
    session: zenoh::Session,
    slot: u32,
    keyframes: zenoh::pubsub::Publisher<'static>,
    feedback: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
}

/// Opens a session to `endpoint` and asks for the slot of `name`; `Ok(None)` while no server
/// answers, an error when the server refuses the client (for good).
fn connect(endpoint: &str, name: &str) -> anyhow::Result<Option<Link>> {
    let Ok(session) = zenoh::open(zenoh_config("client", endpoint, false)?).wait() else {
        return Ok(None);
    };
    let replies = session
        .get(wire::HELLO_KEY)
        .payload(wire::hello(name))
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
    let slot = match Welcome::decode(&sample.payload().to_bytes()) {
        Ok(Welcome::Slot(s)) => s,
        Ok(Welcome::Refused(why)) => {
            return Err(crate::Refused(format!("{endpoint} refused client {name:?}: {why}")).into())
        }
        Err(e) => anyhow::bail!("{endpoint}: {e}"),
    };
    let keyframes = (session.declare_publisher(wire::keyframe_key(slot)))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let feedback = (session.declare_subscriber(wire::feedback_key(slot)))
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(Some(Link {
        session,
        slot,
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
}

impl Client {
    /// The tracker's keyframes to the server (dropped, and counted, without one: the
    /// tracker sends them again); whether there were any.
    fn keyframes_out(&mut self, sub: &KeyframeSub, link: Option<&Link>) -> anyhow::Result<bool> {
        let mut busy = false;
        while let Some(s) = sub.receive()? {
            busy = true;
            let h = *s.user_header();
            let Some(l) = link else {
                self.counters.keyframes_unsent += 1;
                continue;
            };
            let bytes = match wire::encode_keyframe(&h, s.payload()) {
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
            match wire::decode_feedback(&s.payload().to_bytes(), c) {
                Ok(f) => {
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
        let link = match connect(&params.endpoint, &params.name) {
            Ok(l) => l,
            Err(e) => {
                self.status.error(ErrorKind::Remote, format!("{e:#}"));
                self.write(file);
                return Err(e);
            }
        };
        if let Some(l) = &link {
            self.counters.connects += 1;
            self.counters.hellos = 1;
            self.counters.slot = Some(u64::from(l.slot));
            eprintln!(
                "[bridge:{}] connected to {} as slot {}",
                params.client, params.endpoint, l.slot
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
    let mut me = Client {
        counters: start.status.counters_as(),
        trips: crate::RoundTrips::default(),
        status: std::mem::take(&mut start.status),
    };
    shoal_runtime::signal_ready();
    let (mut link, mut next_try, mut written) = (None::<Link>, Instant::now(), Instant::now());
    loop {
        if link.is_none() && Instant::now() >= next_try {
            link = me.connect(params, &mut start.file)?;
            next_try = Instant::now() + RETRY;
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
