//! Calibration health during a run (issue 33): the core's
//! [`crate::photogrammetry::health`] fed a sequence's frames as they are
//! processed.
//!
//! - **Per frame.** The frame job measures, with the particles it has just
//!   matched, each camera's disparity of well-matched particles (seen by at
//!   least 3 cameras, within the matching tolerance, the best 2,000) over
//!   the frame and per sub-volume of a 2 x 2 x 2 grid over the sequence's
//!   volume ([`frame_health`], on the CPU pool with the matching), and
//!   stores it with the particles ([`rows_of`]): at most cameras x (1 + 8)
//!   rows a frame, 144 at 16 cameras. Reprocessing with another
//!   calibration replaces them with the particles.
//! - **Per sequence, in frame order.** After every frame job (succeeded or
//!   failed) and reprocessing job, [`advance`] feeds the sequence's drift
//!   monitor ([`DriftMonitor`]: baseline the first `window` frames' mean,
//!   alarm when the last `window` frames' mean moves `threshold_px` from
//!   it; the sequence's `health` settings, 0.3 px over 50 frames by
//!   default) the frames done after the last one it took, in frame order:
//!   processed with the monitor's calibration, or failed (a gap, passed
//!   over), stopping at the first still queued or running, or at a frame
//!   number not uploaded yet (as tracking does: frames are numbered one
//!   after the other, from the first uploaded). So the alarm's
//!   frame does not depend on the order in which workers finish frames. The
//!   monitor is stored (JSON, one window of frame means per camera) in one
//!   statement fenced on the frame it had reached: of two processes
//!   advancing at once, one writes and the other reads again. The process
//!   whose write took a frame that raised an alarm announces it
//!   ([`Change::CalibrationDrift`]) after the write. A frame that failed
//!   and was passed over as a gap stays a gap if it is retried later.
//! - **Another calibration** (a self-calibration switched the sequence)
//!   starts a new monitor: its baseline is the new calibration's first
//!   frames, taken as reprocessing replaces their particles.
//!
//! Reading ([`summary`]) advances a copy of the stored monitor in memory
//! over the frames done since, so the summary is current even when the
//! process that finished the last frame stopped before advancing.

use std::sync::Arc;

use crate::photogrammetry::correspond::Particle;
use crate::photogrammetry::health::{
    frame_health as measure, CameraHealth, Disparity, DriftAlarm, DriftMonitor, FrameHealth,
    HealthOptions,
};
use crate::photogrammetry::{Camera, Target, Volume};
use crate::service::model::parameters::HealthSettings;
use crate::service::ops::events::Change;
use crate::service::ops::state::AppState;
use crate::service::store::{
    CalibrationId, FrameNumber, HealthFrame, HealthRow, HealthState, SequenceId,
};

/// Sub-volumes per axis.
pub const GRID: [usize; 3] = [2, 2, 2];

/// Frames read per query while advancing.
const BATCH: u32 = 500;

/// The most frames one advance (or one summary) takes: an advance after a
/// frame job normally takes one; after a long stop, the rest follow with
/// the next jobs (or the next read).
const MAX_FRAMES_PER_STEP: usize = 20 * BATCH as usize;

/// How often an advance reads again after another process advanced the
/// same monitor first.
const ATTEMPTS: usize = 8;

/// A frame's calibration health: `targets` per camera, the `particles`
/// matched from them with `cameras`, in `volume`; particles within
/// `tolerance` px count as well matched. Pure (the CPU pool runs it).
pub fn frame_health(
    cameras: &[Camera],
    targets: &[Vec<Target>],
    particles: &[Particle],
    volume: &Volume,
    tolerance: f64,
) -> FrameHealth {
    let mut options = HealthOptions::new(*volume, tolerance);
    options.grid = GRID;
    measure(cameras, targets, particles, &options)
}

/// The rows a frame's health is stored as: per camera the whole frame
/// (cell -1, also when empty) and each sub-volume that had particles. A
/// disparity that is not finite (no projection gives one; a database
/// column cannot hold it) is stored as none.
pub fn rows_of(health: &FrameHealth) -> Vec<HealthRow> {
    let row = |camera: usize, cell: i64, d: &Disparity| {
        let finite = d.mean_px.iter().all(|v| v.is_finite()) && d.rms_px.is_finite();
        HealthRow {
            camera: camera as i64,
            cell,
            count: if finite { d.count as i64 } else { 0 },
            mean: if finite { d.mean_px } else { [0.0; 2] },
            rms: if finite { d.rms_px } else { 0.0 },
        }
    };
    let mut rows = Vec::new();
    for (camera, h) in health.cameras.iter().enumerate() {
        rows.push(row(camera, -1, &h.all));
        for (cell, d) in h.cells.iter().enumerate() {
            if d.count > 0 {
                rows.push(row(camera, cell as i64, d));
            }
        }
    }
    rows
}

