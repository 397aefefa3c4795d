//! A sequence's results: each frame's particles and targets (JSON, CSV,
//! OpenPTV text, VTK) and all particles as one streamed CSV.

use std::sync::Arc;

use axum::body::Body;
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiPath, ApiQuery};
use super::tracking::frame_trajectories;
use crate::formats;
use crate::photogrammetry::correspond::Particle;
use crate::service::infra::codec::{self, CameraTargets};
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, FrameNumber, SequenceId, TrackingRunId};

/// The response header that names the calibration that made a frame's
/// particles (CSV and rt_is; JSON has `calibration_id`).
pub const CALIBRATION_HEADER: &str = "ptv-calibration-id";

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route(
            "/sequences/{id}/frames/{frame}/particles",
            get(frame_particles),
        )
        .route("/sequences/{id}/frames/{frame}/targets", get(frame_targets))
        .route("/sequences/{id}/particles", get(all_particles))
}

/// How to write particles.
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ParticleFormat {
    /// JSON.
    #[default]
    Json,
    /// CSV `x,y,z,sx,sy,sz,rms_px,cameras,t0,...` as `ptv match` writes.
    Csv,
    /// OpenPTV's `rt_is`.
    RtIs,
    /// ParaView's VTK XML `.vtp` of the frame (vertices with their sigmas,
    /// cameras and trajectory), as `ptv export --export vtk` writes it.
    Vtk,
}

/// Query of the particle routes.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct ParticleQuery {
    /// json (default), csv, rt_is or vtk (`particles.<frame>.vtp`,
    /// application/xml).
    #[serde(default)]
    pub format: ParticleFormat,
}

/// One particle.
#[derive(Debug, Serialize, ToSchema)]
pub struct ParticleView {
    /// X (mm).
    pub x: f64,
    /// Y (mm).
    pub y: f64,
    /// Z (mm).
    pub z: f64,
    /// Standard deviations of X, Y, Z (mm).
    pub sigma: [f64; 3],
    /// Root mean square reprojection residual (px).
    pub rms_px: f64,
    /// Per camera, the index of its target in the frame's targets of that
    /// camera, or null.
    pub targets: Vec<Option<usize>>,
    /// Its trajectory in the sequence's current tracking run (null: none
    /// yet, or the sequence is not tracked).
    pub trajectory: Option<i64>,
}

/// A frame's particles.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameParticles {
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The calibration that made these particles (the sequence's, or the
    /// one it had when the frame was processed, until reprocessed).
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// The tracking run that `trajectory` refers to (null: the sequence is
    /// not tracked).
    #[schema(value_type = Option<i64>)]
    pub tracking_run: Option<TrackingRunId>,
    /// The particles the frame's correspondences gave. Particles a tracking
    /// run recovered from the frame's targets (image-space recovery) are
    /// not among them: they exist only as points of their trajectories
    /// (`GET /sequences/{id}/trajectories`), whose `particle` index is at or
    /// above this list's length.
    pub particles: Vec<ParticleView>,
}

/// The frame's stored particles and the calibration that made them, or
/// why there are none.
pub(super) async fn load_particles(
    state: &AppState,
    id: SequenceId,
    frame: FrameNumber,
) -> Result<(usize, Vec<Particle>, CalibrationId), ApiError> {
    let row = sequence(state, id).await?;
    let cameras = state
        .store
        .calibration(row.calibration_id)
        .await?
        .map_or(0, |c| c.cameras as usize);
    match state.store.frame_particles(id, frame).await? {
        Some((_, blob, made_by)) => {
            Ok((cameras, codec::decode_particles(&blob, cameras)?, made_by))
        }
        None => Err(no_results(state, id, frame).await),
    }
}

/// Why a frame has no results: it is not processed yet (409), or it does
/// not exist (404).
pub(super) async fn no_results(state: &AppState, id: SequenceId, frame: FrameNumber) -> ApiError {
    match state.store.frame_exists(id, frame).await {
        Ok(true) => {
            ApiError::conflict(format!("frame {frame} is not processed (yet); see its job"))
        }
        Ok(false) => ApiError::not_found(format!("sequence {id} has no frame {frame}")),
        Err(error) => error.into(),
    }
}

