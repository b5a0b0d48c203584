//! Service names and quality of service of every topic, and the one place that opens them,
//! so that every process opens a service with identical settings.
//!
//! Names: `shoal/v{SCHEMA_VERSION}/c{client}/{topic}` for per-client streams and
//! `shoal/v{SCHEMA_VERSION}/{topic}` for host-wide ones.
use iceoryx2::config::Config;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use crate::{
    CorrectionHeader, CorrectionRecord, Feedback, LoopKeyframeHeader, LoopKeypointRecord,
    ResyncRequest, TrackedFeature, TrackedFeaturesHeader, TrackedPose,
};
use crate::{FrameAck, FrameHeader, ImuMsg, KeyframeHeader, KeyframeRecord, SCHEMA_VERSION};

/// The iceoryx2 service flavour used between processes.
pub type Ipc = ipc::Service;

/// Environment variable carrying the iceoryx2 resource prefix of a run (tests isolate
/// themselves with their own prefix).
pub const ENV_IPC_PREFIX: &str = "SHOAL_IPC_PREFIX";
/// Default iceoryx2 resource prefix.
pub const DEFAULT_IPC_PREFIX: &str = "shoal_";

/// Most clients one run supports (sizes of host-wide services).
pub const MAX_CLIENTS: usize = 8;
/// Frames a tracker may have buffered; older ones are overwritten (safe overflow) and the
/// consumer counts the gap as dropped.
pub const FRAME_BUFFER: usize = 2;
/// IMU samples a tracker may have buffered (5 s at 200 Hz).
pub const IMU_BUFFER: usize = 1024;
/// Poses buffered for the recorder.
pub const POSE_BUFFER: usize = 256;
/// Keyframe messages buffered at the mapper, per client.
pub const KEYFRAME_BUFFER: usize = 64;
/// Buffer of the loop corrections topic.
pub const CORRECTION_BUFFER: usize = 16;
/// Most records of one correction message (keyframe deltas + point pairs).
pub const MAX_CORRECTION_RECORDS: usize = 16384;
/// Largest number of keypoints in one keyframe message.
pub const MAX_KEYPOINTS: usize = 4096;
/// Largest number of IMU records in one keyframe message (10 s at 400 Hz). A longer
/// segment (a keyframe more than 10 s after the previous one at 400 Hz) is cut by the
/// tracker to its first `MAX_IMU_RECORDS` samples, never a panic: the tracker counts it
/// (`keyframe_imu_cut`) and logs an `imu_segment_cut` error; the cut segment ends before
/// its keyframe, so the mapper refuses it (`bad_imu_segment`) and applies the keyframe
/// visual-only: the two keyframes are not linked on the server.
pub const MAX_IMU_RECORDS: usize = 4000;
/// Records of the largest keyframe message payload (keypoints and IMU records).
pub const MAX_KEYFRAME_RECORDS: usize = MAX_KEYPOINTS + MAX_IMU_RECORDS;

/// Errors of opening a topic, naming the service.
#[derive(Debug)]
pub struct TopicError {
    /// The service name.
    pub service: String,
    /// What failed.
    pub detail: String,
}

impl core::fmt::Display for TopicError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "service '{}': {}", self.service, self.detail)
    }
}

impl std::error::Error for TopicError {}

fn err(service: &str, e: impl core::fmt::Debug) -> TopicError {
    let mut detail = format!("{e:?}");
    if detail.contains("IncompatibleTypes") {
        detail.push_str(
            " (a process of another shoal build or schema version uses this service name)",
        );
    }
    TopicError {
        service: service.to_string(),
        detail,
    }
}

/// The name of a per-client topic, e.g. `shoal/v4/c0/frames`.
pub fn client_topic(client: u32, topic: &str) -> String {
    format!("shoal/v{SCHEMA_VERSION}/c{client}/{topic}")
}

/// The name of a host-wide topic, e.g. `shoal/v4/loop_keyframes`.
pub fn host_topic(topic: &str) -> String {
    format!("shoal/v{SCHEMA_VERSION}/{topic}")
}

