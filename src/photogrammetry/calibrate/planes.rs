//! Multi-plane calibration: a flat plate imaged at several known
//! positions (moved along its normal, or one target file per position),
//! every camera's parameters shared, in one adjustment.
//!
//! A plate at one depth cannot determine the principal distance with the
//! position (the plane homography has 8 degrees of freedom, the camera 9
//! with c, xh, yh; see `single_plane_needs_known_interior`): the same
//! plate at two or more depths makes a three-dimensional target, which
//! does. So the planes are merged into one target and one set of
//! observations per camera, and calibrated by the same resection as any
//! target ([`super::calibrate`], [`super::calibrate_from_marks`]): one way
//! to adjust.
//!
//! The planes' control points are in the common frame (each plane's file
//! gives its points where the plate was). Their ids may repeat between
//! planes (the same plate): plane `k` (1-based) point `id` becomes
//! `k * PLANE_ID_STRIDE + id` in the merged target and the report.

use nalgebra::Point3;

use super::identify::{identify_marks, MAX_ROUNDS};
use super::{
    calibrate, dlt, CalibrationError, CalibrationOptions, CheckPoints, ControlPoint,
    MarkObservation, RigCalibration, MIN_POINTS,
};
use crate::photogrammetry::camera::CameraParameters;
use crate::photogrammetry::Target;

/// Plane `k`'s (1-based) point `id` is `k * PLANE_ID_STRIDE + id` in the
/// merged target and the report.
pub const PLANE_ID_STRIDE: u64 = 1_000_000;

/// One position of the plate: its control points in the common frame and,
/// per camera in the setup's order, the measured image coordinates of its
/// points.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    /// The control points where the plate was (mm, the common frame).
    pub control: Vec<ControlPoint>,
    /// Per camera, the observations of this plane's points.
    pub observations: Vec<Vec<MarkObservation>>,
}

/// One position of the plate with its detected marks per camera.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaneMarks {
    /// The control points where the plate was (mm, the common frame).
    pub control: Vec<ControlPoint>,
    /// Per camera, the marks detected in its image of this plane.
    pub marks: Vec<Vec<Target>>,
}

/// Plane `plane`'s (0-based) point `id` in the merged target.
pub fn merged_id(plane: usize, id: u64) -> u64 {
    (plane as u64 + 1) * PLANE_ID_STRIDE + id
}

/// The planes' control points as one target (ids made unique), after
/// checking the ids and that the planes do not all lie in one plane.
pub fn merge_control(planes: &[&[ControlPoint]]) -> Result<Vec<ControlPoint>, CalibrationError> {
    let mut merged = Vec::new();
    for (k, control) in planes.iter().enumerate() {
        if let Some(p) = control.iter().find(|p| p.id >= PLANE_ID_STRIDE) {
            return Err(CalibrationError::PlaneIdTooLarge {
                plane: k + 1,
                id: p.id,
            });
        }
        merged.extend(control.iter().map(|p| ControlPoint {
            id: merged_id(k, p.id),
            position: p.position,
        }));
    }
    if planes.len() > 1 {
        let points: Vec<Point3<f64>> = merged.iter().map(|p| p.position).collect();
        if dlt::flatness(&points) < 1e-3 {
            // Name the first pair that is in one plane together.
            let pair = (0..planes.len())
                .flat_map(|a| (a + 1..planes.len()).map(move |b| (a, b)))
                .find(|&(a, b)| {
                    let two: Vec<Point3<f64>> = planes[a]
                        .iter()
                        .chain(planes[b].iter())
                        .map(|p| p.position)
                        .collect();
                    dlt::flatness(&two) < 1e-3
                })
                .unwrap_or((0, 1));
            return Err(CalibrationError::PlanesCoincide {
                planes: planes.len(),
                first: pair.0 + 1,
                second: pair.1 + 1,
            });
        }
    }
    Ok(merged)
}

fn check_plane_counts(
    setup: &[CameraParameters],
    given: impl Iterator<Item = usize>,
) -> Result<(), CalibrationError> {
    for (k, given) in given.enumerate() {
        if given != setup.len() {
            return Err(CalibrationError::PlaneCameraCount {
                plane: k + 1,
                cameras: setup.len(),
                given,
            });
        }
    }
    Ok(())
}

