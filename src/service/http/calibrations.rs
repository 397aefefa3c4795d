//! `/calibrations`: create one from the calibration JSON or OpenPTV's
//! files, read it, export it as OpenPTV files, and two small synchronous
//! helpers to check a set-up: project 3D points, intersect image points.

use std::sync::Arc;

use axum::extract::{Multipart, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use nalgebra::Point2;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::links;
use super::problem::{parse_json, ApiError, ApiJson, ApiMultipart, ApiPath, ApiQuery, JsonText};
use super::upload::{accepted, check_images, or_drain, persist_and_commit, stream_part, text_part};
use super::Shared;
use crate::formats::{self, control, openptv::OriTexts};
use crate::photogrammetry::calibrate;
use crate::photogrammetry::{intersect, Camera, Cancel, Observation, Sensor, Splitter, StopOnDrop};
use crate::service::app::AppState;
use crate::service::images::UploadedFile;
use crate::service::jobs::{part_source, SolvePayload, SOLVE_CALIBRATION};
use crate::service::parameters::SolveOptions;
use crate::service::store::{CalibrationId, CalibrationRow, JobFile, JobId};

/// Largest OpenPTV text file accepted (bytes).
const MAX_TEXT_PART: usize = 1 << 20;
/// Most projections (points x cameras) in one projection request: each is
/// at most about 45 bytes of JSON (`[-1234.5678901234567,...],`), so the
/// answer stays under 10 MB, and 24 bytes in memory before it is written.
pub const MAX_PROJECTIONS: usize = 200_000;
/// Most points in one projection request whatever the cameras (a
/// calibration has at least 2): refused while the body is parsed, before
/// more are read into memory.
const MAX_POINTS: usize = MAX_PROJECTIONS / 2;

/// Deserializes `points`, refusing more than [`MAX_POINTS`] as soon as the
/// parser reaches one more.
fn bounded_points<'de, D>(deserializer: D) -> Result<Vec<[f64; 3]>, D::Error>
where
    D: serde::Deserializer<'de>,
{
    struct Points;
    impl<'de> serde::de::Visitor<'de> for Points {
        type Value = Vec<[f64; 3]>;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "at most {MAX_POINTS} points [x, y, z]")
        }
        fn visit_seq<A: serde::de::SeqAccess<'de>>(
            self,
            mut seq: A,
        ) -> Result<Self::Value, A::Error> {
            let mut points = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(4096));
            while let Some(point) = seq.next_element()? {
                if points.len() == MAX_POINTS {
                    return Err(serde::de::Error::custom(format!(
                        "more than {MAX_POINTS} points; at most {MAX_PROJECTIONS} projections \
                         (points x cameras) per request"
                    )));
                }
                points.push(point);
            }
            Ok(points)
        }
    }
    deserializer.deserialize_seq(Points)
}

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/calibrations", post(create).get(list))
        .route("/calibrations/openptv", post(create_openptv))
        .route("/calibrations/solve", post(solve))
        .route("/calibrations/{id}", get(read))
        .route("/calibrations/{id}/openptv/{file}", get(openptv_file))
        .route("/calibrations/{id}/project", post(project))
        .route("/calibrations/{id}/intersect", post(intersect_points))
}

/// A stored calibration.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationView {
    /// Its id.
    #[schema(value_type = i64)]
    pub id: CalibrationId,
    /// How many cameras.
    pub cameras: i64,
    /// The calibration JSON (see `src/formats/calibration.rs`).
    #[schema(value_type = Object)]
    pub model: serde_json::Value,
    /// The report: the resection's if the calibration was solved, the
    /// self-calibration's if it was refined from a sequence's particles.
    #[schema(value_type = Option<Object>)]
    pub report: Option<serde_json::Value>,
    /// The calibration this one was refined from by self-calibration
    /// (`POST /sequences/{id}/self-calibration`), if any.
    #[schema(value_type = Option<i64>)]
    pub origin_calibration: Option<CalibrationId>,
    /// When it was stored (UTC).
    pub created_at: String,
}

