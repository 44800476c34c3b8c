//! canpos-core: the CANopen device as firmware would run it.
//!
//! `#![no_std]`, no allocation, sans-IO: frames go in through [`node::Node::handle_frame`], come
//! out of [`node::Node::poll_transmit`], and time is passed in by the caller. One module per
//! CANopen service, so each standard's rules live in one place.
#![no_std]
#![deny(missing_docs)]

pub mod wire;

pub use wire::{Duration, Frame, Instant};
pub mod encoder;
