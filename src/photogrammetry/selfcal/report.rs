//! The self-calibration's report (serde, the JSON `ptv selfcalibrate`
//! prints): per camera the disparities before and after, as statistics and
//! as maps over sub-volumes (Wieneke 2008, section 3: the mean disparity
//! vector of the particles in each sub-volume, per camera), each
//! parameter's change with its standard deviation, the band and particles
//! of every round, and how the gauge was fixed.

use nalgebra::{Point3, Vector2};
use serde::Serialize;

use crate::photogrammetry::calibrate::{Parameter, ParameterStatus};
use crate::photogrammetry::volume::Volume;

/// How the self-calibration ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The disparities settled at the final band.
    Converged,
    /// The rounds ran out before the disparities settled; the cameras are
    /// the last round's.
    RoundLimit,
    /// The adjustment diverged (or made the disparities worse): the input
    /// calibration is kept and `message` says why.
    Diverged,
}

/// The report.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SelfCalibrationReport {
    /// How it ended.
    pub outcome: Outcome,
    /// Why it diverged, or other notes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// Frames given.
    pub frames: usize,
    /// The observation volume the particles were matched and binned in.
    pub volume: Volume,
    /// Sub-volumes per axis (x, y, z) of the cap and the disparity maps.
    pub grid: [usize; 3],
    /// A posteriori standard deviation of unit weight of the last
    /// adjustment (px, per image coordinate).
    pub sigma0_px: f64,
    /// Every round: band, particles, disparities.
    pub rounds: Vec<RoundReport>,
    /// Per camera.
    pub cameras: Vec<CameraSelfCalibration>,
    /// The media terms asked to be adjusted (`--free glass,n_wall,...`):
    /// each scalar unknown's change with its sigma, or why it was held.
    /// Empty when none was asked for.
    pub media: Vec<MediaChange>,
    /// How the gauge (7 dof) was fixed.
    pub gauge: GaugeReport,
}

/// One scalar media unknown (a glass vector's component, shared by the
/// cameras behind one wall, an index, the thickness).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MediaChange {
    /// `glass_x`, `glass_y`, `glass_z`, `n_wall`, `n_object`, `thickness`.
    pub name: String,
    /// The cameras that share it (1-based, as in OpenPTV's file names).
    pub cameras: Vec<usize>,
    /// Value in the input calibration (mm, or an index).
    pub before: f64,
    /// Value in the refined one.
    pub after: f64,
    /// After minus before.
    pub change: f64,
    /// Standard deviation (sigma0 times the root of its cofactor under the
    /// gauge constraints), where adjusted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma: Option<f64>,
    /// Free (adjusted) or held (with the reason).
    pub status: ParameterStatus,
    /// Why it was held.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// One round: match, select, adjust.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RoundReport {
    /// The epipolar band's half-width (px).
    pub band_px: f64,
    /// Particles matched over all frames, by the number of cameras that
    /// see them (index = camera count).
    pub matched_by_cameras: Vec<usize>,
    /// Confident candidates (enough cameras, isolated targets).
    pub candidates: usize,
    /// Selected for the adjustment (after the cap per sub-volume).
    pub selected: usize,
    /// Rejected by the robust loop as wrong matches.
    pub rejected: usize,
    /// RMS of the selected particles' image residuals before this round's
    /// adjustment (px, per observation, the vector's length).
    pub rms_before_px: f64,
    /// The same after it, without the rejected ones.
    pub rms_after_px: f64,
    /// Robust scale of the residuals (px per coordinate).
    pub sigma_px: f64,
    /// Levenberg-Marquardt iterations, all passes of the robust loop.
    pub iterations: usize,
}

/// Disparity statistics: lengths of the disparity vectors (observed minus
/// reprojected, px).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DisparityStats {
    /// Observations.
    pub count: usize,
    /// RMS length (px).
    pub rms_px: f64,
    /// Median length (px).
    pub median_px: f64,
}

impl DisparityStats {
    pub(super) fn of(d: &[Vector2<f64>]) -> DisparityStats {
        if d.is_empty() {
            return DisparityStats::default();
        }
        let mut lengths: Vec<f64> = d.iter().map(|v| v.norm()).collect();
        lengths.sort_by(f64::total_cmp);
        let rms = (lengths.iter().map(|l| l * l).sum::<f64>() / lengths.len() as f64).sqrt();
        DisparityStats {
            count: lengths.len(),
            rms_px: rms,
            median_px: median_sorted(&lengths),
        }
    }
}

