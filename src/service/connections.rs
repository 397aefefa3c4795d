//! Serving HTTP/1.1 connections with hyper, within a connection limit.
//!
//! Every connection lives in a [`Registry`] with the time since which it
//! has been waiting for a complete request (`None` while a request is in
//! flight, from its headers to the end of its answer's body). The accept
//! loop keeps at most `--max-connections` open: when one more arrives, the
//! connection that has waited longest without sending a complete request is
//! closed (an idle kept-alive one, or a slowloris still trickling its
//! headers), so a new client always gets in while no request in flight is
//! cut. Only if every connection has a request in flight does the loop stop
//! accepting until one ends (new clients then wait in the listen backlog).
//! The default limit is the open-file limit, raised to its hard value at
//! start, less a reserve for the database, image files and workers, so
//! that `accept` never fails for want of file descriptors.
//!
//! hyper's header read timeout (`--header-timeout-secs`) still closes a
//! connection that does not complete a request's headers in time, and a
//! kept-alive one idle that long.
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

use std::collections::HashMap;
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes, HttpBody};
use axum::Router;
use http_body::{Frame, SizeHint};
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, Notify};
use tokio::task::AbortHandle;
use tower::ServiceExt;

use super::config::ServeArgs;
use super::metrics::Metrics;

/// The largest request head hyper buffers (request line and header
/// fields); the service's own limits (`http::layers`: 8 KiB of request
/// target, 64 KiB and 100 header fields) lie below it, so that they answer
/// with problem+json. Hyper answers a larger head itself, with an empty 431.
/// It is also hyper's largest read buffer, so it bounds an idle
/// connection's memory.
pub const HYPER_MAX_HEAD_BYTES: usize = 128 * 1024;

/// The most header fields hyper parses; more get its empty 431.
pub const HYPER_MAX_HEADERS: usize = 256;

/// File descriptors kept for everything but connections: standard streams,
/// the listener, the runtime's, the log.
const RESERVE_BASE: u64 = 64;

/// The default limit's ceiling: more idle connections than this cost more
/// memory than they are worth; `--max-connections` can go higher.
const DEFAULT_CEILING: u64 = 65_536;

/// Raises the soft limit on open files to the hard one (on Unix) and
/// returns the soft limit then in force, if known.
pub fn raise_open_file_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        use rustix::process::{getrlimit, setrlimit, Resource, Rlimit};
        let limit = getrlimit(Resource::Nofile);
        if limit.current.is_some() && limit.current != limit.maximum {
            // An unlimited hard limit cannot be the soft one on Linux
            // (`fs.nr_open` caps it); try a large finite value instead.
            let target = limit.maximum.unwrap_or(1 << 20);
            let raised = Rlimit {
                current: Some(target),
                maximum: limit.maximum,
            };
            if let Err(error) = setrlimit(Resource::Nofile, raised) {
                tracing::debug!(%error, "cannot raise the open-file limit");
            }
        }
        getrlimit(Resource::Nofile).current
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// The default connection limit for `open_files` file descriptors: less a
/// reserve of 64, 4 per database connection (database, WAL, shared memory,
/// journal), 16 per worker (the image files of a frame) and a sixteenth of
/// the limit (uploads' temporary files), at most 65,536. Without a known
/// limit, 1,024.
pub fn default_max_connections(open_files: Option<u64>, workers: usize, database: u32) -> usize {
    let Some(open_files) = open_files else {
        return 1024;
    };
    let reserve = RESERVE_BASE + 4 * u64::from(database) + 16 * workers as u64 + open_files / 16;
    let max = if open_files > 2 * reserve {
        open_files - reserve
    } else {
        open_files / 2
    };
    usize::try_from(max.clamp(1, DEFAULT_CEILING)).unwrap_or(1)
}

/// `idle` of a connection with a request in flight.
const BUSY: u64 = 0;
/// `idle` of a connection chosen to be closed.
const EVICTED: u64 = u64::MAX;

/// One connection as the registry sees it.
#[derive(Debug)]
struct Connection {
    /// [`BUSY`], [`EVICTED`], or 1 + the milliseconds from the registry's
    /// epoch to the moment it last became idle (accepted, or its last
    /// answer ended).
    idle: AtomicU64,
    /// Set when a request's body was left unread: close by lingering.
    unread_body: AtomicBool,
    /// Cancels the connection's task.
    task: OnceLock<AbortHandle>,
}

/// The open connections.
#[derive(Debug)]
pub struct Registry {
    max: usize,
    epoch: Instant,
    next_id: AtomicU64,
    open: Mutex<HashMap<u64, Arc<Connection>>>,
    /// Notified when a connection ends or becomes idle.
    changed: Notify,
    metrics: Arc<Metrics>,
}

