//! Linux SocketCAN transport (`socketcan://IFACE`), built on the `socketcan` crate.
//!
//! A reader thread blocks on the raw CAN socket (with a short timeout so it notices when the
//! transport is dropped) and feeds the receive queue; `send` writes from the caller's thread.
//! Kernels without `AF_CAN` make [`SocketCanTransport::open`] fail with an explanatory error.

use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, SystemTime};

use canpos_core::Frame;
use crossbeam_channel::{Receiver, Sender, TrySendError};
use socketcan::{CanFrame, CanSocket, ShouldRetry, Socket};

use crate::transport::{RxFrame, Transport};

/// Receive queue length, in frames.
pub const QUEUE_LEN: usize = 4096;
/// How often the reader thread checks whether the transport was dropped.
const POLL: Duration = Duration::from_millis(100);

/// Converts a canpos frame to a SocketCAN frame.
pub fn to_socketcan(frame: &Frame) -> Option<CanFrame> {
    frame.to_embedded::<CanFrame>()
}

/// Converts a SocketCAN frame to a canpos frame; `None` for error frames, which are not
/// CAN traffic.
pub fn from_socketcan(frame: &CanFrame) -> Option<Frame> {
    match frame {
        CanFrame::Error(_) => None,
        f => Frame::from_embedded(f),
    }
}

/// A raw CAN socket bound to one interface.
pub struct SocketCanTransport {
    socket: Arc<CanSocket>,
    rx: Receiver<RxFrame>,
    stop: Arc<AtomicBool>,
    error: Arc<Mutex<Option<io::Error>>>,
    iface: String,
    dropped: Arc<std::sync::atomic::AtomicU64>,
}

/// Adds a hint for the errors a missing CAN stack or interface produce.
fn explain(iface: &str, e: io::Error) -> io::Error {
    let hint = match e.raw_os_error() {
        Some(97) => " (this kernel has no SocketCAN support: AF_CAN is not available; use socketcand:// or mem:// instead)",
        Some(19) => " (no such network interface; for a virtual bus: ip link add dev vcan0 type vcan && ip link set up vcan0)",
        _ => "",
    };
    io::Error::new(e.kind(), format!("{iface}: {e}{hint}"))
}

impl SocketCanTransport {
    /// Opens interface `iface` (e.g. `can0`, `vcan0`).
    pub fn open(iface: &str) -> io::Result<Self> {
        let socket = CanSocket::open(iface).map_err(|e| explain(iface, e))?;
        socket.set_read_timeout(POLL)?;
        let socket = Arc::new(socket);
        let (tx, rx) = crossbeam_channel::bounded(QUEUE_LEN);
        let stop = Arc::new(AtomicBool::new(false));
        let error = Arc::new(Mutex::new(None));
        let dropped = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let (s, st, er, dr) = (socket.clone(), stop.clone(), error.clone(), dropped.clone());
        thread::Builder::new()
            .name(format!("socketcan {iface}"))
            .spawn(move || {
                let e = reader(&s, &st, &tx, &dr);
                *er.lock().unwrap_or_else(|p| p.into_inner()) = e;
            })?;
        Ok(SocketCanTransport {
            socket,
            rx,
            stop,
            error,
            iface: iface.to_string(),
            dropped,
        })
    }
}

fn reader(
    socket: &CanSocket,
    stop: &AtomicBool,
    tx: &Sender<RxFrame>,
    dropped: &std::sync::atomic::AtomicU64,
) -> Option<io::Error> {
    while !stop.load(Ordering::Relaxed) {
        match socket.read_frame() {
            Ok(f) => {
                let Some(frame) = from_socketcan(&f) else {
                    continue;
                };
                let rx = RxFrame {
                    frame,
                    timestamp: SystemTime::now(),
                };
                match tx.try_send(rx) {
                    Ok(()) => {}
                    // A real bus cannot be paused: losing frames beats blocking the socket.
                    Err(TrySendError::Full(_)) => {
                        dropped.fetch_add(1, Ordering::Relaxed);
                    }
                    Err(TrySendError::Disconnected(_)) => return None,
                }
            }
            Err(e) if e.should_retry() => {}
            Err(e) => return Some(e),
        }
    }
    None
}

impl Drop for SocketCanTransport {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl Transport for SocketCanTransport {
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        let f = to_socketcan(frame).ok_or_else(|| {
            io::Error::new(io::ErrorKind::InvalidInput, "frame not representable")
        })?;
        self.socket.write_frame(&f)
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn dead_error(&self) -> io::Error {
        match &*self.error.lock().unwrap_or_else(|p| p.into_inner()) {
            Some(e) => io::Error::new(e.kind(), format!("socketcan {}: {e}", self.iface)),
            None => io::Error::new(io::ErrorKind::ConnectionAborted, "socketcan reader stopped"),
        }
    }

    fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    fn describe(&self) -> String {
        format!("socketcan://{}", self.iface)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use socketcan::EmbeddedFrame;

    #[test]
    fn converts_frames_both_ways() {
        let cases = [
            Frame::new(0x123, &[1, 2, 3]).unwrap(),
            Frame::new(0x000, &[]).unwrap(),
            Frame::with_id(0x1ABC_DEF0, true, &[0xFF; 8]).unwrap(),
            Frame::remote(0x705, false, 1).unwrap(),
            Frame::remote(0x1234, true, 0).unwrap(),
        ];
        for f in cases {
            let s = to_socketcan(&f).unwrap();
            assert_eq!(s.is_extended(), f.is_extended());
            assert_eq!(s.is_remote_frame(), f.is_remote());
            assert_eq!(EmbeddedFrame::dlc(&s), f.dlc() as usize);
            assert_eq!(from_socketcan(&s), Some(f));
        }
    }

    #[test]
    fn error_frames_are_not_traffic() {
        let e = socketcan::CanErrorFrame::new_error(0x004, &[0; 8]).unwrap();
        assert_eq!(from_socketcan(&CanFrame::Error(e)), None);
    }

    #[test]
    fn open_fails_cleanly_without_can() {
        // Whatever this kernel has, a nonexistent interface must be an error, not a panic.
        let e = match SocketCanTransport::open("canposnone0") {
            Err(e) => e,
            Ok(_) => panic!("opened a nonexistent interface"),
        };
        assert!(e.to_string().contains("canposnone0"), "{e}");
        let e = match crate::transport::open("socketcan://canposnone0") {
            Err(e) => e.to_string(),
            Ok(_) => panic!("opened a nonexistent interface"),
        };
        assert!(
            e.contains("cannot open SocketCAN interface `canposnone0`"),
            "{e}"
        );
    }
}
