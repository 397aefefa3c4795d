//! Self-calibration in the service: a simulated sequence uploaded with a
//! disturbed calibration, self-calibrated from its stored targets into a
//! new calibration that names its origin and is closer to the truth, the
//! frames reprocessed with it (and back), every particle set naming its
//! calibration; and bad requests refused with a 4xx that says why.

use nalgebra::Vector3;
use rand::Rng;
use serde_json::{json, Value};

use ptv::formats;
use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
use ptv::photogrammetry::{intersect, simulate, Camera, Observation, Volume};

use crate::helpers::{rig, spawn_app, targets_form, TestApp, PATIENCE};

/// Each camera moved by `shift_mm` in a random direction and turned by
/// `turn_rad` about a random axis.
fn disturbed(cameras: &[Camera], shift_mm: f64, turn_rad: f64, seed: u64) -> Vec<Camera> {
    let mut rng = simulate::rng(seed);
    let mut unit = || Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
    cameras
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.exterior.position += unit() * shift_mm;
            let e = &p.exterior;
            let turn = nalgebra::Rotation3::from_scaled_axis(unit() * turn_rad);
            let r = turn.matrix() * rotation_matrix(e.omega, e.phi, e.kappa);
            (p.exterior.omega, p.exterior.phi, p.exterior.kappa) = rotation_angles(&r);
            Camera::new(p).unwrap()
        })
        .collect()
}

/// Noise-free true points imaged by the true cameras and intersected with
/// `rig`: the RMS reprojection residual (px), how far the rig is from
/// being consistent with the truth.
fn disparity_px(volume: &Volume, truth: &[Camera], rig: &[Camera]) -> f64 {
    let mut rng = simulate::rng(99);
    let (mut sq, mut count) = (0.0, 0);
    for p in simulate::particles(volume, 500, &mut rng) {
        let observations: Vec<Observation> = truth
            .iter()
            .enumerate()
            .map(|(camera, c)| Observation {
                camera,
                pixel: c.project(&p).unwrap(),
            })
            .collect();
        let x = intersect(rig, &observations).unwrap();
        for r in &x.residuals_px {
            sq += r.norm_squared();
            count += 1;
        }
    }
    (sq / count as f64).sqrt()
}

/// A stored calibration's cameras.
async fn cameras_of(app: &TestApp, id: i64) -> (Value, Vec<Camera>) {
    let (status, body) = app.get_json(&format!("/calibrations/{id}")).await;
    assert_eq!(status, 200, "{body}");
    let cameras =
        formats::calibration::from_json(&body["model"].to_string(), "the served calibration")
            .unwrap();
    (body, cameras)
}

/// The median particle RMS (px) of each frame, and the calibrations that
/// made the frames' particles.
async fn frames_made_by(app: &TestApp, sequence: i64, frames: i64) -> (Vec<f64>, Vec<i64>) {
    let (mut medians, mut made_by) = (Vec::new(), Vec::new());
    for frame in 0..frames {
        let (status, body) = app
            .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
            .await;
        assert_eq!(status, 200, "{body}");
        let mut rms: Vec<f64> = body["particles"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["rms_px"].as_f64().unwrap())
            .collect();
        rms.sort_by(f64::total_cmp);
        medians.push(rms[rms.len() / 2]);
        made_by.push(body["calibration_id"].as_i64().unwrap());
    }
    (medians, made_by)
}

