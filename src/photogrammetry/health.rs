//! Calibration health during a run: per processed frame and camera, the
//! disparity of its well-matched particles (observed target minus the
//! projection of the particle's intersected position, in px), as a mean
//! vector and an RMS, over the whole frame and per sub-volume; and a drift
//! monitor that raises an alarm when a camera's mean disparity, averaged
//! over a window of frames, has moved past a threshold from where the run
//! started.
//!
//! A camera that moves (a bumped mount, a warming lens) shows as a growing
//! mean disparity vector in its images: the disparity maps of volume
//! self-calibration (Wieneke 2008, section 3), computed on the run's own
//! matches as they come instead of afterwards. The particle's position is
//! intersected from all its cameras, so a camera's own error is partly
//! absorbed by the point: with 4 cameras a camera displaced by `d` px shows
//! about 3/4 `d` in its images and small opposite shares in the others'
//! (least squares spreads the error over the rays), enough to tell which
//! camera moved.
//!
//! **Well matched**: seen by at least 3 cameras (all, in a 2-camera rig),
//! a reprojection RMS within the limit (the matching band's own measure of
//! a correct group), at most [`HealthOptions::max_particles`] per frame
//! (the best-fitting), so the work per frame is bounded.
//!
//! **Drift** ([`DriftMonitor`]): per camera the baseline is the mean of the
//! first `window` frames' mean disparity vectors; from then on, after every
//! frame, the mean of the last `window` frames' vectors is compared with
//! the baseline, and the first frame at which their difference exceeds
//! `threshold_px` raises the camera's alarm (once). Defaults: 0.3 px over
//! 50 frames. The cure is a self-calibration (`ptv selfcalibrate`) on the
//! run's targets.
//!
//! Pure: no I/O.

use std::collections::VecDeque;

use nalgebra::{Point3, Vector2};
use serde::{Deserialize, Serialize};

use super::camera::Camera;
use super::correspond::Particle;
use super::target::Target;
use super::volume::Volume;

/// How a frame's health is measured.
#[derive(Clone, Debug, PartialEq)]
pub struct HealthOptions {
    /// The volume whose sub-volumes the disparities are binned in.
    pub volume: Volume,
    /// Sub-volumes per axis.
    pub grid: [usize; 3],
    /// A particle with a larger reprojection RMS (px) is not used.
    pub max_rms_px: f64,
    /// Most particles a frame's health uses (the best-fitting).
    pub max_particles: usize,
}

impl HealthOptions {
    /// 2 x 2 x 2 sub-volumes of `volume`, particles within `max_rms_px`,
    /// at most 2,000 a frame.
    pub fn new(volume: Volume, max_rms_px: f64) -> HealthOptions {
        HealthOptions {
            volume,
            grid: [2, 2, 2],
            max_rms_px,
            max_particles: 2000,
        }
    }
}

/// Disparity statistics of one camera (in a frame or a sub-volume).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Disparity {
    /// Particles.
    pub count: usize,
    /// Mean disparity vector (px, x and y).
    pub mean_px: [f64; 2],
    /// RMS length of the disparity vectors (px).
    pub rms_px: f64,
}

impl Disparity {
    fn of(d: &[Vector2<f64>]) -> Disparity {
        if d.is_empty() {
            return Disparity::default();
        }
        let n = d.len() as f64;
        let mean = d.iter().sum::<Vector2<f64>>() / n;
        Disparity {
            count: d.len(),
            mean_px: [mean.x, mean.y],
            rms_px: (d.iter().map(|v| v.norm_squared()).sum::<f64>() / n).sqrt(),
        }
    }

    /// The mean vector.
    pub fn mean(&self) -> Vector2<f64> {
        Vector2::new(self.mean_px[0], self.mean_px[1])
    }
}

/// One camera's disparities in a frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraHealth {
    /// Over the frame.
    #[serde(flatten)]
    pub all: Disparity,
    /// Per sub-volume, x fastest, then y, then z (empty cells have count 0).
    pub cells: Vec<Disparity>,
}

/// A frame's calibration health.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameHealth {
    /// Sub-volumes per axis of the cells.
    pub grid: [usize; 3],
    /// Per camera.
    pub cameras: Vec<CameraHealth>,
}

/// The sub-volume of `p`, clamped into the grid.
fn cell_of(volume: &Volume, grid: [usize; 3], p: &Point3<f64>) -> usize {
    let mut index = [0usize; 3];
    for k in 0..3 {
        let extent = volume.max[k] - volume.min[k];
        let t = if extent > 0.0 {
            (p[k] - volume.min[k]) / extent
        } else {
            0.0
        };
        index[k] = ((t * grid[k] as f64).floor().max(0.0) as usize).min(grid[k] - 1);
    }
    index[0] + grid[0] * (index[1] + grid[1] * index[2])
}

