//! What every request passes through, built from tower and tower-http
//! layers in one place ([`apply`]), outermost first:
//!
//! 1. `SetRequestIdLayer`: an `x-request-id` (a UUID) unless the client
//!    sent one.
//! 2. `PropagateRequestIdLayer`: the id on every answer, including the
//!    ones the layers below make.
//! 3. `TraceLayer`: a span per request with its id, method, route and
//!    path; status and latency logged at info.
//! 4. `CompressionLayer`: gzip for clients that accept it (particle CSVs
//!    and JSON shrink about fivefold), streamed answers included. It polls
//!    a body once more after its end (tower-http issue 732), which a
//!    streamed answer such as the particle CSV panics on, so the bodies
//!    under it are fused (`fuse_body`).
//! 5. `count_request`: requests by method, route and status for
//!    `/metrics` (what no layer does).
//! 6. `RequestBodyTimeoutLayer`: a body that pauses longer than
//!    `--body-timeout-secs` between two pieces ends in an error.
//! 7. `watch_body`: records whether the body arrived whole, stalled,
//!    arrived below `--min-body-rate` (the connection's body ends it,
//!    [`crate::service::infra::connections::BodyTooSlow`]) or was cut off by the
//!    client; a stalled or too slow one is answered 408, one the client
//!    cut off 499 (counted so in `/metrics`, logged as a warning: the
//!    client's doing, not a server error), and a refused request whose
//!    body is partly unread gets `Connection: close` (what no layer does).
//! 8. `CatchPanicLayer`: a panicking handler is logged and answered with a
//!    problem+json 500.
//! 9. `HeadLimits`: a request target over 8 KiB is a 414, header fields
//!    over 64 KiB or 100 a 431, both problem+json naming the limit (hyper
//!    would answer larger heads itself, with an empty body); a head that
//!    declared both `Content-Length` and `Transfer-Encoding` (noted by the
//!    connection, as hyper drops the length) a 400.
//! 10. [`bearer_token`], a `ValidateRequestHeaderLayer`: with
//!     `--api-token`, any path under `/api` without the token is a 401,
//!     before the route or method is looked at (an unknown route or method
//!     would otherwise answer 404 or 405 and let routes be probed).
//! 11. `ValidateRequestHeaderLayer`: a declared body over `--max-upload-mb`
//!     is refused with 413 before any of it is read.
//! 12. `HandleErrorLayer` over tower's `TimeoutLayer`: a request not
//!     answered within `--request-timeout-secs` gets 408 if its body was
//!     still arriving, else 503.
//! 13. `shed_cpu_routes`: on the routes that run CPU work inside the
//!     request (creating a sequence builds its matcher, projecting points,
//!     drawing a plot),
//!     `load_shed` over a `GlobalConcurrencyLimitLayer` of
//!     `--max-cpu-requests`: one more is answered 503 with `Retry-After`
//!     at once rather than queued on the rayon pool ahead of the frames.
//! 14. `RequestBodyLimitLayer`: a body without a declared length fails
//!     with 413 as soon as it passes the limit, whoever reads it (axum's
//!     own default limit of 2 MB is disabled).
//!
//! `Router::layer` wraps the routes, the fallback and the method-not-allowed
//! answers alike, so all of the above applies to every request. Header read
//! and idle connection timeouts are hyper's, the connection limit and the
//! lingering close after a refused upload are
//! [`crate::service::infra::connections`]'s.

use std::any::Any;
use std::pin::Pin;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};

use axum::body::{Body, Bytes, HttpBody};
use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Router};
use http_body::{Frame, SizeHint};
use http_body_util::BodyExt;
use tokio::sync::Semaphore;
use tower::limit::GlobalConcurrencyLimitLayer;
use tower::{BoxError, ServiceBuilder, ServiceExt};
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::compression::CompressionLayer;
use tower_http::limit::RequestBodyLimitLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::timeout::{RequestBodyTimeoutLayer, TimeoutBody, TimeoutError};
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use tower_http::validate_request::{ValidateRequest, ValidateRequestHeaderLayer};
use tower_http::LatencyUnit;
use tracing::{Level, Span};

