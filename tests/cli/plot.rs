//! `ptv plot` from the files the other commands write: each subcommand's
//! PNG decodes at its layout's size with marks where the data are, its SVG
//! is an SVG document; bad input gets one line naming the file or flag.

use std::path::Path;

use crate::common::{fails, ptv, succeeds, succeeds_silently};
use ptv::formats::calibration;
use ptv::formats::control::{format_control_points, format_mark_observations};
use ptv::formats::csv::{parse_particles, parse_trajectories};
use ptv::photogrammetry::simulate::{self, RigSpec, TargetShape};
use ptv::plot::cameras_colour;
use ptv::plot::overlay::{self, LEGEND, MATCHED, MATCHED_RADIUS, UNMATCHED, UNMATCHED_RADIUS};
use ptv::plot::residuals::{ResidualLayout, ResidualReport, EXCLUDED, USED};
use ptv::plot::views::ViewsLayout;

fn decode(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

fn svg(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\""));
    assert!(text.trim_end().ends_with("</svg>"));
    text
}

fn at(image: &image::RgbImage, (x, y): (f64, f64)) -> image::Rgb<u8> {
    *image.get_pixel(x.round() as u32, y.round() as u32)
}

#[test]
fn frame_particle_and_trajectory_pictures_from_the_sequence_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    succeeds(&ptv(
        &[
            "simulate",
            "--cameras",
            "3",
            "--particles",
            "200",
            "--out",
            "sim",
            "--frames",
            "6",
            "--flow",
            "burgers",
            "--displacement",
            "0.3",
            "--seed",
            "2",
        ],
        d,
    ));
    let targets: Vec<String> = (1..=3)
        .map(|k| format!("sim/cam{k}_targets.00003.csv"))
        .collect();
    let mut args = vec!["match", "--calibration", "sim/calibration.json"];
    for t in &targets {
        args.extend(["--targets", t.as_str()]);
    }
    let particles = succeeds(&ptv(&args, d));
    std::fs::write(d.join("particles.csv"), &particles).unwrap();
    let mut args = vec!["track", "--calibration", "sim/calibration.json"];
    let patterns: Vec<String> = (1..=3)
        .map(|k| format!("sim/cam{k}_targets.%05d.csv"))
        .collect();
    for p in &patterns {
        args.extend(["--targets", p.as_str()]);
    }
    args.extend(["--frames", "0..5", "--max-velocity", "0.5"]);
    std::fs::write(d.join("trajectories.csv"), succeeds(&ptv(&args, d))).unwrap();

    // The overlay of camera 1 (cam2): rings on the isolated targets,
    // matched or not as the particles' t1 column says.
    let plot = |args: &[&str]| succeeds_silently(&ptv(&[&["plot"], args].concat(), d));
    plot(&[
        "overlay",
        "--calibration",
        "sim/calibration.json",
        "--camera",
        "1",
        "--image",
        "sim/cam2.00003.png",
        "--targets",
        "sim/cam2_targets.00003.csv",
        "--particles",
        "particles.csv",
        "-o",
        "overlay.png",
    ]);
    let image = decode(&d.join("overlay.png"));
    let cameras = calibration::from_json(
        &std::fs::read_to_string(d.join("sim/calibration.json")).unwrap(),
        "c",
    )
    .unwrap();
    let sensor = cameras[1].sensor();
    assert_eq!(
        image.dimensions(),
        (sensor.width.max(480), sensor.height + LEGEND)
    );
    let rows = parse_particles(&particles, "particles.csv").unwrap();
    let cam2 = ptv::formats::parse_targets(
        &std::fs::read_to_string(d.join("sim/cam2_targets.00003.csv")).unwrap(),
        "t",
    )
    .unwrap();
    let mut matched = vec![false; cam2.len()];
    for r in &rows {
        if let Some(t) = r.targets[1] {
            matched[t] = true;
        }
    }
    let mut checked = 0;
    for (i, t) in cam2.iter().enumerate() {
        if cam2
            .iter()
            .enumerate()
            .any(|(j, u)| j != i && (u.x - t.x).hypot(u.y - t.y) < 20.0)
        {
            continue;
        }
        let (cx, cy) = overlay::point(t.x, t.y);
        let (colour, r) = if matched[i] {
            (MATCHED, MATCHED_RADIUS)
        } else {
            (UNMATCHED, UNMATCHED_RADIUS)
        };
        assert_eq!(at(&image, (cx - r, cy)), colour, "target {i}");
        assert_eq!(at(&image, (cx, cy - r)), colour, "target {i}");
        checked += 1;
    }
    assert!(checked > 20, "{checked}");
    // Without the image, as SVG: a ring per target and legend key.
    plot(&[
        "overlay",
        "--calibration",
        "sim/calibration.json",
        "--camera",
        "1",
        "--targets",
        "sim/cam2_targets.00003.csv",
        "-o",
        "overlay.svg",
    ]);
    let text = svg(&d.join("overlay.svg"));
    assert!(!text.contains("<image"));
    // No particles: every target unmatched.
    assert_eq!(text.matches("stroke=\"#ff00ff\"").count(), cam2.len() + 1);

    // The particles: each in its camera count's colour or under a better
    // seen one.
    plot(&["particles", "--particles", "particles.csv", "-o", "p.png"]);
    let image = decode(&d.join("p.png"));
    let layout = ViewsLayout::of(rows.iter().map(|r| r.position));
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    for view in 0..3 {
        for r in &rows {
            let seen = r.targets.iter().flatten().count();
            let colour = at(&image, layout.point(view, &r.position));
            assert!((seen..6).any(|c| cameras_colour(c) == colour), "{colour:?}");
        }
    }

    // The trajectories: a drawn (not white) pixel within 1 px of every
    // point of a trajectory of 2 or more points.
    plot(&[
        "trajectories",
        "--trajectories",
        "trajectories.csv",
        "-o",
        "t.png",
    ]);
    plot(&[
        "trajectories",
        "--trajectories",
        "trajectories.csv",
        "-o",
        "t.SVG",
    ]);
    let image = decode(&d.join("t.png"));
    let points = parse_trajectories(
        &std::fs::read_to_string(d.join("trajectories.csv")).unwrap(),
        "t",
    )
    .unwrap();
    assert!(points.len() > 100, "{}", points.len());
    let layout = ViewsLayout::of(points.iter().map(|p| p.position));
    assert_eq!(image.dimensions(), (layout.width, layout.height));
    for p in &points {
        let (x, y) = layout.point(0, &p.position);
        let near = (-1..=1).any(|dy| {
            (-1..=1).any(|dx| {
                *image.get_pixel(
                    (x.round() as i64 + dx) as u32,
                    (y.round() as i64 + dy) as u32,
                ) != ptv::plot::WHITE
            })
        });
        assert!(near, "{p:?}");
    }
    assert!(svg(&d.join("t.SVG")).contains("<line"));

    // Bad input: one line naming the file, flag or format.
    let bad =
        |args: &[&str], needles: &[&str]| fails(&ptv(&[&["plot"], args].concat(), d), needles);
    bad(
        &["particles", "--particles", "particles.csv", "-o", "p.jpg"],
        &["p.jpg", ".png or .svg"],
    );
    std::fs::write(d.join("broken.csv"), "x,y,z\n1,2,oops\n").unwrap();
    bad(
        &["particles", "--particles", "broken.csv", "-o", "p.png"],
        &["broken.csv", "line 2", "column z"],
    );
    bad(
        &[
            "trajectories",
            "--trajectories",
            "particles.csv",
            "-o",
            "t.png",
        ],
        &["particles.csv", "trajectory"],
    );
    bad(
        &[
            "overlay",
            "--calibration",
            "sim/calibration.json",
            "--camera",
            "3",
            "--targets",
            "sim/cam2_targets.00003.csv",
            "-o",
            "o.png",
        ],
        &["--camera", "0 to 2"],
    );
    bad(
        &[
            "overlay",
            "--calibration",
            "sim/calibration.json",
            "--image",
            "sim/nothere.png",
            "--targets",
            "sim/cam2_targets.00003.csv",
            "-o",
            "o.png",
        ],
        &["sim/nothere.png"],
    );
}

