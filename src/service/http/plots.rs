//! Pictures of results ([`crate::plot`]): a calibration's residuals and a
//! self-calibration's disparity maps, a frame's camera image with its
//! targets and reprojections, a frame's particles and a sequence's
//! trajectories in three views. PNG by default, SVG with `?format=svg`;
//! drawn on the CPU pool (these routes are among the shed CPU routes).
//!
//! Statuses: an unknown calibration, sequence, frame, camera or tracking
//! run is a 404; a resource that exists but lacks what the picture needs
//! (a calibration stored as given, so without a report; the other kind of
//! report; a frame not processed yet; a frame image that is not kept; a
//! sequence not tracked) a 409 that says what is missing; an unknown
//! `format` (or other query field) a 400.

use std::sync::Arc;

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use serde::Deserialize;
use utoipa::IntoParams;

use super::calibrations::{calibration, stored_rig};
use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiPath, ApiQuery};
use super::results::{load_particles, no_results};
use super::tracking::current_run;
use crate::formats;
use crate::photogrammetry::image::GreyImage;
use crate::plot::disparity::{disparity_plot, DisparityMaps};
use crate::plot::health::{health_plot, CameraSeries, HealthSeries};
use crate::plot::overlay::{overlay_plot, Overlay};
use crate::plot::residuals::{residual_plot, ResidualReport};
use crate::plot::views::{particles_plot, trajectories_plot, ParticlePoint, TrajectoryPoint};
use crate::plot::PlotFormat;
use crate::service::infra::codec::{self, CameraTargets};
use crate::service::model::raw_layout::StoredRawLayout;
use crate::service::ops::state::AppState;
use crate::service::store::{CalibrationId, FrameNumber, SequenceId, TrackingRunId};

/// The most trajectory points a trajectories picture draws (the first
/// trajectories by number up to it; the picture says so): bounds the
/// memory and the SVG's size.
pub const MAX_TRAJECTORY_POINTS: usize = 200_000;

/// The routes' paths (also the shed CPU routes).
pub const PLOT_ROUTES: [&str; 7] = [
    "/api/v1/calibrations/{id}/residuals.png",
    "/api/v1/calibrations/{id}/disparity.png",
    "/api/v1/sequences/{id}/frames/{frame}/overlay.png",
    "/api/v1/sequences/{id}/frames/{frame}/particles.png",
    "/api/v1/sequences/{id}/trajectories.png",
    "/api/v1/sequences/{id}/frames/{frame}/image.png",
    "/api/v1/sequences/{id}/calibration-health.png",
];

pub(super) fn router() -> Router<Arc<AppState>> {
    let route = |path: &'static str| path.trim_start_matches("/api/v1");
    Router::new()
        .route(route(PLOT_ROUTES[0]), get(residuals))
        .route(route(PLOT_ROUTES[1]), get(disparity))
        .route(route(PLOT_ROUTES[2]), get(overlay))
        .route(route(PLOT_ROUTES[3]), get(particles))
        .route(route(PLOT_ROUTES[4]), get(trajectories))
        .route(route(PLOT_ROUTES[5]), get(kept_image))
        .route(route(PLOT_ROUTES[6]), get(calibration_health))
}

/// Query of a frame's kept image.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct ImageQuery {
    /// The camera, from 0 [default: 0].
    #[serde(default)]
    pub camera: usize,
}

/// Query of the pictures without other options.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct PlotQuery {
    /// png (default) or svg.
    #[serde(default)]
    #[param(value_type = Option<String>)]
    pub format: PlotFormat,
}

/// Query of a camera's picture.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct CameraPlotQuery {
    /// The camera, from 0 [default: 0].
    #[serde(default)]
    pub camera: usize,
    /// png (default) or svg.
    #[serde(default)]
    #[param(value_type = Option<String>)]
    pub format: PlotFormat,
}

