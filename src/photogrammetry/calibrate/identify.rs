//! Which detected mark is which control point.
//!
//! The control points are projected with the current orientation of the
//! camera. Each projection looks at the marks within 0.4 of the distance to
//! its own nearest neighbouring projection, and among those takes the
//! nearest one that is *mark-like*: whose pixel count is within the marks'
//! typical size (below), so that a speck of noise next to a mark, or a mark
//! the camera does not see, yields no observation instead of a wrong one.
//! A mark is taken only if it has no nearer projection (mutual nearest
//! neighbours), so that it can only go to the point it is clearly closest
//! to. Starting from the setup's orientation, or from a resection on a few
//! reference points the user identified (`id x y`), resection and
//! assignment alternate until the assignment no longer changes.
//!
//! The typical size is estimated from the image itself, not given: near a
//! visible mark's projection the mark is the largest blob (noise specks are
//! a few pixels, a mark tens to hundreds), so the median over the
//! projections of the largest nearby blob's log pixel count is the typical
//! log size, robust while at least half of the projected marks are seen,
//! and 1.4826 times the median absolute deviation its spread `s`. Mark-like
//! is within `max(3 s, ln 2)` of it: three robust standard deviations of
//! the marks' own sizes (perspective and focus change them across the
//! image), and never narrower than a factor of 2. Marks of unknown size
//! (`n = 0`: positions measured elsewhere) are all mark-like, and the
//! nearest is taken.

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
use crate::photogrammetry::Target;

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

/// The marks in a calibration image (centre in px, pixel count, sum of
/// grey: the size [`identify_marks`] tells marks from noise by), detected
/// with parameters from [`mark_detection_parameters`]. Detection stops once
/// the image has more marks than [`max_targets_of`] its size (one per 2x2
/// pixels, at most 2^20; a real target has hundreds to thousands), so a
/// hostile image with permissive settings costs no more than a frame.
pub fn detect_marks(
    image: &GreyImage,
    parameters: &DetectionParameters,
) -> Result<Vec<Target>, DetectError> {
    let limit = max_targets_of(image.width(), image.height());
    detect_within(image, &Preprocessing::default(), parameters, limit)
}

/// A mark of unknown size at `pixel` (a position measured elsewhere): it
/// is identified by position alone.
pub fn mark_at(pixel: Point2<f64>) -> Target {
    Target {
        x: pixel.x,
        y: pixel.y,
        n: 0,
        nx: 0,
        ny: 0,
        sumg: 0,
    }
}

/// The marks' typical size, as a range of log pixel counts (see the module
/// documentation): `None` when no blob near a projection has a known size.
fn mark_like_sizes(near: &[Vec<usize>], marks: &[Target]) -> Option<(f64, f64)> {
    let mut largest: Vec<f64> = near
        .iter()
        .filter_map(|candidates| candidates.iter().map(|&m| marks[m].n).max())
        .filter(|&n| n > 0)
        .map(|n| f64::from(n).ln())
        .collect();
    if largest.is_empty() {
        return None;
    }
    let typical = median(&mut largest);
    let mut deviations: Vec<f64> = largest.iter().map(|l| (l - typical).abs()).collect();
    let spread = 1.4826 * median(&mut deviations);
    let half_width = (3.0 * spread).max(std::f64::consts::LN_2);
    Some((typical - half_width, typical + half_width))
}

/// The median of non-empty `values` (reordered).
fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let m = values.len() / 2;
    if values.len() % 2 == 1 {
        values[m]
    } else {
        (values[m - 1] + values[m]) / 2.0
    }
}

