//! `ptv upload`, the binary, against a real in-process service (and a
//! flaky stand-in for it): a recording of the simulator's rig goes up and
//! is processed (`--follow`), a second run resumes (every frame already
//! there), a frame whose file is missing fails with its path while the
//! others go on, a 422 is reported with the server's detail, 503/500
//! answers are retried, an unreachable server is given up on.

use std::path::Path;
use std::process::Output;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::json;

use super::helpers::{png, spawn_app, spawn_app_with};

/// Runs `ptv upload ARGS` as a process (off the runtime's threads).
async fn upload(args: Vec<String>) -> Output {
    tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_ptv"))
            .arg("upload")
            .args(&args)
            .output()
            .expect("the ptv binary runs")
    })
    .await
    .unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// `--server URL --sequence ID --images P0 P1 ... --frames F` and `extra`.
fn args(server: &str, sequence: i64, patterns: &[String], frames: &str) -> Vec<String> {
    let mut args = vec![
        "--server".to_owned(),
        server.to_owned(),
        "--sequence".to_owned(),
        sequence.to_string(),
        "--frames".to_owned(),
        frames.to_owned(),
        "--images".to_owned(),
    ];
    args.extend(patterns.iter().cloned());
    args
}

/// Writes frames `frames` of the rig as `dir/camC.F.png`; the patterns.
fn write_recording(
    dir: &Path,
    rig: &super::helpers::Rig,
    frames: std::ops::RangeInclusive<u64>,
) -> Vec<String> {
    for frame in frames {
        let rendered = rig.render(40, frame);
        for (camera, image) in rendered.images.iter().enumerate() {
            std::fs::write(dir.join(format!("cam{camera}.{frame}.png")), png(image)).unwrap();
        }
    }
    (0..rig.cameras.len())
        .map(|c| dir.join(format!("cam{c}.%d.png")).display().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recording_goes_up_is_processed_and_a_second_run_resumes() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let dir = tempfile::tempdir().unwrap();
    let patterns = write_recording(dir.path(), &rig, 1..=3);

    let mut first = args(&app.address, sequence, &patterns, "1..3");
    first.extend(["--jobs".into(), "2".into(), "--follow".into()]);
    let out = upload(first).await;
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(
        stdout.contains("accepted: 3, already there: 0, failed: 0"),
        "{stdout}"
    );
    // --follow waited for the jobs: all three processed.
    assert!(
        stdout.contains(&format!("sequence {sequence}: done: 3, failed: 0")),
        "{stdout}"
    );
    let view = app.get_json(&format!("/sequences/{sequence}")).await.1;
    assert_eq!(view["frames"]["done"], 3, "{view}");
    // The stderr is not a terminal: no progress bar drawn.
    assert!(out.stderr.is_empty(), "{}", text(&out.stderr));

    // Again, one frame more whose files do not exist: the three are there
    // already, the fourth fails with its path, the exit code says so.
    let out = upload(args(&app.address, sequence, &patterns, "1..4")).await;
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(
        stdout.contains("accepted: 0, already there: 3, failed: 1"),
        "{stdout}"
    );
    let missing = dir.path().join("cam0.4.png").display().to_string();
    assert!(
        stdout.contains(&format!("frame 4 failed: {missing}")),
        "{stdout}"
    );
    let stderr = text(&out.stderr);
    assert!(
        stderr.starts_with("error: upload: 1 of 4 frames failed"),
        "{stderr}"
    );
    let view = app.get_json(&format!("/sequences/{sequence}")).await.1;
    assert_eq!(view["frames"]["done"], 3, "nothing uploaded twice: {view}");
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_frame_is_reported_with_the_servers_detail() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let dir = tempfile::tempdir().unwrap();
    let patterns = write_recording(dir.path(), &rig, 1..=2);
    // Frame 2's camera 1 image is 16x16, not the camera's 1280x1024: 422.
    let small = ptv::photogrammetry::GreyImage::from_u8(16, 16, vec![0; 256]).unwrap();
    std::fs::write(dir.path().join("cam1.2.png"), png(&small)).unwrap();
    let out = upload(args(&app.address, sequence, &patterns, "1..2")).await;
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(
        stdout.contains("accepted: 1, already there: 0, failed: 1"),
        "{stdout}"
    );
    let line = stdout
        .lines()
        .find(|l| l.starts_with("frame 2 failed: "))
        .unwrap_or_else(|| panic!("{stdout}"));
    // The problem+json detail, as the server wrote it.
    assert!(
        line.contains("422 Unprocessable Entity: cam1") && line.contains("16x16"),
        "{line}"
    );
    // Patterns that do not match the calibration's cameras: refused before
    // any upload.
    let out = upload(args(&app.address, sequence, &patterns[..3], "1..2")).await;
    assert_eq!(out.status.code(), Some(1));
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("calibration has 4 cameras but 3 patterns"),
        "{stderr}"
    );
    app.stop().await;
}

