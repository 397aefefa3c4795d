//! Issue 29, defect 3 and the memory budget: a computed median background
//! is streamed one camera at a time, and the workers admit jobs within
//! `--memory-budget-mb` (`service::budget`), so that large jobs queued at
//! once wait for each other instead of all running and the server being
//! killed for memory; a job that can never fit fails once with the reason.
//!
//! Before: two 8192x8192 16-bit cameras' median background over 32 frames
//! held every camera's 32 frames at once (8.3 GiB with one worker); two
//! workers computing two such backgrounds were OOM-killed, in a crash loop
//! after every restart.

use std::time::{Duration, Instant};

use ptv::photogrammetry::GreyImage;
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};

use crate::helpers::{
    logged_grants, png, rig, status_and_json, targets_form, upload as upload_form,
    wait_for_sequence, LoggedGrant, ServiceProcess,
};

/// The largest sensor side the service takes.
const SIDE: u32 = 8192;

/// A calibration of two `side` x `side` cameras looking at one volume.
fn calibration(side: u32) -> Value {
    let camera = |position: [f64; 3], angles: [f64; 3]| {
        json!({"image_size": [side, side], "pixel_size": [0.012, 0.012],
               "position": position, "angles": angles, "principal_distance": 50,
               "media": {"walls": [{"n": 1.5, "thickness": 10}], "n_object": 1.33,
                         "glass_vector": [0, 0, 100]}})
    };
    json!({"cameras": [camera([0.0, 0.0, 600.0], [0.0, 0.0, 0.0]),
                       camera([300.0, 0.0, 520.0], [0.0, 0.5, 0.0])]})
}

async fn post_json(client: &reqwest::Client, url: String, body: &Value) -> (u16, Value) {
    status_and_json(client.post(url).json(body).send().await.unwrap()).await
}

async fn get_json(client: &reqwest::Client, url: String) -> Value {
    let (status, body) = status_and_json(client.get(url).send().await.unwrap()).await;
    assert_eq!(status, 200, "{body}");
    body
}

