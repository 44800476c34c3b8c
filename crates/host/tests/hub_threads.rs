//! The hub's thread count does not grow with its clients (issue 13: one event-driven I/O
//! thread, plus one bus driver per paced channel). One test in its own binary: it counts this
//! process's threads.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use canpos_host::socketcand::{Hub, HubConfig};

fn threads() -> usize {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("Threads:"))
        .and_then(|v| v.trim().parse().ok())
        .expect("Threads in /proc/self/status")
}

#[test]
fn threads_do_not_grow_with_clients() {
    const CAP: usize = 20;
    let config = HubConfig {
        max_clients: CAP,
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    // Counted once the first client has opened the channel: a paced channel has its bus
    // driver thread (one per channel, not per client).
    let mut before = None;
    // Ten times the cap, the admitted ones in raw mode, all kept open and silent.
    let mut conns = Vec::new();
    for _ in 0..10 * CAP {
        let mut s = TcpStream::connect(hub.local_addr()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut first = [0u8; 6];
        s.read_exact(&mut first).unwrap();
        if &first == b"< hi >" {
            let mut ok = [0u8; 6];
            s.write_all(b"< open can0 >").unwrap();
            s.read_exact(&mut ok).unwrap();
            s.write_all(b"< rawmode >").unwrap();
            s.read_exact(&mut ok).unwrap();
            assert_eq!(&ok, b"< ok >");
        }
        conns.push((s, first));
        if before.is_none() {
            // The driver starts with the channel; let it get going.
            std::thread::sleep(Duration::from_millis(50));
            before = Some(threads());
        }
    }
    let before = before.expect("one connection at least");
    let admitted = conns.iter().filter(|(_, f)| f == b"< hi >").count();
    assert_eq!(admitted, CAP);
    assert_eq!(hub.stats().refused, (9 * CAP) as u64);
    assert_eq!(hub.stats().clients, CAP);
    // No thread per client: one I/O thread serves them all.
    let grown = threads().saturating_sub(before);
    assert_eq!(grown, 0, "{grown} threads for {} connections", conns.len());
}
