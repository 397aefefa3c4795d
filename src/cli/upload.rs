//! `ptv upload`: pushes a recording's frames to a running `ptv serve`, as
//! an acquisition PC or a batch job would (issue 13).
//!
//! Each frame is one `POST /api/v1/sequences/{id}/frames`, multipart with
//! a `frame` part (its number) and one image part per camera, `cam0` ..
//! `camN-1` in camera order (see `src/service/http/frames.rs`). The
//! images of frame `F` are named by one pattern per camera with a
//! printf-style frame number: `img/cam1.%d`, `img/cam1_%05d.tif`; or
//! they come from an OpenPTV/pyptv experiment (`--experiment DIR`, read by
//! [`crate::formats::experiment::read_experiment`]): its sequence's image
//! names and, unless `--frames` says otherwise, its first and last frame.
//! An experiment with an image splitter (one sensor, several views) sends
//! its one image per frame as the part `image`, which the service cuts
//! into the views.
//!
//! - `--jobs N` frames are in flight at once (default 4).
//! - A connection error, a timeout and a 5xx are retried with exponential
//!   backoff (0.2 s doubling, at most 10 s between attempts, with jitter),
//!   at most `--retries` times; a 429, or a 5xx with `Retry-After` (the
//!   service's 503 when busy, its 507 when its disk is full), waits what
//!   the server asks (at most 60 s) instead.
//! - A 409 means the frame is already on the server: it counts as done, so
//!   running the same command again after an interruption resumes where
//!   the first run stopped (a frame whose answer was lost also ends as a
//!   409 on its retry).
//! - Any other 4xx fails that frame with the server's problem+json
//!   `detail`; so does a camera image that cannot be read (with its path).
//!   The other frames go on.
//!
//! A progress bar on standard error (hidden when it is not a terminal);
//! at the end a summary on standard output: frames accepted, already
//! there, and failed with the reasons. The command fails (exit 1) if any
//! frame failed. `--follow` then waits until the sequence has no queued or
//! running frame and reports the jobs' states (exit 1 if one of the
//! frames uploaded now failed).
//!
//! The client speaks plain HTTP only (no TLS in the build): labs upload
//! over their own network. For https, put a reverse proxy in front of
//! `ptv serve` and run `ptv upload` on its side of it, or wait for TLS
//! support (future work).

use std::fmt::Write as _;
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use clap::{ArgGroup, Args};
use futures_util::StreamExt;
use reqwest::multipart::{Form, Part};
use reqwest::StatusCode;
use serde_json::Value;

use super::{write_stdout, CliError};
use crate::formats::experiment::{read_experiment, Experiment};
use crate::formats::frames::{FramePattern, FrameRange, WithoutNumber};

/// Arguments of `ptv upload`.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("recording").required(true).args(["experiment", "images"])))]
pub struct UploadArgs {
    /// The service: `http://HOST:PORT` (plain HTTP; see the docs for https).
    #[arg(long, value_name = "URL")]
    pub server: String,
    /// The service's API token, if it has one (`ptv serve --api-token`).
    #[arg(long, env = "PTV_API_TOKEN", hide_env_values = true, value_name = "T")]
    pub token: Option<String>,
    /// The sequence to add the frames to (create it first:
    /// `POST /api/v1/sequences`).
    #[arg(long, value_name = "ID")]
    pub sequence: i64,
    /// One file name pattern per camera, in camera order, with a
    /// printf-style frame number: `img/cam1.%d`, `img/cam1_%05d.tif`.
    #[arg(long = "images", value_name = "PATTERN", num_args = 1..)]
    pub images: Vec<String>,
    /// An OpenPTV experiment directory (`parameters/` or a pyptv YAML): the
    /// images its sequence parameters name, instead of --images.
    #[arg(long, value_name = "DIR", conflicts_with = "images")]
    pub experiment: Option<PathBuf>,
    /// The frames to upload, both ends included: `10001..10004`, or one
    /// frame `10001`; with --experiment, its first to last frame if not
    /// given.
    #[arg(long, value_name = "FIRST..LAST", value_parser = FrameRange::parse,
          required_unless_present = "experiment")]
    pub frames: Option<FrameRange>,
    /// How many frames are uploaded at once.
    #[arg(long, value_name = "N", default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub jobs: u16,
    /// How often a frame is retried after a connection error or a 5xx
    /// before it counts as failed.
    #[arg(long, value_name = "N", default_value_t = 6)]
    pub retries: u32,
    /// After uploading, wait for the sequence's frames to be processed and
    /// report the jobs' states.
    #[arg(long)]
    pub follow: bool,
}

