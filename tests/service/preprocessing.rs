//! A sequence's backgrounds and masks (issue 13): uploaded before the
//! first frame, or a background computed from the sequence's own frames;
//! and the bad inputs around them, which leave nothing stored.
//!
//! The scene: the synthetic rig's particles over a static structure of
//! bright spots that are themselves real 3D points (dirt on a window seen
//! by every camera), added to each frame's image. Without a background
//! those spots are detected and matched like particles; with the static
//! image subtracted they vanish, and each frame gives what its particles
//! alone give.

use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{GreyImage, GreyPixels};
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};

use super::helpers::{
    image_form, png, rig, sequence_body, spawn_app, status_and_json, Rig, TestApp,
};

/// Static spots, and particles per frame.
const STATIC_SPOTS: usize = 150;
const PARTICLES: usize = 120;

/// The static structure's image in every camera: 8-bit, 3 px spots.
fn static_images(rig: &Rig) -> Vec<GreyImage> {
    let mut rng = simulate::rng(4242);
    let points = simulate::particles(&rig.volume, STATIC_SPOTS, &mut rng);
    simulate::render_frame(&rig.cameras, &points, &RenderSpec::eight_bit(3.0), &mut rng)
        .into_iter()
        .map(|r| r.image)
        .collect()
}

/// `a + b` per pixel, saturating.
fn add(a: &GreyImage, b: &GreyImage) -> GreyImage {
    let (GreyPixels::Eight(a_px), GreyPixels::Eight(b_px)) = (a.pixels(), b.pixels()) else {
        panic!("8-bit images expected");
    };
    let sum = a_px
        .iter()
        .zip(b_px)
        .map(|(&x, &y)| x.saturating_add(y))
        .collect();
    GreyImage::from_u8(a.width(), a.height(), sum).unwrap()
}

/// Frame `k`'s particle-only images and its images over the structure.
fn frame(rig: &Rig, k: u64, structure: &[GreyImage]) -> (Vec<GreyImage>, Vec<GreyImage>) {
    let particles = rig.render(PARTICLES, 100 + k).images;
    let over = particles
        .iter()
        .zip(structure)
        .map(|(p, s)| add(p, s))
        .collect();
    (particles, over)
}

fn pngs(images: &[GreyImage]) -> Vec<Vec<u8>> {
    images.iter().map(png).collect()
}

/// Creates a sequence with extra top-level fields; its id.
async fn create(app: &TestApp, calibration: i64, rig: &Rig, extra: Value) -> i64 {
    let mut body = sequence_body(calibration, &rig.volume, true);
    for (key, value) in extra.as_object().unwrap() {
        body[key] = value.clone();
    }
    let (status, body) = app.post_json("/sequences", &body).await;
    assert_eq!(status, 201, "{body}");
    body["id"].as_i64().unwrap()
}

/// POSTs `cam{c}` parts to `/sequences/{id}/{what}`.
async fn post_images(
    app: &TestApp,
    sequence: i64,
    what: &str,
    parts: &[(usize, Vec<u8>)],
) -> (u16, Value) {
    let mut form = Form::new();
    for (camera, bytes) in parts {
        form = form.part(
            format!("cam{camera}"),
            Part::bytes(bytes.clone()).file_name(format!("cam{camera}.png")),
        );
    }
    let response = app
        .client
        .post(app.api(&format!("/sequences/{sequence}/{what}")))
        .multipart(form)
        .send()
        .await
        .unwrap();
    status_and_json(response).await
}

/// Particles of a processed frame.
async fn particles(app: &TestApp, sequence: i64, frame: i64) -> usize {
    let (status, body) = app
        .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
        .await;
    assert_eq!(status, 200, "{body}");
    body["particles"].as_array().unwrap().len()
}