/// A processed frame's 3D particles.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/particles", tag = "sequences",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        ParticleQuery,
    ),
    responses(
        (status = 200, body = FrameParticles, description = "JSON; text/csv, text/plain (rt_is) or application/xml (vtk: ParaView's `.vtp`, an attachment) by `format`, the calibration that made them in the `Ptv-Calibration-Id` header",
            headers(("Ptv-Calibration-Id" = i64, description = "The calibration that made the particles"))),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn frame_particles(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<ParticleQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    let (cameras, particles, made_by) = load_particles(&state, id, frame).await?;
    let provenance = [(CALIBRATION_HEADER, made_by.to_string())];
    Ok(match query.format {
        ParticleFormat::Json => {
            let (tracking_run, trajectories) =
                frame_trajectories(&state, id, frame, particles.len()).await?;
            Json(FrameParticles {
                sequence_id: id,
                frame,
                calibration_id: made_by,
                tracking_run,
                particles: particles
                    .iter()
                    .zip(trajectories)
                    .map(|(p, trajectory)| ParticleView {
                        x: p.position.x,
                        y: p.position.y,
                        z: p.position.z,
                        sigma: [p.sigma.x, p.sigma.y, p.sigma.z],
                        rms_px: p.rms_px,
                        targets: p.targets.clone(),
                        trajectory,
                    })
                    .collect(),
            })
            .into_response()
        }
        ParticleFormat::Csv => (
            [(header::CONTENT_TYPE, "text/csv")],
            provenance,
            formats::csv::format_particles(&particles, cameras),
        )
            .into_response(),
        ParticleFormat::RtIs => (
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            provenance,
            formats::openptv::format_rt_is(&particles, cameras),
        )
            .into_response(),
        ParticleFormat::Vtk => {
            let (_, trajectories) = frame_trajectories(&state, id, frame, particles.len()).await?;
            let records = super::exports::particle_records(&particles, &trajectories);
            (
                provenance,
                super::exports::attachment(
                    super::exports::VTK_CONTENT_TYPE,
                    &format!("particles.{frame}.vtp"),
                    formats::vtk::particles_vtp(&records).into_bytes(),
                ),
            )
                .into_response()
        }
    })
}

/// How to write targets.
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TargetFormat {
    /// JSON.
    #[default]
    Json,
    /// CSV `x,y,n,nx,ny,sumg` as `ptv detect` writes.
    Csv,
    /// OpenPTV's `_targets`.
    Openptv,
}

/// Query of the targets route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct TargetQuery {
    /// The camera, from 0.
    pub camera: usize,
    /// json (default), csv or openptv.
    #[serde(default)]
    pub format: TargetFormat,
}

/// One target.
#[derive(Debug, Serialize, ToSchema)]
pub struct TargetView {
    /// Centroid x (px).
    pub x: f64,
    /// Centroid y (px).
    pub y: f64,
    /// Pixels.
    pub n: u32,
    /// Extent in x (px).
    pub nx: u32,
    /// Extent in y (px).
    pub ny: u32,
    /// Sum of grey values.
    pub sumg: u64,
}

/// A frame's targets in one camera.
#[derive(Debug, Serialize, ToSchema)]
pub struct FrameTargets {
    /// The frame.
    #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: FrameNumber,
    /// The camera.
    pub camera: usize,
    /// The targets, indexed as the particles' `targets` refer to them.
    pub targets: Vec<TargetView>,
}

