//! canpos-host: the `std` side of canpos — CAN transports and log formats, the runtime that
//! drives simulated devices on them, and its control interface.
//!
//! The modules stand in layers; each names only modules below it (`tests/layering.rs` fails on
//! any import circle between the crate's files):
//!
//! ```text
//!  transport (bus URLs, open)   control::server      lib.rs: curated re-exports
//!        |                           |
//!        |          runtime/ (loop, device wrapper, clock glue, requests, waits)
//!        |           plain   eds_device (+ ini)
//!        |                           |
//!  mem/  socketcand/ (codec, session, client, reconnect, hub/)  socketcan  silkit/  bridge  candump
//!        |                           |
//!  bus/ (bits, timeline)   wake   control::request
//!        |                           |
//!  can (frames, bus state and stats, Disturbance, ErrorFrame, the Transport trait)
//!        |
//!  clock   sys   timing   realtime   file_storage
//! ```
//!
//! - [`can`]: the CAN vocabulary and the [`Transport`] trait every bus connection implements.
//! - [`transport`]: bus URLs and [`open`], on top of every transport (re-exports [`can`]'s
//!   names under their former paths).
//! - [`socketcand`]: the socketcand TCP protocol: codec, a hub server, a client transport.
//! - [`bus`]: the physical bus model (bit timing, arbitration, load, error confinement).
//! - [`clock`]: the simulation clock a bus and its runtimes share (wall, stepped).
//! - [`sys`]: precise sleeps, timer slack, the warning for an exposed socket.
//! - [`mem`]: an in-process bus.
//! - `socketcan`: Linux SocketCAN (cargo feature `socketcan`, on by default).
//! - [`silkit`]: Vector SIL Kit (`silkit://`), its C API loaded at run time (docs/SILKIT.md).
//! - [`candump`]: candump `-L` log lines.
//! - [`file_storage`]: a device's non-volatile storage as one atomically written file.
//! - [`runtime`]: drives simulated sensors on a bus on absolute deadlines.
//! - [`plain`]: drives one plain CiA 301 device (no measurement) the same way.
//! - [`eds_device`]: a plain device's model built from an EDS / DCF file ([`ini`] reads it).
//! - [`control`]: the JSON-lines control interface (requests below the runtime, server above).
#![deny(missing_docs)]

pub mod bridge;
pub mod bus;
pub mod can;
pub mod candump;
pub mod clock;
pub mod control;
pub mod eds_device;
pub mod file_storage;
pub mod ini;
pub mod mem;
pub mod plain;
pub mod realtime;
pub mod runtime;
pub mod silkit;
#[cfg(feature = "socketcan")]
pub mod socketcan;
pub mod socketcand;
pub mod sys;
pub mod timing;
pub mod transport;
mod wake;

pub use crossbeam_channel;
pub use file_storage::FileStorage;
pub use mem::{MemBus, MemPort};
pub use runtime::{ControlHandle, Runtime, RuntimeHandle, SensorSetup};
pub use socketcand::{Client as SocketcandClient, Hub, HubHandle};
pub use sys::warn_if_exposed;
pub use transport::{
    open, open_device_bus, open_or_host, BusUrl, Error, HubPolicy, RxFrame, Transport, DEFAULT_URL,
};