/// Targets of a processed frame in one camera, as (x, y).
async fn targets(app: &TestApp, sequence: i64, frame: i64, camera: usize) -> Vec<(f64, f64)> {
    let (status, body) = app
        .get_json(&format!(
            "/sequences/{sequence}/frames/{frame}/targets?camera={camera}"
        ))
        .await;
    assert_eq!(status, 200, "{body}");
    body["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| (t["x"].as_f64().unwrap(), t["y"].as_f64().unwrap()))
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn an_uploaded_background_removes_static_structure_and_a_computed_one_does_too() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let structure = static_images(&rig);
    let frames: Vec<_> = (0..3).map(|k| frame(&rig, k, &structure)).collect();

    // Reference: the particles alone. Plain: over the structure, as is.
    let reference = create(&app, calibration, &rig, json!({})).await;
    let plain = create(&app, calibration, &rig, json!({})).await;
    let uploaded = create(&app, calibration, &rig, json!({})).await;
    let computed = create(
        &app,
        calibration,
        &rig,
        json!({"background": {"mode": "median", "frames": 3}}),
    )
    .await;
    let backgrounds: Vec<(usize, Vec<u8>)> = pngs(&structure).into_iter().enumerate().collect();
    let (status, body) = post_images(&app, uploaded, "background", &backgrounds).await;
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["background"], "uploaded", "{body}");
    assert_eq!(body["background_cameras"], json!([0, 1, 2, 3]));

    for (k, (alone, over)) in frames.iter().enumerate() {
        let k = k as i64;
        for (sequence, images) in [
            (reference, alone),
            (plain, over),
            (uploaded, over),
            (computed, over),
        ] {
            let (status, body) = app.upload(sequence, image_form(k, &pngs(images))).await;
            assert_eq!(status, 202, "{body}");
        }
        if k == 0 {
            // One frame of three: the computed sequence's frame waits, and
            // says why.
            tokio::time::sleep(std::time::Duration::from_millis(300)).await;
            let (_, view) = app.get_json(&format!("/sequences/{computed}")).await;
            assert_eq!(view["background"], "waiting", "{view}");
            assert_eq!(view["frames"]["done"], 0, "{view}");
        }
    }
    for sequence in [reference, plain, uploaded, computed] {
        let view = app.wait_for_sequence(sequence).await;
        assert_eq!(view["frames"]["done"], 3, "{view}");
    }
    let (_, view) = app.get_json(&format!("/sequences/{computed}")).await;
    assert_eq!(view["background"], "computed", "{view}");

    for k in 0..3 {
        let alone = particles(&app, reference, k).await;
        let over = particles(&app, plain, k).await;
        let subtracted = particles(&app, uploaded, k).await;
        let median = particles(&app, computed, k).await;
        // The static spots are real 3D points: without a background most
        // of them come out as particles too.
        assert!(
            over >= alone + STATIC_SPOTS / 2,
            "frame {k}: {over} particles over the structure, {alone} alone"
        );
        // Subtracting the exact structure gives back the particle-only
        // image except where a spot saturated or overlaps a particle: a
        // few percent of the particles at most.
        let close = |n: usize| n.abs_diff(alone) * 20 <= alone;
        assert!(
            close(subtracted),
            "frame {k}: {subtracted} with the uploaded background, {alone} alone"
        );
        // The median of three frames is the structure wherever no particle
        // sits in two of them.
        assert!(
            close(median),
            "frame {k}: {median} with the computed background, {alone} alone"
        );
    }
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_mask_keeps_targets_out_of_its_zero_pixels() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = create(&app, calibration, &rig, json!({})).await;
    let sensor = rig.cameras[0].sensor();
    let (width, height) = (sensor.width, sensor.height);
    // Camera 0 sees only its right half.
    let mask: Vec<u8> = (0..height)
        .flat_map(|_| (0..width).map(|x| u8::from(x >= width / 2) * 255))
        .collect();
    let mask = GreyImage::from_u8(width, height, mask).unwrap();
    let (status, body) = post_images(&app, sequence, "mask", &[(0, png(&mask))]).await;
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["mask_cameras"], json!([0]));
    let images = rig.render(PARTICLES, 7).images;
    let (status, body) = app.upload(sequence, image_form(0, &pngs(&images))).await;
    assert_eq!(status, 202, "{body}");
    app.wait_for_sequence(sequence).await;
    let masked = targets(&app, sequence, 0, 0).await;
    let unmasked = targets(&app, sequence, 0, 1).await;
    assert!(!masked.is_empty() && !unmasked.is_empty());
    assert!(
        masked.iter().all(|&(x, _)| x > f64::from(width / 2)),
        "a target in the masked half: {masked:?}"
    );
    // The other cameras are untouched: their left halves have targets.
    assert!(unmasked.iter().any(|&(x, _)| x < f64::from(width / 2)));
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_backgrounds_and_masks_are_refused_and_change_nothing() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sensor = rig.cameras[0].sensor().clone();
    let blank8 = GreyImage::from_u8(
        sensor.width,
        sensor.height,
        vec![0; (sensor.width * sensor.height) as usize],
    )
    .unwrap();
    let small = GreyImage::from_u8(8, 8, vec![0; 64]).unwrap();

    // A computed background's frame count is checked.
    let mut body = sequence_body(calibration, &rig.volume, true);
    body["background"] = json!({"frames": 1});
    let (status, problem) = app.post_json("/sequences", &body).await;
    assert_eq!(status, 422, "{problem}");
    assert!(
        problem["detail"]
            .as_str()
            .unwrap()
            .contains("background.frames"),
        "{problem}"
    );

    let sequence = create(&app, calibration, &rig, json!({})).await;
    // The wrong size: 422, nothing stored.
    let (status, problem) = post_images(&app, sequence, "background", &[(0, png(&small))]).await;
    assert_eq!(status, 422, "{problem}");
    assert!(
        problem["detail"]
            .as_str()
            .unwrap()
            .contains("background of cam0"),
        "{problem}"
    );
    // A camera the calibration does not have, an unknown part, no part.
    let (status, problem) = post_images(&app, sequence, "mask", &[(9, png(&blank8))]).await;
    assert_eq!(status, 422, "{problem}");
    let form = Form::new().part("image", Part::bytes(png(&blank8)).file_name("x.png"));
    let response = app
        .client
        .post(app.api(&format!("/sequences/{sequence}/background")))
        .multipart(form)
        .send()
        .await
        .unwrap();
    let (status, problem) = status_and_json(response).await;
    assert_eq!(status, 400, "{problem}");
    let (status, problem) = post_images(&app, sequence, "background", &[]).await;
    assert_eq!(status, 400, "{problem}");
    let (_, view) = app.get_json(&format!("/sequences/{sequence}")).await;
    assert_eq!(view["background"], "none", "{view}");
    assert_eq!(view["background_cameras"], json!([]));
    assert_eq!(view["mask_cameras"], json!([]));

    // An 8-bit background, then a 16-bit frame: 422, no frame stored.
    let (status, body) = post_images(&app, sequence, "background", &[(0, png(&blank8))]).await;
    assert_eq!(status, 201, "{body}");
    let (status, problem) = post_images(&app, sequence, "background", &[(1, png(&blank8))]).await;
    assert_eq!(status, 409, "{problem}");
    let sixteen: Vec<Vec<u8>> = (0..4)
        .map(|_| {
            let samples = vec![0u16; (sensor.width * sensor.height) as usize];
            png(&GreyImage::from_u16(sensor.width, sensor.height, samples).unwrap())
        })
        .collect();
    let (status, problem) = app.upload(sequence, image_form(0, &sixteen)).await;
    assert_eq!(status, 422, "{problem}");
    assert!(
        problem["detail"].as_str().unwrap().contains("background"),
        "{problem}"
    );
    let (_, view) = app.get_json(&format!("/sequences/{sequence}")).await;
    assert_eq!(view["frames"]["queued"], 0, "{view}");

    // After a frame: 409 for masks too.
    let images = rig.render(20, 3).images;
    let (status, body) = app.upload(sequence, image_form(0, &pngs(&images))).await;
    assert_eq!(status, 202, "{body}");
    let (status, problem) = post_images(&app, sequence, "mask", &[(0, png(&blank8))]).await;
    assert_eq!(status, 409, "{problem}");
    assert!(
        problem["detail"]
            .as_str()
            .unwrap()
            .contains("before its first frame"),
        "{problem}"
    );

    // A sequence that computes its background takes no upload.
    let computed = create(
        &app,
        calibration,
        &rig,
        json!({"background": {"mode": "min"}}),
    )
    .await;
    let (status, problem) = post_images(&app, computed, "background", &[(0, png(&blank8))]).await;
    assert_eq!(status, 409, "{problem}");
    app.wait_for_sequence(sequence).await;
    app.stop().await;
}
