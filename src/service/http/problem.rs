//! The API's one error type, rendered as RFC 9457 `application/problem+json`
//! with a title and a detail that says what to fix; and the extractors
//! whose rejections use it.
//!
//! Database and other internal errors are logged and answered as a 500
//! without their details; everything a caller can cause is a 4xx. A full
//! disk, the database's (SQLITE_FULL) or the image store's (ENOSPC), is a
//! 507 with `Retry-After`: nothing is stored, and the same request may
//! succeed once space is freed, without a restart. An object store that
//! cannot be reached is a 503 with `Retry-After`. The
//! status follows from the error's type (the `From` impls below, as
//! realworld-axum-sqlx maps its errors), so handlers use `?`.

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, PathRejection, QueryRejection};
use axum::extract::{
    FromRequest, FromRequestParts, Multipart, Path, Query, RawPathParams, Request,
};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;
use serde::Serialize;
use utoipa::ToSchema;

use crate::formats::control::OptionError;
use crate::formats::FormatError;
use crate::photogrammetry::calibrate::CalibrationError;
use crate::photogrammetry::{
    IntersectionError, InvalidDetectionParameters, PipelineError, SensorMismatch,
};
use crate::service::infra::codec::DamagedBlob;
use crate::service::infra::errors::error_chain;
use crate::service::ops::images;
use crate::service::ops::jobs::pipelines::PrepareError;
use crate::service::ops::jobs::pool::CpuError;
use crate::service::store::{self, InsertFrameError};

/// An RFC 9457 problem document.
#[derive(Debug, Serialize, ToSchema)]
pub struct Problem {
    /// Always `about:blank`: the status says the kind.
    #[serde(rename = "type")]
    pub kind: String,
    /// The status' phrase.
    pub title: String,
    /// The HTTP status.
    pub status: u16,
    /// What went wrong and what to do about it.
    pub detail: String,
}

/// An error answered to the caller.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    detail: String,
    /// Seconds for `Retry-After`, if the request may succeed later.
    retry_after: Option<u32>,
}

/// `Retry-After` of a 507: how long a client should wait before trying
/// again once the service's disk was full.
pub const STORAGE_FULL_RETRY_AFTER_S: u32 = 30;

/// `Retry-After` of a 503 for a database or object store that cannot be
/// reached: a restarting PostgreSQL or S3 server is usually back within
/// seconds.
pub const UNAVAILABLE_RETRY_AFTER_S: u32 = 5;

impl ApiError {
    /// An error of `status` with `detail`.
    pub fn new(status: StatusCode, detail: impl Into<String>) -> ApiError {
        ApiError {
            status,
            detail: detail.into(),
            retry_after: None,
        }
    }
    /// 400: the request is malformed.
    pub fn bad_request(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::BAD_REQUEST, detail)
    }
    /// 404.
    pub fn not_found(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::NOT_FOUND, detail)
    }
    /// 409.
    pub fn conflict(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::CONFLICT, detail)
    }
    /// 413.
    pub fn too_large(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, detail)
    }
    /// 415.
    pub fn unsupported(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, detail)
    }
    /// 422: well-formed, but the values do not work.
    pub fn unprocessable(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, detail)
    }
    /// 500: logged here, not detailed to the caller.
    pub fn internal(error: impl std::fmt::Display) -> ApiError {
        tracing::error!(%error, "internal error");
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the service failed; the error is in its log",
        )
    }
    /// 507: the disk is full; logged, answered with `Retry-After`.
    pub fn storage_full(error: impl std::fmt::Display) -> ApiError {
        tracing::error!(%error, "storage full");
        ApiError {
            retry_after: Some(STORAGE_FULL_RETRY_AFTER_S),
            ..ApiError::new(
                StatusCode::INSUFFICIENT_STORAGE,
                "the service's disk is full; nothing was stored. Try again later \
                 (Retry-After); the service recovers by itself once space is freed",
            )
        }
    }
    /// 503: `backend` (the database, the object store) cannot be reached
    /// for now; logged, answered with `Retry-After`.
    pub fn unavailable(backend: &str, error: impl std::fmt::Display) -> ApiError {
        tracing::error!(%error, backend, "unavailable");
        ApiError {
            retry_after: Some(UNAVAILABLE_RETRY_AFTER_S),
            ..ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!(
                    "the service's {backend} cannot be reached for now; nothing was stored. \
                     Try again later (Retry-After)"
                ),
            )
        }
    }
    /// The status.
    pub fn status(&self) -> StatusCode {
        self.status
    }
    /// The same error, its detail prefixed with where in the request it
    /// lies (`part `options``).
    pub fn at(self, place: &str) -> ApiError {
        ApiError {
            detail: format!("{place}: {}", self.detail),
            ..self
        }
    }
}

