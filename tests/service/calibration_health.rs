//! Calibration health during a run (issue 33): a simulated sequence whose
//! camera 2 (index 1) turns by 0.5 mrad over 200 frames, uploaded as
//! targets out of frame order, raises camera 2's drift alarm at the frame
//! the core's monitor gives when fed the same frames in order, with a
//! `calibration_drift` event, the Prometheus gauges and the picture; a
//! steady rig raises none; bad requests get the API's 4xx.
//!
//! `cargo test --test service calibration_health -- --nocapture` prints the
//! alarm's frame.

use std::time::Instant;

use nalgebra::{Rotation3, Vector3};
use serde_json::{json, Value};

use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
use ptv::photogrammetry::health::{frame_health, DriftAlarm, DriftMonitor, HealthOptions};
use ptv::photogrammetry::simulate::{self, TargetFrame};
use ptv::photogrammetry::Camera;

use crate::helpers::{rig, sequence_body, spawn_app, targets_form, Rig, TestApp, PATIENCE};

const FRAMES: i64 = 200;
/// Camera 2's turn at the last frame (rad), about the world's vertical
/// axis through its centre (a pan, as a bumped mount turns).
const TURN_RAD: f64 = 0.5e-3;
/// Target noise (px): the simulator's usual detection noise.
const NOISE_PX: f64 = 0.1;
/// Particles a frame.
const PARTICLES: usize = 300;
/// The matching band (px): 1.5 px, 4 times the drift's share seen in
/// camera 2's images at the alarm, so that camera 2 stays in its
/// particles' groups until then (as in `tests/photogrammetry/health.rs`).
const TOLERANCE_PX: f64 = 1.5;

/// The frames of a run whose camera 2 has turned by `turn * f / 199` at
/// frame `f`: per frame the targets each camera sees.
fn frames(rig: &Rig, turn: f64) -> Vec<TargetFrame> {
    let mut rng = simulate::rng(2);
    (0..FRAMES)
        .map(|f| {
            let angle = turn * f as f64 / (FRAMES - 1) as f64;
            let truth: Vec<Camera> = rig
                .cameras
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
            let points = simulate::particles(&rig.volume, PARTICLES, &mut rng);
            simulate::target_frame(&truth, &points, NOISE_PX, 0.0, &mut rng)
        })
        .collect()
}

/// The alarms of the core's monitor fed the frames in order, matched as
/// the sequence matches them (its tolerance and volume, 2 cameras at
/// least), well-matched within the tolerance.
fn core_alarms(rig: &Rig, frames: &[TargetFrame]) -> Vec<DriftAlarm> {
    let matcher = Matcher::new(
        &rig.cameras,
        &MatchingParameters {
            tolerance: TOLERANCE_PX,
            volume: Some(rig.volume),
            min_cameras: 2,
            ..MatchingParameters::default()
        },
    )
    .unwrap();
    let options = HealthOptions::new(rig.volume, TOLERANCE_PX);
    let mut monitor = DriftMonitor::new(
        4,
        DriftMonitor::DEFAULT_THRESHOLD_PX,
        DriftMonitor::DEFAULT_WINDOW,
    );
    let mut alarms = Vec::new();
    for (f, frame) in frames.iter().enumerate() {
        let particles = matcher.match_frame(&frame.targets).unwrap();
        let health = frame_health(&rig.cameras, &frame.targets, &particles, &options);
        alarms.extend(monitor.push(f as i64, &health));
    }
    alarms
}

/// Uploads the frames out of order (frame `7 k mod 200` k-th: 7 is prime
/// to 200, so every frame once) and waits for them; the sequence's id.
async fn run(app: &TestApp, calibration: i64, rig: &Rig, frames: &[TargetFrame]) -> i64 {
    let mut body = sequence_body(calibration, &rig.volume, false);
    body["matching"]["tolerance"] = json!(TOLERANCE_PX);
    let (status, created) = app.post_json("/sequences", &body).await;
    assert_eq!(status, 201, "{created}");
    assert_eq!(
        created["parameters"]["health"],
        json!({"threshold_px": 0.3, "window": 50}),
        "the defaults are stored with the sequence"
    );
    let sequence = created["id"].as_i64().unwrap();
    for k in 0..FRAMES {
        let f = (7 * k) % FRAMES;
        let (status, body) = app
            .upload(sequence, targets_form(f, &frames[f as usize]))
            .await;
        assert_eq!(status, 202, "{body}");
    }
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], FRAMES, "{view}");
    sequence
}

