//! `/sequences/{id}/events`: a sequence's live progress as server-sent
//! events (the WHATWG HTML standard's `text/event-stream`), from
//! [`crate::service::events`].
//!
//! Each event is `id:` (the service's event number), `event:` (the
//! change's `type`) and `data:` (the change as one line of JSON, with
//! `sequence_id` and `type`). The stream opens with a `snapshot` of the
//! sequence's frame counts, so a client needs no other request to start;
//! a comment every [`KEEP_ALIVE`] keeps proxies from closing an idle
//! stream; a client too slow to keep up gets `lagged` with how many events
//! it missed (read the sequence again), never holding up anyone else. The
//! stream ends when the service shuts down (`event: closing`). Events are
//! not stored, so `Last-Event-ID` is not replayed: a client that reconnects
//! gets a fresh snapshot.
//!
//! Authentication is the API's: `Authorization: Bearer` (with
//! `--api-token`). Browsers' `EventSource` cannot send that header, so the
//! web page reads the stream with `fetch`; the token is never taken from
//! the URL, where it would end up in logs and histories.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use futures_util::stream::{self, Stream};
use serde::Serialize;
use tokio::sync::broadcast::error::RecvError;
use utoipa::ToSchema;

use super::problem::{ApiError, ApiPath};
use super::sequences::{sequence, FrameCountsView};
use super::Shared;
use crate::service::app::AppState;
use crate::service::events::SequenceEvent;
use crate::service::store::SequenceId;

/// How often an idle stream sends a comment line.
pub const KEEP_ALIVE: Duration = Duration::from_secs(15);

pub(super) fn router() -> Router<Arc<AppState>> {
    Router::new().route("/sequences/{id}/events", get(events))
}

/// The first event of a stream: the sequence's frames by state when it
/// opened (`event: snapshot`).
#[derive(Debug, Serialize, ToSchema)]
pub struct Snapshot {
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// Its frames by state.
    pub frames: FrameCountsView,
}

/// Sent to a client that fell behind (`event: lagged`): events were lost;
/// read the sequence again.
#[derive(Debug, Serialize, ToSchema)]
pub struct Lagged {
    /// How many events (of all sequences) it missed.
    pub missed: u64,
}

/// A sequence's changes as server-sent events: `snapshot` first, then
/// `frame_accepted`, `frame_running`, `frame_processed`, `frame_failed`,
/// `frame_requeued`, `job`, `tracked`, `tracking_ended` as they are
/// committed (each `data` one JSON object of schema `SequenceEvent`),
/// `lagged` for a client that fell behind, `closing` at shutdown.
/// `curl -N` prints them as they come.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/events", tag = "sequences",
    params(("id" = i64, Path, description = "Sequence id")),
    responses(
        (status = 200, content_type = "text/event-stream", body = String,
            description = "`id:`, `event:` (the change's type) and `data:` (JSON: SequenceEvent; Snapshot first; Lagged) per event"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn events(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
) -> Result<Response, ApiError> {
    // Subscribed before the snapshot is read, so that no change between
    // the two is lost (one may come twice: counted in the snapshot, then
    // announced).
    let receiver = state.events.subscribe();
    let closing = state.events.closing();
    sequence(&state, id).await?;
    let counts = state.store.frame_counts(id).await?;
    let snapshot = Event::default().event("snapshot").json_data(Snapshot {
        sequence_id: id,
        frames: counts.into(),
    });
    let snapshot = snapshot.map_err(ApiError::internal)?;
    let first = stream::once(async move { Ok::<_, Infallible>(snapshot) });
    let rest = follow(id, receiver, closing);
    use futures_util::StreamExt as _;
    Ok(Sse::new(first.chain(rest))
        .keep_alive(KeepAlive::new().interval(KEEP_ALIVE))
        .into_response())
}

/// The events of sequence `id` from `receiver`, until the service closes.
fn follow(
    id: SequenceId,
    receiver: tokio::sync::broadcast::Receiver<SequenceEvent>,
    closing: tokio::sync::watch::Receiver<bool>,
) -> impl Stream<Item = Result<Event, Infallible>> {
    stream::unfold(Some((receiver, closing)), move |open| async move {
        let (mut receiver, mut closing) = open?;
        loop {
            let received = tokio::select! {
                received = receiver.recv() => received,
                _ = closing.wait_for(|closed| *closed) => {
                    let event = Event::default().event("closing").data("{}");
                    return Some((Ok(event), None));
                }
            };
            let event = match received {
                Ok(event) if event.sequence_id != id => continue,
                Ok(event) => Event::default()
                    .id(event.id.to_string())
                    .event(event.change.name())
                    .json_data(&event),
                Err(RecvError::Lagged(missed)) => Event::default()
                    .event("lagged")
                    .json_data(Lagged { missed }),
                Err(RecvError::Closed) => return None,
            };
            // The events serialise (plain data); were one not to, it
            // is skipped rather than the stream ended.
            match event {
                Ok(event) => return Some((Ok(event), Some((receiver, closing)))),
                Err(error) => tracing::error!(%error, "an event does not serialise"),
            }
        }
    })
}
