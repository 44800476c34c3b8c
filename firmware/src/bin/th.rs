//! The canpos TH firmware on QEMU's mps2-an386 (Cortex-M4F): the board half. UART0 (CMSDK APB
//! UART) carries the CAN bus as SLCAN lines, SysTick is the clock, a flash-like region that a
//! reset does not clear keeps the stored parameters. docs/FIRMWARE.md.
#![no_std]
#![no_main]

#[path = "../board.rs"]
mod board;

use board::{BoardClock, Nvm, Uart, UartCan};
use canpos_encoder::Sample;
use canpos_firmware::{Clock, Firmware, MeasurementSource};
use core::mem::MaybeUninit;
use cortex_m_rt::entry;
use panic_halt as _;

/// A magnet moving at 10 mm/s back and forth between 100 mm and 900 mm: the stand-in for the
/// time-of-flight measurement. Its position follows the clock, so a late cycle sees the
/// magnet where it is by then.
struct SweepingMagnet {
    nm: i64,
    /// +1 or -1.
    dir: i64,
    last_us: u64,
}

impl SweepingMagnet {
    const LOW_NM: i64 = 100_000_000;
    const HIGH_NM: i64 = 900_000_000;
    /// 10 mm/s.
    const NM_PER_US: i64 = 10;
}

impl MeasurementSource for SweepingMagnet {
    fn sample(&mut self, now: canpos_stack::Instant) -> Sample {
        // Elapsed time in 32 bits (a cycle is far shorter than 71 minutes): no 64-bit division.
        let dt = now.micros().wrapping_sub(self.last_us).min(u32::MAX as u64) as i64;
        self.last_us = now.micros();
        self.nm += self.dir * dt * Self::NM_PER_US;
        if self.nm > Self::HIGH_NM {
            self.nm = 2 * Self::HIGH_NM - self.nm;
            self.dir = -1;
        } else if self.nm < Self::LOW_NM {
            self.nm = 2 * Self::LOW_NM - self.nm;
            self.dir = 1;
        }
        let mut s = Sample::default();
        s.positions_nm[0] = Some(self.nm);
        s
    }
}

type Th = Firmware<UartCan, SweepingMagnet, Nvm>;

/// Builds the firmware in its static (counted in .bss). Out of line, so any temporary it is
/// built in lives in this frame, which is gone once the main loop runs, rather than in
/// `main`'s, which never is.
#[inline(never)]
fn place(can: UartCan, source: SweepingMagnet) -> &'static mut Th {
    static mut FW: MaybeUninit<Th> = MaybeUninit::uninit();
    // SAFETY: called once, from `main`; nothing else refers to FW.
    unsafe {
        core::hint::black_box(&mut *core::ptr::addr_of_mut!(FW))
            .write(Firmware::new(can, source, Nvm))
    }
}

#[entry]
fn main() -> ! {
    board::paint_stack();
    let mut cp = cortex_m::Peripherals::take().unwrap_or_else(|| board::halt());
    let clock = BoardClock::start(&mut cp.SYST);
    let uart = Uart::init();
    let can = UartCan::new(uart);
    let source = SweepingMagnet {
        nm: SweepingMagnet::LOW_NM,
        dir: 1,
        last_us: clock.now().micros(),
    };
    let fw = place(can, source);
    fw.power_on(clock.now());
    loop {
        let now = clock.now();
        let next = fw.step(now);
        board::answer_diagnostics();
        // Sleep until the next interrupt (UART byte, SysTick every ms) unless work is due.
        if clock.now() < next && !board::rx_pending() {
            cortex_m::asm::wfi();
        }
    }
}
