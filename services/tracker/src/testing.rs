//! Builders of the tracker's inputs from a synthetic world ([`SimWorld`]), for in-process
//! tests of the tracker core and of the cores downstream (the mapper's `core_in_process`):
//! the frame headers and IMU messages the ingests would publish. Built for the tracker's own
//! tests and, with the `testing` feature, for other packages' tests.
use datasets::sim::SimWorld;
use shm_schema::{FrameHeader, ImuMsg, MsgMeta};

/// The IMU message of sample `s` with sequence number `seq` (client 0, session 1).
pub fn imu_msg(seq: u64, s: &datasets::ImuSample) -> ImuMsg {
    ImuMsg {
        meta: MsgMeta::new(0, 1, seq, 0),
        t_ns: s.t_ns,
        gyro: s.gyro,
        accel: s.accel,
    }
}

/// The header of frame `k` of `world` (client 0, session 1, sequence number `k`); past the
/// last frame (e.g. an end of stream) it carries the last frame's time.
pub fn frame_header(world: &SimWorld, k: usize) -> FrameHeader {
    let c = world.calib().model;
    FrameHeader {
        meta: MsgMeta::new(0, 1, k as u64, 0),
        width: c.width,
        height: c.height,
        stride: c.width,
        dataset_index: k as u64,
        t_mid_ns: world.frame_time_ns(k.min(world.n_frames() - 1)),
        readout_ns: world.readout_ns(),
        intrinsics: shoal_runtime::wire::intrinsics_from_camera(&c).0,
        t_bs: shoal_runtime::wire::wire_from_iso(&world.calib().t_bs),
        ..FrameHeader::default()
    }
}
