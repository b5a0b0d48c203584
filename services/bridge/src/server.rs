//! The server side: every slot's keyframes from the network to the mapper, the mapper's
//! feedback back to its client; the slots given by name ([`crate::slots`]).
use std::time::Instant;

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

/// A slot's ports: its keyframes to the mapper, its feedback from it.
struct Slot {
    keyframes: KeyframePub,
    feedback: FeedbackSub,
}

type Hellos = zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>;
type Incoming =
    zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// The server side's state: the clients' slots, its counters and errors.
struct Server {
    slots: Slots,
    /// `--max-keyframe-rate`.
    rate: crate::RateLimit,
    /// With `--auth`: zenoh's refused handshakes.
    refusals: Option<crate::auth::RefusalCounter>,
    counters: BridgeCounters,
    status: shoal_runtime::Status,
}

impl Server {
    /// Answers the clients' hellos with their slots or a refusal; whether there were any.
    fn hellos(&mut self, hellos: &Hellos) -> bool {
        let mut busy = false;
        while let Ok(Some(q)) = hellos.try_recv() {
            busy = true;
            let answer = match q.payload().map(|p| wire::parse_hello(&p.to_bytes())) {
                Some(Ok(h)) => self.slots.welcome(h.version, &h.name, h.run),
                Some(Err(e)) => Welcome::Refused(e),
                None => Welcome::Refused("an empty hello".into()),
            };
            match &answer {
                Welcome::Slot { .. } => self.counters.hellos += 1,
                Welcome::Refused(why) => {
                    self.counters.hellos_refused += 1;
                    let why = format!("hello refused: {why}");
                    self.status.error(ErrorKind::Remote, why);
                }
            }
            let _ = q.reply(wire::HELLO_KEY, answer.encode()).wait();
        }
        busy
    }

    /// The clients' keyframes to the mapper, each as its name's slot's (a keyframe of a
    /// client without a slot, or that does not decode, is refused and counted); whether
    /// there were any.
    fn keyframes_in(&mut self, incoming: &Incoming, ports: &[Slot]) -> bool {
        let mut busy = false;
        while let Ok(Some(sample)) = incoming.try_recv() {
            busy = true;
            let key = sample.key_expr().as_str();
            let name = wire::name_of(key).unwrap_or_default();
            let slot = self.slots.slot_of(name);
            let Some((s, port)) = slot.and_then(|s| ports.get(s as usize).map(|p| (s, p))) else {
                self.counters.keyframes_refused += 1;
                let why = format!("{key}: no client of this name said hello");
                self.status.error(ErrorKind::Remote, why);
                continue;
            };
            if !self.rate.admit(Instant::now()) {
                if self.counters.keyframes_over_rate == 0 {
                    let why = format!("{key}: over --max-keyframe-rate, refused (sent again)");
                    self.status.error(ErrorKind::Remote, why);
                }
                self.counters.keyframes_over_rate += 1;
                continue;
            }
            let bytes = sample.payload().to_bytes();
            match forward_keyframe(s, &port.keyframes, &bytes) {
                Ok(start) => {
                    self.slots.saw_start(name, start);
                    self.counters.keyframes_forwarded += 1;
                    self.counters.keyframe_bytes += bytes.len() as u64;
                }
                Err(e) => {
                    self.counters.keyframes_refused += 1;
                    self.status
                        .error(ErrorKind::Remote, format!("slot {s}: {e}"));
                }
            }
        }
        busy
    }

    /// The mapper's feedback to each slot's client; whether there was any.
    fn feedback_out(&mut self, session: &zenoh::Session, ports: &[Slot]) -> anyhow::Result<bool> {
        let mut busy = false;
        for (s, p) in ports.iter().enumerate() {
            while let Some(f) = p.feedback.receive()? {
                busy = true;
                // Feedback of a slot nobody has (a journal's from an earlier table) has no
                // one to go to.
                let Some(name) = self.slots.name_of(s as u32) else {
                    continue;
                };
                let _ = (session.put(wire::feedback_key(name), wire::encode_feedback(f.payload())))
                    .wait();
                self.counters.feedback_forwarded += 1;
            }
        }
        Ok(busy)
    }