/// iceoryx2 configuration with the given resource prefix (no config file is read).
pub fn config_with_prefix(prefix: &str) -> Result<Config, TopicError> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).map_err(|e| {
        err(
            "config",
            format!("invalid iceoryx2 prefix '{prefix}': {e:?}"),
        )
    })?;
    Ok(config)
}

/// The prefix of this process: `$SHOAL_IPC_PREFIX` or [`DEFAULT_IPC_PREFIX`].
pub fn prefix_from_env() -> String {
    std::env::var(ENV_IPC_PREFIX).unwrap_or_else(|_| DEFAULT_IPC_PREFIX.to_string())
}

/// Creates this process's node, named `name`, on the run's prefix. Signals SIGINT/SIGTERM
/// end `node.wait()`.
pub fn create_node(name: &str, prefix: &str) -> Result<Node<Ipc>, TopicError> {
    set_log_level(LogLevel::Warn);
    let config = config_with_prefix(prefix)?;
    let node_name = NodeName::new(name).map_err(|e| err(name, e))?;
    NodeBuilder::new()
        .name(&node_name)
        .config(&config)
        .create::<Ipc>()
        .map_err(|e| err(name, e))
}

/// Fails with a clear error when services of another schema version exist on this prefix:
/// two shoal builds speaking different layouts must not run side by side.
pub fn check_foreign_versions(prefix: &str) -> Result<(), TopicError> {
    let config = config_with_prefix(prefix)?;
    let mine = format!("shoal/v{SCHEMA_VERSION}/");
    let mut foreign: Option<String> = None;
    <Ipc as iceoryx2::service::Service>::list(&config, |s| {
        let name = s.static_details.name().as_str().to_string();
        if name.starts_with("shoal/v") && !name.starts_with(&mine) {
            foreign = Some(name);
            return CallbackProgression::Stop;
        }
        CallbackProgression::Continue
    })
    .map_err(|e| err("service list", e))?;
    match foreign {
        Some(name) => Err(TopicError {
            service: name.clone(),
            detail: format!(
                "a pipeline of another schema version is running on prefix '{prefix}' \
                 (found '{name}'); this binary speaks schema version {SCHEMA_VERSION}: \
                 refusing to connect"
            ),
        }),
        None => Ok(()),
    }
}

fn service_name(name: &str) -> Result<ServiceName, TopicError> {
    ServiceName::new(name).map_err(|e| err(name, e))
}

/// Frames of a client: `[u8]` pixels with a [`FrameHeader`]. Safe overflow: a slow or dead
/// tracker never blocks the camera.
pub fn frames_service(
    node: &Node<Ipc>,
    client: u32,
) -> Result<PubSubFactory<Ipc, [u8], FrameHeader>, TopicError> {
    let name = client_topic(client, "frames");
    node.service_builder(&service_name(&name)?)
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeader>()
        .enable_safe_overflow(true)
        .subscriber_max_buffer_size(FRAME_BUFFER)
        .subscriber_max_borrowed_samples(FRAME_BUFFER)
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(8)
        .max_nodes(16)
        .open_or_create()
        .map_err(|e| err(&name, e))
}

/// A frame publisher for `max_bytes` pixel bytes per frame (static allocation: no
/// reallocation can lose a frame).
pub fn frame_publisher(
    service: &PubSubFactory<Ipc, [u8], FrameHeader>,
    max_bytes: usize,
    client: u32,
) -> Result<Publisher<Ipc, [u8], FrameHeader>, TopicError> {
    service
        .publisher_builder()
        .initial_max_slice_len(max_bytes)
        .allocation_strategy(AllocationStrategy::Static)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .max_loaned_samples(2)
        .create()
        .map_err(|e| err(&client_topic(client, "frames"), e))
}

/// A frame subscriber.
pub fn frame_subscriber(
    service: &PubSubFactory<Ipc, [u8], FrameHeader>,
    client: u32,
) -> Result<Subscriber<Ipc, [u8], FrameHeader>, TopicError> {
    service
        .subscriber_builder()
        .buffer_size(FRAME_BUFFER)
        .create()
        .map_err(|e| err(&client_topic(client, "frames"), e))
}

