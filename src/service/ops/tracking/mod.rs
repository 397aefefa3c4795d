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
//! **Backward.** A run whose settings have `backward` (on by default)
//! extends its trajectories backwards once it has taken its last frame,
//! before it is `finished` ([`backward`]).
//!
//! **Runs.** A new run (other settings) supersedes the current one, whose
//! points so far stay readable (`?run=`); frames of a finished run
//! uploaded after it finished are not in it (start a new run).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;

pub mod backward;
pub mod live;

use self::live::{hold_recovered, rows, FrameInput, Live, TrackingError};
use crate::formats;
use crate::photogrammetry::track::ImageSpaceRecovery;
use crate::service::infra::codec::{self, CameraTargets};
use crate::service::infra::errors::error_chain;
use crate::service::model::tracking_settings::TrackingSettings;
use crate::service::ops::events::Change;
use crate::service::ops::state::AppState;
use crate::service::store::{
    FrameNumber, FrameReadiness, LeaseToken, SequenceId, TrackingRunId, TrackingRunRow,
    TrackingState,
};

/// Advances the sequence's current run in the background (after a frame
/// job, a finish request, a new run).
/// A process without workers (`ptv serve --workers 0`) tracks nothing:
/// the worker processes' polls find the run.
pub fn kick(state: &Arc<AppState>, sequence_id: SequenceId) {
    if state.config.workers == 0 {
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
    let settings = run.parameters.clone();
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
        drop(held);
        let finished = if settings.extends_backward() {
            // The pass back over the whole run, then its points replace
            // the stored ones in the transaction that finishes it.
            let (rows, added) = backward::extend(state, &run, &settings.parameters(), rows).await?;
            state
                .store
                .finish_tracking_run_with((id, token), live.through, &rows, Some(added))
                .await?
        } else {
            state
                .store
                .finish_tracking_run((id, token), live.through, &rows)
                .await?
        };
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
type Storing = Option<tokio::task::JoinHandle<Result<bool, crate::service::store::StoreError>>>;

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
            let points = live.push(&state.budget, &state.cpu, frame, input).await?;
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
        live.push(&state.budget, &state.cpu, frame, input).await?;
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
    let recovery = ImageSpaceRecovery::new(cameras, sequence.parameters.matching().tolerance)
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
        for CameraTargets { camera, data, .. } in
            state.store.frame_targets(sequence_id, frame).await?
        {
            let slot = usize::try_from(camera)
                .ok()
                .and_then(|c| per_camera.get_mut(c))
                .ok_or_else(|| {
                    TrackingError::Internal(format!(
                        "frame {frame} has targets of camera {camera}, the calibration {cameras} \
                         cameras"
                    ))
                })?;
            *slot = codec::decode_targets(&data)?;
        }
        Some(per_camera)
    } else {
        None
    };
    Ok(FrameInput { particles, targets })
}

#[cfg(test)]
mod tests {
    use super::live::targets_text;
    use super::*;
    use crate::photogrammetry::track::TrackingParameters;

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
