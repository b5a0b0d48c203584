//! [`SimWorld`]: one agent of a scenario in memory: timing, poses, IMU and frame rendering.

use std::sync::Arc;

use nalgebra::Isometry3;
use slam_core::camera::PinholeRadtan;
use slam_core::rolling_shutter;

use super::imu_gen::{self, GtState, ImuSynthesis};
use super::params::SimParams;
use super::render::{PixelNoise, Renderer};
use super::rng::mix_seed;
use super::scene::Scene;
use super::trajectory::AnalyticTrajectory;
use crate::{CameraCalib, DatasetError, ImuSample};

/// Time from the start of the IMU stream to the first frame stamp, ns.
pub const FIRST_FRAME_OFFSET_NS: i64 = 100_000_000;
/// IMU data kept after the last frame, ns.
pub const IMU_TAIL_NS: i64 = 100_000_000;

/// One simulated agent (camera + IMU) in the world, fully in memory.
///
/// Clocks: [`SimWorld::frame_time_ns`] is the mid-row stamp on the camera clock (as written
/// to `cam0/data.csv`); the true capture time of the middle row is that stamp plus the
/// camera-IMU offset t_d ([`SimWorld::frame_capture_time_ns`]). IMU samples, ground-truth
/// states and [`SimWorld::pose_cam_at`] use the true clock.
#[derive(Debug, Clone)]
pub struct SimWorld {
    params: SimParams,
    agent: usize,
    traj: AnalyticTrajectory,
    scene: Arc<Scene>,
    renderer: Renderer,
    n_frames: usize,
    period_ns: i64,
    readout_ns: i64,
    time_offset_ns: i64,
    imu: Vec<ImuSample>,
    states: Vec<GtState>,
}

impl SimWorld {
    /// Agent 0 of `params.scenario` (builds the scene textures: ~1 s).
    pub fn new(params: SimParams) -> Result<Self, DatasetError> {
        let scene = Arc::new(Scene::room(params.seed));
        Self::with_scene(params, 0, scene)
    }

