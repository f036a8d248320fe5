//! The service's own HTTP listener: a tiny router (`GET /metrics` today; a status page
//! and `/api/status` can join it) behind limits a hostile client cannot get around.
//!
//! - At most `max_connections` connections are held. A new one beyond that closes the
//!   oldest held connection that is not being answered (a client that sent half a
//!   request and waits, or an idle keep-alive one); when every held connection is
//!   being answered, the new one is closed at once. Nothing is queued.
//! - A request's headers must arrive within [`Limits::header_timeout`]; a connection
//!   lives at most [`Limits::connection_timeout`] (then it is closed after the answer
//!   in flight).
//! - Accept errors (e.g. `EMFILE`) never make the loop spin: it backs off, and logs at
//!   most one line per [`Limits::log_every`] with the count.
//! - Other paths answer 404, other methods 405 with `Allow: GET, HEAD`.
//! - A request for another server's URL (the absolute form a proxy gets) answers 421:
//!   plant IT scanners (nmap's `http-open-proxy`) would otherwise report an open proxy.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http_body::{Body, Frame, SizeHint};
use http_body_util::Full;
use hyper::body::Incoming;
use hyper::header::{HeaderValue, ALLOW, CONTENT_TYPE};
use hyper::http::uri::Authority;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

/// A route's answer to a GET, given the request's query string if any.
pub type Handler = Arc<dyn Fn(Option<&str>) -> Response<Full<Bytes>> + Send + Sync>;

/// Paths and what answers them; every route answers GET and HEAD.
#[derive(Clone, Default)]
pub struct Router {
    routes: Vec<(&'static str, Handler)>,
}

impl Router {
    /// A router without routes: everything is 404.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds `path`, answered by `handler` whatever the query.
    pub fn get(
        self,
        path: &'static str,
        handler: impl Fn() -> Response<Full<Bytes>> + Send + Sync + 'static,
    ) -> Self {
        self.get_with_query(path, move |_| handler())
    }

    /// Adds `path`, answered by `handler` from the query string (`None` without one).
    pub fn get_with_query(
        mut self,
        path: &'static str,
        handler: impl Fn(Option<&str>) -> Response<Full<Bytes>> + Send + Sync + 'static,
    ) -> Self {
        self.routes.push((path, Arc::new(handler)));
        self
    }

    /// The answer to `method` on `path` with `query`.
    pub fn respond(
        &self,
        method: &Method,
        path: &str,
        query: Option<&str>,
    ) -> Response<Full<Bytes>> {
        let Some((_, handler)) = self.routes.iter().find(|(p, _)| *p == path) else {
            return text(StatusCode::NOT_FOUND, "not found\n");
        };
        if method == Method::GET || method == Method::HEAD {
            return handler(query);
        }
        let mut r = text(StatusCode::METHOD_NOT_ALLOWED, "method not allowed\n");
        r.headers_mut()
            .insert(ALLOW, HeaderValue::from_static("GET, HEAD"));
        r
    }
}

/// A plain-text response.
pub fn text(status: StatusCode, body: impl Into<Bytes>) -> Response<Full<Bytes>> {
    let mut r = Response::new(Full::new(body.into()));
    *r.status_mut() = status;
    r.headers_mut().insert(
        CONTENT_TYPE,
        HeaderValue::from_static("text/plain; charset=utf-8"),
    );
    r
}

/// The listener's limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Connections held at most.
    pub max_connections: usize,
    /// Time for a request's headers to arrive.
    pub header_timeout: Duration,
    /// Lifetime of a connection.
    pub connection_timeout: Duration,
    /// Accept errors and refused connections are logged at most once per this period.
    pub log_every: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: 64,
            header_timeout: Duration::from_secs(5),
            connection_timeout: Duration::from_secs(60),
            log_every: Duration::from_secs(10),
        }
    }
}

/// What the listener did so far.
#[derive(Debug, Default)]
pub struct Stats {
    /// Connections accepted and served.
    pub accepted: AtomicU64,
    /// Connections closed at once: every held connection was being answered.
    pub refused: AtomicU64,
    /// Held connections closed to make room for a new one.
    pub evicted: AtomicU64,
    /// Failed `accept` calls.
    pub accept_errors: AtomicU64,
}

