//! Bus URLs and the factory that opens a transport by URL ([`open`]), on top of every
//! transport. The [`Transport`] trait and the CAN vocabulary live below in [`crate::can`] and are
//! re-exported here under their former paths.

use std::fmt;
use std::io;
use std::net::ToSocketAddrs;
use std::str::FromStr;

pub use crate::can::{BusState, BusStats, Disturbance, Receiver, RxFrame, Transport};

/// Errors of [`open`] and [`BusUrl::parse`].
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The URL could not be understood.
    #[error("bad bus URL `{url}`: {reason}")]
    BadUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Connecting or the protocol handshake failed.
    #[error("cannot connect to `{url}`: {source}")]
    Connect {
        /// The URL.
        url: String,
        /// The cause; `ConnectionRefused` when nothing listens there.
        #[source]
        source: io::Error,
    },
    /// The SocketCAN interface could not be opened.
    #[error("cannot open SocketCAN interface `{iface}`: {source}")]
    SocketCan {
        /// Interface name.
        iface: String,
        /// The cause.
        #[source]
        source: io::Error,
    },
    /// SIL Kit is missing, or refused to let the participant join (docs/SILKIT.md).
    #[error("cannot join `{url}`: {source}")]
    Silkit {
        /// The URL.
        url: String,
        /// The cause.
        #[source]
        source: crate::silkit::Error,
    },
    /// This build lacks the transport (e.g. the `socketcan` cargo feature is off).
    #[error("`{0}` transport is not compiled in (enable the `socketcan` cargo feature)")]
    Unsupported(String),
}

impl Error {
    /// True when nothing listens at a socketcand URL (the caller may start an embedded hub).
    pub fn is_connection_refused(&self) -> bool {
        matches!(self, Error::Connect { source, .. } if source.kind() == io::ErrorKind::ConnectionRefused)
    }
}

/// Default socketcand TCP port.
pub const DEFAULT_PORT: u16 = 29536;
/// Default socketcand host (loopback only, unless asked otherwise).
pub const DEFAULT_HOST: &str = "127.0.0.1";
/// Default socketcand channel.
pub const DEFAULT_CHANNEL: &str = "can0";
/// The default bus URL.
pub const DEFAULT_URL: &str = "socketcand://127.0.0.1:29536/can0";

/// A parsed bus URL.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BusUrl {
    /// `socketcand://HOST:PORT/CHANNEL`; missing parts take the defaults
    /// (`socketcand://` = `socketcand://127.0.0.1:29536/can0`).
    Socketcand {
        /// Host name or IP address (IPv6 without brackets).
        host: String,
        /// TCP port.
        port: u16,
        /// Channel (virtual bus) name.
        channel: String,
    },
    /// `socketcan://IFACE`: a Linux SocketCAN interface.
    SocketCan {
        /// Interface name, e.g. `can0`, `vcan0`.
        iface: String,
    },
    /// `mem://NAME`: a named in-process bus (see [`MemBus::named`](crate::mem::MemBus::named)).
    Mem {
        /// Bus name.
        name: String,
    },
    /// `silkit://HOST:PORT/NETWORK[?participant=NAME&time=sync&step-us=N]`: the CAN network
    /// `NETWORK` of the Vector SIL Kit registry at `HOST:PORT` (port 8500 when left out), as
    /// one participant (docs/SILKIT.md). Without a participant name each connection takes
    /// `canpos-PID-N`; `time=sync` runs on SIL Kit's simulation time in steps of `step-us` µs
    /// (default 1000), under a system controller.
    Silkit {
        /// Registry host name or IP address (IPv6 without brackets).
        host: String,
        /// Registry port.
        port: u16,
        /// CAN network name.
        network: String,
        /// Participant name, if given.
        participant: Option<String>,
        /// Synchronised mode's step in µs; `None`: wall-clock mode.
        sync_step_us: Option<u64>,
    },
}

fn bad(url: &str, reason: impl Into<String>) -> Error {
    Error::BadUrl {
        url: url.to_string(),
        reason: reason.into(),
    }
}