impl Registry {
    /// A registry allowing `max` connections at once (at least 1).
    pub fn new(max: usize, metrics: Arc<Metrics>) -> Registry {
        metrics.connection_limit(max);
        Registry {
            max: max.max(1),
            epoch: Instant::now(),
            next_id: AtomicU64::new(0),
            open: Mutex::default(),
            changed: Notify::new(),
            metrics,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<Connection>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn now(&self) -> u64 {
        1 + u64::try_from(self.epoch.elapsed().as_millis()).unwrap_or(u64::MAX - 2)
    }

    /// How many connections are open.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether none is open.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn register(self: &Arc<Self>) -> Registered {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let connection = Arc::new(Connection {
            idle: AtomicU64::new(self.now()),
            unread_body: AtomicBool::new(false),
            task: OnceLock::new(),
        });
        let open = {
            let mut open = self.lock();
            open.insert(id, connection.clone());
            open.len()
        };
        self.metrics.connections_open(open);
        Registered {
            registry: self.clone(),
            id,
            connection,
        }
    }

    /// Whether some connection waits without a request in flight.
    fn any_idle(&self) -> bool {
        self.lock()
            .values()
            .any(|c| !matches!(c.idle.load(Ordering::Relaxed), BUSY | EVICTED))
    }

    /// Closes the connection that has waited longest without a complete
    /// request, other than `except`; false if every other one has a request
    /// in flight.
    fn evict_oldest_idle(&self, except: u64) -> bool {
        let mut open = self.lock();
        loop {
            let oldest = open
                .iter()
                .filter(|(id, _)| **id != except)
                .filter_map(|(id, c)| {
                    let idle = c.idle.load(Ordering::Relaxed);
                    (!matches!(idle, BUSY | EVICTED)).then_some((idle, *id))
                })
                .min();
            let Some((idle, id)) = oldest else {
                return false;
            };
            let connection = &open[&id];
            // A request may have begun since the scan: then look again.
            if connection
                .idle
                .compare_exchange(idle, EVICTED, Ordering::AcqRel, Ordering::Relaxed)
                .is_err()
            {
                continue;
            }
            if let Some(task) = connection.task.get() {
                task.abort();
            }
            open.remove(&id);
            let len = open.len();
            drop(open);
            self.metrics.connection_evicted(len);
            return true;
        }
    }
}

/// A connection's place in the registry; leaving it on drop.
struct Registered {
    registry: Arc<Registry>,
    id: u64,
    connection: Arc<Connection>,
}

impl Drop for Registered {
    fn drop(&mut self) {
        let open = {
            let mut open = self.registry.lock();
            open.remove(&self.id);
            open.len()
        };
        self.registry.metrics.connections_open(open);
        self.registry.changed.notify_waiters();
    }
}

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
}

impl Settings {
    /// From the service's settings.
    pub fn new(config: &ServeArgs) -> Settings {
        Settings {
            header_timeout: config.timeouts.header(),
            linger_bytes: config.max_upload_bytes() as u64,
            linger_pause: config.timeouts.body(),
            linger_total: config.timeouts.request(),
        }
    }
}

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
    loop {
        // Every connection has a request in flight: accept nothing until
        // one ends or turns idle.
        if registry.len() >= registry.max && !registry.any_idle() {
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
        if registry.len() > registry.max && !registry.evict_oldest_idle(id) {
            // Every other connection turned busy since the check above.
            registry.evict_oldest_idle(u64::MAX);
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
    if out_of_files && registry.evict_oldest_idle(u64::MAX) {
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
    let stream = connection.into_parts().io.into_inner();
    // A shutdown cuts the lingering short.
    tokio::select! {
        () = linger(stream, &settings) => {}
        _ = stopped.changed() => {}
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
        let busy = Busy {
            registry: self.registry.clone(),
            connection: self.connection.clone(),
        };
        let request = request.map(|body| {
            Body::new(Tracked {
                body,
                connection: self.connection.clone(),
                ended: false,
            })
        });
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

/// A request's body, noting on its connection whether it was left unread.
struct Tracked {
    body: Incoming,
    connection: Arc<Connection>,
    ended: bool,
}

impl HttpBody for Tracked {
    type Data = Bytes;
    type Error = hyper::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, hyper::Error>>> {
        let polled = Pin::new(&mut self.body).poll_frame(cx);
        if matches!(polled, Poll::Ready(None)) {
            self.ended = true;
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        if !self.ended && !self.body.is_end_stream() {
            self.connection.unread_body.store(true, Ordering::Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
