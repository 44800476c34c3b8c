//! Vector SIL Kit: canpos as participants of a SIL Kit simulation (docs/SILKIT.md).
//!
//! - [`sys`]: the C API canpos uses, loaded at run time from `libSilKit.so` (D35).
//! - [`netsim`]: canpos's bus timeline as the CAN network simulator (`canpos bus netsim`).
//! - [`rejoin`]: a registry that goes away and comes back.
//! - [`Participant`]: a participant joined to a registry, destroyed on drop.
//! - [`LocalRegistry`]: a `sil-kit-registry` child process on 127.0.0.1 with a free port, for
//!   tests and for a rig on one machine.
//!
//! SIL Kit's C API is thread-safe; its handlers run on SIL Kit's own threads.

pub mod can;
pub mod discovery;
pub mod log;
pub mod netsim;
pub mod rejoin;
pub mod sys;

use std::ffi::CString;
use std::fmt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub use sys::{api, Api, Error};

/// The longest participant or network name canpos passes on (SIL Kit sets no limit; a bound
/// keeps a bad command line from reaching the registry).
pub const MAX_NAME: usize = 128;

/// Checks a participant, controller or network name: 1–[`MAX_NAME`] printable ASCII
/// characters without spaces or `/`.
pub fn check_name(what: &str, name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err(format!("empty {what}"));
    }
    if name.len() > MAX_NAME {
        return Err(format!("{what} longer than {MAX_NAME} characters"));
    }
    if let Some(c) = name.chars().find(|c| !c.is_ascii_graphic() || *c == '/') {
        return Err(format!("{what} `{name}` contains {c:?}"));
    }
    Ok(())
}

/// A participant name unique to this connection: `canpos-PID-N`.
pub fn default_participant_name() -> String {
    static SEQ: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    format!(
        "canpos-{}-{}",
        std::process::id(),
        SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    )
}

/// A registry's address: `silkit://HOST:PORT` (SIL Kit's own URI form).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RegistryUri {
    /// Host name or IP address (IPv6 without brackets).
    pub host: String,
    /// TCP port.
    pub port: u16,
}

/// SIL Kit's default registry port.
pub const DEFAULT_REGISTRY_PORT: u16 = 8500;

impl fmt::Display for RegistryUri {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.host.contains(':') {
            write!(f, "silkit://[{}]:{}", self.host, self.port)
        } else {
            write!(f, "silkit://{}:{}", self.host, self.port)
        }
    }
}

/// The participant configuration canpos gives SIL Kit: no log sinks (canpos reports errors
/// itself, and its stdout carries a tool's output), one connection attempt to the registry
/// (canpos decides on retries).
pub const PARTICIPANT_CONFIGURATION: &str =
    "{\"Logging\": {\"Sinks\": []}, \"Middleware\": {\"ConnectAttempts\": 1, \"TcpNoDelay\": true}}";

/// A participant joined to a registry; left (destroyed) on drop.
pub struct Participant {
    api: &'static Api,
    raw: *mut sys::Participant,
    name: String,
    /// SIL Kit's records, forwarded into canpos's log (D53); dropped after the participant.
    log: Option<log::SilkitLog>,
}

// SAFETY: the C API is thread-safe (SIL Kit's documentation); the handle is only destroyed
// once, on drop.
unsafe impl Send for Participant {}
// SAFETY: as above: every call through `&self` is a thread-safe C call.
unsafe impl Sync for Participant {}

impl Participant {
    /// Joins the registry at `registry` as `name`. Fails with the registry's reason when it is
    /// unreachable or the name is in use.
    pub fn join(api: &'static Api, name: &str, registry: &RegistryUri) -> Result<Self, Error> {
        check_name("participant name", name).map_err(Error::BadArgument)?;
        let cname = CString::new(name).map_err(|e| Error::BadArgument(e.to_string()))?;
        let curi =
            CString::new(registry.to_string()).map_err(|e| Error::BadArgument(e.to_string()))?;
        // SIL Kit's log into a private directory, read back into canpos's (D53); without it
        // (no temporary directory) the participant joins with no sink, as before.
        let mut silkit_log = log::SilkitLog::create(name)
            .map_err(|e| tracing::warn!("SIL Kit's log of `{name}` is not forwarded: {e}"))
            .ok();
        let config = silkit_log
            .as_ref()
            .and_then(|l| l.configuration(PARTICIPANT_CONFIGURATION).ok())
            .unwrap_or_else(|| PARTICIPANT_CONFIGURATION.to_string());
        let ccfg = CString::new(config).map_err(|e| Error::BadArgument(e.to_string()))?;
        let mut cfg = std::ptr::null_mut();
        // SAFETY: out-pointer and a NUL-terminated string.
        api.check("SilKit_ParticipantConfiguration_FromString", unsafe {
            (api.participant_configuration_from_string)(&mut cfg, ccfg.as_ptr())
        })?;
        let mut raw = std::ptr::null_mut();
        // SAFETY: valid configuration, NUL-terminated strings, out-pointer.
        let rc = unsafe { (api.participant_create)(&mut raw, cfg, cname.as_ptr(), curi.as_ptr()) };
        let created = api.check("SilKit_Participant_Create", rc);
        // SAFETY: the participant keeps its own copy of the configuration.
        unsafe { (api.participant_configuration_destroy)(cfg) };
        if created.is_err() {
            // The error carries SIL Kit's reason; its records only at DEBUG.
            if let Some(l) = &silkit_log {
                l.quiet();
            }
        } else if let Some(l) = &mut silkit_log {
            l.start();
        }
        created.map_err(|e| match e {
            Error::Call { message, .. } => Error::Call {
                call: "SilKit_Participant_Create",
                code: rc,
                code_name: sys::return_code_name(rc),
                message: format!("participant `{name}` at {registry}: {message}"),
            },
            e => e,
        })?;
        Ok(Participant {
            api,
            raw,
            name: name.to_string(),
            log: silkit_log,
        })
    }

