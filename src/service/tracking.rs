//! Tracking a sequence as its frames complete (issue 15): the core's
//! [`Tracker`] (Malik, Dracos and Papantoniou 1993, Part II: links judged
//! over four frames by the least change of acceleration, conflicts
//! resolved per frame, velocities and accelerations from local polynomial
//! fits after Lüthi et al. 2005; see [`crate::photogrammetry::track`]) fed
//! the sequence's frames in frame order.
//!
//! **Settings.** Tracking is off unless a sequence is created with
//! `tracking` settings (or a run is started later, `POST
//! /sequences/{id}/tracking`): its largest velocity is the experiment's,
//! and no default would fit both a 1 mm tank and a 1 m wind tunnel.
//! [`TrackingSettings`] map onto [`TrackingParameters`], checked by the
//! core's own validation (a 422 naming the field).
//!
//! **In frame order.** Frames complete out of order and in parallel. After
//! every frame job (succeeded or failed) [`kick`] advances the sequence's
//! current run: from the frame after `tracked_through` (or `first_frame`),
//! each frame in turn is taken while it is done: processed (its particles)
//! or failed (a gap: pushed as a frame with no particles). A frame still
//! queued or running, or a frame number not uploaded yet, stops the run
//! there until the next kick. Once the client says the sequence has all
//! its frames (`POST /sequences/{id}/tracking/finish`), numbers never
//! uploaded are gaps too, and after the last frame the tracker ends and
//! its last points are stored (the run is `finished`). One tracker per run
//! at a time: each run's tracker sits behind its own async mutex.
//!
//! **State in the store; the tracker rebuilt by replay.** Each frame the
//! tracker takes is one write transaction (`BEGIN IMMEDIATE`): the points
//! that frame made final, the frame recorded in `tracking_frames` (with its
//! particle count, or as a gap), and `tracked_through` advanced, fenced on
//! its old value so that a repeat writes nothing. A crash leaves the frame
//! tracked or not, never half. (A frame's store runs while the tracker
//! takes the next frame; every way out of an advance waits for it, so the
//! tracker in memory and the stored progress agree whenever the run's
//! lock is free.) The tracker itself is kept in memory
//! between frames; after a restart (or when the memory copy does not match
//! the stored progress) it is rebuilt by giving a fresh tracker the
//! recorded frames again, from their stored particles, and discarding what
//! it hands out (already stored). The tracker is deterministic, so the
//! rebuilt one is the one that crashed, and the run goes on with no link
//! lost or repeated. We chose replay over a serialized checkpoint because
//! it needs nothing of the tracker but its public API (its internals are
//! being reworked) and writes nothing per frame besides the points; the
//! price is a restart that costs one pass over the run's frames so far
//! (the tracker's own speed plus decoding the particles), paid once per
//! run after a restart, not per frame. A frame's particles replaced since
//! they were tracked (reprocessing with another calibration) make the
//! replay diverge: the count recorded per frame detects a changed count,
//! and the run then fails, saying to start a new run. The replay also
//! assumes the same tracker: a run resumed by a build whose tracker links
//! differently (an upgrade between the crash and the restart) goes on with
//! that tracker's links from the frames it replays, which the stored
//! points do not show; after an upgrade, start a new run for sequences
//! still being tracked.
//!
//! **Runs.** A new run (other settings) supersedes the current one, whose
//! points so far stay readable (`?run=`); frames of a finished run
//! uploaded after it finished are not in it (start a new run).

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::app::AppState;
use super::codec::{self, DamagedBlob};
use super::jobs::{error_chain, CpuError};
use super::store::{
    FrameNumber, FrameReadiness, PointRow, SequenceId, TrackingRunId, TrackingRunRow, TrackingState,
};
use crate::photogrammetry::correspond::Particle;
use crate::photogrammetry::track::{
    ParticlePosition, TrackError, TrackPoint, Tracker, TrackingParameters,
};

