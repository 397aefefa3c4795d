//! Image-space recovery: a particle the correspondences missed, found
//! again in the images where a trajectory says it must be (Willneff 2003,
//! *A spatio-temporal matching algorithm for 3D particle tracking
//! velocimetry*, ETH Zürich, ch. 6; OpenPTV's `trackcorr` "search in image
//! space").
//!
//! A particle is lost to the correspondence search when one of its images
//! is: overlapped, too faint in one camera, or ambiguous in the epipolar
//! bands. A trajectory that reaches a frame with no particle near its
//! prediction `x̂` (the tracker's Eq. of motion, `x̂ = x_t + v Δ`) still
//! knows, within its search radius `R`, where the particle is; that
//! knowledge replaces the epipolar constraint. In each camera `c`:
//!
//! 1. project `x̂` (the strict model, refraction included) to `p_c`, with the
//!    Jacobian `J_c` (px per mm);
//! 2. the sphere of radius `R` around `x̂` images within `R ‖J_c‖_F` of
//!    `p_c` (the Frobenius norm bounds the spectral norm, the largest
//!    stretch), widened by the image noise allowance `tolerance_px`;
//! 3. the nearest target within that window that no particle of the frame
//!    uses is the camera's candidate.
//!
//! With candidates in two or more cameras the point is intersected by
//! least squares (design paper, Eq. 21-23, [`intersect`]) and accepted when
//! its reprojection RMS is within `tolerance_px`, where the frame's noise
//! `sigma` is known ([`frame_noise`]) also its squared residuals `v'v`
//! within the 99% quantile of `sigma² chi²(2m - 3)` for `m` cameras (the
//! images belong to one point, as closely as the frame's particles'
//! images do: a band of a pixel is ten times the usual noise, and a
//! 2-camera point has one degree of freedom, so the tolerance alone lets
//! chance pairs through), and it lies within `R` of `x̂` (it is where the
//! trajectory goes). Measured with `ptv simulate --frames 20 --flow
//! taylor-green --drop 0.2` and `ptv track` (8,000 particles, 0.1 px
//! noise): the mean trajectory length 12.4 frames without recovery, 14.5
//! with it; wrong links 3.6%, and 5.4% with the tolerance alone, 3.5%
//! with the noise test.
//! Otherwise the camera whose residual is the largest is left out and the
//! rest tried again, down to two cameras: a wrong candidate in one camera
//! (a neighbour's image, nearer to `p_c` than the particle's own) does not
//! lose the particle's images in the others. An accepted point's targets
//! are marked used, so no two recoveries, and no recovery and particle,
//! share an image.
//!
//! Pure and deterministic; nothing is allocated per camera beyond the
//! frame's index, which is built once per frame (linear in its targets).

use nalgebra::{Point2, Point3};

use super::super::camera::Camera;
use super::super::correspond::Particle;
use super::super::intersect::{intersect, Observation};
use super::super::statistics::chi_square_quantile;
use super::super::target::Target;

/// The side of an index cell (px): about the windows searched.
const CELL_PX: f64 = 16.0;

/// One frame's targets, per camera, for the recovery: which of them the
/// frame's particles already use, filed in square cells for searches
/// around a point.
#[derive(Clone, Debug)]
pub struct FrameTargets {
    cameras: Vec<CameraTargets>,
    /// The image noise (px, one coordinate's standard deviation) the
    /// frame's particles show, where known ([`FrameTargets::with_noise`]).
    noise_px: Option<f64>,
}

#[derive(Clone, Debug)]
struct CameraTargets {
    pixels: Vec<Point2<f64>>,
    used: Vec<bool>,
    /// Cells of [`CELL_PX`], row-major over the bounding box of the
    /// targets: `starts[k]..starts[k + 1]` of `order` are cell `k`'s.
    cell: f64,
    columns: usize,
    rows: usize,
    origin: Point2<f64>,
    starts: Vec<u32>,
    order: Vec<u32>,
}

/// A particle's targets that do not exist.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameTargetsError {
    /// A particle names more cameras than there are.
    #[error("particle {particle} names {named} cameras, the frame has targets of {cameras}")]
    Cameras {
        /// The particle's index.
        particle: usize,
        /// Cameras it names.
        named: usize,
        /// Cameras with targets.
        cameras: usize,
    },
    /// A particle names a target its camera does not have.
    #[error("particle {particle} names target {target} of camera {camera}, which has {count}")]
    Target {
        /// The particle's index.
        particle: usize,
        /// The camera.
        camera: usize,
        /// The target named.
        target: usize,
        /// Targets the camera has.
        count: usize,
    },
}