/// A name that can be put into a socketcand element or an interface: printable, no spaces or
/// angle brackets.
fn check_name(url: &str, what: &str, name: &str, max: usize) -> Result<(), Error> {
    if name.is_empty() {
        return Err(bad(url, format!("empty {what}")));
    }
    if name.len() > max {
        return Err(bad(url, format!("{what} longer than {max} characters")));
    }
    if let Some(c) = name
        .chars()
        .find(|c| !c.is_ascii_graphic() || matches!(c, '<' | '>' | '/'))
    {
        return Err(bad(url, format!("{what} `{name}` contains {c:?}")));
    }
    Ok(())
}

impl BusUrl {
    /// Parses a bus URL; see the variants for the accepted forms.
    pub fn parse(url: &str) -> Result<BusUrl, Error> {
        let Some((scheme, rest)) = url.split_once("://") else {
            return Err(bad(
                url,
                "missing scheme; expected socketcand://HOST:PORT/CHANNEL, socketcan://IFACE, mem://NAME or silkit://HOST:PORT/NETWORK",
            ));
        };
        match scheme.to_ascii_lowercase().as_str() {
            "socketcand" => Self::parse_socketcand(url, rest),
            "socketcan" => {
                // Linux IFNAMSIZ is 16 including the NUL.
                check_name(url, "interface name", rest, 15)?;
                Ok(BusUrl::SocketCan {
                    iface: rest.to_string(),
                })
            }
            "mem" => {
                check_name(url, "bus name", rest, 64)?;
                Ok(BusUrl::Mem {
                    name: rest.to_string(),
                })
            }
            "silkit" => Self::parse_silkit(url, rest),
            other => Err(bad(
                url,
                format!("unknown scheme `{other}`; expected socketcand, socketcan, mem or silkit"),
            )),
        }
    }

    fn parse_silkit(url: &str, rest: &str) -> Result<BusUrl, Error> {
        let (rest, query) = match rest.split_once('?') {
            Some((r, q)) => (r, Some(q)),
            None => (rest, None),
        };
        let Some((authority, network)) = rest.split_once('/') else {
            return Err(bad(url, "missing network: silkit://HOST:PORT/NETWORK"));
        };
        crate::silkit::check_name("network name", network).map_err(|r| bad(url, r))?;
        let (host, port) =
            Self::parse_authority(url, authority, crate::silkit::DEFAULT_REGISTRY_PORT)?;
        let (mut participant, mut sync, mut step) = (None, false, None);
        for kv in query.into_iter().flat_map(|q| q.split('&')) {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            match k {
                "participant" => {
                    crate::silkit::check_name("participant name", v).map_err(|r| bad(url, r))?;
                    participant = Some(v.to_string());
                }
                "time" => match v {
                    "sync" => sync = true,
                    "wall" => sync = false,
                    _ => return Err(bad(url, format!("time `{v}`: expected wall or sync"))),
                },
                "step-us" => match v.parse::<u64>() {
                    Ok(n @ 1..=1_000_000_000) => step = Some(n),
                    _ => {
                        return Err(bad(
                            url,
                            format!("step-us `{v}`: expected 1-1000000000 (µs)"),
                        ))
                    }
                },
                _ => {
                    return Err(bad(
                        url,
                        format!("unknown parameter `{k}`; expected participant, time or step-us"),
                    ))
                }
            }
        }
        if step.is_some() && !sync {
            return Err(bad(url, "step-us needs time=sync"));
        }
        Ok(BusUrl::Silkit {
            host,
            port,
            network: network.to_string(),
            participant,
            sync_step_us: sync
                .then(|| step.unwrap_or(crate::silkit::can::DEFAULT_STEP.as_micros() as u64)),
        })
    }

    /// `HOST[:PORT]` or `[V6][:PORT]`; `default_port` when left out.
    fn parse_authority(
        url: &str,
        authority: &str,
        default_port: u16,
    ) -> Result<(String, u16), Error> {
        let (host, port) = if authority.is_empty() {
            (DEFAULT_HOST, None)
        } else if let Some(v6) = authority.strip_prefix('[') {
            let Some((h, after)) = v6.split_once(']') else {
                return Err(bad(url, "unclosed `[` in IPv6 host"));
            };
            match after {
                "" => (h, None),
                p => match p.strip_prefix(':') {
                    Some(p) => (h, Some(p)),
                    None => return Err(bad(url, "expected `:PORT` after `]`")),
                },
            }
        } else {
            match authority.rsplit_once(':') {
                Some((h, _)) if h.contains(':') => {
                    return Err(bad(
                        url,
                        "IPv6 hosts must be written in brackets: [::1]:29536",
                    ))
                }
                Some((h, p)) => (h, Some(p)),
                None => (authority, None),
            }
        };
        if host.is_empty() {
            return Err(bad(url, "empty host"));
        }
        if host.chars().any(|c| c.is_whitespace() || c == '@') {
            return Err(bad(url, format!("bad host `{host}`")));
        }
        let port = match port {
            None => default_port,
            Some(p) => match p.parse::<u16>() {
                Ok(0) => return Err(bad(url, "port 0 is not a valid port to connect to")),
                Ok(p) => p,
                Err(_) => return Err(bad(url, format!("bad port `{p}` (expected 1-65535)"))),
            },
        };
        Ok((host.to_string(), port))
    }