/// Waits until every frame's particles name `calibration`.
async fn wait_until_made_by(app: &TestApp, sequence: i64, frames: i64, calibration: i64) {
    let start = std::time::Instant::now();
    loop {
        let (_, made_by) = frames_made_by(app, sequence, frames).await;
        if made_by.iter().all(|&c| c == calibration) {
            return;
        }
        assert!(start.elapsed() < PATIENCE, "still made by {made_by:?}");
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
}

const FRAMES: i64 = 6;

#[tokio::test]
async fn a_disturbed_calibration_is_self_calibrated_linked_and_the_frames_reprocessed() {
    let app = spawn_app().await;
    let rig = rig();
    // Every camera 0.1 mm and 0.1 mrad off: true points reproject at
    // several tenths of a pixel through it (checked below), while a 1 px
    // band still matches the frames (the core's own test, on the same
    // rig).
    let rough = disturbed(&rig.cameras, 0.1, 1e-4, 5);
    let rough_id = app.create_calibration(&rough).await;
    let sequence = app.create_sequence(rough_id, &rig.volume, true).await;
    for frame in 0..FRAMES {
        let targets = rig.targets(1000, 100 + frame as u64);
        let (status, body) = app.upload(sequence, targets_form(frame, &targets)).await;
        assert_eq!(status, 202, "{body}");
    }
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], FRAMES, "{view}");
    let (before_rms, made_by) = frames_made_by(&app, sequence, FRAMES).await;
    assert!(made_by.iter().all(|&c| c == rough_id), "{made_by:?}");

    let (status, accepted) = app
        .post_json(
            &format!("/sequences/{sequence}/self-calibration"),
            &json!({"tolerance": 2.0, "frames": {"first": 0, "last": FRAMES - 1},
                    "reprocess": true}),
        )
        .await;
    assert_eq!(status, 202, "{accepted}");
    assert_eq!(accepted["calibration_id"], rough_id);
    let job = app.wait_for_job(accepted["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    let link = job["result"].as_str().unwrap();
    let refined_id: i64 = link
        .strip_prefix("/api/v1/calibrations/")
        .unwrap()
        .parse()
        .unwrap();
    assert_ne!(refined_id, rough_id);

    // The new calibration names its origin and carries the report.
    let (view, refined) = cameras_of(&app, refined_id).await;
    assert_eq!(view["origin_calibration"], rough_id, "{view}");
    let (status, report) = app
        .get_json(&format!("/calibrations/{refined_id}/report"))
        .await;
    assert_eq!(status, 200, "{report}");
    assert_eq!(report, view["report"]);
    assert_ne!(report["outcome"], "diverged", "{report}");
    assert_eq!(report["cameras"].as_array().unwrap().len(), 4, "{report}");
    crate::plots::check_disparity_picture(&app, refined_id, &report).await;
    let (_, original) = cameras_of(&app, rough_id).await;
    assert_eq!(original.len(), 4);

    // Closer to the truth. The bound is issue 14's (0.05 px for true
    // points through the refined rig); 6,000 particles at 0.05 px noise
    // determine the exterior orientations to far less (the core's test
    // reaches 0.018 px from 0.1 px noise).
    let before_px = disparity_px(&rig.volume, &rig.cameras, &rough);
    let after_px = disparity_px(&rig.volume, &rig.cameras, &refined);
    eprintln!("true points through the rig: {before_px:.4} -> {after_px:.4} px RMS");
    assert!(before_px > 0.2, "the disturbance is too small: {before_px}");
    assert!(after_px < 0.05, "{before_px} -> {after_px}");

    // `reprocess`: the sequence now uses the refined calibration and every
    // frame's particles are remade with it, fitting better.
    let (_, sequence_view) = app.get_json(&format!("/sequences/{sequence}")).await;
    assert_eq!(sequence_view["calibration_id"], refined_id);
    wait_until_made_by(&app, sequence, FRAMES, refined_id).await;
    let (after_rms, _) = frames_made_by(&app, sequence, FRAMES).await;
    eprintln!("median particle rms per frame: {before_rms:?} -> {after_rms:?}");
    // The targets' noise is 0.05 px, so a consistent rig leaves residuals
    // of that order; the rough rig's several tenths of a pixel dominate.
    for (before, after) in before_rms.iter().zip(&after_rms) {
        assert!(after * 2.0 < *before, "{before_rms:?} -> {after_rms:?}");
    }
    let csv = app
        .get_text(app.api(&format!("/sequences/{sequence}/particles?format=csv")))
        .await;
    let mut lines = csv.lines();
    assert!(lines
        .next()
        .unwrap()
        .starts_with("frame,calibration_id,x,y,z"));
    assert!(lines.all(|l| l.split(',').nth(1) == Some(refined_id.to_string().as_str())));
    let response = app
        .client
        .get(app.api(&format!(
            "/sequences/{sequence}/frames/0/particles?format=csv"
        )))
        .send()
        .await
        .unwrap();
    assert_eq!(
        response.headers()["ptv-calibration-id"],
        refined_id.to_string().as_str()
    );

    // An explicit reprocess back to the rough calibration: its particles
    // again, the sequence switched back.
    let (status, body) = app
        .post_json(
            &format!("/sequences/{sequence}/reprocess"),
            &json!({"calibration": rough_id}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["result"], format!("/api/v1/sequences/{sequence}"));
    let (again_rms, made_by) = frames_made_by(&app, sequence, FRAMES).await;
    assert!(made_by.iter().all(|&c| c == rough_id), "{made_by:?}");
    assert_eq!(again_rms, before_rms);
    app.stop().await;
}

#[tokio::test]
async fn bad_self_calibration_requests_get_a_4xx_that_says_why() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let empty = app.create_sequence(calibration, &rig.volume, true).await;
    let post = |path: String, body: Value| {
        let app = &app;
        async move { app.post_json(&path, &body).await }
    };
    let selfcal = |id: i64| format!("/sequences/{id}/self-calibration");

    let (status, body) = post(selfcal(999), json!({})).await;
    assert_eq!(status, 404, "{body}");
    assert!(body["detail"].as_str().unwrap().contains("sequence 999"));

    let (status, body) = post(selfcal(empty), json!({})).await;
    assert_eq!(status, 422, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(
        detail.contains("no frames") && detail.contains("targets"),
        "{detail}"
    );

    // Frames to work on, for the option checks below (and too few
    // particles: 30 per frame, of the 100 an adjustment takes).
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let targets = rig.targets(30, 1);
    let (status, body) = app.upload(sequence, targets_form(0, &targets)).await;
    assert_eq!(status, 202, "{body}");
    app.wait_for_sequence(sequence).await;

    for (options, status, words) in [
        (
            json!({"tolerance": 0.2, "final_tolerance": 0.5}),
            422,
            vec!["starting band", "final band"],
        ),
        (json!({"free": ["k1", "bogus"]}), 422, vec!["free", "bogus"]),
        (json!({"free": ["x0"]}), 422, vec!["free", "x0"]),
        (json!({"min_cameras": 1}), 422, vec!["2 cameras"]),
        (
            json!({"frames": {"first": 5, "last": 2}}),
            422,
            vec!["frames", "after the last"],
        ),
        (
            json!({"frames": {"first": 5, "last": 9}}),
            422,
            vec!["no frames in 5..9"],
        ),
        (json!({"band": 3}), 422, vec!["band"]),
        (json!({"tolerance": "wide"}), 422, vec!["tolerance"]),
    ] {
        let (got, body) = post(selfcal(sequence), options.clone()).await;
        assert_eq!(got, status, "{options}: {body}");
        let detail = body["detail"].as_str().unwrap();
        for word in words {
            assert!(detail.contains(word), "{options}: {detail}");
        }
    }

    // Too few particles: the job fails saying how many and where the band
    // stood; no calibration is stored.
    let (status, body) = post(selfcal(sequence), json!({})).await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "failed", "{job}");
    let error = job["error"].as_str().unwrap();
    assert!(
        error.contains("confident particles") && error.contains("band"),
        "{error}"
    );
    let (status, _) = app
        .get_json(&format!("/calibrations/{}", calibration + 1))
        .await;
    assert_eq!(status, 404);

    // Reprocessing: an unknown calibration, one of another rig, an unknown
    // sequence.
    let reprocess = |id: i64| format!("/sequences/{id}/reprocess");
    let (status, body) = post(reprocess(sequence), json!({"calibration": 999})).await;
    assert_eq!(status, 422, "{body}");
    assert!(body["detail"].as_str().unwrap().contains("calibration 999"));
    let two = app.create_calibration(&rig.cameras[..2]).await;
    let (status, body) = post(reprocess(sequence), json!({"calibration": two})).await;
    assert_eq!(status, 422, "{body}");
    assert!(
        body["detail"].as_str().unwrap().contains("2 cameras"),
        "{body}"
    );
    let (status, _) = post(reprocess(999), json!({"calibration": calibration})).await;
    assert_eq!(status, 404);
    let (_, view) = app.get_json(&format!("/sequences/{sequence}")).await;
    assert_eq!(view["calibration_id"], calibration, "nothing switched");

    // A calibration stored as given has no report.
    let (status, body) = app
        .get_json(&format!("/calibrations/{calibration}/report"))
        .await;
    assert_eq!(status, 404, "{body}");
    assert!(body["detail"].as_str().unwrap().contains("no report"));
    app.stop().await;
}
