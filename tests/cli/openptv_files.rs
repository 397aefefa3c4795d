//! The `ptv` command line, run as a real process in temporary directories.
//!
//! Round trips through files against the OpenPTV golden data: importing
//! OpenPTV's files gives the golden calibration, export and re-import are
//! lossless, and projecting the golden points then intersecting the images
//! returns the points. Failures print one `error:` line and nothing else.
//!
//! Tolerances: pixels are compared with OpenPTV's with 0.002 px, the accuracy
//! of its iterative projection through the wall (see the data's README). The
//! intersection of exact, noise-free images (written in the shortest form
//! that reads back bit for bit) stops its Gauss-Newton iteration at a step of
//! 1e-8 mm, so it returns the point to far better than the 1e-6 mm checked.

use std::path::{Path, PathBuf};

use nalgebra::Point3;
use ptv::formats::{calibration, csv};
use ptv::photogrammetry::Camera;
use serde_json::Value;

use crate::common::{fails, json_points, ptv, succeeds, text};

const OPENPTV: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv");
const PIXEL_TOLERANCE: f64 = 0.002;
const POINT_TOLERANCE_MM: f64 = 1e-6;

fn data(path: &str) -> PathBuf {
    Path::new(OPENPTV).join(path)
}

fn golden(path: &str) -> Value {
    let text = std::fs::read_to_string(data(path)).expect("golden file");
    serde_json::from_str(&text).expect("golden JSON")
}

fn golden_cameras(golden: &Value) -> Vec<Camera> {
    calibration::from_json(&golden["calibration"].to_string(), "golden")
        .expect("golden calibration")
}

fn golden_points(golden: &Value) -> Vec<Point3<f64>> {
    json_points(&golden["points"])
}

/// The numeric rows of a CSV written by `ptv`, after checking its header.
fn rows(csv: &str, header: &str) -> Vec<Vec<f64>> {
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some(header));
    lines
        .map(|line| {
            line.split(',')
                .map(|f| f.parse().expect("a number"))
                .collect()
        })
        .collect()
}

fn path_str(path: &Path) -> &str {
    path.to_str().expect("UTF-8 path")
}

const TEST_CAVITY_ORIS: [&str; 4] = [
    "test_cavity/cal/cam1.tif.ori",
    "test_cavity/cal/cam2.tif.ori",
    "test_cavity/cal/cam3.tif.ori",
    "test_cavity/cal/cam4.tif.ori",
];

#[test]
fn import_openptv_gives_the_golden_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let ptv_par = data("test_cavity/parameters/ptv.par");
    let oris: Vec<PathBuf> = TEST_CAVITY_ORIS.iter().map(|o| data(o)).collect();
    let mut args = vec![
        "calibration",
        "import-openptv",
        "--ptv-par",
        path_str(&ptv_par),
    ];
    args.extend(oris.iter().map(|o| path_str(o)));
    let expected = golden_cameras(&golden("golden/test_cavity_camera_model.json"));

    let on_stdout = succeeds(&ptv(&args, dir.path()));
    assert_eq!(
        calibration::from_json(&on_stdout, "stdout").unwrap(),
        expected
    );

    args.extend(["-o", "cal.json"]);
    let output = ptv(&args, dir.path());
    assert!(succeeds(&output).is_empty() && output.stderr.is_empty());
    let written = std::fs::read_to_string(dir.path().join("cal.json")).unwrap();
    assert_eq!(written, on_stdout);
}

