//! What HTTP handlers and workers share: the stores, the CPU pool, the
//! memory budget, the caches, the trackers and the event streams of one
//! process (`ptv serve` or `ptv worker`).

use std::sync::Arc;

use tokio::sync::Notify;

use crate::service::infra::budget::MemoryBudget;
use crate::service::infra::config::Config;
use crate::service::infra::metrics::Metrics;
use crate::service::infra::process::host_name;
use crate::service::ops::computing::Computing;
use crate::service::ops::events::{self, Events};
use crate::service::ops::images::ImageStore;
use crate::service::ops::jobs::cache::PipelineCache;
use crate::service::ops::jobs::pool::CpuPool;
use crate::service::ops::tracking::live::Trackers;
use crate::service::store::{Store, WorkerId};

/// What handlers and workers share.
#[derive(Debug)]
pub struct AppState {
    /// The settings, resolved from the flags.
    pub config: Config,
    /// The database.
    pub store: Store,
    /// The image files.
    pub images: ImageStore,
    /// The CPU threads.
    pub cpu: CpuPool,
    /// The memory the jobs of this process may hold at once.
    pub budget: MemoryBudget,
    /// The sequences whose background a worker of this process computes.
    pub computing: Computing,
    /// Prepared pipelines by sequence.
    pub pipelines: PipelineCache,
    /// Counters for /metrics.
    pub metrics: Arc<Metrics>,
    /// Wakes a waiting worker of this process when a job is enqueued
    /// (workers in other processes poll).
    pub wake: Notify,
    /// This process's name in job claims and leases
    /// (`HOST:PID:RANDOM`, [`WorkerId`]).
    pub instance: String,
    /// The tracking runs' trackers.
    pub trackers: Trackers,
    /// Live progress for `GET /sequences/{id}/events`.
    pub events: Events,
}

impl AppState {
    /// The state of a process (`ptv serve` or `ptv worker`) on its opened
    /// stores, with empty caches and its own worker name, and the recorder
    /// of its events running (`service::events`; it ends with the
    /// runtime).
    pub fn start(
        config: Config,
        store: Store,
        images: ImageStore,
        cpu: CpuPool,
        metrics: Arc<Metrics>,
    ) -> Arc<AppState> {
        let budget =
            MemoryBudget::new(config.job_limits.memory_budget_mib(), Some(metrics.clone()));
        let state = Arc::new(AppState {
            config,
            store,
            images,
            cpu,
            budget,
            computing: Default::default(),
            pipelines: PipelineCache::default(),
            metrics,
            wake: Notify::new(),
            instance: WorkerId::instance(&host_name()),
            trackers: Default::default(),
            events: Default::default(),
        });
        tokio::spawn(events::record(state.events.clone(), state.store.clone()));
        state
    }
}
