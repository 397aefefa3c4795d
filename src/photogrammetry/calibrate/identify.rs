//! Which detected mark is which control point.
//!
//! The control points are projected with the current orientation of the
//! camera; each projection takes the nearest mark if that mark has no nearer
//! projection (mutual nearest neighbours) and lies within 0.4 of the
//! distance to the projection's own nearest neighbour, so that a mark can
//! only be taken by the point it is clearly closest to. Starting from the
//! setup's orientation, or from a resection on a few reference points the
//! user identified (`id x y`), resection and assignment alternate until the
//! assignment no longer changes.

use nalgebra::Point2;

use super::{
    adjustment, calibrate, dlt, resection, CalibrationError, CalibrationOptions, ControlPoint,
    MarkObservation, ParameterSet, RigCalibration,
};
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::correspond::max_targets_of;
use crate::photogrammetry::detect::{
    detect_within, DetectError, DetectionParameters, InvalidDetectionParameters, Preprocessing,
};
use crate::photogrammetry::image::GreyImage;

/// The detection parameters for calibration marks: as given, but a mark's
/// extent is bounded only by its pixel count (marks are larger than
/// particles). Validated.
pub fn mark_detection_parameters(
    parameters: &DetectionParameters,
) -> Result<DetectionParameters, InvalidDetectionParameters> {
    let mut parameters = parameters.clone();
    parameters.max_nx = parameters.max_nx.max(parameters.max_pixels);
    parameters.max_ny = parameters.max_ny.max(parameters.max_pixels);
    parameters.validate()?;
    Ok(parameters)
}

/// The centres (px) of the marks in a calibration image, detected with
/// parameters from [`mark_detection_parameters`]. Detection stops once
/// the image has more marks than [`max_targets_of`] its size (one per 2x2
/// pixels, at most 2^20; a real target has hundreds to thousands), so a
/// hostile image with permissive settings costs no more than a frame.
pub fn detect_marks(
    image: &GreyImage,
    parameters: &DetectionParameters,
) -> Result<Vec<Point2<f64>>, DetectError> {
    let limit = max_targets_of(image.width(), image.height());
    let targets = detect_within(image, &Preprocessing::default(), parameters, limit)?;
    Ok(targets.iter().map(|t| Point2::new(t.x, t.y)).collect())
}