/// The health of one frame: `targets` per camera as detected, `particles`
/// as matched from them, with the rig `cameras` they were matched with.
pub fn frame_health(
    cameras: &[Camera],
    targets: &[Vec<Target>],
    particles: &[Particle],
    options: &HealthOptions,
) -> FrameHealth {
    let n = cameras.len();
    let grid = options.grid.map(|g| g.max(1));
    let cells = grid[0] * grid[1] * grid[2];
    let least = 3.min(n);
    let mut good: Vec<&Particle> = particles
        .iter()
        .filter(|p| p.camera_count() >= least && p.rms_px <= options.max_rms_px)
        .collect();
    good.sort_by(|a, b| a.rms_px.total_cmp(&b.rms_px));
    good.truncate(options.max_particles);
    let mut all = vec![Vec::new(); n];
    let mut by_cell = vec![vec![Vec::new(); cells]; n];
    for p in good {
        let cell = cell_of(&options.volume, grid, &p.position);
        for (c, t) in p.targets.iter().enumerate().take(n) {
            let Some(target) = t.and_then(|t| targets.get(c)?.get(t)) else {
                continue;
            };
            let Ok(projected) = cameras[c].project(&p.position) else {
                continue;
            };
            let d = Vector2::new(target.x - projected.x, target.y - projected.y);
            all[c].push(d);
            by_cell[c][cell].push(d);
        }
    }
    FrameHealth {
        grid,
        cameras: all
            .iter()
            .zip(&by_cell)
            .map(|(a, cells)| CameraHealth {
                all: Disparity::of(a),
                cells: cells.iter().map(|d| Disparity::of(d)).collect(),
            })
            .collect(),
    }
}

/// A camera's alarm: its mean disparity drifted past the threshold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DriftAlarm {
    /// The camera (0-based).
    pub camera: usize,
    /// The frame at which it fired.
    pub frame: i64,
    /// The windowed mean's change from the baseline (px, x and y).
    pub drift_px: [f64; 2],
    /// Its length (px).
    pub drift_length_px: f64,
}

/// One camera's running state.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraDrift {
    /// The baseline: the mean of the first window's frames (px).
    pub baseline_px: Option<[f64; 2]>,
    /// The mean of the last window's frames (px).
    pub window_mean_px: [f64; 2],
    /// The drift: window mean minus baseline (px), its length.
    pub drift_px: f64,
    /// The alarm, once fired.
    pub alarm: Option<DriftAlarm>,
    /// The last window's frame means (frame, x, y).
    recent: VecDeque<(i64, f64, f64)>,
    /// Frames seen before the baseline was complete.
    first: Vec<(f64, f64)>,
}

/// The running summary of a sequence's health: see the module's
/// documentation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DriftMonitor {
    /// The alarm threshold (px).
    pub threshold_px: f64,
    /// Frames per window.
    pub window: usize,
    /// Per camera.
    pub cameras: Vec<CameraDrift>,
}

impl DriftMonitor {
    /// The default: 0.3 px over 50 frames.
    pub const DEFAULT_THRESHOLD_PX: f64 = 0.3;
    /// The default window.
    pub const DEFAULT_WINDOW: usize = 50;

    /// A monitor for `cameras` cameras.
    pub fn new(cameras: usize, threshold_px: f64, window: usize) -> DriftMonitor {
        DriftMonitor {
            threshold_px,
            window: window.max(1),
            cameras: vec![CameraDrift::default(); cameras],
        }
    }

    /// Takes frame `frame`'s health (frames in processing order); the
    /// alarms this frame raised.
    pub fn push(&mut self, frame: i64, health: &FrameHealth) -> Vec<DriftAlarm> {
        let mut raised = Vec::new();
        let window = self.window;
        for (c, (state, h)) in self.cameras.iter_mut().zip(&health.cameras).enumerate() {
            if h.all.count == 0 {
                continue;
            }
            let (x, y) = (h.all.mean_px[0], h.all.mean_px[1]);
            state.recent.push_back((frame, x, y));
            while state.recent.len() > window {
                state.recent.pop_front();
            }
            let k = state.recent.len() as f64;
            let mx = state.recent.iter().map(|r| r.1).sum::<f64>() / k;
            let my = state.recent.iter().map(|r| r.2).sum::<f64>() / k;
            state.window_mean_px = [mx, my];
            let Some(base) = state.baseline_px else {
                state.first.push((x, y));
                if state.first.len() == window {
                    let n = window as f64;
                    state.baseline_px = Some([
                        state.first.iter().map(|f| f.0).sum::<f64>() / n,
                        state.first.iter().map(|f| f.1).sum::<f64>() / n,
                    ]);
                    state.first = Vec::new();
                }
                continue;
            };
            let drift = [mx - base[0], my - base[1]];
            state.drift_px = drift[0].hypot(drift[1]);
            if state.alarm.is_none() && state.drift_px > self.threshold_px {
                let alarm = DriftAlarm {
                    camera: c,
                    frame,
                    drift_px: drift,
                    drift_length_px: state.drift_px,
                };
                state.alarm = Some(alarm.clone());
                raised.push(alarm);
            }
        }
        raised
    }
}
