//! canpos-stack: a CANopen device (CiA 301 / 305) as firmware would run it. It names no device
//! profile and no product: the application a node runs (canpos-encoder's CiA 406 encoder, or
//! [`Plain`]) and the device description (a [`Model`]: the object table, the stack's
//! [`Features`], what the application's profile adds) come from the crates above it.
//!
//! `#![no_std]`, no allocation, no `unsafe`, sans-IO: frames go in through
//! [`Node::handle_frame`], come out of [`Node::poll`] (the timers due at the given time, then
//! the next frame), and time is passed in by the caller, who sleeps until
//! [`Node::poll_timeout`]. The device is a [`Node`] of a device description, an
//! [`Application`] and a [`Storage`]. docs/ARCHITECTURE.md follows a frame and time through
//! the code; canpos-models' crate documentation has a firmware loop.
//!
//! One module per CANopen service, so each standard's rules live in one place:
//!
//! | module | standard | what |
//! | --- | --- | --- |
//! | (root) | — | [`Frame`], [`Instant`] / [`Duration`] (µs), the pre-defined COB-ID bases [`cob`]; [`Node`] (the services wired together) and [`Application`] (what a node runs) |
//! | [`model`] | — | the device description: [`Table`], [`Features`], [`Model`], [`UnitConfig`] |
//! | [`od`] | CiA 301 | object dictionary as data, per-object hooks, abort codes |
//! | [`nmt`] | CiA 301 | NMT slave states and commands |
//! | [`sdo`] | CiA 301 | SDO server |
//! | [`pdo`] | CiA 301 | TPDOs and SYNC consumer |
//! | [`rpdo`] | CiA 301 | RPDOs |
//! | [`emcy`] | CiA 301 | EMCY producer, error register, error history |
//! | [`errctl`] | CiA 301 | boot-up, heartbeat, node guarding |
//! | [`storage`] | CiA 301 | store / restore scopes, image format |
//! | [`lss`] | CiA 305 | layer setting services |
//! | [`eds`] | CiA 306 | EDS export from the tables |
//! | [`config`] | — | the build options and sizes |
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
pub mod errctl;
pub mod lss;
pub mod model;
pub mod nmt;
mod node;
pub mod od;
pub mod pdo;
pub mod rpdo;
pub mod sdo;
pub mod storage;
mod timers;
mod txq;
mod wire;

pub use app::{AppCtx, AppView, Application, ModelOf, Plain};
pub use lss::UNCONFIGURED;
pub use model::{CommConfig, Features, Model, Table, UnitConfig, Variant};
pub use node::{Device, Node, Stats};
pub use od::{Abort, Dictionary, Entry, Hook};
pub use storage::{
    NoStorage, RamStorage, Scope, Storage, StorageError, SIG_KILL_ASCII, SIG_KILL_MANUAL, SIG_LOAD,
    SIG_SAVE,
};
pub use wire::{cob, Duration, Frame, FrameError, Instant};
