//! Tracking against known motion: particles in a vortex (solid-body
//! rotation about the z axis and a drift along it), their positions with
//! Gaussian noise, their order shuffled in every frame.

use nalgebra::{Point3, Rotation3, Vector3};
use rand::seq::SliceRandom;
use rand::Rng;
use rand_distr::{Distribution, Normal};

use super::links::Link;
use super::live::{binomial_cdf, decision_length};
use super::*;
use crate::photogrammetry::simulate;

/// Rotation per frame (rad) and drift (mm per frame): at the cylinder's
/// radius of 50 mm a particle moves 1 mm a frame, its centripetal
/// acceleration is 0.02 mm per frame².
const OMEGA: f64 = 0.02;
const DRIFT: f64 = 0.3;
const RADIUS: f64 = 50.0;

struct Scene {
    frames: Vec<(i64, Vec<ParticlePosition>)>,
    /// Per frame, per particle index, the true particle (`None` for a
    /// spurious one).
    truth: Vec<Vec<Option<usize>>>,
    starts: Vec<Point3<f64>>,
}

fn true_position(start: &Point3<f64>, frame: i64) -> Point3<f64> {
    let t = frame as f64;
    Rotation3::from_axis_angle(&Vector3::z_axis(), OMEGA * t) * start
        + Vector3::new(0.0, 0.0, DRIFT * t)
}

fn true_velocity(position: &Point3<f64>) -> Vector3<f64> {
    Vector3::new(-OMEGA * position.y, OMEGA * position.x, DRIFT)
}

fn true_acceleration(position: &Point3<f64>) -> Vector3<f64> {
    Vector3::new(
        -OMEGA * OMEGA * position.x,
        -OMEGA * OMEGA * position.y,
        0.0,
    )
}

/// `count` particles in the cylinder of radius 50 mm, 0..100 mm high
/// (mean spacing about 6 mm at 3,000), over `frames` frames, each kept
/// with probability `1 - dropout`, plus `spurious` random points per frame.
fn vortex(
    count: usize,
    frames: i64,
    noise: f64,
    dropout: f64,
    spurious: usize,
    seed: u64,
) -> Scene {
    let mut rng = simulate::rng(seed);
    let starts: Vec<Point3<f64>> = (0..count)
        .map(|_| loop {
            let p = Point3::new(
                rng.random_range(-RADIUS..RADIUS),
                rng.random_range(-RADIUS..RADIUS),
                rng.random_range(0.0..100.0),
            );
            if p.coords.xy().norm() <= RADIUS {
                break p;
            }
        })
        .collect();
    let normal = Normal::new(0.0, noise).unwrap();
    let mut scene = Scene {
        frames: Vec::new(),
        truth: Vec::new(),
        starts: starts.clone(),
    };
    for frame in 0..frames {
        let mut items: Vec<(Option<usize>, Point3<f64>)> = Vec::new();
        for (i, start) in starts.iter().enumerate() {
            if !rng.random_bool(dropout) {
                let noise = Vector3::from_fn(|_, _| normal.sample(&mut rng));
                items.push((Some(i), true_position(start, frame) + noise));
            }
        }
        for _ in 0..spurious {
            let p = Point3::new(
                rng.random_range(-RADIUS..RADIUS),
                rng.random_range(-RADIUS..RADIUS),
                rng.random_range(0.0..100.0 + DRIFT * frames as f64),
            );
            items.push((None, p));
        }
        items.shuffle(&mut rng);
        scene.truth.push(items.iter().map(|(t, _)| *t).collect());
        scene.frames.push((
            frame,
            items
                .iter()
                .map(|(_, p)| ParticlePosition::new(*p, Vector3::repeat(noise)))
                .collect(),
        ));
    }
    scene
}

/// Links (consecutive points of a trajectory) and how many join the same
/// true particle.
fn links(scene: &Scene, trajectories: &[Trajectory]) -> (usize, usize) {
    let mut all = 0;
    let mut correct = 0;
    for t in trajectories {
        for pair in t.points.windows(2) {
            all += 1;
            let a = scene.truth[pair[0].frame as usize][pair[0].particle];
            let b = scene.truth[pair[1].frame as usize][pair[1].particle];
            if a.is_some() && a == b {
                correct += 1;
            }
        }
    }
    (all, correct)
}

fn parameters() -> TrackingParameters {
    // 1 mm per frame at most (the cylinder's rim), with a margin.
    TrackingParameters::new(1.5)
}

/// 3,000 particles over 30 frames with 10 um noise: spacing (about 6 mm)
/// far above the displacement (up to 1 mm) and the prediction error
/// (0.02 mm of centripetal acceleration), so every link is unambiguous and
/// every particle one trajectory. Velocities and accelerations of interior
/// points scatter about the truth by the sigmas the fit reports.
#[test]
fn a_vortex_is_tracked_whole_with_the_sigmas_it_reports() {
    let noise = 0.01;
    let scene = vortex(3000, 30, noise, 0.0, 0, 7);
    let trajectories = track(scene.frames.clone(), parameters()).unwrap();
    let (all, correct) = links(&scene, &trajectories);
    println!(
        "{} trajectories, {all} links, {correct} correct",
        trajectories.len()
    );
    assert_eq!(correct, all, "every link joins one particle");
    let whole = trajectories.iter().filter(|t| t.points.len() == 30).count();
    assert_eq!(
        whole, 3000,
        "every particle is one trajectory of all 30 frames"
    );

    // Normalised errors of interior points (a full 5-point window). Their
    // RMS is 1 if the sigmas are right: 3,000 x 26 points x 3 axes
    // estimate it to about 0.3%; the quadratic fit's bias on a circle (the
    // cubic term, omega³ r / 6 · 34/10 ~ 2e-4 mm per frame against a sigma
    // of 3.2e-3) adds under 1%. So within 5%.
    let (mut v2, mut a2, mut n) = (0.0, 0.0, 0usize);
    for t in &trajectories {
        let id = scene.truth[t.points[0].frame as usize][t.points[0].particle].unwrap();
        for p in &t.points[2..t.points.len() - 2] {
            let truth = true_position(&scene.starts[id], p.frame);
            let d = &p.derivatives;
            let ev = (d.velocity - true_velocity(&truth)).component_div(&d.velocity_sigma);
            let ea = (d.acceleration.unwrap() - true_acceleration(&truth))
                .component_div(&d.acceleration_sigma.unwrap());
            v2 += ev.norm_squared();
            a2 += ea.norm_squared();
            n += 3;
        }
    }
    let (v_rms, a_rms) = ((v2 / n as f64).sqrt(), (a2 / n as f64).sqrt());
    println!("normalised velocity error RMS {v_rms:.4}, acceleration {a_rms:.4}");
    assert!((0.95..1.05).contains(&v_rms), "{v_rms}");
    assert!((0.95..1.05).contains(&a_rms), "{a_rms}");
    // The sigma of a 5-point quadratic fit's velocity: noise / sqrt(10).
    let sigma = trajectories[0].points[2].derivatives.velocity_sigma.x;
    assert!((sigma - noise / 10f64.sqrt()).abs() < 1e-12, "{sigma}");
}

