//! Serving HTTP/1.1 connections with hyper, within a connection limit.
//!
//! In this folder: `mod.rs` the accept loop and the per-connection
//! service, [`registry`] the connections and the limit, `tracked` a
//! request's body as its connection sees it, [`body_rate`] the least rate
//! of request bodies, [`limits`] the default limit, `framing` the scan of
//! request heads.
//!
//! Every connection lives in a [`Registry`] with the time since which it
//! has been waiting for a complete request (`None` while a request is in
//! flight, from its headers to the end of its answer's body). The accept
//! loop keeps at most `--max-connections` open: when one more arrives, the
//! connection that has waited longest without sending a complete request is
//! closed (a lingering one first, then an idle kept-alive one, or a
//! slowloris still trickling its headers), so a new client always gets in.
//! A connection that has waited less than a second is spared while another
//! can go (a client that just connected gets that long to send its
//! request). Only if every connection has a request in flight (none with a
//! body too slow, see below) or is that new does the loop stop accepting
//! until one ends or ages (new clients then wait in the listen backlog).
//! The default limit is the open-file limit, raised to its hard value at
//! start, less a reserve for the database, image files and workers, so
//! that `accept` never fails for want of file descriptors.
//!
//! hyper's header read timeout (`--header-timeout-secs`) still closes a
//! connection that does not complete a request's headers in time, and a
//! kept-alive one idle that long.
//!
//! A request body must arrive at `--min-body-rate` bytes per second,
//! averaged over `--body-rate-window-secs` of the time the service waits
//! for it (not the time its handler spends on what already came): a slower
//! one ends in a [`BodyTooSlow`] error, which `http::layers` answers with a
//! 408. When every connection has a request in flight, a new one does not
//! wait for them if one of them is a body arriving below that rate (over
//! at least a second): the slowest such body is ended the same way (408)
//! to make room, so that trickling uploads cannot hold every slot.
//!
//! The bytes of each connection pass through a [`framing::Framing`] scan
//! before hyper reads them, which notes each request head that declares
//! both `Content-Length` and `Transfer-Encoding` (hyper drops the length
//! before the service could see it); such a request carries a
//! [`RefusedFraming`] extension and `http::layers` refuses it with a 400
//! and closes the connection (RFC 9112 section 6.1). The scan fails
//! closed: a request it has no note for (it stopped following the
//! connection) is refused the same way, and so is a `CONNECT` (the
//! service is no proxy). An `Upgrade:` header is followed as plain HTTP:
//! the service never answers 101, so hyper reads what follows as the next
//! request, and so does the scan.
//!
//! An answer's write that makes no progress for `--write-timeout-secs`
//! (the client reads none of it: a large particles CSV or PNG asked for
//! and never read) ends the connection, so a client that stops reading
//! holds its slot for that long at most; and at the limit, a connection
//! whose write has been stalled for a second (after the idle ones) is
//! closed to let a new one in. A slow reader that keeps reading is not
//! cut off by the timeout (every bit of progress restarts it), only by
//! that eviction at the limit.
//!
//! A request refused before its body was read (401, 404, 413, 415 ...)
//! would leave the client's unread upload in the socket, and closing a
//! socket with unread data sends a reset, which can reach the client before
//! it reads the answer (Python's `requests` reports a broken pipe or a
//! reset, having sent the whole body before reading). So such a connection
//! is closed by lingering: once the answer is written, the write side is
//! shut (the client sees the answer end) and what the client still sends is
//! read and discarded, up to `--max-upload-mb`, each piece within
//! `--body-timeout-secs` and all within `--request-timeout-secs`, before the
//! socket closes. A lingering connection counts as idle for the limit.

mod body_rate;
mod framing;
mod limits;
mod registry;
mod tracked;