impl CalibrationView {
    fn of(row: CalibrationRow) -> Result<CalibrationView, ApiError> {
        Ok(CalibrationView {
            id: row.id,
            cameras: row.cameras,
            model: serde_json::from_str(&row.model)?,
            report: row
                .report
                .as_deref()
                .map(serde_json::from_str)
                .transpose()?,
            origin_calibration: row.origin,
            created_at: row.created_at,
        })
    }
}

/// A calibration in the list.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationSummaryView {
    /// Its id.
    #[schema(value_type = i64)]
    pub id: CalibrationId,
    /// How many cameras.
    pub cameras: i64,
    /// Whether it has a report (solved, or self-calibrated).
    pub has_report: bool,
    /// The calibration it was refined from, if any.
    #[schema(value_type = Option<i64>)]
    pub origin_calibration: Option<CalibrationId>,
    /// When it was stored (UTC).
    pub created_at: String,
    /// Where it is.
    pub link: String,
}

/// A page of calibrations, newest first.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationList {
    /// The calibrations.
    pub items: Vec<CalibrationSummaryView>,
    /// The next page (older ones), if there may be more.
    pub next: Option<String>,
}

/// The calibrations, newest first, a page at a time (without their models
/// and reports: `GET /calibrations/{id}` has those).
#[utoipa::path(
    get, path = "/api/v1/calibrations", tag = "calibrations",
    params(super::PageQuery),
    responses(
        (status = 200, body = CalibrationList),
        (status = 400, description = "A bad query", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn list(
    State(state): Shared,
    ApiQuery(query): ApiQuery<super::PageQuery>,
) -> Result<Json<CalibrationList>, ApiError> {
    let limit = query.limit()?;
    let rows = state
        .store
        .calibrations_page(query.before.map(CalibrationId), limit)
        .await?;
    let next = (rows.len() == limit as usize)
        .then(|| rows.last().map(|r| query.next("/calibrations", r.id.0)))
        .flatten();
    Ok(Json(CalibrationList {
        items: rows
            .into_iter()
            .map(|r| CalibrationSummaryView {
                id: r.id,
                cameras: r.cameras,
                has_report: r.has_report,
                origin_calibration: r.origin,
                created_at: r.created_at,
                link: links::calibration(r.id),
            })
            .collect(),
        next,
    }))
}

/// Stores validated cameras (and their splitter, if they are views of one
/// sensor) and answers 201 with the calibration.
async fn store_cameras(
    state: &AppState,
    cameras: &[Camera],
    splitter: Option<Splitter>,
) -> Result<Response, ApiError> {
    let model = formats::calibration::to_json_with_splitter(cameras, splitter);
    let row = state
        .store
        .insert_calibration(&model, cameras.len() as i64, None)
        .await?;
    let location = links::calibration(row.id);
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, location)],
        Json(CalibrationView::of(row)?),
    )
        .into_response())
}