/// Where a frame's files are and which parts they go in.
enum Recording {
    /// One pattern per camera: parts `cam0`.. .
    Patterns(Vec<FramePattern>),
    /// An experiment's sequence: parts `cam0`.., or `image` with a
    /// splitter.
    Experiment(Box<Experiment>),
}

impl Recording {
    /// The files of `frame`, each with its part's name.
    fn files(&self, frame: u64) -> Vec<(String, PathBuf)> {
        match self {
            Recording::Patterns(patterns) => patterns
                .iter()
                .enumerate()
                .map(|(c, p)| (format!("cam{c}"), p.path(frame)))
                .collect(),
            Recording::Experiment(experiment) if experiment.splitter.is_some() => {
                vec![(
                    "image".to_owned(),
                    experiment.sequence.image_path(&experiment.root, 0, frame),
                )]
            }
            Recording::Experiment(experiment) => (0..experiment.cameras.len())
                .map(|c| {
                    let path = experiment.sequence.image_path(&experiment.root, c, frame);
                    (format!("cam{c}"), path)
                })
                .collect(),
        }
    }

    /// The cameras the sequence's calibration must have, if that is known
    /// here (the images given, or the experiment's cameras).
    fn cameras(&self) -> (usize, &'static str) {
        match self {
            Recording::Patterns(patterns) => (patterns.len(), "--images"),
            Recording::Experiment(experiment) => (experiment.cameras.len(), "--experiment"),
        }
    }
}

/// How one frame ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Accepted now: its job.
    Accepted(i64),
    /// The server had it already (409).
    AlreadyThere,
    /// Not uploaded: why.
    Failed(String),
}

/// The server, the token and the client.
struct Server {
    client: reqwest::Client,
    api: String,
    token: Option<String>,
    retries: u32,
}

impl Server {
    fn get(&self, path: &str) -> reqwest::RequestBuilder {
        self.authorized(self.client.get(format!("{}{path}", self.api)))
    }

    fn authorized(&self, request: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.token {
            Some(token) => request.bearer_auth(token),
            None => request,
        }
    }

    /// GETs JSON, retrying connection errors and 5xx like uploads; a 4xx
    /// is an error with the server's detail.
    async fn get_json(&self, path: &str) -> Result<Value, String> {
        let mut attempt = 0;
        loop {
            let (wait, reason) = match self.get(path).send().await {
                Ok(response) if response.status().is_success() => {
                    return response
                        .json::<Value>()
                        .await
                        .map_err(|e| format!("GET {path}: the answer is not JSON: {e}"));
                }
                Ok(response) if retried(response.status()) => {
                    let wait = retry_after(&response);
                    let reason = format!("GET {path}: {}", problem(response).await);
                    (wait, reason)
                }
                Ok(response) => return Err(problem(response).await),
                Err(error) => (None, chain(&error)),
            };
            attempt += 1;
            if attempt > self.retries {
                return Err(format!("gave up after {attempt} attempts: {reason}"));
            }
            tokio::time::sleep(wait.unwrap_or_else(|| backoff(attempt))).await;
        }
    }
}

/// Whether a status is worth retrying: 5xx, 429.
fn retried(status: StatusCode) -> bool {
    status.is_server_error() || status == StatusCode::TOO_MANY_REQUESTS
}

