//! System calibration (the design paper's section 5): each camera's 16
//! parameters by spatial resection on control points of known coordinates,
//! through the multimedia geometry, with no hand-made approximate
//! orientation; then check points intersected with the calibrated rig.
//!
//! Per camera (`resection.rs`, step by step):
//!
//! 1. A closed-form start (`dlt.rs`): the DLT on the observed points, or
//!    for control points in one plane the plane homography with the setup's
//!    interior orientation.
//! 2. The strict model (Eq. 1-5 with the multimedia module Eq. 6-12 inside
//!    it, section 4.3's observation equations with the camera parameters as
//!    unknowns): first exterior and interior orientation, then all free
//!    parameters, by Gauss-Markov with Levenberg-Marquardt damping
//!    (`adjustment.rs`).
//! 3. Parameters the data cannot determine are held and reported; gross
//!    errors are found by data snooping and excluded.
//!
//! Two consequences of the model to know about:
//!
//! * OpenPTV's affine form scales *both* image axes by `scx` (see
//!   [`super::camera::Distortion::apply`]), so with c, xh, yh and the
//!   distortion free, `scx` is exactly interchangeable with them (the same
//!   camera has scx = 1, c' = scx c, xh' = scx xh, k1' = k1 / scx², p' =
//!   p / scx, ...). The normal matrix is then singular and scx is held at the
//!   setup's value; fix it (`--fix scx`) to say so up front.
//! * A parameter correlated above the limit is held, judged after an
//!   adjustment with it free: the observations determine only a
//!   combination of the pair (c with z0: the rig's scale). It is held at
//!   the better known of two values: its least-squares estimate, so that
//!   holding it does not move the others, or, when its standard deviation
//!   is over a third of its plausible range, the setup's value (distortion
//!   terms always at the setup's). The others' standard deviations still
//!   include its uncertainty: computed as if it were free (or with the
//!   setup's value as a prior), since conditioning on an uncertain value
//!   would shrink the partner's by sqrt(1 - rho²) and overstate the
//!   accuracy.
//!
//! Then the check points, left out of every resection, are intersected
//! (section 4.3, [`super::intersect()`]) from all cameras: their RMSE
//! against the known coordinates is the honest accuracy figure, as in the
//! paper's section 5 (0.013/0.011/0.024 mm in air over a 200 mm field).
//!
//! Calibration from images ([`identify`]): the detected marks are assigned
//! to control points by projecting the control points with the current
//! orientation, iterating resection and assignment.
//!
//! Pure: no I/O. The entry points are [`calibrate`] (measured image
//! coordinates) and [`calibrate_from_marks`] (detected marks). The other
//! files: `parameter.rs`, the 16 parameters and sets of them; `planes.rs`,
//! the plate at several positions in one adjustment; `prepare.rs`,
//! the inputs validated once for all cameras; `report.rs`, the report and
//! how a camera's is drawn from its adjustment; `check.rs`, the check
//! points; `error.rs`, what can go wrong.

pub(crate) mod adjustment;
mod check;
mod dlt;
mod error;
pub mod identify;
mod parameter;
pub mod planes;
mod prepare;
mod report;
pub(crate) mod resection;

use nalgebra::{Point2, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::{Camera, CameraParameters};
pub use adjustment::projection_with_parameter_jacobian;
use check::check_point_report;
pub use error::{setup_field, CalibrationError};
pub use identify::{
    calibrate_from_marks, detect_marks, identify_marks, mark_at, mark_detection_parameters,
};
pub use parameter::{Parameter, ParameterSet};
pub use planes::{
    calibrate_planes, calibrate_planes_from_marks, Plane, PlaneMarks, PLANE_ID_STRIDE,
};
use prepare::prepare;
pub use report::{
    CalibrationReport, CameraReport, CheckPointDeviation, CheckPointReport, Correlation,
    ExcludedObservation, ParameterReport, ParameterStatus, PointResidual,
};
use resection::resect_camera;

/// The fewest control points a camera needs (the DLT's minimum).
pub const MIN_POINTS: usize = 6;

/// A control point of the calibration target (OpenPTV's calibration block:
/// `id X Y Z`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlPoint {
    /// The point's number.
    pub id: u64,
    /// Its coordinates (mm).
    pub position: Point3<f64>,
}

/// A measured image position of a control point in one camera (`id x y`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MarkObservation {
    /// The control point's number.
    pub id: u64,
    /// Its image position (pixels, the camera model's convention).
    pub pixel: Point2<f64>,
}

/// Which control points are check points, left out of the resections.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum CheckPoints {
    /// None: every control point is used in the resections.
    #[default]
    None,
    /// Every K-th control point in the given order (the K-th, 2K-th, ...).
    Every(usize),
    /// These ids.
    Ids(Vec<u64>),
}

