//! shm schema