impl FrameTargets {
    /// The targets of each camera, and per particle of the frame the
    /// index of its target in each camera (`None` where it has none), as
    /// the correspondences give them ([`Particle::targets`]
    /// (super::super::correspond::Particle::targets)).
    pub fn new<'a>(
        targets: &[Vec<Target>],
        particles: impl IntoIterator<Item = &'a [Option<usize>]>,
    ) -> Result<FrameTargets, FrameTargetsError> {
        let mut cameras: Vec<CameraTargets> = targets
            .iter()
            .map(|t| CameraTargets::new(t.iter().map(|t| Point2::new(t.x, t.y)).collect()))
            .collect();
        for (particle, named) in particles.into_iter().enumerate() {
            if named.len() > cameras.len() {
                return Err(FrameTargetsError::Cameras {
                    particle,
                    named: named.len(),
                    cameras: cameras.len(),
                });
            }
            for (camera, target) in named.iter().enumerate() {
                let Some(target) = *target else { continue };
                let used = &mut cameras[camera].used;
                let count = used.len();
                *used.get_mut(target).ok_or(FrameTargetsError::Target {
                    particle,
                    camera,
                    target,
                    count,
                })? = true;
            }
        }
        Ok(FrameTargets {
            cameras,
            noise_px: None,
        })
    }

    /// The frame's image noise (px, the standard deviation of one image
    /// coordinate, as [`frame_noise`] estimates it from the particles):
    /// a recovered point must then also fit its images as the particles
    /// do (its squared residuals within the 99% quantile of their
    /// chi-square distribution), not merely within the tolerance. Ignored
    /// unless a positive number.
    pub fn with_noise(mut self, noise_px: f64) -> FrameTargets {
        self.noise_px = (noise_px.is_finite() && noise_px > 0.0).then_some(noise_px);
        self
    }

    /// A frame's targets and the particles matched from them, as the
    /// tracker's recovery takes them: which targets the particles use
    /// ([`FrameTargets::new`]) and the frame's noise from the particles'
    /// reprojection RMS ([`frame_noise`], [`FrameTargets::with_noise`]).
    /// The one way `ptv track` and the service build a frame's targets, so
    /// that both recover the same particles.
    pub fn of_particles(
        targets: &[Vec<Target>],
        particles: &[Particle],
    ) -> Result<FrameTargets, FrameTargetsError> {
        let noise = frame_noise(particles.iter().map(|p| (p.rms_px, p.camera_count())));
        Ok(
            FrameTargets::new(targets, particles.iter().map(|p| &p.targets[..]))?
                .with_noise(noise.unwrap_or(f64::NAN)),
        )
    }

    /// The frame's image noise (px) the recovery tests against, where
    /// known ([`FrameTargets::with_noise`]).
    pub fn noise_px(&self) -> Option<f64> {
        self.noise_px
    }

    /// Cameras with targets.
    pub fn cameras(&self) -> usize {
        self.cameras.len()
    }

    /// Targets of camera `camera` no particle or recovery uses.
    pub fn unused(&self, camera: usize) -> usize {
        self.cameras
            .get(camera)
            .map_or(0, |c| c.used.iter().filter(|u| !**u).count())
    }
}

impl CameraTargets {
    fn new(pixels: Vec<Point2<f64>>) -> CameraTargets {
        let finite: Vec<&Point2<f64>> = pixels
            .iter()
            .filter(|p| p.x.is_finite() && p.y.is_finite())
            .collect();
        let (mut low, mut high) = (
            Point2::new(f64::INFINITY, f64::INFINITY),
            Point2::new(f64::NEG_INFINITY, f64::NEG_INFINITY),
        );
        for p in &finite {
            low = low.inf(p);
            high = high.sup(p);
        }
        if finite.is_empty() {
            (low, high) = (Point2::origin(), Point2::origin());
        }
        // Cells of CELL_PX on a sensor; wider where a file's targets
        // spread far beyond one, so that there are at most about 2^20.
        let span = (high - low).amax();
        let cell = CELL_PX.max(span / 1024.0);
        let cells = |span: f64| (span / cell).floor() as usize + 1;
        let (columns, rows) = (cells(high.x - low.x), cells(high.y - low.y));
        let mut index = CameraTargets {
            cell,
            used: vec![false; pixels.len()],
            columns,
            rows,
            origin: low,
            starts: vec![0; columns * rows + 1],
            order: Vec::with_capacity(pixels.len()),
            pixels,
        };
        let keys: Vec<Option<usize>> = index.pixels.iter().map(|p| index.cell(p)).collect();
        for key in keys.iter().flatten() {
            index.starts[key + 1] += 1;
        }
        for k in 0..columns * rows {
            index.starts[k + 1] += index.starts[k];
        }
        let mut fill = index.starts.clone();
        index.order = vec![0; index.starts[columns * rows] as usize];
        for (i, key) in keys.iter().enumerate() {
            if let Some(key) = key {
                index.order[fill[*key] as usize] = i as u32;
                fill[*key] += 1;
            }
        }
        index
    }