/// One held connection.
struct Slot {
    id: u64,
    /// Requests being answered on it right now.
    busy: AtomicUsize,
    evict: CancellationToken,
}

/// Marks its slot busy while a response exists (until hyper has written and dropped it).
struct Busy(Arc<Slot>);

impl Busy {
    fn new(slot: Arc<Slot>) -> Self {
        slot.busy.fetch_add(1, Ordering::AcqRel);
        Busy(slot)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        self.0.busy.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A response body that keeps its connection busy until it is dropped.
struct Guarded {
    inner: Full<Bytes>,
    _busy: Busy,
}

impl Body for Guarded {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        Pin::new(&mut self.get_mut().inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Logs one kind of event at most once per period, with how often it happened.
struct RateLimited {
    every: Duration,
    last: Option<Instant>,
    count: u64,
}

impl RateLimited {
    fn new(every: Duration) -> Self {
        RateLimited {
            every,
            last: None,
            count: 0,
        }
    }

    /// Counts one event; returns the count to log when a line is due.
    fn note(&mut self) -> Option<u64> {
        self.count += 1;
        let now = Instant::now();
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < self.every)
        {
            return None;
        }
        self.last = Some(now);
        Some(std::mem::take(&mut self.count))
    }
}

/// Whether an accept error means the process or system is out of descriptors or
/// memory: then only time helps.
fn exhausted(e: &std::io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(libc::EMFILE | libc::ENFILE | libc::ENOBUFS | libc::ENOMEM)
    )
}

/// Serves `router` on `listener` under `limits` until `shutdown`.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: Limits,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
) {
    let router = Arc::new(router);
    let held: Arc<Mutex<VecDeque<Arc<Slot>>>> = Arc::default();
    let mut accept_log = RateLimited::new(limits.log_every);
    let mut limit_log = RateLimited::new(limits.log_every);
    let mut backoff = Duration::ZERO;
    let mut next_id = 0u64;
    let max = limits.max_connections.max(1);
    loop {
        let accepted = tokio::select! {
            _ = shutdown.cancelled() => break,
            a = listener.accept() => a,
        };
        let (stream, _peer) = match accepted {
            Ok(a) => {
                backoff = Duration::ZERO;
                a
            }
            Err(e) => {
                stats.accept_errors.fetch_add(1, Ordering::Relaxed);
                metrics::counter!("compgate_http_accept_errors_total").increment(1);
                if let Some(count) = accept_log.note() {
                    tracing::warn!(error = %e, count, "metrics endpoint: accept failed ({count} times since the last such line)");
                }
                // Never spin: out of descriptors, wait longer each time (up to 1 s);
                // anything else (a peer that reset before accept) briefly.
                backoff = if exhausted(&e) {
                    (backoff * 2).clamp(Duration::from_millis(10), Duration::from_secs(1))
                } else {
                    Duration::from_millis(1)
                };
                tokio::select! {
                    _ = shutdown.cancelled() => break,
                    _ = tokio::time::sleep(backoff) => {}
                }
                continue;
            }
        };
        let slot = {
            let mut held = held.lock().unwrap_or_else(|p| p.into_inner());
            if held.len() >= max {
                match held
                    .iter()
                    .position(|s| s.busy.load(Ordering::Acquire) == 0)
                {
                    Some(i) => {
                        if let Some(old) = held.remove(i) {
                            old.evict.cancel();
                        }
                        stats.evicted.fetch_add(1, Ordering::Relaxed);
                        metrics::counter!("compgate_http_connections_total", "outcome" => "evicted")
                            .increment(1);
                    }
                    None => {
                        drop(stream);
                        stats.refused.fetch_add(1, Ordering::Relaxed);
                        metrics::counter!("compgate_http_connections_total", "outcome" => "refused")
                            .increment(1);
                        if let Some(count) = limit_log.note() {
                            tracing::warn!(max_connections = max, count, "metrics endpoint: connection limit reached, every connection busy: closed {count} new connections at once");
                        }
                        continue;
                    }
                }
            }
            next_id += 1;
            let slot = Arc::new(Slot {
                id: next_id,
                busy: AtomicUsize::new(0),
                evict: shutdown.child_token(),
            });
            held.push_back(slot.clone());
            slot
        };
        stats.accepted.fetch_add(1, Ordering::Relaxed);
        metrics::counter!("compgate_http_connections_total", "outcome" => "accepted").increment(1);
        let _ = stream.set_nodelay(true);
        tokio::spawn(connection(
            stream,
            router.clone(),
            limits,
            slot,
            held.clone(),
        ));
    }
}

async fn connection(
    stream: tokio::net::TcpStream,
    router: Arc<Router>,
    limits: Limits,
    slot: Arc<Slot>,
    held: Arc<Mutex<VecDeque<Arc<Slot>>>>,
) {
    let svc_slot = slot.clone();
    let local = stream.local_addr().ok();
    let svc = hyper::service::service_fn(move |req: Request<Incoming>| {
        let busy = Busy::new(svc_slot.clone());
        let uri = req.uri();
        let response = match (uri.authority(), local) {
            (Some(a), Some(local)) if !names_this_server(a, local) => text(
                StatusCode::MISDIRECTED_REQUEST,
                "misdirected request: this server answers for itself only, it is not a proxy\n",
            ),
            _ => router.respond(req.method(), uri.path(), uri.query()),
        };
        async move { Ok::<_, Infallible>(response.map(|inner| Guarded { inner, _busy: busy })) }
    });
    let conn = hyper::server::conn::http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_timeout)
        .serve_connection(TokioIo::new(stream), svc);
    tokio::pin!(conn);
    tokio::select! {
        _ = conn.as_mut() => {}
        _ = slot.evict.cancelled() => {}
        _ = tokio::time::sleep(limits.connection_timeout) => {
            conn.as_mut().graceful_shutdown();
            let _ = tokio::time::timeout(limits.header_timeout, conn).await;
        }
    }
    let mut held = held.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(i) = held.iter().position(|s| s.id == slot.id) {
        held.remove(i);
    }
}

