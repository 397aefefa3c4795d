//! The least-squares adjustment of one camera's parameters: the
//! collinearity equations with the multimedia module (Eq. 1-12, section
//! 4.3's observation equations with the 16 camera parameters as unknowns,
//! as the paper's section 5 uses them), adjusted by Gauss-Markov with
//! Levenberg-Marquardt damping (the driver of `levenberg_marquardt.rs`, on
//! the Jacobian's columns scaled to unit length), and the statistics of
//! the result.
//!
//! * Observations are the pixel coordinates of the control points, with
//!   equal weights; `sigma0² = vᵀv / (2n - u)` a posteriori, and the
//!   parameters' covariance `sigma0² (AᵀA)⁻¹`.
//! * The Jacobian of a pixel with respect to the parameters is numerical
//!   (central differences) but cheap: the refraction solve depends only on
//!   the projective centre, so it is repeated only for the three position
//!   derivatives; angles and interior parameters reuse the air direction.
//! * Each observation's data-snooping statistic (Baarda 1968, with Pope's
//!   a posteriori variance): `vᵢᵀ Qvvᵢ⁻¹ vᵢ / sigma0²`, chi-square with 2
//!   degrees of freedom under the null hypothesis.

use nalgebra::{DMatrix, DVector, Matrix2, Point2, Point3, SVector, Vector2};

use super::{Parameter, ParameterSet};
use crate::photogrammetry::camera::{Camera, CameraParameters};
use crate::photogrammetry::levenberg_marquardt::{minimise, LeastSquares, Settings, Trial};

/// The 16 parameters as a vector, in [`Parameter::ALL`]'s order.
pub(crate) type ParameterVector = SVector<f64, 16>;

/// The parameters of `camera` as a vector.
pub(crate) fn to_vector(camera: &CameraParameters) -> ParameterVector {
    let e = &camera.exterior;
    let i = &camera.interior;
    let d = &camera.distortion;
    ParameterVector::from_column_slice(&[
        e.position.x,
        e.position.y,
        e.position.z,
        e.omega,
        e.phi,
        e.kappa,
        i.xh,
        i.yh,
        i.c,
        d.k1,
        d.k2,
        d.k3,
        d.p1,
        d.p2,
        d.scx,
        d.shear,
    ])
}

/// `template` with its 16 parameters replaced by `v`.
pub(crate) fn from_vector(template: &CameraParameters, v: &ParameterVector) -> CameraParameters {
    let mut camera = template.clone();
    camera.exterior.position = v.fixed_rows::<3>(0).into_owned();
    camera.exterior.omega = v[3];
    camera.exterior.phi = v[4];
    camera.exterior.kappa = v[5];
    camera.interior.xh = v[6];
    camera.interior.yh = v[7];
    camera.interior.c = v[8];
    camera.distortion.k1 = v[9];
    camera.distortion.k2 = v[10];
    camera.distortion.k3 = v[11];
    camera.distortion.p1 = v[12];
    camera.distortion.p2 = v[13];
    camera.distortion.scx = v[14];
    camera.distortion.shear = v[15];
    camera
}

/// Central-difference steps: a change of about 1e-4 mm in the image at the
/// sensor's corner for the interior and distortion terms, 0.01 mm and 1e-6
/// rad for the exterior.
fn steps(camera: &CameraParameters) -> ParameterVector {
    let s = &camera.sensor;
    let r = 0.5 * (f64::from(s.width) * s.pixel_size_x).hypot(f64::from(s.height) * s.pixel_size_y);
    let r = r.max(1e-3);
    let image = 1e-4;
    ParameterVector::from_column_slice(&[
        1e-2,
        1e-2,
        1e-2,
        1e-6,
        1e-6,
        1e-6,
        image,
        image,
        image,
        image / r.powi(3),
        image / r.powi(5),
        image / r.powi(7),
        image / r.powi(2),
        image / r.powi(2),
        image / r,
        image / r,
    ])
}

