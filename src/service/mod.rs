//! The service: the HTTP API in front of the core, a durable job queue
//! with a pool of workers, and SQLite (or PostgreSQL) plus an image
//! directory for storage.
//!
//! - [`config`]: `ptv serve`'s flags (each also an environment variable).
//! - [`app`]: builds the service from its settings, binds, serves until a
//!   shutdown signal, drains the workers; `ptv worker`'s loop without HTTP.
//! - [`connections`]: serves HTTP/1.1 with hyper within a connection limit
//!   (the longest-idle connection makes room for a new one) and closes a
//!   connection whose upload was refused unread by lingering.
//! - [`http`]: axum routers per resource under `/api/v1`, one error type
//!   rendered as RFC 9457 problem+json, the OpenAPI document and docs page,
//!   and the tower layers every request passes through.
//! - [`events`]: live progress, a sequence's changes broadcast to its
//!   event streams (server-sent events).
//! - [`jobs`]: the workers, the job kinds, the CPU pool.
//! - [`budget`]: the workers' memory budget, each job's declared need.
//! - [`store`]: all SQL, one text per query for SQLite (WAL mode, the
//!   default) and PostgreSQL (`--database`); migrations in `migrations/`.
//! - [`images`]: uploaded images as content-addressed files, in the data
//!   directory or an S3-compatible object store (`--object-store`).
//! - [`codec`]: the compact blobs in which targets and particles are stored.
//! - [`parameters`]: a sequence's detection and matching parameters.
//! - [`metrics`]: the counters behind `/metrics`.
//! - [`selfcal`]: a sequence's calibration refined from its stored targets
//!   (self-calibration), and its frames reprocessed with another one.
//! - [`tracking`]: a sequence's frames linked into trajectories as they
//!   complete, in frame order; the tracker rebuilt by replay after a
//!   restart.
//!
//! The core ([`crate::photogrammetry`]) knows nothing of this module.

pub mod app;
pub mod budget;
pub mod codec;
pub mod config;
pub mod connections;
pub mod events;
pub mod file_lock;
pub mod http;
pub mod images;
pub mod jobs;
pub mod metrics;
pub mod parameters;
pub mod preprocessing;
pub mod selfcal;
pub mod store;
pub mod tracking;

use std::io::Write;
use std::net::SocketAddr;
use std::path::Path;

pub use app::{AppState, Application};
pub use config::{JobLimits, Lease, ServeArgs, Timeouts, WorkerArgs};

/// Why the service could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The data directory could not be prepared.
    #[error("{path}: {source}")]
    Io {
        /// The directory or file.
        path: String,
        /// The operating system's reason.
        source: std::io::Error,
    },
    /// The database could not be opened or migrated.
    #[error("the database: {0}")]
    Database(#[source] sqlx::Error),
    /// The database server could not be reached within
    /// `--database-wait-secs`.
    #[error(
        "cannot reach the database server at {server} ({url}) after {waited_secs} s of trying \
         (--database-wait-secs)"
    )]
    DatabaseUnreachable {
        /// `HOST:PORT`.
        server: String,
        /// The URL, its password hidden.
        url: String,
        /// How long it was tried.
        waited_secs: u64,
        /// The last attempt's error.
        source: sqlx::Error,
    },
    /// The image store could not be opened (a data directory that cannot
    /// be written, an object store that cannot be reached or refuses the
    /// credentials).
    #[error("{0}")]
    Images(#[source] images::ImageStoreError),
    /// The address could not be bound.
    #[error("cannot listen on {0}: {1}")]
    Bind(SocketAddr, #[source] std::io::Error),
    /// Something else at start-up.
    #[error("cannot start: {0}")]
    Start(String),
    /// Serving failed.
    #[error("serving: {0}")]
    Serve(#[source] std::io::Error),
}

impl ServiceError {
    fn io(path: &Path, source: std::io::Error) -> ServiceError {
        ServiceError::Io {
            path: path.display().to_string(),
            source,
        }
    }
}

impl From<sqlx::migrate::MigrateError> for ServiceError {
    fn from(error: sqlx::migrate::MigrateError) -> Self {
        ServiceError::Database(error.into())
    }
}

/// Logging to standard error, and the multi-threaded runtime that `ptv
/// serve` and `ptv worker` run on.
fn runtime() -> Result<tokio::runtime::Runtime, ServiceError> {
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_target(false)
        .try_init();
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| ServiceError::Start(e.to_string()))
}

/// Runs the service until SIGINT or SIGTERM; prints the address bound and
/// the docs' URL to `stdout` once it listens.
pub fn run(args: ServeArgs, stdout: &mut dyn Write) -> Result<(), ServiceError> {
    runtime()?.block_on(async {
        let app = Application::build(args).await?;
        let address = app.local_addr().map_err(ServiceError::Serve)?;
        let _ = writeln!(stdout, "listening on http://{address}");
        let _ = writeln!(stdout, "API docs: http://{address}/docs");
        let _ = stdout.flush();
        app.run_until(shutdown_signal()).await
    })
}

/// Runs `ptv worker` until SIGINT or SIGTERM (see [`app::run_worker`]).
pub fn run_worker(args: WorkerArgs) -> Result<(), ServiceError> {
    runtime()?.block_on(app::run_worker(
        args,
        jobs::JobKinds::standard(),
        shutdown_signal(),
    ))
}

/// Completes at the first SIGINT (Ctrl-C) or SIGTERM.
pub async fn shutdown_signal() {
    let interrupt = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => {}
        () = terminate => {}
    }
    tracing::info!("shutting down");
}

/// The OpenAPI document, as committed in `openapi/openapi.json`.
pub fn openapi_json() -> String {
    http::docs::openapi_json()
}
