//! loop_closer service