/// The wait a retried answer (429, 503, 507, ...) asks for in
/// `Retry-After` (seconds), at most 60 s.
fn retry_after(response: &reqwest::Response) -> Option<Duration> {
    let seconds: u64 = response
        .headers()
        .get(reqwest::header::RETRY_AFTER)?
        .to_str()
        .ok()?
        .trim()
        .parse()
        .ok()?;
    Some(Duration::from_secs(seconds.min(60)))
}

/// The wait before attempt `attempt` (1-based): 0.2 s doubling, at most
/// 10 s, plus up to half of it again at random (so that many clients
/// refused at once do not come back at once).
fn backoff(attempt: u32) -> Duration {
    let base = Duration::from_millis(200)
        .saturating_mul(1u32 << attempt.saturating_sub(1).min(16))
        .min(Duration::from_secs(10));
    let jitter = rand::random_range(0.0..0.5);
    base.mul_f64(1.0 + jitter)
}

/// The status and the problem+json `detail` of an error answer (else its
/// title, else the text, cut at 300 characters).
async fn problem(response: reqwest::Response) -> String {
    let status = response.status();
    let text = response.text().await.unwrap_or_default();
    let detail = serde_json::from_str::<Value>(&text).ok().and_then(|body| {
        body.get("detail")
            .or_else(|| body.get("title"))
            .and_then(Value::as_str)
            .map(str::to_owned)
    });
    let detail = detail.unwrap_or_else(|| text.chars().take(300).collect());
    if detail.is_empty() {
        status.to_string()
    } else {
        format!("{status}: {detail}")
    }
}

/// An error and its causes as one line.
fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let cause_text = cause.to_string();
        if !text.ends_with(&cause_text) {
            let _ = write!(text, ": {cause_text}");
        }
        source = cause.source();
    }
    text
}

/// Uploads one frame; never an error: a failure is an [`Outcome::Failed`].
async fn upload_frame(
    server: &Server,
    sequence: i64,
    frame: u64,
    parts: &[(String, PathBuf)],
) -> Outcome {
    let mut files = Vec::with_capacity(parts.len());
    for (_, path) in parts {
        match tokio::fs::read(path).await {
            Ok(bytes) => files.push(bytes),
            Err(error) => return Outcome::Failed(format!("{}: {error}", path.display())),
        }
    }
    let url = format!("{}/sequences/{sequence}/frames", server.api);
    let mut attempt = 0;
    loop {
        let mut form = Form::new().text("frame", frame.to_string());
        for (bytes, (part, path)) in files.iter().zip(parts) {
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| part.clone());
            form = form.part(part.clone(), Part::bytes(bytes.clone()).file_name(name));
        }
        let request = server.authorized(server.client.post(&url)).multipart(form);
        let (wait, reason) = match request.send().await {
            Ok(response) => match response.status() {
                status if status.is_success() => {
                    let body: Value = response.json().await.unwrap_or(Value::Null);
                    return Outcome::Accepted(body["job_id"].as_i64().unwrap_or(-1));
                }
                StatusCode::CONFLICT => return Outcome::AlreadyThere,
                status if retried(status) => {
                    let wait = retry_after(&response);
                    (wait, problem(response).await)
                }
                _ => return Outcome::Failed(problem(response).await),
            },
            Err(error) => (None, chain(&error)),
        };
        attempt += 1;
        if attempt > server.retries {
            return Outcome::Failed(format!("gave up after {attempt} attempts: {reason}"));
        }
        tokio::time::sleep(wait.unwrap_or_else(|| backoff(attempt))).await;
    }
}

/// The frames' outcomes, in frame order.
pub type Outcomes = Vec<(u64, Outcome)>;

