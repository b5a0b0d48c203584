//! The tracker's IMU input: takes the IMU stream from shared memory, checks it (schema,
//! gaps, monotonic time) and keeps the recent gyro samples, so that each frame's rolling
//! shutter can be compensated with the gyro rate over its readout (rotated into the camera
//! with the frame's `T_BS`).
use std::collections::VecDeque;

use nalgebra::Vector3;
use shm_schema::{FrameHeader, ImuMsg};
use shoal_runtime::{ErrorKind, Status};

use crate::core::TrackerCounters;

/// Gyro samples older than this before the newest frame are dropped, ns.
const KEEP_NS: i64 = 2_000_000_000;

/// Gyro samples older than this before the newest sample are dropped when samples arrive,
/// ns: the buffer stays bounded when no frame asks for the rate (a global-shutter camera),
/// and still covers frames that lag the IMU stream by seconds.
const KEEP_BEHIND_NEWEST_NS: i64 = 10_000_000_000;

/// State of the IMU stream of one client.
#[derive(Debug, Default)]
pub struct ImuInput {
    /// `(seq, t_ns)` of the last sample taken.
    last: Option<(u64, i64)>,
    /// The IMU ingest sent its end of stream.
    pub ended: bool,
    /// Recent gyro samples `(t_ns, ω_body)`, increasing time.
    gyro: VecDeque<(i64, Vector3<f64>)>,
    /// Scratch for the contiguous slice given to `slam_core::imu::mean_rate`.
    scratch: Vec<(i64, Vector3<f64>)>,
}

impl ImuInput {
    /// Takes one sample of the stream: checks its schema, sequence (gaps counted as
    /// dropped, repeats as duplicates) and time (non-monotonic ones are errors), and keeps
    /// its gyro rate. Returns whether the sample was accepted.
    pub fn on_sample(
        &mut self,
        m: &ImuMsg,
        status: &mut Status,
        counters: &mut TrackerCounters,
        client: u32,
    ) -> bool {
        if let Err(e) = m.meta.check() {
            status.error(
                ErrorKind::SchemaVersion,
                format!("imu of client {client}: {e}"),
            );
            return false;
        }
        if m.meta.is_end_of_stream() {
            self.ended = true;
            return false;
        }
        if let Some((seq, t)) = self.last {
            if m.meta.seq <= seq {
                // A restarted IMU ingest resumes from its last status write and publishes
                // again samples its predecessor had sent: already taken.
                counters.imu_samples_duplicate += 1;
                return false;
            }
            if m.meta.seq > seq + 1 {
                counters.imu_samples_dropped += m.meta.seq - seq - 1;
            }
            if m.t_ns <= t {
                let (seq, t_ns) = (m.meta.seq, m.t_ns);
                status.error(
                    ErrorKind::NonMonotonic,
                    format!("imu sample {seq} at {t_ns} ns not after {t} ns"),
                );
                return false;
            }
        }
        self.last = Some((m.meta.seq, m.t_ns));
        counters.imu_samples_received += 1;
        let w = Vector3::from(m.gyro);
        if w.iter().all(|v| v.is_finite()) {
            self.push_gyro(m.t_ns, w);
        }
        true
    }

    /// Keeps gyro sample `w` (body frame, rad/s) at `t_ns` (after the last one), dropping
    /// those more than [`KEEP_BEHIND_NEWEST_NS`] older.
    fn push_gyro(&mut self, t_ns: i64, w: Vector3<f64>) {
        self.gyro.push_back((t_ns, w));
        while self
            .gyro
            .front()
            .is_some_and(|s| s.0 < t_ns - KEEP_BEHIND_NEWEST_NS)
        {
            self.gyro.pop_front();
        }
    }

    /// The IMU stream is live: samples were seen and it has not ended.
    pub fn live(&self) -> bool {
        self.last.is_some() && !self.ended
    }

    /// Time of the newest sample, ns.
    pub fn newest_ns(&self) -> Option<i64> {
        self.gyro.back().map(|s| s.0)
    }

    /// Mean angular rate of the camera (camera frame, rad/s) over the readout of frame `h`,
    /// from the gyro: `ω_c = R_BSᵀ ω_b`. When the samples end inside the readout, the part
    /// they cover is used (at least up to the mid row); `None` without enough samples.
    pub fn camera_rate(&mut self, h: &FrameHeader) -> Option<Vector3<f64>> {
        let half = h.readout_ns / 2;
        let (t0, t1) = (h.t_mid_ns - half, h.t_mid_ns + half);
        while self
            .gyro
            .front()
            .is_some_and(|s| s.0 < h.t_mid_ns - KEEP_NS)
        {
            self.gyro.pop_front();
        }
        let newest = self.newest_ns()?;
        let end = t1.min(newest);
        if end < h.t_mid_ns {
            return None;
        }
        self.scratch.clear();
        self.scratch.extend(self.gyro.iter().copied());
        let w_b = slam_core::imu::mean_rate(&self.scratch, t0, end)?;
        let q = shoal_runtime::wire::rotation_from_wire(&h.t_bs)?;
        Some(q.inverse() * w_b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 60 s of 200 Hz gyro with no frame asking for the rate (global shutter): the buffer
    /// holds the last 10 s, not the whole stream, and a rolling-shutter frame at the end
    /// still gets its rate.
    #[test]
    fn gyro_buffer_is_bounded_without_frames() {
        let mut imu = ImuInput::default();
        let w = Vector3::new(0.1, -0.2, 0.3);
        for k in 0..12_000i64 {
            imu.push_gyro(k * 5_000_000, w);
        }
        assert!(imu.gyro.len() <= 2_001, "{}", imu.gyro.len());
        let h = FrameHeader {
            t_mid_ns: 59_000_000_000,
            readout_ns: 20_000_000,
            ..Default::default()
        };
        let rate = imu.camera_rate(&h).expect("rate over the readout");
        assert!((rate - w).norm() < 1e-9, "{rate}");
    }
}