/// How to calibrate.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationOptions {
    /// Parameters held at the setup's values in every camera.
    pub fixed: Vec<Parameter>,
    /// Check points.
    pub check_points: CheckPoints,
    /// Parameters correlated above this (in magnitude) are not determinable:
    /// one of the pair is held.
    pub max_correlation: f64,
    /// Family-wise significance level of the data snooping per camera (the
    /// probability of excluding a good point from an error-free camera).
    pub snooping_alpha: f64,
    /// Largest number of Levenberg-Marquardt iterations per adjustment.
    pub max_iterations: usize,
    /// Per camera, in the setup's order, the parameters the setup leaves
    /// out (a setup without orientation: sensor and media only). Their
    /// values in the setup are placeholders: the closed-form start (the DLT)
    /// replaces them, they cannot be fixed, and marks cannot be identified
    /// by projecting the control points with them. Empty (the default): the
    /// setup gives every parameter.
    pub unknown: Vec<ParameterSet>,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        CalibrationOptions {
            fixed: Vec::new(),
            check_points: CheckPoints::None,
            max_correlation: 0.99,
            snooping_alpha: 0.001,
            max_iterations: 500,
            unknown: Vec::new(),
        }
    }
}

/// The calibrated rig and the report.
#[derive(Clone, Debug, PartialEq)]
pub struct RigCalibration {
    /// The calibrated cameras, in the setup's order.
    pub cameras: Vec<CameraParameters>,
    /// How well they are determined.
    pub report: CalibrationReport,
}

impl RigCalibration {
    /// The calibrated cameras as validated camera models.
    pub fn camera_models(&self) -> Result<Vec<Camera>, CalibrationError> {
        self.cameras
            .iter()
            .enumerate()
            .map(|(camera, p)| {
                Camera::new(p.clone())
                    .map_err(|source| CalibrationError::InvalidSetup { camera, source })
            })
            .collect()
    }
}

/// Calibrates every camera of `setup` by resection on `control` with the
/// measured image coordinates `observations[camera]`, then intersects the
/// check points.
///
/// `setup` supplies sensor and media (required) and the values of fixed
/// parameters; its exterior and interior orientation need not be
/// approximately right: starting values are computed. The cameras are
/// calibrated in parallel.
pub fn calibrate(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    observations: &[Vec<MarkObservation>],
    options: &CalibrationOptions,
) -> Result<RigCalibration, CalibrationError> {
    let prepared = prepare(setup, control, observations.len(), options)?;
    let results: Vec<Result<(CameraParameters, CameraReport), CalibrationError>> = setup
        .par_iter()
        .zip(observations)
        .enumerate()
        .map(|(k, (camera, observed))| resect_camera(k, camera, observed, &prepared, options))
        .collect();
    let mut cameras = Vec::with_capacity(setup.len());
    let mut reports = Vec::with_capacity(setup.len());
    for result in results {
        let (camera, report) = result?;
        cameras.push(camera);
        reports.push(report);
    }
    let check_points = (!prepared.check.is_empty())
        .then(|| check_point_report(&cameras, &reports, control, observations, &prepared));
    Ok(RigCalibration {
        cameras,
        report: CalibrationReport {
            cameras: reports,
            check_points,
        },
    })
}

/// Checks what [`calibrate`] and [`calibrate_from_marks`] check before any
/// adjustment (the setup's cameras, the control points, the options, and
/// `given` per-camera inputs for the setup's cameras), cheaply and with the
/// same errors, so that bad input can be refused before the work is queued.
pub fn check_inputs(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    given: usize,
    options: &CalibrationOptions,
) -> Result<(), CalibrationError> {
    prepare(setup, control, given, options).map(|_| ())
}

/// Checks what [`calibrate_from_marks`] checks before any adjustment:
/// [`check_inputs`], and that every camera has a start to identify its
/// marks from (reference points, or a setup with the orientation).
/// `references[camera]` is the number of reference points given.
pub fn check_mark_inputs(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    references: &[usize],
    options: &CalibrationOptions,
) -> Result<(), CalibrationError> {
    check_inputs(setup, control, references.len(), options)?;
    identify::check_identification_start(setup, references, options)
}

/// The snooping critical value: the chi-square (2 dof) quantile `-2 ln(a)`
/// for the Bonferroni level `a = alpha / n` of the largest of `n` tests.
pub fn snooping_critical(alpha: f64, n: usize) -> f64 {
    -2.0 * (alpha / n.max(1) as f64).ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn snooping_critical_value_is_the_bonferroni_chi_square_quantile() {
        // P(chi2_2 > t) = exp(-t / 2).
        let t = snooping_critical(0.001, 200);
        assert!(((-t / 2.0).exp() - 0.001 / 200.0).abs() < 1e-15);
    }
}
