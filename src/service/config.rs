//! The service's settings: `ptv serve`'s flags, each also an environment
//! variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

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
    /// Requests on the CPU-heavy routes (creating a sequence, projecting
    /// points) run at once; more get 503 with Retry-After [default: the
    /// workers]
    #[arg(long, env = "PTV_MAX_CPU_REQUESTS", value_parser = clap::value_parser!(u32).range(1..))]
    pub max_cpu_requests: Option<u32>,
    /// Connections open at once. At the limit, a new connection closes the
    /// one that has waited longest without sending a complete request
    /// [default: the open-file limit (raised to its hard value at start)
    /// less a reserve for the database, image files and workers]
    #[arg(long, env = "PTV_MAX_CONNECTIONS", value_parser = clap::value_parser!(u64).range(1..))]
    pub max_connections: Option<u64>,
    /// Time limits on connections and requests.
    #[command(flatten)]
    pub timeouts: Timeouts,
    /// Time limits on jobs.
    #[command(flatten)]
    pub job_limits: JobLimits,
}

/// How long a job may run: `--job-timeout-secs` plus
/// `--job-timeout-factor` times the single-core time its size is expected
/// to take (see `service::jobs::TimeLimit`). A job past its limit is
/// stopped and fails with the reason; it is not retried.
#[derive(Clone, Debug, Args)]
pub struct JobLimits {
    /// Seconds every job may take whatever its size (the limit's floor).
    #[arg(long = "job-timeout-secs", env = "PTV_JOB_TIMEOUT_SECS",
          default_value_t = JobLimits::FLOOR_SECS)]
    pub floor_secs: f64,
    /// How many times the expected single-core time of a job's size
    /// (pixels decoded and detected, targets matched) it may take on top
    /// of the floor.
    #[arg(long = "job-timeout-factor", env = "PTV_JOB_TIMEOUT_FACTOR",
          default_value_t = JobLimits::FACTOR)]
    pub factor: f64,
}

impl JobLimits {
    /// Default of `--job-timeout-secs`.
    pub const FLOOR_SECS: f64 = 60.0;
    /// Default of `--job-timeout-factor`.
    pub const FACTOR: f64 = 10.0;
}

impl Default for JobLimits {
    fn default() -> Self {
        JobLimits {
            floor_secs: JobLimits::FLOOR_SECS,
            factor: JobLimits::FACTOR,
        }
    }
}

/// How long the service waits for a client, in seconds (each at least 1).
#[derive(Clone, Debug, Args)]
pub struct Timeouts {
    /// Seconds a client has to send a request's headers once it starts one,
    /// and that a kept-alive connection may stay idle before its next
    /// request; then the connection is closed.
    #[arg(long = "header-timeout-secs", env = "PTV_HEADER_TIMEOUT_SECS",
          default_value_t = Timeouts::HEADER_SECS, value_parser = clap::value_parser!(u64).range(1..))]
    pub header_secs: u64,
    /// Seconds a request body may pause between two pieces of data; a
    /// client that stalls longer gets 408. Applies per piece, so a large
    /// upload that keeps moving is never cut off by it.
    #[arg(long = "body-timeout-secs", env = "PTV_BODY_TIMEOUT_SECS",
          default_value_t = Timeouts::BODY_SECS, value_parser = clap::value_parser!(u64).range(1..))]
    pub body_secs: u64,
    /// Seconds from a request's headers to its answer's headers, upload
    /// included (408 while the body still arrives, else 503). A streamed
    /// download is not limited once it starts. The default lets an upload
    /// of 256 MiB through at 7 Mbit/s.
    #[arg(long = "request-timeout-secs", env = "PTV_REQUEST_TIMEOUT_SECS",
          default_value_t = Timeouts::REQUEST_SECS, value_parser = clap::value_parser!(u64).range(1..))]
    pub request_secs: u64,
}

impl Timeouts {
    /// Default of `--header-timeout-secs` (hyper's own default).
    pub const HEADER_SECS: u64 = 30;
    /// Default of `--body-timeout-secs`.
    pub const BODY_SECS: u64 = 30;
    /// Default of `--request-timeout-secs`.
    pub const REQUEST_SECS: u64 = 300;

    /// `--header-timeout-secs`.
    pub fn header(&self) -> Duration {
        Duration::from_secs(self.header_secs)
    }

    /// `--body-timeout-secs`.
    pub fn body(&self) -> Duration {
        Duration::from_secs(self.body_secs)
    }

    /// `--request-timeout-secs`.
    pub fn request(&self) -> Duration {
        Duration::from_secs(self.request_secs)
    }
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            header_secs: Timeouts::HEADER_SECS,
            body_secs: Timeouts::BODY_SECS,
            request_secs: Timeouts::REQUEST_SECS,
        }
    }
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

    /// How many CPU-heavy requests may run at once: the flag, or the workers.
    pub fn cpu_request_limit(&self) -> usize {
        self.max_cpu_requests
            .map_or_else(|| self.worker_count(), |n| n as usize)
    }
}
