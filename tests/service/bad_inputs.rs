//! Bad requests: each gets its 4xx as problem+json (checked by
//! `status_and_json`), nothing panics, and the database holds only what
//! good requests stored.

use std::io::{Read, Write};

use reqwest::multipart::{Form, Part};
use serde_json::json;

use crate::helpers::*;

/// Sends raw bytes over TCP and returns the status of the answer.
fn raw_request(address: &str, request: &[u8]) -> (u16, String) {
    let host = address.strip_prefix("http://").unwrap();
    let mut stream = std::net::TcpStream::connect(host).unwrap();
    stream.write_all(request).unwrap();
    let _ = stream.shutdown(std::net::Shutdown::Write);
    let mut answer = String::new();
    let _ = stream.read_to_string(&mut answer);
    let status = answer
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status in `{answer}`"));
    (status, answer)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_their_4xx_and_store_nothing() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let rendered = rig.render(50, 3);
    let files: Vec<Vec<u8>> = rendered.images.iter().map(png).collect();
    let frames = format!("/sequences/{sequence}/frames");

    // Invalid JSON, JSON of the wrong shape, not JSON at all.
    let send = |path: &str, content_type: &'static str, body: &'static str| {
        app.client
            .post(app.api(path))
            .header("content-type", content_type)
            .body(body)
            .send()
    };
    for (path, content_type, body, expected) in [
        ("/calibrations", "application/json", "{\"cameras\": [", 400),
        ("/calibrations", "application/json", "{\"cameras\": 3}", 422),
        ("/calibrations", "text/plain", "{}", 415),
        ("/sequences", "application/json", "not json", 400),
        (
            "/sequences",
            "application/json",
            "{\"calibration_id\": \"one\"}",
            422,
        ),
        (
            "/sequences",
            "application/json",
            "{\"calibration_id\": 1, \"colour\": 1}",
            422,
        ),
        (
            "/sequences",
            "application/json",
            "{\"calibration_id\": 1, \"detection\": {\"min_pixels\": 9, \"max_pixels\": 3}}",
            422,
        ),
        (
            "/sequences",
            "application/json",
            "{\"calibration_id\": 1, \"matching\": {\"volume\": [1, 0, 0, 1, 0, 1]}}",
            422,
        ),
        (
            "/sequences",
            "application/json",
            "{\"calibration_id\": 1, \"matching\": {\"tolerance\": -1}}",
            422,
        ),
        (
            "/calibrations/1/project",
            "application/json",
            "{\"points\": [[1, 2]]}",
            422,
        ),
        (
            "/calibrations/1/intersect",
            "application/json",
            "{\"pixels\": [[1, 2]]}",
            422,
        ),
    ] {
        let (status, body) = status_and_json(send(path, content_type, body).await.unwrap()).await;
        assert_eq!(status, expected, "{path} {body}");
        assert!(
            body["detail"].as_str().is_some_and(|d| !d.is_empty()),
            "{body}"
        );
    }

    // Unknown ids and malformed ones.
    for (path, expected) in [
        ("/calibrations/999".to_owned(), 404),
        ("/calibrations/abc".to_owned(), 400),
        ("/sequences/999".to_owned(), 404),
        ("/jobs/999".to_owned(), 404),
        (format!("/sequences/{sequence}/frames/5/particles"), 404),
        (
            format!("/sequences/{sequence}/frames/5/targets?camera=0"),
            404,
        ),
        (format!("/sequences/{sequence}/frames/0/targets"), 400),
        (
            format!("/sequences/{sequence}/frames/0/particles?format=xml"),
            400,
        ),
        ("/no/such/route".to_owned(), 404),
    ] {
        let (status, body) = app.get_json(&path).await;
        assert_eq!(status, expected, "{path} {body}");
    }
    let (status, body) = app
        .post_json("/sequences", &json!({"calibration_id": 999}))
        .await;
    assert_eq!(status, 422, "{body}");
    let (status, body) = app.upload(999, image_form(0, &files)).await;
    assert_eq!(status, 404, "{body}");

    // A path-like sequence name.
    let (status, body) = app
        .post_json(
            "/sequences",
            &json!({"calibration_id": calibration, "name": "../../etc/passwd"}),
        )
        .await;
    assert_eq!(status, 422, "{body}");

    // Uploads: wrong camera count, corrupt image, wrong size, unknown and
    // path-like part names, images and targets mixed, raw of the wrong
    // length, no frame number, repeated parts, not multipart.
    let garbage = b"this is not an image at all".to_vec();
    let small = png(&ptv::photogrammetry::GreyImage::from_u8(64, 64, vec![0; 64 * 64]).unwrap());
    let cases: Vec<(Form, u16, &str)> = vec![
        (image_form(0, &files[..3]), 422, "3 were given"),
        (
            image_form(
                0,
                &[
                    files[0].clone(),
                    garbage.clone(),
                    files[2].clone(),
                    files[3].clone(),
                ],
            ),
            415,
            "cam1",
        ),
        (
            image_form(
                0,
                &[files[0].clone(), files[1].clone(), small, files[3].clone()],
            ),
            422,
            "64x64",
        ),
        (
            image_form(0, &files).text("../cam0", "x"),
            400,
            "unknown part",
        ),
        (image_form(0, &files).text("cam4", "x"), 422, "cam0 to cam3"),
        (
            image_form(0, &files).text("targets0", "x,y\n1,2\n"),
            400,
            "not both",
        ),
        (
            image_form(0, &files)
                .text("width", "1280")
                .text("height", "1024")
                .text("bits", "8"),
            422,
            "raw",
        ),
        (
            Form::new().part("cam0", Part::bytes(files[0].clone())),
            400,
            "`frame` part is missing",
        ),
        (image_form(0, &files).text("frame", "1"), 400, "twice"),
        (Form::new().text("frame", "-3"), 400, "non-negative"),
        (
            Form::new()
                .text("frame", "0")
                .text("targets0", "x,y\n1,nan\n"),
            422,
            "targets0",
        ),
    ];
    for (index, (form, expected, needle)) in cases.into_iter().enumerate() {
        let (status, body) = app.upload(sequence, form).await;
        assert_eq!(status, expected, "case {index}: {body}");
        assert!(
            body["detail"].as_str().unwrap().contains(needle),
            "case {index}: {body}"
        );
    }
    let response = app
        .client
        .post(app.api(&frames))
        .json(&json!({"frame": 0}))
        .send()
        .await
        .unwrap();
    assert_eq!(status_and_json(response).await.0, 415);

    // A truncated multipart body (the closing boundary never comes).
    let body = "--XYZ\r\nContent-Disposition: form-data; name=\"frame\"\r\n\r\n0\r\n--XYZ\r\n\
                Content-Disposition: form-data; name=\"cam0\"; filename=\"a.png\"\r\n\r\n\x07\x07";
    let response = app
        .client
        .post(app.api(&frames))
        .header("content-type", "multipart/form-data; boundary=XYZ")
        .body(body)
        .send()
        .await
        .unwrap();
    let (status, problem) = status_and_json(response).await;
    assert_eq!(status, 400, "{problem}");

    // A 2 GB body is refused from its declared length, before it is read.
    let host = app.address.strip_prefix("http://").unwrap().to_owned();
    let address = app.address.clone();
    let path = app.api(&frames).replacen(&address, "", 1);
    let (status, answer) = tokio::task::spawn_blocking(move || {
        raw_request(
            &address,
            format!(
                "POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: multipart/form-data; \
                 boundary=XYZ\r\nContent-Length: 2147483648\r\n\r\n--XYZ\r\n"
            )
            .as_bytes(),
        )
    })
    .await
    .unwrap();
    assert_eq!(status, 413, "{answer}");
    assert!(answer.contains("application/problem+json"), "{answer}");

    // A streamed body (no declared length) is cut off at the limit (64 MiB
    // here) without being held whole: send 65 MiB of one image part.
    let url = app.api(&frames);
    let (status, detail) = {
        let chunk = vec![0u8; 1 << 20];
        let head = "--XYZ\r\nContent-Disposition: form-data; name=\"frame\"\r\n\r\n7\r\n--XYZ\r\n\
                    Content-Disposition: form-data; name=\"cam0\"; filename=\"big\"\r\n\r\n";
        let parts = std::iter::once(Ok::<_, std::io::Error>(head.as_bytes().to_vec()))
            .chain((0..65).map(move |_| Ok(chunk.clone())));
        let body = reqwest::Body::wrap_stream(futures_util::stream::iter(parts));
        let result = app
            .client
            .post(url)
            .header("content-type", "multipart/form-data; boundary=XYZ")
            .body(body)
            .send()
            .await;
        match result {
            Ok(response) => {
                let (status, body) = status_and_json(response).await;
                (status, body.to_string())
            }
            // The server may close the connection while the client still
            // sends; then it must have answered 413 first, which the
            // metrics record.
            Err(error) => (0, error.to_string()),
        }
    };
    if status != 0 {
        assert_eq!(status, 413, "{detail}");
    }

    // One good upload, then the same frame again: 409.
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 202, "{body}");
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 409, "{body}");
    app.wait_for_sequence(sequence).await;

    let metrics = app.get_text(format!("{}/metrics", app.address)).await;
    assert!(!metrics.contains("status=\"5"), "{metrics}");
    assert!(
        metrics.contains("route=\"/api/v1/sequences/{id}/frames\",status=\"413\"} 2"),
        "{metrics}"
    );

    // The database holds the good frame only, its 4 images, and the
    // image store its 4 files; no upload is left half-written.
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM frames").await, 1);
    assert_eq!(count(&db, "SELECT count(*) FROM jobs").await, 1);
    assert_eq!(count(&db, "SELECT count(*) FROM images").await, 4);
    assert_eq!(count(&db, "SELECT count(*) FROM sequences").await, 1);
    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 1);
    let stored = stored_images(app.data_dir.path()).await;
    assert_eq!(stored.len(), 4, "{stored:?}");
    let temporary = crate::api::walk(&app.data_dir.path().join("tmp"));
    assert!(temporary.is_empty(), "{temporary:?}");
    app.stop().await;
}