/// Runs `ptv upload`: the summary to standard output, the progress bar to
/// standard error.
pub fn run(args: &UploadArgs, stdout: &mut dyn Write) -> Result<(), CliError> {
    let (recording, frames) = match &args.experiment {
        Some(dir) => {
            let experiment = read_experiment(dir)?;
            let sequence = &experiment.sequence;
            let frames = args.frames.unwrap_or(FrameRange {
                first: sequence.first,
                last: sequence.last,
            });
            (Recording::Experiment(Box::new(experiment)), frames)
        }
        None => {
            let patterns = args
                .images
                .iter()
                .map(|text| FramePattern::parse(text, WithoutNumber::Refuse))
                .collect::<Result<Vec<_>, _>>()
                .map_err(|reason| CliError::Flag {
                    flag: "--images",
                    reason,
                })?;
            let frames = args.frames.ok_or_else(|| CliError::Flag {
                flag: "--frames",
                reason: "give the frames to upload, FIRST..LAST".into(),
            })?;
            (Recording::Patterns(patterns), frames)
        }
    };
    let server = args.server.trim_end_matches('/');
    if server.starts_with("https://") {
        return Err(CliError::Flag {
            flag: "--server",
            reason: format!(
                "{server}: this client speaks plain HTTP only; upload to the service's \
                 http:// address, or through a reverse proxy that terminates TLS"
            ),
        });
    }
    if !server.starts_with("http://") {
        return Err(CliError::Flag {
            flag: "--server",
            reason: format!("{server}: give the service's address as http://HOST:PORT"),
        });
    }
    let client = reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(10))
        .timeout(Duration::from_secs(600))
        .build()
        .map_err(|e| CliError::Upload(format!("cannot make an HTTP client: {}", chain(&e))))?;
    let server = Server {
        client,
        api: format!("{server}/api/v1"),
        token: args.token.clone(),
        retries: args.retries,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| CliError::Upload(format!("cannot start the runtime: {e}")))?;
    runtime.block_on(async {
        check_sequence(&server, args.sequence, recording.cameras()).await?;
        let outcomes = upload_all(&server, args, &recording, frames).await;
        write_stdout(stdout, &summary(&outcomes))?;
        let mut failed = outcomes
            .iter()
            .filter(|(_, o)| matches!(o, Outcome::Failed(_)))
            .count();
        if args.follow {
            let (report, jobs_failed) = follow(&server, args.sequence, &outcomes).await?;
            write_stdout(stdout, &report)?;
            failed += jobs_failed;
        }
        if failed > 0 {
            return Err(CliError::Upload(format!(
                "{failed} of {} frames failed (see above)",
                outcomes.len()
            )));
        }
        Ok(())
    })
}

