//! The [`Registry`] of open connections: since when each has waited for a
//! complete request, and which to close at the limit (module docs of
//! [`super`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::Notify;
use tokio::task::AbortHandle;

use super::body_rate::{BodyRate, Meter};
use crate::service::infra::metrics::Metrics;

/// `idle` of a connection with a request in flight.
pub(super) const BUSY: u64 = 0;
/// `idle` of a connection chosen to be closed.
pub(super) const EVICTED: u64 = u64::MAX;

/// One connection as the registry sees it.
#[derive(Debug)]
pub(super) struct Connection {
    /// [`BUSY`], [`EVICTED`], or 1 + the milliseconds from the registry's
    /// epoch to the moment it last became idle (accepted, or its last
    /// answer ended).
    pub(super) idle: AtomicU64,
    /// Set when a request's body was left unread: close by lingering.
    pub(super) unread_body: AtomicBool,
    /// Set when a request's body arrived too slowly: linger for at most
    /// the rate window.
    pub(super) too_slow: AtomicBool,
    /// The body of the request in flight, if any.
    pub(super) meter: Mutex<Option<Arc<Meter>>>,
    /// The scan of the incoming bytes for conflicting framing.
    pub(super) framing: Mutex<super::framing::Framing>,
    /// Since when a write to the client has made no progress, if one is
    /// waiting (the client reads none of its answer).
    pub(super) write_stalled: Mutex<Option<Instant>>,
    /// Cancels the connection's task.
    pub(super) task: OnceLock<AbortHandle>,
}

impl Connection {
    pub(super) fn meter(&self) -> Option<Arc<Meter>> {
        self.meter.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    pub(super) fn write_stalled(&self) -> std::sync::MutexGuard<'_, Option<Instant>> {
        self.write_stalled.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The open connections.
#[derive(Debug)]
pub struct Registry {
    pub(super) max: usize,
    pub(super) epoch: Instant,
    pub(super) next_id: AtomicU64,
    pub(super) open: Mutex<HashMap<u64, Arc<Connection>>>,
    /// Notified when a connection ends or becomes idle.
    pub(super) changed: Notify,
    pub(super) metrics: Arc<Metrics>,
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

    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<Connection>>> {
        self.open.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub(super) fn now(&self) -> u64 {
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

    pub(super) fn register(self: &Arc<Self>) -> Registered {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let connection = Arc::new(Connection {
            idle: AtomicU64::new(self.now()),
            unread_body: AtomicBool::new(false),
            too_slow: AtomicBool::new(false),
            meter: Mutex::new(None),
            framing: Mutex::default(),
            write_stalled: Mutex::new(None),
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

    /// The latest `idle` value of a connection idle for at least `min`.
    pub(super) fn idle_cutoff(&self, min: Duration) -> u64 {
        let min = u64::try_from(min.as_millis()).unwrap_or(u64::MAX);
        self.now().saturating_sub(min)
    }

    /// Whether some connection has waited at least `min` without a
    /// request in flight.
    pub(super) fn any_idle_for(&self, min: Duration) -> bool {
        let cutoff = self.idle_cutoff(min);
        self.lock().values().any(|c| {
            let idle = c.idle.load(Ordering::Relaxed);
            !matches!(idle, BUSY | EVICTED) && idle <= cutoff
        })
    }

    /// The request in flight whose body arrives slowest, below `rate`
    /// (over at least [`EVICTION_GRACE`] of waiting), if any.
    pub(super) fn slowest_body(&self, rate: &BodyRate) -> Option<Arc<Meter>> {
        let open = self.lock();
        let slowest = open
            .values()
            .filter(|c| c.idle.load(Ordering::Relaxed) == BUSY)
            .filter_map(|c| c.meter())
            .filter_map(|meter| Some((meter.slow_rate(rate)?, meter)))
            .min_by(|(a, _), (b, _)| a.total_cmp(b))
            .map(|(_, meter)| meter);
        slowest
    }

    /// Whether some request in flight has a body arriving below `rate`.
    pub(super) fn any_slow_body(&self, rate: Option<&BodyRate>) -> bool {
        rate.is_some_and(|rate| self.slowest_body(rate).is_some())
    }

    /// Ends the request whose body arrives slowest below `rate` (its body
    /// fails with [`BodyTooSlow`], answered 408); false if there is none.
    pub(super) fn evict_slowest_body(&self, rate: Option<&BodyRate>) -> bool {
        let Some(rate) = rate else {
            return false;
        };
        let Some(meter) = self.slowest_body(rate) else {
            return false;
        };
        meter.evict(rate);
        self.metrics.slow_body_evicted();
        true
    }

    /// The connection whose write has made no progress longest, for at
    /// least `min`, other than `except`, if any.
    pub(super) fn longest_stalled_writer(&self, except: u64, min: Duration) -> Option<u64> {
        let now = Instant::now();
        self.lock()
            .iter()
            .filter(|(id, c)| **id != except && c.idle.load(Ordering::Relaxed) != EVICTED)
            .filter_map(|(id, c)| {
                let stalled = now.saturating_duration_since((*c.write_stalled())?);
                (stalled >= min).then_some((stalled, *id))
            })
            .max()
            .map(|(_, id)| id)
    }

    /// Closes the connection whose answer has been stalled longest (its
    /// client reads none of it), for at least `min`, other than `except`;
    /// false if there is none.
    pub(super) fn evict_stalled_writer(&self, except: u64, min: Duration) -> bool {
        let Some(id) = self.longest_stalled_writer(except, min) else {
            return false;
        };
        let mut open = self.lock();
        let Some(connection) = open.remove(&id) else {
            return false;
        };
        connection.idle.store(EVICTED, Ordering::Release);
        if let Some(task) = connection.task.get() {
            task.abort();
        }
        let len = open.len();
        drop(open);
        self.metrics.connection_evicted(len);
        true
    }

    /// Closes the connection that has waited longest without a complete
    /// request, other than `except`, if it has waited at least `min`;
    /// false if there is none (every other one has a request in flight, or
    /// has waited less).
    pub(super) fn evict_oldest_idle(&self, except: u64, min: Duration) -> bool {
        let cutoff = self.idle_cutoff(min);
        let mut open = self.lock();
        loop {
            let oldest = open
                .iter()
                .filter(|(id, _)| **id != except)
                .filter_map(|(id, c)| {
                    let idle = c.idle.load(Ordering::Relaxed);
                    (!matches!(idle, BUSY | EVICTED) && idle <= cutoff).then_some((idle, *id))
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
pub(super) struct Registered {
    pub(super) registry: Arc<Registry>,
    pub(super) id: u64,
    pub(super) connection: Arc<Connection>,
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
