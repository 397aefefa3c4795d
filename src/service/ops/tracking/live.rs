//! A tracking run's tracker in memory between frames ([`Live`]), the
//! rows it stores, and [`Trackers`], one slot per run in this process.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use crate::photogrammetry::correspond::Particle;
use crate::photogrammetry::track::recovery::FrameTargetsError;
use crate::photogrammetry::track::{
    FrameTargets, ImageSpaceRecovery, ParticlePosition, RecoveredParticles, TrackError, TrackPoint,
    Tracker, TrackingParameters,
};
use crate::photogrammetry::Target;
use crate::service::infra::budget::{tracking_need, BudgetError, MemoryBudget};
use crate::service::infra::codec::DamagedBlob;
use crate::service::ops::jobs::pool::{CpuError, CpuPool};
use crate::service::store::{FrameNumber, PointRow, TrackingRunId};

/// A run's tracker in memory, with what it needs between frames.
pub(super) struct Live {
    /// The last frame it took (as stored).
    pub(super) through: Option<FrameNumber>,
    /// Out of its slot while it works on the CPU pool (gone if that
    /// panicked).
    pub(super) tracker: Option<Tracker>,
    /// Whether it recovers particles from the images: frames are then
    /// given with their targets.
    pub(super) recovers: bool,
    /// The recent frames' particles' targets (`t0,t1,...` per particle,
    /// those recovered after the frame's own), for the points that become
    /// final later.
    pub(super) targets: VecDeque<(FrameNumber, Vec<String>)>,
    /// Frames kept in `targets`.
    pub(super) keep: i64,
}

/// A frame as the tracker takes it: its particles (none for a gap) and,
/// for a tracker that recovers, its targets per camera.
pub(super) struct FrameInput {
    pub(super) particles: Vec<Particle>,
    pub(super) targets: Option<Vec<Vec<Target>>>,
}

impl Live {
    pub(super) fn new(
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
    pub(super) async fn push(
        &mut self,
        budget: &MemoryBudget,
        cpu: &CpuPool,
        frame: FrameNumber,
        input: FrameInput,
    ) -> Result<Vec<TrackPoint>, TrackingError> {
        let FrameInput { particles, targets } = input;
        // The memory of this step, from the particles held and the frame's
        // (module `budget`), held while the tracker works on it only.
        let held: usize = self.targets.iter().map(|(_, p)| p.len()).sum();
        let target_count: usize = targets.iter().flatten().map(Vec::len).sum();
        let need = tracking_need(
            frame.0,
            held as u64,
            particles.len() as u64,
            target_count as u64,
        );
        let _grant = budget.acquire(&need).await.map_err(|e| match e {
            BudgetError::TooLarge(message) => TrackingError::Memory(message),
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
        let (tracker, pushed) = cpu
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
    pub(super) fn rows(&self, points: &[TrackPoint]) -> Result<Vec<PointRow>, TrackingError> {
        rows(&self.targets, points)
    }
}

/// Adds the particles the tracker recovered to their frames' targets in
/// `held` (numbered after the frame's own, as the tracker numbers them).
pub(super) fn hold_recovered(
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
pub(super) fn rows(
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
pub(super) fn targets_text(targets: &[Option<usize>]) -> String {
    targets
        .iter()
        .map(|t| t.map_or_else(|| "-1".to_owned(), |t| t.to_string()))
        .collect::<Vec<_>>()
        .join(",")
}

pub(super) fn point_row(p: &TrackPoint, targets: String) -> PointRow {
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
    Database(#[from] crate::service::store::StoreError),
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
    pub(super) fn is_fatal(&self) -> bool {
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
    pub(super) slots: Mutex<HashMap<TrackingRunId, Arc<tokio::sync::Mutex<Option<Live>>>>>,
}

impl std::fmt::Debug for Trackers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let runs = self.slots.lock().map(|s| s.len()).unwrap_or_default();
        f.debug_struct("Trackers").field("runs", &runs).finish()
    }
}

impl Trackers {
    pub(super) fn slot(&self, id: TrackingRunId) -> Arc<tokio::sync::Mutex<Option<Live>>> {
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
