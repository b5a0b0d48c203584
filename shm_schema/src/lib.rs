//! The only thing shoal's services share: message types in shared memory, service names,
//! the schema version and the time base.
//!
//! Every payload is `#[repr(C)]` and [`ZeroCopySend`](iceoryx2::prelude::ZeroCopySend), so a
//! sample is read in place by the subscriber. Every message starts with a [`MsgMeta`]
//! carrying a magic number, the [`SCHEMA_VERSION`], (client, session, sequence number) and
//! the host `CLOCK_MONOTONIC` publish stamp: receivers call [`MsgMeta::check`] and count a
//! mismatch as an error instead of misreading the bytes.
//!
//! Service names are versioned (`shoal/v{N}/c{client}/frames`, see [`topics`]): a binary of
//! another schema version opens different services and, through [`topics::check_foreign_versions`],
//! refuses to run next to a pipeline of another version with a clear error.
#![deny(missing_docs)]

pub mod messages;
pub mod time;
pub mod topics;

pub use messages::*;

/// Version of the message layout. Bump on any change of a type in this crate, with the
/// `vN` of every `#[type_name("shoal::vN::…")]` in [`messages`] (a unit test checks that they
/// agree), so that iceoryx2 tells binaries of different layouts apart.
pub const SCHEMA_VERSION: u32 = 4;

/// Magic number at the start of every message (`"SHOL"`).
pub const MAGIC: u32 = 0x5348_4F4C;
