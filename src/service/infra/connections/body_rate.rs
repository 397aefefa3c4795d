//! A request body held to the least rate ([`BodyRate`]): [`Tracked`] meters
//! its arrival, and a body below the rate ends in [`BodyTooSlow`] (module
//! docs of [`super`]).

use std::sync::Mutex;
use std::task::Waker;
use std::time::{Duration, Instant};

use super::EVICTION_GRACE;

/// The least rate at which a request body must arrive: `--min-body-rate`
/// averaged over `--body-rate-window-secs`.
#[derive(Clone, Copy, Debug)]
pub struct BodyRate {
    /// Bytes per second.
    pub bytes_per_second: u64,
    /// Over how much time waiting for the body it is averaged.
    pub window: Duration,
}

impl BodyRate {
    /// The bytes a window must bring.
    pub(super) fn bytes_per_window(&self) -> f64 {
        self.bytes_per_second as f64 * self.window.as_secs_f64()
    }
}

/// Why a request body was ended: it arrived below `--min-body-rate`.
#[derive(Clone, Debug, thiserror::Error)]
pub enum BodyTooSlow {
    /// A whole window brought less than the rate asks.
    #[error(
        "the body arrived at {bytes} bytes in {window_secs} s, below the service's minimum of \
         {bytes_per_second} bytes/s (--min-body-rate, averaged over --body-rate-window-secs)"
    )]
    Window {
        /// What the window brought.
        bytes: u64,
        /// The window.
        window_secs: u64,
        /// The rate asked.
        bytes_per_second: u64,
    },
    /// Ended at the connection limit to let a new connection in.
    #[error(
        "the body arrived at {bytes} bytes in {waited_secs:.1} s, below the service's minimum of \
         {bytes_per_second} bytes/s (--min-body-rate), while every connection was busy; it was \
         ended to let another client in"
    )]
    Evicted {
        /// What had come.
        bytes: u64,
        /// In this much waiting.
        waited_secs: f64,
        /// The rate asked.
        bytes_per_second: u64,
    },
}

/// A request body's arrival: what came in how much waiting, shared by the
/// body and the accept loop (which may end it, [`Meter::evict`]).
#[derive(Debug, Default)]
pub(super) struct Meter(Mutex<MeterState>);

#[derive(Debug, Default)]
pub(super) struct MeterState {
    /// Bytes come.
    bytes: u64,
    /// Time spent waiting for them, before the current wait.
    waited: Duration,
    /// Since when the body is waited for, if it is.
    waiting_since: Option<Instant>,
    /// The bytes and the waiting at the start of the current rate window.
    window_start: (u64, Duration),
    /// Ended (whole, failed, dropped, or too slow).
    ended: bool,
    /// Why it is to end, set by the accept loop.
    evicted: Option<BodyTooSlow>,
    /// Wakes the body's reader, to see that it was evicted.
    waker: Option<Waker>,
}

impl MeterState {
    pub(super) fn waited_until(&self, now: Instant) -> Duration {
        self.waited
            + self
                .waiting_since
                .map_or(Duration::ZERO, |since| now.saturating_duration_since(since))
    }
}

impl Meter {
    pub(super) fn lock(&self) -> std::sync::MutexGuard<'_, MeterState> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// `bytes` came at `now` (`ended`: and nothing more will).
    pub(super) fn arrived(&self, now: Instant, bytes: u64, ended: bool) {
        let mut state = self.lock();
        state.waited = state.waited_until(now);
        state.waiting_since = None;
        state.bytes += bytes;
        state.ended |= ended;
        if ended {
            state.waker = None;
        }
    }

    /// The body is waited for from `now` on (if not already).
    pub(super) fn waiting(&self, now: Instant, waker: &Waker) {
        let mut state = self.lock();
        state.waiting_since.get_or_insert(now);
        if !state.waker.as_ref().is_some_and(|w| w.will_wake(waker)) {
            state.waker = Some(waker.clone());
        }
    }

    /// [`Meter::waiting`], and the rate check: an error if a whole window
    /// of waiting brought less than `rate` asks, else the waiting left in
    /// the current window.
    pub(super) fn waiting_checked(
        &self,
        now: Instant,
        waker: &Waker,
        rate: &BodyRate,
    ) -> Result<Duration, BodyTooSlow> {
        self.waiting(now, waker);
        let mut state = self.lock();
        let waited = state.waited_until(now);
        let (start_bytes, start_waited) = state.window_start;
        let in_window = waited.saturating_sub(start_waited);
        if in_window < rate.window {
            return Ok(rate.window - in_window);
        }
        let bytes = state.bytes - start_bytes;
        if (bytes as f64) < rate.bytes_per_window() {
            return Err(BodyTooSlow::Window {
                bytes,
                window_secs: rate.window.as_secs(),
                bytes_per_second: rate.bytes_per_second,
            });
        }
        state.window_start = (state.bytes, waited);
        Ok(rate.window)
    }

    /// The rate at which the body arrives, if it is waited for now, has
    /// been for at least [`EVICTION_GRACE`] (or the window, if shorter),
    /// and arrives below `rate`: the candidates for [`Meter::evict`].
    pub(super) fn slow_rate(&self, rate: &BodyRate) -> Option<f64> {
        let state = self.lock();
        if state.ended || state.evicted.is_some() || state.waiting_since.is_none() {
            return None;
        }
        let waited = state.waited_until(Instant::now());
        if waited < EVICTION_GRACE.min(rate.window) {
            return None;
        }
        let per_second = state.bytes as f64 / waited.as_secs_f64();
        (per_second < rate.bytes_per_second as f64).then_some(per_second)
    }

    /// Ends the body at its next read (waking its reader).
    pub(super) fn evict(&self, rate: &BodyRate) {
        let mut state = self.lock();
        let waited = state.waited_until(Instant::now());
        state.evicted = Some(BodyTooSlow::Evicted {
            bytes: state.bytes,
            waited_secs: waited.as_secs_f64(),
            bytes_per_second: rate.bytes_per_second,
        });
        if let Some(waker) = state.waker.take() {
            waker.wake();
        }
    }

    /// Why the body is to end, if the accept loop chose it.
    pub(super) fn evicted(&self) -> Option<BodyTooSlow> {
        self.lock().evicted.clone()
    }
}
