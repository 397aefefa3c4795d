//! The matcher: a calibration and matching parameters, validated and
//! prepared once for many frames (refraction tables over the volume, the
//! seed camera pairs, and per camera pair the shape of its epipolar
//! curves), and [`Matcher::match_frame`], which checks a frame's targets
//! and runs the search on them.

use super::epipolar::{EpipolarGeometry, PARABOLA_SHARE};
use super::grid::CameraFrame;
use super::search::Search;
use super::{default_volume, MatchError, MatchingParameters, Particle, Similarity};
use crate::photogrammetry::camera::Camera;
use crate::photogrammetry::cancel::Cancel;
use crate::photogrammetry::target::Target;
use crate::photogrammetry::volume::Volume;

/// Matches frames of targets against one calibration: the cameras are
/// prepared (refraction tables over the volume) once, for many frames.
#[derive(Clone, Debug)]
pub struct Matcher {
    pub(super) cameras: Vec<Camera>,
    pub(super) tolerance: f64,
    pub(super) volume: Volume,
    pub(super) min_cameras: usize,
    similarity: Option<Similarity>,
    /// Seed camera pairs, in the order that decides which seed keeps a group.
    pub(super) seeds: Vec<(usize, usize)>,
    /// Per camera: principal distance over pixel size, for pixel-scale
    /// estimates of distances in object space.
    pub(super) pixels_per_unit_angle: Vec<f64>,
    /// Per ordered camera pair `(i, k)` at `i * count + k`: the shape of
    /// the epipolar curves from i in k.
    pub(super) epipolar: Vec<EpipolarGeometry>,
}

/// Camera pairs such that every set of three cameras contains one: all
/// pairs within the first half of the cameras and within the second half
/// (the complement graph is bipartite, hence free of triangles). Two
/// cameras have the one pair.
fn seed_pairs(cameras: usize) -> Vec<(usize, usize)> {
    if cameras == 2 {
        return vec![(0, 1)];
    }
    let half = cameras.div_ceil(2);
    let mut seeds = Vec::new();
    for (from, to) in [(0, half), (half, cameras)] {
        for i in from..to {
            for j in i + 1..to {
                seeds.push((i, j));
            }
        }
    }
    seeds
}

impl Matcher {
    /// Validates the parameters and prepares the cameras.
    pub fn new(cameras: &[Camera], parameters: &MatchingParameters) -> Result<Matcher, MatchError> {
        let count = cameras.len();
        if count < 2 {
            return Err(MatchError::TooFewCameras(count));
        }
        if !(parameters.tolerance.is_finite() && parameters.tolerance > 0.0) {
            return Err(MatchError::Tolerance(parameters.tolerance));
        }
        if !(2..=count).contains(&parameters.min_cameras) {
            return Err(MatchError::MinCameras {
                min: parameters.min_cameras,
                cameras: count,
            });
        }
        if let Some(s) = parameters.similarity {
            if !(s.max_size_ratio >= 1.0 && s.max_brightness_ratio >= 1.0) {
                return Err(MatchError::Similarity(
                    s.max_size_ratio,
                    s.max_brightness_ratio,
                ));
            }
        }
        let volume = match parameters.volume {
            Some(volume) => volume,
            None => default_volume(cameras).ok_or(MatchError::NoDefaultVolume)?,
        };
        let valid = (0..3).all(|i| {
            volume.min[i] < volume.max[i] && !volume.min[i].is_nan() && !volume.max[i].is_nan()
        });
        if !valid {
            return Err(MatchError::EmptyVolume(volume));
        }
        // The refraction table needs a bounded region; an unbounded axis
        // (allowed, as in OpenPTV, which bounds only the depth) is left to
        // the exact solve.
        let bounded = (0..3).all(|i| volume.min[i].is_finite() && volume.max[i].is_finite());
        let cameras: Vec<Camera> = cameras
            .iter()
            .map(|camera| {
                if bounded {
                    camera.clone().with_refraction_table(&volume)
                } else {
                    camera.clone()
                }
            })
            .collect();
        let pixels_per_unit_angle = cameras
            .iter()
            .map(|camera| {
                let sensor = camera.sensor();
                camera.parameters().interior.c / sensor.pixel_size_x.min(sensor.pixel_size_y)
            })
            .collect();
        let epipolar = (0..count * count)
            .map(|index| {
                let (i, k) = (index / count, index % count);
                EpipolarGeometry::sample(
                    &cameras,
                    &volume,
                    (i, k),
                    PARABOLA_SHARE * parameters.tolerance,
                )
            })
            .collect();
        Ok(Matcher {
            epipolar,
            seeds: seed_pairs(count),
            cameras,
            tolerance: parameters.tolerance,
            volume,
            min_cameras: parameters.min_cameras,
            similarity: parameters.similarity,
            pixels_per_unit_angle,
        })
    }

