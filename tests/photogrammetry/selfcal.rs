//! Self-calibration (`photogrammetry::selfcal`) on simulated rigs whose
//! calibration is off, against the true cameras; and on the real
//! test_cavity recording with OpenPTV's targets.
//!
//! Run with `cargo test --test photogrammetry selfcal -- --nocapture` to see
//! the figures.

use nalgebra::{Matrix3, Point3, Vector3};
use rand::Rng;

use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
use ptv::photogrammetry::selfcal::{
    self_calibrate, Outcome, SelfCalibration, SelfCalibrationError, SelfCalibrationOptions,
};
use ptv::photogrammetry::simulate::{self, RigSpec};
use ptv::photogrammetry::{intersect, Camera, CameraParameters, Cancel, Observation, Target};

/// The true rig: 4 convergent cameras through a glass wall into water.
fn true_rig() -> (RigSpec, Vec<Camera>) {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().expect("the simulated rig");
    (spec, cameras)
}

/// Each camera moved by `shift_mm` in a random direction and turned by
/// `turn_rad` about a random axis.
fn disturbed(cameras: &[Camera], shift_mm: f64, turn_rad: f64, seed: u64) -> Vec<CameraParameters> {
    let mut rng = simulate::rng(seed);
    let mut unit = || {
        let v = Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0));
        v.normalize()
    };
    cameras
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.exterior.position += unit() * shift_mm;
            let e = &p.exterior;
            let turn = nalgebra::Rotation3::from_scaled_axis(unit() * turn_rad);
            let r = turn.matrix() * rotation_matrix(e.omega, e.phi, e.kappa);
            let (omega, phi, kappa) = rotation_angles(&r);
            p.exterior.omega = omega;
            p.exterior.phi = phi;
            p.exterior.kappa = kappa;
            p
        })
        .collect()
}

/// `frames` frames of `count` particles, 0.1 px noise, no dropout.
fn frames(
    spec: &RigSpec,
    cameras: &[Camera],
    frames: usize,
    count: usize,
) -> Vec<Vec<Vec<Target>>> {
    let mut rng = simulate::rng(7);
    (0..frames)
        .map(|_| {
            let points = simulate::particles(&spec.volume, count, &mut rng);
            simulate::target_frame(cameras, &points, 0.1, 0.0, &mut rng).targets
        })
        .collect()
}

/// The best similarity `s R x + t` from `from` to `to` (Umeyama 1991), and
/// the RMS 3D distance after it (mm).
fn similarity_rms(from: &[Point3<f64>], to: &[Point3<f64>]) -> f64 {
    let n = from.len() as f64;
    let mf = from.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    let mt = to.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    let mut var = 0.0;
    for (a, b) in from.iter().zip(to) {
        cov += (b.coords - mt) * (a.coords - mf).transpose();
        var += (a.coords - mf).norm_squared();
    }
    cov /= n;
    var /= n;
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    let s = (svd.singular_values.component_mul(&d.diagonal())).sum() / var;
    let t = mt - s * r * mf;
    let sq: f64 = from
        .iter()
        .zip(to)
        .map(|(a, b)| (s * r * a.coords + t - b.coords).norm_squared())
        .sum();
    (sq / n).sqrt()
}

/// Noise-free true points imaged by the true cameras, intersected with
/// `rig`: (RMS reprojection residual px, RMS 3D error after the best
/// similarity mm).
fn accuracy(spec: &RigSpec, truth: &[Camera], rig: &[CameraParameters]) -> (f64, f64) {
    let rig: Vec<Camera> = rig
        .iter()
        .map(|p| Camera::new(p.clone()).unwrap())
        .collect();
    let mut rng = simulate::rng(99);
    let points = simulate::particles(&spec.volume, 2000, &mut rng);
    let (mut sq, mut count) = (0.0, 0);
    let (mut from, mut to) = (Vec::new(), Vec::new());
    for p in &points {
        let observations: Vec<Observation> = truth
            .iter()
            .enumerate()
            .map(|(camera, c)| Observation {
                camera,
                pixel: c.project(p).unwrap(),
            })
            .collect();
        let x = intersect(&rig, &observations).expect("a point of the volume intersects");
        for r in &x.residuals_px {
            sq += r.norm_squared();
            count += 1;
        }
        from.push(x.point);
        to.push(*p);
    }
    ((sq / count as f64).sqrt(), similarity_rms(&from, &to))
}

