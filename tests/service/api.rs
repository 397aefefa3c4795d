//! The API's main paths.

use ptv::formats;
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};

use crate::helpers::*;

/// Frames of the experiment.
const FRAMES: i64 = 20;
/// Particles per frame.
const PARTICLES: usize = 300;

/// Control points of the calibration target.
const CONTROL_POINTS: usize = 150;
/// Noise of their measured images (px).
const CONTROL_NOISE_PX: f64 = 0.05;

/// `/calibrations/solve` from a setup without orientation fields at all
/// (sensor and media only) reaches the accuracy of the same setup with
/// orientation values: the start comes from the DLT on the observed points.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn solves_a_setup_without_orientation_fields() {
    let app = spawn_app().await;
    let rig = rig();
    let input = rig.solve_input(CONTROL_POINTS, CONTROL_NOISE_PX, 7);
    let mut reports = Vec::new();
    for setup in [input.bare_setup(None), input.setup.clone()] {
        let form = Form::new()
            .text("setup", setup)
            .text("control", input.control.clone())
            .text("options", json!({"check_every": 5}).to_string());
        let form = input
            .observations
            .iter()
            .fold(form, |form, text| form.text("observations", text.clone()));
        let (status, body) = app.solve(form).await;
        assert_eq!(status, 202, "{body}");
        let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
        assert_eq!(job["state"], "succeeded", "{job}");
        let (status, solved) = app
            .get_json(
                job["result"]
                    .as_str()
                    .unwrap()
                    .strip_prefix("/api/v1")
                    .unwrap(),
            )
            .await;
        assert_eq!(status, 200, "{solved}");
        reports.push(solved["report"].clone());
    }
    let rmse = |report: &Value| report["check_points"]["rmse_mm"].as_f64().unwrap();
    let (bare, oriented) = (rmse(&reports[0]), rmse(&reports[1]));
    eprintln!("check-point RMSE: setup without orientation {bare:.5} mm, with it {oriented:.5} mm");
    // Both converge to the same least-squares minimum: equal to the
    // adjustment's convergence tolerance, far below the effect of the
    // 0.05 px noise (the RMSE itself, some um).
    assert!(
        (bare - oriented).abs() < 1e-3 * oriented,
        "{bare} vs {oriented}"
    );
    for report in &reports {
        for camera in report["cameras"].as_array().unwrap() {
            let sigma0 = camera["sigma0_px"].as_f64().unwrap();
            // 120 resection points, redundancy about 224: s/sigma scatters
            // by about 5%.
            assert!(
                (sigma0 / CONTROL_NOISE_PX - 1.0).abs() < 0.25,
                "sigma0 {sigma0}"
            );
        }
    }
    app.stop().await;
}

