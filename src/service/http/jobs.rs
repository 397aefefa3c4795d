//! `/jobs/{id}`: a job's state, for polling after an upload; and
//! `/jobs/{id}/retry`, which queues a failed job again.

use std::sync::Arc;

use axum::extract::State;
use axum::response::Response;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Serialize;
use utoipa::ToSchema;

use super::links;
use super::problem::{ApiError, ApiPath};
use super::upload;
use super::Shared;
use crate::service::app::AppState;
use crate::service::store::{JobId, JobRow, JobState, RetryOutcome};

/// A job's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
#[schema(as = JobState)]
pub enum JobStateView {
    /// Waiting for a worker.
    Queued,
    /// A worker has it.
    Running,
    /// Done; its result is stored.
    Succeeded,
    /// Given up; `error` says why.
    Failed,
}

impl From<JobState> for JobStateView {
    fn from(state: JobState) -> Self {
        match state {
            JobState::Queued => JobStateView::Queued,
            JobState::Running => JobStateView::Running,
            JobState::Succeeded => JobStateView::Succeeded,
            JobState::Failed => JobStateView::Failed,
        }
    }
}

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
    Ok(Json(JobView::of(row)?))
}

impl JobView {
    /// The view of a stored job.
    fn of(row: JobRow) -> Result<JobView, ApiError> {
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
    Ok(upload::accepted(&state, id, JobView::of(row)?))
}
