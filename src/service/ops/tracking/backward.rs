//! A run's backward pass (issue 34; OpenPTV's `trackback_c`, OpenPTV
//! issue 146): once the run's forward tracking has taken its last frame,
//! every trajectory is extended backwards in time from its first points
//! with the forward linking's criteria run the other way, by the core's
//! own pass over the stored run ([`extend_run`], the pass `ptv track
//! --backward` runs: see [`crate::photogrammetry::track::backward`]).
//!
//! **When.** In the advance that ends the run (the client's `POST
//! .../tracking/finish` and every frame tracked), in the background task
//! that tracks the run, never in a request: the forward tracker's last
//! points, then the pass, then one write transaction that finishes the
//! run, replaces its points with the pass's and records what it added
//! ([`crate::service::store::Store::finish_tracking_run_with`]). A
//! failure (the database, a crash, a shutdown) leaves the run tracking
//! with its forward points whole, and the next advance rebuilds the
//! tracker by replay and does the pass again: nothing is lost or half
//! written. The run's lease is renewed while the pass runs, as while it
//! tracks.
//!
//! **What it reads.** The frames the tracker took (`tracking_frames`:
//! each one's particles from the store, a gap as no particles) and every
//! stored point. A particle the forward pass recovered from the images is
//! stored only as a point: it is given to the pass as a particle of its
//! frame after the frame's own, its sigma its frame's median (the
//! forward pass also floors it by its trajectory's, not stored); a
//! recovered particle no trajectory kept is not stored, and the pass does
//! not see it (`ptv track` does). So with recovery the stored
//! result may differ from the command line's in those few particles;
//! without, it is the command line's (tested).
//!
//! **Numbers.** A trajectory keeps its number; one joined onto the
//! trajectory ending before it is gone, its points under that one's
//! number. A new point's targets are its particle's.
//!
//! **Memory.** The pass holds the whole run: every particle given over
//! its frames and every point (the core's pass needs them all, as on the
//! command line), at most [`backward_need`]'s bytes (160 a particle and
//! 768 a point: 50 frames of 10,000 particles, 480,000 points, are about
//! 450 MB), taken from the service's memory budget before anything is
//! read; a run that needs more than the whole budget fails with a message
//! saying so and what to do.

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use super::live::{point_row, targets_text, TrackingError};
use super::{cameras_of, load_frame};
use crate::photogrammetry::track::backward::{extend_run, RunFrame};
use crate::photogrammetry::track::{
    BackwardSummary, Derivatives, ParticlePosition, TrackPoint, TrackingParameters,
};
use crate::service::infra::budget::{backward_need, BudgetError};
use crate::service::model::ids::MAX_FRAME_NUMBER;
use crate::service::ops::state::AppState;
use crate::service::store::{BackwardRow, FrameNumber, PointRow, TrackingRunRow};

