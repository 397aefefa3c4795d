//! OpenPTV experiments in one call (`POST /experiments/openptv`) and
//! calibrations whose cameras are the views of one sensor (a splitter):
//! the real test_cavity recording imported from its `parameters/` folder
//! and from its pyptv YAML, a frame of it processed with the imported
//! settings, bad experiments refused with nothing stored; and a rendered
//! frame uploaded as one four-view image giving what four images give.

use std::path::Path;

use ptv::formats;
use ptv::photogrammetry::{GreyImage, GreyPixels};
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};

use super::helpers::{
    count, image_form, png, repository, rig, sequence_body, spawn_app, status_and_json, TestApp,
};

/// The recording's experiment directory.
fn recording() -> std::path::PathBuf {
    repository().join("tests/data/openptv/test_cavity_recording")
}

/// The legacy experiment's files as parts named by their paths.
fn legacy_files() -> Vec<(String, Vec<u8>)> {
    let root = recording();
    let mut files = Vec::new();
    for name in [
        "ptv.par",
        "criteria.par",
        "targ_rec.par",
        "sequence.par",
        "cal_ori.par",
        "track.par",
    ] {
        let path = format!("parameters/{name}");
        files.push((path.clone(), std::fs::read(root.join(&path)).unwrap()));
    }
    files.extend(calibration_files(&root));
    files
}

fn calibration_files(root: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    for camera in 1..=4 {
        for ext in ["ori", "addpar"] {
            let path = format!("cal/cam{camera}.tif.{ext}");
            files.push((path.clone(), std::fs::read(root.join(&path)).unwrap()));
        }
    }
    files
}