fn run(rough: &[CameraParameters], frames: &[Vec<Vec<Target>>], band: f64) -> SelfCalibration {
    let options = SelfCalibrationOptions {
        start_tolerance_px: band,
        ..SelfCalibrationOptions::default()
    };
    self_calibrate(rough, frames, &options, &Cancel::new(), &mut |_| {}).expect("self-calibrates")
}

fn print(label: &str, result: &SelfCalibration) {
    for r in &result.report.rounds {
        println!(
            "{label}: band {:.2} px, matched {:?}, selected {}, rejected {}, rms {:.3} -> {:.3} px",
            r.band_px,
            r.matched_by_cameras,
            r.selected,
            r.rejected,
            r.rms_before_px,
            r.rms_after_px
        );
    }
    for c in &result.report.cameras {
        println!(
            "{label}: {}: disparity rms {:.3} -> {:.3} px, median {:.3} -> {:.3} px",
            c.name, c.before.rms_px, c.after.rms_px, c.before.median_px, c.after.median_px
        );
    }
    println!("{label}: gauge {:?}", result.report.gauge);
}

/// Issue 14's goal for the disturbances: noise-free true points, imaged
/// by the true cameras and intersected with the refined rig, reproject
/// within 0.05 px RMS and lie within `max_um` um RMS of the truth after
/// the best similarity (the goal: 10 um; the gauge is the input's, not the
/// truth's).
///
/// Why the image bound holds with margin: 20,000 particles of 0.1 px
/// noise in 4 cameras determine each camera's parameters to about 0.1 px
/// / sqrt(5,000 particles per cell of parameters) ~ 0.002 px of image
/// effect. What is left in 3D is the similarity the gauge keeps from the
/// input, which the walls' refraction makes not quite a symmetry: it grows
/// with the disturbance (see the 2 mm test).
fn check(label: &str, shift_mm: f64, turn_rad: f64, band: f64, min_before_px: f64, max_um: f64) {
    let (spec, truth) = true_rig();
    let rough = disturbed(&truth, shift_mm, turn_rad, 3);
    let frames = frames(&spec, &truth, 10, 2000);
    let (before_px, before_mm) = accuracy(&spec, &truth, &rough);
    let result = run(&rough, &frames, band);
    print(label, &result);
    let (after_px, after_mm) = accuracy(&spec, &truth, &result.cameras);
    println!(
        "{label}: true points through the rig: {before_px:.4} -> {after_px:.4} px RMS, {:.2} -> {:.2} um RMS after the best similarity",
        before_mm * 1e3,
        after_mm * 1e3
    );
    assert_ne!(
        result.report.outcome,
        Outcome::Diverged,
        "{:?}",
        result.report.message
    );
    assert!(before_px > min_before_px, "the disturbance: {before_px}");
    assert!(after_px < 0.05, "{after_px}");
    assert!(after_mm < max_um * 1e-3, "{after_mm}");
}

/// A rig moved by 0.1 mm and 0.1 mrad per camera: true points through it
/// reproject at about 0.5 px RMS, and a 1 px band matches them (1,984 of
/// 2,000 correct at 8 px, measured). After: 0.018 px and the figures below
/// (measured in the dev profile in 6 s).
#[test]
fn simulated_rig_moved_by_0_1_mm_and_0_1_mrad() {
    check("0.1 mm, 0.1 mrad", 0.1, 1e-4, 1.0, 0.2, 10.0);
}