/// 5% of the particles lost at random in each frame: gaps of one frame
/// are bridged, so trajectories stay long; without bridging they break
/// at every loss. 5% spurious points per frame take no part in long
/// trajectories.
#[test]
fn gaps_are_bridged_and_spurious_points_stay_out() {
    let scene = vortex(2000, 30, 0.01, 0.05, 100, 11);
    let mean_length = |trajectories: &[Trajectory]| {
        trajectories.iter().map(|t| t.points.len()).sum::<usize>() as f64
            / trajectories.len() as f64
    };
    let bridged = track(scene.frames.clone(), parameters()).unwrap();
    let (all, correct) = links(&scene, &bridged);
    let broken = track(
        scene.frames.clone(),
        TrackingParameters {
            max_gap: 0,
            ..parameters()
        },
    )
    .unwrap();
    println!(
        "bridged: {} trajectories, mean length {:.1}, {correct} of {all} links correct; unbridged: {}, mean length {:.1}",
        bridged.len(),
        mean_length(&bridged),
        broken.len(),
        mean_length(&broken)
    );
    // A particle is lost twice in a row with probability 0.25% per frame
    // pair, ending its trajectory: about 2000 x 28 x 0.0025 = 140 breaks
    // besides the 2000 starts. Without bridging every loss (2000 x 30 x
    // 0.05 = 3000) breaks one.
    assert!(bridged.len() < 2000 + 300, "{}", bridged.len());
    assert!(broken.len() > 2000 + 2000, "{}", broken.len());
    // Spurious points are 5% of all and random: a link through one needs
    // a random point within the look-ahead's radius of a smooth
    // prediction, so very few are linked.
    assert!(correct as f64 >= 0.999 * all as f64, "{correct} of {all}");
}

/// Two particles crossing within 0.3 mm at 1 mm a frame: the smoothest
/// continuation keeps each on its straight line.
#[test]
fn crossing_particles_keep_their_lines() {
    let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..21)
        .map(|f| {
            let t = f as f64 - 10.0;
            let sigma = Vector3::repeat(0.005);
            let a = Point3::new(t, 0.0, 0.0);
            let b = Point3::new(0.0, 0.3 + t * 0.8, t * 0.6);
            // Swap their order every frame, so index order says nothing.
            let pair = if f % 2 == 0 { [a, b] } else { [b, a] };
            (
                f,
                pair.iter()
                    .map(|&position| ParticlePosition::new(position, sigma))
                    .collect(),
            )
        })
        .collect();
    let trajectories = track(frames, TrackingParameters::new(1.5)).unwrap();
    assert_eq!(trajectories.len(), 2);
    for t in &trajectories {
        assert_eq!(t.points.len(), 21);
        let first_is_a = t.points[0].position.y == 0.0 && t.points[0].position.z == 0.0;
        for p in &t.points {
            let on_a = p.position.y == 0.0 && p.position.z == 0.0;
            assert_eq!(on_a, first_is_a, "frame {}", p.frame);
        }
    }
}

/// The tracker holds, per live trajectory, the points whose fit is not
/// final (up to `2w`, and the newest: `kinematics::derivatives_at` may
/// take a window reaching `2w` ahead) and the `2w` behind them, plus the
/// one frame of look-ahead: 50 particles with `w` = 2 hold at most 50 x
/// (4w + 1) + 50 points, however long the sequence.
#[test]
fn memory_is_bounded_by_the_window_not_the_sequence() {
    let p = parameters();
    let bound = 50 * (4 * p.fit_half_window + 1) + 50;
    let mut tracker = Tracker::new(p).unwrap();
    let mut most = 0;
    let mut out = 0;
    for f in 0..2000i64 {
        let particles = (0..50)
            .map(|i| {
                ParticlePosition::new(
                    Point3::new(f as f64 * 0.5, i as f64 * 10.0, 0.0),
                    Vector3::repeat(0.01),
                )
            })
            .collect();
        out += tracker.push(f, particles).unwrap().len();
        most = most.max(tracker.held_points());
    }
    out += tracker.finish().len();
    assert_eq!(out, 50 * 2000);
    assert!(most <= bound, "{most} > {bound}");
}

