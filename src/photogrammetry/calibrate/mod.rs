//! System calibration (the design paper's section 5): each camera's 16
//! parameters by spatial resection on control points of known coordinates,
//! through the multimedia geometry, with no hand-made approximate
//! orientation; then check points intersected with the calibrated rig.
//!
//! Per camera (`calibrate/resection.rs`):
//!
//! 1. A closed-form start (`calibrate/dlt.rs`): the DLT on the observed points, or for
//!    control points in one plane the plane homography with the setup's
//!    interior orientation.
//! 2. The strict model (Eq. 1-5 with the multimedia module Eq. 6-12 inside
//!    it, section 4.3's observation equations with the camera parameters as
//!    unknowns): first exterior and interior orientation, then all free
//!    parameters, by Gauss-Markov with Levenberg-Marquardt damping.
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
//! * A parameter correlated above the limit is held at its least-squares
//!   estimate (distortion terms at the setup's value), judged after an
//!   adjustment with it free, so holding it does not move the others. Their
//!   standard deviations still include its uncertainty: computed as if it
//!   were free, since conditioning on an uncertain value would shrink the
//!   partner's by sqrt(1 - rho²) and overstate the accuracy.
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
//! coordinates) and [`calibrate_from_marks`] (detected marks).

mod check;
mod dlt;
mod error;
pub mod identify;
mod parameter;
mod prepare;
mod report;
mod resection;

use std::collections::HashSet;

