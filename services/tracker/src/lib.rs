//! tracker service