    fn parse_socketcand(url: &str, rest: &str) -> Result<BusUrl, Error> {
        let (authority, channel) = match rest.split_once('/') {
            Some((a, c)) => (a, c),
            None => (rest, ""),
        };
        let channel = if channel.is_empty() {
            DEFAULT_CHANNEL
        } else {
            channel
        };
        check_name(url, "channel", channel, 64)?;
        let (host, port) = Self::parse_authority(url, authority, DEFAULT_PORT)?;
        Ok(BusUrl::Socketcand {
            host,
            port,
            channel: channel.to_string(),
        })
    }
}

impl FromStr for BusUrl {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        BusUrl::parse(s)
    }
}

impl fmt::Display for BusUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BusUrl::Socketcand {
                host,
                port,
                channel,
            } if host.contains(':') => write!(f, "socketcand://[{host}]:{port}/{channel}"),
            BusUrl::Socketcand {
                host,
                port,
                channel,
            } => write!(f, "socketcand://{host}:{port}/{channel}"),
            BusUrl::SocketCan { iface } => write!(f, "socketcan://{iface}"),
            BusUrl::Mem { name } => write!(f, "mem://{name}"),
            BusUrl::Silkit {
                host,
                port,
                network,
                participant,
                sync_step_us,
            } => {
                let registry = crate::silkit::RegistryUri {
                    host: host.clone(),
                    port: *port,
                };
                write!(f, "{registry}/{network}")?;
                let mut sep = '?';
                if let Some(p) = participant {
                    write!(f, "{sep}participant={p}")?;
                    sep = '&';
                }
                if let Some(s) = sync_step_us {
                    write!(f, "{sep}time=sync&step-us={s}")?;
                }
                Ok(())
            }
        }
    }
}

pub use crate::socketcand::client::CONNECT_TIMEOUT;

/// Opens a bus by URL (see [`BusUrl`]).
///
/// For socketcand, [`Error::is_connection_refused`] tells that nothing listens at the address.
pub fn open(url: &str) -> Result<Box<dyn Transport>, Error> {
    open_url(&BusUrl::parse(url)?)
}

/// Opens an already parsed bus URL (a new `mem://` bus is paced at the default rate).
pub fn open_url(url: &BusUrl) -> Result<Box<dyn Transport>, Error> {
    open_url_with(url, crate::bus::Pacing::default())
}