/// The pixel of `point` and its 2x16 Jacobian with respect to the camera's
/// parameters (pixels per parameter unit), in [`Parameter::ALL`]'s order.
///
/// Fails where the point does not image (behind the camera, no refracted
/// ray, distortion not invertible) or the parameters are not a camera.
pub fn projection_with_parameter_jacobian(
    camera: &CameraParameters,
    point: &Point3<f64>,
) -> Option<(Point2<f64>, nalgebra::SMatrix<f64, 2, 16>)> {
    let model = ParameterModel::new(camera, ParameterSet::all())?;
    model.project(point).map(|(pixel, row)| {
        let mut full = nalgebra::SMatrix::<f64, 2, 16>::zeros();
        for (k, p) in model.free.iter().enumerate() {
            full.set_column(p.index(), &row.column(k));
        }
        (pixel, full)
    })
}

/// A camera and its neighbours for the numerical derivatives, rebuilt once
/// per iteration.
pub(crate) struct ParameterModel {
    camera: Camera,
    /// The free parameters: the Jacobian's columns.
    free: ParameterSet,
    /// `(step, camera with +step, camera with -step)` per free parameter.
    shifted: Vec<(f64, Camera, Camera)>,
}

impl ParameterModel {
    pub(crate) fn new(parameters: &CameraParameters, free: ParameterSet) -> Option<ParameterModel> {
        let camera = Camera::new(parameters.clone()).ok()?;
        let v = to_vector(parameters);
        let h = steps(parameters);
        let mut shifted = Vec::new();
        for j in free.iter().map(Parameter::index) {
            let mut plus = v;
            plus[j] += h[j];
            let mut minus = v;
            minus[j] -= h[j];
            let plus = Camera::new(from_vector(parameters, &plus)).ok()?;
            let minus = Camera::new(from_vector(parameters, &minus)).ok()?;
            shifted.push((h[j], plus, minus));
        }
        Some(ParameterModel {
            camera,
            free,
            shifted,
        })
    }

    /// The pixel and the Jacobian's columns of the free parameters.
    pub(crate) fn project(&self, point: &Point3<f64>) -> Option<(Point2<f64>, DMatrix<f64>)> {
        let direction = self.camera.air_direction(point).ok()?;
        let pixel = self.camera.pixel_of_air_direction(&direction).ok()?;
        let mut jacobian = DMatrix::zeros(2, self.free.len());
        for (k, (parameter, (h, plus, minus))) in self.free.iter().zip(&self.shifted).enumerate() {
            let (p, m) = if ParameterSet::position().contains(parameter) {
                (plus.project(point).ok()?, minus.project(point).ok()?)
            } else {
                (
                    plus.pixel_of_air_direction(&direction).ok()?,
                    minus.pixel_of_air_direction(&direction).ok()?,
                )
            };
            jacobian.set_column(k, &((p - m) / (2.0 * h)));
        }
        Some((pixel, jacobian))
    }
}

/// One observation equation: a control point and its measured pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Equation {
    /// The control point (mm).
    pub point: Point3<f64>,
    /// The measured pixel.
    pub pixel: Point2<f64>,
}

/// The linearised system at one set of parameters.
struct Linearised {
    /// Jacobian with columns scaled to unit length.
    a: DMatrix<f64>,
    /// The column scales (multiply a scaled step to get the parameter step).
    scale: DVector<f64>,
    /// Observed minus computed (px).
    residual: DVector<f64>,
}

fn linearise(
    parameters: &CameraParameters,
    free: ParameterSet,
    equations: &[Equation],
) -> Option<Linearised> {
    let model = ParameterModel::new(parameters, free)?;
    let u = model.free.len();
    let mut a = DMatrix::zeros(2 * equations.len(), u);
    let mut residual = DVector::zeros(2 * equations.len());
    for (i, e) in equations.iter().enumerate() {
        let (pixel, j) = model.project(&e.point)?;
        let v = e.pixel - pixel;
        residual[2 * i] = v.x;
        residual[2 * i + 1] = v.y;
        a.view_mut((2 * i, 0), (2, u)).copy_from(&j);
    }
    let mut scale = DVector::zeros(u);
    for k in 0..u {
        let norm = a.column(k).norm();
        let s = if norm > 0.0 { 1.0 / norm } else { 1.0 };
        scale[k] = s;
        a.column_mut(k).scale_mut(s);
    }
    Some(Linearised { a, scale, residual })
}