/// The synthetic experiment end to end: the rig calibrated through
/// `/calibrations/solve` from a setup with no orientation, control points
/// and their noisy images, then a sequence with that calibration, 20
/// frames uploaded as images (PNG and raw alternately), and particles that
/// match the truth.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn synthetic_experiment_gives_the_true_particles() {
    let app = spawn_app().await;
    let rig = rig();
    let input = rig.solve_input(CONTROL_POINTS, CONTROL_NOISE_PX, 5);
    let (status, body) = app
        .solve(input.form(Some(&json!({"check_every": 5, "keep_images": false}))))
        .await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["kind"], "solve_calibration");
    let link = job["result"].as_str().unwrap();
    let calibration: i64 = link
        .strip_prefix("/api/v1/calibrations/")
        .unwrap()
        .parse()
        .unwrap();
    let (status, solved) = app.get_json(&format!("/calibrations/{calibration}")).await;
    assert_eq!(status, 200, "{solved}");
    assert_eq!(solved["cameras"], 4);
    let report = &solved["report"];
    for camera in report["cameras"].as_array().unwrap() {
        let sigma0 = camera["sigma0_px"].as_f64().unwrap();
        assert!(
            (sigma0 / CONTROL_NOISE_PX - 1.0).abs() < 0.25,
            "sigma0 {sigma0} px for {CONTROL_NOISE_PX} px of noise"
        );
    }
    // The honest accuracy of the calibration: the RMSE of the check points
    // (every 5th control point, left out and intersected).
    let checks = &report["check_points"];
    assert_eq!(checks["count"], CONTROL_POINTS / 5, "{checks}");
    let check_rmse = checks["rmse_mm"].as_f64().unwrap();
    eprintln!(
        "solved calibration: check-point RMSE {check_rmse:.5} mm, relative accuracy 1:{:.0}",
        checks["relative_accuracy"].as_f64().unwrap()
    );
    // The solved model is not the truth, but projects like it: a point of
    // the volume lands where the true cameras put it, well within the
    // matching's tolerance.
    let probe = rig.volume.min + (rig.volume.max - rig.volume.min) * 0.3;
    let (status, projected) = app
        .post_json(
            &format!("/calibrations/{calibration}/project"),
            &json!({"points": [[probe.x, probe.y, probe.z]]}),
        )
        .await;
    assert_eq!(status, 200, "{projected}");
    for (camera, pixel) in rig
        .cameras
        .iter()
        .zip(projected["pixels"][0].as_array().unwrap())
    {
        let truth = camera.project(&probe).unwrap();
        let offset =
            (truth.x - pixel[0].as_f64().unwrap()).hypot(truth.y - pixel[1].as_f64().unwrap());
        assert!(offset < 0.1, "projection {offset} px off the truth");
    }
    let sequence = app.create_sequence(calibration, &rig.volume, false).await;

    let mut truth = Vec::new();
    let mut accepted = Vec::new();
    for frame in 0..FRAMES {
        let rendered = rig.render(PARTICLES, 1000 + frame as u64);
        let form = if frame % 2 == 0 {
            image_form(frame, &rendered.images.iter().map(png).collect::<Vec<_>>())
        } else {
            image_form(frame, &rendered.images.iter().map(raw8).collect::<Vec<_>>())
                .text("width", "1280")
                .text("height", "1024")
                .text("bits", "8")
        };
        let (status, body) = app.upload(sequence, form).await;
        assert_eq!(status, 202, "{body}");
        assert_eq!(body["frame"], frame);
        truth.push(rendered.points);
        accepted.push(body);
    }
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], FRAMES, "{view}");
    // A processed frame's job links to its particles.
    for body in &accepted {
        let (status, job) = app.get_json(&format!("/jobs/{}", body["job_id"])).await;
        assert_eq!(status, 200, "{job}");
        assert_eq!(
            job["result"],
            format!(
                "/api/v1/sequences/{sequence}/frames/{}/particles",
                body["frame"]
            ),
            "{job}"
        );
        assert_eq!(job["result"], body["particles"], "{job}");
    }

    // Each particle's error against the nearest true particle. A pixel
    // spans about 0.15 mm in object space here, and isolated particles are
    // detected to a few hundredths of a pixel, so a third of a pixel,
    // 0.05 mm, separates right particles from wrong ones (the pipeline's
    // tests derive the same bound); the nearest other particle of 300 in
    // 80x80x40 mm is millimetres away. The solved calibration adds its own
    // error, independent of the detection's: its check points are off by
    // `check_rmse` (RMS), so the bound grows by 3 of those, in quadrature.
    let right_within = 0.05f64.hypot(3.0 * check_rmse);
    assert!(
        check_rmse < 0.05 / 3.0,
        "the calibration ({check_rmse} mm RMS) is too poor to tell right particles from wrong"
    );
    let (mut found, mut right) = (0, 0);
    // Per right particle, its largest error along X, Y, Z in units of its
    // reported standard deviation there.
    let mut in_sigmas = Vec::new();
    for (frame, points) in truth.iter().enumerate() {
        let (status, body) = app
            .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
            .await;
        assert_eq!(status, 200, "{body}");
        let particles = body["particles"].as_array().unwrap();
        for p in particles {
            let position = nalgebra::Point3::new(
                p["x"].as_f64().unwrap(),
                p["y"].as_f64().unwrap(),
                p["z"].as_f64().unwrap(),
            );
            let sigma: Vec<f64> = p["sigma"]
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s.as_f64().unwrap())
                .collect();
            assert!(sigma.iter().all(|s| *s > 0.0 && s.is_finite()), "{p}");
            let nearest = points
                .iter()
                .min_by(|a, b| (*a - position).norm().total_cmp(&(*b - position).norm()))
                .unwrap();
            let error = nearest - position;
            found += 1;
            if error.norm() < right_within {
                right += 1;
                in_sigmas.push(
                    (0..3)
                        .map(|axis| (error[axis] / sigma[axis]).abs())
                        .fold(0.0, f64::max),
                );
            }
        }
        // Every format gives the same particles.
        let csv = app
            .get_text(app.api(&format!(
                "/sequences/{sequence}/frames/{frame}/particles?format=csv"
            )))
            .await;
        assert_eq!(csv.lines().count(), particles.len() + 1);
        let rt_is = app
            .get_text(app.api(&format!(
                "/sequences/{sequence}/frames/{frame}/particles?format=rt_is"
            )))
            .await;
        assert_eq!(rt_is.lines().next().unwrap(), particles.len().to_string());
    }
    // Of 20 x 300 particles, those whose images overlap another's in some
    // camera may be lost or shifted (the pipeline's own test finds 294 of
    // 300 within 0.05 mm): at least 97% found right, at most 1% of what is
    // reported wrong.
    let total = FRAMES as usize * PARTICLES;
    eprintln!("{right} of {total} particles within {right_within:.4} mm, {found} reported");
    assert!(
        right * 100 >= total * 97,
        "{right} of {total} particles found right"
    );
    assert!(
        (found - right) * 100 <= found,
        "{} of {found} particles are wrong",
        found - right
    );
    // The reported sigmas are the accuracy: for Gaussian errors with these
    // standard deviations, the largest of the three normalised errors has
    // the median m with (2 Phi(m) - 1)^3 = 1/2, m = 1.38; sigmas off by a
    // factor of 1.5 either way would move it below 0.92 or above 2.07.
    in_sigmas.sort_by(f64::total_cmp);
    let median = in_sigmas[in_sigmas.len() / 2];
    eprintln!("median error {median:.2} sigmas");
    assert!(
        (0.92..=2.07).contains(&median),
        "median error {median} sigmas, expected about 1.38"
    );

    // The targets the particles refer to are there, per camera.
    let (status, body) = app
        .get_json(&format!("/sequences/{sequence}/frames/0/targets?camera=3"))
        .await;
    assert_eq!(status, 200, "{body}");
    assert!(body["targets"].as_array().unwrap().len() >= PARTICLES * 9 / 10);

    // All frames as one CSV with a frame column.
    let all = app
        .get_text(app.api(&format!("/sequences/{sequence}/particles?format=csv")))
        .await;
    assert!(all.starts_with("frame,calibration_id,x,y,z,sx,sy,sz,rms_px,cameras,t0,t1,t2,t3\n"));
    assert_eq!(all.lines().count(), found + 1);

    // The sequence keeps no images: their files are gone once processed.
    // Nor does the solve (`keep_images: false`): its input files are gone.
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM images").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM job_files").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM particles").await, FRAMES);
    let files = stored_images(app.data_dir.path()).await;
    assert!(files.is_empty(), "{files:?}");

    let metrics = app.get_text(format!("{}/metrics", app.address)).await;
    assert!(metrics.contains(&format!(
        "ptv_jobs{{kind=\"process_frame\",state=\"succeeded\"}} {FRAMES}"
    )));
    assert!(metrics.contains("ptv_frame_particles_count 20"));
    assert!(metrics.contains("ptv_queue_depth 0"));
    app.stop().await;
}

