//! `ptv reconstruct` and `ptv score` on `ptv simulate`'s rendered frames,
//! run as real processes in temporary directories.
//!
//! The sparse case (2000 particles on 1280x1024, 0.0015 particles per
//! pixel) has almost no overlapping particle images: within the 2-px
//! reach of an image lie other images with a chance of about
//! 0.0015 x pi x 2² = 2% per camera, so nearly every particle is seen
//! alone in at least three cameras and IPR must find it. The position
//! error is set by the renderer's noise: an image of peak A >= 80 grey and
//! sigma 0.69 px under sigma_n ~ 1.5 grey of photon and read noise is
//! located to sigma_n sqrt(2 / pi) / A ~ 0.015 px per camera; 0.05 px
//! RMS reprojected (over 3 sigma) fails only a fit that is not at the
//! noise floor. Recall >= 97% and ghosts <= 3% are the goals,
//! which the sparse case must meet with room (overlaps cost ~2%).

use std::path::Path;

use ptv::photogrammetry::GreyImage;

use crate::common::{fails, ptv, succeeds, text};

const VOLUME: &str = "--volume=-40,40,-40,40,-20,20";

fn images(dir: &str) -> Vec<String> {
    (1..=4)
        .flat_map(|c| ["--image".to_owned(), format!("{dir}/cam{c}.png")])
        .collect()
}

fn reconstruct(dir: &Path, extra: &[&str]) -> std::process::Output {
    let mut args: Vec<String> = vec![
        "reconstruct".into(),
        "--calibration".into(),
        "sim/calibration.json".into(),
    ];
    args.extend(images("sim"));
    args.extend(extra.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    ptv(&args, dir)
}

#[test]
fn reconstruct_then_score_a_sparse_frame_set() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    succeeds(&ptv(
        &[
            "simulate",
            "--cameras",
            "4",
            "--particles",
            "2000",
            "--seed",
            "3",
            "--out",
            "sim",
        ],
        d,
    ));
    let output = reconstruct(d, &[VOLUME]);
    let stdout = succeeds(&output);
    let stderr = text(&output.stderr);
    assert!(
        stdout.starts_with("x,y,z,sx,sy,sz,intensity,rms_px\n"),
        "{stdout}"
    );
    // A progress line per outer loop (8 + 3 by default), the model per
    // camera: the renderer's sigma 2.5/4 px widened by the pixel area to
    // sqrt(0.625² + 1/12) = 0.6875 px; a box-convolved Gaussian is not
    // quite a Gaussian, its best fit lies within 0.01 px of that.
    let defaults = ptv::photogrammetry::ipr::IprParameters::default();
    assert_eq!(
        stderr.lines().filter(|l| l.starts_with("loop ")).count(),
        defaults.loops + defaults.reduced_loops
    );
    for camera in 0..4 {
        let line = stderr
            .lines()
            .find(|l| l.starts_with(&format!("camera {camera}: particle image sigma ")))
            .unwrap_or_else(|| panic!("{stderr}"));
        let sigma: f64 = line.split_whitespace().nth(5).unwrap().parse().unwrap();
        assert!((sigma - 0.6875).abs() < 0.01, "{line}");
    }
    std::fs::write(d.join("ipr.csv"), &stdout).unwrap();
    let score = succeeds(&ptv(
        &[
            "score",
            "--calibration",
            "sim/calibration.json",
            "--truth",
            "sim/truth.csv",
            "--particles",
            "ipr.csv",
            VOLUME,
        ],
        d,
    ));
    let score: serde_json::Value = serde_json::from_str(&score).unwrap();
    assert_eq!(score["truth"], 2000, "{score}");
    assert!(score["recall"].as_f64().unwrap() >= 0.97, "{score}");
    assert!(score["ghost_fraction"].as_f64().unwrap() <= 0.03, "{score}");
    assert!(score["rms_px"].as_f64().unwrap() <= 0.05, "{score}");
    // The density is over the volume's footprint, which is smaller than
    // the sensor in every camera here: above 2,000 over the whole sensor.
    let per_camera = score["ppp_per_camera"].as_array().unwrap();
    assert_eq!(per_camera.len(), 4, "{score}");
    let over_sensor = 2000.0 / (1280.0 * 1024.0);
    for ppp in per_camera {
        let ppp = ppp.as_f64().unwrap();
        assert!(ppp > over_sensor && ppp < 1.0, "{score}");
    }
    let mean = per_camera.iter().map(|p| p.as_f64().unwrap()).sum::<f64>() / 4.0;
    assert!(
        (score["ppp"].as_f64().unwrap() - mean).abs() < 1e-12,
        "{score}"
    );
    // The truth scored against itself: everything found, exactly.
    let perfect: serde_json::Value = serde_json::from_str(&succeeds(&ptv(
        &[
            "score",
            "--calibration",
            "sim/calibration.json",
            "--truth",
            "sim/truth.csv",
            "--particles",
            "sim/truth.csv",
        ],
        d,
    )))
    .unwrap();
    assert_eq!(perfect["found"], 2000, "{perfect}");
    assert_eq!(perfect["ghosts"], 0, "{perfect}");
    assert_eq!(perfect["rms_mm"], 0.0, "{perfect}");
}

#[test]
fn reconstruct_refuses_bad_input_with_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    succeeds(&ptv(
        &[
            "simulate",
            "--cameras",
            "4",
            "--particles",
            "50",
            "--out",
            "sim",
        ],
        d,
    ));
    // A volume the cameras do not see.
    fails(
        &reconstruct(d, &["--volume=400,500,-40,40,-20,20"]),
        &["no two cameras see the observation volume", "x 400..500"],
    );
    // An image of another size than camera 2's sensor.
    let small = GreyImage::from_u8(640, 512, vec![20; 640 * 512]).unwrap();
    let bytes = ptv::formats::image::encode_png(&small, "small.png").unwrap();
    std::fs::write(d.join("sim/cam3.png"), bytes).unwrap();
    fails(
        &reconstruct(d, &[VOLUME]),
        &["sim/cam3.png is not an image of camera 2", "640"],
    );
    // One image too few.
    let output = ptv(
        &[
            "reconstruct",
            "--calibration",
            "sim/calibration.json",
            "--image",
            "sim/cam1.png",
        ],
        d,
    );
    fails(&output, &["has 4 cameras but 1 image was given"]);
}
