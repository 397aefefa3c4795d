//! Live progress: what changed in a sequence, announced to whoever
//! listens (`GET /api/v1/sequences/{id}/events`, server-sent events), so
//! acquisition PCs and the web page need not poll.
//!
//! Every change goes through the event log, the database's `events`
//! table (migration 0009), so that every serving process announces what
//! any process did: `ptv worker` processes on other hosts, or another
//! `ptv serve` behind the same load balancer.
//!
//! - **Recording.** [`Events::send`] never waits: it puts the change in
//!   this process's outbox. The recorder ([`record`], one task per
//!   process) appends what the outbox holds to the log in one transaction
//!   per batch. Changes are sent right after the change they announce
//!   commits, never before, so a client that reads the state on an event
//!   sees the change. While the database cannot be written, the recorder
//!   keeps up to [`MAX_PENDING`] changes and tries again every second;
//!   beyond that it drops the oldest, saying so in the log (the streams'
//!   snapshots stay right).
//! - **Following.** In a serving process the follower ([`follow`]) reads
//!   the log's new rows, at once when this process's recorder wrote some
//!   and otherwise every [`POLL`], and hands them to this process's
//!   subscribers through one [`tokio::sync::broadcast`] channel; each
//!   subscriber keeps its sequence's. A row's id is its event's id on the
//!   streams (the SSE `id:`), rising in the order written. On PostgreSQL,
//!   ids are drawn before their transactions commit, so a row may become
//!   visible after one with a higher id; the follower reads again the last
//!   [`LOOKBACK`] ids and passes on each row once.
//! - **Order.** One frame's events come in the order of its changes,
//!   accepted, running, processed, with one exception: a worker already
//!   looking for work may take up a frame between its upload's commit and
//!   the `frame_accepted` sent right after, and then `frame_running` comes
//!   first.
//! - **Falling behind.** Handing on never waits: a subscriber more than
//!   [`CAPACITY`] events behind loses the oldest and is told how many it
//!   missed (`lagged`), to read the state again.
//! - **Reconnecting.** A client that reconnects with `Last-Event-ID` is
//!   sent the events of its sequence it missed, from the log, then follows
//!   (`http::events`). Rows are deleted after [`RETENTION_S`]; a client
//!   whose last event is older gets a fresh snapshot.

use std::collections::{BTreeSet, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::sync::{broadcast, mpsc, watch, Notify};
use utoipa::ToSchema;

use crate::service::model::job_kind::JobKind;
use crate::service::ops::jobs::attempt::JobError;
use crate::service::store::{
    ClaimedJob, EventId, EventRow, FrameNumber, JobId, JobState, SequenceId, Store, TrackingRunId,
    MAX_ATTEMPTS,
};

/// A job's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
#[schema(as = JobState)]
pub enum JobStateView {
    /// Waiting for a worker.
    Queued,
    /// A worker has it.
    Running,
    /// Done; its result is stored.
    Succeeded,
    /// Given up; `error` says why.
    Failed,
}

impl From<JobState> for JobStateView {
    fn from(state: JobState) -> Self {
        match state {
            JobState::Queued => JobStateView::Queued,
            JobState::Running => JobStateView::Running,
            JobState::Succeeded => JobStateView::Succeeded,
            JobState::Failed => JobStateView::Failed,
        }
    }
}

/// Events a subscriber may fall behind by before it loses the oldest.
pub const CAPACITY: usize = 1024;

/// Changes the recorder keeps while the database cannot be written.
pub const MAX_PENDING: usize = 100_000;

/// How often the follower reads the log when its own recorder wrote
/// nothing (other processes' changes come within this).
pub const POLL: Duration = Duration::from_millis(250);

/// How many ids below the highest seen the follower reads again, for rows
/// committed after rows with higher ids (PostgreSQL).
pub const LOOKBACK: i64 = 64;

/// How long the log keeps an event: a day.
pub const RETENTION_S: u32 = 86_400;

/// Rows the follower reads at a time.
const BATCH: u32 = 1000;

/// What changed, with the sequence it changed in and its number.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct SequenceEvent {
    /// The event's id in the log, rising in the order written, for every
    /// sequence (the SSE `id:`); a gap in one sequence's ids is other
    /// sequences' events.
    #[schema(value_type = i64)]
    pub id: EventId,
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// What changed (the SSE `event:` name is its `type`).
    #[serde(flatten)]
    pub change: Change,
}