use super::problem::ApiError;
use crate::service::infra::config::Config;
use crate::service::infra::connections::{BodyTooSlow, RefusedFraming};
use crate::service::infra::metrics::Metrics;

/// The routes whose handlers do CPU work before answering.
const CPU_ROUTES: [(Method, &str); 3] = [
    (Method::POST, "/api/v1/sequences"),
    (Method::POST, "/api/v1/experiments/openptv"),
    (Method::POST, "/api/v1/calibrations/{id}/project"),
];

/// Wraps `router`'s routes and fallback in the service's layers (see the
/// module's documentation for the order and why).
pub fn apply<S: Clone + Send + Sync + 'static>(
    router: Router<S>,
    config: &Config,
    metrics: Arc<Metrics>,
) -> Router<S> {
    let limit = config.max_upload_bytes;
    let request_secs = config.timeouts.request_secs;
    let cpu = Arc::new(Semaphore::new(config.cpu_request_limit));
    let stack = ServiceBuilder::new()
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(request_span)
                .on_response(
                    DefaultOnResponse::new()
                        .level(Level::INFO)
                        .latency_unit(LatencyUnit::Micros),
                ),
        )
        .layer(CompressionLayer::new())
        .map_response(fuse_body)
        .layer(middleware::from_fn_with_state(metrics, count_request))
        .layer(RequestBodyTimeoutLayer::new(config.timeouts.body()))
        .map_request(|request: Request<TimeoutBody<Body>>| request.map(Body::new))
        .layer(middleware::from_fn_with_state(
            config.timeouts.body_secs,
            watch_body,
        ))
        .layer(CatchPanicLayer::custom(answer_panic))
        .layer(ValidateRequestHeaderLayer::custom(HeadLimits))
        .layer(bearer_token(config.api_token.as_deref()))
        .layer(ValidateRequestHeaderLayer::custom(DeclaredLength { limit }))
        .layer(HandleErrorLayer::new(
            move |progress: Option<Extension<BodyProgress>>, error: BoxError| async move {
                timed_out(error, progress.map(|p| p.0), request_secs)
            },
        ))
        .layer(tower::timeout::TimeoutLayer::new(config.timeouts.request()))
        .layer(middleware::from_fn_with_state(cpu, shed_cpu_routes))
        .layer(RequestBodyLimitLayer::new(limit))
        .layer(DefaultBodyLimit::disable());
    router.layer(stack)
}

/// The longest request target (path and query) taken; longer is a 414.
pub const MAX_TARGET_BYTES: usize = 8 * 1024;
/// The most bytes of header fields taken (name, value and 4 bytes of
/// separators each, as sent); more is a 431.
pub const MAX_HEADER_BYTES: usize = 64 * 1024;
/// The most header fields taken; more is a 431.
pub const MAX_HEADER_FIELDS: usize = 100;

/// Refuses a request head past the service's limits ([`MAX_TARGET_BYTES`],
/// [`MAX_HEADER_BYTES`], [`MAX_HEADER_FIELDS`]) with a 414 or 431 problem
/// that names the limit. Hyper's own limits lie above these (see
/// [`crate::service::infra::connections::HYPER_MAX_HEAD_BYTES`]), so a head between
/// the two gets this problem rather than hyper's empty answer.
#[derive(Clone, Copy, Debug)]
struct HeadLimits;

impl<B> ValidateRequest<B> for HeadLimits {
    type ResponseBody = Body;

    fn validate(&mut self, request: &mut Request<B>) -> Result<(), Response> {
        if let Some(refused) = request.extensions().get::<RefusedFraming>() {
            let mut response = ApiError::bad_request(refused.reason()).into_response();
            response
                .headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            return Err(response);
        }
        let uri = request.uri();
        let target = uri.path_and_query().map_or(0, |p| p.as_str().len())
            + uri.authority().map_or(0, |a| a.as_str().len());
        if target > MAX_TARGET_BYTES {
            return Err(ApiError::new(
                StatusCode::URI_TOO_LONG,
                format!(
                    "the request target is {target} bytes, more than the service's limit of \
                     {MAX_TARGET_BYTES} bytes"
                ),
            )
            .into_response());
        }
        // As the client sent them: without the request id set above.
        let sent = request
            .headers()
            .iter()
            .filter(|(name, _)| name.as_str() != "x-request-id");
        let (fields, bytes) = sent.fold((0, 0), |(fields, bytes), (name, value)| {
            (fields + 1, bytes + name.as_str().len() + value.len() + 4)
        });
        if fields > MAX_HEADER_FIELDS || bytes > MAX_HEADER_BYTES {
            return Err(ApiError::new(
                StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
                format!(
                    "the request has {fields} header fields of {bytes} bytes; the service takes \
                     at most {MAX_HEADER_FIELDS} fields and {MAX_HEADER_BYTES} bytes"
                ),
            )
            .into_response());
        }
        Ok(())
    }
}