/// Files under a directory, recursively.
pub fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut files = Vec::new();
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                files.extend(walk(&path));
            } else {
                files.push(path);
            }
        }
    }
    files
}

/// OpenPTV's test_cavity files make a calibration whose files come back
/// as uploaded, and projecting then intersecting a point gives it back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openptv_calibration_projects_and_intersects() {
    let app = spawn_app().await;
    let dir = repository().join("tests/data/openptv/test_cavity");
    let read = |name: &str| std::fs::read_to_string(dir.join(name)).unwrap();
    let mut form = Form::new().text("ptv_par", read("parameters/ptv.par"));
    for camera in 1..=4 {
        form = form
            .part("ori", Part::text(read(&format!("cal/cam{camera}.tif.ori"))))
            .part(
                "addpar",
                Part::text(read(&format!("cal/cam{camera}.tif.addpar"))),
            );
    }
    let response = app
        .client
        .post(app.api("/calibrations/openptv"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 201, "{body}");
    let id = body["id"].as_i64().unwrap();
    assert_eq!(body["cameras"], 4);
    let (status, body) = app.get_json(&format!("/calibrations/{id}")).await;
    assert_eq!(status, 200);
    assert_eq!(body["model"]["cameras"].as_array().unwrap().len(), 4);
    assert_eq!(body["report"], Value::Null);

    // The .ori comes back as the exporter writes it, and parses to the
    // same camera as the file uploaded.
    let ori = app
        .get_text(app.api(&format!("/calibrations/{id}/openptv/1.ori")))
        .await;
    let ours = formats::openptv::parse_ori(&ori, "served").unwrap();
    let theirs = formats::openptv::parse_ori(&read("cal/cam2.tif.ori"), "file").unwrap();
    assert!((ours.0.position - theirs.0.position).norm() < 1e-6);
    let (status, _) = app
        .get_json(&format!("/calibrations/{id}/openptv/4.ori"))
        .await;
    assert_eq!(status, 404);

    let (status, body) = app
        .post_json(
            &format!("/calibrations/{id}/project"),
            &json!({"points": [[1.0, -2.0, 3.0]]}),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    let pixels = body["pixels"][0].clone();
    assert_eq!(pixels.as_array().unwrap().len(), 4);
    let (status, body) = app
        .post_json(
            &format!("/calibrations/{id}/intersect"),
            &json!({ "pixels": pixels }),
        )
        .await;
    assert_eq!(status, 200, "{body}");
    for (axis, expected) in [1.0, -2.0, 3.0].iter().enumerate() {
        let got = body["point"][axis].as_f64().unwrap();
        assert!((got - expected).abs() < 1e-6, "{body}");
    }
    app.stop().await;
}

/// With `--api-token`, /api needs the bearer; health and metrics do not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_token_is_required_under_api() {
    let app = spawn_app_with(Some("s3cret")).await;
    let get = |path: String, token: Option<&'static str>| {
        let mut request = app.client.get(path);
        if let Some(token) = token {
            request = request.bearer_auth(token);
        }
        async move { request.send().await.unwrap().status().as_u16() }
    };
    assert_eq!(get(app.api("/jobs/1"), None).await, 401);
    assert_eq!(get(app.api("/jobs/1"), Some("wrong")).await, 401);
    assert_eq!(get(app.api("/jobs/1"), Some("s3cret")).await, 404);
    let response = app
        .client
        .post(app.api("/calibrations"))
        .body("{}")
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 401, "{body}");
    assert_eq!(get(format!("{}/healthz", app.address), None).await, 200);
    assert_eq!(get(format!("{}/metrics", app.address), None).await, 200);
    app.stop().await;
}