use body_rate::Meter;
pub use body_rate::{BodyRate, BodyTooSlow};
pub use limits::{default_max_connections, raise_open_file_limit};
pub use registry::Registry;
use registry::{Connection, Registered, BUSY, EVICTED};
use tracked::Tracked;

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes, HttpBody};
use axum::Router;
use http_body::{Frame, SizeHint};
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tower::ServiceExt;

use crate::service::infra::config::Config;

/// The largest request head hyper buffers (request line and header
/// fields); the service's own limits (`http::layers`: 8 KiB of request
/// target, 64 KiB and 100 header fields) lie below it, so that they answer
/// with problem+json. Hyper answers a larger head itself, with an empty 431.
/// It is also hyper's largest read buffer, so it bounds an idle
/// connection's memory.
pub const HYPER_MAX_HEAD_BYTES: usize = 128 * 1024;

/// The most header fields hyper parses; more get its empty 431.
pub const HYPER_MAX_HEADERS: usize = 256;

/// How connections are served.
#[derive(Clone, Debug)]
pub struct Settings {
    /// `--header-timeout-secs`.
    pub header_timeout: Duration,
    /// Lingering close: at most this many bytes discarded...
    pub linger_bytes: u64,
    /// ...each piece within this...
    pub linger_pause: Duration,
    /// ...and all within this.
    pub linger_total: Duration,
    /// The least rate a request body must arrive at (`None`: any).
    pub body_rate: Option<BodyRate>,
    /// How long a write to the client may make no progress.
    pub write_timeout: Duration,
}

impl Settings {
    /// From the service's settings.
    pub fn new(config: &Config) -> Settings {
        let timeouts = &config.timeouts;
        Settings {
            header_timeout: timeouts.header(),
            linger_bytes: config.max_upload_bytes as u64,
            linger_pause: timeouts.body(),
            linger_total: timeouts.request(),
            body_rate: (timeouts.min_body_rate > 0).then(|| BodyRate {
                bytes_per_second: timeouts.min_body_rate,
                window: timeouts.body_rate_window(),
            }),
            write_timeout: timeouts.write(),
        }
    }
}

/// How long a connection is spared at the limit: a new or idle one for
/// this long since it became idle (a client that just connected has that
/// long to send its request before the next arrival may close it), and a
/// request in flight until its body has been waited for this long (at
/// most the rate window; its rate is not known before).
const EVICTION_GRACE: Duration = Duration::from_secs(1);