#[test]
fn bad_input_is_refused_with_what_is_wrong() {
    for (p, field) in [
        (TrackingParameters::new(0.0), "max_velocity"),
        (TrackingParameters::new(f64::NAN), "max_velocity"),
        (
            TrackingParameters {
                max_gap: 3,
                ..parameters()
            },
            "max_gap",
        ),
        (
            TrackingParameters {
                fit_order: 4,
                ..parameters()
            },
            "fit_order",
        ),
        (
            TrackingParameters {
                min_length: 0,
                ..parameters()
            },
            "min_length",
        ),
    ] {
        let error = Tracker::new(p).err().unwrap().to_string();
        assert!(error.contains(field), "{error}");
    }
    let mut tracker = Tracker::new(parameters()).unwrap();
    tracker.push(5, Vec::new()).unwrap();
    assert_eq!(
        tracker.push(5, Vec::new()).unwrap_err(),
        TrackError::FrameOrder { frame: 5, last: 5 }
    );
    let nan = ParticlePosition::new(Point3::new(f64::NAN, 0.0, 0.0), Vector3::repeat(0.01));
    let zero = ParticlePosition::new(Point3::origin(), Vector3::zeros());
    assert!(matches!(
        tracker.push(6, vec![nan]).unwrap_err(),
        TrackError::InvalidParticle {
            frame: 6,
            index: 0,
            ..
        }
    ));
    let error = tracker.push(7, vec![zero, zero]).unwrap_err().to_string();
    assert!(error.contains("standard deviations"), "{error}");
}

/// A skipped frame number is an empty frame: a trajectory bridges it.
#[test]
fn a_skipped_frame_number_is_a_gap() {
    let frames: Vec<(i64, Vec<ParticlePosition>)> = [0, 1, 2, 4, 5, 6]
        .iter()
        .map(|&f| {
            (
                f,
                vec![ParticlePosition::new(
                    Point3::new(f as f64, 0.0, 0.0),
                    Vector3::repeat(0.01),
                )],
            )
        })
        .collect();
    let trajectories = track(frames, parameters()).unwrap();
    assert_eq!(trajectories.len(), 1);
    assert_eq!(trajectories[0].points.len(), 6);
    let v = trajectories[0].points[3].derivatives.velocity;
    assert!((v - Vector3::x()).norm() < 1e-9, "{v}");
}

/// A particle claiming a near-zero sigma (a 2-camera intersection with a
/// near-zero residual) is weighed as the frame's median: the trajectory's
/// velocity is what it is when that particle states the median itself.
#[test]
fn a_near_zero_sigma_does_not_pin_the_fit() {
    let run = |claimed: f64| {
        let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..7)
            .map(|f| {
                // Particle 0 moves 1 mm a frame and is 0.05 mm off at frame 3;
                // particles 1 and 2 stand still far away and set the median.
                let off = if f == 3 { 0.05 } else { 0.0 };
                let sigma0 = if f == 3 { claimed } else { 0.01 };
                let p = |x: f64, y: f64, s: f64| {
                    ParticlePosition::new(Point3::new(x, y, 0.0), Vector3::repeat(s))
                };
                (
                    f,
                    vec![
                        p(f as f64 + off, 0.0, sigma0),
                        p(0.0, 50.0, 0.01),
                        p(0.0, -50.0, 0.01),
                    ],
                )
            })
            .collect();
        let trajectories = track(frames, parameters()).unwrap();
        let moving = trajectories
            .iter()
            .find(|t| t.points[0].position.y == 0.0)
            .unwrap();
        // At frame 2 the offset point is one frame ahead: it moves the slope.
        moving.points[2].derivatives.velocity.x
    };
    assert_eq!(run(1e-12), run(0.01));
}

/// A particle seen by all 4 cameras moves along x at 1 mm a frame; at
/// frame 5 it is 0.02 mm off its line (2 sigma) and a particle seen by 2
/// cameras (a ghost's profile) sits exactly on the line. The 4-camera
/// point's extra cost (about 3 x 0.02 mm of change of acceleration) is
/// within the penalty of the ghost's two missing cameras (2 x 2 x
/// sqrt(20) |sigma| = 0.15 mm): the trajectory takes it, not the ghost.
/// Without the penalty it takes the ghost.
#[test]
fn a_candidate_seen_by_all_cameras_beats_a_weaker_one_of_similar_cost() {
    let sigma = Vector3::repeat(0.01);
    let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..11)
        .map(|f| {
            let x = f as f64;
            let mut particles = vec![ParticlePosition::seen_by(
                Point3::new(x, if f == 5 { 0.02 } else { 0.0 }, 0.0),
                sigma,
                4,
            )];
            if f == 5 {
                particles.insert(
                    0,
                    ParticlePosition::seen_by(Point3::new(x, 0.0, 0.0), sigma, 2),
                );
            }
            (f, particles)
        })
        .collect();
    let trajectories = track(frames, parameters()).unwrap();
    assert_eq!(trajectories.len(), 1);
    let points = &trajectories[0].points;
    assert_eq!(points.len(), 11);
    let at5 = points.iter().find(|p| p.frame == 5).unwrap();
    assert_eq!(at5.particle, 1, "the 4-camera point, not the ghost");
}

/// Straight-line particles and ghost-like tracks in a 3-camera rig, 2,000
/// frames' worth of evidence in miniature: 100 particles seen by 3
/// cameras with 10% of their points seen by 2 (an image lost at random),
/// and 30 equally smooth tracks seen by 2 cameras only. The ghosts'
/// tracks are dropped, every particle's kept. In a 2-camera rig (all
/// seen by 2) and with unknown camera counts, nothing is dropped: the
/// rule is relative to the rig.
#[test]
fn tracks_of_weak_particles_are_dropped_relative_to_the_rig() {
    let mut rng = simulate::rng(21);
    let lines: Vec<(Point3<f64>, Vector3<f64>)> = (0..130)
        .map(|_| {
            (
                Point3::new(
                    rng.random_range(0.0..100.0),
                    rng.random_range(0.0..100.0),
                    rng.random_range(0.0..100.0),
                ),
                Vector3::new(
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-0.5..0.5),
                ),
            )
        })
        .collect();
    // Per frame, per line, whether an image was lost (drawn once, so the
    // three rigs see the same losses).
    let lost: Vec<Vec<bool>> = (0..20)
        .map(|_| (0..130).map(|_| rng.random_bool(0.1)).collect())
        .collect();
    let run = |rig: usize| {
        let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..20)
            .map(|f| {
                let particles = lines
                    .iter()
                    .enumerate()
                    .map(|(i, (start, v))| {
                        let cameras = match rig {
                            0 => 0,
                            _ if i >= 100 => 2,
                            _ => rig - usize::from(lost[f as usize][i] && rig > 2),
                        };
                        ParticlePosition::seen_by(
                            start + v * f as f64,
                            Vector3::repeat(0.005),
                            cameras,
                        )
                    })
                    .collect();
                (f, particles)
            })
            .collect();
        let trajectories = track(frames, parameters()).unwrap();
        let ghosts = trajectories
            .iter()
            .filter(|t| t.points[0].particle >= 100)
            .count();
        (trajectories.len(), ghosts)
    };
    assert_eq!(run(3), (100, 0), "3 cameras: the ghosts' tracks dropped");
    assert_eq!(run(2), (130, 30), "2 cameras: nothing to tell them apart");
    assert_eq!(run(0), (130, 30), "counts unknown: nothing dropped");
}