/// How to track a sequence (all but `max_velocity` optional; the defaults
/// are `ptv track`'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackingSettings {
    /// The largest displacement of a particle between two frames (mm per
    /// frame), above zero.
    pub max_velocity: f64,
    /// The largest change of velocity between two frames (mm per frame²)
    /// [default: half of max_velocity].
    #[serde(default)]
    pub max_acceleration: Option<f64>,
    /// Frames a trajectory may miss and continue, 0 to 2 [default: 1].
    #[serde(default)]
    pub max_gap: Option<usize>,
    /// The fewest points of a trajectory that is stored [default: 3].
    #[serde(default)]
    pub min_length: Option<usize>,
    /// Points on each side of a point in its polynomial fit, 1 to 5
    /// [default: 2].
    #[serde(default)]
    pub fit_half_window: Option<usize>,
    /// The fit's order, 1 to 3 [default: 2].
    #[serde(default)]
    pub fit_order: Option<usize>,
    /// The sequence's first frame: tracking starts there and waits for it
    /// [default: 0].
    #[serde(default)]
    #[schema(value_type = Option<i64>)]
    pub first_frame: Option<FrameNumber>,
}

/// Settings the tracker refuses.
#[derive(Debug, thiserror::Error)]
pub enum InvalidTrackingSettings {
    /// A parameter out of range (the core's check).
    #[error("tracking: {0}")]
    Parameter(#[from] TrackError),
    /// A negative first frame.
    #[error("tracking: first_frame must be a frame number (0 or more), got {0}")]
    FirstFrame(FrameNumber),
}

impl TrackingSettings {
    /// The core's parameters.
    pub fn parameters(&self) -> TrackingParameters {
        let defaults = TrackingParameters::new(self.max_velocity);
        TrackingParameters {
            max_acceleration: self.max_acceleration.unwrap_or(defaults.max_acceleration),
            max_gap: self.max_gap.unwrap_or(defaults.max_gap),
            min_length: self.min_length.unwrap_or(defaults.min_length),
            fit_half_window: self.fit_half_window.unwrap_or(defaults.fit_half_window),
            fit_order: self.fit_order.unwrap_or(defaults.fit_order),
            ..defaults
        }
    }

    /// The settings with every default filled in, checked.
    pub fn with_defaults(&self) -> Result<TrackingSettings, InvalidTrackingSettings> {
        let p = self.parameters();
        p.validate()?;
        let first_frame = self.first_frame.unwrap_or(FrameNumber(0));
        if first_frame.0 < 0 {
            return Err(InvalidTrackingSettings::FirstFrame(first_frame));
        }
        Ok(TrackingSettings {
            max_velocity: p.max_velocity,
            max_acceleration: Some(p.max_acceleration),
            max_gap: Some(p.max_gap),
            min_length: Some(p.min_length),
            fit_half_window: Some(p.fit_half_window),
            fit_order: Some(p.fit_order),
            first_frame: Some(first_frame),
        })
    }

    fn first_frame(&self) -> FrameNumber {
        self.first_frame.unwrap_or(FrameNumber(0))
    }
}

/// A run's tracker in memory, with what it needs between frames.
struct Live {
    /// The last frame it took (as stored).
    through: Option<FrameNumber>,
    /// Out of its slot while it works on the CPU pool (gone if that
    /// panicked).
    tracker: Option<Tracker>,
    /// The recent frames' particles' targets (`t0,t1,...` per particle),
    /// for the points that become final later.
    targets: VecDeque<(FrameNumber, Vec<String>)>,
    /// Frames kept in `targets`.
    keep: i64,
}

impl Live {
    fn new(parameters: &TrackingParameters) -> Result<Live, TrackError> {
        Ok(Live {
            through: None,
            tracker: Some(Tracker::new(parameters.clone())?),
            targets: VecDeque::new(),
            // A point becomes final at most this many frames after its own
            // (as `ptv track` holds frames).
            keep: parameters.report_delay() as i64,
        })
    }

