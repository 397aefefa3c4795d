//! The calibration report (serialised as the JSON that `ptv calibrate`
//! prints): per camera its parameters with their standard deviations,
//! covariance and largest correlations, sigma0, the residuals and the
//! points excluded as gross errors; and the check points' deviations.

use serde::Serialize;

use super::adjustment::{to_vector, Statistics};
use super::resection::Resection;
use super::{snooping_critical, Parameter, ParameterSet};

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
    /// Where the point was measured in the image (px): the residual's
    /// place on the sensor, for plots of the residuals over it.
    pub image_px: [f64; 2],
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

/// One camera's report from its finished resection and final adjustment
/// (`stats`), with the standard deviations and covariance from
/// `uncertainty`, the adjustment over the `estimated` parameters.
pub(super) fn camera_report(
    resection: &Resection,
    stats: &Statistics,
    (uncertainty, estimated): (&Statistics, ParameterSet),
) -> CameraReport {
    let Resection {
        parameters: camera,
        free,
        fixed,
        held,
        active,
        ..
    } = resection;
    let v = to_vector(camera);
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
            } else if fixed.contains(p) {
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
        .map(|(((id, equation), r), t)| PointResidual {
            id: *id,
            x_px: r.x,
            y_px: r.y,
            image_px: [equation.pixel.x, equation.pixel.y],
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
        iterations: resection.iterations,
        snooping_critical: snooping_critical(resection.options.snooping_alpha, active.len()),
        parameters,
        covariance,
        largest_correlations: correlations,
        residuals,
        excluded: resection.excluded.clone(),
    }
}
