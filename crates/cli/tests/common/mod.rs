//! Helpers shared by the binary's integration tests: running `canpos`, long-running children
//! whose output is collected, free loopback ports and the control interface.

#![allow(dead_code)]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_canpos");

/// Runs `canpos ARGS` in `dir` to the end; panics when it takes longer than `limit` (a hang is
/// a failure, not a wait).
pub fn run_in(dir: &Path, args: &[&str], limit: Duration) -> Output {
    let mut child = Command::new(BIN)
        .args(args)
        .current_dir(dir)
        .env("CANPOS_STATE_DIR", dir.join("default-state"))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run canpos");
    let out = collect(&mut child);
    let end = Instant::now() + limit;
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if Instant::now() > end {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "canpos {args:?} still ran after {limit:?}; output: {}",
                out.lock().unwrap()
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    // The reader threads end with the pipes.
    let deadline = Instant::now() + Duration::from_secs(5);
    while Arc::strong_count(&out) > 1 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(2));
    }
    let text = out.lock().unwrap().clone();
    Output {
        status,
        stdout: text.clone().into_bytes(),
        stderr: text.into_bytes(),
    }
}

/// Runs `canpos ARGS` in a fresh directory (10 s limit).
pub fn canpos(args: &[&str]) -> Output {
    let dir = tempfile::tempdir().unwrap();
    run_in(dir.path(), args, Duration::from_secs(10))
}

/// stdout and stderr of a finished command, interleaved as they came.
pub fn text(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Asserts a command failed with `code`, said `needle`, and did not panic.
pub fn assert_fails(o: &Output, code: i32, needle: &str) {
    let t = text(o);
    assert_eq!(o.status.code(), Some(code), "{t}");
    assert!(t.contains(needle), "expected `{needle}` in: {t}");
    assert!(!t.contains("panicked"), "{t}");
}

fn collect(child: &mut Child) -> Arc<Mutex<String>> {
    let out = Arc::new(Mutex::new(String::new()));
    let streams: Vec<Box<dyn Read + Send>> = vec![
        Box::new(child.stdout.take().unwrap()),
        Box::new(child.stderr.take().unwrap()),
    ];
    for s in streams {
        let out = Arc::clone(&out);
        std::thread::spawn(move || {
            for line in BufReader::new(s).lines() {
                let Ok(line) = line else { break };
                let mut o = out.lock().unwrap();
                o.push_str(&line);
                o.push('\n');
            }
        });
    }
    out
}

/// A long-running `canpos` child, killed (by its own handle) when dropped; its output is
/// collected as it comes.
pub struct Proc {
    child: Child,
    out: Arc<Mutex<String>>,
    args: Vec<String>,
}

impl Proc {
    /// Starts `canpos ARGS` in `dir`.
    pub fn start(dir: &Path, args: &[&str]) -> Proc {
        Proc::start_env(dir, args, &[])
    }

    /// Starts `canpos ARGS` in `dir` with these environment variables set too.
    pub fn start_env(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> Proc {
        let mut child = Command::new(BIN)
            .args(args)
            .current_dir(dir)
            .env("CANPOS_STATE_DIR", dir.join("default-state"))
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn canpos");
        let out = collect(&mut child);
        Proc {
            child,
            out,
            args: args.iter().map(|s| s.to_string()).collect(),
        }
    }

    /// Its process id (to stop and continue it with signals).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The output so far.
    pub fn output(&self) -> String {
        self.out.lock().unwrap().clone()
    }

    /// Waits until the output contains `needle`; panics after `within` or when the process
    /// ended without saying it.
    pub fn wait_for(&mut self, needle: &str, within: Duration) -> String {
        let end = Instant::now() + within;
        loop {
            let o = self.output();
            if o.contains(needle) {
                return o;
            }
            if let Some(s) = self.child.try_wait().unwrap() {
                // Let the readers catch up with the last lines.
                std::thread::sleep(Duration::from_millis(50));
                let o = self.output();
                if o.contains(needle) {
                    return o;
                }
                panic!("canpos {:?} ended ({s}) before `{needle}`: {o}", self.args);
            }
            if Instant::now() > end {
                panic!(
                    "canpos {:?}: no `{needle}` within {within:?}: {o}",
                    self.args
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Waits for the process to end by itself; its exit code.
    pub fn wait_exit(&mut self, within: Duration) -> Option<i32> {
        let end = Instant::now() + within;
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                std::thread::sleep(Duration::from_millis(50));
                return s.code();
            }
            if Instant::now() > end {
                panic!(
                    "canpos {:?} still runs after {within:?}: {}",
                    self.args,
                    self.output()
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Whether it still runs.
    pub fn running(&mut self) -> bool {
        self.child.try_wait().unwrap().is_none()
    }

    /// Stops the process (SIGKILL through its handle) and waits for it.
    pub fn stop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A loopback port nobody listens on right now.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Waits until something accepts connections on `port`.
pub fn wait_port(port: u16) {
    let end = Instant::now() + Duration::from_secs(20);
    while Instant::now() < end {
        if TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    panic!("nothing listens on {port}");
}

/// A control-interface connection.
pub struct Ctl {
    out: TcpStream,
    inp: BufReader<TcpStream>,
}

impl Ctl {
    /// Connects to the control interface on `port`.
    pub fn connect(port: u16) -> Ctl {
        // No probe connection first: each connection counts against the server's limit.
        let end = Instant::now() + Duration::from_secs(20);
        let s = loop {
            match TcpStream::connect(("127.0.0.1", port)) {
                Ok(s) => break s,
                Err(e) if Instant::now() > end => panic!("cannot connect to {port}: {e}"),
                Err(_) => std::thread::sleep(Duration::from_millis(10)),
            }
        };
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        Ctl {
            out: s.try_clone().unwrap(),
            inp: BufReader::new(s),
        }
    }

    /// Sends raw bytes. A failed write is left to show in the next [`Ctl::answer`]: a server
    /// that refuses a connection writes its reason and closes, and the reason is what counts.
    pub fn send_raw(&mut self, bytes: &[u8]) {
        let _ = self.out.write_all(bytes);
    }

    /// Reads one answer line.
    pub fn answer(&mut self) -> serde_json::Value {
        let mut line = String::new();
        self.inp.read_line(&mut line).unwrap();
        serde_json::from_str(line.trim()).unwrap_or_else(|e| panic!("bad answer {line:?}: {e}"))
    }

    /// Sends one request line and reads its answer.
    pub fn request(&mut self, json: &str) -> serde_json::Value {
        self.send_raw(format!("{json}\n").as_bytes());
        self.answer()
    }

    /// Polls the state until `pred` holds (or 10 s pass); returns the last state.
    pub fn state_when(&mut self, pred: impl Fn(&serde_json::Value) -> bool) -> serde_json::Value {
        let end = Instant::now() + Duration::from_secs(10);
        loop {
            let st = self.request(r#"{"cmd":"state"}"#);
            if pred(&st) || Instant::now() > end {
                return st;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}
