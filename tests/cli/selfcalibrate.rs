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

/// The true rig's cameras moved by 0.1 mm and turned by 0.1 mrad each
/// (random directions, seeded).
fn disturbed(cameras: &[ptv::photogrammetry::Camera]) -> Vec<ptv::photogrammetry::Camera> {
    use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
    use rand::Rng;
    let mut rng = ptv::photogrammetry::simulate::rng(5);
    let mut unit = || nalgebra::Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
    cameras
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.exterior.position += unit() * 0.1;
            let e = &p.exterior;
            let turn = nalgebra::Rotation3::from_scaled_axis(unit() * 1e-4);
            let r = turn.matrix() * rotation_matrix(e.omega, e.phi, e.kappa);
            (p.exterior.omega, p.exterior.phi, p.exterior.kappa) = rotation_angles(&r);
            ptv::photogrammetry::Camera::new(p).unwrap()
        })
        .collect()
}

/// Noise-free true points imaged by `truth` and intersected with `rig`:
/// the RMS reprojection residual (px).
fn disparity_px(truth: &[ptv::photogrammetry::Camera], rig: &[ptv::photogrammetry::Camera]) -> f64 {
    use ptv::photogrammetry::{intersect, simulate, Observation};
    let volume = simulate::RigSpec::convergent(truth.len()).volume;
    let mut rng = simulate::rng(99);
    let (mut sq, mut count) = (0.0, 0);
    for p in simulate::particles(&volume, 500, &mut rng) {
        let observations: Vec<Observation> = truth
            .iter()
            .enumerate()
            .map(|(camera, c)| Observation {
                camera,
                pixel: c.project(&p).unwrap(),
            })
            .collect();
        for r in &intersect(rig, &observations).unwrap().residuals_px {
            sq += r.norm_squared();
            count += 1;
        }
    }
    (sq / count as f64).sqrt()
}

/// `--images`: 4 frames rendered by `ptv simulate` (600 particles each),
/// detected with detect's defaults, then self-calibrated from a rig 0.1 mm
/// and 0.1 mrad off: the refined rig is consistent with the truth.
#[test]
fn images_are_detected_then_self_calibrated() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("frames")).unwrap();
    for frame in 0..4u64 {
        let out = format!("sim{frame}");
        let seed = (frame + 1).to_string();
        let args = [
            "simulate",
            "--cameras",
            "4",
            "--particles",
            "600",
            "--out",
            out.as_str(),
            "--seed",
            seed.as_str(),
        ];
        crate::common::succeeds(&ptv(&args, d));
        for k in 1..=4 {
            std::fs::rename(
                d.join(&out).join(format!("cam{k}.png")),
                d.join(format!("frames/cam{k}.{frame}.png")),
            )
            .unwrap();
        }
    }
    let read = |path: &Path| {
        let text = std::fs::read_to_string(path).unwrap();
        ptv::formats::calibration::from_json(&text, "calibration").unwrap()
    };
    let truth = read(&d.join("sim0/calibration.json"));
    let rough = disturbed(&truth);
    std::fs::write(
        d.join("rough.json"),
        ptv::formats::calibration::to_json(&rough),
    )
    .unwrap();
    let volume = ptv::photogrammetry::simulate::RigSpec::convergent(4).volume;
    let volume = format!(
        "--volume={},{},{},{},{},{}",
        volume.min.x, volume.max.x, volume.min.y, volume.max.y, volume.min.z, volume.max.z
    );
    let mut args = vec!["selfcalibrate", "--calibration", "rough.json"];
    let patterns: Vec<String> = (1..=4).map(|k| format!("frames/cam{k}.%d.png")).collect();
    for p in &patterns {
        args.extend(["--images", p.as_str()]);
    }
    args.extend([
        "--frames",
        "0..3",
        "--tolerance",
        "2",
        &volume,
        "-o",
        "refined.json",
    ]);
    let stdout = crate::common::succeeds(&ptv(&args, d));
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_ne!(report["outcome"], "diverged", "{report}");
    let refined = read(&d.join("refined.json"));
    let (before, after) = (disparity_px(&truth, &rough), disparity_px(&truth, &refined));
    eprintln!("true points through the rig: {before:.4} -> {after:.4} px RMS");
    // The disturbance matters (several tenths of a pixel); the refined rig
    // is within what 2,400 particles detected at the renderer's 0.05 px
    // centroid RMS (tests/photogrammetry/detect_accuracy.rs) determine:
    // 0.1 px leaves twice that per target.
    assert!(before > 0.2, "{before}");
    assert!(after < 0.1, "{before} -> {after}");

    // Patterns that match no image, and targets with images, are refused.
    let mut bad = args.clone();
    bad[4] = "frames/camX.%d.png";
    fails(
        &ptv(&bad, d),
        &["--images", "camX.%d.png", "matches no file"],
    );
    let mut both = args.clone();
    both.extend(["--targets", "t.%d.csv"]);
    let out = ptv(&both, d);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
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

