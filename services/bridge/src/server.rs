//! The server side: every slot's keyframes from the network to the mapper, the mapper's
//! feedback back to its client; the slots given by name ([`crate::slots`]).
use std::time::{Duration, Instant};

use shm_schema::topics;
use shm_schema::{KeyframeHeader, KeyframeRecord};
use shoal_runtime::{ErrorKind, ServiceStart};
use zenoh::Wait;

use crate::slots::Slots;
use crate::wire::{self, Welcome};
use crate::{zenoh_config, BridgeCounters, Params, SERVICE_NAME};

type KeyframePub =
    iceoryx2::port::publisher::Publisher<topics::Ipc, [KeyframeRecord], KeyframeHeader>;
type FeedbackSub = iceoryx2::port::subscriber::Subscriber<topics::Ipc, shm_schema::Feedback, ()>;

/// A slot's ports: its keyframes to the mapper, its feedback from it, and that feedback's
/// zenoh publisher.
struct Slot {
    keyframes: KeyframePub,
    feedback: FeedbackSub,
    remote: zenoh::pubsub::Publisher<'static>,
}

/// Runs the server side until SIGINT/SIGTERM.
pub fn run(params: &Params) -> anyhow::Result<()> {
    let mut start = ServiceStart::open(
        SERVICE_NAME,
        "bridge_server",
        params.status.clone(),
        params.ipc_prefix.clone(),
    )?;
    let mut slots = Slots::open(params.clients_file.as_deref(), params.capacity)?;
    let session = zenoh::open(zenoh_config("router", &params.endpoint, true)?)
        .wait()
        .map_err(|e| anyhow::anyhow!("listening on {}: {e}", params.endpoint))?;
    let node = &start.node;
    let mut ports = Vec::new();
    for s in 0..params.capacity {
        let remote = (session.declare_publisher(wire::feedback_key(s)))
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        ports.push(Slot {
            keyframes: topics::keyframe_publisher(&topics::keyframes_service(node, s)?)?,
            feedback: topics::subscriber(&topics::feedback_service(node, s)?)?,
            remote,
        });
    }
    let hello =
        (session.declare_queryable(wire::HELLO_KEY).wait()).map_err(|e| anyhow::anyhow!("{e}"))?;
    let incoming = (session.declare_subscriber(wire::ALL_KEYFRAMES).wait())
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut counters: BridgeCounters = start.status.counters_as();
    eprintln!(
        "[bridge] serving {} client slots on {} ({} known: {})",
        params.capacity,
        params.endpoint,
        slots.names().len(),
        slots.names().join(", ")
    );
    shoal_runtime::signal_ready();
    let mut written = Instant::now();
    loop {
        let mut busy = false;
        while let Ok(Some(q)) = hello.try_recv() {
            busy = true;
            let answer = match q.payload().map(|p| wire::parse_hello(&p.to_bytes())) {
                Some(Ok((version, name))) => slots.welcome(version, &name),
                Some(Err(e)) => Welcome::Refused(e),
                None => Welcome::Refused("an empty hello".into()),
            };
            match &answer {
                Welcome::Slot(_) => counters.hellos += 1,
                Welcome::Refused(why) => {
                    counters.hellos_refused += 1;
                    start
                        .status
                        .error(ErrorKind::Remote, format!("hello refused: {why}"));
                }
            }
            let _ = q.reply(wire::HELLO_KEY, answer.encode()).wait();
        }
        while let Ok(Some(sample)) = incoming.try_recv() {
            busy = true;
            let slot = wire::slot_of(sample.key_expr().as_str());
            let known = slot.filter(|s| slots.name_of(*s).is_some());
            let Some(port) = known.and_then(|s| ports.get(s as usize).map(|p| (s, p))) else {
                counters.keyframes_refused += 1;
                let key = sample.key_expr().as_str().to_string();
                start
                    .status
                    .error(ErrorKind::Remote, format!("{key}: no client has this slot"));
                continue;
            };
            let bytes = sample.payload().to_bytes();
            match forward_keyframe(port.0, &port.1.keyframes, &bytes) {
                Ok(()) => {
                    counters.keyframes_forwarded += 1;
                    counters.keyframe_bytes += bytes.len() as u64;
                }
                Err(e) => {
                    counters.keyframes_refused += 1;
                    start
                        .status
                        .error(ErrorKind::Remote, format!("slot {}: {e}", port.0));
                }
            }
        }
        for p in &ports {
            while let Some(f) = p.feedback.receive()? {
                busy = true;
                let _ = p.remote.put(wire::encode_feedback(f.payload())).wait();
                counters.feedback_forwarded += 1;
            }
        }
        if written.elapsed() >= Duration::from_millis(200) {
            written = Instant::now();
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
    start.status.put_counters(&counters);
    let _ = start.file.write(&start.status);
    let _ = session.close().wait();
    Ok(())
}

/// Publishes a keyframe from the network to the mapper as slot `slot`'s.
fn forward_keyframe(slot: u32, publisher: &KeyframePub, bytes: &[u8]) -> anyhow::Result<()> {
    let (mut h, records, imu) = wire::decode_keyframe(bytes).map_err(anyhow::Error::msg)?;
    h.meta.client_id = slot;
    let n = records.len() + imu.len();
    let sample = publisher.loan_slice_uninit(n)?;
    let mut sample = sample.write_from_fn(|i| match i.checked_sub(records.len()) {
        None => KeyframeRecord::from(records[i]),
        Some(j) => KeyframeRecord::from(imu[j]),
    });
    *sample.user_header_mut() = h;
    sample.send()?;
    Ok(())
}
