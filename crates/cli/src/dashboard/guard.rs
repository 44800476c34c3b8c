//! Who may change state through the dashboard (issue 35 item 4), and how long a request body
//! may take.
//!
//! Reads (`GET`, `HEAD`: the page, the API's reads, the event stream) are open to any client.
//! Every other method changes state (an SDO write, a fault, NMT, a power cycle, a scan on the
//! bus) and is taken only when
//! * `Host` (and an absolute request target's authority) names the address the connection
//!   reached: that IP and port, or `localhost` / any loopback IP with that port when it came
//!   over loopback. A DNS-rebinding page (`attacker.example` resolved to the dashboard) sends
//!   its own name and is refused; so is a name of the machine (`box.lan:29080`) — a dashboard
//!   bound to 0.0.0.0 is driven by IP address, and read by any name;
//! * `Origin`, when present, is `http://` and that same host and port: another site's page is
//!   refused, `Origin: null` (a sandboxed frame, a file) too. A script (curl) sends no
//!   `Origin` and is served;
//! * the body is `Content-Type: application/json`: the types a page of another origin may send
//!   without a CORS preflight (`text/plain`, forms) are refused, and the dashboard answers no
//!   preflight.
//!
//! Browsers send `Origin` on every cross-origin request that is not a GET / HEAD, and a
//! JSON body from another origin needs a preflight that is never granted: with these checks a
//! per-process token in the page would refuse nothing more, so there is none.
//!
//! The checks run before the body is read and before any handler: a refusal changes nothing.

use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use axum::body::Body;
use axum::extract::Request;
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt;

use super::answer::{fail, ApiError};

/// Longest request body (an SDO value, a control request).
pub const MAX_BODY: usize = 64 * 1024;
/// Time for a request body to arrive once its head has.
pub const BODY_TIMEOUT: Duration = Duration::from_secs(10);

/// The local address of the connection a request came on (set by the accept loop).
#[derive(Clone, Copy, Debug)]
pub struct Served(pub SocketAddr);

/// Middleware: the origin checks of a state-changing request, then its body, read whole within
/// [`BODY_TIMEOUT`] and [`MAX_BODY`].
pub async fn guard(req: Request, next: Next) -> Response {
    if !matches!(*req.method(), Method::GET | Method::HEAD) {
        let served = req.extensions().get::<Served>().map(|s| s.0);
        if let Err(e) = check(req.method(), req.uri(), req.headers(), served) {
            return e.into_response();
        }
    }
    let (parts, body) = req.into_parts();
    match tokio::time::timeout(BODY_TIMEOUT, read_body(body)).await {
        Ok(Ok(bytes)) => {
            next.run(Request::from_parts(parts, Body::from(bytes)))
                .await
        }
        Ok(Err(e)) => e.into_response(),
        Err(_) => {
            let mut r = fail(
                StatusCode::REQUEST_TIMEOUT,
                format!(
                    "the request body did not arrive within {} s",
                    BODY_TIMEOUT.as_secs()
                ),
            )
            .into_response();
            // The rest of the body may still come: the connection is not reused.
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            r
        }
    }
}

async fn read_body(body: Body) -> Result<Vec<u8>, ApiError> {
    let mut data = body.into_data_stream();
    let mut out = Vec::new();
    while let Some(chunk) = data.next().await {
        let chunk =
            chunk.map_err(|e| fail(StatusCode::BAD_REQUEST, format!("request body: {e}")))?;
        if out.len() + chunk.len() > MAX_BODY {
            return Err(fail(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!("request body over {MAX_BODY} bytes"),
            ));
        }
        out.extend_from_slice(&chunk);
    }
    Ok(out)
}

/// Whether a state-changing request comes from the page's own origin with a JSON body.
fn check(
    method: &Method,
    uri: &Uri,
    headers: &HeaderMap,
    served: Option<SocketAddr>,
) -> Result<(), ApiError> {
    let refuse = |why: String| {
        Err(fail(
            StatusCode::FORBIDDEN,
            format!("{method} refused: {why}; state changes are taken only from the dashboard's own page (docs/DASHBOARD.md)"),
        ))
    };
    let Some(served) = served else {
        return refuse("the connection's address is unknown".into());
    };
    let Some(host) = headers.get(header::HOST) else {
        return refuse("no Host header".into());
    };
    let Ok(host) = host.to_str() else {
        return refuse("Host is not text".into());
    };
    let Some(h) = Authority::parse(host).filter(|h| h.names(served)) else {
        return refuse(format!(
            "Host `{host}` does not name this dashboard ({})",
            served_names(served)
        ));
    };
    if let Some(a) = uri.authority() {
        if Authority::parse(a.as_str())
            .filter(|t| t.names(served))
            .is_none()
        {
            return refuse(format!("request target `{a}` does not name this dashboard"));
        }
    }
    if let Some(origin) = headers.get(header::ORIGIN) {
        let text = origin.to_str().unwrap_or("(not text)");
        let same = text
            .get(..7)
            .filter(|s| s.eq_ignore_ascii_case("http://"))
            .and_then(|_| Authority::parse(&text[7..]))
            .is_some_and(|o| o.same_as(&h));
        if !same {
            return refuse(format!(
                "Origin `{text}` is not the page's own (http://{host})"
            ));
        }
    }
    let ty = headers
        .get(header::CONTENT_TYPE)
        .map(|t| t.to_str().unwrap_or("(not text)"));
    let essence = ty.map(|t| t.split(';').next().unwrap_or("").trim());
    if !essence.is_some_and(|e| e.eq_ignore_ascii_case("application/json")) {
        return Err(fail(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            format!(
                "{method} refused: the body must be Content-Type: application/json (got {})",
                ty.map_or("none".to_string(), |t| format!("`{t}`"))
            ),
        ));
    }
    Ok(())
}

