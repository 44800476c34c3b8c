//! canpos-core: a CANopen device (CiA 301 / 305) as firmware would run it, with the CiA 406
//! position sensors as its application.
//!
//! `#![no_std]`, no allocation, no `unsafe`, sans-IO: frames go in through
//! [`Node::handle_frame`], come out of [`Node::poll`] (the timers due at the given time, then
//! the next frame), and time is passed in by the caller, who sleeps until
//! [`Node::poll_timeout`]. The device is a [`Node`] of a device description ([`Model`]: the
//! object table and its features), an [`Application`] and a [`Storage`]; the three sensors are
//! [`SensorNode`]s. docs/ARCHITECTURE.md follows a frame and time through the code.
//!
//! A firmware loop: the CAN driver's receive and transmit, a clock in µs and the measurement
//! are the firmware's; everything CANopen is the node's.
//!
//! ```
//! use canpos_core::{models, Frame, Instant, RamStorage, Sample, SensorNode};
//!
//! let model = &models::th::TH;
//! let mut node = SensorNode::new(model, model.configure(model.default_config), RamStorage::default());
//! let mut now = Instant::ZERO;
//! node.power_on(now);
//! let mut sent = Vec::new();
//! // One pass of the main loop per millisecond: a received frame, a measurement, the timers.
//! for ms in 0..20u64 {
//!     now = Instant::from_millis(ms);
//!     if ms == 5 {
//!         // NMT start from the master (what the CAN driver received).
//!         node.handle_frame(&Frame::new(0x000, &[0x01, 0x7F]).unwrap(), now);
//!     }
//!     let mut sample = Sample::default();
//!     sample.positions_nm[0] = Some(250_000_000 + ms as i64 * 1000);
//!     node.update_sample(&sample, now);
//!     while let Some(frame) = node.poll(now) {
//!         sent.push(frame); // the CAN driver's transmit
//!     }
//!     // …then sleep until `node.poll_timeout()` or the next interrupt.
//! }
//! // Boot-up, the power-on EMCY, then TPDO1 every millisecond once operational.
//! assert_eq!(sent[0].std_id(), Some(0x77F));
//! assert!(sent.iter().filter(|f| f.std_id() == Some(0x1FF)).count() >= 14);
//! ```
//!
//! One module per CANopen service, so each standard's rules live in one place:
//!
//! | module | standard | what |
//! | --- | --- | --- |
//! | (root) | — | [`Frame`], [`Instant`] / [`Duration`] (µs), the pre-defined COB-ID bases [`cob`]; [`Node`] (the services wired together) and [`Application`] (what a node runs) |
//! | [`od`] | CiA 301 | object dictionary as data, per-object hooks, abort codes |
//! | [`nmt`] | CiA 301 | NMT slave states and commands |
//! | [`sdo`] | CiA 301 | SDO server |
//! | [`pdo`] | CiA 301 | TPDOs and SYNC consumer |
//! | [`emcy`] | CiA 301 | EMCY producer, error register, error history |
//! | [`errctl`] | CiA 301 | boot-up, heartbeat, node guarding |
//! | [`storage`] | CiA 301 | store / restore scopes, image format |
//! | [`lss`] | CiA 305 | layer setting services |
//! | [`encoder`] | CiA 406 | the encoder application |
//! | [`models`] | — | TH, E-Series, TMI device descriptions |
//! | [`eds`] | CiA 306 | EDS export from the model tables |
#![no_std]
#![forbid(unsafe_code)]
#![deny(missing_docs)]

mod app;
pub mod config;
#[doc(hidden)]
pub mod div;
#[cfg(feature = "names")]
pub mod eds;
pub mod emcy;
pub mod encoder;
pub mod errctl;
pub mod lss;
pub mod model;
pub mod models;
pub mod nmt;
mod node;
pub mod od;
pub mod pdo;
pub mod sdo;
pub mod storage;
mod timers;
mod txq;
mod wire;

pub use app::{AppCtx, AppView, Application, ModelOf, Plain};
pub use encoder::{DeviceConfig, Encoder, Fault, Model, Sample};
pub use lss::UNCONFIGURED;
pub use model::{CommConfig, Features, Table, UnitConfig};
pub use node::{Device, Node, Stats};
pub use od::{Abort, Dictionary, Entry, Hook};
pub use storage::{
    NoStorage, RamStorage, Scope, Storage, StorageError, SIG_KILL_ASCII, SIG_KILL_MANUAL, SIG_LOAD,
    SIG_SAVE,
};

/// A position sensor: the CiA 301 / 305 stack running the CiA 406 application.
pub type SensorNode<S> = Node<models::Sensor, S>;
pub use wire::{cob, Duration, Frame, FrameError, Instant};