/// Assigns `marks` (detected image positions, px) to control points by
/// projecting them with `camera`. Returns the identified observations,
/// ordered by control point.
pub fn identify_marks(
    camera: &CameraParameters,
    control: &[ControlPoint],
    marks: &[Point2<f64>],
) -> Vec<MarkObservation> {
    let Ok(model) = Camera::new(camera.clone()) else {
        return Vec::new();
    };
    let projected: Vec<(u64, Point2<f64>)> = control
        .iter()
        .filter_map(|p| {
            let pixel = model.project(&p.position).ok()?;
            (pixel.x.is_finite() && pixel.y.is_finite()).then_some((p.id, pixel))
        })
        .collect();
    let finite: Vec<Point2<f64>> = marks
        .iter()
        .copied()
        .filter(|m| m.x.is_finite() && m.y.is_finite())
        .collect();
    let nearest = |from: &Point2<f64>, among: &mut dyn Iterator<Item = (usize, Point2<f64>)>| {
        among
            .map(|(i, q)| (i, (q - from).norm()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    };
    let mut found = Vec::new();
    for (k, (id, pixel)) in projected.iter().enumerate() {
        let Some((m, distance)) = nearest(pixel, &mut finite.iter().copied().enumerate()) else {
            break;
        };
        let spacing = nearest(
            pixel,
            &mut projected
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != k)
                .map(|(j, (_, q))| (j, *q)),
        )
        .map_or(f64::INFINITY, |(_, d)| d);
        let back = nearest(
            &finite[m],
            &mut projected.iter().map(|(_, q)| *q).enumerate(),
        );
        if back.is_some_and(|(j, _)| j == k) && distance < 0.4 * spacing {
            found.push(MarkObservation {
                id: *id,
                pixel: finite[m],
            });
        }
    }
    found
}

/// The largest number of resection-and-assignment rounds per camera.
const MAX_ROUNDS: usize = 10;

/// Calibrates from detected marks: per camera the marks (px) and either
/// reference points (`references[camera]`: at least 6 identified marks, or
/// 4 in one plane with the setup's interior orientation), or, where that
/// list is empty, the setup's orientation as the starting value. Marks are
/// identified by [`identify_marks`], alternating with resections, then the
/// whole rig is calibrated by [`calibrate`] with check points and report.
pub fn calibrate_from_marks(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    marks: &[Vec<Point2<f64>>],
    references: &[Vec<MarkObservation>],
    options: &CalibrationOptions,
) -> Result<RigCalibration, CalibrationError> {
    for given in [marks.len(), references.len()] {
        if given != setup.len() {
            return Err(CalibrationError::CameraCount {
                cameras: setup.len(),
                given,
            });
        }
    }
    let counts: Vec<usize> = references.iter().map(Vec::len).collect();
    check_identification_start(setup, &counts, options)?;
    let mut identified = Vec::with_capacity(setup.len());
    for (k, camera) in setup.iter().enumerate() {
        let unknown = options.unknown.get(k).copied().unwrap_or_default();
        let too_few = |found: usize| CalibrationError::TooFewIdentified {
            camera: k,
            name: camera.name.clone(),
            found,
        };
        let mut current = if references[k].is_empty() {
            camera.clone()
        } else {
            start_from_references(k, camera, control, &references[k], unknown)?
        };
        let mut assigned = identify_marks(&current, control, &marks[k]);
        for _ in 0..MAX_ROUNDS {
            if assigned.len() < super::MIN_POINTS {
                return Err(too_few(assigned.len()));
            }
            let single = calibrate(
                std::slice::from_ref(camera),
                control,
                std::slice::from_ref(&assigned),
                &CalibrationOptions {
                    check_points: super::CheckPoints::None,
                    unknown: options.unknown.get(k).map(|u| vec![*u]).unwrap_or_default(),
                    ..options.clone()
                },
            )?;
            current = single.cameras.into_iter().next().unwrap_or(current);
            let again = identify_marks(&current, control, &marks[k]);
            if again == assigned {
                break;
            }
            assigned = again;
        }
        identified.push(assigned);
    }
    calibrate(setup, control, &identified, options)
}

/// Where a camera has no reference points, its marks are identified by
/// projecting the control points with the setup's orientation: the setup
/// must give it (`references[camera]` is the number of reference points).
pub(super) fn check_identification_start(
    setup: &[CameraParameters],
    references: &[usize],
    options: &CalibrationOptions,
) -> Result<(), CalibrationError> {
    for (k, (camera, &given)) in setup.iter().zip(references).enumerate() {
        let unknown = options.unknown.get(k).copied().unwrap_or_default();
        let missing: Vec<_> = (ParameterSet::exterior() | ParameterSet::interior())
            .iter()
            .filter(|p| unknown.contains(*p))
            .collect();
        if given == 0 && !missing.is_empty() {
            return Err(CalibrationError::NoStartToIdentify {
                camera: k,
                name: camera.name.clone(),
                missing,
            });
        }
    }
    Ok(())
}

/// The orientation from the user's reference points alone: the closed-form
/// start, then the exterior orientation (with the setup's interior) through
/// the strict model.
fn start_from_references(
    k: usize,
    camera: &CameraParameters,
    control: &[ControlPoint],
    references: &[MarkObservation],
    unknown: ParameterSet,
) -> Result<CameraParameters, CalibrationError> {
    let mut pairs = Vec::new();
    let mut equations = Vec::new();
    for r in references {
        let Some(point) = control.iter().find(|p| p.id == r.id) else {
            return Err(CalibrationError::UnknownId {
                camera: k,
                id: r.id,
            });
        };
        if !(r.pixel.x.is_finite() && r.pixel.y.is_finite()) {
            return Err(CalibrationError::NonFiniteObservation {
                camera: k,
                id: r.id,
            });
        }
        if let Some(m) = dlt::ideal_metric(camera, r.pixel) {
            pairs.push((point.position, m));
        }
        equations.push(adjustment::Equation {
            point: point.position,
            pixel: r.pixel,
        });
    }
    let points: Vec<_> = pairs.iter().map(|(p, _)| *p).collect();
    let no_start = || CalibrationError::NoStart {
        camera: k,
        name: camera.name.clone(),
    };
    let flat = dlt::flatness(&points) < 1e-3;
    let oriented = resection::has_orientation(camera, unknown);
    if pairs.len() >= 4 && !flat && pairs.len() < super::MIN_POINTS && oriented {
        // Too few for the DLT, but the setup has an orientation: OpenPTV's
        // manual orientation (4 points, `man_ori`) adjusts the exterior
        // orientation from the setup's (its `raw_orient`): 8 equations, 6
        // unknowns.
        return resection::valid_start(camera.clone())
            .and_then(|start| adjustment::adjust(&start, ParameterSet::exterior(), &equations, 50))
            .map(|a| a.parameters)
            .ok_or_else(no_start);
    }
    if pairs.len() < 4 || (!flat && pairs.len() < super::MIN_POINTS) {
        return Err(CalibrationError::TooFewReferences {
            camera: k,
            name: camera.name.clone(),
            given: references.len(),
        });
    }
    let missing_interior: Vec<_> = ParameterSet::interior()
        .iter()
        .filter(|p| unknown.contains(*p))
        .collect();
    if flat && !missing_interior.is_empty() {
        return Err(CalibrationError::PlanarReferencesWithoutInterior {
            camera: k,
            name: camera.name.clone(),
            given: references.len(),
            missing: missing_interior,
        });
    }
    let start = if !flat {
        dlt::start_from_dlt(camera, &pairs).map(|mut s| {
            // Keep the setup's distortion; the DLT's interior is only a start.
            s.distortion = camera.distortion.clone();
            s
        })
    } else {
        dlt::start_from_plane(camera, &pairs)
    }
    .and_then(resection::valid_start)
    .ok_or_else(no_start)?;
    adjustment::adjust(&start, ParameterSet::exterior(), &equations, 50)
        .map(|a| a.parameters)
        .ok_or_else(no_start)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec, TargetShape};

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
}