/// Every parameter of the OpenAPI document is declared where it is
/// taken: a path parameter is a `{name}` of its path (and each `{name}`
/// one), anything else (the queries' `camera`, `format`, `limit`, ...) is
/// not in the path, and a query parameter with a default is optional.
#[test]
fn openapi_parameters_are_declared_where_they_are_taken() {
    let document: Value = serde_json::from_str(&ptv::service::openapi_json()).unwrap();
    let mut queries = 0;
    for (path, operations) in document["paths"].as_object().unwrap() {
        let template: Vec<&str> = path
            .split('/')
            .filter_map(|segment| segment.strip_prefix('{')?.strip_suffix('}'))
            .collect();
        for (method, operation) in operations.as_object().unwrap() {
            let parameters = operation["parameters"]
                .as_array()
                .cloned()
                .unwrap_or_default();
            let mut in_path: Vec<&str> = Vec::new();
            for parameter in &parameters {
                let name = parameter["name"].as_str().unwrap();
                match parameter["in"].as_str().unwrap() {
                    "path" => {
                        assert!(
                            template.contains(&name),
                            "{method} {path}: `{name}` is declared in the path but is not one \
                             of its segments"
                        );
                        assert_eq!(parameter["required"], true, "{method} {path}: `{name}`");
                        in_path.push(name);
                    }
                    "query" => {
                        queries += 1;
                        let described = parameter["description"].as_str().unwrap_or("");
                        if described.contains("default")
                            || parameter["schema"].get("default").is_some()
                        {
                            assert_ne!(
                                parameter["required"], true,
                                "{method} {path}: query `{name}` has a default yet is required"
                            );
                        }
                    }
                    _ => {}
                }
            }
            for name in &template {
                assert!(
                    in_path.contains(name),
                    "{method} {path}: segment `{{{name}}}` is not declared as a path parameter"
                );
            }
        }
    }
    assert!(
        queries > 10,
        "the document declares only {queries} query parameters"
    );
}

