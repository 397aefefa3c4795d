//! A sequence's tracking ([`crate::service::ops::tracking`]): its runs, a new
//! run with other settings, the finish request, and the trajectories, as
//! CSV (the header of `ptv track`) or JSON, streamed a page of
//! trajectories at a time.

use std::sync::Arc;

use axum::body::Body;
use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiJson, ApiPath, ApiQuery};
use crate::formats;
use crate::formats::frames::FrameRange;
use crate::photogrammetry::correspond::default_volume;
use crate::photogrammetry::Volume;
use crate::service::model::tracking_settings::TrackingSettings;
use crate::service::ops::state::AppState;
use crate::service::ops::tracking::kick;
use crate::service::store::SequenceRow;
use crate::service::store::{
    CalibrationId, FrameNumber, PointRow, SequenceId, StoreError, TrackingRunId, TrackingRunRow,
    TrackingState, TrajectoryRow,
};

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/sequences/{id}/tracking", post(start).get(runs))
        .route("/sequences/{id}/tracking/finish", post(finish))
        .route("/sequences/{id}/trajectories", get(trajectories))
        .route("/sequences/{id}/trajectories/{tid}", get(trajectory))
}

/// Where a tracking run stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrackingStateView {
    /// Following the frames as they complete.
    Tracking,
    /// Ended after the last frame; every point stored.
    Finished,
    /// The tracker refused the input; see `error`.
    Failed,
    /// A newer run took over; its points so far stay.
    Superseded,
}

/// A tracking run of a sequence.
#[derive(Debug, Serialize, ToSchema)]
pub struct TrackingRunView {
    /// Its id (`?run=` of the trajectory routes).
    #[schema(value_type = i64)]
    pub run_id: TrackingRunId,
    /// Its settings, defaults filled in.
    pub settings: TrackingSettings,
    /// The calibration its image-space recovery projects with: the
    /// sequence's when the run started (null for runs stored before
    /// recovery existed).
    #[schema(value_type = Option<i64>)]
    pub calibration_id: Option<CalibrationId>,
    /// Where it stands.
    pub state: TrackingStateView,
    /// The last frame tracked: trajectories are final up to a few frames
    /// before it (the fit window and look-ahead), and all of them once the
    /// run is finished. Null before the first frame.
    #[schema(value_type = Option<i64>, minimum = 0, maximum = 4_294_967_295_u64)]
    pub tracked_through: Option<FrameNumber>,
    /// Whether the sequence was said to have all its frames (`POST
    /// /sequences/{id}/tracking/finish`).
    pub finish_requested: bool,
    /// Why it failed.
    pub error: Option<String>,
    /// Trajectories stored so far.
    pub trajectories: i64,
    /// What the backward pass added once the run finished (settings'
    /// `backward`); null where it did not run (off, or not finished yet).
    pub backward: Option<BackwardView>,
    /// When it was created (UTC).
    pub created_at: String,
}

/// What a run's backward pass added (as `ptv track` reports
/// it).
#[derive(Debug, Serialize, ToSchema)]
pub struct BackwardView {
    /// Points added before the trajectories' first points.
    pub points: i64,
    /// Trajectories that gained points at their start.
    pub lengthened: i64,
    /// Trajectories joined onto the one that ended before them (each
    /// join makes two trajectories one).
    pub joined: i64,
}

/// A run's view.
pub(super) async fn run_view(
    state: &AppState,
    row: TrackingRunRow,
) -> Result<TrackingRunView, ApiError> {
    let trajectories = state.store.trajectory_count(row.id).await?;
    Ok(TrackingRunView {
        run_id: row.id,
        settings: row.parameters.as_stored(),
        calibration_id: row.calibration_id,
        state: match row.state {
            TrackingState::Tracking => TrackingStateView::Tracking,
            TrackingState::Finished => TrackingStateView::Finished,
            TrackingState::Failed => TrackingStateView::Failed,
            TrackingState::Superseded => TrackingStateView::Superseded,
        },
        tracked_through: row.tracked_through,
        finish_requested: row.finish_requested,
        error: row.error,
        trajectories,
        backward: row.backward.map(|b| BackwardView {
            points: b.points,
            lengthened: b.lengthened,
            joined: b.joined,
        }),
        created_at: row.created_at,
    })
}

