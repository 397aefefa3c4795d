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
//! core's own validation (a 422 naming the field), and against the
//! sequence's observation volume by the rule `ptv track` applies
//! ([`TrackingParameters::check_volume`]: a velocity limit above the
//! volume's diagonal is refused, since it describes no motion there and
//! only widens every search).
//!
//! **Image-space recovery, as `ptv track`.** A run recovers the particles
//! the correspondences missed (Willneff 2003; see
//! [`crate::photogrammetry::track::recovery`]): each processed frame is
//! given to the tracker with its stored targets per camera
//! ([`Tracker::push_with_targets`]), built by the one function `ptv track`
//! uses too ([`FrameTargets::of_particles`]: the targets the particles
//! use, the frame's noise by `frame_noise`), and the recovery projects
//! with the calibration recorded with the run (the sequence's when the run
//! started) within the sequence's matching tolerance, as `ptv track
//! --targets` uses its `--tolerance` for both. So a run gives `ptv track`'s
//! trajectories on the same targets. A recovered particle is numbered
//! after its frame's particles (as the tracker numbers it) and stored only
//! as a trajectory point, with its targets; the frame's particle list (and
//! its per-particle trajectory ids) does not include it. `"recovery":
//! false` switches it off (`ptv track --no-recovery`). Settings stored
//! before the setting existed have no `recovery`, and such runs were
//! tracked without it: they go on without it ([`TrackingSettings::recovers`]).
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
//! recorded frames again, from their stored particles and targets (a
//! frame's targets are never replaced), and discarding what it hands out
//! (already stored). The tracker, its recovery included, is deterministic,
//! and the recovery's calibration is the run's, so the
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
use std::time::Duration;

use tokio::sync::watch;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::app::AppState;
use super::codec::{self, DamagedBlob};
use super::events::Change;
use super::jobs::{error_chain, CpuError};
use super::parameters::SequenceParameters;
use super::store::{
    FrameNumber, FrameReadiness, LeaseToken, PointRow, SequenceId, TrackingRunId, TrackingRunRow,
    TrackingState, MAX_FRAME_NUMBER,
};
use crate::formats;
use crate::photogrammetry::correspond::Particle;
use crate::photogrammetry::track::recovery::FrameTargetsError;
use crate::photogrammetry::track::{
    FrameTargets, ImageSpaceRecovery, ParticlePosition, RecoveredParticles, TrackError, TrackPoint,
    Tracker, TrackingParameters,
};
use crate::photogrammetry::{Target, Volume};

/// How to track a sequence (all but `max_velocity` optional; the defaults
/// are `ptv track`'s).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackingSettings {
    /// The largest displacement of a particle between two frames (mm per
    /// frame): above zero, and at most the diagonal of the sequence's
    /// observation volume (its `matching.volume`, else its calibration's
    /// default volume): a larger limit describes no motion in the volume
    /// and only makes every particle a candidate for every trajectory.
    pub max_velocity: f64,
    /// The largest change of velocity between two frames (mm per frame²),
    /// at most twice the volume's diagonal [default: half of max_velocity].
    #[serde(default)]
    pub max_acceleration: Option<f64>,
    /// Frames a trajectory may miss and continue, 0 to 2 [default: 1].
    #[serde(default)]
    pub max_gap: Option<usize>,
    /// The fewest points of a trajectory that is stored, 1 to 100
    /// (trajectories are held in memory until they have that many)
    /// [default: 3].
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
    #[schema(value_type = Option<i64>, minimum = 0, maximum = 4_294_967_295_u64)]
    pub first_frame: Option<FrameNumber>,
    /// Look in each frame's targets for the particles the correspondences
    /// missed, where a trajectory's prediction has none (Willneff's
    /// image-space recovery, as `ptv track` does unless `--no-recovery`;
    /// within the sequence's matching `tolerance`, with the calibration
    /// the sequence has when the run starts) [default: true]. A recovered
    /// particle is a point of its trajectory whose `particle` index is at
    /// or above its frame's particle count. Runs stored before this
    /// setting existed show false: they were tracked without.
    #[serde(default)]
    pub recovery: Option<bool>,
}