#[test]
fn the_binomial_tail_and_the_decision_length() {
    // P(X <= 1) for (3, 0.8): 0.2³ + 3 x 0.8 x 0.2² = 0.104.
    assert!((binomial_cdf(1, 3, 0.8) - 0.104).abs() < 1e-12);
    assert!((binomial_cdf(3, 3, 0.8) - 1.0).abs() < 1e-12);
    assert_eq!(binomial_cdf(0, 4, 1.0), 0.0);
    // 0.2³ = 0.008 < 1%: 3 points; 0.5⁷ < 1% <= 0.5⁶: 7 points.
    assert_eq!(decision_length(0.8, 3), 3);
    assert_eq!(decision_length(0.5, 3), 7);
    assert_eq!(decision_length(1.0, 5), 5);
    assert_eq!(decision_length(0.0, 3), MAX_DECISION_LENGTH);
}

/// At a trajectory's ends the fit window shifts inward and keeps 2w + 1
/// points: the first point's velocity comes from frames 0..=4 (its
/// standard deviation 1.115 sigma for a quadratic, from `(AᵀA)⁻¹` with
/// `t = 0..4`), not from the one-sided 0..=2 (2.550 sigma).
#[test]
fn the_window_keeps_its_points_at_the_ends() {
    let sigma = 0.01;
    let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..10)
        .map(|f| {
            (
                f,
                vec![ParticlePosition::new(
                    Point3::new(f as f64, 0.0, 0.0),
                    Vector3::repeat(sigma),
                )],
            )
        })
        .collect();
    let trajectories = track(frames, parameters()).unwrap();
    let points = &trajectories[0].points;
    for p in [&points[0], &points[9]] {
        let s = p.derivatives.velocity_sigma.x / sigma;
        assert!((s - 1.114835).abs() < 1e-5, "frame {}: {s}", p.frame);
        assert!((p.derivatives.velocity.x - 1.0).abs() < 1e-9);
    }
}

/// A trajectory shorter than its start test's window is tested as one
/// path when it ends: a zig-zag of 3 or 4 points (each link within the
/// search's limits, the path off any quadratic by tens of sigmas: a chain
/// of several particles' points) is dropped, while a real particle's 3 or
/// 4 points on a curved path are kept. The test trusts the sigmas as far
/// as the run's fits bear them out: a particle on a line through all 130
/// frames gives those fits, and without them (a run too short) nothing is
/// tested.
#[test]
fn short_trajectories_that_are_no_path_are_dropped() {
    let sigma = 0.01;
    let noise = Normal::new(0.0, sigma).unwrap();
    let run = |frames: i64, n: i64, offset: &dyn Fn(i64) -> Vector3<f64>| {
        let mut rng = simulate::rng(7);
        let start = frames - 10 - n;
        let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..frames)
            .map(|f| {
                // The long trajectory: on a line 100 mm away, with noise.
                let e = Vector3::from_fn(|_, _| noise.sample(&mut rng));
                let mut here = vec![ParticlePosition::new(
                    Point3::new(0.5 * f as f64, 100.0, 0.0) + e,
                    Vector3::repeat(sigma),
                )];
                if (start..start + n).contains(&f) {
                    let position = Point3::new(f as f64, 0.0, 0.0) + offset(f);
                    here.push(ParticlePosition::new(position, Vector3::repeat(sigma)));
                }
                (f, here)
            })
            .collect();
        let found = track(frames, parameters()).unwrap();
        // The short one, if kept.
        found
            .into_iter()
            .filter(|t| t.points.len() < 20)
            .collect::<Vec<_>>()
    };
    // 0.3 mm to either side in turn: second differences of 0.6 mm per
    // frame², within `max_acceleration` (0.75), 60 sigmas off a line.
    let zigzag = |f: i64| Vector3::new(0.0, 0.3 * (f % 2) as f64, 0.0);
    // The vortex's centripetal acceleration, 0.02 mm per frame².
    let curved = |f: i64| Vector3::new(0.0, 0.01 * ((f % 100) * (f % 100)) as f64, 0.0);
    for n in [3, 4] {
        assert!(run(130, n, &zigzag).is_empty(), "{n} points, zig-zag");
        let kept = run(130, n, &curved);
        assert_eq!(kept.len(), 1, "{n} points, curved");
        assert_eq!(kept[0].points.len(), n as usize);
        // Too few fits to know how far the sigmas hold: kept.
        assert_eq!(run(30, n, &zigzag).len(), 1, "{n} points, short run");
    }
}

