//! The CPU threads: a rayon pool that the async workers hand their
//! computing to, so that none runs on the runtime's threads.

use std::panic::AssertUnwindSafe;
use std::time::Duration;

use tokio::sync::oneshot;

use crate::photogrammetry::Cancel;

/// Why work handed to the [`CpuPool`] gave no result.
#[derive(Debug, thiserror::Error)]
pub enum CpuError {
    /// The work panicked, with this message.
    #[error("panicked: {0}")]
    Panicked(String),
    /// The pool dropped the work without running it to its end.
    #[error("the CPU pool dropped the work")]
    Dropped,
    /// The work ran past its deadline and did not stop when told to.
    #[error("ran past its time limit of {:.1} s and did not stop", .0.as_secs_f64())]
    Overran(Duration),
}

/// How long work past its deadline gets to notice its [`Cancel`] token
/// before the waiter sets it itself, and then to return, before the waiter
/// gives up on it.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// A bounded pool of CPU threads for detection and matching.
#[derive(Debug)]
pub struct CpuPool {
    pool: rayon::ThreadPool,
}

impl CpuPool {
    /// A pool of `threads` threads.
    pub fn new(threads: usize) -> Result<CpuPool, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("ptv-cpu-{i}"))
            .build()?;
        Ok(CpuPool { pool })
    }

    /// Runs `work` on the pool and waits for it without blocking the async
    /// runtime; a panic in `work` comes back as [`CpuError::Panicked`].
    pub async fn run<T, F>(&self, work: F) -> Result<T, CpuError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let (sender, receiver) = oneshot::channel();
        self.pool.spawn(move || {
            let result = std::panic::catch_unwind(AssertUnwindSafe(work));
            let _ = sender.send(result);
        });
        match receiver.await {
            Ok(Ok(value)) => Ok(value),
            Ok(Err(panic)) => Err(CpuError::Panicked(
                panic
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| panic.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "a panic".to_owned()),
            )),
            Err(_) => Err(CpuError::Dropped),
        }
    }

    /// [`CpuPool::run`] for work that checks `cancel` (a deadline, or a
    /// waiter that may go away): the token's deadline is its own to notice;
    /// `STOP_GRACE` after it the token is stopped from here, and if the
    /// work has still not returned after another grace, the wait ends with
    /// [`CpuError::Overran`] (the thread stays busy until the work's next
    /// check; every loop of the core checks within milliseconds).
    pub async fn run_until<T, F>(&self, cancel: &Cancel, work: F) -> Result<T, CpuError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let run = self.run(work);
        tokio::pin!(run);
        let limit = loop {
            let Some(deadline) = cancel.deadline() else {
                return run.await;
            };
            let at = tokio::time::Instant::from_std(deadline + STOP_GRACE);
            match tokio::time::timeout_at(at, &mut run).await {
                Ok(result) => return result,
                // The limit grew meanwhile: wait on.
                Err(_) if cancel.deadline() > Some(deadline) => continue,
                Err(_) => break cancel.limit().unwrap_or_default(),
            }
        };
        cancel.stop();
        tokio::time::timeout(STOP_GRACE, &mut run)
            .await
            .unwrap_or(Err(CpuError::Overran(limit)))
    }

    /// [`CpuPool::run`] for work that can fail: its error, or the pool's
    /// turned into it.
    pub async fn try_run<T, E, F>(&self, work: F) -> Result<T, E>
    where
        T: Send + 'static,
        E: From<CpuError> + Send + 'static,
        F: FnOnce() -> Result<T, E> + Send + 'static,
    {
        self.run(work).await?
    }
}