/// `From` impls for errors that always mean one status: `$make(error)`.
macro_rules! status_of {
    ($make:expr => $($error:ty),+ $(,)?) => {
        $(impl From<$error> for ApiError {
            fn from(error: $error) -> Self {
                $make(error)
            }
        })+
    };
}

// The service's own failures: logged, a 500. JSON errors here are the
// service's own documents (stored rows, payloads); request bodies are read
// by `parse_json`.
status_of!(ApiError::internal =>
    serde_json::Error,
    tokio::task::JoinError,
    CpuError,
    DamagedBlob,
);

// The core's refusals of the values a caller gave: a 422 with the reason
// and its causes.
status_of!(|error| ApiError::unprocessable(error_chain(&error)) =>
    IntersectionError,
    CalibrationError,
    PipelineError,
    OptionError,
    InvalidDetectionParameters,
    SensorMismatch,
);

impl From<crate::service::ops::selfcal::SelfCalibrationRequestError> for ApiError {
    /// Options, frames or a calibration that do not work for a
    /// self-calibration or reprocessing: a 422 with the reason.
    fn from(error: crate::service::ops::selfcal::SelfCalibrationRequestError) -> Self {
        ApiError::unprocessable(error_chain(&error))
    }
}

impl From<crate::service::model::tracking_settings::InvalidTrackingSettings> for ApiError {
    /// Tracking settings the tracker refuses (a velocity limit that is not
    /// positive, ...): a 422 naming the field and its range.
    fn from(error: crate::service::model::tracking_settings::InvalidTrackingSettings) -> Self {
        ApiError::unprocessable(error_chain(&error))
    }
}

impl From<crate::plot::PlotError> for ApiError {
    /// A picture of something that lacks what it needs (a report of the
    /// other kind, ...) is a 409 saying what; a camera that does not exist
    /// a 404; a picture too large to draw a 422; a stored report that does
    /// not read, or the encoder's failure, the service's (500).
    fn from(error: crate::plot::PlotError) -> Self {
        use crate::plot::PlotError;
        match error {
            PlotError::Missing(_) => ApiError::conflict(error.to_string()),
            PlotError::Camera { .. } => ApiError::not_found(error.to_string()),
            PlotError::TooLarge { .. } | PlotError::Disparity(_) | PlotError::Extension(_) => {
                ApiError::unprocessable(error.to_string())
            }
            PlotError::Input { .. } | PlotError::Encode(_) => ApiError::internal(error),
        }
    }
}

impl From<crate::service::ops::health::HealthError> for ApiError {
    fn from(error: crate::service::ops::health::HealthError) -> Self {
        use crate::service::ops::health::HealthError;
        match error {
            HealthError::Database(error) => error.into(),
            HealthError::NoSequence(_) => ApiError::not_found(error.to_string()),
            HealthError::Stored(..) => ApiError::internal(error),
        }
    }
}

impl From<store::StoreError> for ApiError {
    /// A full disk is a 507, a database that cannot be reached a 503 (both
    /// with `Retry-After`); any other database error a 500.
    fn from(error: store::StoreError) -> Self {
        match error.kind() {
            store::ErrorKind::StorageFull => ApiError::storage_full(error),
            store::ErrorKind::Unavailable => ApiError::unavailable("database", error),
            store::ErrorKind::Other => ApiError::internal(error),
        }
    }
}

impl From<std::io::Error> for ApiError {
    /// A full disk (ENOSPC) is a 507; any other I/O error a 500.
    fn from(error: std::io::Error) -> Self {
        if crate::service::infra::errors::is_storage_full(&error) {
            ApiError::storage_full(error)
        } else {
            ApiError::internal(error)
        }
    }
}

