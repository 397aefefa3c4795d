//! The stored things a handler reads by the id in its path, or a 404.

use crate::service::ops::state::AppState;
use crate::service::store::{SequenceId, SequenceRow};

use super::problem::ApiError;

/// The sequence `id`, or a 404.
pub(super) async fn sequence(state: &AppState, id: SequenceId) -> Result<SequenceRow, ApiError> {
    state
        .store
        .sequence(id)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("sequence {id} does not exist")))
}