/// With a token, every path under `/api` needs `Authorization: Bearer
/// <token>` (the scheme in any case, RFC 9110 section 11.1), whether it
/// names a route and takes the method or not, so that routes cannot be
/// probed without it; the token is compared in constant time, and a missing
/// or wrong one is a 401 problem with `WWW-Authenticate: Bearer`.
pub fn bearer_token(token: Option<&str>) -> ValidateRequestHeaderLayer<BearerToken> {
    ValidateRequestHeaderLayer::custom(BearerToken {
        token: token.map(|t| t.as_bytes().into()),
    })
}

/// The check behind [`bearer_token`] (none without a token).
#[derive(Clone, Debug)]
pub struct BearerToken {
    token: Option<Arc<[u8]>>,
}

/// Whether `path` is under `/api` (as routed: the path as sent, not
/// percent-decoded).
fn under_api(path: &str) -> bool {
    path.strip_prefix("/api")
        .is_some_and(|rest| rest.is_empty() || rest.starts_with('/'))
}

impl ValidateRequest<Body> for BearerToken {
    type ResponseBody = Body;

    fn validate(&mut self, request: &mut Request) -> Result<(), Response> {
        let Some(token) = &self.token else {
            return Ok(());
        };
        if !under_api(request.uri().path()) {
            return Ok(());
        }
        let given = request
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, given)| given.trim());
        if given.is_some_and(|given| constant_time_eq(given.as_bytes(), token)) {
            return Ok(());
        }
        let error = ApiError::new(
            StatusCode::UNAUTHORIZED,
            "this service needs `Authorization: Bearer <token>` with its API token",
        );
        Err(([(header::WWW_AUTHENTICATE, "Bearer")], error).into_response())
    }
}

/// Compares without stopping at the first difference.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The request's span: its id, method, route pattern and path.
fn request_span(request: &Request) -> Span {
    let id = request
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map_or("unmatched", MatchedPath::as_str);
    // A path is logged up to 256 bytes (it may be up to MAX_TARGET_BYTES
    // and more, on a request about to be refused for it).
    let path = request.uri().path();
    let path = match path.char_indices().nth(256) {
        Some((end, _)) => &path[..end],
        None => path,
    };
    tracing::info_span!(
        "request",
        id,
        method = %request.method(),
        route,
        path,
    )
}

/// A body that answers "ended" however often it is polled after its end.
fn fuse_body(response: Response) -> Response {
    response.map(|body| Body::new(body.fuse()))
}

/// Counts the request by method, route and status for `/metrics`.
async fn count_request(
    State(metrics): State<Arc<Metrics>>,
    request: Request,
    next: Next,
) -> Response {
    let method = request.method().to_string();
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map_or("unmatched", MatchedPath::as_str)
        .to_owned();
    let response = next.run(request).await;
    metrics.request(&method, &route, response.status().as_u16());
    response
}

/// How far a request's body got, shared by the body and the layers that
/// answer for it: still arriving, complete, stalled past the body
/// timeout, too slow (with the reason), or cut off by the client.
#[derive(Clone, Debug)]
struct BodyProgress(Arc<(AtomicU8, OnceLock<String>)>);

impl BodyProgress {
    const ARRIVING: u8 = 0;
    const COMPLETE: u8 = 1;
    const STALLED: u8 = 2;
    const TOO_SLOW: u8 = 3;
    const ABORTED: u8 = 4;

    fn new() -> BodyProgress {
        BodyProgress(Arc::new((
            AtomicU8::new(BodyProgress::ARRIVING),
            OnceLock::new(),
        )))
    }