/// Bad solve requests: each gets its 4xx saying what to fix, and no job,
/// file row or image file is left behind.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_solve_requests_get_their_4xx_and_store_nothing() {
    let app = spawn_app().await;
    let rig = rig();
    let input = rig.solve_input(60, 0.05, 9);
    let with = |setup: &str, control: Option<&str>, observations: &[String]| {
        let mut form = Form::new().text("setup", setup.to_owned());
        if let Some(control) = control {
            form = form.text("control", control.to_owned());
        }
        for text in observations {
            form = form.text("observations", text.clone());
        }
        form
    };
    let cases: Vec<(&str, Form, u16, &str)> =
        vec![
        (
            "missing control",
            with(&input.setup, None, &input.observations),
            400,
            "the `control` part is missing",
        ),
        (
            "missing setup",
            Form::new().text("control", input.control.clone()),
            400,
            "the `setup` part is missing",
        ),
        (
            "three observation parts for four cameras",
            with(&input.setup, Some(&input.control), &input.observations[..3]),
            422,
            "the setup has 4 cameras but 3 `observations` parts were given",
        ),
        (
            "no observations or images",
            with(&input.setup, Some(&input.control), &[]),
            422,
            "give per camera",
        ),
        (
            "garbage control file",
            with(
                &input.setup,
                Some("1 0 0 0\n2 0 zero 0\n"),
                &input.observations,
            ),
            422,
            "part `control`: line 2: Y must be a finite number, got `zero`",
        ),
        (
            "garbage observations",
            with(
                &input.setup,
                Some(&input.control),
                &[
                    input.observations[0].clone(),
                    "1 2\n".to_owned(),
                    input.observations[2].clone(),
                    input.observations[3].clone(),
                ],
            ),
            422,
            "part `observations` of camera 1: line 1: expected 3 fields",
        ),
        (
            "setup is not a calibration",
            with(
                "{\"cameras\": 3}",
                Some(&input.control),
                &input.observations,
            ),
            422,
            "part `setup`",
        ),
        (
            "unknown options field",
            input.form(Some(&json!({"check_evry": 5}))),
            422,
            "unknown field `check_evry`",
        ),
        (
            "unknown fixed parameter",
            input.form(Some(&json!({"fix": ["k4"]}))),
            422,
            "part `options`: fix: unknown parameter `k4`; the names are x0,y0,z0,",
        ),
        (
            "check_every of 1",
            input.form(Some(&json!({"check_every": 1}))),
            422,
            "check_every: K must be at least 2",
        ),
        (
            "5 control points",
            with(
                &input.setup,
                Some("1 0 0 0\n2 0 1 0\n3 1 0 0\n4 1 1 0\n5 0 0 1\n"),
                &input.observations,
            ),
            422,
            "5 control points given; a calibration needs at least 6",
        ),
        (
            "a fixed parameter the setup gives no value for",
            with(&input.bare_setup(None), Some(&input.control), &input.observations)
                .text("options", json!({"fix": ["c"]}).to_string()),
            422,
            "camera 0 (cam1): c is fixed, but the setup gives no principal_distance",
        ),
        (
            "images of cameras without orientation or reference points",
            (0..4).fold(
                Form::new()
                    .text("setup", input.bare_setup(None))
                    .text("control", input.control.clone()),
                |form, _| form.part("image", Part::bytes(b"not looked at".to_vec())),
            ),
            422,
            "its marks must be identified in the image, but the setup gives no position, \
             angles, principal_distance to project the control points with, and no reference \
             points were given; give reference points",
        ),
        (
            "a setup camera without its sensor",
            with(
                &input.bare_setup(Some("image_size")),
                Some(&input.control),
                &input.observations,
            ),
            422,
            "part `setup`: cameras[1].image_size: missing: every camera needs its sensor and media",
        ),
        (
            "a setup camera without its media",
            with(
                &input.bare_setup(Some("media")),
                Some(&input.control),
                &input.observations,
            ),
            422,
            "cameras[1].media: missing",
        ),
        (
            "unknown part",
            input.form(None).text("colour", "red"),
            400,
            "unknown part `colour`",
        ),
        (
            "setup twice",
            input.form(None).text("setup", input.setup.clone()),
            400,
            "part `setup` is given twice",
        ),
        (
            "image that is not an image",
            Form::new()
                .text("setup", input.setup.clone())
                .text("control", input.control.clone())
                .part("image", Part::bytes(b"not an image".to_vec()))
                .part("image", Part::bytes(b"not an image".to_vec()))
                .part("image", Part::bytes(b"not an image".to_vec()))
                .part("image", Part::bytes(b"not an image".to_vec())),
            415,
            "part `image` of camera 0: format: neither a PNG nor a TIFF image",
        ),
    ];
    for (case, form, status, detail) in cases {
        let (got, body) = app.solve(form).await;
        assert_eq!(got, status, "{case}: {body}");
        let text = body["detail"].as_str().unwrap_or_default();
        assert!(text.contains(detail), "{case}: `{text}` lacks `{detail}`");
    }
    let (status, body) = app
        .client
        .post(app.api("/calibrations/solve"))
        .header("content-type", "application/json")
        .body("{}")
        .send()
        .await
        .map(|r| (r.status().as_u16(), r))
        .unwrap();
    assert_eq!(status, 415, "{:?}", body.text().await);

    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM jobs").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM job_files").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 0);
    let files = stored_images(app.data_dir.path()).await;
    assert!(files.is_empty(), "{files:?}");
    app.stop().await;
}