    /// The cell of a pixel (`None` if not finite).
    fn cell(&self, p: &Point2<f64>) -> Option<usize> {
        let (i, j) = self.cell_xy(p)?;
        Some(j * self.columns + i)
    }

    fn cell_xy(&self, p: &Point2<f64>) -> Option<(usize, usize)> {
        if !(p.x.is_finite() && p.y.is_finite()) {
            return None;
        }
        let along = |v: f64, origin: f64, n: usize| {
            (((v - origin) / self.cell).floor().max(0.0) as usize).min(n - 1)
        };
        Some((
            along(p.x, self.origin.x, self.columns),
            along(p.y, self.origin.y, self.rows),
        ))
    }

    /// The unused target nearest to `centre` within `radius` (px), the
    /// lower index on a tie.
    fn nearest_unused(&self, centre: &Point2<f64>, radius: f64) -> Option<usize> {
        let low = self.cell_xy(&Point2::new(centre.x - radius, centre.y - radius))?;
        let high = self.cell_xy(&Point2::new(centre.x + radius, centre.y + radius))?;
        let mut best: Option<(f64, usize)> = None;
        for j in low.1..=high.1 {
            let row = j * self.columns;
            let (from, to) = (
                self.starts[row + low.0] as usize,
                self.starts[row + high.0 + 1] as usize,
            );
            for &t in &self.order[from..to] {
                let t = t as usize;
                if self.used[t] {
                    continue;
                }
                let d = (self.pixels[t] - centre).norm_squared();
                if d <= radius * radius && best.map_or(true, |(b, i)| (d, t) < (b, i)) {
                    best = Some((d, t));
                }
            }
        }
        best.map(|(_, t)| t)
    }
}

/// The image noise of a frame (px, the standard deviation of one image
/// coordinate) from its particles' reprojection RMS and camera counts:
/// the median of their a posteriori `sigma0 = rms sqrt(m / (2m - 3))`
/// (the squared residuals of `m` cameras sum to `m rms²`, with `2m - 3`
/// degrees of freedom; design paper Eq. 23), over the particles seen by 3
/// or more cameras (those of 2 have one degree of freedom, a poor
/// estimate each), or by 2 where there are no others. The median of
/// `sigma0` is a few percent below `sigma` (of `sqrt(chi²₅ / 5)`, 0.93),
/// which makes the test of [`FrameTargets::with_noise`] that much
/// stricter; wrong matches among the particles make it larger. `None`
/// without particles.
pub fn frame_noise(particles: impl IntoIterator<Item = (f64, usize)>) -> Option<f64> {
    let mut by_three = Vec::new();
    let mut by_two = Vec::new();
    for (rms, m) in particles {
        if !(rms.is_finite() && rms >= 0.0) || m < 2 {
            continue;
        }
        let sigma0 = rms * (m as f64 / (2 * m - 3) as f64).sqrt();
        if m >= 3 { &mut by_three } else { &mut by_two }.push(sigma0);
    }
    let values = if by_three.is_empty() {
        &mut by_two
    } else {
        &mut by_three
    };
    if values.is_empty() {
        return None;
    }
    let middle = values.len() / 2;
    Some(*values.select_nth_unstable_by(middle, f64::total_cmp).1)
}

/// The standard normal's 99% quantile.
const Z_99: f64 = 2.326;