/// Starts a new tracking run of a sequence with these settings (tracking
/// a sequence created without, or again with other settings). The current
/// run, if still tracking, is superseded; its points stay readable with
/// `?run=`. The new run tracks every frame from `first_frame`.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/tracking", tag = "tracking",
    params(("id" = i64, Path, description = "Sequence id")),
    request_body = TrackingSettings,
    responses(
        (status = 201, body = TrackingRunView),
        (status = 400, description = "Not JSON", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Invalid settings (a velocity limit that is not positive, or larger than the diagonal of the sequence's volume, ...)", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn start(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiJson(settings): ApiJson<TrackingSettings>,
) -> Result<Response, ApiError> {
    let row = sequence(&state, id).await?;
    let settings = settings.with_defaults()?;
    if let Some(volume) = observation_volume(&state, &row).await? {
        settings.check_volume(&volume)?;
    }
    let previous = state.store.current_tracking_run(id).await?;
    let row = state
        .store
        .insert_tracking_run(id, &settings)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("sequence {id} does not exist")))?;
    if let Some(previous) = previous {
        state.trackers.forget(previous.id);
    }
    kick(&state, id);
    Ok((StatusCode::CREATED, Json(run_view(&state, row).await?)).into_response())
}

/// The volume a sequence's particles are found in: its `matching.volume`,
/// else the default volume of its calibration (as its matcher's); `None`
/// where its cameras have none (parallel axes: such a sequence matches
/// nothing anyway).
async fn observation_volume(
    state: &AppState,
    row: &SequenceRow,
) -> Result<Option<Volume>, ApiError> {
    if let Some(volume) = row.parameters.matching().volume {
        return Ok(Some(volume));
    }
    let calibration = super::calibrations::calibration(state, row.calibration_id).await?;
    Ok(default_volume(&super::calibrations::stored_cameras(
        &calibration,
    )?))
}