/// A stand-in for the service whose frame route answers 503 with
/// `Retry-After: 0`, then 500, then 202; the requests it got.
async fn flaky_server() -> (String, Arc<AtomicUsize>) {
    let posts = Arc::new(AtomicUsize::new(0));
    let counter = Arc::clone(&posts);
    let app = Router::new()
        .route(
            "/api/v1/sequences/{id}",
            get(|| async { Json(json!({"calibration_id": 5, "frames": {}})) }),
        )
        .route(
            "/api/v1/calibrations/{id}",
            get(|| async { Json(json!({"id": 5, "cameras": 1})) }),
        )
        .route(
            "/api/v1/sequences/{id}/frames",
            post(move |body: axum::body::Bytes| {
                let counter = Arc::clone(&counter);
                async move {
                    assert!(!body.is_empty());
                    match counter.fetch_add(1, Ordering::SeqCst) {
                        0 => (
                            StatusCode::SERVICE_UNAVAILABLE,
                            [(header::RETRY_AFTER, "0")],
                            "busy",
                        )
                            .into_response(),
                        1 => (StatusCode::INTERNAL_SERVER_ERROR, "oops").into_response(),
                        _ => (StatusCode::ACCEPTED, Json(json!({"frame": 1, "job_id": 9})))
                            .into_response(),
                    }
                }
            }),
        );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (address, posts)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unavailable_and_failing_answers_are_retried() {
    let (address, posts) = flaky_server().await;
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("c.1.png"), b"any bytes").unwrap();
    let pattern = dir.path().join("c.%d.png").display().to_string();
    let out = upload(args(&address, 1, std::slice::from_ref(&pattern), "1")).await;
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(
        stdout.contains("accepted: 1, already there: 0, failed: 0"),
        "{stdout}"
    );
    assert_eq!(posts.load(Ordering::SeqCst), 3, "503, 500, then 202");

    // With no retries allowed, the first 5xx is final; the reason is the
    // server's answer.
    let (address, posts) = flaky_server().await;
    let mut once = args(&address, 1, &[pattern], "1");
    once.extend(["--retries".into(), "0".into()]);
    let out = upload(once).await;
    let stdout = text(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(
        stdout.contains("frame 1 failed: gave up after 1 attempts: 503 Service Unavailable: busy"),
        "{stdout}"
    );
    assert_eq!(posts.load(Ordering::SeqCst), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unreachable_server_is_given_up_on_with_the_reason() {
    // A port that was just free: nothing listens there.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut unreachable = args(
        &format!("http://127.0.0.1:{port}"),
        1,
        &["c.%d.png".to_owned()],
        "1..2",
    );
    unreachable.extend(["--retries".into(), "1".into()]);
    let out = upload(unreachable).await;
    assert_eq!(out.status.code(), Some(1));
    assert!(out.stdout.is_empty());
    let stderr = text(&out.stderr);
    assert!(
        stderr.starts_with("error: upload: cannot read sequence 1")
            && stderr.contains("gave up after 2 attempts"),
        "{stderr}"
    );
    let out = upload(args("https://lab:8080", 1, &["c.%d".to_owned()], "1")).await;
    assert!(text(&out.stderr).contains("plain HTTP only"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_is_sent() {
    let app = spawn_app_with(Some("s3cret")).await;
    let patterns = ["c.%d.png".to_owned()];
    // Without the token: the service's 401 and its detail.
    let out = upload(args(&app.address, 77, &patterns, "1")).await;
    let stderr = text(&out.stderr);
    assert!(
        stderr.starts_with("error: upload: cannot read sequence 77")
            && stderr.contains("401")
            && stderr.contains("--token"),
        "{stderr}"
    );
    // With it: past the token check, to the (missing) sequence's 404.
    let mut with_token = args(&app.address, 77, &patterns, "1");
    with_token.extend(["--token".into(), "s3cret".into()]);
    let out = upload(with_token).await;
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("404") && stderr.contains("create the sequence first"),
        "{stderr}"
    );
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_openptv_experiment_goes_up_by_its_own_sequence_parameters() {
    let app = spawn_app().await;
    let dir = super::helpers::repository().join("tests/data/openptv/test_cavity_recording");
    let experiment = ptv::formats::experiment::read_experiment(&dir).unwrap();
    let calibration = app.create_calibration(&experiment.cameras).await;
    let (status, body) = app
        .post_json(
            "/sequences",
            &json!({"calibration_id": calibration, "keep_images": false}),
        )
        .await;
    assert_eq!(status, 201, "{body}");
    let sequence = body["id"].as_i64().unwrap();
    // No --frames: the experiment's sequence.par says 10001..10004.
    let out = upload(vec![
        "--server".into(),
        app.address.clone(),
        "--sequence".into(),
        sequence.to_string(),
        "--experiment".into(),
        dir.display().to_string(),
    ])
    .await;
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(
        stdout.contains("accepted: 4, already there: 0, failed: 0"),
        "{stdout}"
    );
    let view = app.wait_for_sequence(sequence).await;
    let frames = &view["frames"];
    assert_eq!(
        frames["done"].as_i64().unwrap() + frames["failed"].as_i64().unwrap(),
        4,
        "{view}"
    );
    app.stop().await;
}