/// Sum of squared residuals (px²), or `None` where a point does not image.
pub(crate) fn cost(parameters: &CameraParameters, equations: &[Equation]) -> Option<f64> {
    let camera = Camera::new(parameters.clone()).ok()?;
    equations.iter().try_fold(0.0, |sum, e| {
        let pixel = camera.project(&e.point).ok()?;
        Some(sum + (e.pixel - pixel).norm_squared())
    })
}

/// The result of one converged adjustment.
pub(crate) struct Adjusted {
    /// The adjusted parameters.
    pub parameters: CameraParameters,
    /// Iterations used.
    pub iterations: usize,
    /// Whether a stopping test was met (else the iteration limit ended it,
    /// or no step reduced the cost any more).
    pub converged: bool,
}

/// One camera's resection as a least-squares problem for the driver: the
/// free parameters from the current estimate.
struct Resection<'e> {
    current: CameraParameters,
    free: ParameterSet,
    equations: &'e [Equation],
}

/// The normal equations of the scaled Jacobian (columns of unit length).
struct ScaledNormal {
    /// `AᵀA`.
    n: DMatrix<f64>,
    /// `Aᵀv`.
    g: DVector<f64>,
    /// The column scales (multiply a scaled step to get the parameter step).
    scale: DVector<f64>,
}

impl LeastSquares for Resection<'_> {
    type Normal = ScaledNormal;
    type Estimate = CameraParameters;

    fn cost(&self) -> Option<f64> {
        cost(&self.current, self.equations)
    }

    fn cost_of(&self, estimate: &CameraParameters) -> Option<f64> {
        cost(estimate, self.equations)
    }

    fn normal(&self) -> Option<ScaledNormal> {
        let lin = linearise(&self.current, self.free, self.equations)?;
        Some(ScaledNormal {
            n: lin.a.transpose() * &lin.a,
            g: lin.a.transpose() * &lin.residual,
            scale: lin.scale,
        })
    }

    fn trial(&self, normal: &ScaledNormal, lambda: f64) -> Option<Trial<CameraParameters>> {
        let mut damped = normal.n.clone();
        for k in 0..damped.nrows() {
            damped[(k, k)] += lambda * normal.n[(k, k)].max(1e-12);
        }
        let step = solve(damped, &normal.g)?;
        let delta = step.component_mul(&normal.scale);
        let mut v = to_vector(&self.current);
        for (k, p) in self.free.iter().enumerate() {
            v[p.index()] += delta[k];
        }
        Some(Trial {
            estimate: from_vector(&self.current, &v),
            predicted: step.dot(&(&normal.g * 2.0 - &normal.n * &step)),
        })
    }

    fn accept(&mut self, estimate: CameraParameters) -> CameraParameters {
        std::mem::replace(&mut self.current, estimate)
    }
}

/// Levenberg-Marquardt on the free parameters from `start`: the driver's
/// rules (`levenberg_marquardt.rs`), converged when the Gauss-Newton step
/// promises to reduce `vᵀv` by less than 1e-10 of it (each parameter then
/// within about 1e-4 of its sigma of the minimum for a redundancy of 100).
pub(crate) fn adjust(
    start: &CameraParameters,
    free: ParameterSet,
    equations: &[Equation],
    max_iterations: usize,
) -> Option<Adjusted> {
    let mut resection = Resection {
        current: start.clone(),
        free,
        equations,
    };
    let settings = Settings {
        lambda: 1e-3,
        max_iterations,
        tolerance: 1e-10,
    };
    let outcome = minimise(&mut resection, &settings)?;
    Some(Adjusted {
        parameters: resection.current,
        iterations: outcome.iterations,
        converged: outcome.converged,
    })
}