/// Opens a parsed bus URL; `pacing` applies to a `mem://` bus created by this call.
pub fn open_url_with(
    url: &BusUrl,
    pacing: crate::bus::Pacing,
) -> Result<Box<dyn Transport>, Error> {
    match url {
        BusUrl::Socketcand {
            host,
            port,
            channel,
        } => {
            let connect = || -> io::Result<crate::socketcand::Client> {
                let mut last = None;
                for addr in (host.as_str(), *port).to_socket_addrs()? {
                    match crate::socketcand::Client::connect_timeout(addr, channel, CONNECT_TIMEOUT)
                    {
                        Ok(c) => return Ok(c),
                        Err(e) => last = Some(e),
                    }
                }
                Err(last.unwrap_or_else(|| {
                    io::Error::new(io::ErrorKind::NotFound, "host resolved to no address")
                }))
            };
            connect()
                .map(|c| Box::new(c) as Box<dyn Transport>)
                .map_err(|source| Error::Connect {
                    url: url.to_string(),
                    source,
                })
        }
        BusUrl::Mem { name } => Ok(Box::new(
            crate::mem::MemBus::named_with(name, pacing).attach(),
        )),
        #[cfg(feature = "socketcan")]
        BusUrl::SocketCan { iface } => crate::socketcan::SocketCanTransport::open(iface)
            .map(|t| Box::new(t) as Box<dyn Transport>)
            .map_err(|source| Error::SocketCan {
                iface: iface.clone(),
                source,
            }),
        #[cfg(not(feature = "socketcan"))]
        BusUrl::SocketCan { .. } => Err(Error::Unsupported("socketcan".into())),
        BusUrl::Silkit {
            host,
            port,
            network,
            participant,
            sync_step_us,
        } => {
            let silkit_err = |e: crate::silkit::Error| Error::Silkit {
                url: url.to_string(),
                source: e,
            };
            let api = crate::silkit::api().map_err(silkit_err)?;
            let opts = crate::silkit::can::Options {
                registry: crate::silkit::RegistryUri {
                    host: host.clone(),
                    port: *port,
                },
                network: network.clone(),
                participant: participant
                    .clone()
                    .unwrap_or_else(crate::silkit::default_participant_name),
                time: match sync_step_us {
                    None => crate::silkit::can::TimeMode::Wall,
                    Some(us) => crate::silkit::can::TimeMode::Sync {
                        step: std::time::Duration::from_micros(*us),
                    },
                },
                bitrate_kbps: None,
            };
            crate::silkit::can::SilkitCan::open(api, &opts)
                .map(|t| Box::new(t) as Box<dyn Transport>)
                .map_err(silkit_err)
        }
    }
}

/// When a device's socketcand URL may start an embedded hub (`canpos run --hub`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum HubPolicy {
    /// Connect; if nothing listens at start-up, start an embedded hub there (announced loudly
    /// by the caller). Never after an outage: a server that went away is waited for.
    #[default]
    Auto,
    /// Start an embedded hub; an error if the address is taken.
    Always,
    /// Never start a hub: [`open_device_bus`] fails with a refused connection
    /// ([`Error::is_connection_refused`]) and the caller waits for the server.
    Never,
}

impl FromStr for HubPolicy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "auto" => Ok(HubPolicy::Auto),
            "always" => Ok(HubPolicy::Always),
            "never" => Ok(HubPolicy::Never),
            _ => Err(format!("`{s}`: expected auto, always or never")),
        }
    }
}

/// Opens `url`; for a socketcand URL where nothing listens, starts an embedded hub on that
/// address instead and joins its channel in-process ([`HubPolicy::Auto`]).
pub fn open_or_host(
    url: &str,
) -> Result<(Box<dyn Transport>, Option<crate::socketcand::HubHandle>), Error> {
    open_device_bus(url, HubPolicy::Auto)
}

/// Opens a device's bus (what `canpos run` and `scenario` use). A socketcand connection
/// reconnects when its server goes away ([`crate::socketcand::reconnect`]); whether an embedded
/// hub is started follows `policy`.
///
/// Returns the hub handle when one was started: keep it alive as long as the bus is needed
/// (dropping it stops serving TCP clients).
pub fn open_device_bus(
    url: &str,
    policy: HubPolicy,
) -> Result<(Box<dyn Transport>, Option<crate::socketcand::HubHandle>), Error> {
    open_device_bus_with(url, policy, crate::bus::Pacing::default())
}