/// Query of the frame overlay.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct OverlayQuery {
    /// The camera, from 0 [default: 0].
    #[serde(default)]
    pub camera: usize,
    /// png (default) or svg.
    #[serde(default)]
    #[param(value_type = Option<String>)]
    pub format: PlotFormat,
    /// Draw the camera's image under the marks [default: true]; a frame
    /// whose image is not kept is a 409 unless this is false, which draws
    /// the marks on a black sensor.
    #[serde(default)]
    pub image: Option<bool>,
}

/// Query of the trajectories picture.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct TrajectoriesPlotQuery {
    /// png (default) or svg.
    #[serde(default)]
    #[param(value_type = Option<String>)]
    pub format: PlotFormat,
    /// A tracking run of the sequence [default: its current one].
    #[serde(default)]
    #[param(value_type = Option<i64>)]
    pub run: Option<TrackingRunId>,
}

/// A picture's response.
fn picture(format: PlotFormat, bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, format.content_type()),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        bytes,
    )
        .into_response()
}

/// A calibration's report, or a 409 saying it has none.
async fn report_of(state: &AppState, id: CalibrationId) -> Result<(String, String), ApiError> {
    let row = calibration(state, id).await?;
    let report = row.report.clone().ok_or_else(|| {
        ApiError::conflict(format!(
            "calibration {id} has no report: it was stored as given, not solved from control \
             points (POST /api/v1/calibrations/solve) or self-calibrated, so there are no \
             residuals or disparities to draw"
        ))
    })?;
    Ok((row.model, report))
}

/// One camera's calibration residuals: the residual vectors over its
/// sensor (scaled, with a scale bar), a histogram of their lengths, and
/// the check points' errors.
#[utoipa::path(
    get, path = "/api/v1/calibrations/{id}/residuals.png", tag = "plots",
    params(("id" = i64, Path, description = "Calibration id"), CameraPlotQuery),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration or camera", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The calibration has no report, a self-calibration's, or one written before reports said where points were measured", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn residuals(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
    ApiQuery(query): ApiQuery<CameraPlotQuery>,
) -> Result<Response, ApiError> {
    let row = calibration(&state, id).await?;
    let (cameras, _) = stored_rig(&row)?;
    let (_, report) = report_of(&state, id).await?;
    let camera = cameras.get(query.camera).ok_or_else(|| {
        ApiError::not_found(format!(
            "camera {} does not exist; calibration {id}'s cameras are 0 to {}",
            query.camera,
            cameras.len().saturating_sub(1)
        ))
    })?;
    let sensor = (camera.sensor().width, camera.sensor().height);
    let format = query.format;
    let index = query.camera;
    let bytes = state
        .cpu
        .run(move || {
            let report = ResidualReport::from_json(&report, &format!("calibration {id}'s report"))?;
            residual_plot(&report, index, sensor, format)
        })
        .await??;
    Ok(picture(format, bytes))
}

/// A self-calibrated calibration's disparity maps, before and after, per
/// camera and sub-volume.
#[utoipa::path(
    get, path = "/api/v1/calibrations/{id}/disparity.png", tag = "plots",
    params(("id" = i64, Path, description = "Calibration id"), PlotQuery),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such calibration", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The calibration was not self-calibrated: no disparity maps", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn disparity(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
    ApiQuery(query): ApiQuery<PlotQuery>,
) -> Result<Response, ApiError> {
    let (_, report) = report_of(&state, id).await?;
    let format = query.format;
    let bytes = state
        .cpu
        .run(move || {
            let maps = DisparityMaps::from_json(&report, &format!("calibration {id}'s report"))?;
            disparity_plot(&maps, format)
        })
        .await??;
    Ok(picture(format, bytes))
}