/// Points in any order, with numbers far apart, are gathered as a stable
/// sort by (trajectory, frame) would gather them.
#[test]
fn points_are_gathered_by_trajectory_in_frame_order() {
    let mut rng = simulate::rng(15);
    let ids = [7u64, 1 << 40, 3, 0, 12];
    let mut points = Vec::new();
    for (k, &id) in ids.iter().enumerate() {
        for frame in 0..(3 + k as i64) {
            points.push(TrackPoint {
                trajectory: id,
                frame: 100 - 2 * frame,
                particle: rng.random_range(0..1000),
                position: Point3::new(k as f64, frame as f64, 0.0),
                derivatives: Derivatives {
                    velocity: Vector3::zeros(),
                    velocity_sigma: Vector3::zeros(),
                    acceleration: None,
                    acceleration_sigma: None,
                },
            });
        }
    }
    points.shuffle(&mut rng);
    let mut sorted = points.clone();
    sorted.sort_by_key(|p| (p.trajectory, p.frame));
    let gathered = trajectories(points);
    assert_eq!(
        gathered.iter().map(|t| t.id).collect::<Vec<_>>(),
        vec![0, 3, 7, 12, 1 << 40]
    );
    for t in &gathered {
        assert!(t.points.iter().all(|p| p.trajectory == t.id));
    }
    let flat: Vec<TrackPoint> = gathered.into_iter().flat_map(|t| t.points).collect();
    assert_eq!(flat, sorted);
}

/// A link's integer rank orders links as (without a look-ahead partner,
/// cost) does, zero and equal costs included.
#[test]
fn links_rank_as_their_confirmation_and_cost() {
    let mut rng = simulate::rng(16);
    let mut keys: Vec<(bool, f64)> = (0..2000)
        .map(|_| {
            let cost = match rng.random_range(0..4) {
                0 => 0.0,
                1 => 1.0,
                2 => rng.random_range(0.0..1e-300),
                _ => rng.random_range(0.0..1e3),
            };
            (rng.random_bool(0.3), cost)
        })
        .collect();
    keys.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
    for pair in keys.windows(2) {
        let (a, b) = (
            Link::rank(pair[0].0, pair[0].1),
            Link::rank(pair[1].0, pair[1].1),
        );
        assert_eq!(a.cmp(&b), pair[0].partial_cmp(&pair[1]).expect("finite"));
    }
}

/// The grid's search finds exactly the particles within the radius (brute
/// force), and `cell_order` is a permutation in the order of the cells.
#[test]
fn the_grid_finds_what_brute_force_finds_and_orders_by_cell() {
    let mut rng = simulate::rng(17);
    let particles: Vec<ParticlePosition> = (0..3000)
        .map(|_| {
            ParticlePosition::new(
                Point3::from(Vector3::from_fn(|_, _| rng.random_range(-20.0..30.0))),
                Vector3::repeat(0.01),
            )
        })
        .collect();
    let missing: Vec<usize> = (0..particles.len()).map(|i| i % 3).collect();
    let grid = Grid::new(&particles, &missing, 2.5);
    let mut near = Vec::new();
    for _ in 0..300 {
        // Centres also beyond the particles' box, radii across cells.
        let centre = Point3::from(Vector3::from_fn(|_, _| rng.random_range(-30.0..40.0)));
        let radius = rng.random_range(0.1..8.0);
        near.clear();
        grid.within(&centre, radius, &mut near);
        let mut found: Vec<usize> = near.iter().map(|&e| grid.order[e] as usize).collect();
        for &e in &near {
            let i = grid.order[e] as usize;
            assert_eq!(grid.points[e], particles[i].position);
            assert_eq!(grid.missing[e], missing[i]);
        }
        found.sort_unstable();
        let expected: Vec<usize> = (0..particles.len())
            .filter(|&i| (particles[i].position - centre).norm_squared() <= radius * radius)
            .collect();
        assert_eq!(found, expected);
    }
    let queries: Vec<Point3<f64>> = (0..500)
        .map(|_| Point3::from(Vector3::from_fn(|_, _| rng.random_range(-30.0..40.0))))
        .collect();
    let order = grid.cell_order(queries.iter().copied());
    let mut seen = order.clone();
    seen.sort_unstable();
    assert_eq!(seen, (0..queries.len() as u32).collect::<Vec<_>>());
    let keys: Vec<usize> = order
        .iter()
        .map(|&i| grid.key(&grid.cell_of(&queries[i as usize])))
        .collect();
    assert!(keys.windows(2).all(|k| k[0] <= k[1]));
}

/// A particle that vanishes (it left the light sheet) while other
/// particles appear near its prediction, each for one frame only: the
/// trajectory goes on through them (each is within the search's limits),
/// but its path breaks there, so it is cut where it left its particle and
/// the chain of others' points is not reported with it, nor as a
/// trajectory long enough to be tested. Its first part keeps every one of
/// its points.
#[test]
fn a_trajectory_that_loses_its_particle_is_cut_and_the_chain_dropped() {
    for seed in 0..50 {
        lost_particle_is_cut(seed);
    }
}

fn lost_particle_is_cut(seed: u64) {
    let sigma = Vector3::repeat(0.005);
    let mut rng = simulate::rng(seed);
    let path = |f: f64| Point3::new(f, 0.02 * f * f, 0.0);
    let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..24)
        .map(|f| {
            let position = if f < 12 {
                path(f as f64)
            } else {
                // 0.4..0.7 mm from where the lost particle would be: inside
                // the search radius (max_acceleration 0.75 mm), and beyond
                // what the test can tell from the particle (the cubic
                // through 4 points extrapolated one frame has a standard
                // deviation of sqrt(69) sigma, 0.04 mm; the gross level's
                // χ²(3) quantile, about 30, puts the limit near 0.25 mm).
                let direction = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
                .normalize();
                path(f as f64) + direction * rng.random_range(0.4..0.7)
            };
            (f, vec![ParticlePosition::new(position, sigma)])
        })
        .collect();
    let trajectories = track(frames, TrackingParameters::new(1.5)).unwrap();
    let frames: Vec<Vec<i64>> = trajectories
        .iter()
        .map(|t| t.points.iter().map(|p| p.frame).collect())
        .collect();
    assert_eq!(
        frames[0],
        (0..12).collect::<Vec<_>>(),
        "seed {seed}: {frames:?}"
    );
    // What else is reported is too short to be tested (fewer than 2 w + 1
    // points: the chain's points linked anew, as any trajectory of 3 or 4
    // points may be; the cubic needs 5 to have redundancy).
    for other in &frames[1..] {
        assert!(other.len() < 5, "seed {seed}: {frames:?}");
    }
}

