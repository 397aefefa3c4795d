//! The inputs shared by the cameras, validated once before any adjustment:
//! the setup's cameras, the control points, the check points and the
//! options.

use std::collections::{HashMap, HashSet};

use nalgebra::Point3;

use super::{
    CalibrationError, CalibrationOptions, CheckPoints, ControlPoint, Parameter, ParameterSet,
    MIN_POINTS,
};
use crate::photogrammetry::camera::{Camera, CameraParameters, InvalidCamera};

/// Validated inputs shared by the cameras.
pub(super) struct Prepared {
    /// Control points by id.
    pub(super) control: HashMap<u64, Point3<f64>>,
    /// Ids of check points.
    pub(super) check: HashSet<u64>,
    /// Which parameters the user fixed.
    pub(super) fixed: ParameterSet,
}

pub(super) fn prepare(
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
    if !options.unknown.is_empty() && options.unknown.len() != setup.len() {
        return Err(CalibrationError::InvalidOption(format!(
            "the parameters the setup leaves out are given for {} cameras, but the setup has {}",
            options.unknown.len(),
            setup.len()
        )));
    }
    for (camera, (parameters, unknown)) in setup.iter().zip(&options.unknown).enumerate() {
        if let Some(parameter) = unknown.iter().find(|p| fixed.contains(*p)) {
            return Err(CalibrationError::FixedWithoutValue {
                camera,
                name: parameters.name.clone(),
                parameter,
            });
        }
    }
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