/// Input that parses but cannot calibrate (a camera that sees 5 control
/// points) fails its job with the calibration's reason; nothing is stored,
/// and its files are kept as a failed frame's are, surviving a restart's
/// sweep.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_solve_that_cannot_calibrate_fails_its_job_with_the_reason() {
    let app = spawn_app().await;
    let input = rig().solve_input(60, 0.05, 11);
    let first = |text: &str, n: usize| -> String {
        text.lines()
            .take(n)
            .map(|l| format!("{l}\n"))
            .collect::<String>()
    };
    let few = SolveInput {
        setup: input.setup.clone(),
        control: input.control.clone(),
        observations: input.observations.iter().map(|o| first(o, 5)).collect(),
        target: input.target.clone(),
    };
    let (status, body) = app.solve(few.form(None)).await;
    assert_eq!(status, 202, "{body}");
    let job_id = body["job_id"].as_i64().unwrap();
    assert_eq!(body["job"], format!("/api/v1/jobs/{job_id}"));
    let job = app.wait_for_job(job_id).await;
    assert_eq!(job["state"], "failed", "{job}");
    let error = job["error"].as_str().unwrap();
    assert!(
        error.contains("camera 0 (cam1) has 5 usable control points")
            && error.contains("needs at least 9 for 16 free parameters"),
        "{error}"
    );
    assert!(job["result"].is_null(), "{job}");
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM job_files").await, 6);
    db.close().await;

    // A restart's sweep keeps the files the job's rows name.
    let data_dir = app.stop_keeping_data().await;
    let files = stored_images(data_dir.path()).await;
    assert_eq!(files.len(), 6, "{files:?}");
    let restarted = spawn_app_in(data_dir).await;
    let files = stored_images(restarted.data_dir.path()).await;
    assert_eq!(files.len(), 6, "{files:?}");
    restarted.stop().await;
}
