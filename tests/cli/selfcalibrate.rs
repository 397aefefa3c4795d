//! `ptv selfcalibrate` run as a real process: bad input gets one clear
//! line (a pattern that matches no file, frames without files, too few
//! particles), and on test_cavity_recording's OpenPTV targets it writes a
//! calibration and a report.

use std::path::Path;

use crate::common::{fails, ptv};

const RECORDING: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/openptv/test_cavity_recording"
);
const GOLDEN: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/openptv/golden/test_cavity_recording"
);

/// The recording's calibration as JSON in `dir`.
fn calibration(dir: &Path) {
    let r = Path::new(RECORDING);
    let ori: Vec<String> = (1..=4)
        .map(|k| r.join(format!("cal/cam{k}.tif.ori")).display().to_string())
        .collect();
    let par = r.join("parameters/ptv.par").display().to_string();
    let mut args = vec!["calibration", "import-openptv", "--ptv-par", &par];
    args.extend(ori.iter().map(String::as_str));
    args.extend(["-o", "cal.json"]);
    let out = ptv(&args, dir);
    assert!(out.status.success(), "{:?}", out);
}

fn patterns() -> Vec<String> {
    (1..=4)
        .map(|k| format!("{GOLDEN}/cam{k}.%d_targets"))
        .collect()
}

fn run(dir: &Path, patterns: &[String], frames: &str) -> std::process::Output {
    let mut args = vec!["selfcalibrate", "--calibration", "cal.json"];
    for p in patterns {
        args.extend(["--targets", p.as_str()]);
    }
    args.extend(["--frames", frames, "-o", "refined.json"]);
    ptv(&args, dir)
}

#[test]
fn a_pattern_that_matches_no_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    let mut p = patterns();
    p[2] = format!("{GOLDEN}/camX.%d_targets");
    fails(
        &run(dir.path(), &p, "10001..10004"),
        &[
            "--targets",
            "camX.%d_targets",
            "matches no file",
            "10001..10004",
        ],
    );
    assert!(!dir.path().join("refined.json").exists());
}

#[test]
fn frames_without_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    fails(
        &run(dir.path(), &patterns(), "10003..10006"),
        &["no file", "cam1.10005_targets", "frame 10005", "--frames"],
    );
}

#[test]
fn one_target_pattern_per_camera() {
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    fails(
        &run(dir.path(), &patterns()[..3], "10001..10004"),
        &["--targets"],
    );
}

#[test]
fn too_few_particles_say_how_many_and_the_band() {
    // One frame at a 0.3 px band: the recording's calibration is ~4 px
    // off, so almost nothing is matched.
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    let mut args = vec!["selfcalibrate", "--calibration", "cal.json"];
    let p = patterns();
    for t in &p {
        args.extend(["--targets", t.as_str()]);
    }
    args.extend([
        "--frames",
        "10001..10001",
        "--tolerance",
        "0.3",
        "--final-tolerance",
        "0.3",
        "-o",
        "refined.json",
    ]);
    fails(
        &ptv(&args, dir.path()),
        &["confident particles", "band of 0.3 px", "at least 100"],
    );
}

#[test]
fn a_free_name_that_is_no_parameter_lists_the_media_terms_too() {
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    let mut args = vec!["selfcalibrate", "--calibration", "cal.json"];
    let p = patterns();
    for t in &p {
        args.extend(["--targets", t.as_str()]);
    }
    args.extend([
        "--frames",
        "10001..10004",
        "--free",
        "glas",
        "-o",
        "refined.json",
    ]);
    fails(
        &ptv(&args, dir.path()),
        &["--free", "`glas`", "glass,n_wall,n_object,thickness"],
    );
}

/// `--free glass` on the recording: the report lists each wall's glass
/// vector components (cameras 1-2 behind one wall, 3-4 behind the other),
/// each adjusted with a sigma or held with the reason.
#[test]
fn free_glass_reports_each_walls_vector() {
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    let mut args = vec!["selfcalibrate", "--calibration", "cal.json"];
    let p = patterns();
    for t in &p {
        args.extend(["--targets", t.as_str()]);
    }
    args.extend([
        "--frames",
        "10001..10004",
        "--tolerance",
        "16.7",
        "--free",
        "glass",
        "-o",
        "refined.json",
    ]);
    let out = ptv(&args, dir.path());
    assert!(out.status.success(), "{out:?}");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let media = report["media"].as_array().expect("media in the report");
    assert_eq!(media.len(), 6, "{media:?}");
    for (k, m) in media.iter().enumerate() {
        let axis = ["x", "y", "z"][k % 3];
        assert_eq!(m["name"], format!("glass_{axis}"), "{m}");
        let cameras = if k < 3 { [1, 2] } else { [3, 4] };
        assert_eq!(m["cameras"], serde_json::json!(cameras), "{m}");
        match m["status"].as_str() {
            Some("free") => assert!(m["sigma"].as_f64().is_some_and(|s| s > 0.0), "{m}"),
            _ => assert!(m["reason"].as_str().is_some_and(|r| !r.is_empty()), "{m}"),
        }
    }
    assert!(dir.path().join("refined.json").exists());
}