    /// Agent `agent` of the scenario in an already built scene (agents of one scenario share
    /// the scene and the world frame).
    pub fn with_scene(
        params: SimParams,
        agent: usize,
        scene: Arc<Scene>,
    ) -> Result<Self, DatasetError> {
        params.validate()?;
        let traj =
            params
                .scenario
                .trajectory(agent)
                .ok_or_else(|| DatasetError::InvalidConfig {
                    detail: format!("scenario {} has no agent {agent}", params.scenario),
                })?;
        let n_frames = params.n_frames();
        let period_ns = params.frame_period_ns();
        let readout_ns = params.readout_ns();
        let time_offset_ns = params.time_offset_ns();
        let imu_period_ns = (1e9 / params.imu_rate_hz).round() as i64;
        let last_frame_ns = FIRST_FRAME_OFFSET_NS + (n_frames as i64 - 1) * period_ns;
        let imu_end_ns = last_frame_ns + time_offset_ns.max(0) + readout_ns / 2 + IMU_TAIL_NS;
        let n_imu = (imu_end_ns / imu_period_ns + 1).max(2) as usize;
        let (imu, states) = imu_gen::synthesize(
            &traj,
            &ImuSynthesis {
                start_ns: params.start_ns,
                period_ns: imu_period_ns,
                n_samples: n_imu,
                noise: params.noise,
                intrinsics: params.imu_intrinsics,
                initial_biases: params.initial_biases,
                seed: mix_seed(params.seed, &[0x1A0, agent as u64]),
            },
        );
        let renderer = Renderer::new(params.camera());
        Ok(Self {
            params,
            agent,
            traj,
            scene,
            renderer,
            n_frames,
            period_ns,
            readout_ns,
            time_offset_ns,
            imu,
            states,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &SimParams {
        &self.params
    }

    /// Index of this agent in its scenario.
    pub fn agent(&self) -> usize {
        self.agent
    }

    /// The shared scene.
    pub fn scene(&self) -> &Arc<Scene> {
        &self.scene
    }

    /// The analytic trajectory (time in seconds since `params.start_ns`).
    pub fn trajectory(&self) -> &AnalyticTrajectory {
        &self.traj
    }

    /// The camera model.
    pub fn camera(&self) -> &PinholeRadtan {
        self.renderer.camera()
    }

    /// Camera calibration as a reader of the written dataset reports it.
    pub fn calib(&self) -> CameraCalib {
        CameraCalib {
            model: *self.camera(),
            t_bs: self.traj.t_bs,
            t_bs_given: true,
            readout_ns: self.readout_ns,
            time_offset_ns: self.time_offset_ns,
            rate_hz: self.params.rate_hz,
        }
    }

    /// Number of frames.
    pub fn n_frames(&self) -> usize {
        self.n_frames
    }

    /// Rolling-shutter readout time t_r, ns (0 = global shutter).
    pub fn readout_ns(&self) -> i64 {
        self.readout_ns
    }

    /// Camera-IMU time offset t_d, ns (capture time = stamp + t_d).
    pub fn time_offset_ns(&self) -> i64 {
        self.time_offset_ns
    }

    /// Mid-row stamp of frame `k` on the camera clock (the `cam0/data.csv` timestamp).
    /// Defined for any `k` (the trajectory is analytic), frames `0..n_frames()` are written.
    pub fn frame_time_ns(&self, k: usize) -> i64 {
        self.params.start_ns + FIRST_FRAME_OFFSET_NS + k as i64 * self.period_ns
    }

    /// True capture time of the middle row of frame `k`: stamp + t_d.
    pub fn frame_capture_time_ns(&self, k: usize) -> i64 {
        self.frame_time_ns(k) + self.time_offset_ns
    }

    /// True capture time of image row `row` of frame `k`
    /// ([`rolling_shutter::row_time_ns`] with `v = row`).
    pub fn row_time_ns(&self, k: usize, row: u32) -> i64 {
        rolling_shutter::row_time_ns(
            self.frame_capture_time_ns(k),
            self.readout_ns,
            f64::from(row),
            self.camera().height,
        )
    }

    fn t_s(&self, t_ns: i64) -> f64 {
        (t_ns - self.params.start_ns) as f64 * 1e-9
    }

    /// Camera-to-world pose `T_WC` at true time `t_ns`.
    pub fn pose_cam_at(&self, t_ns: i64) -> Isometry3<f64> {
        self.traj.pose_cam(self.t_s(t_ns))
    }

    /// Body (IMU) pose `T_WB` at true time `t_ns`.
    pub fn pose_body_at(&self, t_ns: i64) -> Isometry3<f64> {
        self.traj.pose_body(self.t_s(t_ns))
    }

    /// The camera pose the renderer uses for row `row` of frame `k`.
    pub fn row_pose(&self, k: usize, row: u32) -> Isometry3<f64> {
        self.pose_cam_at(self.row_time_ns(k, row))
    }

    /// Renders frame `k` into `dst` (`width * height` bytes, caller-owned; no allocation).
    /// Frames of the `blackout` scenario's gap come out all black (0).
    pub fn render_frame_into(&self, k: usize, dst: &mut [u8]) -> Result<(), DatasetError> {
        if self
            .params
            .scenario
            .blank_frames(self.n_frames, self.params.rate_hz)
            .contains(&k)
        {
            let cam = self.renderer.camera();
            let need = cam.width as usize * cam.height as usize;
            if dst.len() != need {
                return Err(DatasetError::InvalidConfig {
                    detail: format!(
                        "render buffer has {} bytes, the image needs {need}",
                        dst.len()
                    ),
                });
            }
            dst.fill(0);
            return Ok(());
        }
        let noise = PixelNoise {
            seed: mix_seed(self.params.seed, &[0x919, self.agent as u64, k as u64]),
            sigma: self.params.pixel_noise_sigma,
        };
        self.renderer
            .render_into(&self.scene, |row| self.row_pose(k, row), noise, dst)
    }

    /// Renders frame `k` into `img` (as [`SimWorld::render_frame_into`]) and wraps it as the
    /// VO's input with the frame's stamp and readout, no angular rate (callers that feed the
    /// VO in-process override `t_ns` or `angular_velocity` with struct-update syntax).
    pub fn vo_frame<'a>(
        &self,
        k: usize,
        img: &'a mut [u8],
    ) -> Result<slam_core::vo::VoFrame<'a>, DatasetError> {
        self.render_frame_into(k, img)?;
        let cam = self.renderer.camera();
        let image = slam_core::features::GrayImage::from_packed(
            img,
            cam.width as usize,
            cam.height as usize,
        )
        .map_err(|e| DatasetError::InvalidConfig {
            detail: format!("frame {k}: {e}"),
        })?;
        Ok(slam_core::vo::VoFrame {
            image,
            t_ns: self.frame_time_ns(k),
            readout_ns: self.readout_ns(),
            angular_velocity: None,
        })
    }

    /// Renders, for frame `k`, the index + 1 of the scene rectangle seen by each pixel
    /// (0 = none), with the same per-row poses as [`SimWorld::render_frame_into`].
    pub fn render_labels_into(&self, k: usize, dst: &mut [u8]) -> Result<(), DatasetError> {
        self.renderer
            .render_labels_into(&self.scene, |row| self.row_pose(k, row), dst)
    }

    /// IMU samples (true clock), covering all frames with margins.
    pub fn imu_samples(&self) -> &[ImuSample] {
        &self.imu
    }

    /// Ground-truth body states at the IMU sample times.
    pub fn ground_truth_states(&self) -> &[GtState] {
        &self.states
    }

    /// Length of the camera path between the first and last frame, m.
    pub fn path_length_m(&self) -> f64 {
        let (t0, t1) = (
            self.frame_capture_time_ns(0),
            self.frame_capture_time_ns(self.n_frames.saturating_sub(1)),
        );
        let step = 5_000_000;
        let mut len = 0.0;
        let mut prev = self.pose_cam_at(t0).translation.vector;
        let mut t = t0;
        while t < t1 {
            t = (t + step).min(t1);
            let p = self.pose_cam_at(t).translation.vector;
            len += (p - prev).norm();
            prev = p;
        }
        len
    }

    /// Duration between the first and the last frame, s.
    pub fn duration_s(&self) -> f64 {
        (self.frame_time_ns(self.n_frames.saturating_sub(1)) - self.frame_time_ns(0)) as f64 * 1e-9
    }
}
