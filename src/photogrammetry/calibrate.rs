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

mod dlt;
pub mod identify;
mod parameter;
mod resection;

use std::collections::{HashMap, HashSet};

use nalgebra::{Point2, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::camera::{Camera, CameraParameters, InvalidCamera};
use super::intersect::{intersect, Observation};
pub use identify::{calibrate_from_marks, detect_marks, identify_marks, mark_detection_parameters};
pub use parameter::{Parameter, ParameterSet};
pub use resection::projection_with_parameter_jacobian;
use resection::{Equation, ParameterVector};

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

/// Why a calibration cannot be done.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// No cameras in the setup.
    #[error("the setup has no cameras")]
    NoCameras,
    /// The observations are not one list per camera.
    #[error("the setup has {cameras} cameras but observations for {given} were given; give one list per camera, in camera order")]
    CameraCount {
        /// Cameras in the setup.
        cameras: usize,
        /// Observation lists given.
        given: usize,
    },
    /// A camera of the setup is not a camera.
    #[error("camera {camera} of the setup: {source}")]
    InvalidSetup {
        /// The camera (0-based).
        camera: usize,
        /// What is wrong.
        #[source]
        source: InvalidCamera,
    },
    /// Too few control points.
    #[error("{count} control points given; a calibration needs at least {MIN_POINTS}")]
    TooFewControlPoints {
        /// How many were given.
        count: usize,
    },
    /// A control point id appears twice.
    #[error("control point {id} is given twice")]
    DuplicateControlPoint {
        /// The id.
        id: u64,
    },
    /// A control point has a non-finite coordinate.
    #[error("control point {id} has a coordinate that is not a finite number")]
    NonFiniteControlPoint {
        /// The id.
        id: u64,
    },
    /// An observation has a non-finite coordinate.
    #[error("camera {camera}: the observation of point {id} is not a finite number")]
    NonFiniteObservation {
        /// The camera (0-based).
        camera: usize,
        /// The point's id.
        id: u64,
    },
    /// An observation names a point that is not a control point.
    #[error("camera {camera}: point {id} is not a control point")]
    UnknownId {
        /// The camera (0-based).
        camera: usize,
        /// The id.
        id: u64,
    },
    /// A point is observed twice in one camera.
    #[error("camera {camera}: point {id} is observed twice")]
    DuplicateObservation {
        /// The camera (0-based).
        camera: usize,
        /// The id.
        id: u64,
    },
    /// A camera has no observations.
    #[error("camera {camera} ({name}) sees no control point: give its observations, or leave the camera out of the setup")]
    NoObservations {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
    },
    /// Too few points for the parameters to estimate.
    #[error("camera {camera} ({name}) has {usable} usable control points (observed and not check points), but needs at least {needed} for {free} free parameters; observe more points, use fewer check points, or fix parameters (--fix)")]
    TooFewPoints {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Observed control points that are not check points.
        usable: usize,
        /// How many are needed.
        needed: usize,
        /// Free parameters.
        free: usize,
    },
    /// All points in one plane, with interior parameters free.
    #[error("camera {camera} ({name}): all {count} control points it sees lie in one plane, which cannot determine the interior orientation ({}) together with the position; fix them (--fix c,xh,yh) at known values in the setup, or use a target with points in a second plane", free.iter().map(|p| p.name()).collect::<Vec<_>>().join(", "))]
    Coplanar {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// How many points.
        count: usize,
        /// The free interior parameters.
        free: Vec<Parameter>,
    },
    /// The points do not give a closed-form start (e.g. all on a line).
    #[error("camera {camera} ({name}): the control points it sees do not determine an orientation (are they all on one line, or mis-identified?)")]
    NoStart {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
    },
    /// The adjustment left the valid region or did not converge.
    #[error("camera {camera} ({name}): the adjustment did not converge; check the identification of the points and the media in the setup")]
    NoConvergence {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
    },
    /// Too few marks could be identified in an image.
    #[error("camera {camera} ({name}): only {found} marks could be identified with control points; give better starting values or reference points (id x y) for at least 6 points")]
    TooFewIdentified {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Marks identified.
        found: usize,
    },
    /// Too few reference points to start identifying marks.
    #[error("camera {camera} ({name}): {given} reference points do not determine a starting orientation; give at least 6 not in one plane, or at least 4 in one plane with c, xh and yh right in the setup")]
    TooFewReferences {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Reference points given.
        given: usize,
    },
    /// An option is out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
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

/// The calibration report (serialised as the JSON that `ptv calibrate`
/// prints).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CalibrationReport {
    /// Per camera, in the setup's order.
    pub cameras: Vec<CameraReport>,
    /// The check points, if any were chosen.
    pub check_points: Option<CheckPointReport>,
}