/// The median of sorted values.
pub(super) fn median_sorted(v: &[f64]) -> f64 {
    match v.len() {
        0 => 0.0,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// One sub-volume of a disparity map.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DisparityCell {
    /// Cell index along x, y, z.
    pub index: [usize; 3],
    /// Its centre (mm).
    pub centre_mm: [f64; 3],
    /// Observations in it.
    pub count: usize,
    /// Mean disparity vector, x (px).
    pub mean_dx_px: f64,
    /// Mean disparity vector, y (px).
    pub mean_dy_px: f64,
    /// RMS length of the disparity vectors (px).
    pub rms_px: f64,
}

/// A camera's disparity map over the sub-volumes (cells without particles
/// left out).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DisparityMap {
    /// The cells with particles, x fastest.
    pub cells: Vec<DisparityCell>,
}

impl DisparityMap {
    pub(super) fn of(
        volume: &Volume,
        grid: [usize; 3],
        points: &[Point3<f64>],
        d: &[Vector2<f64>],
    ) -> DisparityMap {
        let n = grid[0] * grid[1] * grid[2];
        let mut sums = vec![(0usize, Vector2::zeros(), 0.0); n];
        for (p, v) in points.iter().zip(d) {
            let cell = cell_of(volume, grid, p);
            let s = &mut sums[flat(grid, cell)];
            s.0 += 1;
            s.1 += v;
            s.2 += v.norm_squared();
        }
        let mut cells = Vec::new();
        for k in 0..grid[2] {
            for j in 0..grid[1] {
                for i in 0..grid[0] {
                    let (count, sum, sq) = sums[flat(grid, [i, j, k])];
                    if count == 0 {
                        continue;
                    }
                    let centre = |a: usize, idx: usize| {
                        volume.min[a]
                            + (idx as f64 + 0.5) * (volume.max[a] - volume.min[a]) / grid[a] as f64
                    };
                    cells.push(DisparityCell {
                        index: [i, j, k],
                        centre_mm: [centre(0, i), centre(1, j), centre(2, k)],
                        count,
                        mean_dx_px: sum.x / count as f64,
                        mean_dy_px: sum.y / count as f64,
                        rms_px: (sq / count as f64).sqrt(),
                    });
                }
            }
        }
        DisparityMap { cells }
    }
}

/// The sub-volume of a point (points outside go to the nearest cell).
pub(super) fn cell_of(volume: &Volume, grid: [usize; 3], p: &Point3<f64>) -> [usize; 3] {
    let mut cell = [0; 3];
    for a in 0..3 {
        let t = (p[a] - volume.min[a]) / (volume.max[a] - volume.min[a]);
        let i = (t * grid[a] as f64).floor();
        cell[a] = if i.is_finite() {
            i.clamp(0.0, (grid[a] - 1) as f64) as usize
        } else {
            0
        };
    }
    cell
}

/// The flat index of a cell, x fastest.
pub(super) fn flat(grid: [usize; 3], cell: [usize; 3]) -> usize {
    cell[0] + grid[0] * (cell[1] + grid[1] * cell[2])
}

/// One parameter's change.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ParameterChange {
    /// Which.
    pub name: Parameter,
    /// The input calibration's value.
    pub before: f64,
    /// The refined value.
    pub after: f64,
    /// `after - before`.
    pub change: f64,
    /// Standard deviation of the refined value (under the gauge
    /// constraints); `None` unless estimated.
    pub sigma: Option<f64>,
    /// Estimated, fixed by the user, or held.
    pub status: ParameterStatus,
    /// Why it was held.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// One camera's self-calibration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CameraSelfCalibration {
    /// The camera's name.
    pub name: String,
    /// Disparities of the final particles with the input calibration.
    pub before: DisparityStats,
    /// With the refined calibration.
    pub after: DisparityStats,
    /// Disparity map with the input calibration.
    pub map_before: DisparityMap,
    /// Disparity map with the refined calibration.
    pub map_after: DisparityMap,
    /// The 16 parameters.
    pub parameters: Vec<ParameterChange>,
    /// The glass vector (mm), after.
    pub glass_vector_mm: [f64; 3],
    /// Whether the glass vector was adjusted (see the report's `media`),
    /// or why it was held.
    pub glass_vector_reason: String,
}

/// How the gauge was fixed, and what became of the baselines.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GaugeReport {
    /// The method, in words.
    pub method: String,
    /// `L`, weighing an angle change as the displacement at this distance
    /// (mm).
    pub reference_length_mm: f64,
    /// RMS distance of the cameras from their centroid before (mm).
    pub baseline_rms_before_mm: f64,
    /// The same after (mm).
    pub baseline_rms_after_mm: f64,
    /// Shift of the cameras' centroid (mm).
    pub centroid_shift_mm: f64,
    /// RMS change of the camera positions (mm).
    pub position_change_rms_mm: f64,
}
