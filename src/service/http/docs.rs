//! The OpenAPI document, generated from the handlers' annotations (and
//! committed as `openapi/openapi.json`), and the interactive docs page at
//! `/docs`: Swagger UI, vendored into the binary, so it works offline.

use std::sync::Arc;

use axum::Router;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi};
use utoipa_swagger_ui::SwaggerUi;

use super::{
    calibration_health, calibrations, events, experiments, frames, jobs, plots, problem, results,
    selfcal, sequence_images, sequences, tracking,
};
use crate::service::model::parameters;
use crate::service::ops::state::AppState;

/// The API's description.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "ptv",
        description = "3D particle tracking velocimetry: calibrations, frame uploads processed by a durable job queue, particles.",
        license(name = "MIT OR Apache-2.0"),
    ),
    paths(
        calibrations::list,
        calibrations::create,
        calibrations::create_openptv,
        calibrations::solve,
        calibrations::read,
        calibrations::openptv_file,
        calibrations::project,
        calibrations::intersect_points,
        sequences::list,
        sequences::create,
        sequences::read,
        frames::upload_frame,
        frames::frames,
        calibration_health::read,
        events::events,
        sequence_images::upload_background,
        sequence_images::upload_mask,
        experiments::import,
        results::frame_particles,
        results::frame_targets,
        results::all_particles,
        tracking::start,
        tracking::runs,
        tracking::finish,
        tracking::trajectories,
        tracking::trajectory,
        selfcal::self_calibrate,
        selfcal::reprocess,
        selfcal::report,
        plots::residuals,
        plots::disparity,
        plots::overlay,
        plots::particles,
        plots::trajectories,
        plots::kept_image,
        plots::calibration_health,
        jobs::read,
        jobs::retry,
        super::health::healthz,
        super::health::readyz,
        super::health::metrics,
    ),
    components(schemas(
        problem::Problem,
        crate::service::ops::events::SequenceEvent,
        crate::service::ops::events::Change,
        events::Snapshot,
        events::Lagged,
        parameters::DetectionSettings,
        parameters::MatchingSettings,
        parameters::SequenceParameters,
        parameters::ComputedBackground,
        parameters::HealthSettings,
        parameters::SolveOptions,
        crate::service::ops::selfcal::SelfCalibrationRequest,
        crate::service::ops::selfcal::FrameSpan,
        crate::service::model::tracking_settings::TrackingSettings,
        crate::formats::calibration::CalibrationFile,
        crate::formats::calibration::CameraJson,
        crate::formats::calibration::MediaJson,
        crate::formats::calibration::WallJson,
    )),
    modifiers(&BearerToken),
    security(("bearer" = [])),
)]
pub struct ApiDoc;

/// Declares the bearer token (`--api-token`).
struct BearerToken;

impl Modify for BearerToken {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// The document as pretty JSON with a final newline.
pub fn openapi_json() -> String {
    let mut text = ApiDoc::openapi()
        .to_pretty_json()
        .expect("the OpenAPI document serialises");
    text.push('\n');
    text
}

/// `/openapi.json` and `/docs`.
pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new().merge(SwaggerUi::new("/docs").url("/openapi.json", ApiDoc::openapi()))
}
