//! A socketcand connection that outlives its server: when the server goes away (a socketcand
//! daemon restarting, a hub stopped), it reports bus-off and reconnects with exponential
//! back-off; when the server is back, [`Transport::reconnections`] counts one more, and the
//! runtime boots its nodes again as after a power cycle (docs/SOCKETCAND.md, "Outages").
//!
//! One forwarding thread per connection moves frames from the current [`Client`] into a
//! receive queue of its own, so the runtime's [`Transport::receiver`] stays the same queue
//! across reconnections.

use std::io;
use std::net::{SocketAddr, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::Duration;

use canpos_stack::Frame;
use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};

use super::client::CONNECT_TIMEOUT;
use super::client::{Client, CLIENT_QUEUE_LEN};
use crate::can::{BusState, RxFrame, Transport};

/// The first wait after a connection was lost.
pub const BACKOFF_FIRST: Duration = Duration::from_millis(100);
/// The longest wait between two attempts.
pub const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Exponential back-off: [`BACKOFF_FIRST`], doubling up to [`BACKOFF_MAX`].
#[derive(Clone, Debug)]
pub struct Backoff {
    next: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff {
            next: BACKOFF_FIRST,
        }
    }
}

impl Backoff {
    /// The wait before the next attempt; each call doubles the following one.
    pub fn next_wait(&mut self) -> Duration {
        let w = self.next;
        self.next = (self.next * 2).min(BACKOFF_MAX);
        w
    }
}

struct Shared {
    client: Mutex<Option<Client>>,
    /// The server is away (bus-off until it is back).
    down: AtomicBool,
    reconnections: AtomicU64,
    /// Frames not sent because the server was away.
    unsent: AtomicU64,
    dropped: AtomicU64,
    /// Transmit-queue overflows reported to the clients before the current one.
    tx_overflows: AtomicU64,
    stop: AtomicBool,
    /// The runtime's horizon ([`Transport::join_clock`]), forwarded by each new connection to
    /// a hub that takes it.
    timed: Mutex<Option<(crate::clock::SimClock, std::sync::Weak<crate::clock::Slot>)>>,
}

/// A socketcand transport that reconnects; see the [module docs](self).
pub struct Reconnecting {
    shared: Arc<Shared>,
    rx: Receiver<RxFrame>,
    url: String,
}

impl Reconnecting {
    /// Connects to `host:port`, channel `channel` (the first connection must succeed: nothing
    /// to reconnect to otherwise), then keeps the connection.
    pub fn connect(host: &str, port: u16, channel: &str, url: String) -> io::Result<Reconnecting> {
        let first = connect_any(host, port, channel)?;
        let (tx, rx) = crossbeam_channel::bounded(CLIENT_QUEUE_LEN);
        let inner_rx = first.receiver().clone();
        let shared = Arc::new(Shared {
            client: Mutex::new(Some(first)),
            down: AtomicBool::new(false),
            reconnections: AtomicU64::new(0),
            unsent: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            tx_overflows: AtomicU64::new(0),
            stop: AtomicBool::new(false),
            timed: Mutex::new(None),
        });
        let sh = shared.clone();
        let (host, channel, u) = (host.to_string(), channel.to_string(), url.clone());
        thread::Builder::new()
            .name(format!("socketcand keeper {u}"))
            .spawn(move || keep(&sh, inner_rx, &tx, &host, port, &channel, &u))?;
        Ok(Reconnecting { shared, rx, url })
    }

    /// Whether the server is away right now.
    pub fn is_down(&self) -> bool {
        self.shared.down.load(Ordering::Relaxed)
    }
}