macro_rules! fixed_topic {
    ($fn_name:ident, $ty:ty, $topic:expr, $buffer:expr, $doc:expr) => {
        #[doc = $doc]
        pub fn $fn_name(
            node: &Node<Ipc>,
            client: u32,
        ) -> Result<PubSubFactory<Ipc, $ty, ()>, TopicError> {
            fixed_service(node, &client_topic(client, $topic), $buffer)
        }
    };
}

fixed_topic!(
    imu_service,
    ImuMsg,
    "imu",
    IMU_BUFFER,
    "IMU samples of a client. Safe overflow: a dead consumer never blocks the IMU."
);
fixed_topic!(
    frame_ack_service,
    FrameAck,
    "frame_acks",
    64,
    "Frame acknowledgements of a client's tracker (lock-step pacing of the ingests)."
);
fixed_topic!(
    poses_service,
    TrackedPose,
    "poses",
    POSE_BUFFER,
    "Per-frame tracked poses of a client (to the recorder in the launcher)."
);
fixed_topic!(
    feedback_service,
    Feedback,
    "feedback",
    256,
    "Mapper → tracker acknowledgements and pose feedback of a client."
);

/// Keyframe messages of a client: [`KeyframeRecord`] slices (keypoints, then the IMU
/// segment) with a [`KeyframeHeader`].
/// Keyframes must not be lost: the tracker keeps each until the mapper acknowledges it and
/// re-sends unacknowledged ones, so a bounded buffer with safe overflow is safe.
pub fn keyframes_service(
    node: &Node<Ipc>,
    client: u32,
) -> Result<PubSubFactory<Ipc, [KeyframeRecord], KeyframeHeader>, TopicError> {
    keyframe_topic(node, &client_topic(client, "keyframes"))
}

/// Most features in one [`features_service`] message.
pub const MAX_TRACKED_FEATURES: usize = MAX_KEYPOINTS;

/// A frame's tracked features, tracker → viewers (`tracker.publish_features`). Safe
/// overflow: a slow viewer never blocks the tracker.
pub fn features_service(
    node: &Node<Ipc>,
    client: u32,
) -> Result<PubSubFactory<Ipc, [TrackedFeature], TrackedFeaturesHeader>, TopicError> {
    slice_topic(node, &client_topic(client, "features"), POSE_BUFFER)
}

/// Keyframes the mapper kept, forwarded to the loop closer (host-wide, all clients).
/// Safe overflow: a dead loop closer never blocks the mapper.
pub fn loop_keyframes_service(
    node: &Node<Ipc>,
) -> Result<PubSubFactory<Ipc, [LoopKeypointRecord], LoopKeyframeHeader>, TopicError> {
    slice_topic(node, &host_topic("loop_keyframes"), KEYFRAME_BUFFER)
}

/// Resynchronisation requests of a (restarted) loop closer to the mapper (host-wide).
pub fn resync_service(
    node: &Node<Ipc>,
) -> Result<PubSubFactory<Ipc, ResyncRequest, ()>, TopicError> {
    fixed_service(node, &host_topic("loop_resync"), 16)
}

/// A fixed-size topic with safe overflow (a dead consumer never blocks a producer).
fn fixed_service<T: core::fmt::Debug + ZeroCopySend + 'static>(
    node: &Node<Ipc>,
    name: &str,
    buffer: usize,
) -> Result<PubSubFactory<Ipc, T, ()>, TopicError> {
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<T>()
        .enable_safe_overflow(true)
        .subscriber_max_buffer_size(buffer)
        .subscriber_max_borrowed_samples(4)
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(8)
        .max_nodes(16)
        .open_or_create()
        .map_err(|e| err(name, e))
}

/// Loop corrections, loop closer → mapper (host-wide).
pub fn corrections_service(
    node: &Node<Ipc>,
) -> Result<PubSubFactory<Ipc, [CorrectionRecord], CorrectionHeader>, TopicError> {
    slice_topic(node, &host_topic("corrections"), CORRECTION_BUFFER)
}