    fn set(&self, state: u8) {
        self.0 .0.store(state, Ordering::Relaxed);
    }

    fn state(&self) -> u8 {
        self.0 .0.load(Ordering::Relaxed)
    }

    fn complete(&self) -> bool {
        self.state() == BodyProgress::COMPLETE
    }

    /// Whether it stalled, was too slow or was cut off.
    fn failed(&self) -> bool {
        matches!(
            self.state(),
            BodyProgress::STALLED | BodyProgress::TOO_SLOW | BodyProgress::ABORTED
        )
    }

    /// Records why the body was too slow.
    fn too_slow(&self, reason: String) {
        let _ = self.0 .1.set(reason);
        self.set(BodyProgress::TOO_SLOW);
    }

    /// Why the body was too slow, if it was.
    fn too_slow_reason(&self) -> Option<&str> {
        (self.state() == BodyProgress::TOO_SLOW)
            .then(|| self.0 .1.get().map(String::as_str))
            .flatten()
    }
}

/// A request body that records its [`BodyProgress`]. It sits under the
/// body timeout, which hides where the body ends, so a body with a declared
/// length is complete once that many bytes came, one without once it ends.
struct Watched {
    body: Body,
    progress: BodyProgress,
    /// Bytes still to come, when the length is declared.
    remaining: Option<u64>,
}

impl HttpBody for Watched {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let polled = Pin::new(&mut self.body).poll_frame(cx);
        match &polled {
            // A body that failed stays failed (a reader may poll again).
            _ if self.progress.failed() => {}
            Poll::Ready(None) => self.progress.set(BodyProgress::COMPLETE),
            Poll::Ready(Some(Ok(frame))) => {
                let length = frame.data_ref().map_or(0, |data| data.len() as u64);
                if let Some(remaining) = &mut self.remaining {
                    *remaining = remaining.saturating_sub(length);
                    if *remaining == 0 {
                        self.progress.set(BodyProgress::COMPLETE);
                    }
                }
            }
            Poll::Ready(Some(Err(error))) => {
                if is_body_timeout(error) {
                    self.progress.set(BodyProgress::STALLED);
                } else if let Some(slow) = find_cause::<BodyTooSlow>(error) {
                    self.progress.too_slow(slow.to_string());
                } else if is_client_abort(error) {
                    self.progress.set(BodyProgress::ABORTED);
                }
            }
            _ => {}
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

/// The first of `error`'s causes that is an `E`.
fn find_cause<E: std::error::Error + 'static>(error: &axum::Error) -> Option<&E> {
    std::iter::successors(std::error::Error::source(error), |e| e.source())
        .find_map(|e| e.downcast_ref::<E>())
}

/// Whether `error` is the body timeout's.
fn is_body_timeout(error: &axum::Error) -> bool {
    find_cause::<TimeoutError>(error).is_some()
}

/// Whether `error` says that the client closed or reset the connection
/// before its body was complete (hyper's "incomplete message" or an I/O
/// error of that kind), rather than sending a malformed body.
fn is_client_abort(error: &axum::Error) -> bool {
    use std::io::ErrorKind::{BrokenPipe, ConnectionAborted, ConnectionReset, UnexpectedEof};
    find_cause::<hyper::Error>(error).is_some_and(hyper::Error::is_incomplete_message)
        || find_cause::<std::io::Error>(error).is_some_and(|io| {
            matches!(
                io.kind(),
                UnexpectedEof | ConnectionReset | ConnectionAborted | BrokenPipe
            )
        })
}

/// Status 499 (nginx's "client closed request"): a request whose client
/// went away before its body was complete. No one reads the answer; the
/// status keeps it apart from the server's errors in `/metrics`.
pub const CLIENT_CLOSED_REQUEST: u16 = 499;

/// Watches the body: a body that stalled past `--body-timeout-secs` or
/// arrived below `--min-body-rate` is answered 408 whatever the handler
/// made of the error, one the client cut off 499 (a warning in the log,
/// not a server error); and a refused request whose body was not read to
/// its end gets `Connection: close`, so the client does not send another
/// request on a connection that cannot carry it.
async fn watch_body(State(body_secs): State<u64>, request: Request, next: Next) -> Response {
    let progress = BodyProgress::new();
    let (mut parts, body) = request.into_parts();
    // HTTP/1.1: a request has a body if it declares a length or a transfer
    // coding (RFC 9112 section 6.3).
    let remaining = declared_length(&parts.headers);
    if remaining == Some(0)
        || (remaining.is_none() && !parts.headers.contains_key(header::TRANSFER_ENCODING))
    {
        progress.set(BodyProgress::COMPLETE);
    }
    parts.extensions.insert(progress.clone());
    let body = Body::new(Watched {
        body,
        progress: progress.clone(),
        remaining,
    });
    let mut response = next.run(Request::from_parts(parts, body)).await;
    let refused = response.status().is_client_error() || response.status().is_server_error();
    if refused {
        match progress.state() {
            BodyProgress::STALLED => {
                response = ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    format!(
                        "the body stopped arriving for {body_secs} s (--body-timeout-secs); \
                         nothing was stored, send the request again"
                    ),
                )
                .into_response();
            }
            BodyProgress::TOO_SLOW => {
                let reason = progress
                    .too_slow_reason()
                    .unwrap_or("the body arrived too slowly");
                response = ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    format!("{reason}; nothing was stored, send the request again"),
                )
                .into_response();
            }
            BodyProgress::ABORTED => {
                tracing::warn!(
                    "the client closed the connection before its request body was complete; \
                     nothing was stored"
                );
                let status =
                    StatusCode::from_u16(CLIENT_CLOSED_REQUEST).unwrap_or(StatusCode::BAD_REQUEST);
                response = ApiError::new(
                    status,
                    "the connection closed before the request body was complete; nothing was \
                     stored",
                )
                .into_response();
            }
            _ => {}
        }
    }
    if refused && !progress.complete() {
        response
            .headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    response
}