/// What changed in a sequence.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Change {
    /// A frame's upload was stored and its job queued.
    FrameAccepted {
        /// The frame.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A worker took up a frame's job.
    FrameRunning {
        /// The frame.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A frame's particles are stored.
    FrameProcessed {
        /// The frame.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A frame's job failed (its `error` says why; `POST /jobs/{id}/retry`
    /// queues it again).
    FrameFailed {
        /// The frame.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
        /// Why.
        error: String,
    },
    /// A frame's job went back to the queue (a passing failure, a full
    /// disk, or waiting for the sequence's background).
    FrameRequeued {
        /// The frame.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
        /// Why.
        reason: String,
    },
    /// Another job of the sequence (self-calibration, reprocessing)
    /// changed state.
    Job {
        /// The job.
        #[schema(value_type = i64)]
        job_id: JobId,
        /// Its kind.
        kind: String,
        /// Its new state.
        state: JobStateView,
    },
    /// A tracking run took one more frame (its points are stored).
    Tracked {
        /// The run.
        #[schema(value_type = i64)]
        run_id: TrackingRunId,
        /// The last frame tracked.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        tracked_through: FrameNumber,
    },
    /// A tracking run ended: finished, or failed.
    TrackingEnded {
        /// The run.
        #[schema(value_type = i64)]
        run_id: TrackingRunId,
        /// Whether every point is stored (false: it failed; the run says
        /// why).
        finished: bool,
    },
    /// A camera's calibration drifted: the mean of its last `window`
    /// frames' mean disparity vectors moved more than `threshold_px` from
    /// the run's first `window` frames' (`GET
    /// /sequences/{id}/calibration-health`). Self-calibrate the sequence
    /// (`POST /sequences/{id}/self-calibration`). Once per camera and
    /// calibration.
    CalibrationDrift {
        /// The camera, from 0.
        camera: usize,
        /// The frame at which the alarm fired.
        #[schema(value_type = i64, minimum = 0, maximum = 4_294_967_295_u64)]
        frame: FrameNumber,
        /// The calibration the drift is from.
        #[schema(value_type = i64)]
        calibration_id: crate::service::store::CalibrationId,
        /// The windowed mean's change from the baseline (px, x and y).
        drift_px: [f64; 2],
        /// Its length (px).
        drift_length_px: f64,
        /// The sequence's threshold (px).
        threshold_px: f64,
    },
}

impl Change {
    /// The SSE event name: the `type`.
    pub fn name(&self) -> &'static str {
        match self {
            Change::FrameAccepted { .. } => "frame_accepted",
            Change::FrameRunning { .. } => "frame_running",
            Change::FrameProcessed { .. } => "frame_processed",
            Change::FrameFailed { .. } => "frame_failed",
            Change::FrameRequeued { .. } => "frame_requeued",
            Change::Job { .. } => "job",
            Change::Tracked { .. } => "tracked",
            Change::TrackingEnded { .. } => "tracking_ended",
            Change::CalibrationDrift { .. } => "calibration_drift",
        }
    }
}

/// A committed change not logged yet, in the outbox.
type Unrecorded = (SequenceId, Change);

/// The service's event channel (cheap to clone): the outbox to the log,
/// and what the follower hands on to this process's subscribers.
#[derive(Clone, Debug)]
pub struct Events {
    outbox: mpsc::UnboundedSender<Unrecorded>,
    /// The outbox's other end, until the recorder takes it.
    unrecorded: Arc<Mutex<Option<mpsc::UnboundedReceiver<Unrecorded>>>>,
    /// Woken when the recorder wrote to the log.
    recorded: Arc<Notify>,
    sender: broadcast::Sender<SequenceEvent>,
    /// True once the service shuts down: every stream ends.
    closing: watch::Sender<bool>,
}

impl Default for Events {
    fn default() -> Self {
        let (outbox, unrecorded) = mpsc::unbounded_channel();
        Events {
            outbox,
            unrecorded: Arc::new(Mutex::new(Some(unrecorded))),
            recorded: Arc::default(),
            sender: broadcast::channel(CAPACITY).0,
            closing: watch::channel(false).0,
        }
    }
}

impl Events {
    /// Announces `change` in `sequence_id`, which has committed: puts it in
    /// the outbox for the recorder. Never waits.
    pub fn send(&self, sequence_id: SequenceId, change: Change) {
        // The recorder ends only with the process.
        let _ = self.outbox.send((sequence_id, change));
    }

    /// Hands a logged event to this process's subscribers (none: nothing
    /// happens). Never waits.
    fn publish(&self, event: SequenceEvent) {
        let _ = self.sender.send(event);
    }

    /// A new subscriber to every sequence's events from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<SequenceEvent> {
        self.sender.subscribe()
    }

    /// Turns true when the service shuts down.
    pub fn closing(&self) -> watch::Receiver<bool> {
        self.closing.subscribe()
    }

    /// Ends every stream (the service is shutting down, and waits for the
    /// requests in flight, which an open stream would be forever).
    pub fn close(&self) {
        self.closing.send_replace(true);
    }
}

