//! The service's settings: `ptv serve`'s flags, each also an environment
//! variable ([`ServeArgs`], parsed by clap), and what a running process
//! reads of them, resolved once at start ([`Config`]: counts with their
//! defaults applied, sizes in bytes). The store and the listener are opened
//! from the flags; everything after reads the [`Config`].

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

use crate::service::infra::urls::{ObjectStoreUrl, PostgresUrl};

/// Arguments of `ptv serve` (and of `ptv` without a subcommand).
#[derive(Clone, Debug, Args)]
pub struct ServeArgs {
    /// Address and port to listen on; port 0 picks a free one (the address
    /// bound is printed).
    #[arg(long, env = "PTV_BIND", default_value = "127.0.0.1:8080")]
    pub bind: SocketAddr,
    /// Where the state and the images are kept.
    #[command(flatten)]
    pub storage: Storage,
    /// Frames processed at once, each on its own CPU thread; 0 serves only
    /// (jobs are left to `ptv worker` processes on the same data
    /// directory) [default: the number of cores]
    #[arg(long, env = "PTV_WORKERS")]
    pub workers: Option<usize>,
    /// Largest request body (MiB); larger uploads get 413.
    #[arg(long, env = "PTV_MAX_UPLOAD_MB", default_value_t = 256)]
    pub max_upload_mb: u64,
    /// When set, every /api route needs `Authorization: Bearer <token>`.
    /// An empty token (`PTV_API_TOKEN=` left blank) or one with spaces
    /// around it, which no client could send, is refused at start.
    #[arg(long, env = "PTV_API_TOKEN", hide_env_values = true, value_parser = ApiTokenParser)]
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
    /// The most points (trajectory points plus particles) one VTK or
    /// HDF5 export of the API builds in memory, about 0.6 KB each
    /// (docs/service-limits.md); a larger one gets 413, saying to ask for
    /// fewer frames.
    #[arg(long, env = "PTV_MAX_EXPORT_POINTS", default_value_t = DEFAULT_MAX_EXPORT_POINTS,
          value_parser = clap::value_parser!(u64).range(1..))]
    pub max_export_points: u64,
    /// Time limits on connections and requests.
    #[command(flatten)]
    pub timeouts: Timeouts,
    /// Time limits on jobs.
    #[command(flatten)]
    pub job_limits: JobLimits,
    /// How long a worker holds a job (and a tracking run) it claimed.
    #[command(flatten)]
    pub lease: Lease,
}

/// `--max-export-points`' default: 200,000 points, about 120 MB of one
/// export's peak (docs/service-limits.md).
pub const DEFAULT_MAX_EXPORT_POINTS: u64 = 200_000;

/// Where a process keeps the service's state and images: `ptv serve`'s
/// and `ptv worker`'s flags for it, the same for both (a worker must be
/// given what its `ptv serve` was).
#[derive(Clone, Debug, Args)]
pub struct Storage {
    /// Directory of the SQLite database and the image store (created if
    /// missing); with `--database` and `--object-store`, of temporary
    /// files only.
    #[arg(long, env = "PTV_DATA_DIR", default_value = "ptv-data")]
    pub data_dir: PathBuf,
    /// The database: `postgres://USER@HOST:PORT/DATABASE` for PostgreSQL
    /// (state and job queue shared by processes on any hosts); without
    /// it, SQLite (`ptv.sqlite`) in the data directory.
    #[arg(long, env = "PTV_DATABASE_URL", hide_env_values = true, value_parser = DatabaseUrlParser)]
    pub database: Option<PostgresUrl>,
    /// Where the images go: the data directory, or an object store.
    #[command(flatten)]
    pub objects: ObjectStoreArgs,
    /// What an accepted upload survives (`--fsync`).
    #[command(flatten)]
    pub durability: Durability,
    /// Seconds a starting process waits for a database server it cannot
    /// reach (PostgreSQL still starting or restarting, the network), each
    /// attempt logged with the host, port and cause, before it exits with
    /// the reason.
    #[arg(long = "database-wait-secs", env = "PTV_DATABASE_WAIT_SECS",
          default_value_t = Storage::DATABASE_WAIT_SECS)]
    pub database_wait_secs: u64,
}

impl Storage {
    /// Default of `--database-wait-secs`.
    pub const DATABASE_WAIT_SECS: u64 = 60;

    /// SQLite and the image store in `data_dir`, as without any of the
    /// flags but the directory.
    pub fn in_directory(data_dir: impl Into<PathBuf>) -> Storage {
        Storage {
            data_dir: data_dir.into(),
            database: None,
            objects: ObjectStoreArgs::default(),
            durability: Durability::default(),
            database_wait_secs: Storage::DATABASE_WAIT_SECS,
        }
    }