/// Whether a parameter was estimated.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ParameterStatus {
    /// Estimated.
    Free,
    /// Fixed by the user.
    Fixed,
    /// Held because the data cannot determine it.
    Held,
}

/// One parameter's value and accuracy.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ParameterReport {
    /// Which.
    pub name: Parameter,
    /// The value (mm, rad, or the unit of the distortion term).
    pub value: f64,
    /// Its standard deviation; `None` unless estimated.
    pub sigma: Option<f64>,
    /// Estimated, fixed or held.
    pub status: ParameterStatus,
    /// Why it was held, for held parameters.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// A correlation between two estimated parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Correlation {
    /// One parameter.
    pub a: Parameter,
    /// The other.
    pub b: Parameter,
    /// The correlation coefficient.
    pub value: f64,
}

/// A point's residual (observed minus computed).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PointResidual {
    /// The control point.
    pub id: u64,
    /// Residual in x (px).
    pub x_px: f64,
    /// Residual in y (px).
    pub y_px: f64,
    /// The data-snooping statistic `vᵀQvv⁻¹v / sigma0²` (chi-square, 2
    /// degrees of freedom), for excluded points from the last adjustment
    /// that included them; `None` where the point cannot be tested.
    pub test: Option<f64>,
}

/// One camera's calibration.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CameraReport {
    /// The camera's name.
    pub name: String,
    /// A posteriori standard deviation of an image coordinate (px).
    pub sigma0_px: f64,
    /// Control points used in the final adjustment.
    pub points_used: usize,
    /// Redundancy of the final adjustment (`2n - u`).
    pub redundancy: usize,
    /// Levenberg-Marquardt iterations, all adjustments together.
    pub iterations: usize,
    /// The critical value of the snooping test used (chi-square, 2 dof).
    pub snooping_critical: f64,
    /// All 16 parameters.
    pub parameters: Vec<ParameterReport>,
    /// Covariance of the 16 parameters in [`Parameter::ALL`]'s order,
    /// `sigma0² (AᵀA)⁻¹` with the free parameters and those held at their
    /// estimate for a correlation (zero rows and columns for the others):
    /// what propagating the calibration's uncertainty needs. The standard
    /// deviations of the free parameters come from it.
    pub covariance: Vec<Vec<f64>>,
    /// The largest correlations among the estimated parameters (up to 10,
    /// largest magnitude first).
    pub largest_correlations: Vec<Correlation>,
    /// Residuals of the points used.
    pub residuals: Vec<PointResidual>,
    /// Points excluded as gross errors, in the order they were found, with
    /// their residuals from the last adjustment that included them.
    pub excluded: Vec<PointResidual>,
}

/// A check point's deviation from its known coordinates.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CheckPointDeviation {
    /// The control point.
    pub id: u64,
    /// Intersected minus known (mm).
    pub dx: f64,
    /// Intersected minus known (mm).
    pub dy: f64,
    /// Intersected minus known (mm).
    pub dz: f64,
    /// Cameras that observed it.
    pub cameras: usize,
}

/// An observation of a check point excluded from its intersection.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ExcludedObservation {
    /// The check point.
    pub id: u64,
    /// The camera (0-based).
    pub camera: usize,
    /// Its test statistic `vᵀ Cov(v)⁻¹ v` in the intersection (chi-square,
    /// 2 dof), the covariance from the image noise and the calibration's
    /// own uncertainty.
    pub test: f64,
}

/// The check points: the accuracy of the calibrated rig.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CheckPointReport {
    /// Check points intersected (seen by at least two cameras).
    pub count: usize,
    /// RMSE in X (mm).
    pub rmse_x_mm: f64,
    /// RMSE in Y (mm).
    pub rmse_y_mm: f64,
    /// RMSE in Z (mm).
    pub rmse_z_mm: f64,
    /// RMSE of one coordinate over all three axes (mm):
    /// `sqrt((rmse_x² + rmse_y² + rmse_z²) / 3)`.
    pub rmse_mm: f64,
    /// Diagonal of the control points' bounding box (mm).
    pub diagonal_mm: f64,
    /// `diagonal / rmse`: the relative accuracy 1 : this.
    pub relative_accuracy: f64,
    /// Per check point.
    pub points: Vec<CheckPointDeviation>,
    /// Check points seen by fewer than two cameras, or not intersectable.
    pub not_intersected: Vec<u64>,
    /// Observations of check points left out of their intersection as gross
    /// errors (a wrong id or a bad measurement would otherwise spoil the
    /// accuracy figure).
    pub excluded_observations: Vec<ExcludedObservation>,
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

