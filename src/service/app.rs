//! Building the service from its settings and running it until a shutdown
//! signal: open the database (applying migrations) and the image store,
//! queue again the jobs a stopped process left running, bind the listener,
//! start the workers, serve HTTP. [`run_worker`]: the same without HTTP
//! (`ptv worker`).

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::watch;

use crate::service::infra::config::{ServeArgs, WorkerArgs};
use crate::service::infra::connections::{self, Registry};
use crate::service::infra::metrics::Metrics;
use crate::service::infra::process::{host_name, process_exists};
use crate::service::ops::events;
use crate::service::ops::images::{ImageStore, SweepError, SWEEP_INTERVAL};
use crate::service::ops::jobs;
use crate::service::ops::jobs::pool::CpuPool;
use crate::service::ops::state::AppState;
use crate::service::store::{self, Store};
use crate::service::{http, ServiceError};

/// How long a shutdown waits for running jobs before returning them to the
/// queue.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(30);

/// The built service, bound and ready to run.
pub struct Application {
    listener: TcpListener,
    connections: Arc<Registry>,
    state: Arc<AppState>,
}

impl Application {
    /// Opens the data directory and binds the listener.
    pub async fn build(config: ServeArgs) -> Result<Application, ServiceError> {
        let data_dir = &config.storage.data_dir;
        std::fs::create_dir_all(data_dir).map_err(|e| ServiceError::io(data_dir, e))?;
        let workers = config.worker_count();
        let readers = (workers as u32 + 4).min(16);
        let store = open_and_reap(&config, readers).await?;
        let images = ImageStore::open(data_dir, config.storage.objects.location())
            .await
            .map_err(ServiceError::Images)?
            .with_fsync(config.storage.durability.fsync);
        // A process killed between storing a file and committing its rows,
        // or between committing a frame's results and deleting its images,
        // leaves files no row refers to. A worker process may be storing
        // a file meanwhile: see `ImageStore::sweep`.
        sweep(&store, &images).await?;
        let cpu =
            CpuPool::new(config.cpu_threads()).map_err(|e| ServiceError::Start(e.to_string()))?;
        let listener = TcpListener::bind(config.bind)
            .await
            .map_err(|e| ServiceError::Bind(config.bind, e))?;
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
        let state = AppState::start(config.config(), store, images, cpu, metrics);
        Ok(Application {
            listener,
            connections,
            state,
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
        } = self;
        let (stop_workers, stopped) = watch::channel(false);
        let workers = start_workers(&state, stopped);
        tokio::spawn(events::follow(state.events.clone(), state.store.clone()));
        let sweeper = tokio::spawn(sweep_every(state.clone(), SWEEP_INTERVAL));
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
        sweeper.abort();
        let _ = stop_workers.send(true);
        drain(&state, workers).await;
        state.store.close().await;
        Ok(())
    }
}

/// Removes the stored files no row refers to ([`ImageStore::sweep`]),
/// saying how many.
async fn sweep(store: &Store, images: &ImageStore) -> Result<(), ServiceError> {
    let swept = images.sweep(store).await.map_err(|e| match e {
        SweepError::Images(e) => ServiceError::Images(e),
        SweepError::Database(e) => ServiceError::Database(e),
    })?;
    if swept > 0 {
        tracing::warn!(files = swept, "removed image files no frame refers to");
    }
    Ok(())
}

/// The sweep of a running `ptv serve`, every `interval` (the only process
/// that sweeps: workers never do, so there is one sweeper per database).
async fn sweep_every(state: Arc<AppState>, interval: Duration) {
    loop {
        tokio::time::sleep(interval).await;
        if let Err(error) = sweep(&state.store, &state.images).await {
            tracing::warn!(%error, "cannot remove unused image files; trying again later");
        }
    }
}

/// Opens the database and ends the leases that processes of this host
/// left when they died ([`Store::reap`]). A PostgreSQL server that cannot
/// be reached (not up yet, restarting, the network) is waited for up to
/// `--database-wait-secs`, each attempt logged with the server's host and
/// port and the cause; then the process gives up with the last cause.
async fn open_and_reap(config: &ServeArgs, readers: u32) -> Result<Store, ServiceError> {
    let started = std::time::Instant::now();
    let wait = config.storage.database_wait();
    let store = loop {
        let opened = match &config.storage.database {
            None => {
                let synchronous = if config.storage.durability.fsync {
                    store::Synchronous::Full
                } else {
                    store::Synchronous::Normal
                };
                Store::open_sqlite(&config.storage.data_dir, readers, synchronous).await
            }
            Some(url) => {
                // One connection first: its error says why (the pool's
                // would only say that it timed out).
                let left = wait
                    .saturating_sub(started.elapsed())
                    .max(Duration::from_secs(1));
                match Store::reach_postgres(url, left).await {
                    Ok(()) => Store::open_postgres(url, readers).await,
                    Err(error) => Err(error),
                }
            }
        };
        let error = match opened {
            Ok(store) => break store,
            Err(error) => error,
        };
        // A server not up yet (started together with this process,
        // restarting), or a network error on the way, is waited for;
        // anything else (a password refused, a failed migration) ends the
        // start at once.
        let database = config.storage.database.as_ref();
        let unreachable =
            error.kind() == store::ErrorKind::Unavailable || (database.is_some() && error.is_io());
        if !unreachable {
            return Err(ServiceError::Database(error));
        }
        let (server, url) = match database {
            Some(url) => (
                url.server().unwrap_or_else(|| url.to_string()),
                url.to_string(),
            ),
            None => {
                let file = config.storage.data_dir.join("ptv.sqlite");
                (file.display().to_string(), "SQLite".to_owned())
            }
        };
        let waited = started.elapsed();
        if waited >= wait {
            return Err(ServiceError::DatabaseUnreachable {
                server,
                url,
                waited_secs: waited.as_secs(),
                source: error,
            });
        }
        tracing::warn!(
            %server,
            cause = %error,
            waited_secs = waited.as_secs(),
            database_wait_secs = wait.as_secs(),
            "cannot reach the database server; trying again until --database-wait-secs"
        );
        tokio::time::sleep(Duration::from_secs(1).min(wait - waited)).await;
    };
    let (requeued, failed) = store
        .reap(&host_name(), process_exists)
        .await
        .map_err(ServiceError::Database)?;
    if requeued + failed > 0 {
        tracing::warn!(
            requeued,
            failed,
            "jobs left running by a stopped process were queued again or failed"
        );
    }
    Ok(store)
}

/// Starts the workers (none with `--workers 0`) and the tracking of the
/// runs a stopped process left tracking, which goes on from their stored
/// progress; a process without workers tracks nothing (tracking is CPU
/// work, left to the processes that have workers).
fn start_workers(
    state: &Arc<AppState>,
    stopped: watch::Receiver<bool>,
) -> tokio::task::JoinSet<()> {
    let count = state.config.workers;
    let workers = jobs::spawn_workers(state.clone(), count, stopped.clone());
    if count > 0 {
        tracing::info!(
            memory_budget_mib = state.budget.total_mib(),
            "jobs run within a memory budget of {} MiB (--memory-budget-mb)",
            state.budget.total_mib()
        );
        crate::service::ops::tracking::spawn_tracking(state.clone(), stopped);
    }
    workers
}

/// Lets the running jobs finish for up to [`SHUTDOWN_GRACE`], then returns
/// those still running to the queue.
async fn drain(state: &AppState, mut workers: tokio::task::JoinSet<()>) {
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
    // Another process may take this one's tracking runs over at once.
    if let Err(error) = state.store.release_tracking_leases(&state.instance).await {
        tracing::warn!(%error, "cannot give up the tracking runs' leases");
    }
}

/// Runs `ptv worker`: the job queue's workers on the data directory's
/// database and images, without HTTP, until `shutdown` completes; then
/// lets running jobs finish as `ptv serve` does. Everything a job needs is
/// in the database and the image store, so any number of these
/// processes share the queue with a `ptv serve` (SQLite in WAL mode allows
/// several processes on one host, each write taking the lock with `BEGIN
/// IMMEDIATE`; with `--database postgres://...` they may run on any host).
pub async fn run_worker(
    args: WorkerArgs,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServiceError> {
    let config = args.serve_args();
    let data_dir = config.storage.data_dir.clone();
    std::fs::create_dir_all(&data_dir).map_err(|e| ServiceError::io(&data_dir, e))?;
    let workers = config.worker_count();
    let readers = (workers as u32 + 4).min(16);
    let store = open_and_reap(&config, readers).await?;
    let images = ImageStore::open_shared(&data_dir, config.storage.objects.location())
        .await
        .map_err(ServiceError::Images)?
        .with_fsync(config.storage.durability.fsync);
    let cpu = CpuPool::new(workers).map_err(|e| ServiceError::Start(e.to_string()))?;
    let metrics = Arc::new(Metrics::default());
    let state = AppState::start(config.config(), store, images, cpu, metrics);
    tracing::info!(instance = %state.instance, workers, "worker started");
    // Its changes reach the serving processes' streams through the log.
    let (stop_workers, stopped) = watch::channel(false);
    let running = start_workers(&state, stopped);
    shutdown.await;
    let _ = stop_workers.send(true);
    drain(&state, running).await;
    state.store.close().await;
    Ok(())
}