/// The OpenAPI document served and committed are the code's. To update
/// the committed one: `PTV_UPDATE_OPENAPI=1 cargo test --test service openapi`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openapi_document_is_committed_and_served() {
    let generated = ptv::service::openapi_json();
    let path = repository().join("openapi/openapi.json");
    if std::env::var_os("PTV_UPDATE_OPENAPI").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &generated).unwrap();
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "openapi/openapi.json differs from the code's document; regenerate it with \
         `PTV_UPDATE_OPENAPI=1 cargo test --test service openapi` and commit it"
    );
    let app = spawn_app().await;
    let served: Value = app
        .client
        .get(format!("{}/openapi.json", app.address))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let expected: Value = serde_json::from_str(&generated).unwrap();
    assert_eq!(served, expected);
    for path in [
        "/api/v1/calibrations",
        "/api/v1/sequences/{id}/frames",
        "/api/v1/jobs/{id}",
    ] {
        assert!(served["paths"].get(path).is_some(), "{path}");
    }
    let docs = app
        .client
        .get(format!("{}/docs/", app.address))
        .send()
        .await
        .unwrap();
    assert_eq!(docs.status(), 200);
    assert!(docs.text().await.unwrap().contains("swagger"));
    app.stop().await;
}

/// Job kinds are an enum dispatched by `match`: a job whose stored kind
/// this service does not know (a database shared with another release)
/// fails at once with a message that names it, and the worker goes on to
/// the next job.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_of_a_kind_nobody_knows_fails_with_a_message() {
    use ptv::service::Application;

    let data_dir = tempfile::tempdir().unwrap();
    let app = Application::build(test_args(data_dir.path(), None))
        .await
        .unwrap();
    let state = app.state();
    let address = format!("http://{}", app.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(app.run_until(async {
        let _ = stopped.await;
    }));
    let unknown = state.store.enqueue("nope", "{}").await.unwrap();
    let also_unknown = state.store.enqueue("echo", "{}").await.unwrap();
    state.wake.notify_one();

    let client = reqwest::Client::new();
    let mut finished = Vec::new();
    for id in [unknown, also_unknown] {
        let start = std::time::Instant::now();
        loop {
            let (status, body) = status_and_json(
                client
                    .get(format!("{address}/api/v1/jobs/{id}"))
                    .send()
                    .await
                    .unwrap(),
            )
            .await;
            assert_eq!(status, 200, "{body}");
            if body["state"] == "succeeded" || body["state"] == "failed" {
                finished.push(body);
                break;
            }
            assert!(start.elapsed() < PATIENCE, "{body}");
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    }
    assert_eq!(finished[0]["state"], "failed");
    assert_eq!(finished[0]["attempts"], 1);
    assert_eq!(
        finished[0]["error"],
        "this service does not know jobs of kind `nope`"
    );
    assert_eq!(finished[1]["state"], "failed");
    assert_eq!(
        finished[1]["error"],
        "this service does not know jobs of kind `echo`"
    );
    let _ = stop.send(());
    server.await.unwrap().unwrap();
}

/// A frame whose image header is fine but whose data is not is refused at
/// upload (415, as any file that does not decode) with the decoder's reason (it used to be accepted and its job
/// failed later); nothing is stored. A frame whose job fails answers 409
/// for its particles: see `job_bounds`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_whose_image_does_not_decode_is_refused_with_the_reason() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let mut files: Vec<Vec<u8>> = rig.render(20, 5).images.iter().map(png).collect();
    let half = files[2].len() / 2;
    files[2].truncate(half);
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 415, "{body}");
    let detail = body["detail"].as_str().unwrap();
    assert!(
        detail.contains("cam2") && detail.contains("truncated or corrupt"),
        "{detail}"
    );
    let (status, body) = app
        .get_json(&format!("/sequences/{sequence}/frames/0/particles"))
        .await;
    assert_eq!(status, 404, "{body}");
    app.stop().await;
}