/// [`Grid::nearest`] gives the `k` nearest accepted entries within the
/// reach, as brute force does (ties by entry), whatever the cells' size
/// against the reach: cells of the search's size, and the cells a limit
/// of 10^308 mm leaves after the cap by the particles' spacing.
#[test]
fn nearest_finds_what_brute_force_finds() {
    let mut rng = simulate::rng(29);
    let particles: Vec<ParticlePosition> = (0..2000)
        .map(|_| {
            ParticlePosition::new(
                Point3::from(Vector3::from_fn(|_, _| rng.random_range(-20.0..30.0))),
                Vector3::repeat(0.01),
            )
        })
        .collect();
    let missing = vec![0; particles.len()];
    for cell in [2.5, 1e308] {
        let grid = Grid::new(&particles, &missing, cell);
        assert!(
            grid.cell < 10.0,
            "cells capped by the spacing: {}",
            grid.cell
        );
        let mut out = Vec::new();
        for round in 0..300 {
            let centre = Point3::from(Vector3::from_fn(|_, _| rng.random_range(-35.0..45.0)));
            let reach = if round % 3 == 0 {
                f64::INFINITY
            } else {
                rng.random_range(0.1..40.0)
            };
            let k = rng.random_range(1..40);
            let accept = |e: usize| grid.order[e] % 3 != 0;
            grid.nearest(&centre, reach, k, accept, &mut out);
            let mut expected: Vec<(f64, usize)> = (0..grid.points.len())
                .map(|e| ((grid.points[e] - centre).norm_squared(), e))
                .filter(|&(d2, e)| d2 <= reach * reach && accept(e))
                .collect();
            expected.sort_by(|a, b| a.partial_cmp(b).unwrap());
            expected.truncate(k);
            assert_eq!(out, expected, "cell {cell}, round {round}");
        }
    }
}

/// Limits as large as any volume: every particle is within every
/// search, and the searches keep the nearest [`MAX_CANDIDATES`]. 2,000
/// particles a frame in straight lines 5 mm apart (0.4 mm per frame) are
/// still linked right, each into one trajectory, and in bounded work: the
/// whole run takes about the time of one at a sane limit, where all
/// candidates before this bound made it `N³` a frame (8·10^9 link costs).
#[test]
fn limits_as_large_as_any_volume_track_right_in_bounded_work() {
    let mut rng = simulate::rng(8);
    let count = 2000;
    let starts: Vec<Point3<f64>> = (0..count)
        .map(|_| Point3::from(Vector3::from_fn(|_, _| rng.random_range(0.0..60.0))))
        .collect();
    let velocities: Vec<Vector3<f64>> = (0..count)
        .map(|_| Vector3::from_fn(|_, _| rng.random_range(-0.23..0.23)))
        .collect();
    let frames: Vec<(i64, Vec<ParticlePosition>)> = (0..6)
        .map(|f| {
            let mut particles: Vec<(usize, ParticlePosition)> = starts
                .iter()
                .zip(&velocities)
                .enumerate()
                .map(|(i, (s, v))| {
                    (
                        i,
                        ParticlePosition::new(s + v * f as f64, Vector3::repeat(0.005)),
                    )
                })
                .collect();
            particles.shuffle(&mut rng);
            (f, particles.into_iter().map(|(_, p)| p).collect())
        })
        .collect();
    let run = |parameters: TrackingParameters| {
        let started = std::time::Instant::now();
        let trajectories = track(frames.clone(), parameters).unwrap();
        (trajectories, started.elapsed())
    };
    let (sane, sane_time) = run(TrackingParameters::new(0.5));
    let (largest, largest_time) = run(TrackingParameters::new(MAX_DISPLACEMENT));
    println!("sane limit {sane_time:?}, the largest {largest_time:?}");
    for trajectories in [&sane, &largest] {
        assert_eq!(trajectories.len(), count, "one trajectory per particle");
        assert!(trajectories.iter().all(|t| t.points.len() == 6));
        // Each trajectory moves in a straight line: its points are one
        // particle's.
        for t in trajectories.iter() {
            let step = t.points[1].position - t.points[0].position;
            for pair in t.points.windows(2) {
                let d = pair[1].position - pair[0].position - step;
                assert!(d.norm() < 1e-9, "a link to another particle");
            }
        }
    }
    // The searches at the largest limit read a few hundred cells and
    // MAX_CANDIDATES look-aheads where the sane ones read a few cells and
    // one or two: within 100 times the time, where all candidates took
    // 2,000² = 4·10^6 times the work of one each.
    assert!(
        largest_time < sane_time * 100 + std::time::Duration::from_secs(1),
        "sane {sane_time:?}, largest {largest_time:?}"
    );
}