/// Serves HTTP/1.1 connections on `listener` with hyper until `shutdown`
/// completes, within the registry's limit (see the module's
/// documentation); then stops accepting, lets each connection finish its
/// request in flight (idle ones close at once) and waits for them.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    registry: Arc<Registry>,
    settings: Settings,
    shutdown: impl Future<Output = ()>,
) {
    let mut http = http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(settings.header_timeout)
        .max_buf_size(HYPER_MAX_HEAD_BYTES)
        .max_headers(HYPER_MAX_HEADERS);
    let http = Arc::new(http);
    let settings = Arc::new(settings);
    let (stop, stopped) = watch::channel(false);
    let mut shutdown = std::pin::pin!(shutdown);
    let rate = settings.body_rate;
    loop {
        // Every connection has a request in flight, none of them a body
        // arriving too slowly: accept nothing until one ends or turns idle
        // (or its body turns out too slow).
        if registry.len() >= registry.max
            && !registry.any_idle_for(EVICTION_GRACE)
            && !registry.any_slow_body(rate.as_ref())
            && registry
                .longest_stalled_writer(u64::MAX, EVICTION_GRACE)
                .is_none()
        {
            let changed = registry.changed.notified();
            tokio::select! {
                () = changed => {}
                () = tokio::time::sleep(Duration::from_millis(100)) => {}
                () = &mut shutdown => break,
            }
            continue;
        }
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(error) => {
                    accept_failed(error, &registry).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let registered = registry.register();
        let id = registered.id;
        let connection = registered.connection.clone();
        let task = tokio::spawn(serve_connection(
            stream,
            http.clone(),
            router.clone(),
            registered,
            settings.clone(),
            stopped.clone(),
        ));
        let _ = connection.task.set(task.abort_handle());
        if registry.len() > registry.max
            && !registry.evict_oldest_idle(id, EVICTION_GRACE)
            && !registry.evict_stalled_writer(id, EVICTION_GRACE)
            && !registry.evict_slowest_body(rate.as_ref())
            && !registry.evict_oldest_idle(id, Duration::ZERO)
        {
            // Every other connection turned busy since the check above.
            registry.evict_oldest_idle(u64::MAX, Duration::ZERO);
        }
    }
    drop(listener);
    let _ = stop.send(true);
    loop {
        let changed = registry.changed.notified();
        if registry.is_empty() {
            break;
        }
        tokio::select! {
            () = changed => {}
            () = tokio::time::sleep(Duration::from_millis(100)) => {}
        }
    }
}

/// A failed accept: a client that gave up is nothing. Out of file
/// descriptors (which the limit should prevent, but files count too) closes
/// the oldest idle connection and goes on; anything else is logged and
/// waited out for a second, as axum::serve does.
async fn accept_failed(error: std::io::Error, registry: &Registry) {
    use std::io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset};
    if matches!(
        error.kind(),
        ConnectionAborted | ConnectionRefused | ConnectionReset
    ) {
        return;
    }
    // EMFILE, ENFILE.
    let out_of_files = matches!(error.raw_os_error(), Some(23 | 24));
    if out_of_files && registry.evict_oldest_idle(u64::MAX, Duration::ZERO) {
        tracing::warn!(%error, "out of file descriptors: closed the longest idle connection");
        tokio::time::sleep(Duration::from_millis(10)).await;
        return;
    }
    tracing::error!(%error, "cannot accept a connection");
    tokio::time::sleep(Duration::from_secs(1)).await;
}

/// One connection, from accept to close.
async fn serve_connection(
    stream: TcpStream,
    http: Arc<http1::Builder>,
    router: Router,
    registered: Registered,
    settings: Arc<Settings>,
    mut stopped: watch::Receiver<bool>,
) {
    let service = ConnectionService {
        router,
        registry: registered.registry.clone(),
        connection: registered.connection.clone(),
        body_rate: settings.body_rate,
    };
    let stream = Scanned {
        stream,
        connection: registered.connection.clone(),
        write_timeout: settings.write_timeout,
        stall_timer: None,
    };
    let mut connection = http.serve_connection(TokioIo::new(stream), service);
    let mut stopping = *stopped.borrow();
    if stopping {
        Pin::new(&mut connection).graceful_shutdown();
    }
    let result = loop {
        tokio::select! {
            result = std::future::poll_fn(|cx| connection.poll_without_shutdown(cx)) => break result,
            changed = stopped.changed(), if !stopping => {
                stopping = true;
                if changed.is_err() || *stopped.borrow() {
                    Pin::new(&mut connection).graceful_shutdown();
                }
            }
        }
    };
    if let Err(error) = result {
        tracing::debug!(%error, "connection closed with an error");
        return;
    }
    if !registered.connection.unread_body.load(Ordering::Relaxed) || stopping {
        return;
    }
    // Its answer is out: the first to close at the limit.
    let _ = registered
        .connection
        .idle
        .fetch_update(Ordering::AcqRel, Ordering::Relaxed, |v| {
            (!matches!(v, BUSY | EVICTED)).then_some(1)
        });
    let stream = connection.into_parts().io.into_inner().stream;
    let mut settings = Settings::clone(&settings);
    // A body too slow for the service gets to read its answer, no more.
    if let Some(rate) = settings.body_rate {
        if registered.connection.too_slow.load(Ordering::Relaxed) {
            settings.linger_total = settings.linger_total.min(rate.window);
        }
    }
    // A shutdown cuts the lingering short.
    tokio::select! {
        () = linger(stream, &settings) => {}
        _ = stopped.changed() => {}
    }
}