/// Creates a calibration from the calibration JSON.
#[utoipa::path(
    post, path = "/api/v1/calibrations", tag = "calibrations",
    request_body(content = Object, description = "The calibration JSON: {\"cameras\": [...]}, as `ptv calibration import-openptv` writes it", content_type = "application/json"),
    responses(
        (status = 201, description = "Stored", body = CalibrationView),
        (status = 400, description = "Not JSON", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "Not a valid calibration", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create(State(state): Shared, JsonText(text): JsonText) -> Result<Response, ApiError> {
    let (cameras, splitter) = formats::calibration::from_json_with_splitter(&text, "the body")?;
    store_cameras(&state, &cameras, splitter).await
}

/// Creates a calibration from OpenPTV's files: multipart with `ptv_par`,
/// then per camera in camera order an `ori` part, each optionally followed
/// by its `addpar` part.
#[utoipa::path(
    post, path = "/api/v1/calibrations/openptv", tag = "calibrations",
    request_body(content_type = "multipart/form-data", description = "Parts: `ptv_par`; per camera, in order, `ori` and optionally `addpar` right after it."),
    responses(
        (status = 201, description = "Stored", body = CalibrationView),
        (status = 400, description = "Malformed multipart or unknown part", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "The files do not describe valid cameras", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn create_openptv(
    State(state): Shared,
    ApiMultipart(mut multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    let mut ptv_par = None;
    let mut cameras: Vec<OriTexts> = Vec::new();
    while let Some(mut field) = multipart.next_field().await? {
        let name = field.name().unwrap_or("").to_owned();
        match name.as_str() {
            "ptv_par" => ptv_par = Some(text_part(&mut field, &name, MAX_TEXT_PART).await?),
            "ori" => {
                let index = cameras.len();
                cameras.push(OriTexts {
                    name: format!("cam{}", index + 1),
                    ori: (
                        text_part(&mut field, &name, MAX_TEXT_PART).await?,
                        format!("ori part {}", index + 1),
                    ),
                    addpar: None,
                });
            }
            "addpar" => {
                let text = text_part(&mut field, &name, MAX_TEXT_PART).await?;
                let index = cameras.len();
                match cameras.last_mut() {
                    Some(camera) if camera.addpar.is_none() => {
                        camera.addpar = Some((text, format!("addpar part {index}")));
                    }
                    _ => {
                        return Err(ApiError::bad_request(
                            "an `addpar` part must follow its camera's `ori` part, at most one per camera",
                        ))
                    }
                }
            }
            other => {
                return Err(ApiError::bad_request(format!(
                    "unknown part `{other}`; expected `ptv_par`, then `ori` (and optional `addpar`) per camera"
                )))
            }
        }
    }
    let ptv_par = ptv_par.ok_or_else(|| ApiError::bad_request("the `ptv_par` part is missing"))?;
    let cameras = formats::openptv::import_texts(&ptv_par, "ptv_par part", &cameras)?;
    store_cameras(&state, &cameras, None).await
}

/// A stored calibration, or a 404.
pub(super) async fn calibration(
    state: &AppState,
    id: CalibrationId,
) -> Result<CalibrationRow, ApiError> {
    state
        .store
        .calibration(id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("calibration {id} does not exist")))
}

/// The calibration's cameras, from the store.
async fn cameras_of(state: &AppState, id: CalibrationId) -> Result<Vec<Camera>, ApiError> {
    let row = calibration(state, id).await?;
    stored_cameras(&row)
}

/// A stored calibration's cameras (a model that does not read is the
/// service's failure, a 500).
pub(super) fn stored_cameras(row: &CalibrationRow) -> Result<Vec<Camera>, ApiError> {
    Ok(stored_rig(row)?.0)
}

/// A stored calibration's cameras and splitter.
pub(super) fn stored_rig(
    row: &CalibrationRow,
) -> Result<(Vec<Camera>, Option<Splitter>), ApiError> {
    formats::calibration::stored_from_json_with_splitter(&row.model, "the stored calibration")
        .map_err(ApiError::internal)
}

/// A calibration: its model and, if solved, its report.
#[utoipa::path(
    get, path = "/api/v1/calibrations/{id}", tag = "calibrations",
    params(("id" = i64, Path, description = "Calibration id")),
    responses(
        (status = 200, body = CalibrationView),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn read(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
) -> Result<Json<CalibrationView>, ApiError> {
    Ok(Json(CalibrationView::of(calibration(&state, id).await?)?))
}

/// One camera's OpenPTV file: `{camera}.ori` or `{camera}.addpar`, camera
/// from 0.
#[utoipa::path(
    get, path = "/api/v1/calibrations/{id}/openptv/{file}", tag = "calibrations",
    params(
        ("id" = i64, Path, description = "Calibration id"),
        ("file" = String, Path, description = "`{camera}.ori` or `{camera}.addpar`, camera from 0"),
    ),
    responses(
        (status = 200, content_type = "text/plain", body = String),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn openptv_file(
    State(state): Shared,
    ApiPath((id, file)): ApiPath<(CalibrationId, String)>,
) -> Result<Response, ApiError> {
    let cameras = cameras_of(&state, id).await?;
    let unknown = || {
        ApiError::not_found(format!(
            "no file `{file}`; ask for `C.ori` or `C.addpar` with C a camera from 0 to {}",
            cameras.len() - 1
        ))
    };
    let (stem, extension) = file.rsplit_once('.').ok_or_else(unknown)?;
    let camera = super::decimal::parse::<usize>(stem)
        .ok()
        .and_then(|c| cameras.get(c))
        .ok_or_else(unknown)?;
    let text = match extension {
        "ori" => formats::openptv::format_ori(camera),
        "addpar" => formats::openptv::format_addpar(&camera.parameters().distortion),
        _ => return Err(unknown()),
    };
    Ok(([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response())
}

/// Points to project.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ProjectRequest {
    /// 3D points (mm); at most 200,000 projections (points x cameras).
    #[serde(deserialize_with = "bounded_points")]
    pub points: Vec<[f64; 3]>,
}

/// Their images.
#[derive(Debug, Serialize, ToSchema)]
pub struct ProjectResponse {
    /// Per point, per camera: the image position (px), or null where the
    /// camera cannot see it.
    pub pixels: Vec<Vec<Option<[f64; 2]>>>,
}

/// Projects 3D points into every camera (the collinearity equations
/// through the walls).
#[utoipa::path(
    post, path = "/api/v1/calibrations/{id}/project", tag = "calibrations",
    params(("id" = i64, Path, description = "Calibration id")),
    request_body = ProjectRequest,
    responses(
        (status = 200, body = ProjectResponse),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn project(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
    ApiJson(request): ApiJson<ProjectRequest>,
) -> Result<Json<ProjectResponse>, ApiError> {
    if let Some(i) = request
        .points
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(ApiError::unprocessable(format!(
            "points[{i}] is not finite"
        )));
    }
    let cameras = cameras_of(&state, id).await?;
    let projections = request.points.len().saturating_mul(cameras.len());
    if projections > MAX_PROJECTIONS {
        return Err(ApiError::unprocessable(format!(
            "{} points x {} cameras = {projections} projections; at most {MAX_PROJECTIONS} \
             (points x cameras) per request, so that the answer stays under 10 MB: send at most \
             {} points per request to this calibration",
            request.points.len(),
            cameras.len(),
            MAX_PROJECTIONS / cameras.len().max(1)
        )));
    }
    // The work stops when this handler is dropped (its client gone, or
    // the request timeout).
    let cancel = Cancel::new();
    let _stop = StopOnDrop(cancel.clone());
    let pixels = state
        .cpu
        .run(move || {
            let mut pixels = Vec::with_capacity(request.points.len());
            for (i, p) in request.points.iter().enumerate() {
                if i % 1024 == 0 && cancel.check().is_err() {
                    return None;
                }
                let point = nalgebra::Point3::new(p[0], p[1], p[2]);
                pixels.push(
                    cameras
                        .iter()
                        .map(|camera| camera.project(&point).ok().map(|px| [px.x, px.y]))
                        .collect(),
                );
            }
            Some(pixels)
        })
        .await?
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the projection was stopped",
            )
        })?;
    Ok(Json(ProjectResponse { pixels }))
}

/// One point's images.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct IntersectRequest {
    /// Per camera, in camera order, the point's image (px) or null.
    pub pixels: Vec<Option<[f64; 2]>>,
}

/// The intersected point.
#[derive(Debug, Serialize, ToSchema)]
pub struct IntersectResponse {
    /// X, Y, Z (mm).
    pub point: [f64; 3],
    /// Standard deviations of X, Y, Z (mm).
    pub sigma: [f64; 3],
    /// Root mean square residual (px).
    pub rms_px: f64,
    /// Per observation given, its residual (px).
    pub residuals_px: Vec<[f64; 2]>,
}

/// Intersects one point's images into its 3D position with standard
/// deviations (least-squares spatial intersection).
#[utoipa::path(
    post, path = "/api/v1/calibrations/{id}/intersect", tag = "calibrations",
    params(("id" = i64, Path, description = "Calibration id")),
    request_body = IntersectRequest,
    responses(
        (status = 200, body = IntersectResponse),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn intersect_points(
    State(state): Shared,
    ApiPath(id): ApiPath<CalibrationId>,
    ApiJson(request): ApiJson<IntersectRequest>,
) -> Result<Json<IntersectResponse>, ApiError> {
    let cameras = cameras_of(&state, id).await?;
    if request.pixels.len() != cameras.len() {
        return Err(ApiError::unprocessable(format!(
            "`pixels` has {} entries but the calibration has {} cameras; give one per camera \
             (null where a camera does not see the point)",
            request.pixels.len(),
            cameras.len()
        )));
    }
    let observations: Vec<Observation> = request
        .pixels
        .iter()
        .enumerate()
        .filter_map(|(camera, p)| {
            p.map(|p| Observation {
                camera,
                pixel: Point2::new(p[0], p[1]),
            })
        })
        .collect();
    if observations
        .iter()
        .any(|o| !(o.pixel.x.is_finite() && o.pixel.y.is_finite()))
    {
        return Err(ApiError::unprocessable(
            "every pixel coordinate must be finite",
        ));
    }
    let result = intersect(&cameras, &observations)?;
    Ok(Json(IntersectResponse {
        point: [result.point.x, result.point.y, result.point.z],
        sigma: [result.sigma.x, result.sigma.y, result.sigma.z],
        rms_px: result.rms_px,
        residuals_px: result.residuals_px.iter().map(|r| [r.x, r.y]).collect(),
    }))
}

/// Largest `options` part (bytes).
const MAX_OPTIONS_PART: usize = 64 << 10;

/// An accepted calibration to solve.
#[derive(Debug, Serialize, ToSchema)]
pub struct SolveAccepted {
    /// The job that solves it.
    #[schema(value_type = i64)]
    pub job_id: JobId,
    /// Where to poll the job; once succeeded, its `result` is the
    /// calibration.
    pub job: String,
}

/// The parts of a solve request, as read: text parts whole (they are
/// parsed before the request is accepted), images in temporary files.
#[derive(Default)]
struct SolveParts {
    setup: Option<String>,
    control: Option<String>,
    options: Option<String>,
    observations: Vec<String>,
    references: Vec<String>,
    images: Vec<UploadedFile>,
}

async fn read_solve_parts(
    state: &AppState,
    multipart: &mut Multipart,
) -> Result<SolveParts, ApiError> {
    let mut parts = SolveParts::default();
    while let Some(mut field) = multipart.next_field().await? {
        let name = field.name().unwrap_or("").to_owned();
        let once = |slot: &Option<String>| {
            if slot.is_some() {
                Err(ApiError::bad_request(format!(
                    "part `{name}` is given twice; give it once"
                )))
            } else {
                Ok(())
            }
        };
        match name.as_str() {
            "setup" => {
                once(&parts.setup)?;
                parts.setup = Some(text_part(&mut field, &name, MAX_TEXT_PART).await?);
            }
            "control" => {
                once(&parts.control)?;
                parts.control = Some(text_part(&mut field, &name, MAX_TEXT_PART).await?);
            }
            "options" => {
                once(&parts.options)?;
                parts.options = Some(text_part(&mut field, &name, MAX_OPTIONS_PART).await?);
            }
            "observations" => parts
                .observations
                .push(text_part(&mut field, &name, MAX_TEXT_PART).await?),
            "reference" => parts
                .references
                .push(text_part(&mut field, &name, MAX_TEXT_PART).await?),
            "image" => parts
                .images
                .push(stream_part(&state.images, &mut field).await?),
            other => {
                return Err(ApiError::bad_request(format!(
                    "unknown part `{}`; expected `setup`, `control`, per camera `observations` \
                     or `image` (with optional `reference`), and optional `options`",
                    other.escape_debug()
                )))
            }
        }
    }
    Ok(parts)
}

/// Checks that `given` per-camera parts match the setup's cameras.
fn check_count(part: &str, given: usize, cameras: usize) -> Result<(), ApiError> {
    if given == cameras {
        return Ok(());
    }
    Err(ApiError::unprocessable(format!(
        "the setup has {cameras} cameras but {given} `{part}` parts were given; give one per \
         camera, in camera order"
    )))
}

/// A text part to keep: its name, camera (per-camera parts) and text.
type TextFile = (&'static str, Option<usize>, String);

/// A solve request's parts, checked: the text files to keep, the options,
/// and the cameras' sensors.
struct CheckedSolve {
    texts: Vec<TextFile>,
    options: SolveOptions,
    sensors: Vec<Sensor>,
}

/// Checks a solve request's parts (everything but the images' headers and
/// the resection itself).
fn check_solve_parts(parts: &SolveParts) -> Result<CheckedSolve, ApiError> {
    let setup_text = parts.setup.clone().ok_or_else(|| {
        ApiError::bad_request(
            "the `setup` part is missing: give the calibration JSON with sensor and media of \
             every camera",
        )
    })?;
    let control_text = parts.control.clone().ok_or_else(|| {
        ApiError::bad_request(
            "the `control` part is missing: give the control points, `id X Y Z` per line (mm)",
        )
    })?;
    let formats::calibration::Setup {
        cameras: setup,
        unknown,
    } = formats::calibration::setup_from_json(&setup_text, &part_source("setup", None))?;
    let n = setup.len();
    if n < formats::calibration::MIN_CAMERAS {
        return Err(ApiError::unprocessable(format!(
            "part `setup`: {n} cameras; a calibration needs at least {}",
            formats::calibration::MIN_CAMERAS
        )));
    }
    let control_points =
        control::parse_control_points(&control_text, &part_source("control", None))?;
    let options: SolveOptions = match &parts.options {
        None => SolveOptions::default(),
        Some(text) => parse_json(text).map_err(|e| e.at("part `options`"))?,
    };
    let calibration_options = calibrate::CalibrationOptions {
        unknown,
        ..options
            .calibration_options()
            .map_err(|e| ApiError::from(e).at("part `options`"))?
    };
    // What the core checks before any adjustment, with its messages.
    calibrate::check_inputs(&setup, &control_points, n, &calibration_options)?;

    let mut texts = vec![("setup", None, setup_text), ("control", None, control_text)];
    match (parts.observations.len(), parts.images.len()) {
        (0, 0) => {
            return Err(ApiError::unprocessable(format!(
                "give per camera, in camera order, an `observations` part (`id x y` per line, \
                 px) or an `image` part; the setup has {n} cameras"
            )))
        }
        (_, 0) => {
            check_count("observations", parts.observations.len(), n)?;
            if !parts.references.is_empty() {
                return Err(ApiError::bad_request(
                    "`reference` parts go with `image` parts, not with `observations`",
                ));
            }
            for (camera, text) in parts.observations.iter().enumerate() {
                control::parse_mark_observations(text, &part_source("observations", Some(camera)))?;
                texts.push(("observations", Some(camera), text.clone()));
            }
        }
        (0, _) => {
            check_count("image", parts.images.len(), n)?;
            if !parts.references.is_empty() {
                check_count("reference", parts.references.len(), n)?;
            }
            options
                .mark_detection()
                .map_err(|e| ApiError::from(e).at("part `options`: detection"))?;
            let mut counts = vec![0; n];
            for (camera, text) in parts.references.iter().enumerate() {
                counts[camera] = control::parse_mark_observations(
                    text,
                    &part_source("reference", Some(camera)),
                )?
                .len();
                texts.push(("reference", Some(camera), text.clone()));
            }
            // A camera without orientation needs reference points.
            calibrate::check_mark_inputs(&setup, &control_points, &counts, &calibration_options)?;
        }
        _ => {
            return Err(ApiError::bad_request(
                "give either `observations` or `image` parts, not both",
            ))
        }
    }
    Ok(CheckedSolve {
        texts,
        options,
        sensors: setup.iter().map(|camera| camera.sensor.clone()).collect(),
    })
}

/// Solves a calibration by resection on control points: multipart with
/// `setup` (the calibration JSON, schema `CalibrationDocument`: sensor
/// and media of every camera are required; the orientation, `position`,
/// `angles` and `principal_distance`, is optional: left out, the DLT on
/// the observed points starts the resection; with `image` parts, a camera
/// without orientation needs `reference` points), `control` (OpenPTV
/// calibration block, `id X Y Z` per line, mm), per camera in camera order
/// an `observations` part (`id x y` per line, px) or an `image` part (with
/// optional `reference` parts, `id x y` of 4..6 identified marks), and an
/// optional `options` part (JSON: `ptv calibrate`'s flags). Answers 202
/// with the job; once it succeeds, its `result` is the calibration, stored
/// with its report.
#[utoipa::path(
    post, path = "/api/v1/calibrations/solve", tag = "calibrations",
    request_body(content_type = "multipart/form-data", description = "Parts: `setup` (calibration JSON, schema CalibrationDocument: sensor and media required, orientation optional), `control` (`id X Y Z` per line, mm); per camera in camera order `observations` (`id x y` per line, px) or `image` (PNG/TIFF greyscale, with optional `reference` parts: `id x y` of identified marks); optional `options` (JSON, see SolveOptions)."),
    responses(
        (status = 202, body = SolveAccepted),
        (status = 400, description = "Malformed multipart, a missing, unknown or repeated part", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 413, description = "Larger than --max-upload-mb or a text part above 1 MiB", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 415, description = "Not multipart, or an image that does not decode as greyscale PNG/TIFF (unknown, BigTIFF, colour, truncated, corrupt)", body = super::problem::Problem, content_type = "application/problem+json"),
        (status = 422, description = "A file that does not parse (a setup camera without sensor or media), part counts that do not match the setup's cameras, invalid options, a fixed parameter the setup gives no value for, images of a camera with neither orientation nor reference points", body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn solve(
    State(state): Shared,
    ApiMultipart(mut multipart): ApiMultipart,
) -> Result<Response, ApiError> {
    let parts = read_solve_parts(&state, &mut multipart).await;
    let parts = or_drain(parts, &mut multipart).await?;
    let CheckedSolve {
        texts,
        options,
        sensors,
    } = check_solve_parts(&parts)?;
    let images = parts.images;
    if !images.is_empty() {
        check_images(&images, &sensors, None, |camera| {
            part_source("image", Some(camera))
        })
        .await?;
    }

    // Every file goes to the store; text parts become files too.
    let mut uploads: Vec<(&'static str, Option<usize>, UploadedFile)> = Vec::new();
    for (part, camera, text) in texts {
        let mut upload = state.images.create_upload().await?;
        upload.write(text.as_bytes()).await?;
        uploads.push((part, camera, upload.finish().await?));
    }
    for (camera, file) in images.into_iter().enumerate() {
        uploads.push(("image", Some(camera), file));
    }
    let (files, uploads): (Vec<JobFile>, Vec<UploadedFile>) = uploads
        .into_iter()
        .map(|(part, camera, file)| {
            let row = JobFile {
                part: part.to_owned(),
                camera: camera.map(|c| c as i64),
                sha256: file.sha256.clone(),
                size: file.size as i64,
            };
            (row, file)
        })
        .unzip();
    let payload = serde_json::to_string(&SolvePayload { options })?;
    let job_id = persist_and_commit(&state, uploads, || {
        state
            .store
            .enqueue_with_files(SOLVE_CALIBRATION, &payload, &files)
    })
    .await?;
    let body = SolveAccepted {
        job_id,
        job: links::job(job_id),
    };
    Ok(accepted(&state, job_id, body))
}