/// A logged event as subscribers get it; a row whose change does not
/// parse (written by a newer version) is skipped, saying so.
pub fn logged(row: EventRow) -> Option<SequenceEvent> {
    match serde_json::from_str(&row.change) {
        Ok(change) => Some(SequenceEvent {
            id: row.id,
            sequence_id: row.sequence_id,
            change,
        }),
        Err(error) => {
            tracing::warn!(id = %row.id, %error, "an event in the log does not parse; skipped");
            None
        }
    }
}

/// The recorder: appends the outbox's changes to the log, a batch per
/// transaction, until the process ends (the outbox's senders are
/// dropped); deletes the events older than [`RETENTION_S`] at the start
/// and every hour. Where another task took the outbox already, returns.
pub async fn record(events: Events, store: Store) {
    let Some(mut outbox) = events.unrecorded.lock().ok().and_then(|mut o| o.take()) else {
        return;
    };
    let mut pending: VecDeque<(SequenceId, String)> = VecDeque::new();
    // Pruned at the start, then hourly.
    let mut pruned_at: Option<tokio::time::Instant> = None;
    loop {
        if pending.is_empty() {
            match outbox.recv().await {
                Some(change) => pending.extend(encoded(change)),
                None => return,
            }
        }
        while let Ok(change) = outbox.try_recv() {
            pending.extend(encoded(change));
        }
        if pending.len() > MAX_PENDING {
            let dropped = pending.len() - MAX_PENDING;
            pending.drain(..dropped);
            tracing::warn!(dropped, "events dropped: the database cannot be written");
        }
        let due = match pruned_at {
            None => true,
            Some(at) => at.elapsed() >= Duration::from_secs(3600),
        };
        if due {
            pruned_at = Some(tokio::time::Instant::now());
            match store.prune_events(RETENTION_S).await {
                Ok(0) => {}
                Ok(deleted) => tracing::info!(deleted, "old events deleted from the log"),
                Err(error) => tracing::warn!(%error, "cannot delete old events"),
            }
        }
        let batch: Vec<_> = pending.iter().take(500).cloned().collect();
        match store.append_events(&batch).await {
            Ok(_) => {
                pending.drain(..batch.len());
                events.recorded.notify_one();
            }
            Err(error) => {
                tracing::warn!(%error, pending = pending.len(), "cannot log events; trying again in 1 s");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
}

/// A change as the log stores it.
fn encoded((sequence_id, change): Unrecorded) -> Option<(SequenceId, String)> {
    match serde_json::to_string(&change) {
        Ok(json) => Some((sequence_id, json)),
        Err(error) => {
            tracing::error!(%error, "an event does not serialise");
            None
        }
    }
}

/// The follower: hands the log's new rows, from whichever process, to this
/// process's subscribers, from the log's end when it starts until the
/// service closes.
pub async fn follow(events: Events, store: Store) {
    let mut closing = events.closing();
    let start = loop {
        match store.last_event_id().await {
            Ok(last) => break last,
            Err(error) => {
                tracing::warn!(%error, "cannot read the event log; trying again in 1 s");
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                    _ = closing.wait_for(|closed| *closed) => return,
                }
            }
        }
    };
    follow_from(events, store, start).await;
}

/// The follower from the log's event `start` on (exclusive).
async fn follow_from(events: Events, store: Store, start: EventId) {
    let mut closing = events.closing();
    let mut seen = Seen::default();
    seen.start(start);
    loop {
        match store.events_after(seen.from(), BATCH).await {
            Ok(rows) => {
                let full = rows.len() == BATCH as usize;
                for row in rows {
                    if seen.first_time(row.id) {
                        if let Some(event) = logged(row) {
                            events.publish(event);
                        }
                    }
                }
                if full {
                    continue;
                }
            }
            Err(error) => tracing::warn!(%error, "cannot read the event log"),
        }
        tokio::select! {
            _ = events.recorded.notified() => {}
            _ = tokio::time::sleep(POLL) => {}
            _ = closing.wait_for(|closed| *closed) => return,
        }
    }
}

/// The ids the follower handed on, within [`LOOKBACK`] of the highest.
#[derive(Debug, Default)]
struct Seen {
    ids: BTreeSet<i64>,
    /// Ids up to here are not handed on: before the start, or more than
    /// [`LOOKBACK`] below the highest seen.
    floor: i64,
}

impl Seen {
    /// Starts after `last`: the events before it are history.
    fn start(&mut self, last: EventId) {
        self.floor = last.0;
    }

    /// Where the next read starts (exclusive).
    fn from(&self) -> EventId {
        EventId(self.floor)
    }

    /// Whether `id` is new; remembers it.
    fn first_time(&mut self, id: EventId) -> bool {
        if id.0 <= self.floor || !self.ids.insert(id.0) {
            return false;
        }
        let top = *self.ids.last().expect("just inserted");
        self.floor = self.floor.max(top - LOOKBACK);
        while self.ids.first().is_some_and(|&low| low <= self.floor) {
            self.ids.pop_first();
        }
        true
    }
}

/// What a job's payload says about its sequence (jobs of calibrations
/// have none, and announce nothing).
#[derive(serde::Deserialize)]
struct Subject {
    sequence_id: Option<SequenceId>,
    frame: Option<FrameNumber>,
}

/// The sequence and frame a job works on, if any.
fn subject(job: &ClaimedJob) -> Option<(SequenceId, Option<FrameNumber>)> {
    let subject: Subject = serde_json::from_str(&job.payload).ok()?;
    Some((subject.sequence_id?, subject.frame))
}

/// A job's attempt's outcome as announced.
#[derive(Clone, Debug)]
pub enum JobOutcome {
    /// Its results are stored.
    Succeeded,
    /// It failed, with this message.
    Failed(String),
    /// It went back to the queue, for this reason.
    Requeued(String),
    /// Another worker completed it; nothing to announce.
    Lost,
}

impl JobOutcome {
    /// The outcome of attempt number `attempts` that returned `result`, as
    /// the worker records it: a passing failure on the last attempt
    /// ([`MAX_ATTEMPTS`]) fails the job for good.
    pub fn of(result: &Result<(), JobError>, attempts: i64) -> JobOutcome {
        match result {
            Ok(()) => JobOutcome::Succeeded,
            Err(JobError::Failed(message)) => JobOutcome::Failed(message.clone()),
            Err(JobError::Retry(message)) if attempts >= MAX_ATTEMPTS => {
                JobOutcome::Failed(message.clone())
            }
            Err(
                JobError::Retry(message)
                | JobError::StorageFull(message)
                | JobError::Unavailable(message)
                | JobError::Deferred(message),
            ) => JobOutcome::Requeued(message.clone()),
            Err(JobError::LostLease) => JobOutcome::Lost,
        }
    }
}

/// Announces that a worker took up `job` (its claim is committed).
pub fn job_running(events: &Events, job: &ClaimedJob) {
    let Some((sequence_id, frame)) = subject(job) else {
        return;
    };
    let change = match (job.kind.parse::<JobKind>(), frame) {
        (Ok(JobKind::ProcessFrame), Some(frame)) => Change::FrameRunning {
            frame,
            job_id: job.id,
        },
        _ => Change::Job {
            job_id: job.id,
            kind: job.kind.clone(),
            state: JobStateView::Running,
        },
    };
    events.send(sequence_id, change);
}

/// Announces how `job`'s attempt ended, once the worker recorded it.
pub fn job_ended(events: &Events, job: &ClaimedJob, outcome: JobOutcome) {
    let Some((sequence_id, frame)) = subject(job) else {
        return;
    };
    let change = match (job.kind.parse::<JobKind>(), frame, outcome) {
        (_, _, JobOutcome::Lost) => return,
        (Ok(JobKind::ProcessFrame), Some(frame), JobOutcome::Succeeded) => Change::FrameProcessed {
            frame,
            job_id: job.id,
        },
        (Ok(JobKind::ProcessFrame), Some(frame), JobOutcome::Failed(error)) => {
            Change::FrameFailed {
                frame,
                job_id: job.id,
                error,
            }
        }
        (Ok(JobKind::ProcessFrame), Some(frame), JobOutcome::Requeued(reason)) => {
            Change::FrameRequeued {
                frame,
                job_id: job.id,
                reason,
            }
        }
        (_, _, outcome) => Change::Job {
            job_id: job.id,
            kind: job.kind.clone(),
            state: match outcome {
                JobOutcome::Succeeded => JobStateView::Succeeded,
                JobOutcome::Failed(_) => JobStateView::Failed,
                _ => JobStateView::Queued,
            },
        },
    };
    events.send(sequence_id, change);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_serialise_flat_and_changes_round_trip_through_the_log() {
        let event = SequenceEvent {
            id: EventId(1),
            sequence_id: SequenceId(2),
            change: Change::FrameProcessed {
                frame: FrameNumber(3),
                job_id: JobId(7),
            },
        };
        assert_eq!(
            serde_json::to_value(&event).unwrap(),
            serde_json::json!({"id": 1, "sequence_id": 2, "type": "frame_processed",
                               "frame": 3, "job_id": 7})
        );
        let (_, json) = encoded((event.sequence_id, event.change.clone())).unwrap();
        let row = EventRow {
            id: EventId(9),
            sequence_id: SequenceId(2),
            change: json,
        };
        let back = logged(row).unwrap();
        assert_eq!((back.id, back.change), (EventId(9), event.change));
        // A change this version does not know is skipped, not a panic.
        let unknown = EventRow {
            id: EventId(10),
            sequence_id: SequenceId(2),
            change: r#"{"type": "frame_teleported"}"#.into(),
        };
        assert!(logged(unknown).is_none());
    }

    #[test]
    fn the_follower_passes_on_late_rows_once_and_forgets_after_the_lookback() {
        let mut seen = Seen::default();
        seen.start(EventId(10));
        assert_eq!(seen.from(), EventId(10));
        assert!(!seen.first_time(EventId(9)), "before the start");
        assert!(seen.first_time(EventId(12)));
        // 11 committed after 12 (PostgreSQL): read again, passed on once.
        assert_eq!(seen.from(), EventId(10));
        assert!(seen.first_time(EventId(11)));
        assert!(!seen.first_time(EventId(11)));
        assert!(!seen.first_time(EventId(12)));
        // Far ahead: what is more than LOOKBACK below is no longer read.
        let top = 12 + 2 * LOOKBACK;
        assert!(seen.first_time(EventId(top)));
        assert_eq!(seen.from(), EventId(top - LOOKBACK));
        assert!(!seen.first_time(EventId(13)), "below the lookback");
        assert!(seen.first_time(EventId(top - 1)), "within it");
    }

    #[tokio::test]
    async fn every_process_on_the_database_hears_every_change() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path(), 2).await.unwrap();
        // Two processes: `server` serves streams, `worker` only records.
        let (server, worker) = (Events::default(), Events::default());
        // History: not handed on.
        store
            .append_events(&[(SequenceId(1), "{}".into())])
            .await
            .unwrap();
        let start = store.last_event_id().await.unwrap();
        let follower = tokio::spawn(follow_from(server.clone(), store.clone(), start));
        let recorders = [
            tokio::spawn(record(server.clone(), store.clone())),
            tokio::spawn(record(worker.clone(), store.clone())),
        ];
        let mut receiver = server.subscribe();
        let accepted = Change::FrameAccepted {
            frame: FrameNumber(0),
            job_id: JobId(1),
        };
        let processed = Change::FrameProcessed {
            frame: FrameNumber(0),
            job_id: JobId(1),
        };
        server.send(SequenceId(1), accepted.clone());
        worker.send(SequenceId(1), processed.clone());
        let within = Duration::from_secs(5);
        let first = tokio::time::timeout(within, receiver.recv())
            .await
            .unwrap()
            .unwrap();
        let second = tokio::time::timeout(within, receiver.recv())
            .await
            .unwrap()
            .unwrap();
        assert_eq!((first.id, first.change), (EventId(2), accepted));
        assert_eq!((second.id, second.change), (EventId(3), processed));
        server.close();
        follower.await.unwrap();
        for recorder in recorders {
            recorder.abort();
        }
    }

    #[test]
    fn every_change_is_named_by_its_serialised_type() {
        let (frame, job_id, run_id) = (FrameNumber(1), JobId(2), TrackingRunId(3));
        let changes = [
            Change::FrameAccepted { frame, job_id },
            Change::FrameRunning { frame, job_id },
            Change::FrameProcessed { frame, job_id },
            Change::FrameFailed {
                frame,
                job_id,
                error: "why".into(),
            },
            Change::FrameRequeued {
                frame,
                job_id,
                reason: "why".into(),
            },
            Change::Job {
                job_id,
                kind: "self_calibrate".into(),
                state: JobStateView::Running,
            },
            Change::Tracked {
                run_id,
                tracked_through: frame,
            },
            Change::TrackingEnded {
                run_id,
                finished: true,
            },
            Change::CalibrationDrift {
                camera: 1,
                frame,
                calibration_id: crate::service::store::CalibrationId(4),
                drift_px: [0.3, 0.1],
                drift_length_px: 0.316,
                threshold_px: 0.3,
            },
        ];
        for change in changes {
            let json = serde_json::to_value(&change).unwrap();
            assert_eq!(json["type"], change.name(), "{json}");
        }
    }

    #[test]
    fn a_subscriber_that_falls_behind_is_told_how_many_it_missed() {
        let events = Events::default();
        let mut slow = events.subscribe();
        for frame in 0..CAPACITY as i64 + 5 {
            events.publish(SequenceEvent {
                id: EventId(frame + 1),
                sequence_id: SequenceId(1),
                change: Change::FrameAccepted {
                    frame: FrameNumber(frame),
                    job_id: JobId(frame),
                },
            });
        }
        assert!(matches!(
            slow.try_recv(),
            Err(broadcast::error::TryRecvError::Lagged(5))
        ));
        // Then the oldest kept.
        assert_eq!(slow.try_recv().unwrap().id, EventId(6));
    }
}