/// The sequence's health once it has taken every frame (the monitors
/// advance after their frames' jobs, in the background).
async fn health_through_the_end(app: &TestApp, sequence: i64) -> Value {
    let start = Instant::now();
    let db = app.database().await;
    loop {
        let (status, body) = app
            .get_json(&format!("/sequences/{sequence}/calibration-health"))
            .await;
        assert_eq!(status, 200, "{body}");
        // The stored monitor is through the end too (a read advances
        // only a copy).
        let stored: Option<(i64,)> =
            sqlx::query_as("SELECT through_frame FROM calibration_health WHERE sequence_id = $1")
                .bind(sequence)
                .fetch_optional(&db)
                .await
                .unwrap();
        if body["through_frame"] == FRAMES - 1 && stored == Some((FRAMES - 1,)) {
            return body;
        }
        assert!(start.elapsed() < PATIENCE, "health not advanced: {body}");
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
}

/// The sequence's logged events of `kind`.
async fn events_of(app: &TestApp, sequence: i64, kind: &str) -> Vec<Value> {
    let rows: Vec<(String,)> =
        sqlx::query_as("SELECT change FROM events WHERE sequence_id = $1 ORDER BY id")
            .bind(sequence)
            .fetch_all(&app.database().await)
            .await
            .unwrap();
    rows.iter()
        .map(|(c,)| serde_json::from_str::<Value>(c).unwrap())
        .filter(|c| c["type"] == kind)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_turning_half_a_milliradian_raises_its_alarm_and_a_steady_rig_none() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;

    // The steady rig first: no alarm, drifts at the noise's level.
    let steady = run(&app, calibration, &rig, &frames(&rig, 0.0)).await;
    let health = health_through_the_end(&app, steady).await;
    assert_eq!(health["alarm"], false, "{health}");
    assert_eq!(health["frames"], FRAMES, "{health}");
    assert!(health["advice"].is_null(), "{health}");
    for camera in health["cameras"].as_array().unwrap() {
        assert!(camera["alarm"].is_null(), "{health}");
        // Noise only: a window's mean over 50 frames x ~250 particles of
        // 0.1 px noise moves by ~0.1 / sqrt(12,500) = 0.001 px; the two
        // windows' difference stays far below 0.05 px.
        assert!(camera["drift_px"].as_f64().unwrap() < 0.05, "{health}");
        assert!(camera["baseline_px"].is_array(), "{health}");
        // The latest frame per sub-volume: 8 cells of a 2 x 2 x 2 grid,
        // each with particles (300 uniform in the volume).
        assert_eq!(camera["cells"].as_array().unwrap().len(), 8, "{health}");
        assert!(
            camera["latest"]["count"].as_i64().unwrap() > 100,
            "{health}"
        );
    }
    assert!(events_of(&app, steady, "calibration_drift")
        .await
        .is_empty());
    // Rows per frame: 4 cameras x (1 + 8 cells).
    let rows: (i64,) =
        sqlx::query_as("SELECT count(*) FROM frame_health WHERE sequence_id = $1 AND frame = 0")
            .bind(steady)
            .fetch_one(&app.database().await)
            .await
            .unwrap();
    assert_eq!(rows.0, 4 * 9);

    // The drifting rig.
    let drifting = frames(&rig, TURN_RAD);
    let expected = core_alarms(&rig, &drifting);
    let sequence = run(&app, calibration, &rig, &drifting).await;
    let health = health_through_the_end(&app, sequence).await;
    println!("core's alarms: {expected:?}");
    println!(
        "service: {}",
        serde_json::to_string_pretty(&health["cameras"]).unwrap()
    );
    let alarm = &health["cameras"][1]["alarm"];
    let frame = alarm["frame"].as_i64().expect("camera 2's alarm fired");
    // The frame the core's monitor gives for the same frames in order:
    // the service took them in frame order although they were uploaded
    // and processed out of it.
    assert_eq!(expected[0].camera, 1, "{expected:?}");
    assert_eq!(frame, expected[0].frame, "{health}");
    // And where the geometry puts it: the turn moves camera 2's images by
    // about c * angle = 49 mm * 0.5 mrad / 12 um = 2.0 px at frame 199,
    // linearly (0.0102 px a frame). The intersection from 4 cameras
    // absorbs part of it: between 1/2 and 1 of it shows in camera 2's own
    // images. The window's mean lags the current frame by 25 frames and
    // the baseline (frames 0-49) carries 25 frames' worth, so 0.3 px of
    // drift is reached between frame 25 + 25 + 0.3 / 0.0102 = 79 and
    // 25 + 25 + 0.6 / 0.0102 = 109. Noise: 0.001 px on a window's mean
    // (above), far inside.
    assert!((79..=109).contains(&frame), "{health}");
    // Camera 2 first; the others' alarms (its error shared out by the
    // intersection, in the opposite sense) come later or not at all.
    for (k, camera) in health["cameras"].as_array().unwrap().iter().enumerate() {
        if k != 1 {
            if let Some(other) = camera["alarm"]["frame"].as_i64() {
                assert!(other > frame, "{health}");
            }
        }
    }
    assert_eq!(health["alarm"], true);
    let advice = health["advice"].as_str().unwrap();
    assert!(
        advice.contains("camera 1 drifted")
            && advice.contains("self-calibration")
            && advice.contains(&format!("\"first\": {frame}")),
        "{advice}"
    );
    println!("camera 2 (index 1) alarm at frame {frame}: {alarm}");

    // One event per alarm, the first camera 2's at that frame.
    let start = Instant::now();
    let events = loop {
        let events = events_of(&app, sequence, "calibration_drift").await;
        if events.len() == expected.len() || start.elapsed() > PATIENCE {
            break events;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    };
    assert_eq!(events.len(), expected.len(), "{events:?} {expected:?}");
    let first = events.iter().find(|e| e["camera"] == 1).unwrap();
    assert_eq!(first["frame"], frame);
    assert_eq!(first["calibration_id"], calibration);
    assert!(first["drift_length_px"].as_f64().unwrap() > 0.3);

    // The gauges: both sequences' cameras, camera 2 of the drifting one
    // alarmed.
    let metrics = app.get_text(format!("{}/metrics", app.address)).await;
    assert!(
        metrics.contains(&format!(
            "ptv_calibration_drift_alarm{{sequence=\"{sequence}\",camera=\"1\"}} 1"
        )),
        "{metrics}"
    );
    assert!(
        metrics.contains(&format!(
            "ptv_calibration_drift_alarm{{sequence=\"{steady}\",camera=\"1\"}} 0"
        )),
        "{metrics}"
    );
    assert!(metrics.contains(&format!(
        "ptv_calibration_drift_alarms_total {}",
        expected.len()
    )));

    // The picture.
    let response = app
        .client
        .get(app.api(&format!("/sequences/{sequence}/calibration-health.png")))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(crate::helpers::content_type(&response), "image/png");
    let png = response.bytes().await.unwrap();
    // Kept for a look: target/tmp/calibration-health.png.
    std::fs::write(
        std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("calibration-health.png"),
        &png,
    )
    .unwrap();
    let picture = image::load_from_memory(&png).unwrap();
    assert_eq!((picture.width(), picture.height()), (900, 440));

    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calibration_health_refuses_bad_requests_as_the_api_does() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    for path in [
        "/sequences/99/calibration-health",
        "/sequences/99/calibration-health.png",
    ] {
        let (status, body) = app.get_json(path).await;
        assert_eq!(status, 404, "{path}: {body}");
        assert_eq!(body["detail"], "sequence 99 does not exist", "{body}");
    }
    let (status, body) = app.get_json("/sequences/x/calibration-health").await;
    assert_eq!(status, 400, "{body}");
    // Settings out of range: 422 naming the field.
    for (health, field) in [
        (json!({"threshold_px": 0}), "health.threshold_px"),
        (json!({"window": 0}), "health.window"),
        (json!({"window": 501}), "health.window"),
    ] {
        let mut body = sequence_body(calibration, &rig.volume, false);
        body["health"] = health;
        let (status, answer) = app.post_json("/sequences", &body).await;
        assert_eq!(status, 422, "{answer}");
        assert!(
            answer["detail"].as_str().unwrap().contains(field),
            "{answer}"
        );
    }
    let mut body = sequence_body(calibration, &rig.volume, false);
    body["health"] = json!({"threshold": 1});
    let (status, answer) = app.post_json("/sequences", &body).await;
    assert_eq!(status, 422, "{answer}");
    // A sequence without frames: 200, nothing taken; its picture draws
    // empty axes; an unknown format is a 400.
    let (status, created) = app
        .post_json(
            "/sequences",
            &sequence_body(calibration, &rig.volume, false),
        )
        .await;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_i64().unwrap();
    let (status, health) = app
        .get_json(&format!("/sequences/{id}/calibration-health"))
        .await;
    assert_eq!(status, 200, "{health}");
    assert!(
        health["through_frame"].is_null() && health["frames"] == 0,
        "{health}"
    );
    let (status, body) = app
        .get_json(&format!(
            "/sequences/{id}/calibration-health.png?format=gif"
        ))
        .await;
    assert_eq!(status, 400, "{body}");
    let response = app
        .client
        .get(app.api(&format!(
            "/sequences/{id}/calibration-health.png?format=svg"
        )))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    app.stop().await;
}
