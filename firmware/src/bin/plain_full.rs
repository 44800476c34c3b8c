//! The CiA 301 / 305 stack on its own with every service canpos has (also SDO block transfer
//! and node guarding): the size figure compared with CANopenNode built with the same services.
//! `plain_stack.rs` has the rest; docs/FIRMWARE.md says how the figure is taken.
#![no_std]
#![no_main]

#[path = "../board.rs"]
mod board;
#[path = "../plain_stack.rs"]
mod plain_stack;

use canpos_stack::model::Model;
use canpos_stack::od::{cia301, Entry};
use panic_halt as _;

/// The communication dictionary with node guarding's objects (0x100C…0x100E).
static ENTRIES: [Entry; 38] = {
    let head: [Entry; 11] = plain_stack::join(&plain_stack::HEAD, &plain_stack::GUARDING);
    cia301::attach(plain_stack::join(&head, &plain_stack::TAIL))
};
const _: () = assert!(cia301::hooks_complete(&ENTRIES));

static MODEL: Model = plain_stack::model(&ENTRIES, true, true);

#[cortex_m_rt::entry]
fn main() -> ! {
    plain_stack::run()
}
