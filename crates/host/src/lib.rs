//! canpos-host: the `std` side of canpos — CAN transports and log formats.
//!
//! - [`transport`]: the [`Transport`] trait the runtime drives nodes through, bus URLs, [`open`].
//! - [`socketcand`]: the socketcand TCP protocol: codec, a hub server, a client transport.
//! - [`bus`]: the physical bus model (bit timing, arbitration, load, error confinement).
//! - [`clock`]: the simulation clock a bus and its runtimes share (wall, stepped).
//! - [`mem`]: an in-process bus.
//! - `socketcan`: Linux SocketCAN (cargo feature `socketcan`, on by default).
//! - [`candump`]: candump `-L` log lines.
//! - [`file_storage`]: a device's non-volatile storage as one atomically written file.
//! - [`runtime`]: drives simulated sensors on a bus on absolute deadlines.
//! - [`plain`]: drives one plain CiA 301 device (no measurement) the same way.
//! - [`eds_device`]: a plain device's model built from an EDS / DCF file ([`ini`] reads it).
//! - [`control`]: the JSON-lines control interface.
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