#[test]
fn export_then_import_openptv_is_lossless() {
    let dir = tempfile::tempdir().unwrap();
    let ptv_par = data("golden/rig_a/ptv.par");
    let oris: Vec<PathBuf> = ["cam1.ori", "cam2.ori", "cam3.ori"]
        .iter()
        .map(|o| data(&format!("golden/rig_a/{o}")))
        .collect();
    let mut args = vec![
        "calibration",
        "import-openptv",
        "--ptv-par",
        path_str(&ptv_par),
    ];
    args.extend(oris.iter().map(|o| path_str(o)));
    args.extend(["-o", "a.json"]);
    succeeds(&ptv(&args, dir.path()));
    let first = std::fs::read_to_string(dir.path().join("a.json")).unwrap();
    let cameras = calibration::from_json(&first, "a.json").unwrap();
    assert!(cameras
        .iter()
        .all(|c| !c.parameters().distortion.is_identity()));

    let output = ptv(
        &[
            "calibration",
            "export-openptv",
            "--calibration",
            "a.json",
            "--out-dir",
            "out",
        ],
        dir.path(),
    );
    assert!(succeeds(&output).is_empty());
    let listed: Vec<&str> = text(&output.stderr).lines().collect();
    let expected: Vec<PathBuf> = [
        "ptv.par",
        "cam1.ori",
        "cam1.addpar",
        "cam2.ori",
        "cam2.addpar",
        "cam3.ori",
        "cam3.addpar",
    ]
    .iter()
    .map(|name| Path::new("out").join(name))
    .collect();
    assert_eq!(
        listed,
        expected.iter().map(|p| path_str(p)).collect::<Vec<_>>()
    );
    assert!(expected.iter().all(|p| dir.path().join(p).is_file()));

    let output = ptv(
        &[
            "calibration",
            "import-openptv",
            "--ptv-par",
            "out/ptv.par",
            "out/cam1.ori",
            "out/cam2.ori",
            "out/cam3.ori",
        ],
        dir.path(),
    );
    let second = succeeds(&output);
    assert_eq!(calibration::from_json(&second, "again").unwrap(), cameras);
    assert_eq!(second, first);
}

/// `ptv project` then `ptv intersect` of a golden file's points.
fn project_and_intersect(golden_file: &str) {
    let golden = golden(golden_file);
    let points = golden_points(&golden);
    let cameras = golden_cameras(&golden);
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("cal.json"),
        golden["calibration"].to_string(),
    )
    .unwrap();
    std::fs::write(dir.path().join("points.csv"), csv::format_points(&points)).unwrap();

    let observations = succeeds(&ptv(
        &[
            "project",
            "--calibration",
            "cal.json",
            "--points",
            "points.csv",
        ],
        dir.path(),
    ));
    let table = rows(&observations, "point,camera,x,y");
    assert_eq!(table.len(), points.len() * cameras.len());
    for (k, row) in table.iter().enumerate() {
        let (point, camera) = (k / cameras.len(), k % cameras.len());
        assert_eq!((row[0], row[1]), (point as f64, camera as f64), "row {k}");
        let pixel = &golden["cameras"][camera]["pixel"][point];
        let (gx, gy) = (pixel[0].as_f64().unwrap(), pixel[1].as_f64().unwrap());
        assert!(
            (row[2] - gx).abs() < PIXEL_TOLERANCE && (row[3] - gy).abs() < PIXEL_TOLERANCE,
            "{golden_file}: point {point} camera {camera}: ({}, {}) vs OpenPTV ({gx}, {gy})",
            row[2],
            row[3]
        );
    }

    std::fs::write(dir.path().join("obs.csv"), &observations).unwrap();
    let intersections = succeeds(&ptv(
        &[
            "intersect",
            "--calibration",
            "cal.json",
            "--observations",
            "obs.csv",
        ],
        dir.path(),
    ));
    let table = rows(&intersections, "point,x,y,z,sx,sy,sz,rms_px");
    assert_eq!(table.len(), points.len());
    for (k, (row, truth)) in table.iter().zip(&points).enumerate() {
        assert_eq!(row[0], k as f64);
        let error = (Point3::new(row[1], row[2], row[3]) - truth).norm();
        assert!(
            error < POINT_TOLERANCE_MM,
            "{golden_file}: point {k} off by {error} mm"
        );
        assert!(
            row[4..].iter().all(|v| v.is_finite() && *v >= 0.0),
            "{row:?}"
        );
    }
}

#[test]
fn projected_points_intersect_back_test_cavity() {
    project_and_intersect("golden/test_cavity_camera_model.json");
}

#[test]
fn projected_points_intersect_back_rig_a() {
    project_and_intersect("golden/rig_a/golden.json");
}

/// A directory with the test_cavity calibration as `cal.json`.
fn with_calibration() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let golden = golden("golden/test_cavity_camera_model.json");
    std::fs::write(
        dir.path().join("cal.json"),
        golden["calibration"].to_string(),
    )
    .unwrap();
    dir
}