/// Solves a symmetric positive (semi)definite system: Cholesky, else SVD.
pub(crate) fn solve(n: DMatrix<f64>, g: &DVector<f64>) -> Option<DVector<f64>> {
    if let Some(chol) = n.clone().cholesky() {
        let x = chol.solve(g);
        if x.iter().all(|v| v.is_finite()) {
            return Some(x);
        }
    }
    if !n.iter().all(|v| v.is_finite()) {
        return None;
    }
    let x = nalgebra::SVD::try_new(n, true, true, f64::EPSILON, 10_000)?
        .solve(g, 1e-12)
        .ok()?;
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Statistics of a converged adjustment.
pub(crate) struct Statistics {
    /// Residuals (observed minus computed) per equation (px).
    pub residuals: Vec<Vector2<f64>>,
    /// A posteriori sigma0 (px).
    pub sigma0: f64,
    /// Redundancy `2n - u`.
    pub redundancy: usize,
    /// Cofactor matrix of the free parameters (unscaled units), `None` when
    /// the normal matrix is singular.
    pub cofactor: Option<DMatrix<f64>>,
    /// The normal matrix scaled to unit diagonal (for rank and correlations).
    pub scaled_normal: DMatrix<f64>,
    /// The normal matrix in the parameters' own units (the cofactor's
    /// inverse when that exists).
    pub normal: DMatrix<f64>,
    /// Per equation the test statistic `vᵀ Qvv⁻¹ v / sigma0²`, `None` where
    /// the point has no redundancy to test.
    pub test: Vec<Option<f64>>,
}

pub(crate) fn statistics(
    parameters: &CameraParameters,
    free: ParameterSet,
    equations: &[Equation],
) -> Option<Statistics> {
    let lin = linearise(parameters, free, equations)?;
    let u = lin.scale.len();
    let n_obs = lin.residual.len();
    let redundancy = n_obs.saturating_sub(u);
    let vtv = lin.residual.norm_squared();
    let sigma0 = if redundancy > 0 {
        (vtv / redundancy as f64).sqrt()
    } else {
        0.0
    };
    let n = lin.a.transpose() * &lin.a;
    let diag: DVector<f64> = n
        .diagonal()
        .map(|d| if d > 0.0 { 1.0 / d.sqrt() } else { 0.0 });
    let scaled_normal = DMatrix::from_fn(u, u, |i, j| n[(i, j)] * diag[i] * diag[j]);
    let inverse = n.clone().cholesky().map(|c| c.inverse());
    let residuals = (0..equations.len())
        .map(|i| Vector2::new(lin.residual[2 * i], lin.residual[2 * i + 1]))
        .collect();
    let mut test = vec![None; equations.len()];
    if let Some(q) = &inverse {
        if redundancy > 0 && sigma0 > 0.0 {
            for (i, t) in test.iter_mut().enumerate() {
                let ai = lin.a.rows(2 * i, 2);
                let h = ai * q * ai.transpose();
                let qvv =
                    Matrix2::identity() - Matrix2::new(h[(0, 0)], h[(0, 1)], h[(1, 0)], h[(1, 1)]);
                // Points whose residual is forced (almost) to zero cannot
                // be tested: their redundancy number is below 1%.
                if qvv.trace() < 0.02 {
                    continue;
                }
                if let Some(inv) = qvv.try_inverse() {
                    let v = Vector2::new(lin.residual[2 * i], lin.residual[2 * i + 1]);
                    *t = Some(v.dot(&(inv * v)) / (sigma0 * sigma0));
                }
            }
        }
    }
    let cofactor =
        inverse.map(|q| DMatrix::from_fn(u, u, |i, j| q[(i, j)] * lin.scale[i] * lin.scale[j]));
    let normal = DMatrix::from_fn(u, u, |i, j| {
        let scale = lin.scale[i] * lin.scale[j];
        if scale != 0.0 {
            n[(i, j)] / scale
        } else {
            0.0
        }
    });
    Some(Statistics {
        residuals,
        sigma0,
        redundancy,
        cofactor,
        scaled_normal,
        normal,
        test,
    })
}