/// A connection's socket, its incoming bytes scanned for conflicting
/// framing ([`framing::Framing`]) before hyper reads them, its writes
/// bounded: one that makes no progress for the write timeout fails
/// (`TimedOut`), which ends the connection.
struct Scanned {
    stream: TcpStream,
    connection: Arc<Connection>,
    write_timeout: Duration,
    /// Ends the stalled write, from its first `Pending`.
    stall_timer: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl Scanned {
    /// A write's outcome, with the stall noted: a `Pending` write starts
    /// (or goes on) the stall, which fails once it lasts the write
    /// timeout; any progress ends it.
    fn bounded<T>(
        &mut self,
        cx: &mut Context<'_>,
        polled: Poll<std::io::Result<T>>,
    ) -> Poll<std::io::Result<T>> {
        if polled.is_ready() {
            if self.stall_timer.take().is_some() {
                *self.connection.write_stalled() = None;
            }
            return polled;
        }
        let timeout = self.write_timeout;
        let timer = self.stall_timer.get_or_insert_with(|| {
            self.connection
                .write_stalled()
                .get_or_insert_with(Instant::now);
            Box::pin(tokio::time::sleep(timeout))
        });
        if timer.as_mut().poll(cx).is_ready() {
            return Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!(
                    "the client read none of its answer for {} s (--write-timeout-secs)",
                    timeout.as_secs()
                ),
            )));
        }
        Poll::Pending
    }
}

impl AsyncRead for Scanned {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let polled = Pin::new(&mut self.stream).poll_read(cx, buf);
        if let Poll::Ready(Ok(())) = polled {
            self.connection
                .framing
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .scan(&buf.filled()[before..]);
        }
        polled
    }
}

impl AsyncWrite for Scanned {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write(cx, buf);
        self.bounded(cx, polled)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let polled = Pin::new(&mut self.stream).poll_write_vectored(cx, bufs);
        self.bounded(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

/// The extension of a request whose framing the service refuses:
/// `http::layers` answers it with a 400 and closes the connection. The
/// scan fails closed: a request it has no note for is refused too.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RefusedFraming {
    /// Its head declared both `Content-Length` and `Transfer-Encoding`
    /// (hyper keeps only the latter).
    Conflicting,
    /// The scan stopped following the connection's bytes before its head
    /// ([`framing::Framing`] lost), so whether it declared both is not
    /// known.
    Unfollowed,
    /// A `CONNECT`: the service is no proxy, and what follows a `CONNECT`
    /// is not followed by the scan.
    Connect,
}

impl RefusedFraming {
    /// What is wrong and what to do, for the 400's detail.
    pub fn reason(self) -> &'static str {
        match self {
            RefusedFraming::Conflicting => {
                "the request declares both Content-Length and Transfer-Encoding, which frame \
                 its body differently (RFC 9112 section 6.1); send one of them"
            }
            RefusedFraming::Unfollowed => {
                "an earlier request on this connection was framed in a way the service does \
                 not follow (a Content-Length it cannot parse, such as a list), so it cannot \
                 tell where this request begins; send it again on a new connection, with one \
                 plain Content-Length or Transfer-Encoding: chunked"
            }
            RefusedFraming::Connect => {
                "the service is not a proxy and does not take CONNECT; send the request itself \
                 to the service"
            }
        }
    }

    /// The verdict on a request with method `method`, given the scan's
    /// note for its head (`None`: the scan has none).
    fn of(method: &hyper::Method, note: Option<bool>) -> Option<RefusedFraming> {
        if method == hyper::Method::CONNECT {
            return Some(RefusedFraming::Connect);
        }
        match note {
            Some(false) => None,
            Some(true) => Some(RefusedFraming::Conflicting),
            None => Some(RefusedFraming::Unfollowed),
        }
    }
}

