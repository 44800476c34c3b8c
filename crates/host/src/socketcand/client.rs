//! socketcand client transport: connects, performs the raw-mode handshake, then a reader thread
//! turns `< frame ... >` elements into [`RxFrame`]s.

use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpStream, ToSocketAddrs};
use std::os::linux::net::TcpStreamExt;
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use canpos_core::Frame;
use crossbeam_channel::{Receiver, Sender};

use super::codec::{self, Decoder, Element};
use crate::transport::{RxFrame, Transport};

/// Receive queue length of a client, in frames. When full, the reader stops reading and TCP
/// flow control pushes back to the server (which drops frames for us instead of stalling).
pub const CLIENT_QUEUE_LEN: usize = 4096;

/// A connection to a socketcand server in raw mode. Dropping it closes the connection.
pub struct Client {
    stream: TcpStream,
    rx: Receiver<RxFrame>,
    error: Arc<Mutex<Option<io::Error>>>,
    peer: SocketAddr,
    channel: String,
    buf: Vec<u8>,
}

fn proto_err(msg: impl Into<String>) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, msg.into())
}

impl Client {
    /// Connects to `addr` and opens `channel`, waiting at most [`crate::transport::CONNECT_TIMEOUT`].
    pub fn connect(addr: impl ToSocketAddrs, channel: &str) -> io::Result<Client> {
        let mut last = None;
        for a in addr.to_socket_addrs()? {
            match Self::connect_timeout(a, channel, crate::transport::CONNECT_TIMEOUT) {
                Ok(c) => return Ok(c),
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| io::Error::new(io::ErrorKind::NotFound, "no address")))
    }

    /// Connects and completes the handshake within `timeout`.
    pub fn connect_timeout(
        addr: SocketAddr,
        channel: &str,
        timeout: Duration,
    ) -> io::Result<Client> {
        if channel.is_empty()
            || !channel
                .bytes()
                .all(|b| b.is_ascii_graphic() && b != b'<' && b != b'>')
        {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("bad socketcand channel name {channel:?}"),
            ));
        }
        let deadline = Instant::now() + timeout;
        let mut stream = TcpStream::connect_timeout(&addr, timeout)?;
        stream.set_nodelay(true)?;
        let _ = stream.set_quickack(true);
        let mut decoder = Decoder::new();
        let mut pending = Vec::new();

        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< hi >",
            |e| matches!(e, Element::Hi),
        )?;
        let mut open = Vec::new();
        codec::write_open(&mut open, channel);
        stream.write_all(&open)?;
        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< ok > to open",
            |e| matches!(e, Element::Ok),
        )?;
        stream.write_all(codec::RAWMODE)?;
        expect(
            &mut stream,
            &mut decoder,
            &mut pending,
            deadline,
            "< ok > to rawmode",
            |e| matches!(e, Element::Ok),
        )?;
        stream.set_read_timeout(None)?;

        let (tx, rx) = crossbeam_channel::bounded(CLIENT_QUEUE_LEN);
        let error = Arc::new(Mutex::new(None));
        let reader_stream = stream.try_clone()?;
        let err = error.clone();
        thread::Builder::new()
            .name(format!("socketcand client {addr}"))
            .spawn(move || {
                let e = reader(reader_stream, decoder, pending, &tx);
                *err.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
            })?;
        Ok(Client {
            stream,
            rx,
            error,
            peer: addr,
            channel: channel.to_string(),
            buf: Vec::with_capacity(64),
        })
    }

    /// The server's address.
    pub fn peer_addr(&self) -> SocketAddr {
        self.peer
    }
}

/// Reads until an element satisfying `want` arrives; elements after it stay in `pending`.
fn expect(
    stream: &mut TcpStream,
    decoder: &mut Decoder,
    pending: &mut Vec<Element>,
    deadline: Instant,
    what: &str,
    want: impl Fn(&Element) -> bool,
) -> io::Result<()> {
    let mut buf = [0u8; 512];
    loop {
        if let Some(i) = pending.iter().position(&want) {
            if let Some(Element::Error(e)) =
                pending[..i].iter().find(|e| matches!(e, Element::Error(_)))
            {
                return Err(proto_err(format!(
                    "server answered `< {e} >` while expecting {what}"
                )));
            }
            pending.drain(..=i);
            return Ok(());
        }
        if let Some(Element::Error(e)) = pending.iter().find(|e| matches!(e, Element::Error(_))) {
            return Err(proto_err(format!(
                "server answered `< {e} >` while expecting {what}"
            )));
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no {what} from the socketcand server"),
            ));
        }
        stream.set_read_timeout(Some(left))?;
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    format!("server closed the connection while we waited for {what}"),
                ))
            }
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                continue
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        let _ = stream.set_quickack(true);
        decoder.feed(&buf[..n], |b| pending.push(Element::parse(b)));
    }
}

/// Runs until the connection ends or the client is dropped; returns why it ended.
fn reader(
    mut stream: TcpStream,
    mut decoder: Decoder,
    pending: Vec<Element>,
    tx: &Sender<RxFrame>,
) -> io::Error {
    let mut elements = pending;
    let mut buf = [0u8; 4096];
    loop {
        for el in elements.drain(..) {
            match el {
                Element::Frame(f) => {
                    if tx.send(f).is_err() {
                        return io::Error::new(io::ErrorKind::ConnectionAborted, "client closed");
                    }
                }
                Element::Echo | Element::Ok => {}
                other => tracing::trace!("socketcand client ignored {other:?}"),
            }
        }
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                return io::Error::new(
                    io::ErrorKind::ConnectionAborted,
                    "socketcand server closed the connection",
                )
            }
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return e,
        };
        let _ = stream.set_quickack(true);
        decoder.feed(&buf[..n], |b| elements.push(Element::parse(b)));
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        // Wakes the reader thread, which then ends.
        let _ = self.stream.shutdown(Shutdown::Both);
    }
}

impl Transport for Client {
    /// Sends `< send ... >`. A remote frame with DLC 0 goes out as a zero-length data frame;
    /// one with DLC > 0 cannot be carried by socketcand and is refused (`InvalidInput`).
    fn send(&mut self, frame: &Frame) -> io::Result<()> {
        self.buf.clear();
        if !codec::write_send(&mut self.buf, frame) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "socketcand cannot carry remote frames with DLC > 0",
            ));
        }
        self.stream.write_all(&self.buf)
    }

    fn receiver(&self) -> &Receiver<RxFrame> {
        &self.rx
    }

    fn dead_error(&self) -> io::Error {
        match &*self.error.lock().unwrap_or_else(|p| p.into_inner()) {
            Some(e) => io::Error::new(e.kind(), format!("socketcand {}: {e}", self.peer)),
            None => io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "socketcand connection closed",
            ),
        }
    }

    fn describe(&self) -> String {
        format!("socketcand://{}/{}", self.peer, self.channel)
    }
}