use nalgebra::{Point2, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::{Camera, CameraParameters};
use check::check_point_report;
pub use error::CalibrationError;
pub use identify::{calibrate_from_marks, detect_marks, identify_marks, mark_detection_parameters};
pub use parameter::{Parameter, ParameterSet};
use prepare::{prepare, Prepared};
use report::camera_report;
pub use report::{
    CalibrationReport, CameraReport, CheckPointDeviation, CheckPointReport, Correlation,
    ExcludedObservation, ParameterReport, ParameterStatus, PointResidual,
};
pub use resection::projection_with_parameter_jacobian;
use resection::Equation;

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
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        CalibrationOptions {
            fixed: Vec::new(),
            check_points: CheckPoints::None,
            max_correlation: 0.99,
            snooping_alpha: 0.001,
            max_iterations: 500,
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

/// Checks one camera's observations and turns the usable ones (control
/// points that are not check points) into observation equations with ids.
fn equations(
    camera: usize,
    name: &str,
    observed: &[MarkObservation],
    prepared: &Prepared,
) -> Result<Vec<(u64, Equation)>, CalibrationError> {
    if observed.is_empty() {
        return Err(CalibrationError::NoObservations {
            camera,
            name: name.to_owned(),
        });
    }
    let mut seen = HashSet::with_capacity(observed.len());
    let mut usable = Vec::with_capacity(observed.len());
    for o in observed {
        if !(o.pixel.x.is_finite() && o.pixel.y.is_finite()) {
            return Err(CalibrationError::NonFiniteObservation { camera, id: o.id });
        }
        let Some(point) = prepared.control.get(&o.id) else {
            return Err(CalibrationError::UnknownId { camera, id: o.id });
        };
        if !seen.insert(o.id) {
            return Err(CalibrationError::DuplicateObservation { camera, id: o.id });
        }
        if !prepared.check.contains(&o.id) {
            usable.push((
                o.id,
                Equation {
                    point: *point,
                    pixel: o.pixel,
                },
            ));
        }
    }
    Ok(usable)
}

/// Points needed for `free` parameters: the DLT's 6, and a redundancy of at
/// least 2 so that sigma0 exists.
fn points_needed(free: usize) -> usize {
    MIN_POINTS.max((free + 2).div_ceil(2))
}

/// The resection of one camera, from the closed-form start to the report.
fn resect_camera(
    k: usize,
    setup: &CameraParameters,
    observed: &[MarkObservation],
    prepared: &Prepared,
    options: &CalibrationOptions,
) -> Result<(CameraParameters, CameraReport), CalibrationError> {
    let name = setup.name.clone();
    let all = equations(k, &name, observed, prepared)?;
    let free_count = prepared.fixed.complement().len();
    let needed = points_needed(free_count);
    if all.len() < needed {
        return Err(CalibrationError::TooFewPoints {
            camera: k,
            name,
            usable: all.len(),
            needed,
            free: free_count,
        });
    }
    let no_convergence = || CalibrationError::NoConvergence {
        camera: k,
        name: setup.name.clone(),
    };
    let points: Vec<Point3<f64>> = all.iter().map(|(_, e)| e.point).collect();
    let coplanar = dlt::flatness(&points) < 1e-3;
    let free_interior: Vec<Parameter> =
        (ParameterSet::interior() - prepared.fixed).iter().collect();
    if coplanar && !free_interior.is_empty() {
        return Err(CalibrationError::Coplanar {
            camera: k,
            name,
            count: all.len(),
            free: free_interior,
        });
    }

    // 1. Closed-form start, ignoring refraction and (unknown) distortion.
    let metric: Vec<(Point3<f64>, nalgebra::Vector2<f64>)> = all
        .iter()
        .filter_map(|(_, e)| Some((e.point, dlt::ideal_metric(setup, e.pixel)?)))
        .collect();
    let start = if coplanar {
        dlt::start_from_plane(setup, &metric)
    } else {
        dlt::start_from_dlt(setup, &metric)
    }
    .ok_or_else(|| CalibrationError::NoStart {
        camera: k,
        name: setup.name.clone(),
    })?;
    let setup_vector = resection::to_vector(setup);
    let mut v = resection::to_vector(&start);
    // Distortion is not in the closed-form start: it starts at the setup's.
    for p in (prepared.fixed | ParameterSet::distortion()).iter() {
        v[p.index()] = setup_vector[p.index()];
    }
    let start = resection::from_vector(setup, &v);
    let start = valid_start(start).ok_or_else(no_convergence)?;

    let mut active: Vec<(u64, Equation)> = all;
    let eqs = |active: &[(u64, Equation)]| active.iter().map(|(_, e)| *e).collect::<Vec<_>>();

    // 2. Exterior and interior orientation through the strict model.
    let orientation = (ParameterSet::exterior() | ParameterSet::interior()) - prepared.fixed;
    let first = resection::adjust(&start, orientation, &eqs(&active), options.max_iterations)
        .ok_or_else(no_convergence)?;
    let mut iterations = first.iterations;
    let mut current = first.parameters;

    // 3. All free parameters, holding what the data cannot determine, and
    //    data snooping.
    let mut free = prepared.fixed.complement();
    let mut held: Vec<(Parameter, String)> = Vec::new();
    // Parameters held at their least-squares estimate for a correlation:
    // their uncertainty stays in the others' standard deviations.
    let mut held_at_estimate = ParameterSet::empty();
    let mut excluded: Vec<PointResidual> = Vec::new();
    let mut hold = |p: Parameter,
                    reason: String,
                    current: &mut CameraParameters,
                    free: &mut ParameterSet,
                    at_estimate: bool| {
        free.remove(p);
        if p.held_at_setup() {
            let mut v = resection::to_vector(current);
            v[p.index()] = setup_vector[p.index()];
            *current = resection::from_vector(current, &v);
        } else if at_estimate {
            held_at_estimate.insert(p);
        }
        held.push((p, reason));
    };
    let stats = loop {
        // Hold what the data cannot determine at all (a singular normal
        // matrix), judged at the current solution.
        loop {
            let stats =
                resection::statistics(&current, free, &eqs(&active)).ok_or_else(no_convergence)?;
            let Some((p, reason)) =
                resection::undeterminable(&stats, free, options.max_correlation, false)
            else {
                break;
            };
            hold(p, reason, &mut current, &mut free, false);
        }
        let adjusted = resection::adjust(&current, free, &eqs(&active), options.max_iterations)
            .ok_or_else(no_convergence)?;
        iterations += adjusted.iterations;
        // Gross errors can slow the convergence down; only the final
        // adjustment, after snooping, must have converged.
        let converged = adjusted.converged;
        current = adjusted.parameters;
        let stats =
            resection::statistics(&current, free, &eqs(&active)).ok_or_else(no_convergence)?;
        // Then correlations, judged at the least-squares solution, so that a
        // parameter held at its estimate leaves the others' estimates as
        // they are.
        if let Some((p, reason)) =
            resection::undeterminable(&stats, free, options.max_correlation, true)
        {
            hold(p, reason, &mut current, &mut free, true);
            continue;
        }
        // Snooping: the worst point, if significant and one can be spared.
        let critical = snooping_critical(options.snooping_alpha, active.len());
        let worst = stats
            .test
            .iter()
            .enumerate()
            .filter_map(|(i, t)| t.map(|t| (i, t)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match worst {
            Some((i, t)) if t > critical && active.len() > points_needed(free.len()) => {
                let (id, _) = active.remove(i);
                excluded.push(PointResidual {
                    id,
                    x_px: stats.residuals[i].x,
                    y_px: stats.residuals[i].y,
                    test: Some(t),
                });
            }
            _ if converged => break stats,
            _ => return Err(no_convergence()),
        }
    };
    // Standard deviations and covariance with the parameters held at their
    // estimates still free: conditioning on a value that is itself uncertain
    // would make the others' look better than they are.
    let uncertain = free | held_at_estimate;
    let marginal = if uncertain == free {
        None
    } else {
        resection::statistics(&current, uncertain, &eqs(&active))
    };
    let covariance_source = match &marginal {
        Some(m) if m.cofactor.is_some() => (m, uncertain),
        _ => (&stats, free),
    };
    let report = camera_report(
        &current,
        free,
        prepared,
        &held,
        &active,
        &stats,
        covariance_source,
        excluded,
        iterations,
        options,
    );
    Ok((current, report))
}

/// The start, if it is a valid camera; else the same orientation moved back
/// along its axis until the media accept it (a pinhole fit through a
/// refracting wall may put the centre too close to the wall).
fn valid_start(start: CameraParameters) -> Option<CameraParameters> {
    if Camera::new(start.clone()).is_ok() {
        return Some(start);
    }
    let rotation = super::camera::rotation_matrix(
        start.exterior.omega,
        start.exterior.phi,
        start.exterior.kappa,
    );
    // The camera looks along its -z axis: backwards is +z.
    let back = rotation.column(2).into_owned();
    let mut moved = start;
    for _ in 0..20 {
        moved.exterior.position += back * 50.0;
        if Camera::new(moved.clone()).is_ok() {
            return Some(moved);
        }
    }
    None
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
