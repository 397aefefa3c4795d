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

use nalgebra::{Matrix2x3, Matrix3, Point2, Point3, Vector2, Vector3};

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
    /// Residuals, observed minus computed, per observation in input order
    /// (px), from the last iteration (within 1e-6 px of the final point's).
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
    #[error("camera {camera}: {reason}")]
    Projection {
        /// The camera.
        camera: usize,
        /// What failed.
        reason: ProjectionError,
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
/// A step below this (mm) ends the iteration. Gauss-Newton converges
/// linearly with a rate proportional to the residuals times the model's
/// curvature (about 1e-4 for 0.1 px residuals, 1e-2 for 2 px), so the error
/// left after such a step is below 1e-9 mm; a test compares with a
/// 1e-12 mm stop.
const CONVERGED_STEP_MM: f64 = 1e-7;

/// The point nearest, in the least-squares sense, to all rays.
///
/// Minimises `sum_k |(I - d_k d_k') (X - o_k)|^2`; `None` if the rays are
/// parallel.
pub fn ray_midpoint(rays: impl IntoIterator<Item = Ray>) -> Option<Point3<f64>> {
    // The normal equations sum (I - d d') X = sum (I - d d') o, with the
    // symmetric matrix kept as its six distinct entries and solved by its
    // adjugate: this runs in the correspondence search's inner loop.
    let (mut xx, mut xy, mut xz, mut yy, mut yz, mut zz) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let mut rhs = Vector3::zeros();
    for ray in rays {
        let d = ray.direction;
        let o = ray.origin.coords;
        xx += 1.0 - d.x * d.x;
        yy += 1.0 - d.y * d.y;
        zz += 1.0 - d.z * d.z;
        xy -= d.x * d.y;
        xz -= d.x * d.z;
        yz -= d.y * d.z;
        rhs += o - d * d.dot(&o);
    }
    let (c00, c01, c02) = (yy * zz - yz * yz, xz * yz - xy * zz, xy * yz - xz * yy);
    let determinant = xx * c00 + xy * c01 + xz * c02;
    // Parallel rays leave the matrix singular; compare with its scale.
    let scale = xx + yy + zz;
    if determinant.is_nan() || determinant <= 1e-12 * scale * scale * scale {
        return None;
    }
    let (c11, c12, c22) = (xx * zz - xz * xz, xy * xz - xx * yz, xx * yy - xy * xy);
    let solution = Vector3::new(
        c00 * rhs.x + c01 * rhs.y + c02 * rhs.z,
        c01 * rhs.x + c11 * rhs.y + c12 * rhs.z,
        c02 * rhs.x + c12 * rhs.y + c22 * rhs.z,
    ) / determinant;
    solution
        .iter()
        .all(|v| v.is_finite())
        .then(|| Point3::from(solution))
}

/// Least-squares spatial intersection of two or more observations.
pub fn intersect(
    cameras: &[Camera],
    observations: &[Observation],
) -> Result<Intersection, IntersectionError> {
    if observations.len() < 2 {
        return Err(IntersectionError::TooFewObservations(observations.len()));
    }
    let camera_of = |observation: &Observation| {
        cameras
            .get(observation.camera)
            .ok_or(IntersectionError::UnknownCamera {
                camera: observation.camera,
                cameras: cameras.len(),
            })
    };
    let mut failure = None;
    let rays = observations.iter().map_while(|observation| {
        let ray = camera_of(observation).and_then(|camera| {
            camera
                .ray(observation.pixel)
                .map_err(|reason| IntersectionError::Projection {
                    camera: observation.camera,
                    reason,
                })
        });
        ray.map_err(|error| failure = Some(error)).ok()
    });
    let start = ray_midpoint(rays);
    if let Some(error) = failure {
        return Err(error);
    }
    let start = start.ok_or(IntersectionError::Degenerate)?;
    adjust(cameras, observations, start, CONVERGED_STEP_MM)
}

/// Least-squares spatial intersection from a given start point (for
/// callers that already have the rays, e.g. the correspondence search,
/// which passes their [`ray_midpoint`]).
pub fn intersect_from(
    cameras: &[Camera],
    observations: &[Observation],
    start: Point3<f64>,
) -> Result<Intersection, IntersectionError> {
    if observations.len() < 2 {
        return Err(IntersectionError::TooFewObservations(observations.len()));
    }
    if let Some(bad) = observations.iter().find(|o| o.camera >= cameras.len()) {
        return Err(IntersectionError::UnknownCamera {
            camera: bad.camera,
            cameras: cameras.len(),
        });
    }
    adjust(cameras, observations, start, CONVERGED_STEP_MM)
}

/// Gauss-Newton adjustment of a point from a start value.
///
/// The design matrix is kept from one iteration to the next while the steps
/// shrink fast (by 10x or more; from the ray midpoint they shrink by about
/// 1e-6 per iteration, the relative change of the Jacobian over the step),
/// and recomputed otherwise: the same fixed point as full Gauss-Newton, for
/// the price of plain projections in the later iterations.
fn adjust(
    cameras: &[Camera],
    observations: &[Observation],
    start: Point3<f64>,
    converged_step_mm: f64,
) -> Result<Intersection, IntersectionError> {
    let project_error = |observation: &Observation| {
        let camera = observation.camera;
        move |reason| IntersectionError::Projection { camera, reason }
    };
    let mut point = start;
    let mut residuals_px = vec![Vector2::zeros(); observations.len()];
    // The design matrix's rows: on the stack for up to 8 cameras (this
    // runs once per particle of every frame).
    const ON_STACK: usize = 8;
    let mut stack = [Matrix2x3::zeros(); ON_STACK];
    let mut heap = Vec::new();
    let jacobians: &mut [Matrix2x3<f64>] = if observations.len() <= ON_STACK {
        &mut stack[..observations.len()]
    } else {
        heap.resize(observations.len(), Matrix2x3::zeros());
        &mut heap
    };
    let mut normal = Matrix3::zeros();
    let mut cholesky = None;
    let mut last_step = f64::INFINITY;
    for iteration in 1..=MAX_ITERATIONS {
        let refresh = cholesky.is_none();
        let mut rhs = Vector3::zeros();
        for ((observation, residual), jacobian) in observations
            .iter()
            .zip(&mut residuals_px)
            .zip(jacobians.iter_mut())
        {
            let camera = &cameras[observation.camera];
            let computed = if refresh {
                let (computed, j) = camera
                    .project_with_jacobian(&point)
                    .map_err(project_error(observation))?;
                *jacobian = j;
                computed
            } else {
                camera.project(&point).map_err(project_error(observation))?
            };
            *residual = observation.pixel - computed;
            rhs += jacobian.transpose() * *residual;
        }
        if refresh {
            normal = jacobians.iter().map(|j| j.transpose() * j).sum();
            cholesky = Some(normal.cholesky().ok_or(IntersectionError::Degenerate)?);
        }
        let factor = cholesky.as_ref().expect("factorised above");
        let step = factor.solve(&rhs);
        if !step.iter().all(|v| v.is_finite()) {
            return Err(IntersectionError::Degenerate);
        }
        point += step;
        let step_norm = step.norm();
        if step_norm <= converged_step_mm {
            // The residuals are those of the last iteration, within
            // |J| * step (about 1e-6 px) of the final point's. Their sum of
            // squares at the final point, to first order in the step:
            // |v - J s|^2 = |v|^2 - 2 s'(J'v) + s'(J'J)s.
            let sum_sq = (residuals_px.iter().map(|v| v.norm_squared()).sum::<f64>()
                - 2.0 * step.dot(&rhs)
                + step.dot(&(normal * step)))
            .max(0.0);
            let redundancy = 2 * observations.len() - 3;
            let sigma0_px = (sum_sq / redundancy as f64).sqrt();
            let cofactor = factor.inverse();
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
        if step_norm > 0.1 * last_step {
            cholesky = None;
        }
        last_step = step_norm;
    }
    Err(IntersectionError::NoConvergence(MAX_ITERATIONS))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Unit};
    use proptest::prelude::*;

    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec, Tank};
    use crate::photogrammetry::{CameraParameters, Distortion, Wall};

    /// Rebuilds every camera with its wall plane turned by `tilt` about `axis`.
    fn tilt_walls(cameras: Vec<Camera>, axis: Vector3<f64>, tilt: f64) -> Vec<Camera> {
        let rotation = Rotation3::from_axis_angle(&Unit::new_normalize(axis), tilt);
        cameras
            .into_iter()
            .map(|camera| {
                let mut p: CameraParameters = camera.parameters().clone();
                p.media.glass_vector = rotation * p.media.glass_vector;
                Camera::new(p).expect("a tilted wall keeps the camera on its air side")
            })
            .collect()
    }

    /// Largest error of project -> back-project (rays) -> intersect over `points`.
    fn round_trip_error(cameras: &[Camera], points: &[Point3<f64>]) -> f64 {
        points
            .iter()
            .map(|point| {
                let observations: Vec<Observation> = cameras
                    .iter()
                    .enumerate()
                    .map(|(k, camera)| Observation {
                        camera: k,
                        pixel: camera.project(point).expect("the rig sees the volume"),
                    })
                    .collect();
                let rays: Vec<Ray> = observations
                    .iter()
                    .map(|o| cameras[o.camera].ray(o.pixel).unwrap())
                    .collect();
                let start = ray_midpoint(rays).unwrap();
                // Noise-free rays meet in the point itself.
                assert!(
                    (start - point).norm() < 1e-6,
                    "midpoint {start} for {point}"
                );
                let result = intersect(cameras, &observations).unwrap();
                assert!(result.rms_px < 1e-6, "residuals {}", result.rms_px);
                (result.point - point).norm()
            })
            .fold(0.0, f64::max)
    }

    fn rig_with_walls(walls: Vec<Wall>) -> (Vec<Camera>, Vec<Point3<f64>>) {
        let mut spec = RigSpec::convergent(4);
        spec.tank = Some(Tank {
            walls,
            ..Tank::glass_walled()
        });
        spec.distortion = Distortion {
            k1: 1e-4,
            p1: 2e-5,
            scx: 1.002,
            shear: 0.003,
            ..Distortion::default()
        };
        let points = simulate::particles(&spec.volume, 200, &mut simulate::rng(1));
        (spec.build().unwrap(), points)
    }

    #[test]
    fn round_trip_through_one_wall() {
        let (cameras, points) = rig_with_walls(vec![Wall {
            n: 1.49,
            thickness: 10.0,
        }]);
        assert!(round_trip_error(&cameras, &points) < 1e-6);
    }

    #[test]
    fn round_trip_through_three_walls() {
        let walls = vec![
            Wall {
                n: 1.49,
                thickness: 8.0,
            },
            Wall {
                n: 1.0,
                thickness: 2.0,
            },
            Wall {
                n: 1.52,
                thickness: 6.0,
            },
        ];
        let (cameras, points) = rig_with_walls(walls);
        assert!(round_trip_error(&cameras, &points) < 1e-6);
    }

    #[test]
    fn round_trip_through_a_tilted_wall() {
        let (cameras, points) = rig_with_walls(vec![Wall {
            n: 1.49,
            thickness: 10.0,
        }]);
        let cameras = tilt_walls(cameras, Vector3::new(1.0, 2.0, 0.5), 0.25);
        assert!(round_trip_error(&cameras, &points) < 1e-6);
    }

    #[test]
    fn round_trip_in_air() {
        let mut spec = RigSpec::convergent(3);
        spec.tank = None;
        let points = simulate::particles(&spec.volume, 100, &mut simulate::rng(2));
        assert!(round_trip_error(&spec.build().unwrap(), &points) < 1e-6);
    }

    #[test]
    fn standard_deviations_match_the_scatter_of_noisy_intersections() {
        // With image noise sigma, the a priori precision of X_i is
        // sigma * sqrt(Qxx_ii) and E[sigma0^2] = sigma^2. Over N points the
        // RMS of the normalised errors and the mean of sigma0^2 / sigma^2
        // scatter around 1 by about 1/sqrt(2N) and sqrt(2/(f N)) (f = 5,
        // the redundancy of 4 cameras); we allow four times that.
        let spec = RigSpec::convergent(4);
        let cameras = spec.build().unwrap();
        let noise = 0.1;
        let n = 2000;
        let mut rng = simulate::rng(7);
        let points = simulate::particles(&spec.volume, n, &mut rng);
        let images = simulate::observe(&cameras, &points, noise, &mut rng);
        let mut normalised_sq = Vector3::zeros();
        let mut variance_ratio = 0.0;
        for (j, point) in points.iter().enumerate() {
            let observations = simulate::observations_of(&images, j);
            assert_eq!(observations.len(), cameras.len());
            let result = intersect(&cameras, &observations).unwrap();
            let q_sqrt = result.sigma / result.sigma0_px;
            let error = result.point - point;
            normalised_sq += error.component_div(&(q_sqrt * noise)).map(|e| e * e);
            variance_ratio += (result.sigma0_px / noise).powi(2);
        }
        let rms = (normalised_sq / n as f64).map(f64::sqrt);
        let mean_ratio = variance_ratio / n as f64;
        let rms_tolerance = 4.0 / (2.0 * n as f64).sqrt();
        let ratio_tolerance = 4.0 * (2.0 / (5.0 * n as f64)).sqrt();
        for i in 0..3 {
            assert!((rms[i] - 1.0).abs() < rms_tolerance, "axis {i}: {}", rms[i]);
        }
        assert!((mean_ratio - 1.0).abs() < ratio_tolerance, "{mean_ratio}");
    }

    #[test]
    fn the_stopping_step_leaves_no_visible_error() {
        // Noisy and mismatched observations (large residuals converge
        // slowest): stopping at CONVERGED_STEP_MM agrees with stopping at
        // 1e-12 mm to 1e-9 mm.
        let spec = RigSpec::convergent(4);
        let cameras = spec.build().unwrap();
        let mut rng = simulate::rng(8);
        let points = simulate::particles(&spec.volume, 300, &mut rng);
        for noise in [0.1, 2.0] {
            let images = simulate::observe(&cameras, &points, noise, &mut rng);
            for j in 0..points.len() {
                let observations = simulate::observations_of(&images, j);
                let quick = intersect(&cameras, &observations).unwrap();
                let rays: Vec<Ray> = observations
                    .iter()
                    .map(|o| cameras[o.camera].ray(o.pixel).unwrap())
                    .collect();
                let tight =
                    adjust(&cameras, &observations, ray_midpoint(rays).unwrap(), 1e-12).unwrap();
                assert!(
                    (quick.point - tight.point).norm() < 1e-9,
                    "noise {noise}: {:e}",
                    (quick.point - tight.point).norm()
                );
                assert!((quick.sigma - tight.sigma).norm() < 1e-9 * (1.0 + tight.sigma.norm()));
            }
        }
    }

    #[test]
    fn bad_observations_are_errors() {
        let cameras = RigSpec::convergent(2).build().unwrap();
        let pixel = Point2::new(640.0, 512.0);
        assert_eq!(
            intersect(&cameras, &[Observation { camera: 0, pixel }]),
            Err(IntersectionError::TooFewObservations(1))
        );
        assert!(matches!(
            intersect(
                &cameras,
                &[
                    Observation { camera: 0, pixel },
                    Observation { camera: 5, pixel }
                ]
            ),
            Err(IntersectionError::UnknownCamera {
                camera: 5,
                cameras: 2
            })
        ));
        // Twice the same ray: parallel.
        assert!(intersect(
            &cameras,
            &[
                Observation { camera: 0, pixel },
                Observation { camera: 0, pixel }
            ]
        )
        .is_err());
        // NaN pixels never panic.
        let nan = Point2::new(f64::NAN, 1.0);
        assert!(intersect(
            &cameras,
            &[
                Observation {
                    camera: 0,
                    pixel: nan
                },
                Observation { camera: 1, pixel }
            ]
        )
        .is_err());
    }

    fn random_rig() -> impl Strategy<Value = (Vec<Camera>, Vec<Point3<f64>>)> {
        let wall = (1.3..1.8f64, 1.0..20.0f64).prop_map(|(n, thickness)| Wall { n, thickness });
        (
            2usize..=8,
            prop::collection::vec(wall, 1..=3),
            1.33..1.5f64,
            (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, 0.0..0.3f64),
            (
                -3e-4..3e-4f64,
                -3e-5..3e-5f64,
                -3e-5..3e-5f64,
                0.995..1.005f64,
                -0.005..0.005f64,
            ),
            (-0.1..0.1f64, -0.1..0.1f64),
            any::<u64>(),
        )
            .prop_map(|(count, walls, n_object, tilt, d, pp, seed)| {
                let mut spec = RigSpec::convergent(count);
                spec.tank = Some(Tank {
                    walls,
                    n_object,
                    ..Tank::glass_walled()
                });
                spec.distortion = Distortion {
                    k1: d.0,
                    p1: d.1,
                    p2: d.2,
                    scx: d.3,
                    shear: d.4,
                    ..Distortion::default()
                };
                spec.principal_point = nalgebra::Vector2::new(pp.0, pp.1);
                let axis = Vector3::new(tilt.0, tilt.1, tilt.2 + 1e-3);
                let cameras = tilt_walls(spec.build().unwrap(), axis, tilt.3);
                let points = simulate::particles(&spec.volume, 5, &mut simulate::rng(seed));
                (cameras, points)
            })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn round_trip_over_random_rigs((cameras, points) in random_rig()) {
            let error = round_trip_error(&cameras, &points);
            prop_assert!(error < 1e-6, "error {error} mm");
        }
    }
}