/// Uploads frame `frame` of `files` (one per camera); the job's id.
async fn upload(
    client: &reqwest::Client,
    api: &str,
    sequence: i64,
    frame: i64,
    files: &[&[u8]],
) -> i64 {
    let mut form = Form::new().text("frame", frame.to_string());
    for (camera, bytes) in files.iter().enumerate() {
        form = form.part(
            format!("cam{camera}"),
            Part::bytes(bytes.to_vec()).file_name(format!("cam{camera}.png")),
        );
    }
    let response = client
        .post(format!("{api}/sequences/{sequence}/frames"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 202, "{body}");
    body["job_id"].as_i64().unwrap()
}

/// A sequence on `calibration` with `extra` top-level fields; its id.
async fn sequence(client: &reqwest::Client, api: &str, calibration: i64, extra: Value) -> i64 {
    let mut body = json!({"calibration_id": calibration, "name": "budget", "keep_images": true});
    for (key, value) in extra.as_object().unwrap() {
        body[key] = value.clone();
    }
    let (status, body) = post_json(client, format!("{api}/sequences"), &body).await;
    assert_eq!(status, 201, "{body}");
    body["id"].as_i64().unwrap()
}

/// A `side` x `side` 16-bit image of one grey.
fn constant(side: u32) -> Vec<u8> {
    let pixels = vec![1000u16; (side * side) as usize];
    png(&GreyImage::from_u16(side, side, pixels).unwrap())
}

/// A `side` x `side` 16-bit image with a 1-pixel checkerboard over its
/// first `rows` rows: with threshold 1 and one pixel a target, every other
/// pixel there is one (`rows` x `side` / 2 targets).
fn checkerboard(side: u32, rows: u32) -> Vec<u8> {
    let pixels = (0..side)
        .flat_map(|y| {
            (0..side).map(move |x| {
                if y < rows && (x + y) % 2 == 0 {
                    1000
                } else {
                    0
                }
            })
        })
        .collect();
    png(&GreyImage::from_u16(side, side, pixels).unwrap())
}

/// Asserts that no two of `grants` whose MiB together exceed
/// `budget_mib` were held at once: one was released before the other was
/// taken (a grant still held counts as held to the end). Each grant
/// brackets its job's work, so this says the jobs ran one after the
/// other.
fn assert_serialised(grants: &[LoggedGrant], budget_mib: u64) {
    for (i, a) in grants.iter().enumerate() {
        for b in &grants[i + 1..] {
            if a.mib + b.mib <= budget_mib {
                continue;
            }
            let a_before_b = a.released.is_some_and(|end| end <= b.taken);
            let b_before_a = b.released.is_some_and(|end| end <= a.taken);
            assert!(
                a_before_b || b_before_a,
                "{a:?} and {b:?} ran at once, {} MiB together over the budget of {budget_mib} MiB",
                a.mib + b.mib
            );
        }
    }
}

/// The frames a background is computed from: 16 rather than the 32 of
/// the probe, to keep the test's time (two backgrounds decode
/// 2 x 2 x 16 images of 8192x8192); enough that two backgrounds do not
/// fit the budget together.
const FRAMES: u64 = 16;

/// The needs the service declares for this test's jobs
/// (`service::budget`), MiB: a median background of two 8192x8192 16-bit
/// cameras over [`FRAMES`] frames holds one camera's frames (128 MiB
/// each), one decoded frame and its view, the median and its PNG (4 x 128
/// MiB) and the largest file (under 1 MiB); a frame of two such cameras
/// detects one 8192x8192 image at 48 bytes a pixel (3,072 MiB) and
/// matches up to 2^20 targets a camera at 256 bytes (2 x 256 MiB).
const BACKGROUND_NEED_MIB: u64 = FRAMES * 128 + 4 * 128 + 1;
const FRAME_NEED_MIB: u64 = 3072 + 512;

/// Two sequences whose median backgrounds each need
/// [`BACKGROUND_NEED_MIB`], and two frames of a 1-px checkerboard (over
/// 1,024 rows: 4.2 M targets, past the per-camera limit of 1 M; the whole
/// image takes a minute to detect in the dev build) detected with
/// threshold 1 and 1-pixel targets, each needing [`FRAME_NEED_MIB`], all
/// queued at once on two workers with a budget that holds the largest job
/// but no two: they run one after the other, nothing crashes, and the
/// server's peak memory stays within its idle peak plus the budget.
/// Without the budget the two backgrounds and two detections would run
/// two at a time.
#[tokio::test(flavor = "multi_thread")]
async fn large_jobs_queued_at_once_run_one_after_the_other_within_the_budget() {
    // The largest job fits; no two do.
    let budget_mib = BACKGROUND_NEED_MIB.max(FRAME_NEED_MIB) + 100;
    assert!(budget_mib < 2 * BACKGROUND_NEED_MIB.min(FRAME_NEED_MIB));
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("server.log");
    let server = ServiceProcess::start_logged(
        dir.path(),
        2,
        &["--memory-budget-mb", &budget_mib.to_string()],
        &log,
    );
    let client = reqwest::Client::new();
    let api = format!("{}/api/v1", server.address);
    let (status, body) =
        post_json(&client, format!("{api}/calibrations"), &calibration(SIDE)).await;
    assert_eq!(status, 201, "{body}");
    let calibration = body["id"].as_i64().unwrap();
    let hostile = json!({"detection": {"threshold": 1, "min_pixels": 1, "min_snr": 0}});
    let background = json!({"background": {"mode": "median", "frames": FRAMES}});
    let detections = [
        sequence(&client, &api, calibration, hostile.clone()).await,
        sequence(&client, &api, calibration, hostile).await,
    ];
    let backgrounds = [
        sequence(&client, &api, calibration, background.clone()).await,
        sequence(&client, &api, calibration, background).await,
    ];
    // The idle server, its sequences' pipelines prepared.
    let idle_mib = server.peak_memory_mib();

    let started = Instant::now();
    let (flat, board) = (constant(SIDE), checkerboard(SIDE, 1024));
    let mut detection_jobs = Vec::new();
    for sequence in detections {
        detection_jobs.push(upload(&client, &api, sequence, 0, &[&board, &flat]).await);
    }
    for sequence in backgrounds {
        for frame in 0..FRAMES as i64 {
            upload(&client, &api, sequence, frame, &[&flat, &flat]).await;
        }
    }

    // Until both backgrounds are computed and both detections ended (the
    // backgrounds' frames themselves are not waited for).
    loop {
        assert!(
            started.elapsed() < Duration::from_secs(600),
            "the jobs did not end in 10 minutes"
        );
        let mut done = 0;
        for sequence in backgrounds {
            let view = get_json(&client, format!("{api}/sequences/{sequence}")).await;
            done += usize::from(view["background"] == "computed");
        }
        for job in &detection_jobs {
            let view = get_json(&client, format!("{api}/jobs/{job}")).await;
            done += usize::from(view["state"] == "failed" || view["state"] == "succeeded");
        }
        if done == 4 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // When each large job held its memory, from the server's log: the two
    // backgrounds and the two hostile detections (and the backgrounds'
    // frames, detected as they come) each took a grant of their declared
    // need, and no two whose needs exceed the budget together ran at once.
    let grants = logged_grants(&std::fs::read_to_string(&log).unwrap());
    let backgrounds_held: Vec<_> = grants
        .iter()
        .filter(|g| g.what.contains("median background"))
        .collect();
    assert_eq!(backgrounds_held.len(), 2, "{grants:?}");
    assert!(
        backgrounds_held
            .iter()
            .all(|g| g.mib == BACKGROUND_NEED_MIB),
        "{grants:?}"
    );
    let frames_held = grants
        .iter()
        .filter(|g| g.what.contains("detecting and matching"))
        .count();
    assert!(frames_held >= 2, "{grants:?}");
    assert_serialised(&grants, budget_mib);
    // The hostile frames ended with a reason, not a crash.
    for job in &detection_jobs {
        let view = get_json(&client, format!("{api}/jobs/{job}")).await;
        assert_eq!(view["attempts"], 1, "{view}");
    }
    // Still serving: nothing was killed.
    let health = client
        .get(format!("{}/healthz", server.address))
        .send()
        .await
        .unwrap();
    assert_eq!(health.status().as_u16(), 200);
    let peak = server.peak_memory_mib();
    let bound = idle_mib + budget_mib as f64;
    assert!(
        peak <= bound,
        "peak {peak:.0} MiB, more than the idle {idle_mib:.0} MiB plus the budget of \
         {budget_mib} MiB"
    );
    eprintln!(
        "budget: peak {peak:.0} MiB (idle {idle_mib:.0} + budget {budget_mib}), {:.1} s",
        started.elapsed().as_secs_f64()
    );
}

/// A frame whose declared need exceeds the whole budget fails at its first
/// attempt, with a message that says so and what to do; it is not retried
/// (one attempt), and the server stays up.
#[tokio::test(flavor = "multi_thread")]
async fn a_job_that_can_never_fit_fails_once_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    // A frame of two 1024x1024 cameras needs 48 MiB to detect and 2 x 64
    // MiB of possible targets to match: 176 MiB, more than 100.
    let server = ServiceProcess::start_with(dir.path(), 1, &["--memory-budget-mb", "100"]);
    let client = reqwest::Client::new();
    let api = format!("{}/api/v1", server.address);
    let (status, body) =
        post_json(&client, format!("{api}/calibrations"), &calibration(1024)).await;
    assert_eq!(status, 201, "{body}");
    let sequence = sequence(&client, &api, body["id"].as_i64().unwrap(), json!({})).await;
    let flat = constant(1024);
    let job = upload(&client, &api, sequence, 0, &[&flat, &flat]).await;
    let started = Instant::now();
    let view = loop {
        let view = get_json(&client, format!("{api}/jobs/{job}")).await;
        if view["state"] == "failed" {
            break view;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the job did not fail: {view}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(view["attempts"], 1, "{view}");
    let error = view["error"].as_str().unwrap();
    assert!(error.contains("needs about 176 MiB"), "{error}");
    assert!(error.contains("memory budget of 100 MiB"), "{error}");
    assert!(error.contains("--memory-budget-mb"), "{error}");
    // Given time to be taken again, it is not.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let again = get_json(&client, format!("{api}/jobs/{job}")).await;
    assert_eq!(again["attempts"], 1, "{again}");
    assert_eq!(again["state"], "failed", "{again}");
    // The budget shows in /metrics.
    let metrics = client
        .get(format!("{}/metrics", server.address))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(metrics.contains("ptv_memory_budget_mib 100\n"), "{metrics}");
}

/// Self-calibrations take their memory from the budget too, their need
/// derived from the stored target counts of their frames
/// (`budget::selfcal_need`): two queued at once on two workers with a
/// budget that holds one of them but not both run one after the other.
/// The frames are processed first under the default budget (a frame of
/// the rig's four 1280x1024 cameras declares 4 x 80 MiB of matching), and
/// the server restarted on the same data with the small budget.
#[tokio::test(flavor = "multi_thread")]
async fn self_calibrations_queued_at_once_run_one_after_the_other_within_the_budget() {
    const FRAMES: i64 = 4;
    const PARTICLES: usize = 1000;
    let dir = tempfile::tempdir().unwrap();
    let rig = rig();
    let client = reqwest::Client::new();
    let mut targets = 0u64;
    let sequence = {
        let server = ServiceProcess::start(dir.path(), 1);
        let api = format!("{}/api/v1", server.address);
        let response = client
            .post(format!("{api}/calibrations"))
            .header("content-type", "application/json")
            .body(ptv::formats::calibration::to_json(&rig.cameras))
            .send()
            .await
            .unwrap();
        let (status, body) = status_and_json(response).await;
        assert_eq!(status, 201, "{body}");
        let sequence = sequence(&client, &api, body["id"].as_i64().unwrap(), json!({})).await;
        for frame in 0..FRAMES {
            let frame_targets = rig.targets(PARTICLES, 7 + frame as u64);
            targets += frame_targets
                .targets
                .iter()
                .map(|c| c.len() as u64)
                .sum::<u64>();
            let (status, body) = upload_form(
                &client,
                &server.address,
                sequence,
                targets_form(frame, &frame_targets),
            )
            .await;
            assert_eq!(status, 202, "{body}");
        }
        let view = wait_for_sequence(&client, &server.address, sequence).await;
        assert_eq!(view["frames"]["done"], FRAMES, "{view}");
        sequence
    };
    // The need the service declares: every stored target of the frames.
    let log = dir.path().join("server.log");
    let need = ptv::service::budget::selfcal_need(targets, 4, FRAMES as usize).mib();
    assert!(need >= 4, "{targets} targets: {need} MiB");
    // One fits, two do not.
    let budget_mib = need + need / 2;
    let server = ServiceProcess::start_logged(
        dir.path(),
        2,
        &["--memory-budget-mb", &budget_mib.to_string()],
        &log,
    );
    let api = format!("{}/api/v1", server.address);
    let mut jobs = Vec::new();
    for _ in 0..2 {
        let (status, body) = post_json(
            &client,
            format!("{api}/sequences/{sequence}/self-calibration"),
            &json!({"tolerance": 2.0}),
        )
        .await;
        assert_eq!(status, 202, "{body}");
        jobs.push(body["job_id"].as_i64().unwrap());
    }
    let started = Instant::now();
    for job in &jobs {
        loop {
            let view = get_json(&client, format!("{api}/jobs/{job}")).await;
            if view["state"] == "succeeded" || view["state"] == "failed" {
                assert_eq!(view["attempts"], 1, "{view}");
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(300),
                "the self-calibrations did not end: {view}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    let grants: Vec<_> = logged_grants(&std::fs::read_to_string(&log).unwrap())
        .into_iter()
        .filter(|g| g.what.starts_with("self-calibrating"))
        .collect();
    assert_eq!(grants.len(), 2, "{grants:?}");
    assert!(
        grants.iter().all(|g| g.mib == need),
        "{grants:?} for {need} MiB"
    );
    assert!(2 * need > budget_mib);
    assert_serialised(&grants, budget_mib);
}