/// Validated inputs shared by the cameras.
struct Prepared {
    /// Control points by id.
    control: HashMap<u64, Point3<f64>>,
    /// Ids of check points.
    check: HashSet<u64>,
    /// Which parameters the user fixed.
    fixed: ParameterSet,
}

fn prepare(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    given: usize,
    options: &CalibrationOptions,
) -> Result<Prepared, CalibrationError> {
    if setup.is_empty() {
        return Err(CalibrationError::NoCameras);
    }
    if given != setup.len() {
        return Err(CalibrationError::CameraCount {
            cameras: setup.len(),
            given,
        });
    }
    if !(options.max_correlation > 0.0 && options.max_correlation <= 1.0) {
        return Err(CalibrationError::InvalidOption(format!(
            "the correlation limit must be in (0, 1], got {}",
            options.max_correlation
        )));
    }
    if !(options.snooping_alpha > 0.0 && options.snooping_alpha < 1.0) {
        return Err(CalibrationError::InvalidOption(format!(
            "the snooping significance level must be in (0, 1), got {}",
            options.snooping_alpha
        )));
    }
    let fixed: ParameterSet = options.fixed.iter().copied().collect();
    for (camera, parameters) in setup.iter().enumerate() {
        validate_setup(parameters, fixed)
            .map_err(|source| CalibrationError::InvalidSetup { camera, source })?;
    }
    if control.len() < MIN_POINTS {
        return Err(CalibrationError::TooFewControlPoints {
            count: control.len(),
        });
    }
    let mut by_id = HashMap::with_capacity(control.len());
    for point in control {
        if !point.position.iter().all(|v| v.is_finite()) {
            return Err(CalibrationError::NonFiniteControlPoint { id: point.id });
        }
        if by_id.insert(point.id, point.position).is_some() {
            return Err(CalibrationError::DuplicateControlPoint { id: point.id });
        }
    }
    let check: HashSet<u64> = match &options.check_points {
        CheckPoints::None => HashSet::new(),
        CheckPoints::Every(0) => {
            return Err(CalibrationError::InvalidOption(
                "check points every 0-th point: give K >= 2".into(),
            ))
        }
        CheckPoints::Every(k) => control
            .iter()
            .enumerate()
            .filter(|(i, _)| (i + 1) % k == 0)
            .map(|(_, p)| p.id)
            .collect(),
        CheckPoints::Ids(ids) => {
            if let Some(id) = ids.iter().find(|id| !by_id.contains_key(id)) {
                return Err(CalibrationError::InvalidOption(format!(
                    "check point {id} is not a control point"
                )));
            }
            ids.iter().copied().collect()
        }
    };
    Ok(Prepared {
        control: by_id,
        check,
        fixed,
    })
}

