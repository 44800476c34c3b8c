//! The hub's thread count is bounded by its connection cap, whatever connects (issue 13). One
//! test in its own binary: it counts this process's threads.

use std::io::Read;
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
fn threads_stay_bounded_by_the_cap() {
    const CAP: usize = 20;
    let config = HubConfig {
        max_clients: CAP,
        ..HubConfig::default()
    };
    let hub = Hub::bind_with("127.0.0.1:0", config)
        .unwrap()
        .spawn()
        .unwrap();
    let before = threads();
    // Ten times the cap, all kept open and silent.
    let mut conns = Vec::new();
    for _ in 0..10 * CAP {
        let mut s = TcpStream::connect(hub.local_addr()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut first = [0u8; 6];
        s.read_exact(&mut first).unwrap();
        conns.push((s, first));
    }
    let admitted = conns.iter().filter(|(_, f)| f == b"< hi >").count();
    assert_eq!(admitted, CAP);
    assert_eq!(hub.stats().refused, (9 * CAP) as u64);
    // One reader thread per admitted client (writers come with raw mode).
    let grown = threads().saturating_sub(before);
    assert!(
        grown <= CAP,
        "{grown} threads for {} connections",
        conns.len()
    );
}
