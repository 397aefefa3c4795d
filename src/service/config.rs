//! The service's settings: `ptv serve`'s flags, each also an environment
//! variable.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Args;

/// Arguments of `ptv serve` (and of `ptv` without a subcommand).
#[derive(Clone, Debug, Args)]
pub struct ServeArgs {
    /// Address and port to listen on; port 0 picks a free one (the address
    /// bound is printed).
    #[arg(long, env = "PTV_BIND", default_value = "127.0.0.1:8080")]
    pub bind: SocketAddr,
    /// Directory of the SQLite database and the image store (created if
    /// missing).
    #[arg(long, env = "PTV_DATA_DIR", default_value = "ptv-data")]
    pub data_dir: PathBuf,
    /// Frames processed at once, each on its own CPU thread [default: the
    /// number of cores]
    #[arg(long, env = "PTV_WORKERS")]
    pub workers: Option<usize>,
    /// Largest request body (MiB); larger uploads get 413.
    #[arg(long, env = "PTV_MAX_UPLOAD_MB", default_value_t = 256)]
    pub max_upload_mb: u64,
    /// When set, every /api route needs `Authorization: Bearer <token>`.
    #[arg(long, env = "PTV_API_TOKEN", hide_env_values = true)]
    pub api_token: Option<String>,
}

impl ServeArgs {
    /// The number of workers: the flag, or the cores.
    pub fn worker_count(&self) -> usize {
        self.workers
            .unwrap_or_else(|| {
                std::thread::available_parallelism()
                    .map(usize::from)
                    .unwrap_or(1)
            })
            .max(1)
    }

    /// The body limit in bytes.
    pub fn max_upload_bytes(&self) -> usize {
        usize::try_from(self.max_upload_mb.saturating_mul(1024 * 1024)).unwrap_or(usize::MAX)
    }
}