#[test]
fn limits_are_bounded_by_the_volume_and_the_largest_one() {
    let volume = Volume {
        min: Point3::new(-30.0, -30.0, -10.0),
        max: Point3::new(30.0, 30.0, 10.0),
    };
    let diagonal = (volume.max - volume.min).norm(); // 87.2 mm
    let at = |v: f64, a: f64| TrackingParameters {
        max_velocity: v,
        max_acceleration: a,
        ..TrackingParameters::new(v)
    };
    assert!(at(diagonal, 2.0 * diagonal).check_volume(&volume).is_ok());
    assert!(at(2.0, 1.0).check_volume(&volume).is_ok());
    let error = at(1e308, 1.0).validate().unwrap_err().to_string();
    assert!(
        error.contains("max_velocity 1e308") && error.contains("1000000 mm"),
        "{error}"
    );
    let error = at(diagonal * 1.01, 1.0)
        .check_volume(&volume)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("max_velocity 88.")
            && error.contains("the diagonal of the observation volume")
            && error.contains("x -30..30, y -30..30, z -10..10 mm"),
        "{error}"
    );
    let error = at(1.0, 2.0 * diagonal * 1.01)
        .check_volume(&volume)
        .unwrap_err()
        .to_string();
    assert!(error.contains("max_acceleration 176."), "{error}");
    let error = at(1.0, 2.0e6 * 1.5).validate().unwrap_err().to_string();
    assert!(error.contains("max_acceleration 3000000"), "{error}");
    // An unbounded axis (OpenPTV's depth-only bounds) bounds nothing.
    let open = Volume {
        min: Point3::new(-30.0, f64::NEG_INFINITY, -10.0),
        ..volume
    };
    assert!(at(1e5, 1.0).check_volume(&open).is_ok());
    let error = TrackingParameters {
        min_length: MAX_MIN_LENGTH + 1,
        ..TrackingParameters::new(1.0)
    }
    .validate()
    .unwrap_err()
    .to_string();
    assert!(error.contains("min_length 101"), "{error}");
}

/// Particles entering the vortex mid-sequence whose second image is lost:
/// forward, a trajectory of one point does not bridge a gap (it has no
/// velocity to predict with), so each starts two frames late, at its third
/// point. Backward tracking predicts from the first two points it has, over
/// the gap, and takes the entering point back: every such trajectory then
/// starts where its particle did, with no wrong link, and its first
/// points' velocities are fitted again.
#[test]
fn backward_tracking_recovers_the_starts_forward_tracking_picks_up_late() {
    let noise = 0.01;
    let frames = 30;
    let mut scene = vortex(3000, frames, noise, 0.0, 0, 41);
    // Every 10th particle enters at frame 5 + (i / 10) % 15, and its image
    // of the frame after is lost.
    let birth = |i: usize| (i % 10 == 0).then_some(5 + ((i / 10) % 15) as i64);
    for (f, (number, particles)) in scene.frames.iter_mut().enumerate() {
        let keep: Vec<bool> = scene.truth[f]
            .iter()
            .map(|t| match t.and_then(birth) {
                Some(b) => *number >= b && *number != b + 1,
                None => true,
            })
            .collect();
        let mut k = keep.iter();
        particles.retain(|_| *k.next().unwrap());
        let mut k = keep.iter();
        scene.truth[f].retain(|_| *k.next().unwrap());
    }
    let entering = (0..3000).filter(|&i| birth(i).is_some()).count();
    let starts_at_birth = |trajectories: &[Trajectory]| {
        trajectories
            .iter()
            .filter(|t| {
                let first = &t.points[0];
                let id = scene.truth[first.frame as usize][first.particle];
                id.and_then(birth) == Some(first.frame)
            })
            .count()
    };

    let forward = track(scene.frames.clone(), parameters()).unwrap();
    assert_eq!(
        starts_at_birth(&forward),
        0,
        "forward, every one starts late"
    );

    let (both, added) = track_both_ways(scene.frames.clone(), parameters()).unwrap();
    let (all, correct) = links(&scene, &both);
    assert_eq!(correct, all, "every link joins one particle");
    // A right addition is refused where its fit window is inconsistent at
    // 99.9% (`kinematics::is_consistent`): of 300, 0.3 expected; more than
    // 3 has probability 3e-4 (Poisson).
    let recovered = starts_at_birth(&both);
    assert!(recovered + 3 >= entering, "{recovered} of {entering}");
    assert_eq!(
        added,
        BackwardSummary {
            points: recovered,
            lengthened: recovered,
            joined: 0
        }
    );
    assert_eq!(both.len(), forward.len(), "no trajectory lost or split");
    assert!(both
        .iter()
        .all(|t| t.points.windows(2).all(|w| w[0].frame < w[1].frame)));
    // The first points' velocities (one-sided windows across the gap) are
    // fitted again: each within 5 of its own sigmas of the truth per axis
    // (a Gaussian error beyond 5 sigma has probability 6e-7; 300 entering
    // points x 3 axes make a false failure about 5e-4 likely; the
    // quadratic's bias on the circle, omega³ r / 6 times a few frames², is
    // under 1e-3 mm per frame against sigmas near 0.01).
    for t in &both {
        let first = &t.points[0];
        let Some(id) = scene.truth[first.frame as usize][first.particle] else {
            continue;
        };
        if birth(id) != Some(first.frame) {
            continue;
        }
        let truth = true_position(&scene.starts[id], first.frame);
        let d = &first.derivatives;
        let error = (d.velocity - true_velocity(&truth)).component_div(&d.velocity_sigma);
        assert!(error.amax() < 5.0, "{error:?} at {truth:?}");
    }
    // Points of trajectories nobody extended are as the forward pass gave
    // them.
    let forward_points: usize = forward.iter().map(|t| t.points.len()).sum();
    let both_points: usize = both.iter().map(|t| t.points.len()).sum();
    assert_eq!(both_points, forward_points + recovered);
}