/// A frame's image in one camera (where the service keeps it), with the
/// detected targets ringed (unmatched ones larger, in magenta) and the
/// particles' reprojections as crosses coloured by how many cameras saw
/// them.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/overlay.png", tag = "plots",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        OverlayQuery,
    ),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg. The sensor at its own scale (a picture pixel a sensor pixel) and a legend strip under it"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence, frame or camera", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet, or the frame's image is not kept (ask with image=false)", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn overlay(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<OverlayQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    let (cameras_n, particles, made_by) = load_particles(&state, id, frame).await?;
    let stored = state.store.frame_targets(id, frame).await?;
    let Some(CameraTargets { data: blob, .. }) =
        stored.iter().find(|t| t.camera == query.camera as i64)
    else {
        if stored.is_empty() {
            return Err(no_results(&state, id, frame).await);
        }
        return Err(ApiError::not_found(format!(
            "camera {} does not exist; cameras are 0 to {}",
            query.camera,
            cameras_n.saturating_sub(1)
        )));
    };
    let targets = codec::decode_targets(blob)?;
    let calibration = calibration(&state, made_by).await?;
    let (cameras, splitter) = stored_rig(&calibration)?;
    let camera = cameras.get(query.camera).cloned().ok_or_else(|| {
        ApiError::internal("a frame's targets name a camera its calibration lacks")
    })?;
    // The image, if asked for: the camera's file, or the frame's one file
    // that the splitter cuts into views.
    let image = if query.image.unwrap_or(true) {
        let hint = "ask with image=false for the targets and reprojections on a blank sensor";
        Some(stored_image(&state, (id, frame, query.camera), splitter.is_some(), hint).await?)
    } else {
        None
    };
    let format = query.format;
    let index = query.camera;
    let title = format!(
        "Sequence {id}, frame {frame}, camera {index} ({})",
        camera.name()
    );
    let bytes = state
        .cpu
        .run(move || -> Result<Vec<u8>, ApiError> {
            let image: Option<GreyImage> = image
                .map(|stored| stored.decode(frame, index, splitter.as_ref()))
                .transpose()?;
            let mut overlay = Overlay::new(
                &camera,
                index,
                &targets,
                particles.iter().map(|p| (p.position, p.targets.as_slice())),
                image.as_ref(),
            );
            overlay.title = title;
            Ok(overlay_plot(&overlay, format)?)
        })
        .await??;
    Ok(picture(format, bytes))
}

/// A frame's stored image file of a camera (a splitter's one file for
/// every view), not decoded yet.
struct StoredImage {
    bytes: Vec<u8>,
    layout: Option<formats::image::RawLayout>,
}

impl StoredImage {
    /// The camera's image: the file decoded, a splitter's view cut out.
    fn decode(
        self,
        frame: FrameNumber,
        camera: usize,
        splitter: Option<&crate::photogrammetry::splitter::Splitter>,
    ) -> Result<GreyImage, ApiError> {
        let source = format!("the image of frame {frame}");
        let image = match &self.layout {
            Some(layout) => formats::image::decode_raw(&self.bytes, layout, &source),
            None => formats::image::decode_image(&self.bytes, &source),
        }
        .map_err(ApiError::internal)?;
        match splitter {
            None => Ok(image),
            Some(splitter) => splitter
                .split(&image)
                .map_err(ApiError::internal)?
                .into_iter()
                .nth(camera)
                .ok_or_else(|| ApiError::internal("the splitter has fewer views")),
        }
    }
}

/// Reads the kept image file of `camera` of a frame: a 409 where it is
/// not kept, which ends with `hint` (what to ask for instead).
async fn stored_image(
    state: &AppState,
    (id, frame, camera): (SequenceId, FrameNumber, usize),
    splitter: bool,
    hint: &str,
) -> Result<StoredImage, ApiError> {
    let images = state.store.frame_images(id, frame).await?;
    let wanted = if splitter { 0 } else { camera };
    let not_kept = || {
        ApiError::conflict(format!(
            "the image of camera {camera} of frame {frame} is not kept: sequence {id} was \
             created with keep_images false, or the frame came as targets; {hint}"
        ))
    };
    let image = images.get(wanted).ok_or_else(not_kept)?;
    let bytes = match state.images.read(&image.sha256).await {
        Ok(bytes) => bytes,
        Err(crate::service::ops::images::ImageStoreError::Missing { .. }) => return Err(not_kept()),
        Err(e) => return Err(e.into()),
    };
    let layout = state
        .store
        .frame_input(id, frame)
        .await?
        .and_then(|input| input.raw_layout)
        .map(|text| {
            serde_json::from_str::<StoredRawLayout>(&text)
                .ok()
                .and_then(|l| l.layout())
                .ok_or_else(|| ApiError::internal(format!("malformed raw layout {text}")))
        })
        .transpose()?;
    Ok(StoredImage { bytes, layout })
}