/// A sequence's tracking runs, oldest first; the last is the current one.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/tracking", tag = "tracking",
    params(("id" = i64, Path, description = "Sequence id")),
    responses(
        (status = 200, body = Vec<TrackingRunView>),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn runs(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
) -> Result<Json<Vec<TrackingRunView>>, ApiError> {
    sequence(&state, id).await?;
    let mut views = Vec::new();
    for row in state.store.tracking_runs(id).await? {
        views.push(run_view(&state, row).await?);
    }
    Ok(Json(views))
}

/// Says that the sequence has all its frames: once every uploaded frame is
/// processed or failed, the current run tracks them (frame numbers never
/// uploaded are gaps), ends its trajectories and stores their last points
/// (state `finished`). Frames uploaded after that are not in the run.
#[utoipa::path(
    post, path = "/api/v1/sequences/{id}/tracking/finish", tag = "tracking",
    params(("id" = i64, Path, description = "Sequence id")),
    responses(
        (status = 202, body = TrackingRunView),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence is not tracked", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn finish(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
) -> Result<Response, ApiError> {
    let run = current_run(&state, id, None).await?;
    let row = state
        .store
        .request_tracking_finish(run.id)
        .await?
        .ok_or_else(|| ApiError::internal("the tracking run vanished"))?;
    kick(&state, id);
    Ok((StatusCode::ACCEPTED, Json(run_view(&state, row).await?)).into_response())
}

/// The run `run` of the sequence, or its current one.
pub(super) async fn current_run(
    state: &AppState,
    id: SequenceId,
    run: Option<TrackingRunId>,
) -> Result<TrackingRunRow, ApiError> {
    sequence(state, id).await?;
    match run {
        Some(run) => state
            .store
            .tracking_run(run)
            .await?
            .filter(|r| r.sequence_id == id)
            .ok_or_else(|| {
                ApiError::not_found(format!(
                    "sequence {id} has no tracking run {run}; see GET /api/v1/sequences/{id}/tracking"
                ))
            }),
        None => state.store.current_tracking_run(id).await?.ok_or_else(|| {
            ApiError::conflict(format!(
                "sequence {id} is not tracked; start tracking with POST \
                 /api/v1/sequences/{id}/tracking {{\"max_velocity\": MM_PER_FRAME}}"
            ))
        }),
    }
}

/// How to write trajectories.
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryFormat {
    /// JSON.
    #[default]
    Json,
    /// CSV `trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,...`
    /// as `ptv track` writes it, by trajectory and frame.
    Csv,
    /// ParaView's VTK XML `trajectories.vtp` (polylines with velocity,
    /// acceleration and their sigmas) as `ptv export --export vtk` writes
    /// it; built whole, at most the service's `--max-export-points`
    /// (default 200,000) points.
    Vtk,
    /// The sequence's one-file HDF5 (particles by frame and trajectories,
    /// units in attributes) as `ptv export --export hdf5` writes it; built
    /// whole, at most the service's `--max-export-points` (default
    /// 200,000) points (trajectory points plus particles).
    Hdf5,
    /// ParaView's time series as one zip (`application/zip`, stored
    /// entries): `particles.pvd`, each processed frame's
    /// `particles.<frame>.vtp` within `frames` and `trajectories.vtp`, the
    /// files `ptv track --export vtk` writes into a directory; unzip and
    /// open `particles.pvd`. Built whole, within the same
    /// `--max-export-points`.
    Pvd,
}

/// Query of the trajectories route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct TrajectoriesQuery {
    /// json (default), csv, vtk (`trajectories.vtp`, application/xml),
    /// hdf5 (the sequence's HDF5 file, application/x-hdf5) or pvd
    /// (ParaView's time series: a zip of `particles.pvd`, the frames'
    /// `.vtp` and `trajectories.vtp`, application/zip); vtk, hdf5 and pvd
    /// are refused with 413 above the service's `--max-export-points`
    /// (default 200,000 points: cut them with `frames`).
    #[serde(default)]
    pub format: TrajectoryFormat,
    /// Only trajectories of at least this many points [default: all the
    /// run stored, which have at least its `min_length`].
    #[serde(default)]
    pub min_length: Option<u32>,
    /// Only points within `FIRST..LAST` (both included, each 0 to
    /// 4294967295 in decimal digits), of trajectories with a point there.
    #[serde(default)]
    pub frames: Option<String>,
    /// A tracking run of the sequence [default: its current one].
    #[serde(default)]
    #[param(value_type = Option<i64>)]
    pub run: Option<TrackingRunId>,
}

/// Query of the one-trajectory route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryQuery {
    /// A tracking run of the sequence [default: its current one].
    #[serde(default)]
    #[param(value_type = Option<i64>)]
    pub run: Option<TrackingRunId>,
}

/// A trajectory point.
#[derive(Debug, Serialize, ToSchema)]
pub struct TrajectoryPointView {
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The particle's index in the frame's particles; at or above their
    /// count, a particle the tracker recovered from the frame's targets
    /// (image-space recovery), which is not among the frame's particles.
    pub particle: i64,
    /// Position (mm).
    pub position: [f64; 3],
    /// Velocity (mm per frame) from the local polynomial fit; null where
    /// the fit has none.
    pub velocity: Option<[f64; 3]>,
    /// Acceleration (mm per frame²); null where the fit window has two
    /// points.
    pub acceleration: Option<[f64; 3]>,
    /// The velocity's standard deviations (mm per frame).
    pub velocity_sigma: Option<[f64; 3]>,
    /// Per camera, the particle's target index in that camera, or null.
    pub targets: Vec<Option<i64>>,
}

