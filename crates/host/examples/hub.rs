//! A standalone socketcand hub.
//!
//! `cargo run -p canpos-host --example hub -- [LISTEN_ADDR]` (default `127.0.0.1:29536`; port 0
//! picks a free port). Prints `listening on ADDR` once ready, then serves until killed.

use std::io::Write;

use canpos_host::socketcand::{Hub, DEFAULT_LISTEN};

fn main() {
    let addr = std::env::args()
        .nth(1)
        .unwrap_or_else(|| DEFAULT_LISTEN.to_string());
    let hub = match Hub::bind(&addr) {
        Ok(h) => h,
        Err(e) => {
            eprintln!("hub: cannot listen on {addr}: {e}");
            std::process::exit(1);
        }
    };
    println!("listening on {}", hub.local_addr());
    let _ = std::io::stdout().flush();
    if let Err(e) = hub.run() {
        eprintln!("hub: {e}");
        std::process::exit(1);
    }
}
