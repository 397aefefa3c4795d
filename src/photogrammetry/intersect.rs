//! Spatial intersection: the 3D point seen at given image positions in two or
//! more cameras.
//!
//! The strict solution is the least-squares adjustment of the design paper's
//! section 4.3: the collinearity equations with the multimedia module
//! (Eq. 21) as observation equations with the object coordinates as the
//! only unknowns, linearised (Eq. 22) and solved by Gauss-Markov (Eq. 23)
//! with equal weights in pixel space, iterated (Gauss-Newton) to convergence.
//! It minimises the reprojection error and yields the standard deviations of
//! the point, `sigma_i = sigma0 * sqrt(Qxx_ii)` with the a posteriori
//! `sigma0^2 = v'v / (2m - 3)` for m cameras.
//!
//! Its start is the closed-form point nearest to all rays in the object
//! medium ([`ray_midpoint`]), the least-squares generalisation of the
//! direct solution of section 4.2.2 (Eq. 18-20) to any number of rays.

use nalgebra::{Matrix3, Point2, Point3, Vector2, Vector3};

use super::camera::{Camera, ProjectionError, Ray};

/// One camera's measurement of a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// Index of the camera in the rig.
    pub camera: usize,
    /// Measured image position (pixels).
    pub pixel: Point2<f64>,
}

/// The adjusted point and its accuracy.
#[derive(Clone, Debug, PartialEq)]
pub struct Intersection {
    /// The point (mm).
    pub point: Point3<f64>,
    /// Standard deviations of X, Y, Z from the adjustment (mm).
    pub sigma: Vector3<f64>,
    /// A posteriori standard deviation of unit weight (px).
    pub sigma0_px: f64,
    /// Residuals, observed minus computed, per observation in input order (px).
    pub residuals_px: Vec<Vector2<f64>>,
    /// Root mean square of the residual vectors' lengths (px).
    pub rms_px: f64,
    /// Gauss-Newton iterations used.
    pub iterations: usize,
}

/// Why no point could be intersected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IntersectionError {
    /// Fewer than two observations.
    #[error("a point needs observations from at least 2 cameras, got {0}")]
    TooFewObservations(usize),
    /// An observation names a camera that the rig does not have.
    #[error("observation of camera {camera}, but the calibration has {cameras} cameras (0-based indices)")]
    UnknownCamera {
        /// The index given.
        camera: usize,
        /// How many cameras there are.
        cameras: usize,
    },
    /// A ray or projection could not be formed.
    #[error("camera {camera}: {source}")]
    Projection {
        /// The camera.
        camera: usize,
        /// What failed.
        source: ProjectionError,
    },
    /// The rays are (nearly) parallel: the point is not determined.
    #[error("the rays are parallel: the point is not determined")]
    Degenerate,
    /// The iteration did not settle.
    #[error("the intersection did not converge in {0} iterations")]
    NoConvergence(usize),
}

/// Largest number of Gauss-Newton iterations. Two or three suffice from the
/// ray midpoint; more means the observations do not belong together.
const MAX_ITERATIONS: usize = 20;
/// A step below this (mm) ends the iteration. Gauss-Newton converges at
/// least linearly with a rate proportional to the residuals' curvature
/// effect, so the remaining error is far below the step.
const CONVERGED_STEP_MM: f64 = 1e-8;

/// The point nearest, in the least-squares sense, to all rays.
///
/// Minimises `sum_k |(I - d_k d_k') (X - o_k)|^2`; `None` if the rays are
/// parallel.
pub fn ray_midpoint(rays: &[Ray]) -> Option<Point3<f64>> {
    let mut normal = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for ray in rays {
        let projector = Matrix3::identity() - ray.direction * ray.direction.transpose();
        normal += projector;
        rhs += projector * ray.origin.coords;
    }
    let solution = normal.cholesky()?.solve(&rhs);
    solution.iter().all(|v| v.is_finite()).then(|| Point3::from(solution))
}

/// Least-squares spatial intersection of two or more observations.
pub fn intersect(cameras: &[Camera], observations: &[Observation]) -> Result<Intersection, IntersectionError> {
    if observations.len() < 2 {
        return Err(IntersectionError::TooFewObservations(observations.len()));
    }
    let camera_of = |observation: &Observation| {
        cameras.get(observation.camera).ok_or(IntersectionError::UnknownCamera {
            camera: observation.camera,
            cameras: cameras.len(),
        })
    };
    let mut rays = Vec::with_capacity(observations.len());
    for observation in observations {
        let ray = camera_of(observation)?
            .ray(observation.pixel)
            .map_err(|source| IntersectionError::Projection {
                camera: observation.camera,
                source,
            })?;
        rays.push(ray);
    }
    let start = ray_midpoint(&rays).ok_or(IntersectionError::Degenerate)?;
    adjust(cameras, observations, start)
}

/// Gauss-Newton adjustment of a point from a start value.
fn adjust(cameras: &[Camera], observations: &[Observation], start: Point3<f64>) -> Result<Intersection, IntersectionError> {
    let mut point = start;
    let mut residuals_px = vec![Vector2::zeros(); observations.len()];
    let mut jacobians = Vec::with_capacity(observations.len());
    for iteration in 1..=MAX_ITERATIONS {
        let mut normal = Matrix3::zeros();
        let mut rhs = Vector3::zeros();
        jacobians.clear();
        for (observation, residual) in observations.iter().zip(residuals_px.iter_mut()) {
            let camera = &cameras[observation.camera];
            let (computed, jacobian) =
                camera
                    .project_with_jacobian(&point)
                    .map_err(|source| IntersectionError::Projection {
                        camera: observation.camera,
                        source,
                    })?;
            *residual = observation.pixel - computed;
            normal += jacobian.transpose() * jacobian;
            rhs += jacobian.transpose() * *residual;
            jacobians.push(jacobian);
        }
        let cholesky = normal.cholesky().ok_or(IntersectionError::Degenerate)?;
        let step = cholesky.solve(&rhs);
        if !step.iter().all(|v| v.is_finite()) {
            return Err(IntersectionError::Degenerate);
        }
        point += step;
        if step.norm() <= CONVERGED_STEP_MM {
            // Residuals at the final point, to first order in the (tiny) step.
            for (residual, jacobian) in residuals_px.iter_mut().zip(&jacobians) {
                *residual -= jacobian * step;
            }
            let sum_sq: f64 = residuals_px.iter().map(|v| v.norm_squared()).sum();
            let redundancy = 2 * observations.len() - 3;
            let sigma0_px = (sum_sq / redundancy as f64).sqrt();
            let cofactor = cholesky.inverse();
            let sigma = Vector3::from_fn(|i, _| sigma0_px * cofactor[(i, i)].sqrt());
            return Ok(Intersection {
                point,
                sigma,
                sigma0_px,
                rms_px: (sum_sq / observations.len() as f64).sqrt(),
                residuals_px,
                iterations: iteration,
            });
        }
    }
    Err(IntersectionError::NoConvergence(MAX_ITERATIONS))
}