/// [`open_device_bus`] with the pacing of a bus this call creates (a `mem://` bus, or the
/// embedded hub's channels).
pub fn open_device_bus_with(
    url: &str,
    policy: HubPolicy,
    pacing: crate::bus::Pacing,
) -> Result<(Box<dyn Transport>, Option<crate::socketcand::HubHandle>), Error> {
    let parsed = BusUrl::parse(url)?;
    let BusUrl::Socketcand {
        host,
        port,
        channel,
    } = &parsed
    else {
        return open_url_with(&parsed, pacing).map(|t| (t, None));
    };
    let connect = || {
        crate::socketcand::reconnect::Reconnecting::connect(
            host,
            *port,
            channel,
            parsed.to_string(),
        )
        .map(|c| Box::new(c) as Box<dyn Transport>)
        .map_err(|source| Error::Connect {
            url: parsed.to_string(),
            source,
        })
    };
    let host_here =
        || -> Result<(Box<dyn Transport>, Option<crate::socketcand::HubHandle>), Error> {
            let config = crate::socketcand::HubConfig {
                pacing,
                ..Default::default()
            };
            let hub = crate::socketcand::Hub::bind_with((host.as_str(), *port), config).map_err(
                |source| Error::Connect {
                    url: parsed.to_string(),
                    source,
                },
            )?;
            let port_ = hub.attach(channel);
            let handle = hub.spawn().map_err(|source| Error::Connect {
                url: parsed.to_string(),
                source,
            })?;
            Ok((Box::new(port_), Some(handle)))
        };
    match policy {
        HubPolicy::Always => return host_here(),
        // One attempt: the caller waits and retries (it can be interrupted there).
        HubPolicy::Never => return connect().map(|t| (t, None)),
        HubPolicy::Auto => {}
    }
    // Two attempts: another process may win the race to bind between our connect and bind.
    let mut last = None;
    for _ in 0..2 {
        match connect() {
            Ok(t) => return Ok((t, None)),
            Err(e) if e.is_connection_refused() => last = Some(e),
            Err(e) => return Err(e),
        }
        let config = crate::socketcand::HubConfig {
            pacing,
            ..Default::default()
        };
        match crate::socketcand::Hub::bind_with((host.as_str(), *port), config) {
            Ok(hub) => {
                let port_ = hub.attach(channel);
                let handle = hub.spawn().map_err(|source| Error::Connect {
                    url: parsed.to_string(),
                    source,
                })?;
                tracing::info!(addr = %handle.local_addr(), "no socketcand server found; started an embedded hub");
                return Ok((Box::new(port_), Some(handle)));
            }
            Err(e) if e.kind() == io::ErrorKind::AddrInUse => continue,
            Err(source) => {
                return Err(Error::Connect {
                    url: parsed.to_string(),
                    source,
                })
            }
        }
    }
    Err(last.unwrap_or_else(|| bad(url, "unreachable")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use canpos_stack::Frame;
    use std::time::Duration;

    #[test]
    fn silkit_urls() {
        let u = BusUrl::parse("silkit://127.0.0.1:8501/can0").unwrap();
        assert_eq!(
            u,
            BusUrl::Silkit {
                host: "127.0.0.1".into(),
                port: 8501,
                network: "can0".into(),
                participant: None,
                sync_step_us: None,
            }
        );
        assert_eq!(u.to_string(), "silkit://127.0.0.1:8501/can0");
        let u = BusUrl::parse("silkit://rig/net1?participant=th-11&time=sync").unwrap();
        assert_eq!(
            u.to_string(),
            "silkit://rig:8500/net1?participant=th-11&time=sync&step-us=1000"
        );
        let u = BusUrl::parse("silkit://[::1]:9/n?time=sync&step-us=250").unwrap();
        assert_eq!(u.to_string(), "silkit://[::1]:9/n?time=sync&step-us=250");
        assert_eq!(BusUrl::parse(&u.to_string()).unwrap(), u);
        for (bad_url, why) in [
            ("silkit://127.0.0.1:8500", "missing network"),
            ("silkit://127.0.0.1:8500/", "empty network name"),
            ("silkit://127.0.0.1:0/can0", "port 0"),
            ("silkit://h/can0?participant=", "empty participant name"),
            ("silkit://h/can0?participant=a b", "contains"),
            ("silkit://h/can0?time=fast", "expected wall or sync"),
            ("silkit://h/can0?step-us=10", "step-us needs time=sync"),
            (
                "silkit://h/can0?time=sync&step-us=0",
                "expected 1-1000000000",
            ),
            ("silkit://h/can0?foo=1", "unknown parameter `foo`"),
        ] {
            let e = BusUrl::parse(bad_url).unwrap_err().to_string();
            assert!(e.contains(why), "{bad_url}: {e}");
        }
    }

    fn sc(host: &str, port: u16, channel: &str) -> BusUrl {
        BusUrl::Socketcand {
            host: host.into(),
            port,
            channel: channel.into(),
        }
    }

    #[test]
    fn parses_socketcand_urls() {
        assert_eq!(
            BusUrl::parse(DEFAULT_URL).unwrap(),
            sc("127.0.0.1", 29536, "can0")
        );
        assert_eq!(
            BusUrl::parse("socketcand://").unwrap(),
            sc("127.0.0.1", 29536, "can0")
        );
        assert_eq!(
            BusUrl::parse("socketcand://host").unwrap(),
            sc("host", 29536, "can0")
        );
        assert_eq!(
            BusUrl::parse("socketcand://h:1/").unwrap(),
            sc("h", 1, "can0")
        );
        assert_eq!(
            BusUrl::parse("socketcand://h:1/vcan3").unwrap(),
            sc("h", 1, "vcan3")
        );
        assert_eq!(
            BusUrl::parse("socketcand://[::1]:7/x").unwrap(),
            sc("::1", 7, "x")
        );
        assert_eq!(
            BusUrl::parse("socketcand://[::1]/x").unwrap(),
            sc("::1", 29536, "x")
        );
        assert_eq!(
            BusUrl::parse("SocketCAND://h:2/c").unwrap(),
            sc("h", 2, "c")
        );
        let u = BusUrl::parse("socketcand://[::1]:7/x").unwrap();
        assert_eq!(u.to_string(), "socketcand://[::1]:7/x");
        assert_eq!(BusUrl::parse(&u.to_string()).unwrap(), u);
    }

    #[test]
    fn parses_other_schemes() {
        assert_eq!(
            BusUrl::parse("socketcan://vcan0").unwrap(),
            BusUrl::SocketCan {
                iface: "vcan0".into()
            }
        );
        assert_eq!(
            BusUrl::parse("mem://line1").unwrap(),
            BusUrl::Mem {
                name: "line1".into()
            }
        );
    }

    #[test]
    fn rejects_bad_urls_with_reasons() {
        for (url, needle) in [
            ("", "missing scheme"),
            ("127.0.0.1:29536", "missing scheme"),
            ("tcp://x", "unknown scheme `tcp`"),
            ("socketcand://h:99999/c", "bad port `99999`"),
            ("socketcand://h:abc/c", "bad port `abc`"),
            ("socketcand://h:0/c", "port 0"),
            ("socketcand://:5/c", "empty host"),
            ("socketcand://::1:5/c", "brackets"),
            ("socketcand://[::1/c", "unclosed"),
            ("socketcand://[::1]x/c", "`:PORT`"),
            ("socketcand://h/a b", "contains ' '"),
            ("socketcand://h/a>", "contains '>'"),
            ("socketcand://h/a/b", "contains '/'"),
            ("socketcan://", "empty interface"),
            ("socketcan://averyveryverylongname", "longer than 15"),
            ("mem://", "empty bus name"),
        ] {
            let e = BusUrl::parse(url).expect_err(url).to_string();
            assert!(e.contains(needle), "{url}: {e}");
            assert!(e.contains(&format!("`{url}`")), "{e}");
        }
    }

    #[test]
    fn open_reports_refused_connection() {
        // Bind then drop a listener to get a port that (almost surely) refuses.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let e = match open(&format!("socketcand://127.0.0.1:{port}/can0")) {
            Err(e) => e,
            Ok(_) => panic!("connected to a closed port"),
        };
        assert!(e.is_connection_refused(), "{e}");
        assert!(e.to_string().contains("cannot connect"), "{e}");
    }

    #[test]
    fn open_mem_shares_named_bus() {
        let mut a = open("mem://transport-test-bus").unwrap();
        let mut b = open("mem://transport-test-bus").unwrap();
        let f = Frame::new(0x123, &[1, 2]).unwrap();
        a.send(&f).unwrap();
        let got = b
            .recv_timeout(Some(Duration::from_secs(1)))
            .unwrap()
            .unwrap();
        assert_eq!(got.frame, f);
        assert_eq!(a.try_recv().unwrap(), None);
    }

    #[test]
    fn open_or_host_starts_a_hub_then_reuses_it() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let url = format!("socketcand://127.0.0.1:{port}/can0");
        let (mut first, hub) = open_or_host(&url).unwrap();
        let hub = hub.expect("a hub should have been started");
        let (mut second, none) = open_or_host(&url).unwrap();
        assert!(none.is_none(), "second open must connect to the first hub");
        let f = Frame::new(0x1, &[2]).unwrap();
        second.send(&f).unwrap();
        let got = first
            .recv_timeout(Some(Duration::from_secs(5)))
            .unwrap()
            .unwrap();
        assert_eq!(got.frame, f);
        first.send(&f).unwrap();
        let got = second
            .recv_timeout(Some(Duration::from_secs(5)))
            .unwrap()
            .unwrap();
        assert_eq!(got.frame, f);
        drop(hub);
    }
}