/// Checks that the sequence exists and its calibration has one camera per
/// pattern, before any upload.
async fn check_sequence(
    server: &Server,
    sequence: i64,
    (given, flag): (usize, &'static str),
) -> Result<(), CliError> {
    let failed = |reason: String| {
        let hint = if reason.starts_with("401") {
            "; give the service's API token with --token"
        } else if reason.starts_with("404") {
            "; check --sequence, or create the sequence first (POST /api/v1/sequences)"
        } else {
            ""
        };
        CliError::Upload(format!(
            "cannot read sequence {sequence} at {}: {reason}{hint}",
            server.api
        ))
    };
    let view = server
        .get_json(&format!("/sequences/{sequence}"))
        .await
        .map_err(failed)?;
    let calibration = view["calibration_id"].as_i64().unwrap_or(-1);
    let calibration = server
        .get_json(&format!("/calibrations/{calibration}"))
        .await
        .map_err(failed)?;
    if let Some(cameras) = calibration["cameras"].as_i64() {
        if cameras != given as i64 {
            let what = if flag == "--images" {
                "patterns were given; give one per camera, in camera order"
            } else {
                "cameras are in the experiment; upload to a sequence made from it"
            };
            return Err(CliError::Flag {
                flag,
                reason: format!(
                    "sequence {sequence}'s calibration has {cameras} cameras but {given} {what}"
                ),
            });
        }
    }
    Ok(())
}

/// Uploads every frame, `--jobs` at once, with a progress bar.
async fn upload_all(
    server: &Server,
    args: &UploadArgs,
    recording: &Recording,
    frames: FrameRange,
) -> Outcomes {
    let total = frames.last - frames.first + 1;
    let progress = progress_bar(total, "uploaded");
    let frames = frames.first..=frames.last;
    let mut outcomes: Outcomes = futures_util::stream::iter(frames)
        .map(|frame| {
            let parts = recording.files(frame);
            let progress = &progress;
            async move {
                let outcome = upload_frame(server, args.sequence, frame, &parts).await;
                progress.inc(1);
                (frame, outcome)
            }
        })
        .buffer_unordered(usize::from(args.jobs))
        .collect()
        .await;
    progress.finish_and_clear();
    outcomes.sort_by_key(|(frame, _)| *frame);
    outcomes
}

fn progress_bar(total: u64, what: &str) -> indicatif::ProgressBar {
    let progress = indicatif::ProgressBar::with_draw_target(
        Some(total),
        indicatif::ProgressDrawTarget::stderr(),
    );
    let template = format!("{{bar:40}} {{pos}}/{{len}} frames {what} ({{per_sec}}, {{eta}})");
    progress.set_style(
        indicatif::ProgressStyle::with_template(&template)
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    progress
}

/// The summary: counts, then one line per failed frame.
fn summary(outcomes: &Outcomes) -> String {
    let count = |f: fn(&Outcome) -> bool| outcomes.iter().filter(|(_, o)| f(o)).count();
    let mut text = format!(
        "accepted: {}, already there: {}, failed: {}\n",
        count(|o| matches!(o, Outcome::Accepted(_))),
        count(|o| matches!(o, Outcome::AlreadyThere)),
        count(|o| matches!(o, Outcome::Failed(_))),
    );
    for (frame, outcome) in outcomes {
        if let Outcome::Failed(reason) = outcome {
            let _ = writeln!(text, "frame {frame} failed: {}", one_line(reason));
        }
    }
    text
}

fn one_line(text: &str) -> String {
    text.replace(['\r', '\n'], " ")
}

/// Waits until the sequence has no queued or running frame; the report
/// (the sequence's frames by state, and the jobs of the frames accepted
/// now that failed, with their errors) and how many of those failed.
async fn follow(
    server: &Server,
    sequence: i64,
    outcomes: &Outcomes,
) -> Result<(String, usize), CliError> {
    let failed =
        |reason: String| CliError::Upload(format!("cannot follow sequence {sequence}: {reason}"));
    let path = format!("/sequences/{sequence}");
    let mut progress: Option<indicatif::ProgressBar> = None;
    let view = loop {
        let view = server.get_json(&path).await.map_err(failed)?;
        let count = |state: &str| view["frames"][state].as_i64().unwrap_or(0).max(0) as u64;
        let (queued, running) = (count("queued"), count("running"));
        let finished = count("done") + count("failed");
        let bar =
            progress.get_or_insert_with(|| progress_bar(finished + queued + running, "processed"));
        bar.set_length(finished + queued + running);
        bar.set_position(finished);
        if queued == 0 && running == 0 {
            break view;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    if let Some(bar) = progress {
        bar.finish_and_clear();
    }
    let count = |state: &str| view["frames"][state].as_i64().unwrap_or(0);
    let mut report = format!(
        "sequence {sequence}: done: {}, failed: {}\n",
        count("done"),
        count("failed")
    );
    let mut jobs_failed = 0;
    if count("failed") > 0 {
        for (frame, outcome) in outcomes {
            let Outcome::Accepted(job) = outcome else {
                continue;
            };
            let job = server
                .get_json(&format!("/jobs/{job}"))
                .await
                .map_err(failed)?;
            if job["state"] == "failed" {
                jobs_failed += 1;
                let error = job["error"].as_str().unwrap_or("no reason given");
                let _ = writeln!(
                    report,
                    "frame {frame}: job {} failed: {}",
                    job["id"],
                    one_line(error)
                );
            }
        }
    }
    Ok((report, jobs_failed))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_and_is_bounded() {
        for attempt in 1..40 {
            let wait = backoff(attempt);
            let base = 0.2 * 2f64.powi(attempt as i32 - 1);
            let base = base.min(10.0);
            assert!(
                wait.as_secs_f64() >= base - 1e-9 && wait.as_secs_f64() <= 1.5 * base + 1e-9,
                "{attempt}: {wait:?}"
            );
        }
    }
}
