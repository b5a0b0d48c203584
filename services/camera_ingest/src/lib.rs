//! camera_ingest service