/// A frame's whole-frame health from its rows, for `cameras` cameras.
fn whole_frame(rows: &[HealthRow], cameras: usize) -> FrameHealth {
    let mut health = FrameHealth {
        grid: GRID,
        cameras: vec![CameraHealth::default(); cameras],
    };
    for row in rows.iter().filter(|r| r.cell == -1) {
        if let Some(h) = usize::try_from(row.camera)
            .ok()
            .and_then(|c| health.cameras.get_mut(c))
        {
            h.all = Disparity {
                count: usize::try_from(row.count).unwrap_or(0),
                mean_px: row.mean,
                rms_px: row.rms,
            };
        }
    }
    health
}

/// A sequence's monitor, advanced in memory.
#[derive(Clone, Debug)]
pub struct Monitor {
    /// The calibration it follows (the sequence's).
    pub calibration_id: CalibrationId,
    /// The settings.
    pub settings: HealthSettings,
    /// The monitor.
    pub monitor: DriftMonitor,
    /// The last frame taken.
    pub through: Option<FrameNumber>,
    /// Frames taken with health rows.
    pub frames: i64,
    /// Where the stored one was (None: no row).
    stored: Option<(CalibrationId, Option<FrameNumber>)>,
    /// The alarms the frames taken here raised.
    pub raised: Vec<DriftAlarm>,
    /// Whether it moved from the stored one.
    changed: bool,
}