/// `--disparity-png` draws the report's disparity maps: a PNG of the
/// layout's size with an arrow (the arrow colour) starting at the centre of
/// every cell that has particles and reaching towards its mean disparity,
/// and none in the cells without.
#[test]
fn draws_the_disparity_maps_as_a_png() {
    use ptv::plot::disparity::{DisparityLayout, ARROW, EMPTY};
    let dir = tempfile::tempdir().unwrap();
    calibration(dir.path());
    let mut args = vec!["selfcalibrate", "--calibration", "cal.json"];
    let p = patterns();
    for t in &p {
        args.extend(["--targets", t.as_str()]);
    }
    // OpenPTV's band on this recording (eps0 = 0.2 mm, about 17 px): the
    // input calibration is some px off.
    args.extend([
        "--frames",
        "10001..10004",
        "--tolerance",
        "16.7",
        "-o",
        "refined.json",
        "--disparity-png",
        "maps.png",
    ]);
    let out = ptv(&args, dir.path());
    assert!(out.status.success(), "{out:?}");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let image = image::open(dir.path().join("maps.png")).unwrap().to_rgb8();
    // `ptv plot disparity` draws the same picture from the report file.
    std::fs::write(dir.path().join("report.json"), &out.stdout).unwrap();
    let plot = ptv(
        &[
            "plot",
            "disparity",
            "--report",
            "report.json",
            "-o",
            "again.png",
        ],
        dir.path(),
    );
    assert!(plot.status.success(), "{plot:?}");
    assert_eq!(
        std::fs::read(dir.path().join("again.png")).unwrap(),
        std::fs::read(dir.path().join("maps.png")).unwrap()
    );

    let grid: Vec<usize> = report["grid"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let grid = [grid[0], grid[1], grid[2]];
    let cameras = report["cameras"].as_array().unwrap();
    let names: Vec<&str> = cameras
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    let maps = |c: &serde_json::Value| {
        [
            (false, c["map_before"].clone()),
            (true, c["map_after"].clone()),
        ]
    };
    let vector = |cell: &serde_json::Value| {
        (
            cell["mean_dx_px"].as_f64().unwrap(),
            cell["mean_dy_px"].as_f64().unwrap(),
        )
    };
    let max = cameras
        .iter()
        .flat_map(maps)
        .flat_map(|(_, m)| m["cells"].as_array().unwrap().clone())
        .map(|cell| {
            let (x, y) = vector(&cell);
            x.hypot(y)
        })
        .fold(0.0, f64::max);
    let layout = DisparityLayout::new(grid, &names, max).unwrap();
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    // Arrow pixels within `r` of a point.
    let arrow_near = |(x, y): (f64, f64), r: i64| {
        (-r..=r).any(|dy| {
            (-r..=r).any(|dx| {
                image
                    .get_pixel_checked((x as i64 + dx) as u32, (y as i64 + dy) as u32)
                    .is_some_and(|p| *p == ARROW)
            })
        })
    };
    let (mut cells, mut long) = (0, 0);
    for (c, camera) in cameras.iter().enumerate() {
        for (after, map) in maps(camera) {
            let mut filled = std::collections::HashSet::new();
            for cell in map["cells"].as_array().unwrap() {
                let index: Vec<usize> = cell["index"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_u64().unwrap() as usize)
                    .collect();
                let index = [index[0], index[1], index[2]];
                filled.insert(index);
                let centre = layout.cell_centre(c, after, index);
                assert!(
                    arrow_near(centre, 1),
                    "camera {c} after {after} cell {index:?}"
                );
                cells += 1;
                // Long arrows reach towards their vector: arrow pixels at
                // two thirds of the way to the tip.
                let tip = layout.arrow_tip(c, after, index, vector(cell));
                if (tip.0 - centre.0).hypot(tip.1 - centre.1) > 6.0 {
                    let on = (
                        centre.0 + (tip.0 - centre.0) * 2.0 / 3.0,
                        centre.1 + (tip.1 - centre.1) * 2.0 / 3.0,
                    );
                    assert!(
                        arrow_near(on, 1),
                        "camera {c} cell {index:?}: no shaft at {on:?}"
                    );
                    long += 1;
                }
            }
            // Empty cells are drawn empty.
            for k in 0..grid[2] {
                for j in 0..grid[1] {
                    for i in 0..grid[0] {
                        if !filled.contains(&[i, j, k]) {
                            let (x, y) = layout.cell_centre(c, after, [i, j, k]);
                            assert_eq!(*image.get_pixel(x as u32, y as u32), EMPTY);
                        }
                    }
                }
            }
        }
    }
    eprintln!(
        "disparity picture {}x{}: {cells} cells with arrows, {long} long enough to trace",
        layout.width, layout.height
    );
    assert!(cells > 100 && long > 5, "{cells} cells, {long} long arrows");
}