    /// The cameras, with refraction tables.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// The observation volume in use.
    pub fn volume(&self) -> &Volume {
        &self.volume
    }

    /// Finds the particles of one frame: `targets[c]` are camera c's targets.
    pub fn match_frame(&self, targets: &[Vec<Target>]) -> Result<Vec<Particle>, MatchError> {
        self.match_frame_until(targets, &Cancel::new())
    }

    /// [`Matcher::match_frame`], stopped with [`MatchError::Cancelled`]
    /// once `cancel` fires (checked between cameras and every few dozen
    /// targets of the search's outer loops).
    pub fn match_frame_until(
        &self,
        targets: &[Vec<Target>],
        cancel: &Cancel,
    ) -> Result<Vec<Particle>, MatchError> {
        cancel.check()?;
        let count = self.cameras.len();
        if targets.len() != count {
            return Err(MatchError::CameraCount {
                targets: targets.len(),
                cameras: count,
            });
        }
        for (camera, list) in targets.iter().enumerate() {
            if let Some(index) = list
                .iter()
                .position(|t| !(t.x.is_finite() && t.y.is_finite()))
            {
                return Err(MatchError::InvalidTarget { camera, index });
            }
        }
        let mut frames = Vec::with_capacity(count);
        for (camera, list) in self.cameras.iter().zip(targets) {
            cancel.check()?;
            frames.push(CameraFrame::new(camera, list, self.tolerance));
        }
        Ok(Search::new(self, &frames).until(cancel).run()?)
    }