    /// `--database-wait-secs`.
    pub fn database_wait(&self) -> Duration {
        Duration::from_secs(self.database_wait_secs)
    }
}

/// `--database`'s parser. Clap's own message for a value it cannot parse
/// repeats the value, and a database URL's password with it; this one
/// names the URL with its password hidden ([`PostgresUrl`]'s parse error).
#[derive(Clone, Copy, Debug)]
struct DatabaseUrlParser;

impl clap::builder::TypedValueParser for DatabaseUrlParser {
    type Value = PostgresUrl;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        _arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<PostgresUrl, clap::Error> {
        let invalid = |reason: String| {
            clap::Error::raw(
                clap::error::ErrorKind::ValueValidation,
                format!("invalid value for --database: {reason}\n"),
            )
            .with_cmd(cmd)
        };
        value
            .to_str()
            .ok_or_else(|| invalid("it is not UTF-8".to_owned()))?
            .parse()
            .map_err(invalid)
    }
}

/// `--api-token`'s parser: refuses a token no client can send (empty, or
/// with white space around it, which header parsing strips), without
/// repeating the value. An empty token most likely means a variable meant
/// to hold the secret was left blank (`PTV_API_TOKEN=${UNSET}` in a
/// compose file): starting without a token would open the API the
/// operator meant to close, and starting with it would answer every /api
/// call 401, so the process stops with the reason instead.
#[derive(Clone, Copy, Debug)]
struct ApiTokenParser;

impl clap::builder::TypedValueParser for ApiTokenParser {
    type Value = String;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        _arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<String, clap::Error> {
        let invalid = |reason: &str| {
            clap::Error::raw(
                clap::error::ErrorKind::ValueValidation,
                format!("invalid value for --api-token (PTV_API_TOKEN): {reason}\n"),
            )
            .with_cmd(cmd)
        };
        let token = value.to_str().ok_or_else(|| invalid("it is not UTF-8"))?;
        check_api_token(token).map_err(invalid)?;
        Ok(token.to_owned())
    }
}

/// Why `token` cannot be the API token, if it cannot.
pub fn check_api_token(token: &str) -> Result<(), &'static str> {
    if token.trim().is_empty() {
        Err(
            "the token is empty, so every /api request would be refused with 401; \
             give a token, or leave the flag and the variable unset to serve without one",
        )
    } else if token.trim() != token {
        Err(
            "the token has white space around it, which no client can send \
             (header values are trimmed); remove it",
        )
    } else if token.chars().any(|c| c.is_control()) {
        Err("the token has control characters, which no client can send in a header")
    } else {
        Ok(())
    }
}

/// Where images (and every other stored file) are kept: under the data
/// directory by default, or in an S3-compatible object store, which
/// workers on other hosts read without a shared disk.
#[derive(Clone, Debug, Default, Args)]
pub struct ObjectStoreArgs {
    /// `s3://bucket/prefix`: images in an S3-compatible object store
    /// (credentials and region from `AWS_ACCESS_KEY_ID`,
    /// `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`; `AWS_ALLOW_HTTP=true` for a
    /// plain-http endpoint) instead of the data directory, which then
    /// holds only temporary files [default: DATA_DIR/images]
    #[arg(long = "object-store", env = "PTV_OBJECT_STORE")]
    pub url: Option<ObjectStoreUrl>,
    /// The S3 endpoint for `--object-store` (MinIO, Ceph: `http://host:9000`)
    /// [default: AWS's, for the region]
    #[arg(long = "s3-endpoint", env = "AWS_ENDPOINT_URL")]
    pub s3_endpoint: Option<String>,
}

impl ObjectStoreArgs {
    /// The object store and its endpoint, if one is given.
    pub fn location(&self) -> Option<(&ObjectStoreUrl, Option<&str>)> {
        self.url
            .as_ref()
            .map(|url| (url, self.s3_endpoint.as_deref()))
    }
}

/// Arguments of `ptv worker`: a process that runs jobs from the data
/// directory's queue without serving HTTP (any number of them, next to a
/// `ptv serve`, which may run with `--workers 0`).
#[derive(Clone, Debug, Args)]
pub struct WorkerArgs {
    /// Where the state and the images are kept: as given to `ptv serve`.
    #[command(flatten)]
    pub storage: Storage,
    /// Jobs processed at once, each on its own CPU thread, at least 1
    /// [default: the number of cores]
    #[arg(long, env = "PTV_WORKERS", value_parser = clap::value_parser!(u64).range(1..))]
    pub workers: Option<u64>,
    /// Time limits on jobs.
    #[command(flatten)]
    pub job_limits: JobLimits,
    /// How long a worker holds a job (and a tracking run) it claimed.
    #[command(flatten)]
    pub lease: Lease,
}