/// A graceful stop lets running jobs finish: none is left running, and
/// every frame is either processed or still queued for the next start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_graceful_stop_leaves_no_job_running() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let files: Vec<Vec<u8>> = rig.render(200, 8).images.iter().map(png).collect();
    for frame in 0..6 {
        let (status, body) = app.upload(sequence, image_form(frame, &files)).await;
        assert_eq!(status, 202, "{body}");
    }
    // Stop while jobs are queued and running.
    let data_dir = app.stop_keeping_data().await;
    let db_path = data_dir.path().to_owned();
    let db = open_database(&db_path).await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs WHERE state = 'running'").await,
        0
    );
    let done = count(&db, "SELECT count(*) FROM jobs WHERE state = 'succeeded'").await;
    let queued = count(&db, "SELECT count(*) FROM jobs WHERE state = 'queued'").await;
    assert_eq!(done + queued, 6);
    assert_eq!(count(&db, "SELECT count(*) FROM particles").await, done);
}

/// A calibration solved from calibration images: marks rendered at the
/// control points, detected on the server, identified from 12 reference
/// points per camera clicked to a pixel (with 8, one camera's adjustment
/// did not converge in this rig).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_calibration_is_solved_from_images_and_reference_points() {
    let app = spawn_app().await;
    let rig = rig();
    let input = rig.solve_input(100, 0.0, 21);
    let points: Vec<nalgebra::Point3<f64>> = input.target.iter().map(|p| p.position).collect();
    let mut rng = ptv::photogrammetry::simulate::rng(22);
    let rendered = ptv::photogrammetry::simulate::render_frame(
        &rig.cameras,
        &points,
        &ptv::photogrammetry::simulate::RenderSpec::eight_bit(8.0),
        &mut rng,
    );
    let mut form = Form::new()
        .text("setup", input.setup.clone())
        .text("control", input.control.clone())
        .text(
            "options",
            json!({"detection": {"max_pixels": 400, "highpass_radius": 12}, "check_every": 4})
                .to_string(),
        );
    for image in &rendered {
        let reference: Vec<ptv::photogrammetry::calibrate::MarkObservation> = image
            .truth
            .iter()
            .zip(&input.target)
            .filter_map(|(pixel, p)| pixel.map(|pixel| (p.id, pixel)))
            .step_by(7)
            .take(12)
            .map(
                |(id, pixel)| ptv::photogrammetry::calibrate::MarkObservation {
                    id,
                    pixel: pixel.map(|v| v.round()),
                },
            )
            .collect();
        form = form
            .part("image", Part::bytes(png(&image.image)).file_name("cal.png"))
            .text(
                "reference",
                formats::control::format_mark_observations(&reference),
            );
    }
    let (status, body) = app.solve(form).await;
    assert_eq!(status, 202, "{body}");
    let job = app.wait_for_job(body["job_id"].as_i64().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    let (status, solved) = app
        .get_json(
            job["result"]
                .as_str()
                .unwrap()
                .trim_start_matches("/api/v1"),
        )
        .await;
    assert_eq!(status, 200, "{solved}");
    for camera in solved["report"]["cameras"].as_array().unwrap() {
        let used = camera["points_used"].as_u64().unwrap();
        eprintln!(
            "{}: {used} marks used, sigma0 {} px",
            camera["name"], camera["sigma0_px"]
        );
        assert!(used >= 65, "{used} of 75 marks identified and used");
    }
    let checks = &solved["report"]["check_points"];
    let rmse = checks["rmse_mm"].as_f64().unwrap();
    eprintln!("check-point RMSE {rmse} mm");
    // A pixel spans about 0.15 mm here; marks detected to a few hundredths
    // of a pixel put the check points within a tenth of a pixel.
    assert!(rmse < 0.015, "check-point RMSE {rmse} mm");
    // The images are kept (the default): a rerun could use them.
    let db = app.database().await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM job_files WHERE part = 'image'").await,
        4
    );
    app.stop().await;
}