/// The 99% quantile of the chi-square distribution with `dof` degrees of
/// freedom (the odd ones of `2m - 3`, 2..8 cameras; beyond, the
/// Wilson-Hilferty approximation).
fn chi_square_99(dof: usize) -> f64 {
    match dof {
        1 => 6.635,
        3 => 11.345,
        5 => 15.086,
        7 => 18.475,
        9 => 21.666,
        11 => 24.725,
        13 => 27.688,
        _ => chi_square_quantile(dof as f64, Z_99),
    }
}

/// The rig and the image noise allowance of the recovery.
#[derive(Clone, Debug)]
pub struct ImageSpaceRecovery {
    cameras: Vec<Camera>,
    tolerance_px: f64,
}

/// A recovery that cannot be set up.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RecoveryError {
    /// Fewer than two cameras.
    #[error("image-space recovery needs at least 2 cameras, the calibration has {0}")]
    TooFewCameras(usize),
    /// The tolerance is not a positive number of pixels.
    #[error("the recovery's tolerance must be a positive number of pixels, got {0}")]
    Tolerance(f64),
}

impl ImageSpaceRecovery {
    /// Recovery with `cameras`, accepting points whose reprojection RMS is
    /// within `tolerance_px` (the correspondence band is the natural
    /// choice: the same images would have been accepted there).
    pub fn new(cameras: Vec<Camera>, tolerance_px: f64) -> Result<Self, RecoveryError> {
        if cameras.len() < 2 {
            return Err(RecoveryError::TooFewCameras(cameras.len()));
        }
        if !(tolerance_px.is_finite() && tolerance_px > 0.0) {
            return Err(RecoveryError::Tolerance(tolerance_px));
        }
        Ok(ImageSpaceRecovery {
            cameras,
            tolerance_px,
        })
    }