/// Issue 14's goal: a rig moved by 0.7 mm and 1 mrad per camera (true
/// points through it reproject at 4.7 px RMS, 1.2-6.3 px per camera). The
/// first round votes pairwise in an 8 px band (`selfcal/vote.rs`) and keeps
/// 863 groups; the rounds after it match at 0.5 px. Measured: 0.010 px
/// and 6.2 um after (14 s in the test profile).
#[test]
fn simulated_rig_moved_by_0_7_mm_and_1_mrad() {
    check("0.7 mm, 1 mrad", 0.7, 1e-3, 8.0, 0.5, 10.0);
}

/// A rig moved by 2 mm and 3 mrad per camera (true points through it
/// reproject at 13.8 px RMS, 3-18.5 px per camera): the first round votes
/// in a 20 px band and keeps 777 groups, the rounds after it match at
/// 0.5 px. Measured: 0.0157 px RMS after (the 0.05 px goal reached), but
/// 18.2 um after the best similarity: issue 14's 10 um is NOT REACHED for
/// this disturbance. The 3D error grows linearly with the disturbance
/// (6.2 um at 0.7 mm, 18.2 um at 2 mm) while the image fit stays at the
/// noise: the gauge keeps the input's similarity, and through the walls a
/// similarity of the rig is not a symmetry, so the part of the
/// disturbance along it stays. The reduced normal matrix shows 4 free
/// directions and 3 weak ones (sigma 0.09, 0.25 and 1.0 mm); freeing the
/// two best determined (tried) made it worse (19.8 um). Asserted: the
/// image goal, and the 3D level reached with a margin (25 um).
#[test]
fn simulated_rig_moved_by_2_mm_and_3_mrad() {
    check("2 mm, 3 mrad", 2.0, 3e-3, 20.0, 0.5, 25.0);
}

/// Self-calibrates the true rig with its media changed by `disturb`, the
/// cameras exact, with `terms` free: the result, the true points' RMS
/// reprojection through the rough and the refined rig (px).
fn media_case(
    label: &str,
    disturb: impl Fn(&mut CameraParameters),
    terms: Vec<ptv::photogrammetry::selfcal::MediaTerm>,
) -> (SelfCalibration, f64, f64) {
    let (spec, truth) = true_rig();
    let rough: Vec<CameraParameters> = truth
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            disturb(&mut p);
            p
        })
        .collect();
    let frames = frames(&spec, &truth, 10, 2000);
    let (before_px, _) = accuracy(&spec, &truth, &rough);
    let options = SelfCalibrationOptions {
        start_tolerance_px: 1.0_f64.max(2.0 * before_px),
        free_media: terms,
        ..SelfCalibrationOptions::default()
    };
    let result = self_calibrate(&rough, &frames, &options, &Cancel::new(), &mut |_| {})
        .expect("self-calibrates");
    print(label, &result);
    for m in &result.report.media {
        println!("{label}: {m:?}");
    }
    let (after_px, after_mm) = accuracy(&spec, &truth, &result.cameras);
    println!(
        "{label}: true points through the rig {before_px:.4} -> {after_px:.4} px RMS, {:.2} um \
         after the best similarity",
        after_mm * 1e3
    );
    assert_ne!(result.report.outcome, Outcome::Diverged);
    (result, before_px, after_px)
}