#[test]
fn points_without_an_image_are_counted_in_one_warning() {
    let dir = with_calibration();
    // Far beyond the walls at z = -125 and 125: behind cameras 3 and 4
    // (at z = 585 and 573, looking down).
    std::fs::write(dir.path().join("points.csv"), "x,y,z\n0,0,0\n0,0,2000\n").unwrap();
    let output = ptv(
        &[
            "project",
            "--calibration",
            "cal.json",
            "--points",
            "points.csv",
        ],
        dir.path(),
    );
    assert!(output.status.success());
    let stderr = text(&output.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with("warning: ") && stderr.contains(" of 8 "),
        "{stderr}"
    );
    let table = rows(text(&output.stdout), "point,camera,x,y");
    assert_eq!(table.iter().filter(|r| r[0] == 0.0).count(), 4);
    let missing: usize = stderr["warning: ".len()..]
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(table.iter().filter(|r| r[0] == 1.0).count(), 4 - missing);
}

#[test]
fn points_with_one_observation_are_skipped_with_a_warning() {
    let dir = with_calibration();
    let observations = "camera,point,y,x,comment\n0,42,500,600,a\n1,7,512,640,b\n2,7,500,620,c\n";
    std::fs::write(dir.path().join("obs.csv"), observations).unwrap();
    let output = ptv(
        &[
            "intersect",
            "--calibration",
            "cal.json",
            "--observations",
            "obs.csv",
        ],
        dir.path(),
    );
    assert!(output.status.success());
    let stderr = text(&output.stderr);
    assert_eq!(
        stderr,
        "warning: point 42 skipped: a point needs observations from at least 2 cameras, got 1\n"
    );
    let table = rows(text(&output.stdout), "point,x,y,z,sx,sy,sz,rms_px");
    assert_eq!(table.len(), 1);
    assert_eq!(table[0][0], 7.0);
}

#[test]
fn failures_print_one_error_line() {
    let dir = with_calibration();
    let write = |name: &str, text: &str| std::fs::write(dir.path().join(name), text).unwrap();
    write("points.csv", "x,y,z\n1,2,3\n4,abc,6\n");
    write("obs.csv", "point,camera,x,y\n0,0,1,2\n0,4,1,2\n");
    write("dup.csv", "point,camera,x,y\n0,0,1,2\n0,1,1,2\n0,0,3,4\n");
    write("nan.csv", "point,camera,x,y\n0,0,NaN,2\n");
    write("nocol.csv", "point,cam,x,y\n0,0,1,2\n");
    let calibration = std::fs::read_to_string(dir.path().join("cal.json")).unwrap();
    write(
        "typo.json",
        &calibration.replacen("\"principal_distance\"", "\"principal_distanse\"", 1),
    );

    for (args, needles) in [
        (
            vec![
                "project",
                "--calibration",
                "missing.json",
                "--points",
                "points.csv",
            ],
            vec!["missing.json", "No such file"],
        ),
        (
            vec![
                "project",
                "--calibration",
                "cal.json",
                "--points",
                "points.csv",
            ],
            vec!["points.csv: line 3, column y", "abc"],
        ),
        (
            vec![
                "project",
                "--calibration",
                "typo.json",
                "--points",
                "points.csv",
            ],
            vec!["typo.json", "cameras[0]", "principal_distanse"],
        ),
        (
            vec![
                "intersect",
                "--calibration",
                "cal.json",
                "--observations",
                "obs.csv",
            ],
            vec!["obs.csv: line 3, column camera", "camera 4 does not exist"],
        ),
        (
            vec![
                "intersect",
                "--calibration",
                "cal.json",
                "--observations",
                "dup.csv",
            ],
            vec!["dup.csv: line 4, column camera", "line 2"],
        ),
        (
            vec![
                "intersect",
                "--calibration",
                "cal.json",
                "--observations",
                "nan.csv",
            ],
            vec!["nan.csv: line 2, column x"],
        ),
        (
            vec![
                "intersect",
                "--calibration",
                "cal.json",
                "--observations",
                "nocol.csv",
            ],
            vec!["nocol.csv: line 1, column camera"],
        ),
        (
            vec![
                "intersect",
                "--calibration",
                "cal.json",
                "--observations",
                "none.csv",
            ],
            vec!["none.csv", "No such file"],
        ),
        (
            vec![
                "calibration",
                "export-openptv",
                "--calibration",
                "typo.json",
                "--out-dir",
                "out",
            ],
            vec!["typo.json", "principal_distanse"],
        ),
        (
            vec![
                "calibration",
                "import-openptv",
                "--ptv-par",
                "nothing.par",
                "a.ori",
                "b.ori",
            ],
            vec!["nothing.par", "No such file"],
        ),
    ] {
        let output = ptv(&args, dir.path());
        fails(&output, &needles);
        // The OS reason appears once, not once per level of the error chain.
        assert!(
            text(&output.stderr).matches("No such file").count() <= 1,
            "{args:?}"
        );
    }
}