/// A frame's kept camera image, plain (no marks), as an 8-bit grey PNG
/// at the sensor's size: a 16-bit or 12-bit image's top 8 bits of its
/// depth, as the overlay shows it. For a viewer that draws its own marks
/// (the page's frame viewer).
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/image.png", tag = "plots",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        ImageQuery,
    ),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "8-bit grey PNG, a picture pixel a sensor pixel"),
        (status = 400, description = "Unknown query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence, frame or camera", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The frame's image is not kept", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn kept_image(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<ImageQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    let sequence = super::lookups::sequence(&state, id).await?;
    let calibration = calibration(&state, sequence.calibration_id).await?;
    let (cameras, splitter) = stored_rig(&calibration)?;
    if query.camera >= cameras.len() {
        return Err(ApiError::not_found(format!(
            "camera {} does not exist; sequence {id}'s cameras are 0 to {}",
            query.camera,
            cameras.len().saturating_sub(1)
        )));
    }
    if state.store.frame_input(id, frame).await?.is_none() {
        return Err(ApiError::not_found(format!(
            "sequence {id} has no frame {frame}"
        )));
    }
    let hint = format!(
        "its targets are at {}/frames/{frame}/targets?camera={}",
        crate::service::ops::links::sequence(id),
        query.camera
    );
    let stored = stored_image(&state, (id, frame, query.camera), splitter.is_some(), &hint).await?;
    let camera = query.camera;
    let bytes = state
        .cpu
        .run(move || -> Result<Vec<u8>, ApiError> {
            let image = stored.decode(frame, camera, splitter.as_ref())?;
            crate::plot::grey_png(&image).map_err(|e| ApiError::internal(e.to_string()))
        })
        .await??;
    Ok(picture(PlotFormat::Png, bytes))
}

/// A processed frame's particles in three orthographic views (XY, XZ,
/// YZ), coloured by how many cameras saw them.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/frames/{frame}/particles.png", tag = "plots",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("frame" = i64, Path, description = "Frame number", minimum = 0, maximum = 4_294_967_295_u64),
        PlotQuery,
    ),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence or frame", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "Not processed yet", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn particles(
    State(state): Shared,
    ApiPath((id, frame)): ApiPath<(SequenceId, u32)>,
    ApiQuery(query): ApiQuery<PlotQuery>,
) -> Result<Response, ApiError> {
    let frame = FrameNumber(frame.into());
    let (_, particles, _) = load_particles(&state, id, frame).await?;
    let format = query.format;
    let bytes = state
        .cpu
        .run(move || {
            let points: Vec<ParticlePoint> = particles
                .iter()
                .map(|p| ParticlePoint {
                    position: p.position,
                    cameras: p.camera_count(),
                })
                .collect();
            particles_plot(&format!("Sequence {id}, frame {frame}"), &points, format)
        })
        .await??;
    Ok(picture(format, bytes))
}