/// A panic in a handler: logged with its message, answered with a 500.
fn answer_panic(panic: Box<dyn Any + Send + 'static>) -> Response {
    let message = panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("no message");
    ApiError::internal(format_args!("a request handler panicked: {message}")).into_response()
}

/// The body's length, if the request declares it.
fn declared_length(headers: &HeaderMap) -> Option<u64> {
    headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
}

/// Refuses a body declared larger than `limit` bytes before reading it.
#[derive(Clone, Copy, Debug)]
struct DeclaredLength {
    limit: usize,
}

impl ValidateRequest<Body> for DeclaredLength {
    type ResponseBody = Body;

    fn validate(&mut self, request: &mut Request) -> Result<(), Response> {
        let limit = self.limit;
        match declared_length(request.headers()) {
            Some(length) if length > limit as u64 => Err(ApiError::too_large(format!(
                "the body is {length} bytes, more than the service's limit of {limit} bytes \
                 (--max-upload-mb); send fewer or smaller images per request"
            ))
            .into_response()),
            _ => Ok(()),
        }
    }
}

/// The answer to a request the timeout gave up on: 408 if its body was
/// still arriving (the client's link is the slow part), else 503.
fn timed_out(error: BoxError, progress: Option<BodyProgress>, request_secs: u64) -> Response {
    if !error.is::<tower::timeout::error::Elapsed>() {
        return ApiError::internal(error).into_response();
    }
    if progress.is_some_and(|p| !p.complete()) {
        ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the body was still arriving after {request_secs} s (--request-timeout-secs); \
                 nothing was stored: send fewer or smaller images per request, or ask for a \
                 higher limit"
            ),
        )
        .into_response()
    } else {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("the service did not answer within {request_secs} s (--request-timeout-secs)"),
        )
        .into_response()
    }
}