/// The glass vector as an unknown. The true rig has one wall, shared by
/// the 4 cameras, 100 mm from the centre (glass vector (0, 0, 100)).
///
/// 1. The wall tilted by 3 mrad (0.3 mm at 100 mm), its distance exact
///    (true points through the rough rig: 0.21 px RMS).
/// 2. Tilted and moved 1.5 mm along its normal (0.46 px).
///
/// The tilt (x, y) comes back: measured errors 0.027 and 0.026 mm (2.7 and
/// 1.4 sigma) in case 1, 0.033 and 0.051 mm (3.1 and 2.7 sigma) in case 2,
/// sigma from the adjustment at 0.1 px noise; asserted within 4 sigma and
/// 0.1 mm (a third of the tilt). The distance (z) of this one-sided rig
/// trades against the cameras' exterior (measured: correlation 0.999 with a
/// camera's phi under the gauge, in both cases), so the rule holds it and
/// says why, and the cameras absorb it: true points through the refined rig
/// reproject within issue 14's 0.05 px (measured 0.021 px; the 0.1 px noise
/// over 20,000 particles leaves ~0.002 px).
#[test]
fn simulated_glass_vector_is_recovered() {
    use ptv::photogrammetry::calibrate::ParameterStatus;
    use ptv::photogrammetry::selfcal::MediaTerm;
    let true_glass = Vector3::new(0.0, 0.0, 100.0);
    let tilt = nalgebra::Rotation3::from_scaled_axis(Vector3::new(3e-3, 0.0, 0.0));
    for (label, shift) in [("glass tilt", 0.0), ("glass tilt+shift", 1.5)] {
        let (result, before_px, after_px) = media_case(
            label,
            |p| {
                assert!(
                    (p.media.glass_vector - true_glass).norm() < 1e-9,
                    "one wall"
                );
                let g = p.media.glass_vector;
                p.media.glass_vector = tilt * (g + g.normalize() * shift);
            },
            vec![MediaTerm::Glass],
        );
        assert_eq!(result.report.media.len(), 3, "one wall: x, y, z");
        // The tilt (x, y: the wall's normal) is determined and recovered.
        for (axis, m) in result.report.media.iter().enumerate().take(2) {
            assert_eq!(m.status, ParameterStatus::Free, "{label}: {m:?}");
            let sigma = m.sigma.expect("a sigma");
            let error = (m.after - true_glass[axis]).abs();
            println!(
                "{label}: {} error {error:.4} mm = {:.2} sigma",
                m.name,
                error / sigma
            );
            assert!(
                error <= 4.0 * sigma && error < 0.1,
                "{label}: {m:?}: error {error}"
            );
        }
        let z = &result.report.media[2];
        match z.status {
            ParameterStatus::Free => {
                let sigma = z.sigma.expect("a sigma");
                assert!(
                    (z.after - true_glass[2]).abs() <= 4.0 * sigma,
                    "{label}: {z:?}"
                );
            }
            _ => assert!(
                z.reason
                    .as_deref()
                    .is_some_and(|r| r.contains("correlation")),
                "{label}: {z:?}"
            ),
        }
        assert!(before_px > 0.15, "{label}: the disturbance: {before_px}");
        assert!(after_px < 0.05, "{label}: {after_px}");
    }
}

/// The object medium's index as an unknown: the true water's index given
/// 0.02 higher in the rough rig (true points through it: 0.54 px RMS).
/// Either it is determined and comes back within 4 sigma, or the rule
/// holds it with the reason (a change of index acts much as a change of the
/// cameras' distance); in both cases the refined rig must reproject true
/// points within 0.05 px (issue 14's goal). Measured: determined, back to
/// 0.0006 of the truth (sigma 0.0005), true points at 0.013 px.
#[test]
fn simulated_object_index_is_recovered_or_held_with_the_reason() {
    use ptv::photogrammetry::calibrate::ParameterStatus;
    use ptv::photogrammetry::selfcal::MediaTerm;
    let (_, truth) = true_rig();
    let n_true = truth[0].parameters().media.n_object;
    let (result, before_px, after_px) = media_case(
        "n_object",
        |p| p.media.n_object += 0.02,
        vec![MediaTerm::ObjectIndex],
    );
    assert_eq!(result.report.media.len(), 1);
    let m = &result.report.media[0];
    match m.status {
        ParameterStatus::Free => {
            let sigma = m.sigma.expect("a sigma");
            assert!((m.after - n_true).abs() <= 4.0 * sigma, "{m:?}");
        }
        _ => assert!(
            m.reason
                .as_deref()
                .is_some_and(|r| r.contains("correlation")),
            "{m:?}"
        ),
    }
    assert!(before_px > 0.3, "the disturbance: {before_px}");
    assert!(after_px < 0.05, "{after_px}");
}

