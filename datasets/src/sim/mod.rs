//! The synthetic world generator behind `shoal sim`.
//!
//! A room of textured planes (procedural "dead leaves" textures with mip levels), cameras
//! and IMUs on smooth analytic trajectories, rolling-shutter rendering (each image row at
//! its own time, seed eq. 2.61-2.63), IMU synthesis with noise, bias random walk and
//! intrinsics (seed eq. 2.53-2.56), written as EuRoC ASL folders.
//!
//! ```no_run
//! use datasets::sim::{generate, Scenario, SimParams, SimWorld};
//! let mut params = SimParams::new(Scenario::FastRs);
//! params.frames = Some(40);
//! // On disk (EuRoC layout + groundtruth_cam0.txt):
//! let summary = generate(&params, std::path::Path::new("/tmp/sim_fast_rs"))?;
//! // Or in memory, without disk:
//! let world = SimWorld::new(params)?;
//! let mut img = vec![0u8; 752 * 480];
//! world.render_frame_into(0, &mut img)?;
//! # Ok::<(), datasets::DatasetError>(())
//! ```
//!
//! Time conventions: `cam0/data.csv` holds mid-row stamps on the camera clock; the true
//! capture time of the middle row is stamp + t_d (`time_offset_ns` in `cam0/sensor.yaml`);
//! row `v` (pixel centres at integer `v`) is captured at `t_mid + (v - N/2) t_r / N`
//! (`readout_time_ns`). IMU and ground-truth stamps are on the true clock.
//! `groundtruth_cam0.txt` holds, for each frame, the camera-to-world pose at the true
//! mid-row capture time, stamped with the frame's `data.csv` stamp (identical when t_d = 0).

mod imu_gen;
mod params;
mod render;
mod rng;
mod scenario;
mod scene;
mod texture;
mod trajectory;
mod world;
mod writer;

pub use imu_gen::GtState;
pub use params::{phone_imu, SimParams};
pub use render::{PixelNoise, Renderer};
pub use rng::{mix_seed, splitmix64, Rng};
pub use scenario::{Scenario, CALIB_S, LAP_S, PHONE_LAP_S, PHONE_STEP_HZ};
pub use scene::{Rect, Scene, FIRST_PANEL, MAX_RECTS};
pub use texture::MipTexture;
pub use trajectory::{euroc_t_bs, AnalyticTrajectory, BodyState, Signal, Sine};
pub use world::{SimWorld, FIRST_FRAME_OFFSET_NS, IMU_TAIL_NS};
pub use writer::{generate, AgentSummary, SimSummary};
