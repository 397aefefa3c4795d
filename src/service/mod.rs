//! The service: the HTTP API in front of the core, a durable job queue
//! with a pool of workers, and SQLite (or PostgreSQL) plus an image
//! directory for storage.
//!
//! Floors, each importing only its own and those below it (checked by
//! `python3 scripts/import_graph.py src/service --floors
//! app,http,ops,store,model,infra`):
//!
//! - [`app`]: builds the service from its settings, binds, serves until a
//!   shutdown signal, drains the workers; `ptv worker`'s loop without HTTP.
//! - [`http`]: axum routers per resource under `/api/v1`, one error type
//!   rendered as RFC 9457 problem+json, the OpenAPI document and docs page,
//!   and the tower layers every request passes through.
//! - [`ops`]: what handlers and workers both call: the shared state, the
//!   workers and the job kinds, the CPU pool, self-calibration,
//!   backgrounds, live tracking, the event streams, the stored images.
//! - [`store`]: all SQL, one text per query for SQLite (WAL mode, the
//!   default) and PostgreSQL (`--database`); migrations in `migrations/`.
//! - [`model`]: the types rows carry: typed ids, a sequence's parameters,
//!   tracking settings, the stored raw layout, the job kinds.
//! - [`infra`]: `ptv serve`'s flags, HTTP/1.1 connections within a limit,
//!   the memory budget, the counters behind `/metrics`, the blob codec,
//!   file locks, error and process helpers.
//!
//! The core ([`crate::photogrammetry`]) knows nothing of this module.

pub mod app;
pub mod http;
pub mod infra;
pub mod model;
pub mod ops;
pub mod store;

use std::io::Write;
use std::net::SocketAddr;
use std::path::Path;

pub use app::Application;
pub use infra::config::{Config, JobLimits, Lease, ServeArgs, Timeouts, WorkerArgs};
pub use ops::state::AppState;

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
    Database(#[source] store::StoreError),
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
        source: store::StoreError,
    },
    /// The image store could not be opened (a data directory that cannot
    /// be written, an object store that cannot be reached or refuses the
    /// credentials).
    #[error("{0}")]
    Images(#[source] ops::images::ImageStoreError),
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
    runtime()?.block_on(app::run_worker(args, shutdown_signal()))
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
