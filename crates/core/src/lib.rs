//! canpos-core: the CANopen device as firmware would run it.
//!
//! `#![no_std]`, no allocation, sans-IO: frames go in through [`node::Node::handle_frame`], come
//! out of [`node::Node::poll`] (the timers due at the given time, then the next frame; or the
//! separate [`node::Node::handle_timeout`] and [`node::Node::poll_transmit`]), and time is
//! passed in by the caller, who sleeps until [`node::Node::poll_timeout`]. One module per
//! CANopen service, so each standard's rules live in one place:
//!
//! | module | standard | what |
//! | --- | --- | --- |
//! | [`wire`] | — | frame, time, COB-ID bases |
//! | [`od`] | CiA 301 | object dictionary as data, abort codes |
//! | [`nmt`] | CiA 301 | NMT slave states and commands |
//! | [`sdo`] | CiA 301 | SDO server |
//! | [`pdo`] | CiA 301 | TPDOs and SYNC consumer |
//! | [`emcy`] | CiA 301 | EMCY producer, error register, error history |
//! | [`errctl`] | CiA 301 | boot-up, heartbeat, node guarding |
//! | [`storage`] | CiA 301 | store / restore, image format |
//! | [`lss`] | CiA 305 | layer setting services |
//! | [`encoder`] | CiA 406 | the encoder application |
//! | [`models`] | — | TH, E-Series, TMI dictionaries |
//! | [`eds`] | CiA 306 | EDS export from the model tables |
//! | [`node`] | — | the services wired together |
#![no_std]
#![deny(missing_docs)]

pub mod app;
pub mod eds;
pub mod emcy;
pub mod encoder;
pub mod errctl;
pub mod lss;
pub mod models;
pub mod nmt;
pub mod node;
pub mod od;
pub mod pdo;
pub mod sdo;
pub mod storage;
pub mod txq;
pub mod wire;

pub use node::Node;

/// A position sensor: the CiA 301 / 305 stack running the CiA 406 application.
pub type SensorNode<S> = Node<encoder::Encoder, S>;
pub use wire::{Duration, Frame, Instant};
