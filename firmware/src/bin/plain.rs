//! The CiA 301 / 305 stack on its own with the services of CANopenNode's default configuration
//! that canpos has (no SDO block transfer, no node guarding): the size figure compared with
//! CANopenNode's default stack. `plain_stack.rs` has the rest; docs/FIRMWARE.md says how the
//! figure is taken.
#![no_std]
#![no_main]

#[path = "../board.rs"]
mod board;
#[path = "../plain_stack.rs"]
mod plain_stack;

use canpos_stack::model::Model;
use canpos_stack::od::{cia301, Entry};
use panic_halt as _;

/// The communication dictionary without node guarding's objects.
static ENTRIES: [Entry; 35] =
    cia301::attach(plain_stack::join(&plain_stack::HEAD, &plain_stack::TAIL));
const _: () = assert!(cia301::hooks_complete(&ENTRIES));

static MODEL: Model = plain_stack::model(&ENTRIES, false, false);

#[cortex_m_rt::entry]
fn main() -> ! {
    plain_stack::run()
}