/// Why a monitor could not be read.
#[derive(Debug, thiserror::Error)]
pub enum HealthError {
    /// The database failed.
    #[error(transparent)]
    Database(#[from] crate::service::store::StoreError),
    /// The sequence does not exist.
    #[error("sequence {0} does not exist")]
    NoSequence(SequenceId),
    /// Its stored parameters or calibration do not read.
    #[error("sequence {0}'s stored {1} does not read")]
    Stored(SequenceId, &'static str),
}

/// The sequence's monitor, the stored one advanced in memory over the
/// frames done since (at most [`MAX_FRAMES_PER_STEP`]).
async fn step(state: &AppState, sequence_id: SequenceId) -> Result<Monitor, HealthError> {
    let sequence = state
        .store
        .sequence(sequence_id)
        .await?
        .ok_or(HealthError::NoSequence(sequence_id))?;
    let settings = sequence.parameters.health();
    let cameras = state
        .store
        .calibration(sequence.calibration_id)
        .await?
        .map(|c| usize::try_from(c.cameras).unwrap_or(0))
        .ok_or(HealthError::Stored(sequence_id, "calibration"))?;
    let fresh = || DriftMonitor::new(cameras, settings.threshold_px, settings.window as usize);
    let stored = state.store.health_state(sequence_id).await?;
    let mut monitor = match &stored {
        Some(HealthState {
            calibration_id,
            through_frame,
            frames,
            monitor,
            ..
        }) if *calibration_id == sequence.calibration_id => Monitor {
            calibration_id: *calibration_id,
            settings: settings.clone(),
            monitor: serde_json::from_str(monitor)
                .map_err(|_| HealthError::Stored(sequence_id, "drift monitor"))?,
            through: *through_frame,
            frames: *frames,
            stored: Some((*calibration_id, *through_frame)),
            raised: Vec::new(),
            changed: false,
        },
        other => Monitor {
            calibration_id: sequence.calibration_id,
            settings: settings.clone(),
            monitor: fresh(),
            through: None,
            frames: 0,
            stored: other.as_ref().map(|s| (s.calibration_id, s.through_frame)),
            raised: Vec::new(),
            // A monitor of another calibration is replaced even before a
            // frame of the new one is done.
            changed: other.is_some(),
        },
    };
    let mut taken = 0usize;
    while taken < MAX_FRAMES_PER_STEP {
        let frames = state
            .store
            .health_frames(sequence_id, monitor.calibration_id, monitor.through, BATCH)
            .await?;
        let full = frames.len() == BATCH as usize;
        for frame in frames {
            taken += 1;
            monitor.changed = true;
            match frame {
                HealthFrame::Taken(frame, rows) => {
                    if !rows.is_empty() {
                        let health = whole_frame(&rows, cameras);
                        monitor
                            .raised
                            .extend(monitor.monitor.push(frame.0, &health));
                        monitor.frames += 1;
                    }
                    monitor.through = Some(frame);
                }
                HealthFrame::Gap(frame) => monitor.through = Some(frame),
            }
        }
        if !full {
            break;
        }
    }
    Ok(monitor)
}

/// The sequence's monitor as of now, for reading: the stored one advanced
/// in memory over the frames done since (nothing written).
pub async fn summary(state: &AppState, sequence_id: SequenceId) -> Result<Monitor, HealthError> {
    step(state, sequence_id).await
}

/// Advances the sequence's stored monitor over the frames done since it
/// last moved, and announces the alarms those frames raised.
pub async fn advance(state: &AppState, sequence_id: SequenceId) -> Result<(), HealthError> {
    for _ in 0..ATTEMPTS {
        let monitor = step(state, sequence_id).await?;
        // Nothing taken (a new calibration's monitor starts with its
        // first frame): nothing to store.
        let (Some(through), true) = (monitor.through, monitor.changed) else {
            return Ok(());
        };
        let json = serde_json::to_string(&monitor.monitor)
            .map_err(|_| HealthError::Stored(sequence_id, "drift monitor"))?;
        let written = state
            .store
            .store_health(
                sequence_id,
                monitor.stored,
                (monitor.calibration_id, through, monitor.frames),
                &json,
            )
            .await?;
        if written {
            for alarm in &monitor.raised {
                tracing::warn!(
                    %sequence_id,
                    camera = alarm.camera,
                    frame = alarm.frame,
                    drift_px = alarm.drift_length_px,
                    "calibration drift: self-calibrate the sequence"
                );
                state.metrics.calibration_alarm();
                state.events.send(
                    sequence_id,
                    Change::CalibrationDrift {
                        camera: alarm.camera,
                        frame: FrameNumber(alarm.frame),
                        calibration_id: monitor.calibration_id,
                        drift_px: alarm.drift_px,
                        drift_length_px: alarm.drift_length_px,
                        threshold_px: monitor.settings.threshold_px,
                    },
                );
            }
            return Ok(());
        }
    }
    Ok(())
}

/// [`advance`] in the background, its errors logged (after a job).
pub fn advance_later(state: &Arc<AppState>, sequence_id: SequenceId) {
    let state = state.clone();
    tokio::spawn(async move {
        if let Err(error) = advance(&state, sequence_id).await {
            tracing::warn!(%error, %sequence_id, "cannot advance the calibration health");
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_is_stored_as_a_row_per_camera_and_one_per_cell_with_particles() {
        let d = |count: usize, x: f64| Disparity {
            count,
            mean_px: [x, -x],
            rms_px: x.abs() * 2.0,
        };
        let mut cells = vec![Disparity::default(); 8];
        cells[3] = d(5, 0.2);
        let health = FrameHealth {
            grid: GRID,
            cameras: vec![
                CameraHealth {
                    all: d(5, 0.2),
                    cells,
                },
                // No well-matched particle: its frame row only.
                CameraHealth {
                    all: Disparity::default(),
                    cells: vec![Disparity::default(); 8],
                },
                // Not finite: stored as none.
                CameraHealth {
                    all: d(3, f64::NAN),
                    cells: vec![Disparity::default(); 8],
                },
            ],
        };
        let rows = rows_of(&health);
        assert_eq!(
            rows.iter()
                .map(|r| (r.camera, r.cell, r.count))
                .collect::<Vec<_>>(),
            vec![(0, -1, 5), (0, 3, 5), (1, -1, 0), (2, -1, 0)]
        );
        assert_eq!(rows[2].mean, [0.0, 0.0]);
        // Read back for the monitor: the whole-frame rows, by camera.
        let back = whole_frame(&rows, 3);
        assert_eq!(back.cameras[0].all, d(5, 0.2));
        assert_eq!(back.cameras[1].all.count, 0);
        assert_eq!(back.cameras[2].all.count, 0);
    }
}
