//! `/jobs/{id}`: a job's state, for polling after an upload; and
//! `/jobs/{id}/retry`, which queues a failed job again.

use std::sync::Arc;

use axum::extract::State;
use axum::response::Response;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Serialize;
use utoipa::ToSchema;

use super::extract::Shared;
use super::problem::{ApiError, ApiPath};
use super::upload;
use crate::service::ops::events::JobStateView;
use crate::service::ops::links;
use crate::service::ops::state::AppState;
use crate::service::store::{ClaimOutcome, JobClaim, JobId, JobRow, JobState, RetryOutcome};

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/jobs/{id}", get(read))
        .route("/jobs/{id}/retry", post(retry))
}

/// A job.
#[derive(Debug, Serialize, ToSchema)]
pub struct JobView {
    /// Its id.
    #[schema(value_type = i64)]
    pub id: JobId,
    /// What it does: `process_frame`, ...
    pub kind: String,
    /// Its state.
    pub state: JobStateView,
    /// How often a worker took it up.
    pub attempts: i64,
    /// Why it failed (or why its last attempt did).
    pub error: Option<String>,
    /// Where its result is, once it succeeded.
    pub result: Option<String>,
    /// What it works on.
    #[schema(value_type = Object)]
    pub payload: serde_json::Value,
    /// Enqueued at (UTC).
    pub created_at: String,
    /// Last taken up at.
    pub started_at: Option<String>,
    /// Finished at.
    pub finished_at: Option<String>,
    /// The worker holding it while it runs (`HOST:PID:RANDOM/INDEX`: a
    /// `ptv serve` or `ptv worker` process and its worker).
    pub worker: Option<String>,
    /// Until when that worker holds it (UTC; its heartbeat renews this
    /// every third of `--lease-secs`); once past, another worker takes the
    /// job over.
    pub lease_until: Option<String>,
    /// Its claims by workers, oldest first (the last 20):
    /// who took it up and how each attempt ended, e.g. `expired` when a
    /// worker died and another took the job over.
    pub claims: Vec<ClaimView>,
}

/// Claims a job view shows at most.
pub const CLAIMS_SHOWN: u32 = 20;

/// One claim of a job by a worker.
#[derive(Debug, Serialize, ToSchema)]
pub struct ClaimView {
    /// The claim's fencing token, from 1, one more at every claim: only the
    /// holder of the latest may complete the job.
    pub token: i64,
    /// The worker that claimed it.
    pub worker: String,
    /// When (UTC).
    pub claimed_at: String,
    /// How the attempt ended; absent while it runs.
    pub outcome: Option<ClaimOutcomeView>,
}

/// How a claim of a job ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
#[schema(as = ClaimOutcome)]
pub enum ClaimOutcomeView {
    /// The job succeeded with this attempt's results.
    Succeeded,
    /// The job failed in this attempt.
    Failed,
    /// Queued again after a passing failure or at a shutdown.
    Released,
    /// Queued again uncounted (a full disk, or waiting for other work).
    GivenBack,
    /// The worker's lease ran out (it died, hung or lost the database);
    /// the job went back to the queue for another worker.
    Expired,
}

impl From<ClaimOutcome> for ClaimOutcomeView {
    fn from(outcome: ClaimOutcome) -> Self {
        match outcome {
            ClaimOutcome::Succeeded => ClaimOutcomeView::Succeeded,
            ClaimOutcome::Failed => ClaimOutcomeView::Failed,
            ClaimOutcome::Released => ClaimOutcomeView::Released,
            ClaimOutcome::GivenBack => ClaimOutcomeView::GivenBack,
            ClaimOutcome::Expired => ClaimOutcomeView::Expired,
        }
    }
}

impl From<JobClaim> for ClaimView {
    fn from(claim: JobClaim) -> Self {
        ClaimView {
            token: claim.token.0,
            worker: claim.worker,
            claimed_at: claim.claimed_at,
            outcome: claim.outcome.map(Into::into),
        }
    }
}

/// A job's state, timestamps, attempts, error and result.
#[utoipa::path(
    get, path = "/api/v1/jobs/{id}", tag = "jobs",
    params(("id" = i64, Path, description = "Job id")),
    responses(
        (status = 200, body = JobView),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn read(
    State(state): Shared,
    ApiPath(id): ApiPath<JobId>,
) -> Result<Json<JobView>, ApiError> {
    let row = state
        .store
        .job(id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("job {id} does not exist")))?;
    let claims = state.store.job_claims(id, CLAIMS_SHOWN).await?;
    Ok(Json(JobView::of(row, claims)?))
}

impl JobView {
    /// The view of a stored job and its claims.
    fn of(row: JobRow, claims: Vec<JobClaim>) -> Result<JobView, ApiError> {
        Ok(JobView {
            id: row.id,
            kind: row.kind,
            state: row.state.into(),
            attempts: row.attempts,
            error: row.error,
            result: row.result.as_ref().map(links::job_result),
            payload: serde_json::from_str(&row.payload)?,
            created_at: row.created_at,
            started_at: row.started_at,
            finished_at: row.finished_at,
            worker: row.worker,
            lease_until: row.lease_until,
            claims: claims.into_iter().map(Into::into).collect(),
        })
    }
}

/// Queues a failed job again, its attempts reset to 0 (its error stays
/// until it runs): a frame whose processing failed, e.g. because the
/// service stopped while running it 3 times, gets processed after all. A
/// frame's inputs (and a solve's files) are kept until its job succeeds,
/// so they are still there. Only a `failed` job can be retried.
#[utoipa::path(
    post, path = "/api/v1/jobs/{id}/retry", tag = "jobs",
    params(("id" = i64, Path, description = "Job id")),
    responses(
        (status = 202, body = JobView, description = "Queued again; `Location` is the job",
         headers(("Location" = String, description = "The job"))),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, body = super::problem::Problem, content_type = "application/problem+json",
         description = "The job is not failed"),
    )
)]
pub async fn retry(
    State(state): Shared,
    ApiPath(id): ApiPath<JobId>,
) -> Result<Response, ApiError> {
    match state.store.retry(id).await? {
        RetryOutcome::Queued => {}
        RetryOutcome::Unknown => {
            return Err(ApiError::not_found(format!("job {id} does not exist")))
        }
        RetryOutcome::NotFailed(job_state) => {
            let why = match job_state {
                JobState::Queued => "it is queued already",
                JobState::Running => "it is running",
                JobState::Succeeded => "it succeeded; its result stays as it is",
                JobState::Failed => "it failed",
            };
            return Err(ApiError::conflict(format!(
                "job {id} is not retried: {why}; only a failed job can be"
            )));
        }
    }
    let row = state
        .store
        .job(id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("job {id} does not exist")))?;
    let claims = state.store.job_claims(id, CLAIMS_SHOWN).await?;
    Ok(upload::accepted(&state, id, JobView::of(row, claims)?))
}