#[test]
fn too_few_particles_say_how_many_and_the_band() {
    let (spec, truth) = true_rig();
    let frames = frames(&spec, &truth, 1, 30);
    let rough: Vec<CameraParameters> = truth.iter().map(|c| c.parameters().clone()).collect();
    let error = self_calibrate(
        &rough,
        &frames,
        &SelfCalibrationOptions::default(),
        &Cancel::new(),
        &mut |_| {},
    )
    .unwrap_err();
    assert!(
        matches!(error, SelfCalibrationError::TooFewParticles { selected, band_px, .. } if selected <= 30 && band_px == 4.0),
        "{error}"
    );
    let message = error.to_string();
    assert!(
        message.contains("4 px") && message.contains("at least 100"),
        "{message}"
    );
}

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv");

/// The recording's OpenPTV targets of frames 10001-10004, per frame per
/// camera.
fn cavity_frames() -> Vec<Vec<Vec<Target>>> {
    (10001..=10004)
        .map(|frame| {
            (1..=4)
                .map(|k| {
                    let path = std::path::Path::new(DATA).join(format!(
                        "golden/test_cavity_recording/cam{k}.{frame}_targets"
                    ));
                    ptv::formats::parse_targets(
                        &ptv::formats::read_text(&path).unwrap(),
                        &path.display().to_string(),
                    )
                    .unwrap()
                })
                .collect()
        })
        .collect()
}

/// Per frame, 4-camera particles and the median RMS of all particles
/// matched with `band`.
fn cavity_counts(cameras: &[Camera], frames: &[Vec<Vec<Target>>], band: f64) -> Vec<(usize, f64)> {
    use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
    let matcher = Matcher::new(
        cameras,
        &MatchingParameters {
            tolerance: band,
            ..MatchingParameters::default()
        },
    )
    .unwrap();
    frames
        .iter()
        .map(|f| {
            let particles = matcher.match_frame(f).unwrap();
            let mut rms: Vec<f64> = particles.iter().map(|p| p.rms_px).collect();
            rms.sort_by(f64::total_cmp);
            let median = rms.get(rms.len() / 2).copied().unwrap_or(0.0);
            (
                particles.iter().filter(|p| p.camera_count() == 4).count(),
                median,
            )
        })
        .collect()
}

/// Particles of all frames matched with `band`, 4-camera ones by their RMS
/// (px): below 0.5, 0.5-1, 1-2, 2-4, above 4.
fn cavity_rms_histogram(cameras: &[Camera], frames: &[Vec<Vec<Target>>], band: f64) -> [usize; 5] {
    use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
    let matcher = Matcher::new(
        cameras,
        &MatchingParameters {
            tolerance: band,
            ..MatchingParameters::default()
        },
    )
    .unwrap();
    let mut h = [0; 5];
    for f in frames {
        for p in matcher.match_frame(f).unwrap() {
            if p.camera_count() == 4 {
                let k = [0.5, 1.0, 2.0, 4.0]
                    .iter()
                    .position(|&e| p.rms_px < e)
                    .unwrap_or(4);
                h[k] += 1;
            }
        }
    }
    h
}