/// A frame's targets in one camera (detected, or as uploaded).
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/targets", tag = "sequences",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        TargetQuery,
    ),
    responses(
        (status = 200, body = FrameTargets, description = "JSON; text/csv or text/plain (openptv) by `format`"),
        (status = 400, description = "No or bad camera", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn frame_targets(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<TargetQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    sequence(&state, id).await?;
    let stored = state.store.frame_targets(id, frame).await?;
    if stored.is_empty() {
        return Err(no_results(&state, id, frame).await);
    }
    let CameraTargets { data: blob, .. } = stored
        .iter()
        .find(|t| t.camera == query.camera as i64)
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "camera {} does not exist; cameras are 0 to {}",
                query.camera,
                stored.len() - 1
            ))
        })?;
    let targets = codec::decode_targets(blob)?;
    Ok(match query.format {
        TargetFormat::Json => Json(FrameTargets {
            frame,
            camera: query.camera,
            targets: targets
                .iter()
                .map(|t| TargetView {
                    x: t.x,
                    y: t.y,
                    n: t.n,
                    nx: t.nx,
                    ny: t.ny,
                    sumg: t.sumg,
                })
                .collect(),
        })
        .into_response(),
        TargetFormat::Csv => (
            [(header::CONTENT_TYPE, "text/csv")],
            formats::csv::format_targets(&targets),
        )
            .into_response(),
        TargetFormat::Openptv => (
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            formats::openptv::format_targets(&targets),
        )
            .into_response(),
    })
}

/// Query of the all-particles route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct AllParticlesQuery {
    /// Only csv.
    #[serde(default)]
    pub format: Option<String>,
}

/// All processed frames' particles as one CSV with a `frame` column and
/// the calibration that made each frame's particles, streamed frame by
/// frame.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/particles", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id"), AllParticlesQuery),
    responses(
        (status = 200, content_type = "text/csv", body = String, description = "frame,calibration_id,x,y,z,sx,sy,sz,rms_px,cameras,t0,...: calibration_id is the calibration that made the frame's particles"),
        (status = 400, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn all_particles(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<AllParticlesQuery>,
) -> Result<Response, ApiError> {
    if let Some(format) = query.format.as_deref().filter(|f| *f != "csv") {
        return Err(ApiError::bad_request(format!(
            "format `{format}`: all frames come only as csv"
        )));
    }
    let row = sequence(&state, id).await?;
    let cameras = state
        .store
        .calibration(row.calibration_id)
        .await?
        .map_or(0, |c| c.cameras as usize);
    let frames = state.store.processed_frames(id).await?;
    let header_line = {
        let mut line = String::from("frame,calibration_id,");
        line.push_str(formats::csv::format_particles(&[], cameras).trim_end());
        line.push('\n');
        line
    };
    let first = futures_util::stream::once(async move { Ok::<_, std::io::Error>(header_line) });
    let rest = futures_util::stream::unfold(
        (state, frames.into_iter()),
        move |(state, mut frames)| async move {
            let frame = frames.next()?;
            let chunk = match state.store.frame_particles(id, frame).await {
                Ok(Some((_, blob, made_by))) => match codec::decode_particles(&blob, cameras) {
                    Ok(particles) => Ok(frame_rows(frame, made_by, &particles, cameras)),
                    Err(e) => Err(std::io::Error::other(e)),
                },
                Ok(None) => Ok(String::new()),
                Err(e) => Err(std::io::Error::other(e)),
            };
            Some((chunk, (state, frames)))
        },
    );
    use futures_util::StreamExt as _;
    Ok((
        [(header::CONTENT_TYPE, "text/csv")],
        Body::from_stream(first.chain(rest)),
    )
        .into_response())
}

/// A frame's particle rows with the frame number and the calibration that
/// made them in front.
fn frame_rows(
    frame: FrameNumber,
    made_by: CalibrationId,
    particles: &[Particle],
    cameras: usize,
) -> String {
    let table = formats::csv::format_particles(particles, cameras);
    let mut out = String::with_capacity(table.len() + particles.len() * 12);
    for line in table.lines().skip(1) {
        out.push_str(&frame.to_string());
        out.push(',');
        out.push_str(&made_by.to_string());
        out.push(',');
        out.push_str(line);
        out.push('\n');
    }
    out
}