/// Per camera, the observations of all planes with merged ids, after
/// checking that every camera sees every plane in at least
/// [`MIN_POINTS`] marks.
fn merge_observations(
    setup: &[CameraParameters],
    per_plane: &[Vec<Vec<MarkObservation>>],
) -> Result<Vec<Vec<MarkObservation>>, CalibrationError> {
    let mut merged = vec![Vec::new(); setup.len()];
    for (k, observations) in per_plane.iter().enumerate() {
        for (camera, (observed, name)) in observations.iter().zip(setup).enumerate() {
            if observed.len() < MIN_POINTS {
                return Err(CalibrationError::TooFewPlaneMarks {
                    plane: k + 1,
                    camera,
                    name: name.name.clone(),
                    found: observed.len(),
                });
            }
            merged[camera].extend(observed.iter().map(|o| MarkObservation {
                id: merged_id(k, o.id),
                pixel: o.pixel,
            }));
        }
    }
    Ok(merged)
}

/// Calibrates every camera of `setup` on the plate at all `planes` in one
/// adjustment per camera (see the module's documentation); otherwise as
/// [`calibrate`], whose options apply (check point ids are merged ids).
pub fn calibrate_planes(
    setup: &[CameraParameters],
    planes: &[Plane],
    options: &CalibrationOptions,
) -> Result<RigCalibration, CalibrationError> {
    check_plane_counts(setup, planes.iter().map(|p| p.observations.len()))?;
    let controls: Vec<&[ControlPoint]> = planes.iter().map(|p| p.control.as_slice()).collect();
    let control = merge_control(&controls)?;
    let per_plane: Vec<Vec<Vec<MarkObservation>>> =
        planes.iter().map(|p| p.observations.clone()).collect();
    let observations = merge_observations(setup, &per_plane)?;
    calibrate(setup, &control, &observations, options)
}

/// Calibrates from detected marks of the plate at all `planes`: each
/// image's marks are identified with its plane's control points by
/// projecting them with the setup's orientation, then with the resection
/// of all planes together, until the identification no longer changes
/// (as [`super::calibrate_from_marks`] does for one target); then
/// [`calibrate_planes`]. The setup must give every camera's orientation.
pub fn calibrate_planes_from_marks(
    setup: &[CameraParameters],
    planes: &[PlaneMarks],
    options: &CalibrationOptions,
) -> Result<RigCalibration, CalibrationError> {
    check_plane_counts(setup, planes.iter().map(|p| p.marks.len()))?;
    let controls: Vec<&[ControlPoint]> = planes.iter().map(|p| p.control.as_slice()).collect();
    let control = merge_control(&controls)?;
    super::check_mark_inputs(setup, &control, &vec![0; setup.len()], options)?;
    let identify = |camera: &CameraParameters, k: usize| -> Vec<Vec<MarkObservation>> {
        planes
            .iter()
            .map(|plane| identify_marks(camera, &plane.control, &plane.marks[k]))
            .collect()
    };
    let mut identified: Vec<Vec<Vec<MarkObservation>>> = Vec::with_capacity(setup.len());
    for (k, camera) in setup.iter().enumerate() {
        let mut assigned = identify(camera, k);
        for _ in 0..MAX_ROUNDS {
            let per_plane: Vec<Vec<Vec<MarkObservation>>> =
                assigned.iter().map(|o| vec![o.clone()]).collect();
            let observations = merge_observations(std::slice::from_ref(camera), &per_plane)?;
            let single = calibrate(
                std::slice::from_ref(camera),
                &control,
                &observations,
                &CalibrationOptions {
                    check_points: CheckPoints::None,
                    unknown: options.unknown.get(k).map(|u| vec![*u]).unwrap_or_default(),
                    ..options.clone()
                },
            )
            .map_err(|e| renumber_camera(e, k))?;
            let current = single.cameras.into_iter().next().unwrap_or(camera.clone());
            let again = identify(&current, k);
            if again == assigned {
                break;
            }
            assigned = again;
        }
        identified.push(assigned);
    }
    // Plane-major, as calibrate_planes takes them.
    let planes: Vec<Plane> = planes
        .iter()
        .enumerate()
        .map(|(p, plane)| Plane {
            control: plane.control.clone(),
            observations: identified.iter().map(|per| per[p].clone()).collect(),
        })
        .collect();
    calibrate_planes(setup, &planes, options)
}

/// An error of a one-camera calibration, renumbered to camera `k`.
fn renumber_camera(error: CalibrationError, k: usize) -> CalibrationError {
    use CalibrationError as E;
    match error {
        E::TooFewPlaneMarks {
            plane, name, found, ..
        } => E::TooFewPlaneMarks {
            plane,
            camera: k,
            name,
            found,
        },
        E::NoConvergence { name, .. } => E::NoConvergence { camera: k, name },
        E::ImplausibleGeometry { name, reason, .. } => E::ImplausibleGeometry {
            camera: k,
            name,
            reason,
        },
        other => other,
    }
}