/// A trajectory with its points in frame order.
#[derive(Debug, Serialize, ToSchema)]
pub struct TrajectoryView {
    /// Its number within the run.
    pub id: i64,
    /// Its first frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub first_frame: FrameNumber,
    /// Its last frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub last_frame: FrameNumber,
    /// Its points (all of them, also where `points` is cut by `frames`).
    pub length: i64,
    /// Its points.
    pub points: Vec<TrajectoryPointView>,
}

/// The page of trajectories the list streams at a time.
pub(super) const TRAJECTORIES_PER_PAGE: u32 = 500;

fn point_view(p: &PointRow) -> TrajectoryPointView {
    TrajectoryPointView {
        frame: p.frame,
        particle: p.particle,
        position: p.position,
        velocity: p.velocity,
        acceleration: p.acceleration,
        velocity_sigma: p.velocity_sigma,
        targets: p
            .targets
            .split(',')
            .filter(|t| !t.is_empty())
            .map(|t| t.parse::<i64>().ok().filter(|&t| t >= 0))
            .collect(),
    }
}

/// A point as `ptv track` writes it ([`formats::csv::write_trajectory_point`]:
/// an absent velocity as NaN, an absent acceleration as empty fields).
fn csv_row(p: &PointRow, out: &mut String) {
    let targets: Vec<Option<usize>> = p
        .targets
        .split(',')
        .filter(|t| !t.is_empty())
        .map(|t| t.parse().ok())
        .collect();
    let point = formats::csv::TrajectoryPointLine {
        trajectory: p.trajectory,
        frame: p.frame.0,
        position: p.position,
        velocity: p.velocity,
        acceleration: p.acceleration,
        velocity_sigma: p.velocity_sigma,
        targets: Some(&targets),
    };
    formats::csv::write_trajectory_point(out, &point, targets.len());
}

/// A page of trajectories and their points, formatted.
async fn page(
    state: &AppState,
    run: TrackingRunId,
    format: TrajectoryFormat,
    list: &[TrajectoryRow],
    frames: (FrameNumber, FrameNumber),
    first_of_all: bool,
) -> Result<String, StoreError> {
    let (Some(low), Some(high)) = (list.first(), list.last()) else {
        return Ok(String::new());
    };
    let points = state
        .store
        .trajectory_points(run, (low.id, high.id), frames)
        .await?;
    let mut out = String::new();
    let mut points = points.iter().peekable();
    for (i, t) in list.iter().enumerate() {
        // Trajectories below min_length in the id range are skipped here.
        while points.peek().is_some_and(|p| p.trajectory < t.id) {
            points.next();
        }
        let mut mine = Vec::new();
        while let Some(p) = points.next_if(|p| p.trajectory == t.id) {
            mine.push(p);
        }
        match format {
            // Built whole by `exports`, not paged.
            TrajectoryFormat::Vtk | TrajectoryFormat::Hdf5 | TrajectoryFormat::Pvd => {}
            TrajectoryFormat::Csv => {
                for p in mine {
                    csv_row(p, &mut out);
                }
            }
            TrajectoryFormat::Json => {
                if !(first_of_all && i == 0) {
                    out.push(',');
                }
                let view = TrajectoryView {
                    id: t.id,
                    first_frame: t.first_frame,
                    last_frame: t.last_frame,
                    length: t.length,
                    points: mine.into_iter().map(point_view).collect(),
                };
                out.push_str(&serde_json::to_string(&view).unwrap_or_default());
            }
        }
    }
    Ok(out)
}

