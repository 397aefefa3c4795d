//! Live progress: what changed in a sequence, announced to whoever
//! listens (`GET /api/v1/sequences/{id}/events`, server-sent events), so
//! acquisition PCs and the web page need not poll.
//!
//! One [`tokio::sync::broadcast`] channel for the whole service
//! ([`Events`], in the app state); every [`SequenceEvent`] carries its
//! sequence's id and a number from one counter, in the order sent, and
//! each subscriber keeps its sequence's. Events are sent right after the
//! change they announce is committed (the frame's upload, a job's outcome,
//! a tracked frame), never before, so a client that reads the state on an
//! event sees the change. One frame's events come in the order of its
//! changes, accepted, running, processed; with one exception: a worker
//! already looking for work (finishing another job, or at its 1 s poll)
//! may take up a frame between its upload's commit and the
//! `frame_accepted` sent right after, and then `frame_running` comes
//! first. Sending never waits: a subscriber more than
//! [`CAPACITY`] events behind loses the oldest and is told how many it
//! missed (`lagged`), to read the state again. Nothing is stored: a client
//! that reconnects reads the sequence's state, then follows the events.
//! The channel is the process's own: changes made by `ptv worker`
//! processes (`app::run_worker`) are not announced to a serving process's
//! subscribers, who see them in the next snapshot; a channel between
//! processes (PostgreSQL's LISTEN/NOTIFY) comes with issue 17's backends.

use serde::Serialize;
use tokio::sync::{broadcast, watch};
use utoipa::ToSchema;

use super::app::AppState;
use super::http::jobs::JobStateView;
use super::jobs::{JobError, PROCESS_FRAME};
use super::store::{ClaimedJob, FrameNumber, JobId, SequenceId, TrackingRunId, MAX_ATTEMPTS};

/// Events a subscriber may fall behind by before it loses the oldest.
pub const CAPACITY: usize = 1024;

/// What changed, with the sequence it changed in and its number.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct SequenceEvent {
    /// Numbered from 1 in the order sent, for the whole service (the SSE
    /// `id:`); a gap in one sequence's numbers is other sequences' events.
    pub id: u64,
    /// The sequence.
    #[schema(value_type = i64)]
    pub sequence_id: SequenceId,
    /// What changed (the SSE `event:` name is its `type`).
    #[serde(flatten)]
    pub change: Change,
}

/// What changed in a sequence.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Change {
    /// A frame's upload was stored and its job queued.
    FrameAccepted {
        /// The frame.
        #[schema(value_type = i64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A worker took up a frame's job.
    FrameRunning {
        /// The frame.
        #[schema(value_type = i64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A frame's particles are stored.
    FrameProcessed {
        /// The frame.
        #[schema(value_type = i64)]
        frame: FrameNumber,
        /// Its job.
        #[schema(value_type = i64)]
        job_id: JobId,
    },
    /// A frame's job failed (its `error` says why; `POST /jobs/{id}/retry`
    /// queues it again).
    FrameFailed {
        /// The frame.
        #[schema(value_type = i64)]
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
        #[schema(value_type = i64)]
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
        #[schema(value_type = i64)]
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
        }
    }
}

/// The service's event channel (cheap to clone).
#[derive(Clone, Debug)]
pub struct Events {
    sender: broadcast::Sender<SequenceEvent>,
    counter: std::sync::Arc<std::sync::atomic::AtomicU64>,
    /// True once the service shuts down: every stream ends.
    closing: watch::Sender<bool>,
}

impl Default for Events {
    fn default() -> Self {
        Events {
            sender: broadcast::channel(CAPACITY).0,
            counter: Default::default(),
            closing: watch::channel(false).0,
        }
    }
}

impl Events {
    /// Announces `change` in `sequence_id` to the current subscribers (none:
    /// nothing happens). Never waits.
    pub fn send(&self, sequence_id: SequenceId, change: Change) {
        if self.sender.receiver_count() == 0 {
            return;
        }
        let id = 1 + self
            .counter
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let _ = self.sender.send(SequenceEvent {
            id,
            sequence_id,
            change,
        });
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
pub fn job_running(state: &AppState, job: &ClaimedJob) {
    let Some((sequence_id, frame)) = subject(job) else {
        return;
    };
    let change = match (job.kind.as_str(), frame) {
        (PROCESS_FRAME, Some(frame)) => Change::FrameRunning {
            frame,
            job_id: job.id,
        },
        _ => Change::Job {
            job_id: job.id,
            kind: job.kind.clone(),
            state: JobStateView::Running,
        },
    };
    state.events.send(sequence_id, change);
}

/// Announces how `job`'s attempt ended, once the worker recorded it.
pub fn job_ended(state: &AppState, job: &ClaimedJob, outcome: JobOutcome) {
    let Some((sequence_id, frame)) = subject(job) else {
        return;
    };
    let change = match (job.kind.as_str(), frame, outcome) {
        (_, _, JobOutcome::Lost) => return,
        (PROCESS_FRAME, Some(frame), JobOutcome::Succeeded) => Change::FrameProcessed {
            frame,
            job_id: job.id,
        },
        (PROCESS_FRAME, Some(frame), JobOutcome::Failed(error)) => Change::FrameFailed {
            frame,
            job_id: job.id,
            error,
        },
        (PROCESS_FRAME, Some(frame), JobOutcome::Requeued(reason)) => Change::FrameRequeued {
            frame,
            job_id: job.id,
            reason,
        },
        (kind, _, outcome) => Change::Job {
            job_id: job.id,
            kind: kind.to_owned(),
            state: match outcome {
                JobOutcome::Succeeded => JobStateView::Succeeded,
                JobOutcome::Failed(_) => JobStateView::Failed,
                _ => JobStateView::Queued,
            },
        },
    };
    state.events.send(sequence_id, change);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_are_numbered_in_order_and_named_by_their_type() {
        let events = Events::default();
        // Nobody listens: nothing is numbered.
        events.send(
            SequenceId(1),
            Change::FrameAccepted {
                frame: FrameNumber(0),
                job_id: JobId(1),
            },
        );
        let mut receiver = events.subscribe();
        events.send(
            SequenceId(2),
            Change::FrameProcessed {
                frame: FrameNumber(3),
                job_id: JobId(7),
            },
        );
        events.send(
            SequenceId(2),
            Change::Tracked {
                run_id: TrackingRunId(1),
                tracked_through: FrameNumber(3),
            },
        );
        let first = receiver.try_recv().unwrap();
        let second = receiver.try_recv().unwrap();
        assert_eq!((first.id, second.id), (1, 2));
        assert_eq!(first.change.name(), "frame_processed");
        let json = serde_json::to_value(&first).unwrap();
        assert_eq!(
            json,
            serde_json::json!({"id": 1, "sequence_id": 2, "type": "frame_processed",
                               "frame": 3, "job_id": 7})
        );
        // The name is the serialised type, for every variant.
        assert_eq!(
            serde_json::to_value(&second).unwrap()["type"],
            second.change.name()
        );
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
            events.send(
                SequenceId(1),
                Change::FrameAccepted {
                    frame: FrameNumber(frame),
                    job_id: JobId(frame),
                },
            );
        }
        assert!(matches!(
            slow.try_recv(),
            Err(broadcast::error::TryRecvError::Lagged(5))
        ));
        // Then the oldest kept.
        assert_eq!(slow.try_recv().unwrap().id, 6);
    }
}