/// What a refusal lists as the accepted `Host`s.
fn served_names(served: SocketAddr) -> String {
    let ip = served.ip().to_canonical();
    let port = served.port();
    let own = SocketAddr::new(ip, port);
    if ip.is_loopback() {
        format!("{own}, localhost:{port}, or another loopback address with port {port}")
    } else {
        own.to_string()
    }
}

/// A host and port from `Host`, an `Origin` after its scheme or a request target.
#[derive(Debug, PartialEq)]
struct Authority {
    host: Host,
    /// 80 when not given (plain HTTP).
    port: u16,
}

#[derive(Debug, PartialEq)]
enum Host {
    Ip(IpAddr),
    /// Lower case.
    Name(String),
}

impl Authority {
    /// `host[:port]` with an IPv6 host in brackets; nothing else (no user, path or zone).
    fn parse(s: &str) -> Option<Authority> {
        let (host, port) = if let Some(rest) = s.strip_prefix('[') {
            let (h, after) = rest.split_once(']')?;
            let ip: std::net::Ipv6Addr = h.parse().ok()?;
            (Host::Ip(IpAddr::V6(ip)), after)
        } else {
            let (h, after) = match s.find(':') {
                Some(i) => (&s[..i], &s[i..]),
                None => (s, ""),
            };
            if h.is_empty()
                || !h
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"-._".contains(&b))
            {
                return None;
            }
            match h.parse::<std::net::Ipv4Addr>() {
                Ok(ip) => (Host::Ip(IpAddr::V4(ip)), after),
                Err(_) => (Host::Name(h.to_ascii_lowercase()), after),
            }
        };
        let port = match port {
            "" => 80,
            p => {
                let digits = p.strip_prefix(':')?;
                if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
                    return None;
                }
                digits.parse().ok()?
            }
        };
        let host = match host {
            Host::Ip(ip) => Host::Ip(ip.to_canonical()),
            n => n,
        };
        Some(Authority { host, port })
    }

    /// Whether it names `served`, the address the connection reached.
    fn names(&self, served: SocketAddr) -> bool {
        let local = served.ip().to_canonical();
        self.port == served.port()
            && match &self.host {
                Host::Ip(ip) => *ip == local || (ip.is_loopback() && local.is_loopback()),
                Host::Name(n) => n == "localhost" && local.is_loopback(),
            }
    }

    fn same_as(&self, other: &Authority) -> bool {
        self == other
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(list: &[(&'static str, &'static str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in list {
            h.insert(*k, HeaderValue::from_static(v));
        }
        h
    }

    fn status(
        list: &[(&'static str, &'static str)],
        served: &str,
        target: &str,
    ) -> Result<(), u16> {
        let uri: Uri = target.parse().unwrap();
        check(
            &Method::POST,
            &uri,
            &headers(list),
            Some(served.parse().unwrap()),
        )
        .map_err(|e| e.0.as_u16())
    }

    const JSON: (&str, &str) = ("content-type", "application/json");

    #[test]
    fn authorities_parse_strictly() {
        let a = |s| Authority::parse(s);
        assert_eq!(
            a("127.0.0.1:29080"),
            Some(Authority {
                host: Host::Ip("127.0.0.1".parse().unwrap()),
                port: 29080
            })
        );
        assert_eq!(a("[::1]:8").unwrap().host, Host::Ip("::1".parse().unwrap()));
        assert_eq!(
            a("LocalHost").unwrap(),
            Authority {
                host: Host::Name("localhost".into()),
                port: 80
            }
        );
        // An IPv4-mapped address is its IPv4 address.
        assert_eq!(
            a("[::ffff:127.0.0.1]:1").unwrap().host,
            a("127.0.0.1:1").unwrap().host
        );
        for bad in [
            "",
            ":80",
            "::1:80",
            "[::1",
            "[::1]80",
            "a:+80",
            "a:",
            "a:99999",
            "u@a:80",
            "a:80/x",
            "[fe80::1%eth0]:80",
            "a b:80",
            "a:80:80",
        ] {
            assert_eq!(a(bad), None, "{bad}");
        }
    }

    #[test]
    fn loopback_dashboards_take_their_loopback_names() {
        let on = "127.0.0.1:29080";
        for host in [
            "127.0.0.1:29080",
            "localhost:29080",
            "LOCALHOST:29080",
            "[::1]:29080",
            "127.0.0.2:29080",
        ] {
            let ok = status(&[("host", host), JSON], on, "/api/scan");
            assert_eq!(ok, Ok(()), "{host}");
        }
        for host in [
            "attacker.example:29080",
            "127.0.0.1:29081",
            "127.0.0.1",
            "localhost",
            "10.0.0.1:29080",
            "localhost.:29080",
        ] {
            assert_eq!(
                status(&[("host", host), JSON], on, "/api/scan"),
                Err(403),
                "{host}"
            );
        }
        assert_eq!(status(&[JSON], on, "/api/scan"), Err(403));
        // An absolute target must name it too.
        assert_eq!(
            status(
                &[("host", "127.0.0.1:29080"), JSON],
                on,
                "http://attacker.example:29080/api/scan"
            ),
            Err(403)
        );
        assert_eq!(
            status(
                &[("host", "127.0.0.1:29080"), JSON],
                on,
                "http://localhost:29080/api/scan"
            ),
            Ok(())
        );
    }

    #[test]
    fn a_wildcard_dashboard_takes_the_address_it_was_reached_at() {
        // Bound to 0.0.0.0, reached at 192.0.2.7 (the connection's local address).
        let at = "192.0.2.7:29080";
        assert_eq!(
            status(&[("host", "192.0.2.7:29080"), JSON], at, "/"),
            Ok(())
        );
        for host in [
            "localhost:29080",
            "127.0.0.1:29080",
            "box.lan:29080",
            "192.0.2.8:29080",
        ] {
            assert_eq!(status(&[("host", host), JSON], at, "/"), Err(403), "{host}");
        }
        // A v4 client of a dual-stack [::] socket.
        assert_eq!(
            status(
                &[("host", "192.0.2.7:29080"), JSON],
                "[::ffff:192.0.2.7]:29080",
                "/"
            ),
            Ok(())
        );
        assert_eq!(
            status(
                &[("host", "[2001:db8::1]:80"), JSON],
                "[2001:db8::1]:80",
                "/"
            ),
            Ok(())
        );
        assert_eq!(
            status(&[("host", "[2001:db8::1]"), JSON], "[2001:db8::1]:80", "/"),
            Ok(())
        );
    }

    #[test]
    fn origin_must_be_the_hosts() {
        let on = "127.0.0.1:29080";
        let host = ("host", "127.0.0.1:29080");
        assert_eq!(
            status(&[host, ("origin", "http://127.0.0.1:29080"), JSON], on, "/"),
            Ok(())
        );
        assert_eq!(
            status(&[host, ("origin", "HTTP://127.0.0.1:29080"), JSON], on, "/"),
            Ok(())
        );
        for origin in [
            "http://evil.example",
            "null",
            "http://localhost:29080",
            "https://127.0.0.1:29080",
            "http://127.0.0.1:29081",
            "http://127.0.0.1:29080/x",
            "http://127.0.0.1",
        ] {
            assert_eq!(
                status(&[host, ("origin", origin), JSON], on, "/"),
                Err(403),
                "{origin}"
            );
        }
        let lh = ("host", "localhost:29080");
        assert_eq!(
            status(&[lh, ("origin", "http://localhost:29080"), JSON], on, "/"),
            Ok(())
        );
    }

    #[test]
    fn only_json_bodies_change_state() {
        let on = "127.0.0.1:29080";
        let host = ("host", "127.0.0.1:29080");
        assert_eq!(
            status(
                &[host, ("content-type", "application/json; charset=utf-8")],
                on,
                "/"
            ),
            Ok(())
        );
        assert_eq!(
            status(&[host, ("content-type", "Application/JSON")], on, "/"),
            Ok(())
        );
        for ty in [
            "text/plain",
            "application/x-www-form-urlencoded",
            "multipart/form-data; boundary=x",
            "application/jsonx",
            "text/plain; application/json",
        ] {
            assert_eq!(
                status(&[host, ("content-type", ty)], on, "/"),
                Err(415),
                "{ty}"
            );
        }
        assert_eq!(status(&[host], on, "/"), Err(415));
        // The origin is refused before the type is looked at.
        assert_eq!(
            status(
                &[
                    host,
                    ("origin", "http://evil.example"),
                    ("content-type", "text/plain")
                ],
                on,
                "/"
            ),
            Err(403)
        );
    }
}
