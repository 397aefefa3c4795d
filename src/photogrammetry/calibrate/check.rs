//! The check points (section 5's accuracy figure): left out of every
//! resection, intersected from all cameras with the calibrated rig
//! (section 4.3), and compared with their known coordinates. A bad
//! observation is left out of its point's intersection by data snooping,
//! with the calibration's own uncertainty in the residuals' covariance.

use nalgebra::Point3;

use super::prepare::Prepared;
use super::report::{CameraReport, CheckPointDeviation, CheckPointReport, ExcludedObservation};
use super::{adjustment, snooping_critical, ControlPoint, MarkObservation};
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::intersect::{intersect, Intersection, Observation};

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
    intersection: &Intersection,
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
        let Some((_, b)) = adjustment::projection_with_parameter_jacobian(
            camera.parameters(),
            &intersection.point,
        ) else {
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
pub(super) fn check_point_report(
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