impl From<images::ImageStoreError> for ApiError {
    /// A full local disk is a 507 and an object store out of reach a 503,
    /// both with `Retry-After`; an image missing that a row refers to,
    /// and anything else, a 500 (logged with what is missing).
    fn from(error: images::ImageStoreError) -> Self {
        match error {
            images::ImageStoreError::Io(error) => error.into(),
            images::ImageStoreError::Unavailable(_) => ApiError::unavailable("object store", error),
            images::ImageStoreError::Missing { .. } => ApiError::internal(format!(
                "{error}, although a committed row refers to it: the store lost it"
            )),
            images::ImageStoreError::Other(_) => ApiError::internal(error),
        }
    }
}

impl From<FormatError> for ApiError {
    /// A file the caller gave that does not parse is a 422, an image of a
    /// kind this service does not open a 415; a file the service could not
    /// read itself is a 500.
    fn from(error: FormatError) -> Self {
        match error {
            FormatError::Io { .. } => ApiError::internal(error),
            FormatError::UnsupportedImage { .. } => ApiError::unsupported(error.to_string()),
            FormatError::Invalid { .. } => ApiError::unprocessable(error.to_string()),
        }
    }
}

impl From<PrepareError> for ApiError {
    /// Parameters that do not work with the calibration are a 422; a stored
    /// calibration that does not read, or work that did not finish, a 500.
    fn from(error: PrepareError) -> Self {
        match error {
            PrepareError::Pipeline(error) => error.into(),
            PrepareError::Calibration(_) | PrepareError::Cpu(_) => ApiError::internal(error),
        }
    }
}

impl From<InsertFrameError> for ApiError {
    /// A frame uploaded twice is a 409.
    fn from(error: InsertFrameError) -> Self {
        match error {
            InsertFrameError::Exists { .. } => {
                ApiError::conflict(format!("{error}; frames are uploaded once"))
            }
            InsertFrameError::Database(error) => error.into(),
        }
    }
}

impl From<axum::extract::multipart::MultipartError> for ApiError {
    fn from(error: axum::extract::multipart::MultipartError) -> Self {
        multipart_error(error)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let problem = Problem {
            kind: "about:blank".to_owned(),
            title: self.status.canonical_reason().unwrap_or("Error").to_owned(),
            status: self.status.as_u16(),
            detail: self.detail,
        };
        let body = serde_json::to_vec(&problem).unwrap_or_default();
        let mut response = (
            self.status,
            [(header::CONTENT_TYPE, "application/problem+json")],
            body,
        )
            .into_response();
        if let Some(seconds) = self.retry_after {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, seconds.into());
        }
        response
    }
}

/// A JSON body, parsed with the path of any error: syntax errors are 400,
/// values of the wrong shape 422, a body that is not JSON 415.
pub struct ApiJson<T>(pub T);

/// The request body as UTF-8 text, after checking that it is declared as
/// JSON (or not declared at all).
pub struct JsonText(pub String);

fn check_json_content_type(headers: &HeaderMap) -> Result<(), ApiError> {
    let Some(value) = headers.get(header::CONTENT_TYPE) else {
        return Ok(());
    };
    let text = value.to_str().unwrap_or("");
    let essence = text.split(';').next().unwrap_or("").trim();
    if essence.eq_ignore_ascii_case("application/json") || essence.ends_with("+json") {
        Ok(())
    } else {
        Err(ApiError::unsupported(format!(
            "the body is `{text}`; send JSON with Content-Type: application/json"
        )))
    }
}

/// The body's bytes, within the body limit.
async fn body_bytes<S: Send + Sync>(req: Request, state: &S) -> Result<Bytes, ApiError> {
    Bytes::from_request(req, state)
        .await
        .map_err(|rejection: BytesRejection| {
            let status = rejection.status();
            if status == StatusCode::PAYLOAD_TOO_LARGE {
                ApiError::too_large("the body is larger than the service's limit (--max-upload-mb)")
            } else {
                ApiError::new(status, rejection.body_text())
            }
        })
}

