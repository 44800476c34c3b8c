//! mps2-an386 peripherals: CMSDK APB UART0, SysTick, and the flash-like parameter region.

use canpos_firmware::slcan::{self, LineReader, LINE_MAX};
use canpos_firmware::Clock;
use canpos_stack::{Frame, Instant, Storage, StorageError};
use core::ptr::{read_volatile, write_volatile};
use core::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};
use cortex_m::peripheral::{syst::SystClkSource, SYST};
use cortex_m_rt::exception;

/// Stops the CPU (unrecoverable set-up error), like `panic-halt`.
pub fn halt() -> ! {
    loop {
        cortex_m::asm::wfi();
    }
}

// --- UART0 ---------------------------------------------------------------------------------

const UART0: usize = 0x4000_4000;
const DATA: usize = UART0;
const STATE: usize = UART0 + 0x04;
const CTRL: usize = UART0 + 0x08;
const INTCLEAR: usize = UART0 + 0x0C;
const BAUDDIV: usize = UART0 + 0x10;
const STATE_TX_FULL: u32 = 1 << 0;
const STATE_RX_FULL: u32 = 1 << 1;
const CTRL_TX_EN: u32 = 1 << 0;
const CTRL_RX_EN: u32 = 1 << 1;
const CTRL_RX_INT_EN: u32 = 1 << 3;
const INT_RX: u32 = 1 << 1;
/// UART0 RX is interrupt 0 on the AN386.
const IRQ_UART0_RX: u16 = 0;

fn reg_read(addr: usize) -> u32 {
    // SAFETY: a device register of this board, 32-bit aligned.
    unsafe { read_volatile(addr as *const u32) }
}
fn reg_write(addr: usize, v: u32) {
    // SAFETY: a device register of this board, 32-bit aligned.
    unsafe { write_volatile(addr as *mut u32, v) }
}

/// Received bytes, filled by the RX interrupt, drained by the main loop (single producer,
/// single consumer).
const RX_LEN: usize = 64;
static mut RX_BUF: [u8; RX_LEN] = [0; RX_LEN];
static RX_HEAD: AtomicUsize = AtomicUsize::new(0);
static RX_TAIL: AtomicUsize = AtomicUsize::new(0);
/// Bytes lost because the buffer was full.
static RX_LOST: AtomicU32 = AtomicU32::new(0);

/// UART0: 8N1, transmit by polling, receive by interrupt into [`RX_BUF`].
pub struct Uart;

impl Uart {
    /// Enables UART0 and its receive interrupt.
    pub fn init() -> Uart {
        // QEMU ignores a baud divisor below 16; the value is otherwise irrelevant there.
        reg_write(BAUDDIV, 16);
        reg_write(CTRL, CTRL_TX_EN | CTRL_RX_EN | CTRL_RX_INT_EN);
        // SAFETY: the handler below is ready; unmasking an interrupt breaks no critical section.
        unsafe { cortex_m::peripheral::NVIC::unmask(Irq(IRQ_UART0_RX)) };
        Uart
    }

    /// Sends `bytes`, waiting while the transmitter is full.
    pub fn write(&self, bytes: &[u8]) {
        for &b in bytes {
            while reg_read(STATE) & STATE_TX_FULL != 0 {}
            reg_write(DATA, b as u32);
        }
    }

    /// The next received byte, if any.
    pub fn read(&self) -> Option<u8> {
        let tail = RX_TAIL.load(Ordering::Relaxed);
        if tail == RX_HEAD.load(Ordering::Acquire) {
            return None;
        }
        // SAFETY: the slot at `tail` was published by the ISR (Acquire above) and the ISR does
        // not write it again until `RX_TAIL` moves past it.
        let b = unsafe { (*core::ptr::addr_of!(RX_BUF))[tail % RX_LEN] };
        RX_TAIL.store(tail.wrapping_add(1), Ordering::Release);
        Some(b)
    }
}

/// Whether received bytes wait in the buffer.
pub fn rx_pending() -> bool {
    RX_TAIL.load(Ordering::Relaxed) != RX_HEAD.load(Ordering::Acquire)
}