fn connect_any(host: &str, port: u16, channel: &str) -> io::Result<Client> {
    let mut last = None;
    for a in (host, port).to_socket_addrs()? {
        match Client::connect_device_timeout(a, channel, CONNECT_TIMEOUT) {
            Ok(c) => return Ok(c),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
}

/// The forwarding thread: frames of the current client into `tx`; on loss, back-off and
/// reconnect.
fn keep(
    sh: &Shared,
    mut inner: Receiver<RxFrame>,
    tx: &Sender<RxFrame>,
    host: &str,
    port: u16,
    channel: &str,
    url: &str,
) {
    loop {
        // Connected: forward until the client's reader ends.
        loop {
            if sh.stop.load(Ordering::Relaxed) {
                return;
            }
            match inner.recv_timeout(Duration::from_millis(100)) {
                Ok(f) => {
                    if tx.try_send(f).is_err() {
                        sh.dropped.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        let why = sh
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
            .map(|c| {
                sh.tx_overflows
                    .fetch_add(c.tx_overflows(), Ordering::Relaxed);
                c.dead_error().to_string()
            })
            .unwrap_or_default();
        sh.down.store(true, Ordering::Relaxed);
        tracing::warn!(%url, %why, "socketcand server lost: bus-off until it is back; reconnecting");
        let mut backoff = Backoff::default();
        let client = loop {
            if sh.stop.load(Ordering::Relaxed) {
                return;
            }
            let wait = backoff.next_wait();
            thread::sleep(wait);
            match connect_any(host, port, channel) {
                Ok(c) => break c,
                Err(e) => tracing::debug!(%url, error = %e, next_in = ?wait, "reconnect failed"),
            }
        };
        inner = client.receiver().clone();
        if let Some((clock, slot)) = &*sh.timed.lock().unwrap_or_else(|e| e.into_inner()) {
            if !client.attach_clock(clock, slot.clone()) {
                tracing::warn!(%url, "the server is back without a clock for this client: its frames are stamped when they arrive");
            }
        }
        *sh.client.lock().unwrap_or_else(|e| e.into_inner()) = Some(client);
        sh.reconnections.fetch_add(1, Ordering::Relaxed);
        sh.down.store(false, Ordering::Relaxed);
        tracing::warn!(%url, unsent = sh.unsent.load(Ordering::Relaxed), "socketcand server back");
    }
}

impl Drop for Reconnecting {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        // Dropping the client closes its connection and ends its reader.
        self.shared
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take();
    }
}

impl Reconnecting {
    /// A count kept across connections plus the current connection's own.
    fn total(&self, kept: &AtomicU64, current: fn(&Client) -> u64) -> u64 {
        let inner = self
            .shared
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map_or(0, current);
        kept.load(Ordering::Relaxed) + inner
    }
}

impl Transport for Reconnecting {
    /// Sends through the current connection; while the server is away the frame is not sent
    /// (a controller in bus-off sends nothing) and counted.
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        let mut c = self.shared.client.lock().unwrap_or_else(|e| e.into_inner());
        match c.as_mut() {
            Some(c) if !self.shared.down.load(Ordering::Relaxed) => {
                if let Err(e) = c.send(frame) {
                    if e.kind() == io::ErrorKind::InvalidInput {
                        return Err(e);
                    }
                    // The reader notices the loss too; until then, this frame is not sent.
                    self.shared.unsent.fetch_add(1, Ordering::Relaxed);
                }
                Ok(())
            }
            _ => {
                self.shared.unsent.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn dropped(&self) -> u64 {
        self.total(&self.shared.dropped, Client::dropped)
    }

    fn tx_overflows(&self) -> u64 {
        self.total(&self.shared.tx_overflows, Client::tx_overflows)
    }

    /// Bus-off while the server is away; otherwise what the server's error frames say.
    fn bus_state(&self) -> BusState {
        if self.shared.down.load(Ordering::Relaxed) {
            return BusState::BusOff;
        }
        self.shared
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map_or(BusState::BusOff, |c| c.bus_state())
    }

    fn send_error_frame(&mut self, e: &super::codec::ErrorFrame) -> io::Result<bool> {
        match self
            .shared
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_mut()
        {
            Some(c) => c.send_error_frame(e),
            None => Ok(false),
        }
    }

    /// On a canpos hub that made the connection a timed participant (`< clock on >`): the
    /// runtime's horizon, forwarded as `< at … >` by this connection and the next ones.
    fn join_clock(&mut self) -> Option<crate::clock::Horizon> {
        let c = self.shared.client.lock().unwrap_or_else(|e| e.into_inner());
        let c = c.as_ref()?;
        if !c.is_timed() {
            return None;
        }
        let clock = crate::clock::SimClock::wall();
        let h = clock.participant("socketcand runtime");
        if !c.attach_clock(&clock, h.slot()) {
            return None;
        }
        *self.shared.timed.lock().unwrap_or_else(|e| e.into_inner()) = Some((clock, h.slot()));
        Some(h)
    }

    fn reconnections(&self) -> u64 {
        self.shared.reconnections.load(Ordering::Relaxed)
    }

    fn describe(&self) -> String {
        let peer: Option<SocketAddr> = self
            .shared
            .client
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map(|c| c.peer_addr());
        match peer {
            Some(p) => format!("{} ({p})", self.url),
            None => format!("{} (server away)", self.url),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_to_its_cap() {
        let mut b = Backoff::default();
        let waits: Vec<u64> = (0..9).map(|_| b.next_wait().as_millis() as u64).collect();
        assert_eq!(waits, [100, 200, 400, 800, 1600, 3200, 5000, 5000, 5000]);
    }
}