/// The run's points after its backward pass (`last`: the forward
/// tracker's last points, not stored yet), and what the pass added.
pub(super) async fn extend(
    state: &Arc<AppState>,
    run: &TrackingRunRow,
    parameters: &TrackingParameters,
    last: Vec<PointRow>,
) -> Result<(Vec<PointRow>, BackwardRow), TrackingError> {
    let (particles, stored) = state.store.tracking_run_size(run.id).await?;
    let need = backward_need(
        run.id.0,
        particles.max(0) as u64,
        (stored.max(0) as u64).saturating_add(last.len() as u64),
    );
    let _grant = state.budget.acquire(&need).await.map_err(|e| match e {
        BudgetError::TooLarge(message) => TrackingError::Memory(format!(
            "{message}; start a new run with \"backward\": false (or with a later \
             first_frame), or give the service more memory"
        )),
        other => TrackingError::Interrupted(other.to_string()),
    })?;
    let mut rows = state
        .store
        .trajectory_points(
            run.id,
            (i64::MIN, i64::MAX),
            (FrameNumber(0), FrameNumber(MAX_FRAME_NUMBER)),
        )
        .await?;
    rows.extend(last);
    let cameras = cameras_of(state, run.sequence_id).await?;
    // Per frame: the particles given, then the recovered ones the points
    // hold (renumbered after the given ones, in index order), and the
    // given ones' targets.
    let mut recovered: HashMap<i64, Vec<&PointRow>> = HashMap::new();
    let mut given: HashMap<i64, i64> = HashMap::new();
    let tracked = state.store.tracked_frames(run.id).await?;
    for (frame, count) in &tracked {
        given.insert(frame.0, count.unwrap_or(0));
    }
    for row in &rows {
        let count = given.get(&row.frame.0).copied().ok_or_else(|| {
            TrackingError::Internal(format!(
                "run {}: trajectory {} has a point in frame {}, which the run did not track",
                run.id, row.trajectory, row.frame
            ))
        })?;
        if row.particle >= count {
            recovered.entry(row.frame.0).or_default().push(row);
        }
    }
    let mut frames = Vec::with_capacity(tracked.len());
    let mut targets: HashMap<i64, Vec<String>> = HashMap::new();
    // Per frame, the recovered particles' stored indices, in the order
    // the pass numbers them.
    let mut renumbered: HashMap<i64, Vec<i64>> = HashMap::new();
    for (frame, count) in &tracked {
        let mut particles: Vec<ParticlePosition> = Vec::new();
        if count.is_some() {
            let input = load_frame(state, run.sequence_id, *frame, cameras, false).await?;
            particles.extend(
                input
                    .particles
                    .iter()
                    .map(|p| ParticlePosition::seen_by(p.position, p.sigma, p.camera_count())),
            );
            targets.insert(
                frame.0,
                input
                    .particles
                    .iter()
                    .map(|p| targets_text(&p.targets))
                    .collect(),
            );
        }
        let given = particles.len();
        if let Some(mut points) = recovered.remove(&frame.0) {
            points.sort_by_key(|p| p.particle);
            for p in &points {
                let cameras = p.targets.split(',').filter(|t| *t != "-1").count();
                // Its sigma: the frame's median (the pass floors it so).
                particles.push(ParticlePosition::seen_by(
                    Point3::from(p.position),
                    Vector3::zeros(),
                    cameras,
                ));
            }
            renumbered.insert(frame.0, points.iter().map(|p| p.particle).collect());
        }
        frames.push(RunFrame {
            number: frame.0,
            particles,
            given,
        });
    }
    // The points as the pass takes them, and their targets by (frame,
    // stored index).
    let index_in = |frame: i64, particle: i64, given: usize| -> usize {
        if (particle as usize) < given {
            return particle as usize;
        }
        let list = &renumbered[&frame];
        given + list.binary_search(&particle).expect("listed above")
    };
    let given_of: HashMap<i64, usize> = frames.iter().map(|f| (f.number, f.given)).collect();
    let mut stored_targets: HashMap<(i64, usize), String> = HashMap::with_capacity(rows.len());
    let mut points = Vec::with_capacity(rows.len());
    for row in rows {
        let given = given_of[&row.frame.0];
        let particle = index_in(row.frame.0, row.particle, given);
        points.push(track_point(&row, particle));
        stored_targets.insert((row.frame.0, particle), row.targets);
    }
    let parameters = parameters.clone();
    let (points, summary) = state
        .cpu
        .run(move || extend_run(frames, points, &parameters))
        .await??;
    let rows = points
        .iter()
        .map(|p| {
            let given = given_of[&p.frame];
            let text = stored_targets
                .remove(&(p.frame, p.particle))
                .or_else(|| {
                    targets
                        .get(&p.frame)
                        .and_then(|t| t.get(p.particle))
                        .cloned()
                })
                .ok_or_else(|| {
                    TrackingError::Internal(format!(
                        "the backward pass gave frame {}'s particle {}, which has no targets",
                        p.frame, p.particle
                    ))
                })?;
            let stored = if p.particle < given {
                p.particle as i64
            } else {
                renumbered[&p.frame][p.particle - given]
            };
            let mut row = point_row(p, text);
            row.particle = stored;
            Ok(row)
        })
        .collect::<Result<Vec<_>, TrackingError>>()?;
    Ok((rows, summary_row(summary)))
}

fn summary_row(s: BackwardSummary) -> BackwardRow {
    BackwardRow {
        points: s.points as i64,
        lengthened: s.lengthened as i64,
        joined: s.joined as i64,
    }
}

/// A stored point as the tracker handed it out (its acceleration's sigma
/// is not stored: the pass needs none).
fn track_point(row: &PointRow, particle: usize) -> TrackPoint {
    let vector = |v: Option<[f64; 3]>| v.map_or(Vector3::repeat(f64::NAN), Vector3::from);
    TrackPoint {
        trajectory: row.trajectory as u64,
        frame: row.frame.0,
        particle,
        position: Point3::from(row.position),
        derivatives: Derivatives {
            velocity: vector(row.velocity),
            velocity_sigma: vector(row.velocity_sigma),
            acceleration: row.acceleration.map(Vector3::from),
            acceleration_sigma: None,
        },
    }
}