/// Shuts the write side (the answer is complete) and reads and discards
/// what the client still sends, within the settings' bounds, so that the
/// close sends no reset ahead of the answer.
async fn linger(mut stream: TcpStream, settings: &Settings) {
    if stream.shutdown().await.is_err() {
        return;
    }
    let deadline = tokio::time::Instant::now() + settings.linger_total;
    let mut buffer = vec![0u8; 64 * 1024];
    let mut discarded = 0u64;
    while discarded < settings.linger_bytes {
        let until = deadline.min(tokio::time::Instant::now() + settings.linger_pause);
        match tokio::time::timeout_at(until, stream.read(&mut buffer)).await {
            Ok(Ok(0)) | Ok(Err(_)) | Err(_) => break,
            Ok(Ok(n)) => discarded += n as u64,
        }
    }
}

/// The router as hyper's service for one connection: marks the connection
/// busy from a request's headers to the end of its answer's body, and
/// notes a request body left unread.
#[derive(Clone)]
struct ConnectionService {
    router: Router,
    registry: Arc<Registry>,
    connection: Arc<Connection>,
    body_rate: Option<BodyRate>,
}

impl hyper::service::Service<hyper::Request<Incoming>> for ConnectionService {
    type Response = hyper::Response<Body>;
    type Error = Infallible;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Infallible>> + Send>>;

    fn call(&self, request: hyper::Request<Incoming>) -> Self::Future {
        // A connection chosen for closing keeps that mark: its task is
        // being aborted.
        let _ = self
            .connection
            .idle
            .fetch_update(Ordering::AcqRel, Ordering::Relaxed, |v| {
                (v != EVICTED).then_some(BUSY)
            });
        self.connection.unread_body.store(false, Ordering::Relaxed);
        let meter = Arc::new(Meter::default());
        *self
            .connection
            .meter
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = Some(meter.clone());
        let note = self
            .connection
            .framing
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take_note();
        let refused = RefusedFraming::of(request.method(), note);
        let busy = Busy {
            registry: self.registry.clone(),
            connection: self.connection.clone(),
        };
        let mut request = request.map(|body| {
            Body::new(Tracked {
                body,
                connection: self.connection.clone(),
                ended: false,
                meter,
                rate: self.body_rate,
                timer: None,
            })
        });
        if let Some(refused) = refused {
            request.extensions_mut().insert(refused);
        }
        let router = self.router.clone();
        Box::pin(async move {
            let response = router.oneshot(request).await?;
            Ok(response.map(|body| Body::new(Answer { body, _busy: busy })))
        })
    }
}

/// Marks its connection idle again when dropped (with the answer's body,
/// once hyper has written it).
struct Busy {
    registry: Arc<Registry>,
    connection: Arc<Connection>,
}

impl Drop for Busy {
    fn drop(&mut self) {
        let now = self.registry.now();
        let _ = self
            .connection
            .idle
            .fetch_update(Ordering::AcqRel, Ordering::Relaxed, |v| {
                (v != EVICTED).then_some(now)
            });
        self.registry.changed.notify_waiters();
    }
}

/// An answer's body, holding its connection busy until dropped.
struct Answer {
    body: Body,
    _busy: Busy,
}

impl HttpBody for Answer {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use std::task::Waker;

    use super::*;
    use crate::service::infra::metrics::Metrics;

    #[test]
    fn the_default_limit_keeps_a_reserve() {
        assert_eq!(default_max_connections(None, 2, 6), 1024);
        // 20,000 files, 2 workers, 6 database connections: 64 + 24 + 32 +
        // 1,250 kept.
        assert_eq!(default_max_connections(Some(20_000), 2, 6), 18_630);
        assert_eq!(default_max_connections(Some(1024), 2, 6), 840);
        assert_eq!(default_max_connections(Some(100), 2, 6), 50);
        assert_eq!(default_max_connections(Some(10_000_000), 2, 6), 65_536);
    }