fn slice_topic<T, H>(
    node: &Node<Ipc>,
    name: &str,
    buffer: usize,
) -> Result<PubSubFactory<Ipc, [T], H>, TopicError>
where
    T: core::fmt::Debug + ZeroCopySend + 'static,
    H: core::fmt::Debug + ZeroCopySend + Default + 'static,
{
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<[T]>()
        .user_header::<H>()
        .enable_safe_overflow(true)
        .subscriber_max_buffer_size(buffer)
        .subscriber_max_borrowed_samples(4)
        .history_size(0)
        .max_publishers(2)
        .max_subscribers(8)
        .max_nodes(16)
        .open_or_create()
        .map_err(|e| err(name, e))
}

/// A publisher of a slice topic with a static allocation of `max_len` elements that never
/// blocks.
pub fn slice_publisher<T, H>(
    service: &PubSubFactory<Ipc, [T], H>,
    max_len: usize,
) -> Result<Publisher<Ipc, [T], H>, TopicError>
where
    T: core::fmt::Debug + ZeroCopySend + 'static,
    H: core::fmt::Debug + ZeroCopySend + 'static,
{
    service
        .publisher_builder()
        .initial_max_slice_len(max_len)
        .allocation_strategy(AllocationStrategy::Static)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .max_loaned_samples(2)
        .create()
        .map_err(|e| err(service.name().as_str(), e))
}

/// A subscriber of a slice topic with a buffer of `buffer` samples.
pub fn slice_subscriber<T, H>(
    service: &PubSubFactory<Ipc, [T], H>,
    buffer: usize,
) -> Result<Subscriber<Ipc, [T], H>, TopicError>
where
    T: core::fmt::Debug + ZeroCopySend + 'static,
    H: core::fmt::Debug + ZeroCopySend + 'static,
{
    service
        .subscriber_builder()
        .buffer_size(buffer)
        .create()
        .map_err(|e| err(service.name().as_str(), e))
}

fn keyframe_topic(
    node: &Node<Ipc>,
    name: &str,
) -> Result<PubSubFactory<Ipc, [KeyframeRecord], KeyframeHeader>, TopicError> {
    slice_topic(node, name, KEYFRAME_BUFFER)
}

/// A keyframe publisher with room for [`MAX_KEYFRAME_RECORDS`] records per message
/// ([`MAX_KEYPOINTS`] keypoints and [`MAX_IMU_RECORDS`] IMU samples).
pub fn keyframe_publisher(
    service: &PubSubFactory<Ipc, [KeyframeRecord], KeyframeHeader>,
) -> Result<Publisher<Ipc, [KeyframeRecord], KeyframeHeader>, TopicError> {
    slice_publisher(service, MAX_KEYFRAME_RECORDS)
}

/// A keyframe subscriber with the service's full buffer.
pub fn keyframe_subscriber(
    service: &PubSubFactory<Ipc, [KeyframeRecord], KeyframeHeader>,
) -> Result<Subscriber<Ipc, [KeyframeRecord], KeyframeHeader>, TopicError> {
    slice_subscriber(service, KEYFRAME_BUFFER)
}

/// Publisher of a fixed-size topic that never blocks.
pub fn publisher<T: core::fmt::Debug + ZeroCopySend>(
    service: &PubSubFactory<Ipc, T, ()>,
) -> Result<Publisher<Ipc, T, ()>, TopicError> {
    service
        .publisher_builder()
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .create()
        .map_err(|e| err(service.name().as_str(), e))
}

/// Subscriber of a fixed-size topic with the service's full buffer.
pub fn subscriber<T: core::fmt::Debug + ZeroCopySend>(
    service: &PubSubFactory<Ipc, T, ()>,
) -> Result<Subscriber<Ipc, T, ()>, TopicError> {
    let size = service.static_config().subscriber_max_buffer_size();
    service
        .subscriber_builder()
        .buffer_size(size)
        .create()
        .map_err(|e| err(service.name().as_str(), e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_versioned() {
        assert_eq!(
            client_topic(3, "frames"),
            format!("shoal/v{SCHEMA_VERSION}/c3/frames")
        );
        assert!(host_topic("loop_keyframes").starts_with("shoal/v"));
    }
}
