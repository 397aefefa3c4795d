//! What handlers extract besides the problem-aware extractors of
//! [`super::problem`]: the shared state, the list pages' query.

use std::sync::Arc;

use axum::extract::State;
use serde::Deserialize;
use utoipa::IntoParams;

use super::problem::ApiError;
use crate::service::ops::state::AppState;

/// The shared state handlers get.
pub type Shared = State<Arc<AppState>>;

/// The longest page of a list.
pub const MAX_PAGE: u32 = 100;
/// A list's page when the query does not say.
pub const DEFAULT_PAGE: u32 = 20;

/// The query of the lists that go newest first (`GET /calibrations`,
/// `GET /sequences`): a page of `limit` below the id `before`.
#[derive(Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct PageQuery {
    /// Items per page, 1 to 100 [default: 20].
    #[serde(default)]
    pub limit: Option<u32>,
    /// Only items with a lower id (the `next` link sets it).
    #[serde(default)]
    pub before: Option<i64>,
}

impl PageQuery {
    /// The page's length, checked.
    pub fn limit(&self) -> Result<u32, ApiError> {
        match self.limit {
            None => Ok(DEFAULT_PAGE),
            Some(n @ 1..=MAX_PAGE) => Ok(n),
            Some(n) => Err(ApiError::bad_request(format!(
                "limit: {n} is not within 1 to {MAX_PAGE}"
            ))),
        }
    }

    /// The link to the page after one whose last item has id `last`.
    pub fn next(&self, path: &str, last: i64) -> String {
        format!(
            "/api/v1{path}?limit={}&before={last}",
            self.limit.unwrap_or(DEFAULT_PAGE)
        )
    }
}
