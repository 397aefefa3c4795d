//! `ptv calibration import-myptv|export-myptv|import-openlpt|export-openlpt`:
//! MyPTV's and OpenLPT's camera files, run as a real process.
//!
//! Each conversion reports, per camera, how far the other tool's images
//! and ptv's differ over an 11x11x11 grid through `--volume`. Where the
//! model carries ptv's (a camera in air) the export and its re-import are
//! exact: every number is written in its shortest exact form, so only the
//! conversions' floating-point arithmetic is left, ~1e-16 relative of
//! ~1,000 px, and 1e-9 px leaves a margin of 1e4. test_cavity's cameras
//! look through 6 mm of glass into water: neither model has refraction, so
//! they go out through the best fit, whose error is the models' difference
//! and is reported, not chosen: the test checks that the re-import
//! reproduces the exported camera exactly, and that the best fit beats the
//! same camera with its refraction simply dropped.

use std::path::{Path, PathBuf};

use ptv::formats::calibration;
use serde_json::Value;

use crate::common::{fails, ptv, succeeds, text};

const OPENPTV: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv");
/// test_cavity's observation volume (criteria.par: X -40..40, Z -20..20;
/// Y as X).
const VOLUME: &str = "-40,40,-40,40,-20,20";
const EXACT_PX: f64 = 1e-9;

fn path_str(path: &Path) -> &str {
    path.to_str().expect("UTF-8 path")
}

/// test_cavity's calibration as JSON, in `dir`.
fn test_cavity(dir: &Path) -> PathBuf {
    let cal = Path::new(OPENPTV).join("test_cavity/cal");
    let oris: Vec<PathBuf> = (1..=4)
        .map(|k| cal.join(format!("cam{k}.tif.ori")))
        .collect();
    let par = Path::new(OPENPTV).join("test_cavity/parameters/ptv.par");
    let mut args = vec!["calibration", "import-openptv", "--ptv-par", path_str(&par)];
    args.extend(oris.iter().map(|o| path_str(o)));
    args.extend(["-o", "cavity.json"]);
    succeeds(&ptv(&args, dir));
    dir.join("cavity.json")
}

/// The same rig in air (no walls, water replaced by air).
fn in_air(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(test_cavity(dir)).unwrap();
    let mut json: Value = serde_json::from_str(&text).unwrap();
    for camera in json["cameras"].as_array_mut().unwrap() {
        camera["media"] = serde_json::json!({"n_object": 1.0});
    }
    let path = dir.join("air.json");
    std::fs::write(&path, json.to_string()).unwrap();
    path
}

/// Per camera reported: (how, max px, RMS px).
fn reported(stderr: &str) -> Vec<(String, f64, f64)> {
    stderr
        .lines()
        .filter(|l| l.contains("differ by at most"))
        .map(|line| {
            let how = line.split(';').next().unwrap().to_owned();
            let number = |after: &str| -> f64 {
                let rest = &line[line.find(after).unwrap() + after.len()..];
                rest.split_whitespace().next().unwrap().parse().unwrap()
            };
            (how, number("at most "), number("(RMS "))
        })
        .collect()
}

fn export(tool: &str, calibration: &Path, out: &str, dir: &Path) -> Vec<(String, f64, f64)> {
    let output = ptv(
        &[
            "calibration",
            &format!("export-{tool}"),
            "--calibration",
            path_str(calibration),
            "--volume",
            VOLUME,
            "--out-dir",
            out,
        ],
        dir,
    );
    // OpenLPT's warning about a distortion it would ignore may come.
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(output.stdout.is_empty());
    reported(text(&output.stderr))
}

