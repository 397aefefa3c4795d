//! `/sequences/{id}/events`: a sequence's live progress as server-sent
//! events (the WHATWG HTML standard's `text/event-stream`), from
//! [`crate::service::ops::events`].
//!
//! Each event is `id:` (the event's id in the event log), `event:` (the
//! change's `type`) and `data:` (the change as one line of JSON, with
//! `sequence_id` and `type`). The stream opens with a `snapshot` of the
//! sequence's frame counts, so a client needs no other request to start;
//! a comment every [`KEEP_ALIVE`] keeps proxies from closing an idle
//! stream; a client too slow to keep up gets `lagged` with how many events
//! it missed (read the sequence again), never holding up anyone else. The
//! stream ends when the service shuts down (`event: closing`).
//!
//! A client that reconnects with `Last-Event-ID` (as browsers'
//! `EventSource` does) is sent the sequence's events after that id from
//! the log, at most [`REPLAY_LIMIT`], instead of the snapshot, then
//! follows. When the log no longer holds them all (kept for a day), or
//! they are more, it gets the snapshot as a new client does.
//!
//! Authentication is the API's: `Authorization: Bearer` (with
//! `--api-token`). Browsers' `EventSource` cannot send that header, so the
//! web page reads the stream with `fetch`; the token is never taken from
//! the URL, where it would end up in logs and histories.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use futures_util::stream::{self, Stream};
use serde::Serialize;
use tokio::sync::broadcast::error::RecvError;
use utoipa::ToSchema;

use super::extract::Shared;
use super::lookups::sequence;
use super::problem::{ApiError, ApiPath};
use super::sequences::FrameCountsView;
use crate::service::ops::events::{logged, SequenceEvent};
use crate::service::ops::state::AppState;
use crate::service::store::{EventId, SequenceId};

/// How often an idle stream sends a comment line.
pub const KEEP_ALIVE: Duration = Duration::from_secs(15);

/// The most events a reconnecting client is sent from the log; one that
/// missed more gets a snapshot.
pub const REPLAY_LIMIT: u32 = 10_000;

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
/// With `Last-Event-ID`, the events after it instead of the snapshot,
/// where the log still holds them all. `curl -N` prints them as they come.
#[utoipa::path(
    get, path = "/api/v1/sequences/{id}/events", tag = "sequences",
    params(
        ("id" = i64, Path, description = "Sequence id"),
        ("Last-Event-ID" = Option<i64>, Header, description = "The id of the last event received: the stream starts with the events after it (no snapshot) where the log still holds them, else with a snapshot"),
    ),
    responses(
        (status = 200, content_type = "text/event-stream", body = String,
            description = "`id:`, `event:` (the change's type) and `data:` (JSON: SequenceEvent; Snapshot first; Lagged) per event"),
        (status = 404, body = super::problem::Problem, content_type = "application/problem+json"),
    )
)]
pub async fn events(
    State(state): Shared,
    ApiPath(id): ApiPath<SequenceId>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    // Subscribed before the snapshot or the missed events are read, so
    // that no change between the two is lost. What the client has (the
    // snapshot, or the events up to the last it was sent) it is not sent
    // again: the follower may hand on events logged before this request.
    let receiver = state.events.subscribe();
    let closing = state.events.closing();
    sequence(&state, id).await?;
    let (first, after) = match missed(&state, id, &headers).await? {
        Some(missed) => missed,
        None => {
            // Changes are logged after they commit: those logged up to
            // here are in the counts read next.
            let after = state.store.last_event_id().await?;
            let counts = state.store.frame_counts(id).await?;
            let snapshot = Event::default().event("snapshot").json_data(Snapshot {
                sequence_id: id,
                frames: counts.into(),
            });
            (vec![snapshot.map_err(ApiError::internal)?], after)
        }
    };
    let first = stream::iter(first.into_iter().map(Ok::<_, Infallible>));
    let rest = follow(id, receiver, closing, after);
    use futures_util::StreamExt as _;
    Ok(Sse::new(first.chain(rest))
        .keep_alive(KeepAlive::new().interval(KEEP_ALIVE))
        .into_response())
}

/// The events of sequence `id` after the request's `Last-Event-ID`, from
/// the log, and the last id the client then has; `None` without the
/// header, or where the log no longer holds them all (the client gets a
/// snapshot). A header that is not an event id is a 400.
async fn missed(
    state: &AppState,
    id: SequenceId,
    headers: &HeaderMap,
) -> Result<Option<(Vec<Event>, EventId)>, ApiError> {
    let Some(value) = headers.get("last-event-id") else {
        return Ok(None);
    };
    let last = value
        .to_str()
        .ok()
        .and_then(|text| super::decimal::parse::<i64>(text).ok())
        .map(EventId)
        .ok_or_else(|| {
            ApiError::bad_request(
                "Last-Event-ID is not an event id: send the `id:` of the last event received, \
                 or no header for a snapshot",
            )
        })?;
    // Events after `last` may have been deleted when the oldest kept is
    // past it (ids rise by one, whatever their sequence; a gap left by a
    // rolled-back write only costs a snapshot), or when none is kept.
    match state.store.oldest_event_id().await? {
        Some(oldest) if oldest.0 <= last.0.saturating_add(1) => {}
        _ => return Ok(None),
    }
    let rows = state
        .store
        .sequence_events_after(id, last, REPLAY_LIMIT)
        .await?;
    if rows.len() == REPLAY_LIMIT as usize {
        return Ok(None);
    }
    let after = rows.last().map_or(last, |row| row.id.max(last));
    let events = rows
        .into_iter()
        .filter_map(logged)
        .filter_map(|event| sse(&event));
    Ok(Some((events.collect(), after)))
}

/// An event as sent; one that does not serialise (plain data: none does)
/// is skipped rather than the stream ended.
fn sse(event: &SequenceEvent) -> Option<Event> {
    let sent = Event::default()
        .id(event.id.to_string())
        .event(event.change.name())
        .json_data(event);
    match sent {
        Ok(sent) => Some(sent),
        Err(error) => {
            tracing::error!(%error, "an event does not serialise");
            None
        }
    }
}

/// The events of sequence `id` from `receiver` with ids above `after`,
/// until the service closes. (On PostgreSQL an event may be logged with a
/// lower id than one logged before it, see `service::events`; a stream
/// whose client had the later one skips it.)
fn follow(
    id: SequenceId,
    receiver: tokio::sync::broadcast::Receiver<SequenceEvent>,
    closing: tokio::sync::watch::Receiver<bool>,
    after: EventId,
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
                Ok(event) if event.sequence_id != id || event.id <= after => continue,
                Ok(event) => sse(&event),
                Err(RecvError::Lagged(missed)) => {
                    match Event::default()
                        .event("lagged")
                        .json_data(Lagged { missed })
                    {
                        Ok(event) => Some(event),
                        Err(error) => {
                            tracing::error!(%error, "an event does not serialise");
                            None
                        }
                    }
                }
                Err(RecvError::Closed) => return None,
            };
            if let Some(event) = event {
                return Some((Ok(event), Some((receiver, closing))));
            }
        }
    })
}