    /// The SIL Kit API it was made with.
    pub fn api(&self) -> &'static Api {
        self.api
    }

    /// The raw handle, for services created on it (valid while `self` lives).
    pub fn raw(&self) -> *mut sys::Participant {
        self.raw
    }

    /// Its name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// SIL Kit's log of it, as canpos reads it (`None` when it could not be set up).
    pub fn silkit_log(&self) -> Option<&log::SilkitLog> {
        self.log.as_ref()
    }
}

impl Drop for Participant {
    fn drop(&mut self) {
        // SAFETY: created by SilKit_Participant_Create, destroyed once.
        let rc = unsafe { (self.api.participant_destroy)(self.raw) };
        if let Err(e) = self.api.check("SilKit_Participant_Destroy", rc) {
            tracing::warn!("leaving SIL Kit as `{}`: {e}", self.name);
        }
    }
}

/// A `sil-kit-registry` child process listening on 127.0.0.1 at a free port the registry
/// chose itself (port 0, read back from its generated configuration); killed on drop.
pub struct LocalRegistry {
    child: Child,
    uri: RegistryUri,
    _dir: TempDir,
}

/// A directory removed on drop (the registry's generated configuration).
struct TempDir(PathBuf);
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

impl LocalRegistry {
    /// Starts the registry [`sys::registry_executable`] finds, waiting up to `timeout` for it
    /// to listen (a wall-clock question: be generous on a loaded machine).
    pub fn start(timeout: Duration) -> Result<LocalRegistry, String> {
        let exe = sys::registry_executable().ok_or_else(|| {
            format!(
                "no sil-kit-registry (run scripts/silkit.sh, or set {})",
                sys::REGISTRY_ENV
            )
        })?;
        Self::start_exe(&exe, 0, timeout)
    }

    /// Starts `exe` on 127.0.0.1:`port` (0: a free one).
    pub fn start_exe(exe: &Path, port: u16, timeout: Duration) -> Result<LocalRegistry, String> {
        static SEQ: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let dir = std::env::temp_dir().join(format!(
            "canpos-silkit-registry-{}-{}",
            std::process::id(),
            SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        let dir = TempDir(dir);
        let cfg = dir.0.join("registry.yaml");
        let mut child = Command::new(exe)
            .arg("--listen-uri")
            .arg(format!("silkit://127.0.0.1:{port}"))
            .arg("--generate-configuration")
            .arg(&cfg)
            .args(["--log", "off"])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", exe.display()))?;
        let t0 = Instant::now();
        loop {
            if let Some(uri) = std::fs::read_to_string(&cfg)
                .ok()
                .and_then(|t| registry_uri_of_configuration(&t))
            {
                return Ok(LocalRegistry {
                    child,
                    uri,
                    _dir: dir,
                });
            }
            if let Ok(Some(status)) = child.try_wait() {
                return Err(format!(
                    "{} exited before listening: {status}",
                    exe.display()
                ));
            }
            if t0.elapsed() > timeout {
                let _ = child.kill();
                let _ = child.wait();
                return Err(format!(
                    "{} did not listen within {timeout:?}",
                    exe.display()
                ));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Its address.
    pub fn uri(&self) -> &RegistryUri {
        &self.uri
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Stops it (a registry that goes away) and waits for the process to end.
    pub fn stop(mut self) {
        self.kill();
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for LocalRegistry {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The `RegistryUri: 'silkit://HOST:PORT'` line of a registry's generated configuration.
fn registry_uri_of_configuration(text: &str) -> Option<RegistryUri> {
    let line = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("RegistryUri:"))?;
    let uri = line.trim().trim_matches(['\'', '"']);
    let rest = uri.strip_prefix("silkit://")?;
    let (host, port) = rest.rsplit_once(':')?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    Some(RegistryUri {
        host: host.to_string(),
        port: port.parse().ok().filter(|p| *p != 0)?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_generated_configuration_gives_the_port() {
        let t = "SchemaVersion: 1\nMiddleware:\n  RegistryUri: 'silkit://127.0.0.1:39635'\n";
        let u = registry_uri_of_configuration(t).unwrap();
        assert_eq!(u.to_string(), "silkit://127.0.0.1:39635");
        assert_eq!(registry_uri_of_configuration("Middleware:\n"), None);
        assert_eq!(
            registry_uri_of_configuration("RegistryUri: 'silkit://127.0.0.1:0'"),
            None
        );
    }

    #[test]
    fn names_are_checked() {
        assert!(check_name("participant name", "canpos-th-1").is_ok());
        assert!(check_name("participant name", "").is_err());
        assert!(check_name("participant name", "a b").is_err());
        assert!(check_name("participant name", "a/b").is_err());
        assert!(check_name("participant name", &"x".repeat(129)).is_err());
    }

    #[test]
    fn ipv6_registry_uris_have_brackets() {
        let u = RegistryUri {
            host: "::1".into(),
            port: 8500,
        };
        assert_eq!(u.to_string(), "silkit://[::1]:8500");
    }
}