/// On the [`CPU_ROUTES`], at most as many requests at once as the
/// semaphore has permits; one more is answered 503 with `Retry-After: 1`.
async fn shed_cpu_routes(
    State(permits): State<Arc<Semaphore>>,
    request: Request,
    next: Next,
) -> Response {
    let route = request
        .extensions()
        .get::<MatchedPath>()
        .map(MatchedPath::as_str);
    let heavy = CPU_ROUTES
        .iter()
        .any(|(method, path)| request.method() == method && route == Some(*path))
        || (request.method() == Method::GET
            && route.is_some_and(|r| super::plots::PLOT_ROUTES.contains(&r)));
    if !heavy {
        return next.run(request).await;
    }
    ServiceBuilder::new()
        .load_shed()
        .layer(GlobalConcurrencyLimitLayer::with_semaphore(permits))
        .service(next)
        .oneshot(request)
        .await
        .unwrap_or_else(|_overloaded| {
            let error = ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the service is busy with as many of these requests as it runs at once \
                 (--max-cpu-requests); try again in a moment",
            );
            ([(header::RETRY_AFTER, "1")], error).into_response()
        })
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use axum::body::to_bytes;
    use axum::routing::{get, post};
    use tower::ServiceExt;

    use super::*;
    use crate::service::infra::config::Timeouts;

    fn config(request_secs: u64, max_cpu_requests: u32) -> Config {
        crate::service::infra::config::ServeArgs {
            bind: "127.0.0.1:0".parse().unwrap(),
            storage: crate::service::infra::config::Storage::in_directory("unused"),
            workers: Some(1),
            max_upload_mb: 1,
            api_token: None,
            max_cpu_requests: Some(max_cpu_requests),
            max_connections: None,
            max_export_points: crate::service::infra::config::DEFAULT_MAX_EXPORT_POINTS,
            timeouts: Timeouts {
                request_secs,
                ..Timeouts::default()
            },
            job_limits: Default::default(),
            lease: Default::default(),
        }
        .config()
    }

    async fn panics() -> &'static str {
        panic!("on purpose")
    }

    /// The routes under test, in the service's stack.
    fn app(config: &Config) -> Router {
        let slow = || async {
            tokio::time::sleep(Duration::from_millis(1500)).await;
            "done"
        };
        let routes = Router::new()
            .route("/panic", get(panics))
            .route("/slow", get(slow))
            .route("/api/v1/calibrations/{id}/project", post(slow));
        apply(routes, config, Arc::new(Metrics::default()))
    }

    async fn call(app: &Router, method: Method, uri: &str) -> (StatusCode, HeaderMap, String) {
        let request = Request::builder()
            .method(method)
            .uri(uri)
            .body(Body::empty())
            .unwrap();
        let response = app.clone().oneshot(request).await.unwrap();
        let (parts, body) = response.into_parts();
        let body = to_bytes(Body::new(body), usize::MAX).await.unwrap();
        (
            parts.status,
            parts.headers,
            String::from_utf8(body.to_vec()).unwrap(),
        )
    }

    #[tokio::test]
    async fn a_panic_is_a_problem_500_with_the_request_id() {
        let (status, headers, body) = call(&app(&config(5, 1)), Method::GET, "/panic").await;
        assert_eq!(status, StatusCode::INTERNAL_SERVER_ERROR);
        assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
        assert!(headers.contains_key("x-request-id"));
        assert!(
            body.contains("the service failed; the error is in its log"),
            "{body}"
        );
    }

    #[tokio::test]
    async fn a_request_past_the_timeout_is_a_problem_503() {
        let (status, headers, body) = call(&app(&config(1, 1)), Method::GET, "/slow").await;
        assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
        assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
        assert!(body.contains("--request-timeout-secs"), "{body}");
    }

    #[tokio::test]
    async fn cpu_routes_past_their_limit_are_shed_with_retry_after() {
        let app = app(&config(5, 1));
        let uri = "/api/v1/calibrations/1/project";
        let (first, second) = tokio::join!(call(&app, Method::POST, uri), async {
            tokio::time::sleep(Duration::from_millis(200)).await;
            call(&app, Method::POST, uri).await
        });
        assert_eq!(first.0, StatusCode::OK);
        assert_eq!(second.0, StatusCode::SERVICE_UNAVAILABLE, "{}", second.2);
        assert_eq!(second.1[header::RETRY_AFTER], "1");
        assert!(second.2.contains("--max-cpu-requests"), "{}", second.2);
        // Other routes are not limited, and the permit comes back.
        assert_eq!(call(&app, Method::GET, "/slow").await.0, StatusCode::OK);
        assert_eq!(call(&app, Method::POST, uri).await.0, StatusCode::OK);
    }
}