impl<S: Send + Sync> FromRequest<S> for JsonText {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        check_json_content_type(req.headers())?;
        let bytes = body_bytes(req, state).await?;
        let text = String::from_utf8(bytes.to_vec())
            .map_err(|_| ApiError::bad_request("the body is not UTF-8 text"))?;
        // Syntax first, so that a broken document is a 400 whatever its content.
        serde_json::from_str::<serde::de::IgnoredAny>(&text)
            .map_err(|e| ApiError::bad_request(format!("the body is not valid JSON: {e}")))?;
        Ok(JsonText(text))
    }
}

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let JsonText(text) = JsonText::from_request(req, state).await?;
        parse_json(&text).map(ApiJson)
    }
}

/// A JSON document as `T`: a value of the wrong shape is a 422 that names
/// its path (`fix: unknown parameter ...`).
pub fn parse_json<T: DeserializeOwned>(text: &str) -> Result<T, ApiError> {
    let deserializer = &mut serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize(deserializer).map_err(|e| {
        let path = e.path().to_string();
        let location = if path == "." {
            String::new()
        } else {
            format!("{path}: ")
        };
        ApiError::unprocessable(format!("{location}{}", e.into_inner()))
    })
}

/// Path parameters; malformed ones are 400 problems.
pub struct ApiPath<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned + Send> FromRequestParts<S> for ApiPath<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        // Integer segments in the one accepted form (`super::decimal`):
        // `/frames/+5` or `/frames/05` is not frame 5.
        if let Ok(raw) = RawPathParams::from_request_parts(parts, state).await {
            super::decimal::check_pairs("path segment", raw.iter())
                .map_err(ApiError::bad_request)?;
        }
        Path::<T>::from_request_parts(parts, state)
            .await
            .map(|Path(value)| ApiPath(value))
            .map_err(|rejection: PathRejection| ApiError::bad_request(rejection.body_text()))
    }
}

/// Query parameters; malformed ones are 400 problems.
pub struct ApiQuery<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned + Send> FromRequestParts<S> for ApiQuery<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        // Integer values in the one accepted form (`super::decimal`).
        if let Ok(Query(pairs)) = Query::<Vec<(String, String)>>::try_from_uri(&parts.uri) {
            super::decimal::check_pairs(
                "query parameter",
                pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())),
            )
            .map_err(ApiError::bad_request)?;
        }
        Query::<T>::from_request_parts(parts, state)
            .await
            .map(|Query(value)| ApiQuery(value))
            .map_err(|rejection: QueryRejection| ApiError::bad_request(rejection.body_text()))
    }
}

/// A multipart/form-data body; anything else is 415.
pub struct ApiMultipart(pub Multipart);

impl<S: Send + Sync> FromRequest<S> for ApiMultipart {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let content_type = req
            .headers()
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_owned();
        if !content_type
            .to_ascii_lowercase()
            .starts_with("multipart/form-data")
        {
            return Err(ApiError::unsupported(format!(
                "the body is `{content_type}`; send multipart/form-data"
            )));
        }
        Multipart::from_request(req, state)
            .await
            .map(ApiMultipart)
            .map_err(|rejection| ApiError::bad_request(rejection.body_text()))
    }
}

/// A multipart error while reading parts: 413 past the body limit, else 400.
pub fn multipart_error(error: axum::extract::multipart::MultipartError) -> ApiError {
    let status = error.status();
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::too_large("the upload is larger than the service's limit (--max-upload-mb)")
    } else {
        ApiError::new(
            status,
            format!(
                "the multipart body is malformed or truncated: {}",
                error.body_text()
            ),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_disk_is_a_507_with_retry_after() {
        for error in [
            ApiError::from(std::io::Error::from_raw_os_error(28)),
            ApiError::from(store::StoreError::from(std::io::Error::from_raw_os_error(
                28,
            ))),
        ] {
            let response = error.into_response();
            assert_eq!(response.status(), StatusCode::INSUFFICIENT_STORAGE);
            assert_eq!(response.headers()[header::RETRY_AFTER], "30");
            assert_eq!(
                response.headers()[header::CONTENT_TYPE],
                "application/problem+json"
            );
        }
        let other = ApiError::from(std::io::Error::from_raw_os_error(13)).into_response();
        assert_eq!(other.status(), StatusCode::INTERNAL_SERVER_ERROR);
        assert!(other.headers().get(header::RETRY_AFTER).is_none());
    }
}
