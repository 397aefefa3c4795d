//! Why a calibration cannot be done: each error names the camera and what
//! to change.

use super::{Parameter, MIN_POINTS};
use crate::photogrammetry::camera::InvalidCamera;

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
    /// Multi-plane calibration: a plane's inputs are not one per camera.
    #[error("plane {plane}: {given} images or observation lists for {cameras} cameras; give one per camera, in camera order, for every plane")]
    PlaneCameraCount {
        /// The plane (1-based, in the order given).
        plane: usize,
        /// Cameras in the setup.
        cameras: usize,
        /// Inputs given for the plane.
        given: usize,
    },
    /// Multi-plane calibration: a plane seen in too few marks by a camera.
    #[error("plane {plane}: camera {camera} ({name}) has only {found} marks of it, and a plane needs at least {MIN_POINTS} in every camera; check its image and the detection (threshold, pixel counts), or leave the plane out")]
    TooFewPlaneMarks {
        /// The plane (1-based, in the order given).
        plane: usize,
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Marks of the plane the camera has.
        found: usize,
    },
    /// Multi-plane calibration: the planes' control points all lie in one
    /// plane (the plate was not moved out of its plane, or the same
    /// positions were given twice).
    #[error("the {planes} planes' control points all lie in one plane (plane {first} and plane {second} coincide or the plate only slid within its plane), which cannot determine the interior orientation; give each position's control points in the common frame, the plate moved along its normal (e.g. Z = 0, 10, 20 mm)")]
    PlanesCoincide {
        /// How many planes were given.
        planes: usize,
        /// The first plane (1-based).
        first: usize,
        /// A second plane in the same plane (1-based).
        second: usize,
    },
    /// Multi-plane calibration: a control point id too large to be told
    /// apart from the other planes' (see [`super::PLANE_ID_STRIDE`]).
    #[error("plane {plane}: control point id {id} is {} or more; number the points of each plane below it", super::PLANE_ID_STRIDE)]
    PlaneIdTooLarge {
        /// The plane (1-based).
        plane: usize,
        /// The id.
        id: u64,
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
    /// The result's geometry is not fixed by the observations.
    #[error("camera {camera} ({name}): the observations do not fix the camera's geometry: {reason}. The target is too shallow (or too small in the image) for the parameters left free: fix the interior orientation at known values (--fix c,xh,yh and the distortion, with their values in the setup; OpenPTV's orient.par does the same), or calibrate with a deeper target or with the plate at several known positions (multi-plane)")]
    ImplausibleGeometry {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// What is implausible.
        reason: String,
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
    #[error("camera {camera} ({name}): {given} reference points do not determine a starting orientation; give at least 6 not in one plane, at least 4 in one plane with c, xh and yh right in the setup, or at least 4 with the camera's approximate orientation in the setup")]
    TooFewReferences {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Reference points given.
        given: usize,
    },
    /// A fixed parameter that the setup leaves out: there is no value to
    /// hold it at.
    #[error("camera {camera} ({name}): {} is fixed, but the setup gives no {}: give its value in the setup, or do not fix it (a setup without orientation needs only the sensor and media; the start comes from the DLT on the observed points)", parameter.name(), setup_field(*parameter))]
    FixedWithoutValue {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// The parameter.
        parameter: Parameter,
    },
    /// Marks to identify from images, in a camera whose setup has no
    /// orientation and with no reference points to start from.
    #[error("camera {camera} ({name}): its marks must be identified in the image, but the setup gives no {} to project the control points with, and no reference points were given; give reference points (`id x y` of at least 6 identified marks not in one plane: --reference in `ptv calibrate`, `reference` parts in /calibrations/solve), or measured observations of the control points instead of images, or the camera's approximate orientation in the setup", setup_fields(missing))]
    NoStartToIdentify {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// The orientation parameters the setup leaves out.
        missing: Vec<Parameter>,
    },
    /// Reference points in one plane, in a camera whose setup gives no
    /// interior orientation for the plane's start.
    #[error("camera {camera} ({name}): its {given} reference points lie in one plane, which needs the interior orientation from the setup, but the setup gives no {}; give at least 6 reference points not in one plane, or principal_distance and principal_point in the setup", setup_fields(missing))]
    PlanarReferencesWithoutInterior {
        /// The camera (0-based).
        camera: usize,
        /// Its name.
        name: String,
        /// Reference points given.
        given: usize,
        /// The interior parameters the setup leaves out.
        missing: Vec<Parameter>,
    },
    /// An option is out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
}

/// The calibration JSON field that holds a parameter (for messages about
/// setups).
pub fn setup_field(parameter: Parameter) -> &'static str {
    use Parameter::*;
    match parameter {
        X0 | Y0 | Z0 => "position",
        Omega | Phi | Kappa => "angles",
        C => "principal_distance",
        Xh | Yh => "principal_point",
        K1 | K2 | K3 => "radial",
        P1 | P2 => "decentering",
        Scx | She => "affine",
    }
}

/// The calibration JSON fields that hold `parameters`, each once, in order.
fn setup_fields(parameters: &[Parameter]) -> String {
    let mut fields: Vec<&str> = parameters.iter().map(|p| setup_field(*p)).collect();
    fields.dedup();
    fields.join(", ")
}
