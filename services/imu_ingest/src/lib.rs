//! imu_ingest service