/// A file larger than one request's worth (20 MiB: a multipart upload to
/// S3, in 8 MiB parts) goes through the image store's steps and comes back
/// byte for byte, in whichever backend the tests run; once deleted,
/// reading it says it is missing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_file_round_trips_through_the_image_store() {
    use ptv::service::ops::images::{ImageStore, ImageStoreError, MULTIPART_ABOVE};
    let data_dir = tempfile::tempdir().unwrap();
    let objects = object_store_args(data_dir.path());
    let images = ImageStore::open_shared(data_dir.path(), objects.location())
        .await
        .unwrap();
    let store = open_store(data_dir.path()).await;
    let size = 2 * MULTIPART_ABOVE + 12_345;
    let bytes: Vec<u8> = (0..size).map(|i| (i * 7 % 251) as u8).collect();
    let mut upload = images.create_upload().await.unwrap();
    for chunk in bytes.chunks(100_000) {
        upload.write(chunk).await.unwrap();
    }
    let file = upload.finish().await.unwrap();
    let sha256 = file.sha256.clone();
    images.stage(&file).await.unwrap();
    {
        let _lock = images.lock(&store).await.unwrap();
        images.persist(file).await.unwrap();
    }
    assert_eq!(stored_images(data_dir.path()).await, vec![sha256.clone()]);
    let read = images.read(&sha256).await.unwrap();
    assert!(read == bytes, "{} bytes read of {size}", read.len());
    // No upload is left in tmp/.
    assert!(walk(&data_dir.path().join("tmp")).is_empty());

    {
        let _lock = images.lock(&store).await.unwrap();
        images.remove(&sha256).await.unwrap();
    }
    match images.read(&sha256).await {
        Err(ImageStoreError::Missing { sha256: missing }) => assert_eq!(missing, sha256),
        other => panic!("{:?}", other.map(|b| b.len())),
    }
}
