//! Pure SLAM algorithms: no IPC, no threads. Every function here can be tested on plain data.
#![deny(missing_docs)]

pub mod calib;
pub mod camera;
pub mod error;
pub mod features;
pub mod geometry;
pub mod ids;
pub mod imu;
pub mod lie;
pub mod loop_closing;
pub mod metrics;
pub mod optim;
pub mod pgo;
pub mod place;
pub mod pnp;
pub mod ransac;
pub mod rolling_shutter;
#[cfg(feature = "serde")]
pub mod serde_sorted;
pub mod server;
pub mod sessions;
pub mod twoview;
pub mod vio;
pub mod vo;

pub use error::CoreError;