fn import(tool: &str, files: &[PathBuf], dir: &Path) -> (Vec<(String, f64, f64)>, String) {
    let mut args = vec![
        "calibration".to_owned(),
        format!("import-{tool}"),
        "--pixel-size".to_owned(),
        "0.012".to_owned(),
        "--volume".to_owned(),
        VOLUME.to_owned(),
    ];
    args.extend(files.iter().map(|f| path_str(f).to_owned()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let output = ptv(&args, dir);
    let json = succeeds(&output);
    (reported(text(&output.stderr)), json)
}

fn files(dir: &Path, tool: &str) -> Vec<PathBuf> {
    (1..=4)
        .map(|k| match tool {
            "myptv" => dir.join(format!("{tool}/cam{k}")),
            _ => dir.join(format!("{tool}/cam{k}.txt")),
        })
        .collect()
}

#[test]
fn a_rig_in_air_goes_out_and_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let air = in_air(dir.path());
    let original = calibration::from_json(&std::fs::read_to_string(&air).unwrap(), "air").unwrap();
    for tool in ["myptv", "openlpt"] {
        let out = export(tool, &air, tool, dir.path());
        assert_eq!(out.len(), 4, "{tool}");
        for (how, max, _) in &out {
            assert!(
                how.ends_with("exact") && *max < EXACT_PX,
                "{tool}: {how} {max}"
            );
        }
        let (back, json) = import(tool, &files(dir.path(), tool), dir.path());
        for (how, max, _) in &back {
            assert!(
                how.ends_with("exact") && *max < EXACT_PX,
                "{tool}: {how} {max}"
            );
        }
        let again = calibration::from_json(&json, "again").unwrap();
        let points = ptv::formats::between::grid(&ptv::photogrammetry::Volume {
            min: nalgebra::Point3::new(-40.0, -40.0, -20.0),
            max: nalgebra::Point3::new(40.0, 40.0, 20.0),
        });
        for (a, b) in original.iter().zip(&again) {
            for point in &points {
                let (pa, pb) = (a.project(point).unwrap(), b.project(point).unwrap());
                assert!((pa - pb).norm() < EXACT_PX, "{tool}: {pa} {pb}");
            }
        }
    }
}

#[test]
fn refraction_goes_out_through_the_best_fit_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let cavity = test_cavity(dir.path());
    let air = in_air(dir.path());
    for tool in ["myptv", "openlpt"] {
        let fitted = export(tool, &cavity, tool, dir.path());
        // The yardstick: the same cameras with their refraction simply
        // dropped (the rig in air against the rig in water).
        let dropped = dropped_refraction_px(&cavity, &air);
        for ((how, max, rms), dropped) in fitted.iter().zip(&dropped) {
            assert!(
                how.contains("best fit") && how.contains("refraction"),
                "{how}"
            );
            assert!(max.is_finite() && *rms <= *max, "{how}: {max} {rms}");
            assert!(max < dropped, "{tool}: the best fit ({max} px) is no better than dropping the refraction ({dropped} px)");
        }
        // The files re-imported are those cameras, exactly: their
        // reprojection against the exported files' is that of the export.
        let (back, _) = import(tool, &files(dir.path(), tool), dir.path());
        for (how, max, _) in &back {
            assert!(
                how.ends_with("exact") && *max < EXACT_PX,
                "{tool}: {how} {max}"
            );
        }
        eprintln!("{tool}: {fitted:?}");
    }
}

/// Per camera, the largest image difference over the grid between the rig
/// in water and the same rig with its refraction dropped.
fn dropped_refraction_px(water: &Path, air: &Path) -> Vec<f64> {
    let read =
        |p: &Path| calibration::from_json(&std::fs::read_to_string(p).unwrap(), "x").unwrap();
    let (water, air) = (read(water), read(air));
    let volume = ptv::photogrammetry::Volume {
        min: nalgebra::Point3::new(-40.0, -40.0, -20.0),
        max: nalgebra::Point3::new(40.0, 40.0, 20.0),
    };
    water
        .iter()
        .zip(&air)
        .map(|(w, a)| {
            ptv::formats::between::reprojection_difference(w, &|p| a.project(p).ok(), &volume)
                .max_px
        })
        .collect()
}