impl WorkerArgs {
    /// The settings the jobs read: `ptv serve`'s, with this process's
    /// data directory, workers, limits and lease (nothing is served).
    pub fn serve_args(&self) -> ServeArgs {
        ServeArgs {
            bind: ([127, 0, 0, 1], 0).into(),
            storage: self.storage.clone(),
            workers: Some(self.worker_count()),
            max_upload_mb: 0,
            api_token: None,
            max_cpu_requests: None,
            max_connections: None,
            max_export_points: DEFAULT_MAX_EXPORT_POINTS,
            timeouts: Timeouts::default(),
            job_limits: self.job_limits.clone(),
            lease: self.lease.clone(),
        }
    }

    /// The number of workers: the flag, or the cores.
    pub fn worker_count(&self) -> usize {
        self.workers
            .and_then(|n| usize::try_from(n).ok())
            .unwrap_or_else(cores)
            .max(1)
    }
}

/// What an accepted upload survives on the embedded default (SQLite and
/// the image directory): by default a killed process, with `--fsync` also
/// a power loss.
#[derive(Clone, Debug, Default, Args)]
pub struct Durability {
    /// Make every accepted upload and stored result survive a power loss,
    /// not only a killed process: SQLite commits with `synchronous =
    /// FULL`, and each stored image file and its directory are flushed to
    /// disk before the rows that name it commit (so before the 202). Costs
    /// disk flushes per upload. PostgreSQL and S3 keep their own
    /// guarantees (PostgreSQL's `synchronous_commit`, an S3 PUT's
    /// acknowledgement); there it changes nothing.
    #[arg(long = "fsync", env = "PTV_FSYNC", action = clap::ArgAction::SetTrue,
          value_parser = clap::builder::BoolishValueParser::new())]
    pub fsync: bool,
}

/// How long a claim holds its job or tracking run: the holder renews it
/// every third of this while it works ([`Lease::heartbeat`]); once it
/// runs out (the holder died, hung, or lost the database) another worker
/// takes the work over. Longer: fewer renewals, slower takeover.
#[derive(Clone, Debug, Args)]
pub struct Lease {
    /// Seconds a worker holds a claimed job or tracking run without
    /// renewing it; a job whose worker stops renewing is taken by another
    /// worker within this time.
    #[arg(long = "lease-secs", env = "PTV_LEASE_SECS", default_value_t = Lease::SECS,
          value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub secs: u64,
}

impl Lease {
    /// Default of `--lease-secs`.
    pub const SECS: u64 = 30;

    /// The lease.
    pub fn duration(&self) -> Duration {
        Duration::from_secs(self.secs)
    }

    /// How often a holder renews it: a third of the lease, so that two
    /// renewals may fail (a busy database) before it runs out.
    pub fn heartbeat(&self) -> Duration {
        self.duration() / 3
    }
}

impl Default for Lease {
    fn default() -> Self {
        Lease { secs: Lease::SECS }
    }
}

/// The machine's cores.
fn cores() -> usize {
    std::thread::available_parallelism()
        .map(usize::from)
        .unwrap_or(1)
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
    /// MiB of memory this process's jobs may hold at once: each job
    /// declares what it needs from its pixels and settings and waits
    /// until that much is free; a job that needs more than the whole
    /// budget fails with the reason (see `service::budget`)
    /// [default: half the memory: MemTotal, or the cgroup's memory.max
    /// when lower]
    #[arg(long = "memory-budget-mb", env = "PTV_MEMORY_BUDGET_MB",
          value_parser = clap::value_parser!(u64).range(1..))]
    pub memory_budget_mb: Option<u64>,
}

impl JobLimits {
    /// Default of `--job-timeout-secs`.
    pub const FLOOR_SECS: f64 = 60.0;
    /// Default of `--job-timeout-factor`.
    pub const FACTOR: f64 = 10.0;

    /// The memory budget (MiB): the flag, or its default share of the
    /// machine's memory.
    pub fn memory_budget_mib(&self) -> u64 {
        self.memory_budget_mb
            .unwrap_or_else(crate::service::infra::budget::default_budget_mib)
    }
}

impl Default for JobLimits {
    fn default() -> Self {
        JobLimits {
            floor_secs: JobLimits::FLOOR_SECS,
            factor: JobLimits::FACTOR,
            memory_budget_mb: None,
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
    /// Bytes per second a request body must arrive at, averaged over
    /// `--body-rate-window-secs` of waiting for it; a slower one gets 408,
    /// and at the connection limit the slowest such body makes room for a
    /// new connection. 0: no minimum.
    #[arg(long = "min-body-rate", env = "PTV_MIN_BODY_RATE",
          default_value_t = Timeouts::MIN_BODY_RATE)]
    pub min_body_rate: u64,
    /// Seconds over which `--min-body-rate` is averaged.
    #[arg(long = "body-rate-window-secs", env = "PTV_BODY_RATE_WINDOW_SECS",
          default_value_t = Timeouts::BODY_RATE_WINDOW_SECS,
          value_parser = clap::value_parser!(u64).range(1..=3600))]
    pub body_rate_window_secs: u64,
    /// Seconds an answer's write may make no progress (the client reads
    /// none of it); then the connection is closed. A client that reads a
    /// large answer slowly is never cut off by it, only one that stops
    /// reading; at the connection limit such a connection stalled for a
    /// second makes room for a new one.
    #[arg(long = "write-timeout-secs", env = "PTV_WRITE_TIMEOUT_SECS",
          default_value_t = Timeouts::WRITE_SECS, value_parser = clap::value_parser!(u64).range(1..))]
    pub write_secs: u64,
}