/// A tracked sequence's trajectories (its current run, or `run`), by
/// trajectory and then frame, streamed a page of trajectories at a time.
/// Points become final a few frames behind `tracked_through` (their fit
/// window), and the last ones when the run is finished.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/trajectories", tag = "tracking",
    params(("id" = i64, Path, description = "Sequence id"), TrajectoriesQuery),
    responses(
        (status = 200, description = "JSON `{\"run_id\", \"trajectories\": [TrajectoryView, ...]}`, or text/csv `trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,...` (mm, mm per frame, mm per frame²) as `ptv track` writes it, by `format`; `format=vtk`: application/xml ParaView `trajectories.vtp`; `format=hdf5`: application/x-hdf5, the sequence's HDF5 file (particles by frame and trajectories), both as attachments",
            headers(("Ptv-Tracking-Run" = i64, description = "The tracking run"))),
        (status = 400, description = "A bad query", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence is not tracked", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 413, description = "`format=vtk` or `hdf5` above 200,000 points; cut it with `frames`", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn trajectories(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<TrajectoriesQuery>,
) -> Result<Response, ApiError> {
    let frames = match &query.frames {
        None => (FrameNumber(i64::MIN), FrameNumber(i64::MAX)),
        Some(text) => {
            // Each end a frame number in the one accepted form.
            let ends = match text.split_once("..") {
                Some((first, last)) => [first, last.strip_prefix('=').unwrap_or(last)],
                None => [text.as_str(), text.as_str()],
            };
            for end in ends {
                if super::decimal::parse::<u32>(end).is_err() {
                    return Err(ApiError::bad_request(format!(
                        "frames: `{}` in `{}` is not a frame number; give FIRST..LAST, each 0 \
                         to {} written as {}",
                        end.escape_debug(),
                        text.escape_debug(),
                        u32::MAX,
                        super::decimal::FORM
                    )));
                }
            }
            let range = FrameRange::parse(text)
                .map_err(|e| ApiError::bad_request(format!("frames: {e}")))?;
            let number = |f: u64| i64::try_from(f).map(FrameNumber);
            match (number(range.first), number(range.last)) {
                (Ok(first), Ok(last)) => (first, last),
                _ => {
                    return Err(ApiError::bad_request(format!(
                        "frames: `{text}` is beyond the frame numbers"
                    )))
                }
            }
        }
    };
    let run = current_run(&state, id, query.run).await?;
    let cameras = {
        let row = sequence(&state, id).await?;
        state
            .store
            .calibration(row.calibration_id)
            .await?
            .map_or(0, |c| c.cameras as usize)
    };
    let min_length = i64::from(query.min_length.unwrap_or(1));
    let format = query.format;
    let run_header = (
        header::HeaderName::from_static(RUN_HEADER),
        run.id.to_string(),
    );
    let (content_type, head, tail) = match format {
        TrajectoryFormat::Vtk | TrajectoryFormat::Hdf5 | TrajectoryFormat::Pvd => {
            let collected =
                super::exports::collect(&state, id, run.id, cameras, min_length, frames).await?;
            // Encoding up to the point limit is CPU work: on the pool,
            // as the plots are, not on the async runtime.
            let bytes = state
                .cpu
                .run(move || match format {
                    TrajectoryFormat::Vtk => {
                        Ok(formats::vtk::trajectories_vtp(&collected.trajectories).into_bytes())
                    }
                    TrajectoryFormat::Pvd => super::exports::paraview_zip(&collected),
                    _ => super::exports::hdf5(&collected),
                })
                .await??;
            let file = match format {
                TrajectoryFormat::Vtk => super::exports::attachment(
                    super::exports::VTK_CONTENT_TYPE,
                    "trajectories.vtp",
                    bytes,
                ),
                TrajectoryFormat::Pvd => super::exports::attachment(
                    super::exports::ZIP_CONTENT_TYPE,
                    &format!("sequence_{id}_paraview.zip"),
                    bytes,
                ),
                _ => super::exports::attachment(
                    super::exports::HDF5_CONTENT_TYPE,
                    &format!("sequence_{id}.h5"),
                    bytes,
                ),
            };
            return Ok(([run_header], file).into_response());
        }
        TrajectoryFormat::Csv => (
            "text/csv",
            formats::csv::trajectory_header(cameras),
            String::new(),
        ),
        TrajectoryFormat::Json => (
            "application/json",
            format!("{{\"run_id\":{},\"trajectories\":[", run.id),
            "]}".to_owned(),
        ),
    };
    let run_id = run.id;
    let head = futures_util::stream::once(async move { Ok::<_, std::io::Error>(head) });
    // The state of the stream: the last trajectory written, and whether
    // the list has ended.
    let pages =
        futures_util::stream::unfold((state, Some(-1i64)), move |(state, after)| async move {
            let after = after?;
            let chunk = async {
                let list = state
                    .store
                    .trajectories(run_id, min_length, frames, after, TRAJECTORIES_PER_PAGE)
                    .await?;
                let text = page(&state, run_id, format, &list, frames, after < 0).await?;
                let next = (list.len() == TRAJECTORIES_PER_PAGE as usize)
                    .then(|| list.last().map_or(after, |t| t.id));
                Ok::<_, StoreError>((text, next))
            }
            .await;
            match chunk {
                Ok((text, next)) => Some((Ok(text), (state, next))),
                Err(error) => Some((Err(std::io::Error::other(error)), (state, None))),
            }
        });
    let tail = futures_util::stream::once(async move { Ok::<_, std::io::Error>(tail) });
    use futures_util::StreamExt as _;
    Ok((
        [
            (header::CONTENT_TYPE, content_type.to_owned()),
            (
                header::HeaderName::from_static(RUN_HEADER),
                run_id.to_string(),
            ),
        ],
        Body::from_stream(head.chain(pages).chain(tail)),
    )
        .into_response())
}

/// The response header that names the tracking run served.
pub const RUN_HEADER: &str = "ptv-tracking-run";

/// One trajectory of a tracked sequence (its current run, or `run`).
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/trajectories/{tid}", tag = "tracking",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("tid" = i64, Path, description = "Trajectory number within the run"),
        TrajectoryQuery,
    ),
    responses(
        (status = 200, body = TrajectoryView,
            headers(("Ptv-Tracking-Run" = i64, description = "The tracking run"))),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence is not tracked", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn trajectory(
    State(state): Shared,
    ApiPath((id, tid)): ApiPath<(SequenceId, i64)>,
    ApiQuery(query): ApiQuery<TrajectoryQuery>,
) -> Result<Response, ApiError> {
    let run = current_run(&state, id, query.run).await?;
    let row = state.store.trajectory(run.id, tid).await?.ok_or_else(|| {
        ApiError::not_found(format!(
            "tracking run {} of sequence {id} has no trajectory {tid} (yet)",
            run.id
        ))
    })?;
    let points = state
        .store
        .trajectory_points(
            run.id,
            (tid, tid),
            (FrameNumber(i64::MIN), FrameNumber(i64::MAX)),
        )
        .await?;
    Ok((
        [(RUN_HEADER, run.id.to_string())],
        Json(TrajectoryView {
            id: row.id,
            first_frame: row.first_frame,
            last_frame: row.last_frame,
            length: row.length,
            points: points.iter().map(point_view).collect(),
        }),
    )
        .into_response())
}

/// The trajectory of each particle of a frame in the sequence's current
/// run (`None` where a particle has none, or the sequence is not tracked),
/// and the run. Points of particles the run recovered from the images
/// (indices from `particles` on) are left out: they are not the frame's
/// particles.
pub(super) async fn frame_trajectories(
    state: &AppState,
    id: SequenceId,
    frame: FrameNumber,
    particles: usize,
) -> Result<(Option<TrackingRunId>, Vec<Option<i64>>), ApiError> {
    let mut out = vec![None; particles];
    let Some(run) = state.store.current_tracking_run(id).await? else {
        return Ok((None, out));
    };
    for (particle, trajectory) in state.store.frame_trajectories(run.id, frame).await? {
        if let Some(slot) = usize::try_from(particle).ok().and_then(|p| out.get_mut(p)) {
            *slot = Some(trajectory);
        }
    }
    Ok((Some(run.id), out))
}
