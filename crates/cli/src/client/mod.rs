//! The master's protocol clients, independent of the command line so that other commands
//! (benchmarks, the dashboard, tests) reuse them: [`SdoClient`], [`LssMaster`], the frame
//! decoders of [`decode`], the [`monitor`]'s per-node state and the bus [`scan`].

pub mod decode;
pub mod lss;
pub mod monitor;
pub mod scan;
pub mod sdo;

pub use lss::{Inquire, LssAddress, LssError, LssMaster, LssStatus};
pub use monitor::Monitor;
pub use scan::{scan_bus, ScanResult};
pub use sdo::{SdoClient, SdoError, ValueType};