impl Timeouts {
    /// Default of `--header-timeout-secs` (hyper's own default).
    pub const HEADER_SECS: u64 = 30;
    /// Default of `--body-timeout-secs`.
    pub const BODY_SECS: u64 = 30;
    /// Default of `--request-timeout-secs`.
    pub const REQUEST_SECS: u64 = 300;
    /// Default of `--min-body-rate`: 1 KiB/s, which a client on any link
    /// that could upload a frame in the request timeout passes by far
    /// (256 MiB in 300 s is 870 KiB/s), and which a client trickling bytes
    /// to hold a connection does not.
    pub const MIN_BODY_RATE: u64 = 1024;
    /// Default of `--body-rate-window-secs`.
    pub const BODY_RATE_WINDOW_SECS: u64 = 10;
    /// Default of `--write-timeout-secs`: as a body's pause.
    pub const WRITE_SECS: u64 = 30;

    /// `--write-timeout-secs`.
    pub fn write(&self) -> Duration {
        Duration::from_secs(self.write_secs)
    }

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

    /// `--body-rate-window-secs`.
    pub fn body_rate_window(&self) -> Duration {
        Duration::from_secs(self.body_rate_window_secs)
    }
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            header_secs: Timeouts::HEADER_SECS,
            body_secs: Timeouts::BODY_SECS,
            request_secs: Timeouts::REQUEST_SECS,
            min_body_rate: Timeouts::MIN_BODY_RATE,
            body_rate_window_secs: Timeouts::BODY_RATE_WINDOW_SECS,
            write_secs: Timeouts::WRITE_SECS,
        }
    }
}

/// What a running process (`ptv serve`, `ptv worker`) reads of its
/// settings: the flags resolved once at start ([`ServeArgs::config`]),
/// defaults applied, so nothing downstream falls back on its own.
#[derive(Clone, Debug)]
pub struct Config {
    /// Jobs run at once in this process (0: it serves only).
    pub workers: usize,
    /// Threads of the CPU pool: the workers', and at least one for the
    /// CPU-heavy requests.
    pub cpu_threads: usize,
    /// CPU-heavy requests run at once.
    pub cpu_request_limit: usize,
    /// The largest request body (bytes).
    pub max_upload_bytes: usize,
    /// The most points one VTK or HDF5 export builds in memory.
    pub max_export_points: u64,
    /// The bearer token every /api route needs, if one is set.
    pub api_token: Option<String>,
    /// Time limits on connections and requests.
    pub timeouts: Timeouts,
    /// Time and memory limits on jobs.
    pub job_limits: JobLimits,
    /// How long a worker holds a job or a tracking run it claimed.
    pub lease: Lease,
}

impl ServeArgs {
    /// What the running process reads of these flags, resolved.
    pub fn config(&self) -> Config {
        Config {
            workers: self.worker_count(),
            cpu_threads: self.cpu_threads(),
            cpu_request_limit: self.cpu_request_limit(),
            max_upload_bytes: self.max_upload_bytes(),
            max_export_points: self.max_export_points,
            api_token: self.api_token.clone(),
            timeouts: self.timeouts.clone(),
            job_limits: self.job_limits.clone(),
            lease: self.lease.clone(),
        }
    }

    /// The number of workers: the flag (0: serve only), or the cores.
    pub fn worker_count(&self) -> usize {
        self.workers.unwrap_or_else(cores)
    }

    /// Threads for the CPU pool: the workers', and at least one for the
    /// CPU-heavy requests of a process that serves only.
    pub fn cpu_threads(&self) -> usize {
        self.worker_count().max(1)
    }

    /// The body limit in bytes.
    pub fn max_upload_bytes(&self) -> usize {
        usize::try_from(self.max_upload_mb.saturating_mul(1024 * 1024)).unwrap_or(usize::MAX)
    }

    /// How many CPU-heavy requests may run at once: the flag, or the workers.
    pub fn cpu_request_limit(&self) -> usize {
        self.max_cpu_requests
            .map_or_else(|| self.cpu_threads(), |n| n as usize)
    }
}