    /// Fail closed: a request without a note (the scan stopped
    /// following) is refused, as is every CONNECT.
    #[test]
    fn requests_the_scan_cannot_vouch_for_are_refused() {
        use hyper::Method;
        assert_eq!(RefusedFraming::of(&Method::POST, Some(false)), None);
        assert_eq!(
            RefusedFraming::of(&Method::POST, Some(true)),
            Some(RefusedFraming::Conflicting)
        );
        assert_eq!(
            RefusedFraming::of(&Method::GET, None),
            Some(RefusedFraming::Unfollowed)
        );
        assert_eq!(
            RefusedFraming::of(&Method::CONNECT, Some(false)),
            Some(RefusedFraming::Connect)
        );
    }

    /// Serves `router` on a new port with `max` connections and a write
    /// timeout of `write_timeout`: its address, registry, and its stop.
    async fn serve_for_test(
        router: Router,
        max: usize,
        write_timeout: Duration,
    ) -> (
        std::net::SocketAddr,
        Arc<Registry>,
        tokio::sync::oneshot::Sender<()>,
    ) {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let registry = Arc::new(Registry::new(max, Arc::new(Metrics::default())));
        let settings = Settings {
            header_timeout: Duration::from_secs(30),
            linger_bytes: 0,
            linger_pause: Duration::from_secs(1),
            linger_total: Duration::from_secs(1),
            body_rate: None,
            write_timeout,
        };
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        tokio::spawn(serve(listener, router, registry.clone(), settings, async {
            let _ = stopped.await;
        }));
        (address, registry, stop)
    }

    /// A router with a large answer streamed in 1 MiB pieces (64 MiB:
    /// more than the socket buffers of both ends hold, so a client that
    /// reads none of it stalls the write while the answer is still in
    /// flight, as a particles CSV's) and a small one.
    fn large_and_small() -> Router {
        Router::new()
            .route(
                "/large",
                axum::routing::get(|| async {
                    let pieces = (0..64).map(|_| Ok::<_, Infallible>(vec![b'x'; 1 << 20]));
                    Body::from_stream(futures_util::stream::iter(pieces))
                }),
            )
            .route("/small", axum::routing::get(|| async { "small" }))
    }

    /// Sends `GET path` on a new connection and reads nothing.
    async fn ask_and_never_read(address: std::net::SocketAddr, path: &str) -> TcpStream {
        let mut stream = TcpStream::connect(address).await.unwrap();
        let request = format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n");
        stream.write_all(request.as_bytes()).await.unwrap();
        stream
    }

