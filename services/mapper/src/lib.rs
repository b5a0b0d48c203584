//! mapper service
