//! Building the service from its settings and running it until a shutdown
//! signal: open the database (applying migrations) and the image store,
//! queue again the jobs a stopped process left running, bind the listener,
//! start the workers, serve HTTP.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio::sync::{watch, Notify};

use super::config::ServeArgs;
use super::images::ImageStore;
use super::jobs::{self, CpuPool, JobKinds, PipelineCache};
use super::metrics::Metrics;
use super::store::Store;
use super::{http, ServiceError};

/// How long a shutdown waits for running jobs before returning them to the
/// queue.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(30);

/// What handlers and workers share.
#[derive(Debug)]
pub struct AppState {
    /// The settings.
    pub config: ServeArgs,
    /// The database.
    pub store: Store,
    /// The image files.
    pub images: ImageStore,
    /// The CPU threads.
    pub cpu: CpuPool,
    /// Prepared pipelines by sequence.
    pub pipelines: PipelineCache,
    /// Counters for /metrics.
    pub metrics: Arc<Metrics>,
    /// Wakes a waiting worker when a job is enqueued.
    pub wake: Notify,
    /// This process's name in job claims.
    pub instance: String,
}

/// The built service, bound and ready to run.
pub struct Application {
    listener: TcpListener,
    state: Arc<AppState>,
    kinds: JobKinds,
}

impl Application {
    /// Opens the data directory and binds the listener.
    pub async fn build(config: ServeArgs) -> Result<Application, ServiceError> {
        let data_dir = &config.data_dir;
        std::fs::create_dir_all(data_dir).map_err(|e| ServiceError::io(data_dir, e))?;
        let workers = config.worker_count();
        let store = Store::open(data_dir, (workers as u32 + 4).min(16))
            .await
            .map_err(ServiceError::Database)?;
        let (requeued, failed) = store.reap().await.map_err(ServiceError::Database)?;
        if requeued + failed > 0 {
            tracing::warn!(
                requeued,
                failed,
                "jobs left running by a stopped process were queued again or failed"
            );
        }
        let images = ImageStore::open(data_dir).map_err(|e| ServiceError::io(data_dir, e))?;
        // A process killed between committing a frame's results and
        // deleting its images leaves files no row refers to.
        let mut swept = 0;
        for hash in images.stored().map_err(|e| ServiceError::io(data_dir, e))? {
            if !store
                .image_in_use(&hash)
                .await
                .map_err(ServiceError::Database)?
            {
                images
                    .remove(&hash)
                    .await
                    .map_err(|e| ServiceError::io(data_dir, e))?;
                swept += 1;
            }
        }
        if swept > 0 {
            tracing::warn!(files = swept, "removed image files no frame refers to");
        }
        let cpu = CpuPool::new(workers).map_err(|e| ServiceError::Start(e.to_string()))?;
        let listener = TcpListener::bind(config.bind)
            .await
            .map_err(|e| ServiceError::Bind(config.bind, e))?;
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or_default();
        let state = Arc::new(AppState {
            config,
            store,
            images,
            cpu,
            pipelines: PipelineCache::default(),
            metrics: Arc::default(),
            wake: Notify::new(),
            instance: format!("{}-{nanos}", std::process::id()),
        });
        Ok(Application {
            listener,
            state,
            kinds: JobKinds::standard(),
        })
    }

    /// The address bound (the port is the one picked for port 0).
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// What handlers and workers share (the store, to enqueue jobs).
    pub fn state(&self) -> Arc<AppState> {
        self.state.clone()
    }

    /// The job kinds the workers run; register new kinds here before
    /// [`Application::run_until`].
    pub fn kinds_mut(&mut self) -> &mut JobKinds {
        &mut self.kinds
    }

    /// Serves until `shutdown` completes: then stops taking connections,
    /// finishes the requests in flight, lets running jobs finish (for up to
    /// 30 s; jobs still running then go back to the queue) and closes the
    /// database.
    pub async fn run_until(
        self,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> Result<(), ServiceError> {
        let Application {
            listener,
            state,
            kinds,
        } = self;
        let (stop_workers, stopped) = watch::channel(false);
        let mut workers =
            jobs::spawn_workers(state.clone(), kinds, state.config.worker_count(), stopped);
        let router = http::router(state.clone());
        serve(listener, router, state.config.timeouts.header(), shutdown).await;
        let _ = stop_workers.send(true);
        let drained = tokio::time::timeout(SHUTDOWN_GRACE, async {
            while workers.join_next().await.is_some() {}
        })
        .await;
        if drained.is_err() {
            workers.abort_all();
            match state.store.release_held(&state.instance).await {
                Ok(n) => tracing::warn!(jobs = n, "running jobs returned to the queue"),
                Err(error) => tracing::error!(%error, "cannot return running jobs to the queue"),
            }
        }
        state.store.close().await;
        Ok(())
    }
}

/// Serves HTTP/1.1 connections with hyper until `shutdown` completes, then
/// stops accepting and waits for the connections to finish their requests
/// (idle ones close at once). A client gets `header_timeout` to send a
/// request's headers; the same limit closes a kept-alive connection that
/// stays idle (hyper times the wait for the next request's headers).
/// axum::serve offers no header timeout, hence this loop (axum's
/// serve-with-hyper example, with its graceful shutdown).
async fn serve(
    listener: TcpListener,
    router: Router,
    header_timeout: Duration,
    shutdown: impl Future<Output = ()>,
) {
    let mut http = http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(header_timeout);
    let connections = GracefulShutdown::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(error) => {
                    accept_failed(error).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let service = TowerToHyperService::new(router.clone());
        let connection = connections.watch(http.serve_connection(TokioIo::new(stream), service));
        tokio::spawn(async move {
            if let Err(error) = connection.await {
                tracing::debug!(%error, "connection closed with an error");
            }
        });
    }
    drop(listener);
    connections.shutdown().await;
}

/// A failed accept: a client that gave up is nothing; anything else (out
/// of file descriptors, most likely) is logged and waited out for a second,
/// as axum::serve does.
async fn accept_failed(error: std::io::Error) {
    use std::io::ErrorKind::{ConnectionAborted, ConnectionRefused, ConnectionReset};
    if matches!(
        error.kind(),
        ConnectionAborted | ConnectionRefused | ConnectionReset
    ) {
        return;
    }
    tracing::error!(%error, "cannot accept a connection");
    tokio::time::sleep(Duration::from_secs(1)).await;
}