async fn post_experiment(app: &TestApp, files: &[(String, Vec<u8>)]) -> (u16, Value) {
    let mut form = Form::new().text("name", "cavity");
    for (path, bytes) in files {
        form = form.part("file", Part::bytes(bytes.clone()).file_name(path.clone()));
    }
    let response = app
        .client
        .post(app.api("/experiments/openptv"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    status_and_json(response).await
}

#[tokio::test(flavor = "multi_thread")]
async fn the_recording_imports_from_its_par_files_and_its_yaml_and_a_frame_processes() {
    let app = spawn_app().await;
    let (status, legacy) = post_experiment(&app, &legacy_files()).await;
    assert_eq!(status, 201, "{legacy}");
    assert_eq!(
        legacy["images"],
        json!(["img/cam1.%d", "img/cam2.%d", "img/cam3.%d", "img/cam4.%d"])
    );
    assert_eq!(
        (
            legacy["first_frame"].as_u64(),
            legacy["last_frame"].as_u64()
        ),
        (Some(10001), Some(10004))
    );
    assert!(
        !legacy["unmapped"].as_array().unwrap().is_empty(),
        "{legacy}"
    );
    let file = legacy["unmapped"][0]["file"].as_str().unwrap();
    assert!(
        !file.contains("experiment-"),
        "the scratch directory shows: {file}"
    );

    let mut yaml = vec![(
        "parameters_Run1.yaml".to_owned(),
        std::fs::read(recording().join("parameters_Run1.yaml")).unwrap(),
    )];
    yaml.extend(calibration_files(&recording()));
    let (status, from_yaml) = post_experiment(&app, &yaml).await;
    assert_eq!(status, 201, "{from_yaml}");

    // Both give the same settings: the experiment's own.
    let (_, a) = app
        .get_json(&format!("/sequences/{}", legacy["sequence_id"]))
        .await;
    let (_, b) = app
        .get_json(&format!("/sequences/{}", from_yaml["sequence_id"]))
        .await;
    assert_eq!(a["parameters"], b["parameters"]);
    let detection = &a["parameters"]["detection"];
    assert_eq!(detection["thresholds"], json!([9, 9, 9, 11]), "{a}");
    assert_eq!(detection["split_depth"], 100, "{a}");
    assert_eq!(
        (
            detection["min_pixels"].as_u64(),
            detection["min_sumg"].as_u64()
        ),
        (Some(4), Some(151))
    );
    // eps0 = 0.2 mm on 0.012 mm pixels.
    let band = a["parameters"]["matching"]["tolerance"].as_f64().unwrap();
    assert!((band - 0.2 / 0.012).abs() < 1e-9, "{band}");

    // Frame 10001 of the recording, as the acquisition PC sends it.
    let sequence = legacy["sequence_id"].as_i64().unwrap();
    let images: Vec<Vec<u8>> = (1..=4)
        .map(|c| std::fs::read(recording().join(format!("img/cam{c}.10001"))).unwrap())
        .collect();
    let (status, body) = app.upload(sequence, image_form(10001, &images)).await;
    assert_eq!(status, 202, "{body}");
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], 1, "{view}");
    let (_, particles) = app
        .get_json(&format!("/sequences/{sequence}/frames/10001/particles"))
        .await;
    let particles = particles["particles"].as_array().unwrap();
    let quadruplets = particles
        .iter()
        .filter(|p| {
            p["targets"]
                .as_array()
                .unwrap()
                .iter()
                .all(|t| !t.is_null())
        })
        .count();
    // OpenPTV (optv 0.3.2) with these settings finds about 400
    // four-camera particles in this frame (tests/data/openptv/README.md);
    // half of that is a floor any working import and pipeline clears.
    assert!(
        quadruplets >= 200,
        "{quadruplets} four-camera particles of {}",
        particles.len()
    );

    // track.par made the sequence's tracking run: the sphere around its
    // -15.5..15.5 mm box, dacc 2.8, flagNewParticles as the recovery, from
    // the first frame. The other frames uploaded, the run finished, its
    // trajectories are there.
    let run = legacy["tracking_run_id"].as_i64().expect("a tracking run");
    assert_eq!(
        legacy["trajectories"],
        format!("/api/v1/sequences/{sequence}/trajectories")
    );
    let (_, runs) = app
        .get_json(&format!("/sequences/{sequence}/tracking"))
        .await;
    let settings = &runs[0]["settings"];
    assert_eq!(runs[0]["run_id"], run, "{runs}");
    assert!(
        (settings["max_velocity"].as_f64().unwrap() - 15.5 * 3f64.sqrt()).abs() < 1e-9,
        "{runs}"
    );
    assert_eq!(settings["max_acceleration"], 2.8, "{runs}");
    assert_eq!(settings["recovery"], true, "{runs}");
    // Backward tracking is on unless turned off (docs/tracking.md).
    assert_eq!(settings["backward"], true, "{runs}");
    assert_eq!(settings["first_frame"], 10001, "{runs}");
    for frame in 10002..=10004 {
        let images: Vec<Vec<u8>> = (1..=4)
            .map(|c| std::fs::read(recording().join(format!("img/cam{c}.{frame}"))).unwrap())
            .collect();
        let (status, body) = app.upload(sequence, image_form(frame, &images)).await;
        assert_eq!(status, 202, "{body}");
    }
    app.wait_for_sequence(sequence).await;
    let (status, body) = app
        .post_json(
            &format!("/sequences/{sequence}/tracking/finish"),
            &json!({}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let start = std::time::Instant::now();
    while app.get_json(&format!("/sequences/{sequence}")).await.1["tracking"]["state"] != "finished"
    {
        assert!(
            start.elapsed() < std::time::Duration::from_secs(120),
            "tracking did not finish"
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    let (_, tracked) = app
        .get_json(&format!("/sequences/{sequence}/trajectories"))
        .await;
    let trajectories = tracked["trajectories"].as_array().unwrap();
    // Four frames of some 500 particles: most are tracked through.
    assert!(
        trajectories.len() > 100,
        "{} trajectories",
        trajectories.len()
    );
    app.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_experiments_are_refused_by_file_line_and_key_and_store_nothing() {
    let app = spawn_app().await;
    let db = app.database().await;

    // A ptv.par whose camera count is not a number.
    let mut files = legacy_files();
    let ptv_par = files
        .iter_mut()
        .find(|(p, _)| p == "parameters/ptv.par")
        .unwrap();
    ptv_par.1 = b"four\n".to_vec();
    let (status, problem) = post_experiment(&app, &files).await;
    assert_eq!(status, 422, "{problem}");
    let detail = problem["detail"].as_str().unwrap();
    assert!(
        detail.contains("parameters/ptv.par") && detail.contains("line 1"),
        "{detail}"
    );
    assert!(
        !detail.contains("experiment-"),
        "the scratch directory shows: {detail}"
    );

    // An .ori the experiment names but the request does not carry.
    let files: Vec<_> = legacy_files()
        .into_iter()
        .filter(|(p, _)| p != "cal/cam3.tif.ori")
        .collect();
    let (status, problem) = post_experiment(&app, &files).await;
    assert_eq!(status, 422, "{problem}");
    assert!(
        problem["detail"]
            .as_str()
            .unwrap()
            .contains("cal/cam3.tif.ori"),
        "{problem}"
    );

    // A path that leaves the directory.
    let mut files = legacy_files();
    files.push(("../../etc/passwd".to_owned(), b"x".to_vec()));
    let (status, problem) = post_experiment(&app, &files).await;
    assert_eq!(status, 400, "{problem}");
    assert!(problem["detail"]
        .as_str()
        .unwrap()
        .contains("leaves the experiment directory"));

    // Nothing at all.
    let (status, problem) = post_experiment(&app, &[]).await;
    assert_eq!(status, 400, "{problem}");

    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM sequences").await, 0);
    app.stop().await;
}

/// Four equal views as one image, in the splitter's quadrant order:
/// camera 0 top left, 1 top right, 2 bottom right, 3 bottom left.
fn quadrants(views: &[GreyImage]) -> GreyImage {
    let (w, h) = (views[0].width() as usize, views[0].height() as usize);
    let mut whole = vec![0u8; 4 * w * h];
    for (camera, (column, row)) in [(0, 0), (1, 0), (1, 1), (0, 1)].into_iter().enumerate() {
        let GreyPixels::Eight(samples) = views[camera].pixels() else {
            panic!("8-bit views expected");
        };
        for y in 0..h {
            let start = (row * h + y) * 2 * w + column * w;
            whole[start..start + w].copy_from_slice(&samples[y * w..(y + 1) * w]);
        }
    }
    GreyImage::from_u8(2 * w as u32, 2 * h as u32, whole).unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn a_splitter_frame_is_one_image_cut_into_the_cameras_views() {
    let app = spawn_app().await;
    let rig = rig();
    let plain = app.create_calibration(&rig.cameras).await;
    let mut model: Value =
        serde_json::from_str(&formats::calibration::to_json(&rig.cameras)).unwrap();
    model["splitter"] = json!({"layout": "quadrants"});
    let (status, body) = app.post_json("/calibrations", &model).await;
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["model"]["splitter"]["layout"], "quadrants", "{body}");
    let split = body["id"].as_i64().unwrap();

    let create = |calibration| sequence_body(calibration, &rig.volume, true);
    let (status, a) = app.post_json("/sequences", &create(plain)).await;
    assert_eq!(status, 201, "{a}");
    let (status, b) = app.post_json("/sequences", &create(split)).await;
    assert_eq!(status, 201, "{b}");
    let (four, one) = (a["id"].as_i64().unwrap(), b["id"].as_i64().unwrap());

    let frame = rig.render(150, 11);
    let (status, body) = app
        .upload(
            four,
            image_form(0, &frame.images.iter().map(png).collect::<Vec<_>>()),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let whole = png(&quadrants(&frame.images));
    let form = Form::new()
        .text("frame", "0")
        .part("image", Part::bytes(whole.clone()).file_name("whole.png"));
    let (status, body) = app.upload(one, form).await;
    assert_eq!(status, 202, "{body}");

    // Per-camera parts, or an image of the views' size, are refused.
    let (status, problem) = app
        .upload(
            one,
            image_form(1, &frame.images.iter().map(png).collect::<Vec<_>>()),
        )
        .await;
    assert_eq!(status, 422, "{problem}");
    assert!(
        problem["detail"].as_str().unwrap().contains("part `image`"),
        "{problem}"
    );
    let form = Form::new().text("frame", "2").part(
        "image",
        Part::bytes(png(&frame.images[0])).file_name("view.png"),
    );
    let (status, problem) = app.upload(one, form).await;
    assert_eq!(status, 422, "{problem}");

    for sequence in [four, one] {
        let view = app.wait_for_sequence(sequence).await;
        assert_eq!(view["frames"]["done"], 1, "{view}");
    }
    // The same views, detected and matched alike: the same particles.
    let (_, a) = app
        .get_json(&format!("/sequences/{four}/frames/0/particles"))
        .await;
    let (_, b) = app
        .get_json(&format!("/sequences/{one}/frames/0/particles"))
        .await;
    assert!(!a["particles"].as_array().unwrap().is_empty());
    assert_eq!(a["particles"], b["particles"]);
    // The frame overlay of camera 2: its own image, or its view of the one
    // image, under the same marks (the legends name the sequences).
    let sensor = rig.cameras[2].sensor();
    let mut overlays = Vec::new();
    for sequence in [four, one] {
        let path = format!("/sequences/{sequence}/frames/0/overlay.png?camera=2");
        let image = crate::plots::png_picture(&app, &path).await;
        assert_eq!(image.height(), sensor.height + ptv::plot::overlay::LEGEND);
        overlays
            .push(image::imageops::crop_imm(&image, 0, 0, sensor.width, sensor.height).to_image());
    }
    assert!(
        overlays[0] == overlays[1],
        "the split view's overlay differs"
    );
    app.stop().await;
}