#[test]
fn bad_camera_files_name_the_file_and_the_line() {
    let dir = tempfile::tempdir().unwrap();
    let air = in_air(dir.path());
    export("myptv", &air, "myptv", dir.path());
    export("openlpt", &air, "openlpt", dir.path());
    let corrupt = |tool: &str, line: usize, value: &str| -> PathBuf {
        let path = &files(dir.path(), tool)[0];
        let text = std::fs::read_to_string(path).unwrap();
        let mut lines: Vec<&str> = text.lines().collect();
        lines[line - 1] = value;
        let bad = dir.path().join(format!("bad_{tool}_{line}"));
        std::fs::write(&bad, lines.join("\n")).unwrap();
        bad
    };
    let run = |tool: &str, first: PathBuf, extra: &[&str]| {
        let mut all = files(dir.path(), tool);
        all[0] = first;
        let mut args = vec![
            "calibration".to_owned(),
            format!("import-{tool}"),
            "--pixel-size".to_owned(),
            "0.012".to_owned(),
            "--volume".to_owned(),
            VOLUME.to_owned(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend(all.iter().map(|f| path_str(f).to_owned()));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        ptv(&args, dir.path())
    };
    let bad = corrupt("myptv", 6, "NaN ");
    fails(
        &run("myptv", bad.clone(), &[]),
        &[path_str(&bad), "line 6", "`NaN`"],
    );
    let bad = corrupt("myptv", 5, "0.1 0.2");
    fails(
        &run("myptv", bad.clone(), &[]),
        &[path_str(&bad), "line 5", "3 numbers, found 2"],
    );
    let bad = corrupt("openlpt", 14, "0,0,0");
    fails(
        &run("openlpt", bad.clone(), &[]),
        &[path_str(&bad), "line 14", "found 3"],
    );
    let bad = corrupt("openlpt", 2, "PINPLATE");
    fails(
        &run("openlpt", bad.clone(), &[]),
        &[path_str(&bad), "line 2", "PINPLATE"],
    );
    let missing = dir.path().join("no_such_camera");
    fails(&run("myptv", missing.clone(), &[]), &["no_such_camera"]);
    let good = files(dir.path(), "myptv")[0].clone();
    let output = ptv(
        &[
            "calibration",
            "import-myptv",
            "--pixel-size",
            "12",
            "--volume",
            VOLUME,
            path_str(&good),
        ],
        dir.path(),
    );
    fails(&output, &["--pixel-size", "12"]);
    let output = ptv(
        &[
            "calibration",
            "export-openlpt",
            "--calibration",
            path_str(&air),
            "--volume",
            "-inf,40,-40,40,-20,20",
            "--out-dir",
            "x",
        ],
        dir.path(),
    );
    fails(&output, &["--volume", "finite"]);
}

/// The LPT challenge's `CalibPoints.txt` solved as control points:
/// simulated cameras (the 4-camera convergent rig in water) image 300
/// points through the volume with Gaussian noise of sigma = 0.1 px; the
/// setup gives only sensors and media. The a-posteriori sigma0 of each
/// camera must be sigma within 20% (with ~580 degrees of freedom its
/// relative standard deviation is 1/sqrt(2 * 580) = 3%: 20% is over 6 of
/// them), and the solved cameras' images over the volume's grid must agree
/// with the true ones to 3 sigma sqrt(p / n) RMS (the least-squares
/// prediction error of p = 16 parameters from n points, tripled).
#[test]
fn lpt_calib_points_are_solved_as_control_points() {
    use ptv::photogrammetry::simulate::{self, RigSpec};
    let dir = tempfile::tempdir().unwrap();
    let spec = RigSpec::convergent(4);
    let truth = spec.build().unwrap();
    let sigma = 0.1;
    let mut rng = simulate::rng(33);
    let points = simulate::particles(&spec.volume, 300, &mut rng);
    let images = simulate::observe(&truth, &points, sigma, &mut rng);
    let mut text = String::from("# X Y Z x1 y1 x2 y2 x3 y3 x4 y4\n");
    let mut n = 0;
    for (k, point) in points.iter().enumerate() {
        let seen: Option<Vec<_>> = images.iter().map(|camera| camera[k]).collect();
        let Some(seen) = seen else { continue };
        n += 1;
        text += &format!("{:?} {:?} {:?}", point.x, point.y, point.z);
        for pixel in seen {
            text += &format!(" {:?} {:?}", pixel.x, pixel.y);
        }
        text.push('\n');
    }
    assert!(n > 200, "{n}");
    std::fs::write(dir.path().join("CalibPoints.txt"), &text).unwrap();
    let mut setup: Value = serde_json::from_str(&calibration::to_json(&truth)).unwrap();
    for camera in setup["cameras"].as_array_mut().unwrap() {
        let camera = camera.as_object_mut().unwrap();
        for field in [
            "position",
            "angles",
            "principal_distance",
            "principal_point",
            "radial",
            "decentering",
            "affine",
        ] {
            camera.remove(field);
        }
    }
    std::fs::write(dir.path().join("setup.json"), setup.to_string()).unwrap();
    let report = succeeds(&ptv(
        &[
            "calibrate",
            "--calibration",
            "setup.json",
            "--calib-points",
            "CalibPoints.txt",
            "-o",
            "solved.json",
        ],
        dir.path(),
    ));
    let report: Value = serde_json::from_str(&report).unwrap();
    let solved = calibration::from_json(
        &std::fs::read_to_string(dir.path().join("solved.json")).unwrap(),
        "solved",
    )
    .unwrap();
    let bound = 3.0 * sigma * (16.0 / n as f64).sqrt();
    for (k, (a, b)) in truth.iter().zip(&solved).enumerate() {
        let sigma0 = report["cameras"][k]["sigma0_px"].as_f64().unwrap();
        assert!(
            (sigma0 / sigma - 1.0).abs() < 0.2,
            "camera {k}: sigma0 {sigma0}"
        );
        let d =
            ptv::formats::between::reprojection_difference(a, &|p| b.project(p).ok(), &spec.volume);
        eprintln!("camera {k}: sigma0 {sigma0:.4} px, images over the grid: RMS {:.4} px, max {:.4} px (bound RMS {bound:.4})", d.rms_px, d.max_px);
        assert!(d.rms_px < bound, "camera {k}: {d:?} against {bound}");
    }
    // A line with a camera's coordinates missing names the file and line.
    let bad: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| {
            if i == 3 {
                l.rsplit_once(' ').unwrap().0.to_owned() + "\n"
            } else {
                l.to_owned() + "\n"
            }
        })
        .collect();
    std::fs::write(dir.path().join("bad.txt"), bad).unwrap();
    fails(
        &ptv(
            &[
                "calibrate",
                "--calibration",
                "setup.json",
                "--calib-points",
                "bad.txt",
                "-o",
                "x.json",
            ],
            dir.path(),
        ),
        &["bad.txt", "line 4", "expected 11 numbers", "got 10"],
    );
}