#[test]
fn export_of_a_calibration_openptv_cannot_hold_is_refused() {
    let dir = with_calibration();
    let calibration = std::fs::read_to_string(dir.path().join("cal.json")).unwrap();
    let mixed = calibration.replacen("1280", "640", 1);
    std::fs::write(dir.path().join("mixed.json"), mixed).unwrap();
    let output = ptv(
        &[
            "calibration",
            "export-openptv",
            "--calibration",
            "mixed.json",
            "--out-dir",
            "out",
        ],
        dir.path(),
    );
    fails(
        &output,
        &[
            "cannot export mixed.json as OpenPTV files",
            "another sensor",
        ],
    );
    assert!(!dir.path().join("out").exists());
}

#[test]
fn export_under_a_hostile_camera_name_is_impossible() {
    // Export writes NAME.ori and NAME.addpar: a name that is a path would
    // write outside the output directory. Such names are refused when the
    // calibration is read, before anything is written.
    let dir = with_calibration();
    let mut calibration: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("cal.json")).unwrap())
            .unwrap();
    for name in [
        "../escaped",
        "/tmp/ptv-absolute",
        "..",
        "a\\b",
        ".hidden",
        "cam\u{0}1",
        &"n".repeat(65),
    ] {
        calibration["cameras"][0]["name"] = Value::from(name);
        std::fs::write(dir.path().join("hostile.json"), calibration.to_string()).unwrap();
        let output = ptv(
            &[
                "calibration",
                "export-openptv",
                "--calibration",
                "hostile.json",
                "--out-dir",
                "out/deeper",
            ],
            dir.path(),
        );
        fails(
            &output,
            &["hostile.json", "cameras[0].name", "1 to 64 characters"],
        );
        assert!(!dir.path().join("out").exists(), "{name:?}");
        assert!(!dir.path().join("escaped.ori").exists());
        assert!(!Path::new("/tmp/ptv-absolute.ori").exists());
    }
}

#[test]
fn help_lists_the_commands_and_no_subcommand_serves() {
    let dir = tempfile::tempdir().unwrap();
    let output = ptv(&["--help"], dir.path());
    assert!(output.status.success());
    let stdout = text(&output.stdout);
    for command in ["calibration", "project", "intersect", "serve", "worker"] {
        assert!(stdout.contains(command), "{stdout}");
    }
    assert!(output.stderr.is_empty());

    // Without a subcommand: the service, its flags from the environment.
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_ptv"))
        .env("PTV_BIND", "127.0.0.1:0")
        .env("PTV_DATA_DIR", dir.path().join("data"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(child.stdout.take().unwrap()),
        &mut line,
    )
    .unwrap();
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(line.starts_with("listening on http://127.0.0.1:"), "{line}");
    assert!(dir.path().join("data/ptv.sqlite").exists());
}

#[test]
fn a_database_url_that_does_not_parse_is_named_without_its_password() {
    let dir = tempfile::tempdir().unwrap();
    for command in ["serve", "worker"] {
        let output = ptv(
            &[command, "--database", "mysql://lab:s3cret@db.lab/ptv"],
            dir.path(),
        );
        assert_eq!(output.status.code(), Some(2), "{command}");
        let stderr = text(&output.stderr);
        assert!(!stderr.contains("s3cret"), "{command}: {stderr}");
        assert!(
            stderr.contains("invalid value for --database: `mysql://lab:***@db.lab/ptv` is not a PostgreSQL URL"),
            "{command}: {stderr}"
        );
    }
}

#[test]
fn usage_errors_keep_clap_exit_code() {
    let dir = tempfile::tempdir().unwrap();
    for args in [
        vec!["frobnicate"],
        vec!["project", "--calibration", "cal.json"],
        vec!["calibration", "import-openptv", "--ptv-par", "ptv.par"],
    ] {
        let output = ptv(&args, dir.path());
        assert_eq!(output.status.code(), Some(2), "{args:?}");
        assert!(output.stdout.is_empty());
    }
}