#[derive(Clone, Copy)]
struct Irq(u16);
// SAFETY: the number is a valid AN386 interrupt.
unsafe impl cortex_m::interrupt::InterruptNumber for Irq {
    fn number(self) -> u16 {
        self.0
    }
}

/// The device part of the vector table (cortex-m-rt's `device` feature, the place a PAC's table
/// goes): IRQ 0, UART0 RX, the one interrupt this firmware unmasks. Without it cortex-m-rt links
/// all 240 ARMv7-M slots (docs/FIRMWARE.md, "Build options in figures"); the rest stay masked,
/// so none of them is taken.
#[link_section = ".vector_table.interrupts"]
#[no_mangle]
static __INTERRUPTS: [unsafe extern "C" fn(); 1] = [uart0_rx];

/// UART0 RX: moves the received bytes into the buffer.
unsafe extern "C" fn uart0_rx() {
    // Clear first: a byte arriving after the loop raises the interrupt again.
    reg_write(INTCLEAR, INT_RX);
    while reg_read(STATE) & STATE_RX_FULL != 0 {
        let b = reg_read(DATA) as u8;
        let head = RX_HEAD.load(Ordering::Relaxed);
        if head.wrapping_sub(RX_TAIL.load(Ordering::Acquire)) >= RX_LEN {
            RX_LOST.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        // SAFETY: only this handler writes the buffer, at a slot the reader has released.
        unsafe { (*core::ptr::addr_of_mut!(RX_BUF))[head % RX_LEN] = b };
        RX_HEAD.store(head.wrapping_add(1), Ordering::Release);
    }
}

// --- the CAN controller: SLCAN lines over UART0 --------------------------------------------

/// Set when the host asked for the stack high-water mark (`W\r`).
static STACK_QUERY: AtomicBool = AtomicBool::new(false);

/// The CAN controller of this board: frames as SLCAN lines on UART0. A real board has a CAN
/// peripheral whose HAL driver implements the same [`embedded_can::nb::Can`].
pub struct UartCan {
    uart: Uart,
    lines: LineReader,
}

impl UartCan {
    /// The controller over `uart`.
    pub fn new(uart: Uart) -> Self {
        UartCan {
            uart,
            lines: LineReader::default(),
        }
    }
}

/// Errors of the UART CAN controller (none surface today: a bad line is dropped).
#[derive(Debug, Clone, Copy)]
pub struct UartCanError;

impl embedded_can::Error for UartCanError {
    fn kind(&self) -> embedded_can::ErrorKind {
        embedded_can::ErrorKind::Other
    }
}

impl embedded_can::nb::Can for UartCan {
    type Frame = Frame;
    type Error = UartCanError;

    fn transmit(&mut self, frame: &Frame) -> nb::Result<Option<Frame>, UartCanError> {
        let mut line = [0u8; LINE_MAX];
        let n = slcan::format(frame, &mut line);
        self.uart.write(line.get(..n).unwrap_or(&[]));
        Ok(None)
    }

    fn receive(&mut self) -> nb::Result<Frame, UartCanError> {
        while let Some(b) = self.uart.read() {
            if let Some(line) = self.lines.push(b) {
                if let Some(f) = slcan::parse::<Frame>(line) {
                    return Ok(f);
                }
                match line.first() {
                    Some(b'W') => STACK_QUERY.store(true, Ordering::Relaxed),
                    // Adapter commands a SLCAN host sends (open, close, bit rate): accepted.
                    Some(b'O' | b'C' | b'S') => self.uart.write(b"\r"),
                    _ => self.uart.write(b"\x07"),
                }
            }
        }
        Err(nb::Error::WouldBlock)
    }
}

// --- stack high-water mark -----------------------------------------------------------------

const PAINT: u32 = 0xA5A5_A5A5;

extern "C" {
    static mut __sheap: u32;
    static _stack_start: u32;
}

fn stack_bounds() -> (usize, usize) {
    // Linker symbols: only their addresses are taken.
    (
        core::ptr::addr_of!(__sheap) as usize,
        core::ptr::addr_of!(_stack_start) as usize,
    )
}

/// Fills the free stack below the current frame with a pattern, so the deepest use can be
/// measured later. Called first thing in `main`, before any interrupt source is enabled, from
/// a leaf function: nothing else uses the stack below its frame meanwhile.
#[inline(never)]
pub fn paint_stack() {
    let (lo, _) = stack_bounds();
    let sp = cortex_m::register::msp::read() as usize;
    let mut p = lo;
    while p + 16 < sp {
        // SAFETY: free RAM between the end of the statics and the stack in use.
        unsafe { write_volatile(p as *mut u32, PAINT) };
        p += 4;
    }
}

/// The most stack bytes used since start-up.
pub fn stack_peak() -> u32 {
    let (lo, hi) = stack_bounds();
    let mut p = lo;
    // SAFETY: reads of RAM between the statics and the top of the stack.
    while p < hi && unsafe { read_volatile(p as *const u32) } == PAINT {
        p += 4;
    }
    (hi - p) as u32
}

/// Answers a pending `W` query with `W` and the stack high-water mark in 8 hex digits.
pub fn answer_diagnostics() {
    if !STACK_QUERY.swap(false, Ordering::Relaxed) {
        return;
    }
    let v = stack_peak();
    let mut line = *b"W00000000\r";
    for (i, d) in line[1..9].iter_mut().enumerate() {
        *d = b"0123456789ABCDEF"[(v >> (28 - 4 * i) & 0xF) as usize];
    }
    Uart.write(&line);
}

// --- time: APB timer 0 as a free-running counter, SysTick as the wake-up --------------------

/// The AN386's processor and peripheral clock.
const CPU_HZ: u32 = 25_000_000;
const TICKS_PER_US: u32 = CPU_HZ / 1_000_000;
const TICKS_PER_MS: u32 = CPU_HZ / 1000;
/// CMSDK APB timer 0: a 32-bit down-counter on the 25 MHz peripheral clock.
const TIMER0: usize = 0x4000_0000;
const TIMER_CTRL: usize = TIMER0;
const TIMER_VALUE: usize = TIMER0 + 0x04;
const TIMER_RELOAD: usize = TIMER0 + 0x08;

/// SysTick only wakes the main loop once per millisecond; time itself is read from the timer.
#[exception]
fn SysTick() {}

/// Microseconds from a free-running 32-bit counter (wraps every 171 s; the main loop reads it
/// far more often). Time comes from the counter's value, never from counting interrupts: a
/// machine that is late (an emulator starved by its host, an interrupt masked too long) loses
/// wake-ups but no time.
pub struct BoardClock {
    last: core::cell::Cell<u32>,
    us: core::cell::Cell<u64>,
    /// Ticks read but not yet a whole microsecond.
    rem: core::cell::Cell<u32>,
}

impl BoardClock {
    /// Starts timer 0 free-running and SysTick at 1 kHz on the processor clock.
    pub fn start(syst: &mut SYST) -> Self {
        reg_write(TIMER_CTRL, 0);
        reg_write(TIMER_RELOAD, u32::MAX);
        reg_write(TIMER_VALUE, u32::MAX);
        reg_write(TIMER_CTRL, 1); // enable, no interrupt
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(TICKS_PER_MS - 1);
        syst.clear_current();
        syst.enable_interrupt();
        syst.enable_counter();
        BoardClock {
            last: core::cell::Cell::new(reg_read(TIMER_VALUE)),
            us: core::cell::Cell::new(0),
            rem: core::cell::Cell::new(0),
        }
    }
}

impl Clock for BoardClock {
    // One shared copy: the main loop and the firmware read the clock in several places.
    #[inline(never)]
    fn now(&self) -> Instant {
        let v = reg_read(TIMER_VALUE);
        // A down-counter over all 2^32 values: the wrapping difference is the ticks elapsed.
        let ticks = self.last.get().wrapping_sub(v);
        self.last.set(v);
        // 32-bit division (one instruction on the M4), the remainder carried.
        let mut us = (ticks / TICKS_PER_US) as u64;
        let mut rem = self.rem.get() + ticks % TICKS_PER_US;
        if rem >= TICKS_PER_US {
            rem -= TICKS_PER_US;
            us += 1;
        }
        self.rem.set(rem);
        self.us.set(self.us.get() + us);
        Instant::from_micros(self.us.get())
    }
}

// --- the flash-like parameter region ---------------------------------------------------------

/// Two banks of emulated NOR flash (erase to 0xFF, programming only clears bits) in SSRAM1
/// beyond the firmware image. QEMU reloads only the ELF's segments on a reset, so this RAM
/// keeps its contents across SYSRESETREQ and the monitor's `system_reset`, as flash would.
const NVM_BASE: usize = 0x0020_0000;
const BANK_LEN: usize = 2048;
const BANKS: [usize; 2] = [NVM_BASE, NVM_BASE + BANK_LEN];
/// Bank header: commit word (written last), sequence number, image length.
const HDR: usize = 12;
const COMMIT: u32 = 0x314D_564E; // "NVM1"

fn nvm_word(addr: usize) -> u32 {
    // SAFETY: the NVM region is RAM of this board, reserved for it, word-aligned here.
    unsafe { read_volatile(addr as *const u32) }
}

/// NOR programming: bits only go from 1 to 0; a word that does not read back failed.
fn nvm_program(addr: usize, v: u32) -> Result<(), StorageError> {
    let old = nvm_word(addr);
    // SAFETY: as `nvm_word`.
    unsafe { write_volatile(addr as *mut u32, old & v) };
    if nvm_word(addr) == v {
        Ok(())
    } else {
        Err(StorageError::Io)
    }
}

fn nvm_erase(bank: usize) {
    let mut a = bank;
    while a < bank + BANK_LEN {
        // SAFETY: as `nvm_word`.
        unsafe { write_volatile(a as *mut u32, u32::MAX) };
        a += 4;
    }
}

/// A committed bank: (sequence, length).
fn bank_state(bank: usize) -> Option<(u32, usize)> {
    let len = nvm_word(bank + 8) as usize;
    (nvm_word(bank) == COMMIT && len <= BANK_LEN - HDR).then(|| (nvm_word(bank + 4), len))
}

/// The bank with the newest committed image.
fn newest() -> Option<(usize, u32, usize)> {
    let a = bank_state(BANKS[0]).map(|(s, l)| (BANKS[0], s, l));
    let b = bank_state(BANKS[1]).map(|(s, l)| (BANKS[1], s, l));
    match (a, b) {
        (Some(x), Some(y)) => Some(if y.1.wrapping_sub(x.1) as i32 > 0 {
            y
        } else {
            x
        }),
        (x, y) => x.or(y),
    }
}

/// The core's [`Storage`] on the two flash banks: a save writes the bank not holding the
/// newest image and commits it with its last word, so a reset during a save leaves the old
/// image loadable.
pub struct Nvm;

impl Storage for Nvm {
    fn load(&mut self, buf: &mut [u8]) -> Result<usize, StorageError> {
        let (bank, _, len) = newest().ok_or(StorageError::Empty)?;
        let dst = buf.get_mut(..len).ok_or(StorageError::Corrupt)?;
        for (i, d) in dst.iter_mut().enumerate() {
            // SAFETY: within the committed bank.
            *d = unsafe { read_volatile((bank + HDR + i) as *const u8) };
        }
        Ok(len)
    }

    fn save(&mut self, image: &[u8]) -> Result<(), StorageError> {
        if image.len() > BANK_LEN - HDR {
            return Err(StorageError::Io);
        }
        let (target, seq) = match newest() {
            Some((bank, seq, _)) if bank == BANKS[0] => (BANKS[1], seq.wrapping_add(1)),
            Some((_, seq, _)) => (BANKS[0], seq.wrapping_add(1)),
            None => (BANKS[0], 1),
        };
        nvm_erase(target);
        for (i, chunk) in image.chunks(4).enumerate() {
            let mut w = [0xFFu8; 4];
            w[..chunk.len()].copy_from_slice(chunk);
            nvm_program(target + HDR + 4 * i, u32::from_le_bytes(w))?;
        }
        nvm_program(target + 4, seq)?;
        nvm_program(target + 8, image.len() as u32)?;
        nvm_program(target, COMMIT)
    }

    fn erase(&mut self) -> Result<(), StorageError> {
        nvm_erase(BANKS[0]);
        nvm_erase(BANKS[1]);
        Ok(())
    }
}
