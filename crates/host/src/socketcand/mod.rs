//! The socketcand TCP protocol (raw mode): codec, hub server and client transport.
//!
//! See `docs/TRANSPORT.md` for what python-can expects on the wire.

pub mod client;
pub mod codec;
pub mod hub;
pub mod reconnect;
pub mod session;

pub use client::Client;
pub use hub::{Hub, HubConfig, HubHandle, HubStats, ShutdownHandle, DEFAULT_LISTEN};