/// The 4-camera particles of all frames matched with `band` whose RMS lies
/// in `range` (px): per camera, per third of the volume's depth (z), the
/// count and the mean residual (observed minus projected, px) and its RMS.
/// A mean far beyond RMS / sqrt(count) is a systematic offset. The thirds
/// split the z span of all matched particles, ghosts far out included, so
/// the true ones fall mostly in the middle third.
fn cavity_residual_field(
    cameras: &[Camera],
    frames: &[Vec<Vec<Target>>],
    band: f64,
    range: std::ops::Range<f64>,
) -> Vec<Vec<(usize, f64, f64, f64)>> {
    use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
    let matcher = Matcher::new(
        cameras,
        &MatchingParameters {
            tolerance: band,
            ..MatchingParameters::default()
        },
    )
    .unwrap();
    let particles: Vec<_> = frames
        .iter()
        .map(|f| matcher.match_frame(f).unwrap())
        .collect();
    let z: Vec<f64> = particles.iter().flatten().map(|p| p.position.z).collect();
    let (lo, hi) = z
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let mut sums = vec![vec![(0usize, 0.0, 0.0, 0.0); 3]; cameras.len()];
    for (f, ps) in frames.iter().zip(&particles) {
        for p in ps {
            if p.camera_count() != 4 || !range.contains(&p.rms_px) {
                continue;
            }
            let layer = (((p.position.z - lo) / (hi - lo + 1e-9)) * 3.0) as usize;
            for (c, t) in p.targets.iter().enumerate() {
                let (Some(t), Ok(pixel)) = (t, cameras[c].project(&p.position)) else {
                    continue;
                };
                let (dx, dy) = (f[c][*t].x - pixel.x, f[c][*t].y - pixel.y);
                let e = &mut sums[c][layer.min(2)];
                e.0 += 1;
                e.1 += dx;
                e.2 += dy;
                e.3 += dx * dx + dy * dy;
            }
        }
    }
    sums.iter()
        .map(|layers| {
            layers
                .iter()
                .map(|&(n, sx, sy, sq)| {
                    let k = n.max(1) as f64;
                    (n, sx / k, sy / k, (sq / k).sqrt())
                })
                .collect()
        })
        .collect()
}

/// The 3-camera particles of all frames matched with `band`, projected
/// into their missing camera: the distance to the nearest target there,
/// counted below 0.5, 0.5-1, 1-2, 2-4, 4-8 px, beyond, and off the sensor.
/// A rig right everywhere leaves the missing targets either near (a
/// member the band refused: a model error) or absent (occluded, merged,
/// too faint): then the distances follow the targets' random density.
fn cavity_missing_member(cameras: &[Camera], frames: &[Vec<Vec<Target>>], band: f64) -> [usize; 7] {
    use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
    let matcher = Matcher::new(
        cameras,
        &MatchingParameters {
            tolerance: band,
            ..MatchingParameters::default()
        },
    )
    .unwrap();
    let mut h = [0; 7];
    for f in frames {
        for p in matcher.match_frame(f).unwrap() {
            if p.camera_count() != 3 {
                continue;
            }
            let Some(missing) = p.targets.iter().position(Option::is_none) else {
                continue;
            };
            let Ok(pixel) = cameras[missing].project(&p.position) else {
                h[6] += 1;
                continue;
            };
            if !(0.0..1280.0).contains(&pixel.x) || !(0.0..1024.0).contains(&pixel.y) {
                h[6] += 1;
                continue;
            }
            let nearest = f[missing]
                .iter()
                .map(|t| (t.x - pixel.x).hypot(t.y - pixel.y))
                .fold(f64::INFINITY, f64::min);
            let k = [0.5, 1.0, 2.0, 4.0, 8.0]
                .iter()
                .position(|&e| nearest < e)
                .unwrap_or(5);
            h[k] += 1;
        }
    }
    h
}