/// Settings the tracker refuses.
#[derive(Debug, thiserror::Error)]
pub enum InvalidTrackingSettings {
    /// A parameter out of range (the core's check).
    #[error("tracking: {0}")]
    Parameter(#[from] TrackError),
    /// A first frame that is no frame number.
    #[error("tracking: first_frame must be a frame number, 0 to {MAX_FRAME_NUMBER}, got {0}")]
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
        if !(0..=MAX_FRAME_NUMBER).contains(&first_frame.0) {
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
            recovery: Some(self.recovery.unwrap_or(true)),
        })
    }

    /// Checks the limits against the sequence's observation volume (its
    /// matcher's: the `matching.volume` given, else the default volume of
    /// its calibration), by the rule `ptv track` applies too
    /// ([`TrackingParameters::check_volume`]: `max_velocity` at most the
    /// volume's diagonal, `max_acceleration` at most twice that).
    pub fn check_volume(&self, volume: &Volume) -> Result<(), InvalidTrackingSettings> {
        Ok(self.parameters().check_volume(volume)?)
    }

    fn first_frame(&self) -> FrameNumber {
        self.first_frame.unwrap_or(FrameNumber(0))
    }

    /// Whether a stored run recovers particles from the images. Every run
    /// is stored with its settings filled in ([`TrackingSettings::with_defaults`]:
    /// true unless switched off), so `recovery` is absent only from runs
    /// stored before the setting existed, which were tracked without it:
    /// those go on without it (a replay with it would not give what they
    /// stored).
    pub fn recovers(&self) -> bool {
        self.recovery.unwrap_or(false)
    }

    /// The settings of a stored run as the API shows them (`recovery`
    /// as [`TrackingSettings::recovers`] reads it).
    pub fn as_stored(self) -> TrackingSettings {
        TrackingSettings {
            recovery: Some(self.recovers()),
            ..self
        }
    }
}

/// A run's tracker in memory, with what it needs between frames.
struct Live {
    /// The last frame it took (as stored).
    through: Option<FrameNumber>,
    /// Out of its slot while it works on the CPU pool (gone if that
    /// panicked).
    tracker: Option<Tracker>,
    /// Whether it recovers particles from the images: frames are then
    /// given with their targets.
    recovers: bool,
    /// The recent frames' particles' targets (`t0,t1,...` per particle,
    /// those recovered after the frame's own), for the points that become
    /// final later.
    targets: VecDeque<(FrameNumber, Vec<String>)>,
    /// Frames kept in `targets`.
    keep: i64,
}

/// A frame as the tracker takes it: its particles (none for a gap) and,
/// for a tracker that recovers, its targets per camera.
struct FrameInput {
    particles: Vec<Particle>,
    targets: Option<Vec<Vec<Target>>>,
}

impl Live {
    fn new(
        parameters: &TrackingParameters,
        recovery: Option<ImageSpaceRecovery>,
    ) -> Result<Live, TrackError> {
        let recovers = recovery.is_some();
        let tracker = match recovery {
            Some(recovery) => Tracker::with_recovery(parameters.clone(), recovery)?,
            None => Tracker::new(parameters.clone())?,
        };
        Ok(Live {
            through: None,
            tracker: Some(tracker),
            recovers,
            targets: VecDeque::new(),
            // A point becomes final at most this many frames after its own
            // (as `ptv track` holds frames); a frame's recovered particles
            // come sooner, when it leaves the tracker's look-ahead.
            keep: parameters.report_delay() as i64,
        })
    }

    /// Takes `frame`: the tracker's new final points. Particles it
    /// recovered meanwhile are added to their frames' targets.
    async fn push(
        &mut self,
        state: &AppState,
        frame: FrameNumber,
        input: FrameInput,
    ) -> Result<Vec<TrackPoint>, TrackingError> {
        let FrameInput { particles, targets } = input;
        // The memory of this step, from the particles held and the frame's
        // (module `budget`), held while the tracker works on it only.
        let held: usize = self.targets.iter().map(|(_, p)| p.len()).sum();
        let target_count: usize = targets.iter().flatten().map(Vec::len).sum();
        let need = super::budget::tracking_need(
            frame.0,
            held as u64,
            particles.len() as u64,
            target_count as u64,
        );
        let _grant = state.budget.acquire(&need).await.map_err(|e| match e {
            super::jobs::JobError::Failed(message) => TrackingError::Memory(message),
            other => TrackingError::Interrupted(other.to_string()),
        })?;
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
        let tracker = self
            .tracker
            .take()
            .ok_or_else(|| TrackingError::Internal("the tracker was lost to a panic".to_owned()))?;
        let (tracker, pushed) = state
            .cpu
            .run(move || {
                let mut tracker = tracker;
                let positions: Vec<ParticlePosition> = particles
                    .iter()
                    .map(|p| ParticlePosition::seen_by(p.position, p.sigma, p.camera_count()))
                    .collect();
                let pushed = match targets {
                    // The same frame targets and noise as `ptv track`.
                    Some(targets) => FrameTargets::of_particles(&targets, &particles)
                        .map_err(|error| TrackingError::Targets { frame, error })
                        .and_then(|targets| {
                            Ok(tracker.push_with_targets(frame.0, positions, targets)?)
                        }),
                    None => tracker.push(frame.0, positions).map_err(Into::into),
                };
                let recovered = tracker.take_recovered();
                (tracker, pushed.map(|points| (points, recovered)))
            })
            .await?;
        self.tracker = Some(tracker);
        self.through = Some(frame);
        let (points, recovered) = pushed?;
        hold_recovered(&mut self.targets, recovered)?;
        Ok(points)
    }

