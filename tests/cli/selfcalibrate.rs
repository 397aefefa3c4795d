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
