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
/// How often the status file is written.
const STATUS_PERIOD: Duration = Duration::from_millis(200);

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
    let mut counters: BridgeCounters = start.status.counters_as();
    let mut trips = crate::RoundTrips::default();
    shoal_runtime::signal_ready();
    let (mut link, mut next_try, mut written) = (None::<Link>, Instant::now(), Instant::now());
    loop {
        if link.is_none() && Instant::now() >= next_try {
            link = match connect(&params.endpoint, &params.name) {
                Ok(l) => l,
                Err(e) => {
                    start.status.error(ErrorKind::Remote, format!("{e:#}"));
                    start.status.put_counters(&counters);
                    let _ = start.file.write(&start.status);
                    return Err(e);
                }
            };
            next_try = Instant::now() + RETRY;
            if let Some(l) = &link {
                counters.connects += 1;
                counters.hellos = 1;
                counters.slot = Some(u64::from(l.slot));
                eprintln!(
                    "[bridge:{c}] connected to {} as slot {}",
                    params.endpoint, l.slot
                );
            }
        }
        let mut busy = false;
        while let Some(s) = keyframes.receive()? {
            busy = true;
            let h = *s.user_header();
            let Some(l) = &link else {
                counters.keyframes_unsent += 1;
                continue;
            };
            match wire::encode_keyframe(&h, s.payload()) {
                Ok(bytes) => {
                    counters.keyframe_bytes += bytes.len() as u64;
                    match l.keyframes.put(bytes).wait() {
                        Ok(()) => {
                            counters.keyframes_forwarded += 1;
                            trips.sent((h.meta.session_id, h.keyframe_id));
                        }
                        Err(_) => counters.keyframes_unsent += 1,
                    }
                }
                Err(e) => {
                    counters.keyframes_refused += 1;
                    start
                        .status
                        .error(ErrorKind::Remote, format!("keyframe: {e}"));
                }
            }
        }
        if let Some(l) = &link {
            while let Ok(Some(s)) = l.feedback.try_recv() {
                busy = true;
                match wire::decode_feedback(&s.payload().to_bytes(), c) {
                    Ok(f) => {
                        trips.acked((f.acked_session_id, f.acked_keyframe_id));
                        feedback.send_copy(f)?;
                        counters.feedback_forwarded += 1;
                    }
                    Err(e) => {
                        counters.feedback_refused += 1;
                        start
                            .status
                            .error(ErrorKind::Remote, format!("feedback: {e}"));
                    }
                }
            }
        }
        if written.elapsed() >= STATUS_PERIOD {
            written = Instant::now();
            trips.put(&mut counters);
            start.status.put_counters(&counters);
            let _ = start.file.write(&start.status);
        }
        let pause = if busy {
            Duration::ZERO
        } else {
            Duration::from_millis(1)
        };
        if node.wait(pause).is_err() {
            break;
        }
    }
    trips.put(&mut counters);
    start.status.put_counters(&counters);
    let _ = start.file.write(&start.status);
    if let Some(l) = link {
        let _ = l.session.close().wait();
    }
    Ok(())
}
