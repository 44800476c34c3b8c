//! `canpos bus serve` keeps its output to a client bounded, replies included (issue 35 item
//! 3): a client that sends 40 MB of `<x>` and never reads the answers does not grow the hub's
//! memory (it was 861 MB for 100 MB): the hub stops reading from it until it reads.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn rss_kib(pid: u32) -> u64 {
    let st = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    st.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap()
}

fn expect(s: &mut TcpStream, want: &[u8]) {
    let mut buf = vec![0u8; want.len()];
    s.read_exact(&mut buf).unwrap();
    assert_eq!(buf, want, "{:?}", String::from_utf8_lossy(&buf));
}

fn raw(port: u16) -> TcpStream {
    let end = Instant::now() + Duration::from_secs(10);
    let mut s = loop {
        match TcpStream::connect(("127.0.0.1", port)) {
            Ok(s) => break s,
            Err(e) => {
                assert!(Instant::now() < end, "the hub did not listen: {e}");
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    };
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    expect(&mut s, b"< hi >");
    s.write_all(b"< open can0 >< rawmode >").unwrap();
    expect(&mut s, b"< ok >< ok >");
    s
}

#[test]
fn forty_megabytes_of_unread_replies_do_not_grow_the_hub() {
    let port = {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let hub = Kill(
        Command::new(env!("CARGO_BIN_EXE_canpos"))
            .args(["bus", "serve", "--listen", &format!("127.0.0.1:{port}")])
            .args(["--stats-interval", "0"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut bad = raw(port);
    let before = rss_kib(hub.0.id());
    // 40 MB of `<x>` (333 MB of `< error unknown command >` answers), never read; the
    // writes stop when the hub stops reading (a write blocked for 2 s ends the flood).
    bad.set_write_timeout(Some(Duration::from_secs(2))).unwrap();
    let chunk = b"<x>".repeat(64 * 1024 / 3);
    let mut sent = 0usize;
    while sent < 40 << 20 {
        match bad.write(&chunk) {
            Ok(n) => sent += n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                break
            }
            Err(e) => panic!("write: {e}"),
        }
    }
    let grown = rss_kib(hub.0.id()).saturating_sub(before);
    assert!(
        grown < 64 * 1024,
        "the hub grew {grown} KiB for {sent} bytes of unread commands"
    );
    // The hub serves the others meanwhile.
    let mut good = raw(port);
    good.write_all(b"< echo >").unwrap();
    expect(&mut good, b"< echo >");
}