/// test_cavity_recording with the glass vectors (one per wall: cameras 1-2
/// look through the wall at z = -125 mm, cameras 3-4 through the one at
/// +125 mm) and the liquid's index free too. Run with `--nocapture` for the
/// figures. Measured: the first wall's vector is adjusted (z moves 16.9 mm,
/// sigma 2.1 mm; x, y by -0.22 and 0.87 mm, sigmas 0.08 and 0.11 mm); the
/// second wall's components are held (correlations 0.997-0.9997 with the
/// first's: the two walls trade against each other), and the liquid's
/// index too (correlation 0.996 with camera 4's z0 under the gauge). No
/// gain: 4-camera particles under a 1 px band 118-139 per frame (116-145
/// with the media held), median RMS 0.24-0.25 px. With all four media
/// terms free (`ptv selfcalibrate --free glass,n_wall,n_object,thickness`,
/// measured) sigma0 is 0.241 px against 0.24 held, and the terms wander
/// within sigmas as large as their changes (the first wall 50 mm, sigma
/// 6 mm; the liquid's index 1.46 -> 1.54, sigma 0.15; the thickness 6 -> 0
/// mm, sigma 9 mm): the particles do not determine the media here, and
/// no media model error is left to find. Asserted: the same level as with
/// the media held, and that every held term says why.
#[test]
fn test_cavity_recording_with_the_media_free() {
    use ptv::photogrammetry::selfcal::MediaTerm;
    let experiment = ptv::formats::experiment::read_experiment(
        &std::path::Path::new(DATA).join("test_cavity_recording"),
    )
    .unwrap();
    let start: Vec<CameraParameters> = experiment
        .cameras
        .iter()
        .map(|c| c.parameters().clone())
        .collect();
    let frames = cavity_frames();
    let options = SelfCalibrationOptions {
        start_tolerance_px: 16.7,
        free_media: vec![MediaTerm::Glass, MediaTerm::ObjectIndex],
        ..SelfCalibrationOptions::default()
    };
    let result = self_calibrate(&start, &frames, &options, &Cancel::new(), &mut |_| {})
        .expect("self-calibrates");
    print("cavity media", &result);
    for m in &result.report.media {
        println!("cavity media: {m:?}");
    }
    let refined: Vec<Camera> = result
        .cameras
        .iter()
        .map(|p| Camera::new(p.clone()).unwrap())
        .collect();
    for band in [16.7, 2.0, 1.0] {
        println!(
            "cavity media band {band}: after {:?}",
            cavity_counts(&refined, &frames, band)
        );
    }
    println!(
        "cavity media: 4-camera particles at 4 px by RMS <0.5/0.5-1/1-2/2-4/>4 px: {:?}",
        cavity_rms_histogram(&refined, &frames, 4.0)
    );
    assert_ne!(result.report.outcome, Outcome::Diverged);
    assert_eq!(result.report.media.len(), 7, "2 walls x 3 + the index");
    for m in &result.report.media {
        use ptv::photogrammetry::calibrate::ParameterStatus;
        match m.status {
            ParameterStatus::Free => assert!(m.sigma.is_some_and(|s| s > 0.0), "{m:?}"),
            _ => assert!(m.reason.is_some(), "{m:?}"),
        }
    }
    for (four, rms) in cavity_counts(&refined, &frames, 1.0) {
        assert!(four >= 90 && rms < 0.3, "{four} {rms}");
    }
}