    /// The points as rows, with their particles' targets.
    fn rows(&self, points: &[TrackPoint]) -> Result<Vec<PointRow>, TrackingError> {
        rows(&self.targets, points)
    }
}

/// Adds the particles the tracker recovered to their frames' targets in
/// `held` (numbered after the frame's own, as the tracker numbers them).
fn hold_recovered(
    held: &mut VecDeque<(FrameNumber, Vec<String>)>,
    recovered: Vec<RecoveredParticles>,
) -> Result<(), TrackingError> {
    for frame in recovered {
        let (_, targets) = held
            .iter_mut()
            .find(|(f, t)| f.0 == frame.frame && t.len() == frame.first)
            .ok_or_else(|| {
                TrackingError::Internal(format!(
                    "frame {}'s recovered particles came after the frame was let go",
                    frame.frame
                ))
            })?;
        targets.extend(frame.particles.iter().map(|p| targets_text(&p.targets)));
    }
    Ok(())
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
    /// A frame's stored particles name targets it does not have (the run
    /// fails).
    #[error("frame {frame}'s particles do not fit its stored targets: {error}")]
    Targets {
        /// The frame.
        frame: FrameNumber,
        /// What does not fit.
        error: FrameTargetsError,
    },
    /// The image-space recovery cannot be set up with the run's
    /// calibration and the sequence's tolerance (the run fails).
    #[error("the image-space recovery: {0}; start a new run with \"recovery\": false")]
    Recovery(String),
    /// A frame needs more memory than the whole budget (the run fails).
    #[error("{0}")]
    Memory(String),
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
/// A process without workers (`ptv serve --workers 0`) tracks nothing:
/// the worker processes' polls find the run.
pub fn kick(state: &Arc<AppState>, sequence_id: SequenceId) {
    if state.config.worker_count() == 0 {
        return;
    }
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

/// How often a process with workers looks for runs to advance whose frames
/// other processes processed (and renews the leases of the runs it holds;
/// at most a third of the lease apart).
const TRACKING_POLL: Duration = Duration::from_secs(1);

/// Advances, until `stopped`, every run still tracking that this process
/// holds or may take (its lease free or run out: at start-up, the runs a
/// stopped process left, and later those whose holder died), every
/// [`TRACKING_POLL`]: frames processed by other processes (`ptv worker`)
/// kick no tracker here, so the holder looks for them.
pub fn spawn_tracking(state: Arc<AppState>, mut stopped: watch::Receiver<bool>) {
    tokio::spawn(async move {
        let every = TRACKING_POLL.min(state.config.lease.heartbeat());
        loop {
            match state.store.tracking_runs_to_advance(&state.instance).await {
                Ok(runs) => {
                    for id in runs {
                        if *stopped.borrow() {
                            return;
                        }
                        advance_logged(&state, id).await;
                    }
                }
                Err(error) => tracing::warn!(%error, "cannot list the tracking runs to advance"),
            }
            tokio::select! {
                _ = tokio::time::sleep(every) => {}
                _ = stopped.changed() => return,
            }
        }
    });
}

/// Renews a run's lease every third of it while an advance runs (a
/// replay may take longer than the lease); stops when dropped.
struct LeaseHeartbeat(tokio::task::JoinHandle<()>);

impl LeaseHeartbeat {
    fn start(state: &Arc<AppState>, id: TrackingRunId) -> LeaseHeartbeat {
        let state = state.clone();
        LeaseHeartbeat(tokio::spawn(async move {
            let lease = state.config.lease.duration();
            loop {
                tokio::time::sleep(state.config.lease.heartbeat()).await;
                match state
                    .store
                    .take_tracking_lease(id, &state.instance, lease)
                    .await
                {
                    Ok(Some(_)) => {}
                    Ok(None) => {
                        tracing::warn!(run = %id, "lost the tracking run's lease; what this \
                                       process tracks of it from now on is not stored");
                        return;
                    }
                    Err(error) => {
                        tracing::warn!(run = %id, %error, "cannot renew a tracking lease")
                    }
                }
            }
        }))
    }
}

impl Drop for LeaseHeartbeat {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn advance_logged(state: &Arc<AppState>, id: TrackingRunId) {
    if let Err(error) = advance(state, id).await {
        let message = error_chain(&error);
        if error.is_fatal() {
            tracing::warn!(run = %id, %message, "tracking run failed");
            if let Err(error) = state.store.fail_tracking_run(id, &message).await {
                tracing::error!(run = %id, %error, "cannot record a tracking run's failure");
            } else if let Ok(Some(run)) = state.store.tracking_run(id).await {
                let ended = Change::TrackingEnded {
                    run_id: id,
                    finished: false,
                };
                state.events.send(run.sequence_id, ended);
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
    let lease = state.config.lease.duration();
    let Some(token) = state
        .store
        .take_tracking_lease(id, &state.instance, lease)
        .await?
    else {
        // Another process holds the run's tracker (or the run ended).
        *guard = None;
        return Ok(());
    };
    let _heartbeat = LeaseHeartbeat::start(state, id);
    let Some(run) = state.store.tracking_run(id).await? else {
        return Ok(());
    };
    if run.state != TrackingState::Tracking {
        *guard = None;
        state.trackers.forget(id);
        return Ok(());
    }
    let settings: TrackingSettings = serde_json::from_str(&run.parameters)?;
    if guard.as_ref().map(|l| l.through) != Some(run.tracked_through) {
        *guard = None;
        *guard = Some(rebuild(state, &run, &settings).await?);
    }
    let live = guard.as_mut().expect("a tracker was put in");
    let cameras = cameras_of(state, run.sequence_id).await?;
    // A frame's points are stored while the tracker takes the next frame;
    // every way out waits for that store first, so that the tracker in
    // memory and the stored progress agree whenever the lock is free.
    let mut storing = None;
    let taken = take_frames(state, (&run, token), &settings, live, cameras, &mut storing).await;
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
        let (points, recovered) = state
            .cpu
            .run(move || tracker.finish_with_recovered())
            .await?;
        let mut held = live.targets;
        hold_recovered(&mut held, recovered)?;
        let rows = rows(&held, &points)?;
        let finished = state
            .store
            .finish_tracking_run((id, token), live.through, &rows)
            .await?;
        if finished {
            let ended = Change::TrackingEnded {
                run_id: id,
                finished: true,
            };
            state.events.send(run.sequence_id, ended);
        }
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
    (run, token): (&TrackingRunRow, LeaseToken),
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
            let (input, recorded) = match readiness {
                FrameReadiness::Pending => return Ok(Taken::Waiting),
                FrameReadiness::Failed => (FrameInput::gap(), None),
                FrameReadiness::Processed => {
                    let input =
                        load_frame(state, run.sequence_id, frame, cameras, live.recovers).await?;
                    let n = input.particles.len() as i64;
                    (input, Some(n))
                }
            };
            let previous = live.through;
            let points = live.push(state, frame, input).await?;
            let rows = live.rows(&points)?;
            if !settle(storing).await? {
                return Err(TrackingError::Moved);
            }
            let (store, id) = (state.store.clone(), run.id);
            let (events, sequence_id) = (state.events.clone(), run.sequence_id);
            *storing = Some(tokio::spawn(async move {
                let stored = store
                    .store_tracked_frame((id, token), previous, frame, recorded, &rows)
                    .await;
                if matches!(stored, Ok(true)) {
                    let tracked_through = frame;
                    let change = Change::Tracked {
                        run_id: id,
                        tracked_through,
                    };
                    events.send(sequence_id, change);
                }
                stored
            }));
            next = FrameNumber(frame.0 + 1);
        }
        if count < FRAMES_PER_QUERY as usize {
            return Ok(Taken::AtEnd);
        }
    }
}

/// A run's tracker as it was after its last stored frame: a fresh tracker
/// given the frames it took again, from their stored particles (and
/// targets, where it recovers: the recovery is as deterministic as the
/// linking), its output discarded (stored already).
async fn rebuild(
    state: &AppState,
    run: &TrackingRunRow,
    settings: &TrackingSettings,
) -> Result<Live, TrackingError> {
    let recovery = recovery(state, run, settings).await?;
    let mut live = Live::new(&settings.parameters(), recovery)?;
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
        let input = match recorded {
            None => FrameInput::gap(),
            Some(count) => {
                let input =
                    load_frame(state, run.sequence_id, frame, cameras, live.recovers).await?;
                if input.particles.len() as i64 != count {
                    return Err(TrackingError::Diverged(format!(
                        "frame {frame} had {count} particles when it was tracked and has {} now \
                         (reprocessed?); start a new tracking run (POST \
                         /sequences/{}/tracking)",
                        input.particles.len(),
                        run.sequence_id
                    )));
                }
                input
            }
        };
        live.push(state, frame, input).await?;
    }
    Ok(live)
}

/// The run's image-space recovery: `None` where its settings switch it
/// off; else the calibration recorded with the run (the sequence's when it
/// started) and the sequence's matching tolerance, as `ptv track
/// --targets` takes `--tolerance` for both.
async fn recovery(
    state: &AppState,
    run: &TrackingRunRow,
    settings: &TrackingSettings,
) -> Result<Option<ImageSpaceRecovery>, TrackingError> {
    if !settings.recovers() {
        return Ok(None);
    }
    let calibration_id = run.calibration_id.ok_or_else(|| {
        TrackingError::Internal(format!(
            "run {} recovers but has no calibration recorded",
            run.id
        ))
    })?;
    let calibration = state
        .store
        .calibration(calibration_id)
        .await?
        .ok_or_else(|| TrackingError::Internal(format!("calibration {calibration_id} is gone")))?;
    let (cameras, _) = formats::calibration::stored_from_json_with_splitter(
        &calibration.model,
        "the stored calibration",
    )
    .map_err(|e| TrackingError::Recovery(e.to_string()))?;
    let sequence = state
        .store
        .sequence(run.sequence_id)
        .await?
        .ok_or_else(|| TrackingError::Internal(format!("sequence {} is gone", run.sequence_id)))?;
    let parameters: SequenceParameters = serde_json::from_str(&sequence.parameters)?;
    let recovery = ImageSpaceRecovery::new(cameras, parameters.matching().tolerance)
        .map_err(|e| TrackingError::Recovery(e.to_string()))?;
    Ok(Some(recovery))
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

impl FrameInput {
    /// A frame that failed.
    fn gap() -> FrameInput {
        FrameInput {
            particles: Vec::new(),
            targets: None,
        }
    }
}

/// A processed frame's stored particles, and with `targets` its stored
/// targets per camera (a camera without a row has none).
async fn load_frame(
    state: &AppState,
    sequence_id: SequenceId,
    frame: FrameNumber,
    cameras: usize,
    targets: bool,
) -> Result<FrameInput, TrackingError> {
    let (_, blob, _) = state
        .store
        .frame_particles(sequence_id, frame)
        .await?
        .ok_or_else(|| TrackingError::Internal(format!("frame {frame}'s particles are gone")))?;
    let particles = codec::decode_particles(&blob, cameras)?;
    let targets = if targets {
        let mut per_camera = vec![Vec::new(); cameras];
        for (camera, _, blob) in state.store.frame_targets(sequence_id, frame).await? {
            let slot = usize::try_from(camera)
                .ok()
                .and_then(|c| per_camera.get_mut(c))
                .ok_or_else(|| {
                    TrackingError::Internal(format!(
                        "frame {frame} has targets of camera {camera}, the calibration {cameras} \
                         cameras"
                    ))
                })?;
            *slot = codec::decode_targets(&blob)?;
        }
        Some(per_camera)
    } else {
        None
    };
    Ok(FrameInput { particles, targets })
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
        // Recovery: on unless switched off, and stored filled in.
        assert_eq!(filled.recovery, Some(true));
        assert!(filled.recovers());
        let off = settings(r#"{"max_velocity": 2.0, "recovery": false}"#)
            .with_defaults()
            .unwrap();
        assert_eq!(off.recovery, Some(false));
        assert!(!off.recovers());
        // A run stored before the setting existed was tracked without it,
        // and is shown and resumed so.
        let old = settings(r#"{"max_velocity": 2.0, "max_acceleration": 1.0, "max_gap": 1}"#);
        assert!(!old.recovers());
        assert_eq!(old.as_stored().recovery, Some(false));
        assert!(serde_json::from_str::<TrackingSettings>(
            r#"{"max_velocity": 1, "recovery": "yes"}"#
        )
        .unwrap_err()
        .to_string()
        .contains("expected a boolean"));
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