    /// Reads `GET /small`'s whole answer on a new connection.
    async fn small_answer(address: std::net::SocketAddr) -> String {
        let mut stream = TcpStream::connect(address).await.unwrap();
        let request = "GET /small HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n";
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).await.unwrap();
        String::from_utf8_lossy(&answer).into_owned()
    }

    /// Waits until a connection's write has stalled (its socket buffers
    /// full), with a patience of 30 s for a loaded machine.
    async fn until_a_write_stalls(registry: &Registry) {
        let started = Instant::now();
        while registry
            .longest_stalled_writer(u64::MAX, Duration::ZERO)
            .is_none()
        {
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "no write stalled"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Issue 29, slow readers: a client that asks for a large answer and
    /// reads none of it holds its connection for the write timeout (here
    /// 1 s) and no longer; the connection is then closed.
    #[tokio::test]
    async fn a_client_that_never_reads_its_answer_is_closed_after_the_write_timeout() {
        let timeout = Duration::from_secs(1);
        let (address, registry, _stop) = serve_for_test(large_and_small(), 100, timeout).await;
        let _client = ask_and_never_read(address, "/large").await;
        // The write stalls once the socket buffers are full...
        until_a_write_stalls(&registry).await;
        assert_eq!(registry.len(), 1);
        // ...then fails after the timeout, closing the connection
        // (patience 30 s for a loaded machine).
        let stalled = Instant::now();
        while !registry.is_empty() {
            assert!(
                stalled.elapsed() < Duration::from_secs(30),
                "the stalled connection is still open"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// At the connection limit (here 1) a connection whose answer has
    /// been stalled for the eviction grace is closed to let a new client
    /// in, long before its write timeout (here 600 s).
    #[tokio::test]
    async fn a_stalled_reader_makes_room_at_the_connection_limit() {
        let timeout = Duration::from_secs(600);
        let (address, registry, _stop) = serve_for_test(large_and_small(), 1, timeout).await;
        let _client = ask_and_never_read(address, "/large").await;
        // Until its write has stalled.
        until_a_write_stalls(&registry).await;
        let answer = tokio::time::timeout(Duration::from_secs(60), small_answer(address))
            .await
            .expect("the new client got in");
        assert!(answer.starts_with("HTTP/1.1 200 "), "{answer}");
        assert!(answer.ends_with("small"), "{answer}");
    }

    fn noop_waker() -> Waker {
        Waker::noop().clone()
    }

    /// A window of waiting must bring the rate's bytes: the check passes
    /// while it runs, fails at its end if it brought less, and starts a
    /// new window if it brought enough; time spent not waiting (the
    /// handler busy with what came) does not count.
    #[test]
    fn the_rate_is_checked_over_windows_of_waiting() {
        let rate = BodyRate {
            bytes_per_second: 100,
            window: Duration::from_secs(10),
        };
        let waker = noop_waker();
        let t0 = Instant::now();
        let at = |s: u64| t0 + Duration::from_secs(s);
        let meter = Meter::default();
        assert_eq!(
            meter.waiting_checked(at(0), &waker, &rate).unwrap(),
            Duration::from_secs(10)
        );
        meter.arrived(at(4), 1000, false);
        // 20 s not waiting: the handler was busy.
        assert_eq!(
            meter.waiting_checked(at(24), &waker, &rate).unwrap(),
            Duration::from_secs(6)
        );
        // The window ends with 1,000 bytes: enough; a new one starts.
        assert_eq!(
            meter.waiting_checked(at(30), &waker, &rate).unwrap(),
            Duration::from_secs(10)
        );
        meter.arrived(at(35), 999, false);
        assert_eq!(
            meter.waiting_checked(at(40), &waker, &rate).unwrap(),
            Duration::from_secs(5)
        );
        let error = meter.waiting_checked(at(45), &waker, &rate).unwrap_err();
        assert!(
            matches!(
                error,
                BodyTooSlow::Window {
                    bytes: 999,
                    window_secs: 10,
                    ..
                }
            ),
            "{error:?}"
        );
        assert!(error.to_string().contains("--min-body-rate"), "{error}");
    }

    /// Only a body waited for now, for at least the grace, below the rate,
    /// is a candidate for eviction; once evicted it says why.
    #[test]
    fn slow_bodies_waited_for_are_the_candidates_for_eviction() {
        let rate = BodyRate {
            bytes_per_second: 1024,
            window: Duration::from_secs(10),
        };
        let waker = noop_waker();
        let meter = Meter::default();
        assert!(meter.slow_rate(&rate).is_none(), "not waited for");
        let long_ago = Instant::now() - Duration::from_secs(5);
        meter.waiting(long_ago, &waker);
        let slow = meter.slow_rate(&rate).expect("5 s for nothing");
        assert!(slow < 1.0, "{slow}");
        meter.arrived(Instant::now(), 1 << 20, false);
        meter.waiting(Instant::now(), &waker);
        assert!(meter.slow_rate(&rate).is_none(), "1 MiB in 5 s is fast");
        let fresh = Meter::default();
        fresh.waiting(Instant::now(), &waker);
        assert!(fresh.slow_rate(&rate).is_none(), "within the grace");
        meter.evict(&rate);
        assert!(matches!(meter.evicted(), Some(BodyTooSlow::Evicted { .. })));
        assert!(meter.slow_rate(&rate).is_none(), "evicted once");
    }
}