    /// Whether `a` and `b` pass the similarity criteria.
    pub(super) fn similar(&self, a: &Target, b: &Target) -> bool {
        let Some(s) = self.similarity else {
            return true;
        };
        let within =
            |x: f64, y: f64, limit: f64| x <= 0.0 || y <= 0.0 || (x / y).max(y / x) <= limit;
        within(f64::from(a.n), f64::from(b.n), s.max_size_ratio)
            && within(a.sumg as f64, b.sumg as f64, s.max_brightness_ratio)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;

    use super::*;
    use crate::photogrammetry::simulate::{self, MatchScore, RigSpec, TargetFrame};

    struct Scene {
        cameras: Vec<Camera>,
        points: Vec<Point3<f64>>,
        frame: TargetFrame,
        volume: Volume,
    }

    fn scene(cameras: usize, particles: usize, noise: f64, drop: f64, seed: u64) -> Scene {
        let spec = RigSpec::convergent(cameras);
        let rig = spec.build().unwrap();
        let mut rng = simulate::rng(seed);
        let points = simulate::particles(&spec.volume, particles, &mut rng);
        let frame = simulate::target_frame(&rig, &points, noise, drop, &mut rng);
        Scene {
            cameras: rig,
            points,
            frame,
            volume: spec.volume,
        }
    }

    fn run(scene: &Scene, tolerance: f64, min_cameras: usize) -> (Vec<Particle>, MatchScore) {
        let parameters = MatchingParameters {
            tolerance,
            volume: Some(scene.volume),
            min_cameras,
            similarity: None,
        };
        let particles = Matcher::new(&scene.cameras, &parameters)
            .unwrap()
            .match_frame(&scene.frame.targets)
            .unwrap();
        let score = MatchScore::of(&particles, &scene.frame, &scene.points);
        (particles, score)
    }

    #[test]
    fn noise_free_particles_are_exact() {
        // Every correct particle within 1 um of the truth; the tolerance is
        // what any real frame would need (0.5 px), not tuned to noise-free data.
        let scene = scene(4, 2000, 0.0, 0.1, 11);
        let (_, score) = run(&scene, 0.5, 2);
        assert!(score.max_error < 1e-3, "{score:?}");
        // At least as complete as the 10% losses allow: a particle needs two
        // of its four images (99.6% of them have that).
        assert!(score.correct as f64 > 0.98 * 2000.0, "{score:?}");
    }

    #[test]
    fn reported_sigmas_match_the_errors() {
        // The RMS error per axis over the mean reported sigma: the adjustment's
        // a posteriori sigmas must describe the actual scatter.
        let scene = scene(4, 3000, 0.1, 0.1, 12);
        let (_, score) = run(&scene, 0.5, 2);
        let ratio = score.rms_error / score.mean_sigma;
        assert!((0.8..=1.25).contains(&ratio), "ratio {ratio}: {score:?}");
    }

    #[test]
    fn three_cameras_find_nearly_all_particles_as_triplets() {
        let scene = scene(3, 2000, 0.1, 0.0, 13);
        let (_, score) = run(&scene, 0.5, 2);
        assert!(score.by_cameras[3] as f64 >= 0.99 * 2000.0, "{score:?}");
        assert!(score.ghosts <= 10, "{score:?}");
    }

    #[test]
    fn two_four_and_six_cameras_work() {
        for (cameras, particles) in [(4, 2000), (6, 2000)] {
            let scene = scene(cameras, particles, 0.1, 0.0, 14);
            let (found, score) = run(&scene, 0.5, 2);
            assert!(
                score.correct as f64 >= 0.99 * particles as f64,
                "{cameras} cameras: {score:?}"
            );
            assert!(
                score.ghosts * 100 <= particles,
                "{cameras} cameras: {score:?}"
            );
            let full = found.iter().filter(|p| p.camera_count() == cameras).count();
            assert!(
                full as f64 >= 0.95 * particles as f64,
                "{cameras} cameras: {full} seen by all"
            );
        }
    }

    #[test]
    fn two_cameras_find_the_unambiguous_pairs() {
        // With two cameras only a pair whose targets are each other's single
        // candidate may be accepted. Count those among the true pairs with
        // the matcher's own bands; each is lost only if its miss exceeds the
        // 3-sigma acceptance (1.1%). Of the ~200 here, at least 97% (four
        // binomial standard deviations, 0.7% each, below 98.9%).
        let scene = scene(2, 300, 0.1, 0.0, 14);
        let (found, score) = run(&scene, 0.5, 2);
        assert!(score.ghosts <= 3, "{score:?}");
        let parameters = MatchingParameters {
            tolerance: 0.5,
            volume: Some(scene.volume),
            ..MatchingParameters::default()
        };
        let matcher = Matcher::new(&scene.cameras, &parameters).unwrap();
        let frames: Vec<CameraFrame> = matcher
            .cameras
            .iter()
            .zip(&scene.frame.targets)
            .map(|(camera, targets)| CameraFrame::new(camera, targets, 0.5))
            .collect();
        let mut search = Search::new(&matcher, &frames);
        // Sorted index of each particle's target per camera.
        let sorted = |c: usize, j: usize| {
            frames[c]
                .original
                .iter()
                .position(|&o| scene.frame.truth[c][o as usize] == j)
                .unwrap()
        };
        let mut unambiguous = Vec::new();
        for j in 0..scene.points.len() {
            let (a, b) = (sorted(0, j), sorted(1, j));
            let (mut forward, mut back) = (Vec::new(), Vec::new());
            search.band(0, a, 1, |t| forward.push(t));
            search.band(1, b, 0, |t| back.push(t));
            if forward == [b] && back == [a] {
                unambiguous.push(j);
            }
        }
        let found_pairs = unambiguous
            .iter()
            .filter(|&&j| {
                found.iter().any(|p| {
                    p.targets
                        .iter()
                        .enumerate()
                        .all(|(c, t)| t.is_some_and(|t| scene.frame.truth[c][t] == j))
                })
            })
            .count();
        assert!(
            unambiguous.len() >= 100,
            "{} unambiguous",
            unambiguous.len()
        );
        assert!(
            found_pairs as f64 >= 0.97 * unambiguous.len() as f64,
            "{found_pairs} of {} unambiguous pairs found",
            unambiguous.len()
        );
    }

    /// Hides every tenth particle in one of the four cameras (in turn) and
    /// counts how many of those are found from their three other images.
    fn hidden_found_from_three(noise: f64) -> usize {
        let scene = scene(4, 1000, noise, 0.0, 15);
        let mut frame = scene.frame.clone();
        for j in (0..scene.points.len()).step_by(10) {
            let camera = (j / 10) % 4;
            let index = frame.truth[camera].iter().position(|&p| p == j).unwrap();
            frame.truth[camera].remove(index);
            frame.targets[camera].remove(index);
        }
        let hidden = Scene { frame, ..scene };
        let (found, _) = run(&hidden, 0.5, 3);
        (0..hidden.points.len())
            .step_by(10)
            .filter(|&j| {
                found.iter().any(|p| {
                    p.camera_count() == 3
                        && p.targets
                            .iter()
                            .enumerate()
                            .all(|(c, t)| t.is_none_or(|t| hidden.frame.truth[c][t] == j))
                })
            })
            .count()
    }

    #[test]
    fn a_particle_hidden_in_one_of_four_images_is_found_from_three() {
        // Without noise, every one.
        assert_eq!(hidden_found_from_three(0.0), 100);
        // With noise, each of the three members must miss by at most the
        // 3-sigma acceptance (see estimate_noise): a triplet survives with
        // probability (1 - exp(-4.5))^3 = 0.967; of 100, at least 89 (four
        // binomial standard deviations, 1.8 each, below the expected 96.7).
        let found = hidden_found_from_three(0.1);
        assert!(found >= 89, "{found} of 100");
    }

    #[test]
    fn parallel_cameras_without_a_volume_are_asked_for_one() {
        // Two cameras looking the same way have no point their axes meet.
        let spec = RigSpec::convergent(2);
        let rig = spec.build().unwrap();
        let mut twin = rig[0].parameters().clone();
        twin.exterior.position.x += 50.0;
        let cameras = vec![rig[0].clone(), Camera::new(twin).unwrap()];
        let error = Matcher::new(&cameras, &MatchingParameters::default()).unwrap_err();
        assert_eq!(error, MatchError::NoDefaultVolume);
        assert!(error.to_string().contains("--volume"), "{error}");
        let parameters = MatchingParameters {
            volume: Some(spec.volume),
            ..MatchingParameters::default()
        };
        assert!(Matcher::new(&cameras, &parameters).is_ok());
    }

    #[test]
    fn empty_frames_give_no_particles() {
        let scene = scene(4, 10, 0.1, 0.0, 16);
        let matcher = Matcher::new(&scene.cameras, &MatchingParameters::default()).unwrap();
        assert!(matcher
            .match_frame(&vec![Vec::new(); 4])
            .unwrap()
            .is_empty());
        let mut one_empty = scene.frame.targets.clone();
        one_empty[2].clear();
        assert!(matcher.match_frame(&one_empty).is_ok());
    }

    #[test]
    fn bad_parameters_and_input_are_errors() {
        let scene = scene(4, 10, 0.1, 0.0, 17);
        let with = |f: &dyn Fn(&mut MatchingParameters)| {
            let mut parameters = MatchingParameters {
                volume: Some(scene.volume),
                ..MatchingParameters::default()
            };
            f(&mut parameters);
            Matcher::new(&scene.cameras, &parameters).map(|_| ())
        };
        assert_eq!(
            with(&|p| p.tolerance = -1.0),
            Err(MatchError::Tolerance(-1.0))
        );
        assert!(matches!(
            with(&|p| p.tolerance = f64::NAN),
            Err(MatchError::Tolerance(_))
        ));
        assert!(matches!(
            with(&|p| p.min_cameras = 5),
            Err(MatchError::MinCameras { min: 5, cameras: 4 })
        ));
        let flat = Volume {
            min: Point3::new(0.0, 0.0, 0.0),
            max: Point3::new(10.0, 10.0, 0.0),
        };
        assert!(matches!(
            with(&|p| p.volume = Some(flat)),
            Err(MatchError::EmptyVolume(_))
        ));
        let matcher = Matcher::new(&scene.cameras, &MatchingParameters::default()).unwrap();
        assert_eq!(
            matcher.match_frame(&scene.frame.targets[..3]),
            Err(MatchError::CameraCount {
                targets: 3,
                cameras: 4
            })
        );
        let mut nan = scene.frame.targets.clone();
        nan[1][0].x = f64::NAN;
        assert_eq!(
            matcher.match_frame(&nan),
            Err(MatchError::InvalidTarget {
                camera: 1,
                index: 0
            })
        );
    }
}
