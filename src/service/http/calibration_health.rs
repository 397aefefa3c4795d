//! `GET /sequences/{id}/calibration-health`: the running summary of a
//! sequence's calibration health ([`crate::service::ops::health`]): per
//! camera the baseline, the last window's mean disparity, its drift and
//! the alarm once fired, and the latest frame's disparities per
//! sub-volume; with the advice to self-calibrate once an alarm fired. The
//! picture over frames is `calibration-health.png` ([`super::plots`]).
//!
//! Statuses: an unknown sequence is a 404; a query field a 400. A sequence
//! with no frame processed yet answers 200 with no frames taken.

use std::sync::Arc;

use axum::extract::State;
use axum::routing::get;
use axum::{Json, Router};
use serde::Serialize;
use utoipa::ToSchema;

use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiPath};
use crate::service::ops::health::{summary, GRID};
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, HealthRow, SequenceId};

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new().route("/sequences/{id}/calibration-health", get(read))
}

/// A disparity: the mean vector and the RMS of the vectors' lengths.
#[derive(Debug, Serialize, ToSchema)]
pub struct DisparityView {
    /// The sub-volume, x fastest, then y, then z (absent: the whole frame).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cell: Option<i64>,
    /// Well-matched particles seen by the camera there.
    pub count: i64,
    /// The mean disparity vector (px): observed target minus the projection
    /// of the particle's intersected position.
    pub mean_px: [f64; 2],
    /// The RMS of the vectors' lengths (px).
    pub rms_px: f64,
}

impl From<&HealthRow> for DisparityView {
    fn from(row: &HealthRow) -> Self {
        DisparityView {
            cell: (row.cell >= 0).then_some(row.cell),
            count: row.count,
            mean_px: row.mean,
            rms_px: row.rms,
        }
    }
}

/// A camera's alarm.
#[derive(Debug, Serialize, ToSchema)]
pub struct DriftAlarmView {
    /// The frame at which it fired.
    #[schema(minimum = 0, maximum = 4_294_967_295_u64)]
    pub frame: i64,
    /// The windowed mean's change from the baseline (px, x and y).
    pub drift_px: [f64; 2],
    /// Its length (px).
    pub drift_length_px: f64,
}

/// One camera's health.
#[derive(Debug, Serialize, ToSchema)]
pub struct CameraHealthView {
    /// The camera, from 0.
    pub camera: usize,
    /// The mean of the first window's frame means (px); null until that
    /// many frames were taken.
    pub baseline_px: Option<[f64; 2]>,
    /// The mean of the last window's frame means (px).
    pub window_mean_px: [f64; 2],
    /// The length of the window mean's change from the baseline (px).
    pub drift_px: f64,
    /// The alarm, once fired (it stays until the calibration changes).
    pub alarm: Option<DriftAlarmView>,
    /// The latest frame's disparity over the frame (null: no frame yet).
    pub latest: Option<DisparityView>,
    /// The latest frame's disparity per sub-volume that had particles.
    pub cells: Vec<DisparityView>,
}

/// A sequence's calibration health.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationHealthView {
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// The calibration its particles are made with, whose health this is.
    #[schema(value_type = i64)]
    pub calibration_id: CalibrationId,
    /// The drift that raises a camera's alarm (px).
    pub threshold_px: f64,
    /// Frames per window.
    pub window: u32,
    /// Sub-volumes per axis over the sequence's volume.
    pub grid: [usize; 3],
    /// The last frame taken, in frame order (null: none yet). Frames
    /// after it are still queued or running, or were processed with
    /// another calibration and wait for reprocessing.
    #[schema(minimum = 0, maximum = 4_294_967_295_u64)]
    pub through_frame: Option<i64>,
    /// Frames taken with particles to measure.
    pub frames: i64,
    /// The latest frame measured (null: none).
    #[schema(minimum = 0, maximum = 4_294_967_295_u64)]
    pub latest_frame: Option<i64>,
    /// Per camera.
    pub cameras: Vec<CameraHealthView>,
    /// Whether any camera's alarm fired.
    pub alarm: bool,
    /// What to do, once an alarm fired.
    pub advice: Option<String>,
    /// The picture of the disparities over frames.
    pub plot: String,
}

/// The running summary of a sequence's calibration health: per camera the
/// mean disparity of its well-matched particles, its drift from the run's
/// first frames, the alarm when it drifted past the sequence's threshold,
/// and the latest frame's disparities per sub-volume.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/calibration-health", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    responses(
        (status = 200, body = CalibrationHealthView),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn read(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
) -> Result<Json<CalibrationHealthView>, ApiError> {
    sequence(&state, id).await?;
    let monitor = summary(&state, id).await?;
    let latest = match monitor.through {
        Some(through) => state.store.latest_frame_health(id, through).await?,
        None => None,
    };
    let cameras: Vec<CameraHealthView> = monitor
        .monitor
        .cameras
        .iter()
        .enumerate()
        .map(|(camera, c)| {
            let rows: Vec<&HealthRow> = latest
                .iter()
                .flat_map(|(_, rows)| rows)
                .filter(|r| r.camera == camera as i64)
                .collect();
            CameraHealthView {
                camera,
                baseline_px: c.baseline_px,
                window_mean_px: c.window_mean_px,
                drift_px: c.drift_px,
                alarm: c.alarm.as_ref().map(|a| DriftAlarmView {
                    frame: a.frame,
                    drift_px: a.drift_px,
                    drift_length_px: a.drift_length_px,
                }),
                latest: rows.iter().find(|r| r.cell == -1).map(|r| (*r).into()),
                cells: rows
                    .iter()
                    .filter(|r| r.cell >= 0)
                    .map(|r| (*r).into())
                    .collect(),
            }
        })
        .collect();
    let alarmed: Vec<String> = cameras
        .iter()
        .filter_map(|c| {
            c.alarm.as_ref().map(|a| {
                format!(
                    "camera {} drifted {:.2} px by frame {}",
                    c.camera, a.drift_length_px, a.frame
                )
            })
        })
        .collect();
    let first_alarm = cameras
        .iter()
        .filter_map(|c| c.alarm.as_ref().map(|a| a.frame))
        .min();
    let advice = first_alarm.map(|first| {
        let last = monitor.through.map_or(first, |f| f.0);
        format!(
            "{}: the calibration no longer fits the images. Self-calibrate the sequence from \
             the frames since the drift (POST /api/v1/sequences/{id}/self-calibration with \
             {{\"frames\": {{\"first\": {first}, \"last\": {last}}}, \"reprocess\": true}}), \
             or check the rig.",
            alarmed.join("; ")
        )
    });
    Ok(Json(CalibrationHealthView {
        sequence_id: id,
        calibration_id: monitor.calibration_id,
        threshold_px: monitor.settings.threshold_px,
        window: monitor.settings.window,
        grid: GRID,
        through_frame: monitor.through.map(|f| f.0),
        frames: monitor.frames,
        latest_frame: latest.map(|(f, _)| f.0),
        alarm: !alarmed.is_empty(),
        advice,
        cameras,
        plot: format!("/api/v1/sequences/{id}/calibration-health.png"),
    }))
}