/// Assigns `marks` (detected in the image) to control points by projecting
/// them with `camera`, preferring mark-sized blobs (see the module
/// documentation). Returns the identified observations, ordered by control
/// point.
pub fn identify_marks(
    camera: &CameraParameters,
    control: &[ControlPoint],
    marks: &[Target],
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
    let finite: Vec<Target> = marks
        .iter()
        .copied()
        .filter(|m| m.x.is_finite() && m.y.is_finite())
        .collect();
    let at = |m: &Target| Point2::new(m.x, m.y);
    let nearest = |from: &Point2<f64>, among: &mut dyn Iterator<Item = (usize, Point2<f64>)>| {
        among
            .map(|(i, q)| (i, (q - from).norm()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    };
    // Per projection the marks within 0.4 of the distance to its nearest
    // neighbouring projection.
    let near: Vec<Vec<usize>> = projected
        .iter()
        .enumerate()
        .map(|(k, (_, pixel))| {
            let spacing = nearest(
                pixel,
                &mut projected
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != k)
                    .map(|(j, (_, q))| (j, *q)),
            )
            .map_or(f64::INFINITY, |(_, d)| d);
            finite
                .iter()
                .enumerate()
                .filter(|(_, m)| (at(m) - pixel).norm() < 0.4 * spacing)
                .map(|(i, _)| i)
                .collect()
        })
        .collect();
    let sizes = mark_like_sizes(&near, &finite);
    let mark_like = |m: &Target| {
        m.n == 0
            || sizes.map_or(true, |(low, high)| {
                let size = f64::from(m.n).ln();
                (low..=high).contains(&size)
            })
    };
    let mut found = Vec::new();
    for (k, ((id, pixel), candidates)) in projected.iter().zip(&near).enumerate() {
        let Some((m, _)) = nearest(
            pixel,
            &mut candidates
                .iter()
                .filter(|&&m| mark_like(&finite[m]))
                .map(|&m| (m, at(&finite[m]))),
        ) else {
            continue;
        };
        let back = nearest(
            &at(&finite[m]),
            &mut projected.iter().map(|(_, q)| *q).enumerate(),
        );
        if back.is_some_and(|(j, _)| j == k) {
            found.push(MarkObservation {
                id: *id,
                pixel: at(&finite[m]),
            });
        }
    }
    found
}

/// The largest number of resection-and-assignment rounds per camera.
pub(super) const MAX_ROUNDS: usize = 10;

/// Calibrates from detected marks: per camera the marks (centre in px and,
/// where known, pixel count; [`mark_at`] for positions alone) and either
/// reference points (`references[camera]`: at least 6 identified marks, or
/// 4 in one plane with the setup's interior orientation), or, where that
/// list is empty, the setup's orientation as the starting value. Marks are
/// identified by [`identify_marks`], alternating with resections, then the
/// whole rig is calibrated by [`calibrate`] with check points and report.
pub fn calibrate_from_marks(
    setup: &[CameraParameters],
    control: &[ControlPoint],
    marks: &[Vec<Target>],
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
        let mut marks: Vec<Target> = target
            .iter()
            .map(|p| mark_at(camera.project(&p.position).unwrap()))
            .collect();
        marks.push(mark_at(Point2::new(3.0, 4.0)));
        let mut rough = camera.parameters().clone();
        rough.exterior.position.x += 2.0;
        rough.exterior.kappa += 0.002;
        let found = identify_marks(&rough, &target, &marks);
        assert!(found.len() >= 45, "{}", found.len());
        for o in &found {
            let truth = target.iter().position(|p| p.id == o.id).unwrap();
            assert_eq!(o.pixel, Point2::new(marks[truth].x, marks[truth].y));
        }
    }

    /// With sizes known, a speck of noise nearer to the projection than the
    /// mark is passed over for the mark, and a mark the camera does not see
    /// gives no observation rather than the speck next to its projection;
    /// by position alone (the same blobs, sizes unknown) both specks are
    /// taken.
    #[test]
    fn prefers_mark_sized_blobs_to_nearer_specks() {
        let spec = RigSpec::convergent(1);
        let camera = spec.build().unwrap().remove(0);
        let mut rng = simulate::rng(3);
        let target =
            simulate::calibration_target(TargetShape::TwoPlanes, &spec.volume, 50, &mut rng);
        // Marks of 60-120 px; the first is hidden, the second has a speck
        // (3 px) nearer to its projection than its own 1.5 px offset.
        let mut marks: Vec<Target> = Vec::new();
        for (i, p) in target.iter().enumerate() {
            let pixel = camera.project(&p.position).unwrap();
            if i == 0 {
                marks.push(Target {
                    n: 3,
                    ..mark_at(pixel + nalgebra::Vector2::new(0.8, 0.0))
                });
                continue;
            }
            let offset = if i == 1 { 1.5 } else { 0.0 };
            marks.push(Target {
                n: 60 + (i as u32 * 7) % 60,
                ..mark_at(pixel + nalgebra::Vector2::new(offset, 0.0))
            });
            if i == 1 {
                marks.push(Target {
                    n: 3,
                    ..mark_at(pixel + nalgebra::Vector2::new(0.0, 0.5))
                });
            }
        }
        let found = identify_marks(camera.parameters(), &target, &marks);
        assert!(found.iter().all(|o| o.id != target[0].id), "{found:?}");
        let second = found.iter().find(|o| o.id == target[1].id).unwrap();
        let truth = camera.project(&target[1].position).unwrap();
        assert!((second.pixel.x - truth.x - 1.5).abs() < 1e-12, "{second:?}");
        assert_eq!(found.len(), target.len() - 1);
        // The same blobs by position alone: the specks are taken.
        let by_position: Vec<Target> = marks.iter().map(|m| Target { n: 0, ..*m }).collect();
        let found = identify_marks(camera.parameters(), &target, &by_position);
        assert!(found.iter().any(|o| o.id == target[0].id));
        let second = found.iter().find(|o| o.id == target[1].id).unwrap();
        assert!((second.pixel.y - truth.y - 0.5).abs() < 1e-12, "{second:?}");
    }
}