    fn write(&mut self, file: &mut shoal_runtime::StatusFile) {
        self.counters.auth_refused = self.refusals.as_ref().map_or(0, |r| r.count());
        self.status.put_counters(&self.counters);
        let _ = file.write(&self.status);
    }
}

/// Each slot's shared-memory ports.
fn slot_ports(
    node: &iceoryx2::node::Node<topics::Ipc>,
    capacity: u32,
) -> anyhow::Result<Vec<Slot>> {
    let mut ports = Vec::new();
    for s in 0..capacity {
        ports.push(Slot {
            keyframes: topics::keyframe_publisher(&topics::keyframes_service(node, s)?)?,
            feedback: topics::subscriber(&topics::feedback_service(node, s)?)?,
        });
    }
    Ok(ports)
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
    let mut config = zenoh_config("router", &params.endpoint, true)?;
    if let (Some(cert), Some(key)) = (&params.tls_cert, &params.tls_key) {
        crate::tls::server_config(&mut config, cert, key)?;
    }
    let refusals = match &params.auth {
        Some(file) => {
            slots = slots.only(crate::auth::server_config(&mut config, file)?);
            Some(crate::auth::RefusalCounter::install())
        }
        None => None,
    };
    let session = (zenoh::open(config).wait())
        .map_err(|e| anyhow::anyhow!("listening on {}: {e}", params.endpoint))?;
    let ports = slot_ports(&start.node, params.capacity)?;
    let hellos =
        (session.declare_queryable(wire::HELLO_KEY).wait()).map_err(|e| anyhow::anyhow!("{e}"))?;
    let incoming = (session.declare_subscriber(wire::ALL_KEYFRAMES).wait())
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let wire = if crate::tls::is_tls(&params.endpoint) {
        "TLS"
    } else {
        "not encrypted"
    };
    eprintln!(
        "[bridge] serving {} client slots on {} ({wire}; known: {})",
        params.capacity,
        params.endpoint,
        slots.names().join(", ")
    );
    let mut me = Server {
        slots,
        rate: crate::RateLimit::new(params.max_keyframe_rate),
        refusals,
        counters: start.status.counters_as(),
        status: std::mem::take(&mut start.status),
    };
    shoal_runtime::signal_ready();
    let mut written = Instant::now();
    loop {
        let busy = me.hellos(&hellos)
            | me.keyframes_in(&incoming, &ports)
            | me.feedback_out(&session, &ports)?;
        if written.elapsed() >= crate::STATUS_PERIOD {
            written = Instant::now();
            me.write(&mut start.file);
        }
        if !crate::keep_going(&start.node, busy) {
            break;
        }
    }
    me.write(&mut start.file);
    let _ = session.close().wait();
    Ok(())
}

/// Publishes a keyframe from the network to the mapper as slot `slot`'s; the tracker start
/// its ids carry ([`crate::run_ids::server_start`]).
fn forward_keyframe(slot: u32, publisher: &KeyframePub, bytes: &[u8]) -> anyhow::Result<u32> {
    let (mut h, records, imu) = wire::decode_keyframe(bytes).map_err(anyhow::Error::msg)?;
    h.meta.client_id = slot;
    // Published on this host now: the client's clock is not this one.
    h.meta.publish_mono_ns = shm_schema::time::monotonic_ns();
    let n = records.len() + imu.len();
    let sample = publisher.loan_slice_uninit(n)?;
    let mut sample = sample.write_from_fn(|i| match i.checked_sub(records.len()) {
        None => KeyframeRecord::from(records[i]),
        Some(j) => KeyframeRecord::from(imu[j]),
    });
    *sample.user_header_mut() = h;
    sample.send()?;
    Ok(crate::run_ids::server_start(&h))
}
