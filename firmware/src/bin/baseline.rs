//! The board without the CANopen stack: the same start-up, clock, UART controller, storage
//! driver and main
//! loop as `plain`, echoing frames instead of running a node. Its flash is what the
//! "stack on its own" figure subtracts from `plain`'s (docs/FIRMWARE.md).
#![no_std]
#![no_main]

#[path = "../board.rs"]
mod board;

use board::{BoardClock, Nvm, Uart, UartCan};
use canpos_firmware::Clock;
use canpos_stack::Storage;
use embedded_can::nb::Can;
use panic_halt as _;

#[cortex_m_rt::entry]
fn main() -> ! {
    board::paint_stack();
    let mut cp = cortex_m::Peripherals::take().unwrap_or_else(|| board::halt());
    let clock = BoardClock::start(&mut cp.SYST);
    let mut can = UartCan::new(Uart::init());
    let mut last = clock.now();
    // The storage driver is the board's too: linked here by keeping each frame's data.
    let mut buf = [0u8; 8];
    let _ = Nvm.load(&mut buf);
    loop {
        let now = clock.now();
        while let Ok(f) = can.receive() {
            let _ = can.transmit(&f);
            let _ = Nvm.save(embedded_can::Frame::data(&f));
        }
        board::answer_diagnostics();
        if now > last && !board::rx_pending() {
            last = now;
            cortex_m::asm::wfi();
        }
    }
}
