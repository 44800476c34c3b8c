//! The control interface (SPEC §12): a loopback TCP server speaking JSON lines, so a test
//! harness in any language can move magnets, inject faults, power-cycle and read the true and
//! reported state. The protocol is documented in `docs/CONTROL.md`.
//!
//! One request per line, one answer line per request:
//!
//! ```text
//! → {"cmd":"magnet","index":0,"mm":250.0}
//! ← {"ok":true}
//! → {"cmd":"fault","name":"nonsense","on":true}
//! ← {"ok":false,"error":"unknown fault `nonsense`; known: missing-magnet, …"}
//! ```

//!
//! [`request`] holds the requests and their parsing (below the runtime, which carries them
//! out); [`server`] the loopback server and its client (above the runtime, whose
//! [`ControlHandle`](crate::runtime::ControlHandle) it calls). Both are re-exported here.

pub mod request;
pub mod server;

pub use request::*;
pub use server::*;

#[cfg(test)]
mod tests;