#[test]
fn residual_pictures_from_ptv_calibrate_and_bad_reports() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut rng = simulate::rng(5);
    let spec = RigSpec::calibration(3);
    let truth = spec.build().unwrap();
    let target = simulate::calibration_target(TargetShape::Volume, &spec.volume, 120, &mut rng);
    let observations = simulate::observe_target(&truth, &target, 0.05, &mut rng);
    std::fs::write(d.join("setup.json"), calibration::to_json(&truth)).unwrap();
    std::fs::write(d.join("block.txt"), format_control_points(&target)).unwrap();
    let mut args = vec![
        "calibrate",
        "--calibration",
        "setup.json",
        "--control",
        "block.txt",
        "--check-every",
        "6",
        "-o",
        "cal.json",
    ];
    let names: Vec<String> = (1..=3).map(|k| format!("cam{k}.txt")).collect();
    for (name, marks) in names.iter().zip(&observations) {
        std::fs::write(d.join(name), format_mark_observations(marks)).unwrap();
        args.extend(["--observations", name.as_str()]);
    }
    let report = succeeds(&ptv(&args, d));
    std::fs::write(d.join("report.json"), &report).unwrap();
    let report = ResidualReport::from_json(&report, "report.json").unwrap();
    assert!(report.check_points.is_some());

    let plot = |args: &[&str]| succeeds_silently(&ptv(&[&["plot"], args].concat(), d));
    for camera in ["0", "2"] {
        plot(&[
            "residuals",
            "--calibration",
            "cal.json",
            "--report",
            "report.json",
            "--camera",
            camera,
            "-o",
            "r.png",
        ]);
        let image = decode(&d.join("r.png"));
        let residuals = &report.cameras[camera.parse::<usize>().unwrap()];
        let sensor = truth[0].sensor();
        let layout = ResidualLayout::new(residuals, (sensor.width, sensor.height));
        assert_eq!(image.dimensions(), (layout.width, layout.height));
        for r in residuals.residuals.iter().chain(&residuals.excluded) {
            let [x, y] = r.image_px.unwrap();
            let colour = at(&image, layout.sensor_point(x, y));
            assert!(colour == USED || colour == EXCLUDED, "{r:?}: {colour:?}");
        }
    }
    plot(&[
        "residuals",
        "--calibration",
        "cal.json",
        "--report",
        "report.json",
        "-o",
        "r.svg",
    ]);
    assert!(svg(&d.join("r.svg")).contains("Check points"));

    let bad =
        |args: &[&str], needles: &[&str]| fails(&ptv(&[&["plot"], args].concat(), d), needles);
    bad(
        &["disparity", "--report", "report.json", "-o", "d.png"],
        &["report.json", "not a self-calibration's report"],
    );
    bad(
        &[
            "residuals",
            "--calibration",
            "cal.json",
            "--report",
            "missing.json",
            "-o",
            "r.png",
        ],
        &["missing.json"],
    );
    std::fs::write(d.join("truncated.json"), "{\"cameras\": [").unwrap();
    bad(
        &[
            "residuals",
            "--calibration",
            "cal.json",
            "--report",
            "truncated.json",
            "-o",
            "r.png",
        ],
        &["truncated.json", "not JSON"],
    );
    bad(
        &[
            "residuals",
            "--calibration",
            "cal.json",
            "--report",
            "report.json",
            "--camera",
            "5",
            "-o",
            "r.png",
        ],
        &["--camera", "0 to 2"],
    );
}