    /// The cameras.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// The particle near `predicted` (within `radius` mm) made of targets
    /// of `frame` that nothing uses yet, as the correspondences would have
    /// given it; its targets are then marked used.
    /// `None` where fewer than two cameras have a fitting target.
    pub fn recover(
        &self,
        frame: &mut FrameTargets,
        predicted: &Point3<f64>,
        radius: f64,
    ) -> Option<Particle> {
        if !(radius.is_finite() && radius > 0.0) {
            return None;
        }
        let mut candidates: Vec<(usize, usize, Point2<f64>)> = Vec::new();
        for (c, camera) in self.cameras.iter().enumerate() {
            let Some(targets) = frame.cameras.get(c) else {
                break;
            };
            let Ok((pixel, jacobian)) = camera.project_with_jacobian(predicted) else {
                continue;
            };
            let window = radius * jacobian.norm() + self.tolerance_px;
            if let Some(t) = targets.nearest_unused(&pixel, window) {
                candidates.push((c, t, targets.pixels[t]));
            }
        }
        while candidates.len() >= 2 {
            let observations: Vec<Observation> = candidates
                .iter()
                .map(|&(camera, _, pixel)| Observation { camera, pixel })
                .collect();
            let Ok(fit) = intersect(&self.cameras, &observations) else {
                return None;
            };
            let m = candidates.len();
            let fits_noise = frame.noise_px.map_or(true, |sigma| {
                fit.rms_px * fit.rms_px * m as f64 <= chi_square_99(2 * m - 3) * sigma * sigma
            });
            if fit.rms_px <= self.tolerance_px
                && fits_noise
                && (fit.point - predicted).norm() <= radius
            {
                let mut targets = vec![None; self.cameras.len()];
                for &(c, t, _) in &candidates {
                    targets[c] = Some(t);
                    frame.cameras[c].used[t] = true;
                }
                return Some(Particle {
                    position: fit.point,
                    sigma: fit.sigma,
                    rms_px: fit.rms_px,
                    targets,
                });
            }
            // Leave out the camera that fits worst and try the rest.
            let worst = fit
                .residuals_px
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.norm_squared().total_cmp(&b.1.norm_squared()))
                .map(|(k, _)| k)?;
            candidates.remove(worst);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::simulate::{self, RigSpec};
    use nalgebra::Vector3;
    use rand::Rng;

    fn rig() -> (RigSpec, Vec<Camera>) {
        let spec = RigSpec::convergent(4);
        let cameras = spec.build().expect("the simulated rig");
        (spec, cameras)
    }

    use crate::photogrammetry::simulate::ideal_target as target;

    #[test]
    fn a_missed_particle_is_found_where_its_trajectory_predicts_it() {
        // 500 particles imaged with 0.1 px noise; one of them (the last)
        // lost by the correspondences. The prediction is 0.2 mm off (a
        // trajectory's extrapolation error), the radius 0.5 mm.
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(3);
        let points = simulate::particles(&spec.volume, 500, &mut rng);
        let frame = simulate::target_frame(&cameras, &points, 0.1, 0.0, &mut rng);
        let lost = points.len() - 1;
        // Every other point is a particle that uses its targets.
        let particles: Vec<Vec<Option<usize>>> = (0..lost)
            .map(|j| {
                frame
                    .truth
                    .iter()
                    .map(|truth| truth.iter().position(|&t| t == j))
                    .collect()
            })
            .collect();
        let mut targets =
            FrameTargets::new(&frame.targets, particles.iter().map(Vec::as_slice)).unwrap();
        for c in 0..4 {
            assert_eq!(targets.unused(c), 1, "camera {c}");
        }
        let recovery = ImageSpaceRecovery::new(cameras.clone(), 0.5).unwrap();
        let offset = Vector3::new(0.12, -0.1, 0.12);
        let found = recovery
            .recover(&mut targets, &(points[lost] + offset), 0.5)
            .expect("recovered");
        assert_eq!(found.camera_count(), 4);
        for (c, t) in found.targets.iter().enumerate() {
            assert_eq!(frame.truth[c][t.unwrap()], lost, "camera {c}");
        }
        // 0.1 px of noise is about 10 um in this rig (about 100 um a px
        // at 600 mm): the point is the particle, not the prediction.
        let error = (found.position - points[lost]).norm();
        assert!(error < 0.03, "{error} mm");
        assert!(found.rms_px < 0.3, "{}", found.rms_px);
        // Its targets are taken now.
        assert!(recovery
            .recover(&mut targets, &(points[lost] + offset), 0.5)
            .is_none());
    }

    #[test]
    fn a_wrong_target_in_one_camera_is_left_out() {
        // The particle's image in camera 2 is gone and a stray target sits
        // 1.5 px from where it was: nearest in that camera, but 15 sigma
        // off the other three's rays. The point comes from the other three.
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(5);
        let point = simulate::particles(&spec.volume, 1, &mut rng)[0];
        let mut targets: Vec<Vec<Target>> = cameras
            .iter()
            .map(|c| {
                let p = c.project(&point).unwrap();
                vec![target(
                    p + nalgebra::Vector2::new(rng.random_range(-0.1..0.1), 0.0),
                )]
            })
            .collect();
        targets[2][0].x += 1.5;
        let mut frame = FrameTargets::new(&targets, std::iter::empty()).unwrap();
        let recovery = ImageSpaceRecovery::new(cameras, 0.5).unwrap();
        let found = recovery.recover(&mut frame, &point, 0.3).unwrap();
        assert_eq!(found.targets, vec![Some(0), Some(0), None, Some(0)]);
        assert!((found.position - point).norm() < 0.03);
        assert_eq!(frame.unused(2), 1, "the stray target stays free");
    }

    #[test]
    fn targets_that_do_not_meet_give_nothing() {
        // One target per camera near the prediction's images, each moved
        // 3 px in a random direction: no pair of them meets within 0.5 px.
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(8);
        let point = simulate::particles(&spec.volume, 1, &mut rng)[0];
        let targets: Vec<Vec<Target>> = cameras
            .iter()
            .map(|c| {
                let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                let p = c.project(&point).unwrap();
                vec![target(
                    p + 3.0 * nalgebra::Vector2::new(angle.cos(), angle.sin()),
                )]
            })
            .collect();
        let mut frame = FrameTargets::new(&targets, std::iter::empty()).unwrap();
        let recovery = ImageSpaceRecovery::new(cameras, 0.5).unwrap();
        // A radius of 0.1 mm images to about 1 px: the targets, 3 px off,
        // are outside every window.
        assert!(recovery.recover(&mut frame, &point, 0.1).is_none());
        // With a window wide enough to hold them (3 mm), they are
        // candidates but do not intersect within the tolerance.
        assert!(recovery.recover(&mut frame, &point, 3.0).is_none());
        for c in 0..4 {
            assert_eq!(frame.unused(c), 1);
        }
    }

    #[test]
    fn two_cameras_are_enough() {
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(9);
        let point = simulate::particles(&spec.volume, 1, &mut rng)[0];
        let mut targets: Vec<Vec<Target>> = vec![Vec::new(); 4];
        for c in [0, 3] {
            targets[c].push(target(cameras[c].project(&point).unwrap()));
        }
        let mut frame = FrameTargets::new(&targets, std::iter::empty()).unwrap();
        let recovery = ImageSpaceRecovery::new(cameras, 0.5).unwrap();
        let found = recovery.recover(&mut frame, &point, 0.2).unwrap();
        assert_eq!(found.targets, vec![Some(0), None, None, Some(0)]);
        assert!((found.position - point).norm() < 1e-6);
    }

    /// A tracked sequence where the correspondences lost some particles:
    /// 300 particles in the rig's volume turning about the z axis (0.01
    /// rad a frame) and drifting 0.4 mm a frame along x, 12 frames, their
    /// targets with 0.05 px noise; each frame's particles intersected from
    /// their targets, less a share `lost` of them whose targets stay in
    /// the frame unused.
    fn lossy_sequence(lost: f64, recover: bool, max_gap: usize) -> Outcome {
        use crate::photogrammetry::intersect::intersect;
        use crate::photogrammetry::track::{ParticlePosition, Tracker, TrackingParameters};
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(21);
        let starts = simulate::particles(&spec.volume, 300, &mut rng);
        let centre = spec.volume.centre();
        let at = |start: &Point3<f64>, frame: i64| {
            let t = frame as f64;
            let r = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), 0.01 * t);
            centre + r * (start - centre) + Vector3::new(0.4 * t - 2.0, 0.0, 0.0)
        };
        let parameters = TrackingParameters {
            max_gap,
            ..TrackingParameters::new(2.0)
        };
        let mut tracker = if recover {
            Tracker::with_recovery(
                parameters,
                ImageSpaceRecovery::new(cameras.clone(), 0.5).unwrap(),
            )
            .unwrap()
        } else {
            Tracker::new(parameters).unwrap()
        };
        // Per frame, the true particle of each particle index.
        let mut truth: Vec<Vec<usize>> = Vec::new();
        let mut given = Vec::new();
        let mut frames_targets = Vec::new();
        let mut points = Vec::new();
        let mut recovered = Vec::new();
        for frame in 0..12 {
            let positions: Vec<Point3<f64>> = starts.iter().map(|s| at(s, frame)).collect();
            let images = simulate::target_frame(&cameras, &positions, 0.05, 0.0, &mut rng);
            let mut particles = Vec::new();
            let mut named = Vec::new();
            let mut who = Vec::new();
            for j in 0..positions.len() {
                if rng.random_bool(lost) {
                    continue;
                }
                let targets: Vec<Option<usize>> = images
                    .truth
                    .iter()
                    .map(|truth| truth.iter().position(|&t| t == j))
                    .collect();
                let observations: Vec<Observation> = targets
                    .iter()
                    .enumerate()
                    .filter_map(|(camera, t)| {
                        let t = &images.targets[camera][(*t)?];
                        Some(Observation {
                            camera,
                            pixel: Point2::new(t.x, t.y),
                        })
                    })
                    .collect();
                let Ok(fit) = intersect(&cameras, &observations) else {
                    continue;
                };
                particles.push(ParticlePosition::seen_by(
                    fit.point,
                    fit.sigma.add_scalar(1e-6),
                    observations.len(),
                ));
                named.push(targets);
                who.push(j);
            }
            let targets =
                FrameTargets::new(&images.targets, named.iter().map(Vec::as_slice)).unwrap();
            points.extend(
                tracker
                    .push_with_targets(frame, particles, targets)
                    .unwrap(),
            );
            recovered.extend(tracker.take_recovered());
            given.push(who.len());
            truth.push(who);
            frames_targets.push(images);
        }
        let (last, last_recovered) = tracker.finish_with_recovered();
        points.extend(last);
        recovered.extend(last_recovered);
        // The recovered particles' truth: all their targets image one
        // particle, or they are wrong.
        let mut wrong = 0;
        let mut count = 0;
        for r in &recovered {
            let images = &frames_targets[r.frame as usize];
            let who = &mut truth[r.frame as usize];
            assert_eq!(who.len(), r.first);
            for particle in &r.particles {
                count += 1;
                let seen: Vec<usize> = particle
                    .targets
                    .iter()
                    .enumerate()
                    .filter_map(|(c, t)| Some(images.truth[c][(*t)?]))
                    .collect();
                if seen.iter().any(|&j| j != seen[0]) {
                    wrong += 1;
                }
                who.push(seen[0]);
            }
        }
        // Recoverable: lost in a frame and present (given or recovered) in
        // the three before it, so that its trajectory has a velocity (a
        // new trajectory's first link waits for the frame after it, so
        // two points are not always enough).
        let present = |frame: usize, j: usize| truth[frame].contains(&j);
        let (mut recoverable, mut missed) = (0, 0);
        for frame in 3..truth.len() {
            for j in 0..starts.len() {
                if (1..=3).all(|back| present(frame - back, j))
                    && !truth[frame][..given[frame]].contains(&j)
                {
                    recoverable += 1;
                    missed += usize::from(!present(frame, j));
                }
            }
        }
        // Trajectories, and links that join two different particles.
        let mut by_trajectory: std::collections::BTreeMap<u64, Vec<(i64, usize)>> =
            Default::default();
        for p in &points {
            by_trajectory
                .entry(p.trajectory)
                .or_default()
                .push((p.frame, truth[p.frame as usize][p.particle]));
        }
        let mut wrong_links = 0;
        for t in by_trajectory.values_mut() {
            t.sort();
            wrong_links += t.windows(2).filter(|w| w[0].1 != w[1].1).count();
        }
        assert_eq!(
            wrong, 0,
            "recovered particles made of several particles' images"
        );
        Outcome {
            trajectories: by_trajectory.len(),
            points: points.len(),
            recovered: count,
            recoverable,
            missed,
            wrong_links,
        }
    }

    struct Outcome {
        trajectories: usize,
        points: usize,
        recovered: usize,
        recoverable: usize,
        missed: usize,
        wrong_links: usize,
    }

    #[test]
    fn the_tracker_recovers_what_the_correspondences_lost() {
        // 10% of the particles lost per frame. Without recovery and
        // without gap bridging every loss breaks a trajectory (300
        // particles make about 400 trajectories); with it, a lost particle
        // whose trajectory has a velocity is found again from its images,
        // all of them but those with another particle within the search
        // radius of the prediction (a few in a thousand at this density).
        // Lost before a trajectory has its velocity (in the first frames,
        // or just after another loss) stays lost.
        let plain = lossy_sequence(0.1, false, 0);
        assert_eq!(plain.recovered, 0);
        let with = lossy_sequence(0.1, true, 0);
        assert!(with.recoverable > 200, "{}", with.recoverable);
        assert!(
            with.missed * 50 <= with.recoverable,
            "{} of {} recoverable losses missed",
            with.missed,
            with.recoverable
        );
        assert!(
            plain.trajectories as f64 > 1.25 * with.trajectories as f64,
            "{} trajectories without recovery, {} with",
            plain.trajectories,
            with.trajectories
        );
        // Every recovered point is reported, and pieces shorter than
        // `min_length` no longer fall away.
        assert!(with.points >= plain.points + with.recovered);
        assert_eq!((plain.wrong_links, with.wrong_links), (0, 0));
        // Nothing lost, nothing recovered.
        assert_eq!(lossy_sequence(0.0, true, 0).recovered, 0);
    }

    #[test]
    fn a_point_must_fit_its_images_as_the_frames_particles_do() {
        // Two cameras' targets whose rays miss each other by about a
        // pixel: within a 1 px tolerance, but far beyond what a frame with
        // 0.05 px of noise allows (2 m rms² within chi-square(1)'s 99%
        // quantile, 6.6 sigma²: an RMS of 0.09 px).
        let (spec, cameras) = rig();
        let mut rng = simulate::rng(12);
        let point = simulate::particles(&spec.volume, 1, &mut rng)[0];
        let mut targets: Vec<Vec<Target>> = vec![Vec::new(); 4];
        targets[0].push(target(cameras[0].project(&point).unwrap()));
        let shifted = cameras[3].project(&point).unwrap() + nalgebra::Vector2::new(0.7, 0.7);
        targets[3].push(target(shifted));
        let recovery = ImageSpaceRecovery::new(cameras, 1.0).unwrap();
        let loose = FrameTargets::new(&targets, std::iter::empty()).unwrap();
        let found = recovery.recover(&mut loose.clone(), &point, 0.3).unwrap();
        assert!(found.rms_px > 0.2, "{}", found.rms_px);
        let mut strict = loose.with_noise(0.05);
        assert!(recovery.recover(&mut strict, &point, 0.3).is_none());
        // And with the noise of that frame, the exact images fit.
        targets[3][0] = target(shifted - nalgebra::Vector2::new(0.7, 0.7));
        let mut exact = FrameTargets::new(&targets, std::iter::empty())
            .unwrap()
            .with_noise(0.05);
        assert!(recovery.recover(&mut exact, &point, 0.3).is_some());
    }

    #[test]
    fn the_frame_noise_is_the_particles_median_sigma0() {
        // sigma0 = rms sqrt(m / (2m - 3)): 4 cameras, rms 0.1 -> 0.0894.
        let noise = frame_noise((0..9).map(|k| (0.1 + 0.01 * (k as f64 - 4.0), 4))).unwrap();
        assert!((noise - 0.1 * (4f64 / 5.0).sqrt()).abs() < 1e-12, "{noise}");
        // 2-camera particles only where there are no others.
        assert_eq!(frame_noise([(0.1, 2), (0.3, 3)]), Some(0.3));
        assert!((frame_noise([(0.1, 2)]).unwrap() - 0.1 * 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(frame_noise([(f64::NAN, 4), (0.2, 1)]), None);
        // The chi-square quantiles: the table and the approximation agree
        // where both exist.
        assert!((chi_square_quantile(13.0, Z_99) - chi_square_99(13)).abs() < 0.05);
    }

    #[test]
    fn a_frames_targets_of_its_particles_mark_their_targets_and_carry_their_noise() {
        let targets = vec![
            vec![target(Point2::new(1.0, 1.0)), target(Point2::new(5.0, 5.0))],
            vec![target(Point2::new(2.0, 2.0))],
        ];
        let particle = |rms_px: f64, targets: Vec<Option<usize>>| Particle {
            position: Point3::origin(),
            sigma: Vector3::repeat(0.01),
            rms_px,
            targets,
        };
        let particles = [
            particle(0.1, vec![Some(1), Some(0)]),
            particle(0.3, vec![Some(0), None]),
        ];
        let frame = FrameTargets::of_particles(&targets, &particles).unwrap();
        assert_eq!((frame.unused(0), frame.unused(1)), (0, 0));
        // The noise is frame_noise's over the same particles: only the
        // 2-camera one counts (the other has one camera).
        assert_eq!(
            frame.noise_px(),
            frame_noise([(0.1, 2), (0.3, 1)]),
            "{frame:?}"
        );
        assert!(frame.noise_px().is_some());
        let none = FrameTargets::of_particles(&targets, &[]).unwrap();
        assert_eq!((none.unused(0), none.noise_px()), (2, None));
        // A particle naming a target that is not there is refused.
        assert!(
            FrameTargets::of_particles(&targets, &[particle(0.1, vec![None, Some(3)])]).is_err()
        );
    }

    #[test]
    fn bad_input_is_refused() {
        let (_, cameras) = rig();
        assert_eq!(
            ImageSpaceRecovery::new(cameras[..1].to_vec(), 0.5).unwrap_err(),
            RecoveryError::TooFewCameras(1)
        );
        assert!(ImageSpaceRecovery::new(cameras.clone(), 0.0).is_err());
        assert!(ImageSpaceRecovery::new(cameras, f64::NAN).is_err());
        let targets = vec![vec![target(Point2::new(1.0, 1.0))]; 2];
        let named = [Some(0), Some(1)];
        assert_eq!(
            FrameTargets::new(&targets, [&named[..]]).unwrap_err(),
            FrameTargetsError::Target {
                particle: 0,
                camera: 1,
                target: 1,
                count: 1
            }
        );
        let three = [None, None, Some(0)];
        assert!(matches!(
            FrameTargets::new(&targets, [&three[..]]),
            Err(FrameTargetsError::Cameras { .. })
        ));
        // Non-finite targets are never candidates, and do not break the index.
        let odd = vec![
            vec![
                target(Point2::new(f64::NAN, 3.0)),
                target(Point2::new(2.0, 2.0)),
            ],
            vec![],
        ];
        let frame = FrameTargets::new(&odd, std::iter::empty()).unwrap();
        assert_eq!(
            frame.cameras[0].nearest_unused(&Point2::new(2.5, 2.5), 1.0),
            Some(1)
        );
    }
}
