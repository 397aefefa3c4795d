//! Calibration health during a run (`photogrammetry::health`): a simulated
//! run whose camera 2 turns by 0.5 mrad over 200 frames raises camera 2's
//! drift alarm, and only it; a steady run raises none.
//!
//! `cargo test --test photogrammetry health -- --nocapture` prints the
//! alarm's frame.

use nalgebra::{Rotation3, Vector3};

use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
use ptv::photogrammetry::health::{frame_health, DriftAlarm, DriftMonitor, HealthOptions};
use ptv::photogrammetry::simulate::{self, RigSpec};
use ptv::photogrammetry::Camera;

const FRAMES: usize = 200;
/// Camera 2's turn at the last frame (rad), about the world's vertical
/// axis through its centre (a pan, as a bumped mount turns).
const TURN_RAD: f64 = 0.5e-3;
/// Target noise (px): the simulator's usual detection noise.
const NOISE_PX: f64 = 0.1;

/// Runs the sequence; the alarms and, per frame, camera 2's mean
/// disparity length.
fn run(turn: f64) -> (Vec<DriftAlarm>, Vec<f64>) {
    let spec = RigSpec::convergent(4);
    let calibration = spec.build().unwrap();
    // 1.5 px band: 4 times the drift's seen share at the alarm, wide
    // enough that camera 2 stays in its particles' groups until then.
    let matcher = Matcher::new(
        &calibration,
        &MatchingParameters {
            tolerance: 1.5,
            volume: Some(spec.volume),
            min_cameras: 3,
            similarity: None,
        },
    )
    .unwrap();
    let options = HealthOptions::new(spec.volume, 1.0);
    let mut monitor = DriftMonitor::new(
        4,
        DriftMonitor::DEFAULT_THRESHOLD_PX,
        DriftMonitor::DEFAULT_WINDOW,
    );
    let mut rng = simulate::rng(2);
    let mut alarms = Vec::new();
    let mut camera2 = Vec::new();
    for f in 0..FRAMES {
        let angle = turn * f as f64 / (FRAMES - 1) as f64;
        let truth: Vec<Camera> = calibration
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let mut p = c.parameters().clone();
                if k == 1 {
                    let e = &p.exterior;
                    let r = Rotation3::from_scaled_axis(Vector3::y() * angle).matrix()
                        * rotation_matrix(e.omega, e.phi, e.kappa);
                    (p.exterior.omega, p.exterior.phi, p.exterior.kappa) = rotation_angles(&r);
                }
                Camera::new(p).unwrap()
            })
            .collect();
        let points = simulate::particles(&spec.volume, 300, &mut rng);
        let frame = simulate::target_frame(&truth, &points, NOISE_PX, 0.0, &mut rng);
        let particles = matcher.match_frame(&frame.targets).unwrap();
        let health = frame_health(&calibration, &frame.targets, &particles, &options);
        camera2.push(health.cameras[1].all.mean().norm());
        alarms.extend(monitor.push(f as i64, &health));
    }
    (alarms, camera2)
}

#[test]
fn a_camera_turning_half_a_milliradian_raises_its_drift_alarm() {
    let (alarms, camera2) = run(TURN_RAD);
    println!("alarms: {alarms:?}");
    println!(
        "camera 2 mean disparity: frame 0 {:.3} px, 100 {:.3} px, 199 {:.3} px",
        camera2[0], camera2[100], camera2[199]
    );
    // Camera 2's alarm comes first. The others follow later (simulated:
    // cameras 1 and 3 at frames 131 and 166): each particle's position is
    // intersected from all 4 cameras, so camera 2's error is shared out,
    // about 0.6 of it seen in camera 2's images and 0.2-0.3 in the others'
    // (in the opposite sense), which pass 0.3 px once camera 2 has moved
    // by 1-1.5 px.
    let alarm = &alarms[0];
    assert_eq!(alarm.camera, 1, "{alarms:?}");
    assert!(
        alarms[1..].iter().all(|a| a.frame > alarm.frame + 20),
        "{alarms:?}"
    );
    // When: the turn moves camera 2's images by about c * angle = 49 mm *
    // 0.5 mrad / 12 um = 2.0 px at frame 199, linearly; the window's mean
    // lags the current frame by 25 frames and the baseline (frames 0-49)
    // carries the first 25 frames' share. The alarm must wait for the
    // baseline (frame >= 50) and fire before the end; with the share seen
    // in camera 2's images between 1/2 and 1 (the intersection absorbs
    // the rest), 0.3 px of drift comes between frame 25 + 25 + 0.3 /
    // (0.0102 px/frame) = 79 and 25 + 25 + 0.6 / 0.0102 = 109 (the
    // baseline's own share, 25 frames' worth, adds 25); the
    // window's mean of 50 frames x ~200 particles has a noise of 0.1 px /
    // sqrt(10,000) = 0.001 px, far inside.
    assert!((79..=109).contains(&alarm.frame), "{alarm:?}");
}

#[test]
fn a_steady_rig_raises_no_alarm() {
    let (alarms, camera2) = run(0.0);
    assert!(alarms.is_empty(), "{alarms:?}");
    // Noise only: 200 particles of 0.1 px give means of ~0.01 px.
    assert!(camera2.iter().all(|d| *d < 0.05), "{camera2:?}");
}
