//! Cooperative stopping of long CPU work: a [`Cancel`] token that the
//! caller can fire (a request whose client has gone) or that expires at a
//! deadline (a job past its time limit), and that the work checks between
//! its steps ([`Cancel::check`]): between cameras in detection, in the
//! matcher's outer loops. Pure std: the shell decides when to fire it.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Why work stopped before its end.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Cancelled {
    /// The caller stopped it (for example, its client went away).
    #[error("stopped: nobody waits for the result any more")]
    Stopped,
    /// It ran past its deadline.
    #[error("stopped at its time limit of {:.1} s", .0.as_secs_f64())]
    TimedOut(Duration),
}

#[derive(Debug)]
struct Inner {
    stopped: AtomicBool,
    origin: Instant,
    /// Nanoseconds after `origin`; `u64::MAX` for none.
    deadline_ns: AtomicU64,
}

/// A shared stop flag with an optional deadline; clones share both.
#[derive(Clone, Debug)]
pub struct Cancel {
    inner: Arc<Inner>,
}

impl Default for Cancel {
    fn default() -> Self {
        Cancel::new()
    }
}

impl Cancel {
    /// A token that stops only when [`Cancel::stop`] is called.
    pub fn new() -> Cancel {
        Cancel {
            inner: Arc::new(Inner {
                stopped: AtomicBool::new(false),
                origin: Instant::now(),
                deadline_ns: AtomicU64::new(u64::MAX),
            }),
        }
    }

    /// A token that also stops `limit` from now.
    pub fn with_limit(limit: Duration) -> Cancel {
        let cancel = Cancel::new();
        cancel.set_limit(limit);
        cancel
    }

    /// Sets the deadline to `limit` after the token was made (a limit that
    /// grows as the work's size becomes known, such as the targets found).
    pub fn set_limit(&self, limit: Duration) {
        let ns = u64::try_from(limit.as_nanos()).unwrap_or(u64::MAX - 1);
        self.inner.deadline_ns.store(ns, Ordering::Relaxed);
    }

    /// The limit, counted from the token's making, if one is set.
    pub fn limit(&self) -> Option<Duration> {
        match self.inner.deadline_ns.load(Ordering::Relaxed) {
            u64::MAX => None,
            ns => Some(Duration::from_nanos(ns)),
        }
    }

    /// When the deadline is, if one is set.
    pub fn deadline(&self) -> Option<Instant> {
        self.limit().map(|limit| self.inner.origin + limit)
    }

    /// Stops the work at its next check.
    pub fn stop(&self) {
        self.inner.stopped.store(true, Ordering::Relaxed);
    }

    /// Whether [`Cancel::stop`] was called.
    pub fn is_stopped(&self) -> bool {
        self.inner.stopped.load(Ordering::Relaxed)
    }

    /// `Err` once the token was stopped or its deadline passed. Cheap (an
    /// atomic load and, with a deadline, a clock read): call it between
    /// steps of a millisecond or less, not per pixel.
    pub fn check(&self) -> Result<(), Cancelled> {
        if self.is_stopped() {
            return Err(Cancelled::Stopped);
        }
        if let Some(limit) = self.limit() {
            if self.inner.origin.elapsed() > limit {
                return Err(Cancelled::TimedOut(limit));
            }
        }
        Ok(())
    }
}

/// Stops a [`Cancel`] when dropped: held by whoever waits for the work, so
/// that the work stops when the waiter goes away (a request handler's
/// future dropped because its client closed the connection or a timeout
/// fired).
#[derive(Debug)]
pub struct StopOnDrop(pub Cancel);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.stop();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stops_when_told_or_at_the_deadline() {
        let cancel = Cancel::new();
        assert_eq!(cancel.check(), Ok(()));
        let clone = cancel.clone();
        clone.stop();
        assert_eq!(cancel.check(), Err(Cancelled::Stopped));

        let timed = Cancel::with_limit(Duration::from_millis(1));
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(
            timed.check(),
            Err(Cancelled::TimedOut(Duration::from_millis(1)))
        );
        timed.set_limit(Duration::from_secs(3600));
        assert_eq!(timed.check(), Ok(()));
    }

    #[test]
    fn the_guard_stops_on_drop() {
        let cancel = Cancel::new();
        {
            let _guard = StopOnDrop(cancel.clone());
        }
        assert!(cancel.is_stopped());
    }
}