/// test_cavity_recording from OpenPTV's targets, starting at a 16.7 px band
/// (OpenPTV's eps0 = 0.2 mm). Measured: per camera the final particles'
/// disparity RMS 1.9-2.8 px before, 0.25-0.27 px after; 4-camera
/// particles under a 1 px band 0..1 per frame before, 115-136 after
/// (2 px: 11-20 before, 139-174 after), median RMS 0.24-0.26 px. Issue
/// 14's count goal (350 per frame at 1 px) is NOT REACHED, and these
/// targets do not hold that many 4-camera particles (measured, printed
/// below):
/// * with the refined rig at a 4 px band, 4-camera particles by RMS:
///   381 under 0.5 px, 230 at 0.5-1, 143 at 1-2, 8 at 2-4, none beyond, over
///   the 4 frames: about 190 a frame in all, 153 under 1 px, which the 1 px
///   band nearly all finds (116-145);
/// * the 3-camera particles at 1 px (704), projected into their missing
///   camera: the nearest target is within 1 px for 3, 1-2 px for 52, 2-4
///   px for 102, 4-8 px for 102, beyond 8 px for 444 (1 off the sensor).
///   The targets' density (~1,300 a camera over 1280x1024 px) gives 1.2%
///   within 2 px and 3.7% at 2-4 px by chance (9 and 26 of 704): about 120
///   (30 a frame) have a candidate 1-4 px away (merged or biased images, or
///   a local model error), the rest (63%) no image in that camera at all;
/// * the disparity maps after show no field: cell means within 0.1 px
///   where a cell holds 10 or more particles, against an RMS of 0.2-0.3 px;
/// * the tail is not an offset either: the 4-camera particles at 4 px with
///   RMS 0.5-2 px (343 in the middle depth third) have per camera mean
///   residuals of -0.013..0.062 px against an RMS of 0.9-1.1 px (a standard
///   error of ~0.04 px): per-particle errors (wrong or merged members,
///   biased centroids), not the rig. The core (RMS < 0.5 px, 381) has means
///   under 0.01 px.
///
/// So even all of those would make about 220 a frame. What remains is the
/// targets' own scatter (sigma0 0.24 px per coordinate, random over the
/// volume) and images missing in one camera. Freeing the media
/// (`test_cavity_recording_with_the_media_free`) does not change it.
/// Asserted: the levels reached, with a margin.
#[test]
fn test_cavity_recording_from_openptv_targets() {
    let experiment = ptv::formats::experiment::read_experiment(
        &std::path::Path::new(DATA).join("test_cavity_recording"),
    )
    .unwrap();
    let start: Vec<CameraParameters> = experiment
        .cameras
        .iter()
        .map(|c| c.parameters().clone())
        .collect();
    let frames = cavity_frames();
    let result = run(&start, &frames, 16.7);
    print("test_cavity", &result);
    let refined: Vec<Camera> = result
        .cameras
        .iter()
        .map(|p| Camera::new(p.clone()).unwrap())
        .collect();
    for band in [16.7, 2.0, 1.0] {
        println!(
            "test_cavity band {band}: before {:?}, after {:?}",
            cavity_counts(&experiment.cameras, &frames, band),
            cavity_counts(&refined, &frames, band)
        );
    }
    println!(
        "test_cavity: 4-camera particles at 4 px by RMS <0.5/0.5-1/1-2/2-4/>4 px: {:?}",
        cavity_rms_histogram(&refined, &frames, 4.0)
    );
    println!(
        "test_cavity: 3-camera particles at 1 px, nearest target in the missing camera \
         <0.5/0.5-1/1-2/2-4/4-8/>8 px/off the sensor: {:?}",
        cavity_missing_member(&refined, &frames, 1.0)
    );
    for (label, range) in [("core <0.5 px", 0.0..0.5), ("tail 0.5-2 px", 0.5..2.0)] {
        for (c, layers) in cavity_residual_field(&refined, &frames, 4.0, range)
            .iter()
            .enumerate()
        {
            println!(
                "test_cavity: 4 px, {label}, cam{}: per depth third (n, mean dx, mean dy, rms) {:.3?}",
                c + 1,
                layers
            );
        }
    }
    for c in &result.report.cameras {
        println!("test_cavity: {} map after:", c.name);
        for cell in &c.map_after.cells {
            println!("  {cell:?}");
        }
    }
    assert_ne!(result.report.outcome, Outcome::Diverged);
    for c in &result.report.cameras {
        assert!(c.before.rms_px > 1.5 && c.after.rms_px < 0.35, "{c:?}");
    }
    for (four, _) in cavity_counts(&refined, &frames, 1.0) {
        assert!(four >= 90, "{four}");
    }
}