    /// Takes the particles of `frame`: the tracker's new final points.
    async fn push(
        &mut self,
        state: &AppState,
        frame: FrameNumber,
        particles: Vec<Particle>,
    ) -> Result<Vec<TrackPoint>, TrackingError> {
        self.targets.push_back((
            frame,
            particles.iter().map(|p| targets_text(&p.targets)).collect(),
        ));
        while self
            .targets
            .front()
            .is_some_and(|(f, _)| f.0 + self.keep < frame.0)
        {
            self.targets.pop_front();
        }
        let positions: Vec<ParticlePosition> = particles
            .iter()
            .map(|p| ParticlePosition::seen_by(p.position, p.sigma, p.camera_count()))
            .collect();
        let tracker = self
            .tracker
            .take()
            .ok_or_else(|| TrackingError::Internal("the tracker was lost to a panic".to_owned()))?;
        let (tracker, points) = state
            .cpu
            .run(move || {
                let mut tracker = tracker;
                let points = tracker.push(frame.0, positions);
                (tracker, points)
            })
            .await?;
        self.tracker = Some(tracker);
        self.through = Some(frame);
        Ok(points?)
    }

    /// The points as rows, with their particles' targets.
    fn rows(&self, points: &[TrackPoint]) -> Result<Vec<PointRow>, TrackingError> {
        rows(&self.targets, points)
    }
}

/// Points as rows, with their particles' targets from `held`.
fn rows(
    held: &VecDeque<(FrameNumber, Vec<String>)>,
    points: &[TrackPoint],
) -> Result<Vec<PointRow>, TrackingError> {
    points
        .iter()
        .map(|p| {
            let targets = held
                .iter()
                .find(|(f, _)| f.0 == p.frame)
                .and_then(|(_, t)| t.get(p.particle))
                .ok_or(TrackingError::Internal(format!(
                    "frame {}'s particles were let go before trajectory {} was stored",
                    p.frame, p.trajectory
                )))?;
            Ok(point_row(p, targets.clone()))
        })
        .collect()
}

/// `t0,t1,...`: each camera's target, -1 for none.
fn targets_text(targets: &[Option<usize>]) -> String {
    targets
        .iter()
        .map(|t| t.map_or_else(|| "-1".to_owned(), |t| t.to_string()))
        .collect::<Vec<_>>()
        .join(",")
}

fn point_row(p: &TrackPoint, targets: String) -> PointRow {
    let d = &p.derivatives;
    let finite =
        |v: nalgebra::Vector3<f64>| v.iter().all(|x| x.is_finite()).then(|| [v.x, v.y, v.z]);
    PointRow {
        trajectory: p.trajectory as i64,
        frame: FrameNumber(p.frame),
        particle: p.particle as i64,
        position: [p.position.x, p.position.y, p.position.z],
        velocity: finite(d.velocity),
        acceleration: d.acceleration.and_then(finite),
        velocity_sigma: finite(d.velocity_sigma),
        targets,
    }
}

/// Why a run did not advance.
#[derive(Debug, thiserror::Error)]
pub enum TrackingError {
    /// The database failed (the next kick tries again).
    #[error("database: {0}")]
    Database(#[from] sqlx::Error),
    /// The CPU pool failed.
    #[error("tracking {0}")]
    Cpu(#[from] CpuError),
    /// The tracker refused the input (the run fails).
    #[error(transparent)]
    Track(#[from] TrackError),
    /// A stored particle blob does not read (the run fails).
    #[error(transparent)]
    Blob(#[from] DamagedBlob),
    /// The stored settings do not read (the run fails).
    #[error("the stored tracking settings: {0}")]
    Settings(#[from] serde_json::Error),
    /// The stored frames no longer give what was tracked (the run fails).
    #[error("{0}")]
    Diverged(String),
    /// A broken invariant (the run fails).
    #[error("internal: {0}; please report this")]
    Internal(String),
    /// A frame's store did not run to its end (a shutdown; the next
    /// advance finds what was stored).
    #[error("storing a frame was interrupted: {0}")]
    Interrupted(String),
    /// Another advance moved the run meanwhile (nothing to do).
    #[error("the run was advanced elsewhere")]
    Moved,
}

impl TrackingError {
    /// Whether the run cannot go on (rather than a passing failure).
    fn is_fatal(&self) -> bool {
        !matches!(
            self,
            TrackingError::Database(_)
                | TrackingError::Cpu(_)
                | TrackingError::Interrupted(_)
                | TrackingError::Moved
        )
    }
}

/// The runs' trackers in memory, one slot per run.
#[derive(Default)]
pub struct Trackers {
    slots: Mutex<HashMap<TrackingRunId, Arc<tokio::sync::Mutex<Option<Live>>>>>,
}

impl std::fmt::Debug for Trackers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let runs = self.slots.lock().map(|s| s.len()).unwrap_or_default();
        f.debug_struct("Trackers").field("runs", &runs).finish()
    }
}

impl Trackers {
    fn slot(&self, id: TrackingRunId) -> Arc<tokio::sync::Mutex<Option<Live>>> {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        slots.entry(id).or_default().clone()
    }

    /// Drops a run's tracker (a run superseded or ended); an advance still
    /// holding it finds the run's state changed when it stores.
    pub fn forget(&self, id: TrackingRunId) {
        let mut slots = self.slots.lock().unwrap_or_else(|e| e.into_inner());
        slots.remove(&id);
    }
}

/// Advances the sequence's current run in the background (after a frame
/// job, a finish request, a new run).
pub fn kick(state: &Arc<AppState>, sequence_id: SequenceId) {
    let state = state.clone();
    tokio::spawn(async move {
        match state.store.current_tracking_run(sequence_id).await {
            Ok(Some(run)) if run.state == TrackingState::Tracking => {
                advance_logged(&state, run.id).await
            }
            Ok(_) => {}
            Err(error) => tracing::warn!(%error, %sequence_id, "cannot read the tracking run"),
        }
    });
}

/// Advances every run still tracking (at start-up).
pub fn resume_all(state: &Arc<AppState>) {
    let state = state.clone();
    tokio::spawn(async move {
        match state.store.unfinished_tracking_runs().await {
            Ok(runs) => {
                for id in runs {
                    advance_logged(&state, id).await;
                }
            }
            Err(error) => tracing::warn!(%error, "cannot list the tracking runs to resume"),
        }
    });
}

async fn advance_logged(state: &Arc<AppState>, id: TrackingRunId) {
    if let Err(error) = advance(state, id).await {
        let message = error_chain(&error);
        if error.is_fatal() {
            tracing::warn!(run = %id, %message, "tracking run failed");
            if let Err(error) = state.store.fail_tracking_run(id, &message).await {
                tracing::error!(run = %id, %error, "cannot record a tracking run's failure");
            }
        } else {
            tracing::warn!(run = %id, %message, "tracking did not advance; next frame retries");
        }
    }
}

/// Frames read per query while advancing.
const FRAMES_PER_QUERY: u32 = 256;

/// Advances a run as far as its sequence's frames allow, and ends it once
/// finish was requested and every frame is tracked.
pub async fn advance(state: &Arc<AppState>, id: TrackingRunId) -> Result<(), TrackingError> {
    let slot = state.trackers.slot(id);
    let mut guard = slot.lock().await;
    let Some(run) = state.store.tracking_run(id).await? else {
        return Ok(());
    };
    if run.state != TrackingState::Tracking {
        *guard = None;
        state.trackers.forget(id);
        return Ok(());
    }
    let settings: TrackingSettings = serde_json::from_str(&run.parameters)?;
    let parameters = settings.parameters();
    if guard.as_ref().map(|l| l.through) != Some(run.tracked_through) {
        *guard = None;
        *guard = Some(rebuild(state, &run, &parameters).await?);
    }
    let live = guard.as_mut().expect("a tracker was put in");
    let cameras = cameras_of(state, run.sequence_id).await?;
    // A frame's points are stored while the tracker takes the next frame;
    // every way out waits for that store first, so that the tracker in
    // memory and the stored progress agree whenever the lock is free.
    let mut storing = None;
    let taken = take_frames(state, &run, &settings, live, cameras, &mut storing).await;
    let stored = settle(&mut storing).await;
    let at_end = match (taken, stored) {
        (Ok(Taken::AtEnd), Ok(true)) => true,
        (Ok(Taken::Waiting), Ok(true)) => false,
        (Ok(_), Ok(false)) => {
            // Someone else moved the run: the next advance rebuilds.
            *guard = None;
            return Ok(());
        }
        (Err(TrackingError::Moved), _) => {
            *guard = None;
            return Ok(());
        }
        (Err(error), _) | (Ok(_), Err(error)) => {
            *guard = None;
            return Err(error);
        }
    };
    if at_end && run.finish_requested {
        let Some(live) = guard.take() else {
            return Ok(());
        };
        let Some(tracker) = live.tracker else {
            return Err(TrackingError::Internal(
                "the tracker was lost to a panic".to_owned(),
            ));
        };
        let points = state.cpu.run(move || tracker.finish()).await?;
        let rows = rows(&live.targets, &points)?;
        state
            .store
            .finish_tracking_run(id, live.through, &rows)
            .await?;
        state.trackers.forget(id);
    }
    Ok(())
}

/// How taking frames ended.
enum Taken {
    /// At a frame not yet done or not yet uploaded.
    Waiting,
    /// After the last uploaded frame.
    AtEnd,
}

/// A frame's store, running.
type Storing = Option<tokio::task::JoinHandle<Result<bool, sqlx::Error>>>;

/// Waits for the frame being stored: false if the run had moved (nothing
/// was stored).
async fn settle(storing: &mut Storing) -> Result<bool, TrackingError> {
    match storing.take() {
        None => Ok(true),
        Some(handle) => Ok(handle
            .await
            .map_err(|e| TrackingError::Interrupted(e.to_string()))??),
    }
}

/// Gives the tracker the run's next frames while each is done, storing
/// each frame's points (the last one's store may still run in `storing`).
async fn take_frames(
    state: &AppState,
    run: &TrackingRunRow,
    settings: &TrackingSettings,
    live: &mut Live,
    cameras: usize,
    storing: &mut Storing,
) -> Result<Taken, TrackingError> {
    let mut next = live
        .through
        .map_or(settings.first_frame(), |f| FrameNumber(f.0 + 1));
    loop {
        let frames = state
            .store
            .frames_to_track(run.sequence_id, next, FRAMES_PER_QUERY)
            .await?;
        let count = frames.len();
        for (frame, readiness) in frames {
            if frame != next && !run.finish_requested {
                // Frame `next` is not uploaded yet.
                return Ok(Taken::Waiting);
            }
            let (particles, recorded) = match readiness {
                FrameReadiness::Pending => return Ok(Taken::Waiting),
                FrameReadiness::Failed => (Vec::new(), None),
                FrameReadiness::Processed => {
                    let particles = load_particles(state, run.sequence_id, frame, cameras).await?;
                    let n = particles.len() as i64;
                    (particles, Some(n))
                }
            };
            let previous = live.through;
            let points = live.push(state, frame, particles).await?;
            let rows = live.rows(&points)?;
            if !settle(storing).await? {
                return Err(TrackingError::Moved);
            }
            let (store, id) = (state.store.clone(), run.id);
            *storing = Some(tokio::spawn(async move {
                store
                    .store_tracked_frame(id, previous, frame, recorded, &rows)
                    .await
            }));
            next = FrameNumber(frame.0 + 1);
        }
        if count < FRAMES_PER_QUERY as usize {
            return Ok(Taken::AtEnd);
        }
    }
}

/// A run's tracker as it was after its last stored frame: a fresh tracker
/// given the frames it took again, from their stored particles, its output
/// discarded (stored already).
async fn rebuild(
    state: &AppState,
    run: &TrackingRunRow,
    parameters: &TrackingParameters,
) -> Result<Live, TrackingError> {
    let mut live = Live::new(parameters)?;
    let frames = state.store.tracked_frames(run.id).await?;
    if frames.last().map(|(f, _)| *f) != run.tracked_through {
        return Err(TrackingError::Internal(format!(
            "run {} is tracked through {:?} but its last recorded frame is {:?}",
            run.id,
            run.tracked_through,
            frames.last().map(|(f, _)| f)
        )));
    }
    if !frames.is_empty() {
        tracing::info!(run = %run.id, frames = frames.len(), "rebuilding a tracker by replay");
    }
    let cameras = cameras_of(state, run.sequence_id).await?;
    for (frame, recorded) in frames {
        let particles = match recorded {
            None => Vec::new(),
            Some(count) => {
                let particles = load_particles(state, run.sequence_id, frame, cameras).await?;
                if particles.len() as i64 != count {
                    return Err(TrackingError::Diverged(format!(
                        "frame {frame} had {count} particles when it was tracked and has {} now \
                         (reprocessed?); start a new tracking run (POST \
                         /sequences/{}/tracking)",
                        particles.len(),
                        run.sequence_id
                    )));
                }
                particles
            }
        };
        live.push(state, frame, particles).await?;
    }
    Ok(live)
}

async fn cameras_of(state: &AppState, sequence_id: SequenceId) -> Result<usize, TrackingError> {
    let sequence = state
        .store
        .sequence(sequence_id)
        .await?
        .ok_or_else(|| TrackingError::Internal(format!("sequence {sequence_id} is gone")))?;
    Ok(state
        .store
        .calibration(sequence.calibration_id)
        .await?
        .map_or(0, |c| c.cameras as usize))
}

async fn load_particles(
    state: &AppState,
    sequence_id: SequenceId,
    frame: FrameNumber,
    cameras: usize,
) -> Result<Vec<Particle>, TrackingError> {
    let (_, blob, _) = state
        .store
        .frame_particles(sequence_id, frame)
        .await?
        .ok_or_else(|| TrackingError::Internal(format!("frame {frame}'s particles are gone")))?;
    Ok(codec::decode_particles(&blob, cameras)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(json: &str) -> TrackingSettings {
        serde_json::from_str(json).unwrap()
    }

    #[test]
    fn defaults_are_ptv_tracks_and_are_stored_filled_in() {
        let filled = settings(r#"{"max_velocity": 2.0}"#)
            .with_defaults()
            .unwrap();
        // `ptv track --max-velocity 2` without other flags.
        assert_eq!(filled.parameters(), TrackingParameters::new(2.0));
        assert_eq!(filled.first_frame, Some(FrameNumber(0)));
        assert!(filled.max_acceleration.is_some() && filled.fit_order.is_some());
        // Filling in again changes nothing.
        assert_eq!(filled.with_defaults().unwrap(), filled);
        let given = settings(
            r#"{"max_velocity": 2.0, "max_gap": 2, "min_length": 5, "first_frame": 10001}"#,
        )
        .with_defaults()
        .unwrap();
        assert_eq!(given.parameters().max_gap, 2);
        assert_eq!(given.parameters().min_length, 5);
        assert_eq!(given.first_frame(), FrameNumber(10001));
    }

    #[test]
    fn settings_the_tracker_refuses_name_the_field() {
        for (json, says) in [
            (r#"{"max_velocity": 0}"#, "max_velocity must be a positive"),
            (
                r#"{"max_velocity": -1.5}"#,
                "max_velocity must be a positive",
            ),
            (
                r#"{"max_velocity": 1, "max_acceleration": 0}"#,
                "max_acceleration",
            ),
            (r#"{"max_velocity": 1, "min_length": 0}"#, "min_length"),
            (r#"{"max_velocity": 1, "fit_order": 4}"#, "fit_order"),
            (
                r#"{"max_velocity": 1, "fit_half_window": 0}"#,
                "fit_half_window",
            ),
            (r#"{"max_velocity": 1, "first_frame": -3}"#, "first_frame"),
        ] {
            let error = settings(json).with_defaults().unwrap_err().to_string();
            assert!(error.starts_with("tracking: "), "{json}: {error}");
            assert!(error.contains(says), "{json}: {error}");
        }
        assert!(
            serde_json::from_str::<TrackingSettings>(r#"{"max_velocity": 1, "v": 2}"#).is_err()
        );
    }

    #[test]
    fn targets_are_written_as_the_csv_columns() {
        assert_eq!(targets_text(&[Some(3), None, Some(0)]), "3,-1,0");
        assert_eq!(targets_text(&[]), "");
    }
}