/// A tracked sequence's trajectories (its current run, or `run`) in three
/// orthographic views, coloured by speed; at most
/// 200,000 points (the first trajectories by number; the picture says
/// when some are left out).
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/trajectories.png", tag = "plots",
    params(("id" = i64, Path, description = "Sequence id"), TrajectoriesPlotQuery),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence or run", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 409, description = "The sequence is not tracked", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn trajectories(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<TrajectoriesPlotQuery>,
) -> Result<Response, ApiError> {
    let run = current_run(&state, id, query.run).await?;
    let all = (FrameNumber(i64::MIN), FrameNumber(i64::MAX));
    let total = state.store.trajectory_count(run.id).await?;
    let mut trajectories: Vec<Vec<TrajectoryPoint>> = Vec::new();
    let (mut points, mut after, mut full) = (0usize, -1i64, false);
    'pages: loop {
        let list = state.store.trajectories(run.id, 1, all, after, 500).await?;
        let (Some(low), Some(high)) = (list.first(), list.last()) else {
            break;
        };
        let rows = state
            .store
            .trajectory_points(run.id, (low.id, high.id), all)
            .await?;
        let mut current = None;
        for p in rows {
            if current != Some(p.trajectory) {
                if points >= MAX_TRAJECTORY_POINTS {
                    full = true;
                    break 'pages;
                }
                current = Some(p.trajectory);
                trajectories.push(Vec::new());
            }
            points += 1;
            if let Some(t) = trajectories.last_mut() {
                t.push(TrajectoryPoint {
                    frame: p.frame.0,
                    position: p.position.into(),
                    velocity: p.velocity.map(Into::into),
                });
            }
        }
        after = high.id;
        if list.len() < 500 {
            break;
        }
    }
    let note = if full {
        format!(
            "The first {} of {total} trajectories (at most {MAX_TRAJECTORY_POINTS} points)",
            trajectories.len()
        )
    } else {
        String::new()
    };
    let format = query.format;
    let title = format!("Sequence {id}, tracking run {}", run.id);
    let bytes = state
        .cpu
        .run(move || trajectories_plot(&title, &note, &trajectories, format))
        .await??;
    Ok(picture(format, bytes))
}

/// The most bins of frames the calibration health picture draws: a bin
/// is the mean of its frames, so the picture reads at most cameras x
/// 1,000 rows whatever the run's length.
pub const MAX_HEALTH_BINS: i64 = 1000;

/// A sequence's calibration health over its frames: per camera the change
/// of its frames' mean disparity from the run's first window of frames,
/// the alarm threshold, and each camera's alarm; frames averaged in bins
/// beyond 1,000 frames.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/calibration-health.png", tag = "plots",
    params(("id" = i64, Path, description = "Sequence id"), PlotQuery),
    responses(
        (status = 200, content_type = "image/png", body = Vec<u8>, description = "PNG; image/svg+xml with format=svg"),
        (status = 400, description = "Unknown format or query field", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such sequence", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn calibration_health(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    ApiQuery(query): ApiQuery<PlotQuery>,
) -> Result<Response, ApiError> {
    sequence(&state, id).await?;
    let monitor = crate::service::ops::health::summary(&state, id).await?;
    let points = state
        .store
        .health_series(id, monitor.calibration_id, MAX_HEALTH_BINS)
        .await?;
    let mut cameras: Vec<CameraSeries> = monitor
        .monitor
        .cameras
        .iter()
        .map(|c| CameraSeries {
            points: Vec::new(),
            baseline: c.baseline_px,
            alarm: c.alarm.as_ref().map(|a| a.frame),
        })
        .collect();
    for p in points {
        if let Some(c) = usize::try_from(p.camera)
            .ok()
            .and_then(|c| cameras.get_mut(c))
        {
            c.points.push((p.frame.0, p.mean));
        }
    }
    let series = HealthSeries {
        title: format!(
            "Sequence {id}, calibration {}: calibration health",
            monitor.calibration_id
        ),
        threshold_px: monitor.settings.threshold_px,
        window: monitor.settings.window as usize,
        cameras,
    };
    let format = query.format;
    let bytes = state
        .cpu
        .run(move || health_plot(&series, format))
        .await??;
    Ok(picture(format, bytes))
}
