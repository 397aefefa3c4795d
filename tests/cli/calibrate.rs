//! `ptv calibrate` end to end: files in, calibration JSON and report out.

use crate::common::{fails, ptv, succeeds};
use nalgebra::Point3;
use ptv::formats::calibration;
use ptv::formats::control::{format_control_points, format_mark_observations};
use ptv::photogrammetry::calibrate::{
    calibrate, CalibrationOptions, CheckPoints, MarkObservation, Parameter,
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
/// `block.txt` and `camN.txt` (0.05 px noise).
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
    let mut args: Vec<String> = [
        "calibrate",
        "--calibration",
        "setup.json",
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