/// Validates what the calibration takes from a setup camera: sensor, media,
/// distortion, and the values of fixed parameters. Free exterior and
/// interior values are only unused starting values, so they are replaced by
/// valid ones first (a position on the air side of the wall, c = 1).
fn validate_setup(parameters: &CameraParameters, fixed: ParameterSet) -> Result<(), InvalidCamera> {
    let mut probe = parameters.clone();
    let media = &probe.media;
    let outside = media.glass_vector.norm()
        + media.walls.iter().map(|w| w.thickness.abs()).sum::<f64>()
        + 1000.0;
    let normal = media
        .glass_vector
        .try_normalize(0.0)
        .unwrap_or_else(nalgebra::Vector3::z);
    for (k, p) in ParameterSet::position().iter().enumerate() {
        if !fixed.contains(p) {
            probe.exterior.position[k] = normal[k] * outside;
        }
    }
    for (p, angle) in ParameterSet::rotation().iter().zip([
        &mut probe.exterior.omega,
        &mut probe.exterior.phi,
        &mut probe.exterior.kappa,
    ]) {
        if !fixed.contains(p) {
            *angle = 0.0;
        }
    }
    if !fixed.contains(Parameter::C) {
        probe.interior.c = 1.0;
    }
    if !fixed.contains(Parameter::Xh) {
        probe.interior.xh = 0.0;
    }
    if !fixed.contains(Parameter::Yh) {
        probe.interior.yh = 0.0;
    }
    Camera::new(probe).map(|_| ())
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

#[allow(clippy::too_many_arguments)]
fn camera_report(
    camera: &CameraParameters,
    free: ParameterSet,
    prepared: &Prepared,
    held: &[(Parameter, String)],
    active: &[(u64, Equation)],
    stats: &resection::Statistics,
    (uncertainty, estimated): (&resection::Statistics, ParameterSet),
    excluded: Vec<PointResidual>,
    iterations: usize,
    options: &CalibrationOptions,
) -> CameraReport {
    let v: ParameterVector = resection::to_vector(camera);
    // The cofactor matrix's parameters: the free ones and those held at
    // their estimates.
    let order: Vec<Parameter> = estimated.iter().collect();
    let sigma = |k: usize| {
        uncertainty
            .cofactor
            .as_ref()
            .map(|q| uncertainty.sigma0 * q[(k, k)].max(0.0).sqrt())
    };
    let parameters = Parameter::ALL
        .iter()
        .map(|&p| {
            let held_reason = held.iter().find(|(h, _)| *h == p).map(|(_, r)| r.clone());
            let (status, sigma) = if free.contains(p) {
                let k = order.iter().position(|&o| o == p).unwrap_or(0);
                (ParameterStatus::Free, sigma(k))
            } else if prepared.fixed.contains(p) {
                (ParameterStatus::Fixed, None)
            } else {
                (ParameterStatus::Held, None)
            };
            ParameterReport {
                name: p,
                value: v[p.index()],
                sigma,
                status,
                reason: if status == ParameterStatus::Held {
                    held_reason
                } else {
                    None
                },
            }
        })
        .collect();
    let mut correlations = Vec::new();
    if let Some(q) = &uncertainty.cofactor {
        for a in 0..order.len() {
            for b in a + 1..order.len() {
                let r = q[(a, b)] / (q[(a, a)] * q[(b, b)]).sqrt();
                correlations.push(Correlation {
                    a: order[a],
                    b: order[b],
                    value: r,
                });
            }
        }
    }
    let mut covariance = vec![vec![0.0; 16]; 16];
    if let Some(q) = &uncertainty.cofactor {
        let s2 = uncertainty.sigma0 * uncertainty.sigma0;
        for (a, pa) in order.iter().enumerate() {
            for (b, pb) in order.iter().enumerate() {
                covariance[pa.index()][pb.index()] = s2 * q[(a, b)];
            }
        }
    }
    correlations.sort_by(|x, y| y.value.abs().total_cmp(&x.value.abs()));
    correlations.truncate(10);
    let residuals = active
        .iter()
        .zip(&stats.residuals)
        .zip(&stats.test)
        .map(|(((id, _), r), t)| PointResidual {
            id: *id,
            x_px: r.x,
            y_px: r.y,
            test: *t,
        })
        .collect();
    CameraReport {
        name: camera.name.clone(),
        // A parameter held at its estimate was estimated: it counts
        // against the redundancy.
        sigma0_px: uncertainty.sigma0,
        points_used: active.len(),
        redundancy: uncertainty.redundancy,
        iterations,
        snooping_critical: snooping_critical(options.snooping_alpha, active.len()),
        parameters,
        covariance,
        largest_correlations: correlations,
        residuals,
        excluded,
    }
}

/// The test statistic `vᵢᵀ Cov(vᵢ)⁻¹ vᵢ` (chi-square, 2 dof) of each
/// observation of an intersected check point, `None` where an observation
/// has no redundancy to test. The intersection (section 4.3, equal weights)
/// gives `v = (I - H) e` with `H = A (AᵀA)⁻¹ Aᵀ`, and a check point's image
/// errors `e` hold the calibration's errors besides the noise:
/// `Cov(eₖ) = sigma0ₖ² I + Bₖ Cₖ Bₖᵀ` with camera k's parameter Jacobian
/// `Bₖ` and parameter covariance `Cₖ` from its report.
fn intersection_tests(
    rig: &[Camera],
    reports: &[CameraReport],
    seen: &[Observation],
    intersection: &super::intersect::Intersection,
) -> Vec<Option<f64>> {
    let m = seen.len();
    let mut a = nalgebra::DMatrix::zeros(2 * m, 3);
    let mut cov_e = nalgebra::DMatrix::zeros(2 * m, 2 * m);
    for (i, o) in seen.iter().enumerate() {
        let (Some(camera), Some(report)) = (rig.get(o.camera), reports.get(o.camera)) else {
            return vec![None; m];
        };
        let Ok((_, j)) = camera.project_with_jacobian(&intersection.point) else {
            return vec![None; m];
        };
        a.view_mut((2 * i, 0), (2, 3)).copy_from(&j);
        let Some((_, b)) =
            resection::projection_with_parameter_jacobian(camera.parameters(), &intersection.point)
        else {
            return vec![None; m];
        };
        let c = nalgebra::SMatrix::<f64, 16, 16>::from_fn(|r, k| {
            report
                .covariance
                .get(r)
                .and_then(|row| row.get(k))
                .copied()
                .unwrap_or(0.0)
        });
        let block = b * c * b.transpose()
            + nalgebra::Matrix2::identity() * report.sigma0_px * report.sigma0_px;
        cov_e.view_mut((2 * i, 2 * i), (2, 2)).copy_from(&block);
    }
    let Some(q) = (a.transpose() * &a).try_inverse() else {
        return vec![None; m];
    };
    let projector = nalgebra::DMatrix::identity(2 * m, 2 * m) - &a * q * a.transpose();
    let cov_v = &projector * &cov_e * projector.transpose();
    (0..m)
        .map(|i| {
            let block = cov_v.view((2 * i, 2 * i), (2, 2)).into_owned();
            let v = intersection.residuals_px.get(i)?;
            let scale = cov_e[(2 * i, 2 * i)] + cov_e[(2 * i + 1, 2 * i + 1)];
            // No redundancy to test: the residual is forced to (almost) zero.
            if block.trace() < 0.01 * scale {
                return None;
            }
            let inverse =
                nalgebra::Matrix2::new(block[(0, 0)], block[(0, 1)], block[(1, 0)], block[(1, 1)])
                    .try_inverse()?;
            let t = v.dot(&(inverse * v));
            t.is_finite().then_some(t)
        })
        .collect()
}

/// Intersects the check points from every camera that observed them.
fn check_point_report(
    cameras: &[CameraParameters],
    reports: &[CameraReport],
    control: &[ControlPoint],
    observations: &[Vec<MarkObservation>],
    prepared: &Prepared,
) -> CheckPointReport {
    let rig: Vec<Camera> = cameras
        .iter()
        .filter_map(|c| Camera::new(c.clone()).ok())
        .collect();
    let tests = observations
        .iter()
        .map(|list| {
            list.iter()
                .filter(|o| prepared.check.contains(&o.id))
                .count()
        })
        .sum();
    let critical = snooping_critical(0.001, tests);
    let observed = |id: u64| -> Vec<Observation> {
        observations
            .iter()
            .enumerate()
            .filter_map(|(camera, list)| {
                list.iter().find(|o| o.id == id).map(|o| Observation {
                    camera,
                    pixel: o.pixel,
                })
            })
            .collect()
    };
    let complete = rig.len() == cameras.len();
    let mut points = Vec::new();
    let mut not_intersected = Vec::new();
    let mut excluded_observations = Vec::new();
    for point in control.iter().filter(|p| prepared.check.contains(&p.id)) {
        let mut seen = observed(point.id);
        let mut found = complete.then(|| intersect(&rig, &seen).ok()).flatten();
        // Snooping within the point: with three or more observations the
        // worst one goes while it is significant.
        while let Some(intersection) = found.as_ref().filter(|_| seen.len() >= 3) {
            let worst = intersection_tests(&rig, reports, &seen, intersection)
                .into_iter()
                .enumerate()
                .filter_map(|(i, t)| t.map(|t| (i, t)))
                .max_by(|a, b| a.1.total_cmp(&b.1));
            match worst {
                Some((i, t)) if t > critical => {
                    let gone = seen.remove(i);
                    excluded_observations.push(ExcludedObservation {
                        id: point.id,
                        camera: gone.camera,
                        test: t,
                    });
                    found = intersect(&rig, &seen).ok();
                }
                _ => break,
            }
        }
        match found {
            Some(found) => {
                let d = found.point - point.position;
                points.push(CheckPointDeviation {
                    id: point.id,
                    dx: d.x,
                    dy: d.y,
                    dz: d.z,
                    cameras: seen.len(),
                });
            }
            None => not_intersected.push(point.id),
        }
    }
    let rms = |f: fn(&CheckPointDeviation) -> f64| {
        if points.is_empty() {
            return f64::NAN;
        }
        (points.iter().map(|p| f(p).powi(2)).sum::<f64>() / points.len() as f64).sqrt()
    };
    let (rmse_x_mm, rmse_y_mm, rmse_z_mm) = (rms(|p| p.dx), rms(|p| p.dy), rms(|p| p.dz));
    let rmse_mm = ((rmse_x_mm.powi(2) + rmse_y_mm.powi(2) + rmse_z_mm.powi(2)) / 3.0).sqrt();
    let mut min = Point3::new(f64::INFINITY, f64::INFINITY, f64::INFINITY);
    let mut max = -min;
    for p in control {
        min = min.inf(&p.position);
        max = max.sup(&p.position);
    }
    let diagonal_mm = (max - min).norm();
    CheckPointReport {
        count: points.len(),
        rmse_x_mm,
        rmse_y_mm,
        rmse_z_mm,
        rmse_mm,
        diagonal_mm,
        relative_accuracy: diagonal_mm / rmse_mm,
        points,
        not_intersected,
        excluded_observations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec, TargetShape};

    /// A pinhole rig in air, points in a box: the DLT start is exact to
    /// rounding on noise-free images, and the plane start (with the true
    /// interior) is exact on a plane.
    #[test]
    fn closed_form_starts_are_exact_without_noise() {
        let mut spec = RigSpec::convergent(3);
        spec.tank = None;
        spec.principal_point = nalgebra::Vector2::new(0.05, -0.08);
        let mut rng = simulate::rng(1);
        let target = simulate::calibration_target(TargetShape::Volume, &spec.volume, 30, &mut rng);
        for camera in spec.build().unwrap() {
            let pairs: Vec<_> = target
                .iter()
                .map(|p| {
                    let pixel = camera.project(&p.position).unwrap();
                    (
                        p.position,
                        dlt::ideal_metric(camera.parameters(), pixel).unwrap(),
                    )
                })
                .collect();
            let start = dlt::start_from_dlt(camera.parameters(), &pairs).unwrap();
            let truth = camera.parameters();
            assert!((start.exterior.position - truth.exterior.position).norm() < 1e-6);
            assert!((start.interior.c - truth.interior.c).abs() < 1e-7);
            assert!((start.interior.xh - truth.interior.xh).abs() < 1e-7);
            let r = super::super::camera::rotation_matrix(
                start.exterior.omega,
                start.exterior.phi,
                start.exterior.kappa,
            );
            assert!((r - camera.rotation()).abs().max() < 1e-9);
            let plane: Vec<_> = pairs
                .iter()
                .map(|(p, _)| Point3::new(p.x, p.y, 0.0))
                .map(|p| {
                    let pixel = camera.project(&p).unwrap();
                    (p, dlt::ideal_metric(truth, pixel).unwrap())
                })
                .collect();
            assert!(dlt::flatness(&plane.iter().map(|p| p.0).collect::<Vec<_>>()) < 1e-12);
            let start = dlt::start_from_plane(truth, &plane).unwrap();
            assert!((start.exterior.position - truth.exterior.position).norm() < 1e-6);
        }
    }

    /// Marks are assigned to the right points from a rough orientation, and
    /// stray marks are left alone.
    #[test]
    fn identifies_marks_from_a_rough_orientation() {
        let spec = RigSpec::convergent(1);
        let camera = spec.build().unwrap().remove(0);
        let mut rng = simulate::rng(2);
        let target =
            simulate::calibration_target(TargetShape::TwoPlanes, &spec.volume, 50, &mut rng);
        let mut marks: Vec<Point2<f64>> = target
            .iter()
            .map(|p| camera.project(&p.position).unwrap())
            .collect();
        marks.push(Point2::new(3.0, 4.0));
        let mut rough = camera.parameters().clone();
        rough.exterior.position.x += 2.0;
        rough.exterior.kappa += 0.002;
        let found = identify_marks(&rough, &target, &marks);
        assert!(found.len() >= 45, "{}", found.len());
        for o in &found {
            let truth = target.iter().position(|p| p.id == o.id).unwrap();
            assert_eq!(o.pixel, marks[truth]);
        }
    }

    #[test]
    fn snooping_critical_value_is_the_bonferroni_chi_square_quantile() {
        // P(chi2_2 > t) = exp(-t / 2).
        let t = snooping_critical(0.001, 200);
        assert!(((-t / 2.0).exp() - 0.001 / 200.0).abs() < 1e-15);
    }
}
