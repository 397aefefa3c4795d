//! Bounds on the work a request or a job can cause: projections per
//! request, a frame's time limit, and uploads decoded whole before they
//! are accepted.

use std::time::Instant;

use serde_json::{json, Value};

use crate::helpers::{image_form, png, rig, spawn_app, spawn_app_configured, targets_form};
use ptv::service::JobLimits;

fn points(count: usize) -> Value {
    let points: Vec<[f64; 3]> = (0..count)
        .map(|i| [(i % 100) as f64 - 50.0, (i / 100 % 100) as f64 - 50.0, 0.0])
        .collect();
    json!({ "points": points })
}

/// Defect 1: points x cameras built in memory. At most 200,000
/// projections per request: 50,000 points on 4 cameras pass, one more is
/// refused naming the limit, and more than 100,000 points are refused
/// while the body is parsed, whatever the cameras.
#[tokio::test]
async fn projections_per_request_are_bounded() {
    let app = spawn_app().await;
    let calibration = app.create_calibration(&rig().cameras).await;
    let path = format!("/calibrations/{calibration}/project");

    let (status, body) = app.post_json(&path, &points(50_000)).await;
    assert_eq!(status, 200);
    assert_eq!(body["pixels"].as_array().unwrap().len(), 50_000);

    let (status, body) = app.post_json(&path, &points(50_001)).await;
    assert_eq!(status, 422, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(
        detail.contains("200004 projections") && detail.contains("at most 200000"),
        "{detail}"
    );

    let (status, body) = app.post_json(&path, &points(100_001)).await;
    assert_eq!(status, 422, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(detail.contains("more than 100000 points"), "{detail}");
    app.stop().await;
}

/// Defect 4: a frame that runs past its time limit is stopped and fails
/// with the reason, once (not retried), and the worker goes on with the
/// next frame.
#[tokio::test]
async fn a_frame_past_its_time_limit_fails_and_frees_the_worker() {
    let app = spawn_app_configured(|args| {
        args.workers = Some(1);
        args.job_limits = JobLimits {
            floor_secs: 0.2,
            factor: 0.0,
            ..Default::default()
        };
    })
    .await;
    let (rig, sequence) = app.rig_sequence().await;

    let (status, body) = app
        .upload(sequence, targets_form(0, &rig.targets(40_000, 1)))
        .await;
    assert_eq!(status, 202, "{body}");
    let started = Instant::now();
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["attempts"], 1, "{job}");
    let error = job["error"].as_str().unwrap();
    assert!(
        error.contains("time limit of 0.2 s") && error.contains("--job-timeout-secs"),
        "{error}"
    );
    assert!(error.contains("160000 targets"), "{error}");
    assert!(
        started.elapsed().as_secs_f64() < 10.0,
        "stopped after {:?}",
        started.elapsed()
    );
    let (status, body) = app
        .get_json(&format!("/sequences/{sequence}/frames/0/particles"))
        .await;
    assert_eq!(status, 409, "{body}");

    let (status, body) = app
        .upload(sequence, targets_form(1, &rig.targets(100, 2)))
        .await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    app.stop().await;
}

/// A greyscale TIFF of `width` x `height` 8-bit samples in one strip whose
/// offset points far beyond the file's end.
fn tiff_with_bad_strip_offset(width: u32, height: u32) -> Vec<u8> {
    let entries: [(u16, u16, u32); 8] = [
        (256, 4, width),          // ImageWidth, LONG
        (257, 4, height),         // ImageLength
        (258, 3, 8),              // BitsPerSample, SHORT
        (259, 3, 1),              // Compression: none
        (262, 3, 1),              // Photometric: black is zero
        (273, 4, 0x7fff_0000),    // StripOffsets: far outside the file
        (278, 4, height),         // RowsPerStrip
        (279, 4, width * height), // StripByteCounts
    ];
    let mut bytes = b"II*\0".to_vec();
    bytes.extend_from_slice(&8u32.to_le_bytes());
    bytes.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    for (tag, kind, value) in entries {
        bytes.extend_from_slice(&tag.to_le_bytes());
        bytes.extend_from_slice(&kind.to_le_bytes());
        bytes.extend_from_slice(&1u32.to_le_bytes());
        if kind == 3 {
            bytes.extend_from_slice(&(value as u16).to_le_bytes());
            bytes.extend_from_slice(&[0, 0]);
        } else {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
    }
    bytes.extend_from_slice(&0u32.to_le_bytes());
    bytes.extend_from_slice(&[0; 64]);
    bytes
}

/// The smaller issue: a truncated PNG or a TIFF whose strips point outside
/// the file passed the header check and got 202; now each is decoded
/// before the answer and refused with 415 (as any file that does not
/// decode) naming the camera.
#[tokio::test]
async fn corrupt_images_are_refused_at_upload() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let frame = rig.render(50, 3);
    let mut files: Vec<Vec<u8>> = frame.images.iter().map(png).collect();

    let whole = files[1].clone();
    files[1].truncate(whole.len() / 2);
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 415, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(
        detail.contains("cam1") && detail.contains("truncated or corrupt"),
        "{detail}"
    );
    files[1] = whole;

    let sensor = rig.cameras[2].sensor();
    files[2] = tiff_with_bad_strip_offset(sensor.width, sensor.height);
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 415, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(detail.contains("cam2"), "{detail}");

    // Nothing was stored: the frame uploads with good images.
    files[2] = png(&frame.images[2]);
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    app.stop().await;
}
