//! Building the service from its settings and running it until a shutdown
//! signal: open the database (applying migrations) and the image store,
//! queue again the jobs a stopped process left running, bind the listener,
//! start the workers, serve HTTP.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::{watch, Notify};

use super::config::ServeArgs;
use super::connections::{self, Registry};
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
    /// The tracking runs' trackers.
    pub trackers: super::tracking::Trackers,
    /// Live progress for `GET /sequences/{id}/events`.
    pub events: super::events::Events,
}

/// The built service, bound and ready to run.
pub struct Application {
    listener: TcpListener,
    connections: Arc<Registry>,
    state: Arc<AppState>,
    kinds: JobKinds,
}

impl Application {
    /// Opens the data directory and binds the listener.
    pub async fn build(config: ServeArgs) -> Result<Application, ServiceError> {
        let data_dir = &config.data_dir;
        std::fs::create_dir_all(data_dir).map_err(|e| ServiceError::io(data_dir, e))?;
        let workers = config.worker_count();
        let readers = (workers as u32 + 4).min(16);
        let store = Store::open(data_dir, readers)
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
        let open_files = connections::raise_open_file_limit();
        let max_connections = config.max_connections.map_or_else(
            || connections::default_max_connections(open_files, workers, readers + 1),
            |n| usize::try_from(n).unwrap_or(usize::MAX),
        );
        tracing::info!(
            open_files = open_files.map_or_else(|| "unknown".to_owned(), |n| n.to_string()),
            max_connections,
            "connection limit"
        );
        let metrics = Arc::new(Metrics::default());
        let connections = Arc::new(Registry::new(max_connections, metrics.clone()));
        let state = Arc::new(AppState {
            config,
            store,
            images,
            cpu,
            pipelines: PipelineCache::default(),
            metrics,
            wake: Notify::new(),
            instance: format!("{}-{nanos}", std::process::id()),
            trackers: Default::default(),
            events: Default::default(),
        });
        Ok(Application {
            listener,
            connections,
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
            connections,
            state,
            kinds,
        } = self;
        let (stop_workers, stopped) = watch::channel(false);
        let mut workers =
            jobs::spawn_workers(state.clone(), kinds, state.config.worker_count(), stopped);
        // Runs a stopped process left tracking go on from their stored
        // progress.
        super::tracking::resume_all(&state);
        let router = http::router(state.clone());
        let settings = connections::Settings::new(&state.config);
        // Event streams never end by themselves: they end at the shutdown,
        // so that the requests in flight can finish.
        let events = state.events.clone();
        let shutdown = async move {
            shutdown.await;
            events.close();
        };
        connections::serve(listener, router, connections, settings, shutdown).await;
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
