//! The lab web page at `/`: plain HTML, CSS and JavaScript under
//! `src/service/web/`, compiled into the binary (no CDN, no build step, no
//! download at install time: lab networks are often offline). It reads the
//! API like any client (see `app.js`): lists, a calibration's parameters
//! with their sigmas and its plots, a sequence's frame counts with live
//! progress from its event stream, a frame viewer (targets, reprojections,
//! the overlay image, zoom, camera switch) and a rotatable 3D view of a
//! frame's particles and trajectories.
//!
//! The page and its assets lie outside `/api`, so they load without the
//! API token; the page asks for the token when the API answers 401 and
//! keeps it in the tab's `sessionStorage`.
//!
//! Caching: the assets' URLs carry their content's hash (`?v=`), so they
//! are cached for a year (`immutable`) and a new binary's page loads its
//! own; the HTML is revalidated every time (`no-cache`, with an `ETag`).
//! A `Content-Security-Policy` lets the page load only its own scripts,
//! styles and API (images also from `blob:`, where the page puts the
//! plots it fetched with the token). The page puts every value it gets
//! into the document as text, never as HTML, so a sequence's name cannot
//! inject markup.

use std::sync::{Arc, OnceLock};

use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use sha2::{Digest, Sha256};

use super::problem::ApiError;
use crate::service::ops::state::AppState;

/// A file of the page.
#[derive(Debug)]
pub struct Asset {
    /// Its name under `/ui/`.
    pub name: &'static str,
    /// Its content type.
    pub content_type: &'static str,
    /// Its bytes.
    pub bytes: &'static [u8],
}

/// The page's scripts and styles, served under `/ui/`.
pub const ASSETS: [Asset; 2] = [
    Asset {
        name: "app.js",
        content_type: "text/javascript; charset=utf-8",
        bytes: include_bytes!("../web/app.js"),
    },
    Asset {
        name: "app.css",
        content_type: "text/css; charset=utf-8",
        bytes: include_bytes!("../web/app.css"),
    },
];

/// The HTML, with `{{app.js}}` and `{{app.css}}` where the assets' URLs go.
const INDEX: &str = include_str!("../web/index.html");

/// The page's policy: its own origin only.
const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; \
     style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; \
     form-action 'none'; frame-ancestors 'none'";

/// A content's hash as an ETag and URL version: 16 hex digits of SHA-256.
fn version(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .take(8)
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The HTML with the assets' versioned URLs, and its ETag.
fn index() -> &'static (String, String) {
    static INDEX_PAGE: OnceLock<(String, String)> = OnceLock::new();
    INDEX_PAGE.get_or_init(|| {
        let mut html = INDEX.to_owned();
        for asset in &ASSETS {
            let url = format!("/ui/{}?v={}", asset.name, version(asset.bytes));
            html = html.replace(&format!("{{{{{}}}}}", asset.name), &url);
        }
        let etag = format!("\"{}\"", version(html.as_bytes()));
        (html, etag)
    })
}

/// The page's total size in bytes: the HTML and every asset, as served
/// (before gzip).
pub fn page_weight() -> usize {
    index().0.len() + ASSETS.iter().map(|a| a.bytes.len()).sum::<usize>()
}

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/", get(page))
        .route("/ui/{file}", get(asset))
}

/// Whether the request's `If-None-Match` names `etag`.
fn fresh(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == etag || t.trim() == "*"))
}

/// The answer with `body`, or 304 when the client has it.
fn answer(
    headers: &HeaderMap,
    etag: &str,
    content_type: &'static str,
    cache: &'static str,
    body: &'static [u8],
) -> Response {
    let mut response = if fresh(headers, etag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, content_type)], body).into_response()
    };
    let fields = response.headers_mut();
    fields.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    if let Ok(value) = HeaderValue::from_str(etag) {
        fields.insert(header::ETAG, value);
    }
    fields.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    response
}

/// The page.
async fn page(headers: HeaderMap) -> Response {
    let (html, etag) = index();
    let mut response = answer(
        &headers,
        etag,
        "text/html; charset=utf-8",
        "no-cache",
        html.as_bytes(),
    );
    response.headers_mut().insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CONTENT_SECURITY_POLICY),
    );
    response.headers_mut().insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    response
}

/// One of the page's assets: cached for a year at its versioned URL (the
/// page's), revalidated at any other.
async fn asset(
    Path(file): Path<String>,
    query: axum::extract::RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let asset = ASSETS
        .iter()
        .find(|a| a.name == file)
        .ok_or_else(|| ApiError::not_found(format!("the page has no file `{file}`")))?;
    let current = version(asset.bytes);
    let cache = if query.0.as_deref() == Some(&format!("v={current}")) {
        "public, max-age=31536000, immutable"
    } else {
        "no-cache"
    };
    let etag = format!("\"{current}\"");
    Ok(answer(
        &headers,
        &etag,
        asset.content_type,
        cache,
        asset.bytes,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_page_names_each_asset_by_its_version() {
        let (html, etag) = index();
        for asset in &ASSETS {
            let url = format!("/ui/{}?v={}", asset.name, version(asset.bytes));
            assert!(html.contains(&url), "{url} not in the page");
        }
        assert!(!html.contains("{{"), "a placeholder is left");
        assert_eq!(etag.len(), 18);
        assert!(page_weight() > html.len());
    }

    #[test]
    fn if_none_match_is_compared_as_a_list() {
        let mut headers = HeaderMap::new();
        headers.insert(
            header::IF_NONE_MATCH,
            HeaderValue::from_static("\"a\", \"b\""),
        );
        assert!(fresh(&headers, "\"b\""));
        assert!(!fresh(&headers, "\"c\""));
        assert!(!fresh(&HeaderMap::new(), "\"b\""));
    }
}