/// A particle that enters at frame 5, its image of frame 4 lost, with
/// another particle in frame 3 near where its path extrapolates: 0.5 mm
/// (50 sigma) off it. Backward, the decoy is within the search and the
/// forward pass's start tests pass it: the cubic through it and the first
/// 4 points (one degree of freedom per axis, the gap giving the decoy
/// almost all the leverage) takes up the offset, its χ² far under the
/// gross-error level. The quadratic that fits its velocity does not: its
/// window is inconsistent at the fits' own 99.9%, and the decoy is not
/// added. Where the particle itself is seen in frame 3, it is.
#[test]
fn backward_tracking_adds_no_point_its_own_fit_would_doubt() {
    let noise = 0.01;
    let velocity = Vector3::new(1.0, 0.2, 0.3);
    let start = Point3::new(10.0, 20.0, 30.0);
    let normal = Normal::new(0.0, noise).unwrap();
    let mut rng = simulate::rng(47);
    let scene = |at_three: Point3<f64>, rng: &mut rand::rngs::StdRng| {
        (0..20i64)
            .map(|n| {
                let particles = match n {
                    3 => vec![ParticlePosition::new(at_three, Vector3::repeat(noise))],
                    5.. => {
                        let jitter = Vector3::from_fn(|_, _| normal.sample(rng));
                        vec![ParticlePosition::new(
                            start + velocity * n as f64 + jitter,
                            Vector3::repeat(noise),
                        )]
                    }
                    _ => Vec::new(),
                };
                (n, particles)
            })
            .collect::<Vec<_>>()
    };
    let on_path = start + velocity * 3.0;
    let decoy = on_path + Vector3::new(0.0, 0.5, 0.0);
    let frames = scene(decoy, &mut rng);
    // The forward pass's start tests pass the decoy: its window is smooth
    // at the gross-error level and its point no intruder.
    let window: Vec<Sample> = std::iter::once((3, decoy))
        .chain((5..9).map(|n| (n, frames[n as usize].1[0].position)))
        .map(|(frame, position)| Sample {
            frame,
            position: position.coords,
            sigma: Vector3::repeat(noise),
        })
        .collect();
    assert!(is_smooth(&window, 3));
    assert!(!end_is_intruder(&window, true, 2, 2));
    assert!(!kinematics::is_consistent(&window, 2));

    let (forward, _) = (track(frames.clone(), parameters()).unwrap(), ());
    assert_eq!(forward.len(), 1);
    assert_eq!(forward[0].points[0].frame, 5);
    let (both, added) = track_both_ways(frames, parameters()).unwrap();
    assert_eq!(added, BackwardSummary::default(), "the decoy is not added");
    assert_eq!(both.len(), 1);
    assert_eq!(both[0].points[0].frame, 5);

    // The particle itself in frame 3 is added.
    let frames = scene(on_path, &mut rng);
    let (both, added) = track_both_ways(frames, parameters()).unwrap();
    assert_eq!(added.points, 1, "{added:?}");
    assert_eq!(both[0].points[0].frame, 3);
}

/// The pass over a run tracked forward and held elsewhere (the service's
/// store: the frames' particles as given, every point handed out) gives
/// what the tracker's own pass gives: the same trajectories (as point
/// lists: the numbers are the forward pass's, not renumbered), the same
/// derivatives, and the same summary. With a skipped frame number (an
/// empty frame to both), dropout and spurious points (no join happens
/// here: the service's test compares its joins, where there are any, with
/// `ptv track --backward`'s).
#[test]
fn the_pass_over_a_stored_run_is_the_trackers_own() {
    let mut scene = vortex(2000, 24, 0.02, 0.08, 40, 43);
    scene.frames.retain(|(n, _)| *n != 11);
    let forward = {
        let mut tracker = Tracker::new(parameters()).unwrap();
        let mut points = Vec::new();
        for (n, particles) in scene.frames.clone() {
            points.extend(tracker.push(n, particles).unwrap());
        }
        points.extend(tracker.finish());
        points
    };
    let (both, added) = track_both_ways(scene.frames.clone(), parameters()).unwrap();
    assert!(added.points > 100, "{added:?}");
    let frames: Vec<backward::RunFrame> = scene
        .frames
        .iter()
        .map(|(n, particles)| backward::RunFrame {
            number: *n,
            given: particles.len(),
            particles: particles.clone(),
        })
        .collect();
    let forward_ids: std::collections::HashSet<u64> =
        forward.iter().map(|p| p.trajectory).collect();
    let (points, summary) = backward::extend_run(frames.clone(), forward, &parameters()).unwrap();
    assert_eq!(summary, added);
    let stored = trajectories(points);
    // Numbers kept: every one is a forward trajectory's; the joined ones
    // are gone.
    assert!(stored.iter().all(|t| forward_ids.contains(&t.id)));
    assert_eq!(stored.len() + added.joined, forward_ids.len());
    let key = |t: &Trajectory| {
        t.points
            .iter()
            .map(|p| (p.frame, p.particle))
            .collect::<Vec<_>>()
    };
    let mut a: Vec<_> = stored.iter().map(|t| (key(t), t)).collect();
    let mut b: Vec<_> = both.iter().map(|t| (key(t), t)).collect();
    a.sort_by(|x, y| x.0.cmp(&y.0));
    b.sort_by(|x, y| x.0.cmp(&y.0));
    assert_eq!(a.len(), b.len());
    for ((ka, ta), (kb, tb)) in a.iter().zip(&b) {
        assert_eq!(ka, kb);
        for (p, q) in ta.points.iter().zip(&tb.points) {
            assert_eq!(p.position, q.position);
            // Bit-equal where both are numbers (NaN for no fit).
            let same = |x: Vector3<f64>, y: Vector3<f64>| {
                x.iter()
                    .zip(y.iter())
                    .all(|(a, b)| a == b || (a.is_nan() && b.is_nan()))
            };
            assert!(same(p.derivatives.velocity, q.derivatives.velocity));
        }
    }
    // A point of no frame given is refused, naming it.
    let (mut points, _) = (Vec::new(), ());
    points.push(TrackPoint {
        trajectory: 7,
        frame: 11,
        particle: 0,
        position: Point3::origin(),
        derivatives: backward_unfitted(),
    });
    let error = backward::extend_run(frames, points, &parameters()).unwrap_err();
    assert!(error.to_string().contains("trajectory 7"), "{error}");
}

fn backward_unfitted() -> Derivatives {
    Derivatives {
        velocity: Vector3::repeat(f64::NAN),
        velocity_sigma: Vector3::repeat(f64::NAN),
        acceleration: None,
        acceleration_sigma: None,
    }
}