/// Whether a request target's authority (`http://host:port/...`) names the listener
/// the request came in on: its address, `localhost` on loopback, or this host's name.
fn names_this_server(authority: &Authority, local: std::net::SocketAddr) -> bool {
    if authority.port_u16().unwrap_or(80) != local.port() {
        return false;
    }
    let host = authority
        .host()
        .trim_start_matches('[')
        .trim_end_matches(']');
    // A listener on `[::]` sees IPv4 clients at IPv4-mapped addresses.
    let local_ip = local.ip().to_canonical();
    if let Ok(ip) = host.parse::<std::net::IpAddr>() {
        return ip.to_canonical() == local_ip;
    }
    let first_label = host.split('.').next().unwrap_or_default();
    (host.eq_ignore_ascii_case("localhost") && local_ip.is_loopback())
        || rustix::system::uname()
            .nodename()
            .to_str()
            .is_ok_and(|name| !name.is_empty() && first_label.eq_ignore_ascii_case(name))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    async fn start(limits: Limits) -> (std::net::SocketAddr, Arc<Stats>, CancellationToken) {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
        let addr = listener.local_addr().expect("addr");
        let router = Router::new().get("/metrics", || text(StatusCode::OK, "m 1\n"));
        let stats = Arc::new(Stats::default());
        let shutdown = CancellationToken::new();
        tokio::spawn(serve(
            listener,
            router,
            limits,
            stats.clone(),
            shutdown.clone(),
        ));
        (addr, stats, shutdown)
    }

    async fn ask(addr: std::net::SocketAddr, request: &str) -> String {
        let mut s = tokio::net::TcpStream::connect(addr).await.expect("connect");
        s.write_all(request.as_bytes()).await.expect("write");
        let mut out = String::new();
        let _ = tokio::time::timeout(Duration::from_secs(5), s.read_to_string(&mut out)).await;
        out
    }

    #[tokio::test]
    async fn routes_answer_404_and_405_and_the_metrics_path_200() {
        let (addr, _, shutdown) = start(Limits::default()).await;
        let ok = ask(
            addr,
            "GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        )
        .await;
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        assert!(ok.ends_with("m 1\n"), "{ok}");
        let nf = ask(
            addr,
            "GET /nope HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        )
        .await;
        assert!(nf.starts_with("HTTP/1.1 404"), "{nf}");
        let na = ask(
            addr,
            "POST /metrics HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
        )
        .await;
        assert!(na.starts_with("HTTP/1.1 405"), "{na}");
        assert!(na.to_ascii_lowercase().contains("allow: get, head"), "{na}");
        shutdown.cancel();
    }

    // A request for another server's URL (absolute form, as to a proxy) is refused,
    // so scanners do not report an open proxy; one naming this server is answered.
    #[tokio::test]
    async fn absolute_urls_of_other_servers_are_misdirected() {
        let (addr, _, shutdown) = start(Limits::default()).await;
        for foreign in [
            "http://www.google.com/metrics".to_string(),
            "http://www.google.com".to_string(),
            format!("http://127.0.0.2:{}/metrics", addr.port()),
            "http://127.0.0.1/metrics".to_string(),
        ] {
            let r = ask(
                addr,
                &format!(
                    "GET {foreign} HTTP/1.1\r\nHost: www.google.com\r\nConnection: close\r\n\r\n"
                ),
            )
            .await;
            assert!(r.starts_with("HTTP/1.1 421"), "{foreign}: {r}");
            assert!(r.contains("not a proxy"), "{foreign}: {r}");
        }
        for own in [
            format!("http://127.0.0.1:{}/metrics", addr.port()),
            format!("http://LocalHost:{}/metrics", addr.port()),
            format!(
                "http://{}:{}/metrics",
                rustix::system::uname().nodename().to_string_lossy(),
                addr.port()
            ),
        ] {
            let r = ask(
                addr,
                &format!("GET {own} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"),
            )
            .await;
            assert!(r.starts_with("HTTP/1.1 200"), "{own}: {r}");
        }
        shutdown.cancel();
    }

    // Half-sent requests fill every slot: a new client still gets its answer (the
    // oldest waiting connection makes room), and the header timeout closes the rest.
    #[tokio::test]
    async fn half_sent_requests_neither_block_a_scrape_nor_stay_open() {
        let limits = Limits {
            max_connections: 4,
            header_timeout: Duration::from_millis(300),
            ..Limits::default()
        };
        let (addr, stats, shutdown) = start(limits).await;
        let mut idle = Vec::new();
        for _ in 0..10 {
            let mut s = tokio::net::TcpStream::connect(addr).await.expect("connect");
            s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")
                .await
                .expect("write");
            idle.push(s);
        }
        let ok = ask(
            addr,
            "GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        )
        .await;
        assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
        assert!(stats.evicted.load(Ordering::Relaxed) >= 7, "{stats:?}");
        // Every half-sent request ends closed, by eviction or the header timeout.
        for mut s in idle {
            let mut buf = Vec::new();
            let _ = tokio::time::timeout(Duration::from_secs(2), s.read_to_end(&mut buf))
                .await
                .expect("closed by the server");
        }
        shutdown.cancel();
    }

    #[test]
    fn an_ipv4_client_of_a_dual_stack_listener_names_it() {
        let local: std::net::SocketAddr = "[::ffff:127.0.0.1]:9464".parse().expect("addr");
        let named = |a: &str| names_this_server(&a.parse().expect("authority"), local);
        assert!(named("127.0.0.1:9464"));
        assert!(named("localhost:9464"));
        assert!(!named("127.0.0.1:80"));
        assert!(!named("www.google.com:9464"));
    }

    #[test]
    fn rate_limited_logs_once_per_period_with_the_count() {
        let mut r = RateLimited::new(Duration::from_secs(3600));
        assert_eq!(r.note(), Some(1));
        for _ in 0..999 {
            assert_eq!(r.note(), None);
        }
    }
}
