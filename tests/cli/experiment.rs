//! `ptv experiment import` and `ptv process-sequence` on OpenPTV's
//! test_cavity recording (its legacy `parameters/` folder and pyptv's YAML
//! of the same experiment), on YAMLs written here, and on broken copies.
//!
//! Counts on the real frames are compared with OpenPTV's (optv 0.3.2):
//! targets within 10% per camera and frame (the goal for the same
//! parameters), particles at least 60% of OpenPTV's correspondences on the
//! same rig's frames (a sanity bound: our matcher keeps fewer ambiguous
//! candidates, and those frames' targets came from OpenPTV's own detection).

use std::path::{Path, PathBuf};

use ptv::formats::{calibration, image::read_image, openptv, vtk};
use ptv::photogrammetry::{Centroid, GreyPixels, Splitter};
use ptv::service::model::parameters::{DetectionSettings, MatchingSettings};
use serde_json::Value;

use crate::common::{fails, ptv, text};

const RECORDING: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/data/openptv/test_cavity_recording"
);
const GOLDEN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv/golden");

fn recording(path: &str) -> PathBuf {
    Path::new(RECORDING).join(path)
}

/// Runs `ptv`, asserts success and returns (stdout, stderr).
fn run(args: &[&str], dir: &Path) -> (String, String) {
    let output = ptv(args, dir);
    let stderr = text(&output.stderr).to_owned();
    assert!(output.status.success(), "{:?}: {stderr}", output.status);
    assert!(!stderr.contains("panicked"), "{stderr}");
    (text(&output.stdout).to_owned(), stderr)
}

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).expect("written")).expect("JSON")
}

/// A copy of the recording's parameters and calibration (no images).
fn copy_experiment() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for sub in ["parameters", "cal"] {
        std::fs::create_dir(dir.path().join(sub)).unwrap();
        for entry in std::fs::read_dir(recording(sub)).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), dir.path().join(sub).join(entry.file_name())).unwrap();
        }
    }
    dir
}

#[test]
fn the_legacy_folder_and_its_yaml_give_the_same_settings() {
    let out = tempfile::tempdir().unwrap();
    let (stdout, legacy_stderr) = run(
        &["experiment", "import", RECORDING, "-o", "legacy"],
        out.path(),
    );
    assert!(stdout.is_empty(), "{stdout}");
    let yaml = recording("parameters_Run1.yaml");
    let (_, yaml_stderr) = run(
        &["experiment", "import", yaml.to_str().unwrap(), "-o", "yaml"],
        out.path(),
    );
    let file = |form: &str, name: &str| read_json(&out.path().join(form).join(name));
    for name in ["calibration.json", "sequence.json"] {
        assert_eq!(file("legacy", name), file("yaml", name), "{name}");
    }
    // The settings, as OpenPTV means them.
    let sequence = file("legacy", "sequence.json");
    let detection: DetectionSettings =
        serde_json::from_value(sequence["detection"].clone()).unwrap();
    assert_eq!(detection.thresholds, Some(vec![9, 9, 9, 11]));
    assert_eq!(detection.split_depth, Some(100));
    // OpenPTV has no noise-relative test; its sum-of-grey bound decides.
    assert_eq!(detection.min_snr, Some(0));
    assert_eq!(detection.split, Some(true));
    assert_eq!(
        (detection.min_pixels, detection.max_pixels),
        (Some(4), Some(500))
    );
    assert_eq!((detection.min_nx, detection.max_nx), (Some(2), Some(100)));
    assert_eq!((detection.min_ny, detection.max_ny), (Some(2), Some(100)));
    // OpenPTV keeps sumg > 150, ours sumg >= 151.
    assert_eq!(detection.min_sumg, Some(151));
    assert_eq!(detection.highpass_radius, Some(25));
    let matching: MatchingSettings = serde_json::from_value(sequence["matching"].clone()).unwrap();
    // eps0 = 0.2 mm over 0.012 mm pixels.
    let tolerance = matching.tolerance.unwrap();
    assert!((tolerance - 0.2 / 0.012).abs() < 1e-9, "{tolerance}");
    assert_eq!(matching.min_cameras, Some(2));
    let volume = matching.volume.unwrap();
    assert_eq!(
        [volume[0], volume[1], volume[4], volume[5]],
        [-40.0, 40.0, -20.0, 25.0]
    );
    // Y is what the cameras see: wider than nothing, narrower than a metre.
    assert!(volume[2] < -10.0 && volume[3] > 10.0 && volume[3] - volume[2] < 1000.0);
    // The calibration is the .ori files' (as `calibration import-openptv`).
    let oris: Vec<PathBuf> = (1..=4)
        .map(|c| recording(&format!("cal/cam{c}.tif.ori")))
        .collect();
    let expected = openptv::import(&recording("parameters/ptv.par"), &oris).unwrap();
    let text = std::fs::read_to_string(out.path().join("legacy/calibration.json")).unwrap();
    let (cameras, splitter) = calibration::from_json_with_splitter(&text, "import").unwrap();
    assert_eq!(cameras, expected);
    assert_eq!(splitter, None);
    // What cannot be mapped is said, with the reason.
    for stderr in [&legacy_stderr, &yaml_stderr] {
        // track.par maps but for its turning angle, which ptv has no
        // counterpart of.
        assert!(
            stderr.contains("criteria.corrmin = 33")
                && stderr.contains("track.angle = 100")
                && stderr.contains("no angle limit")
                && !stderr.contains("track.dacc")
                && !stderr.contains("track.dvx"),
            "{stderr}"
        );
        assert!(
            stderr.lines().all(|l| l.starts_with("not mapped: ")),
            "{stderr}"
        );
    }
    let experiment = file("legacy", "experiment.json");
    assert_eq!(experiment["images"][3], "img/cam4.%d");
    assert_eq!(
        (experiment["first"].as_u64(), experiment["last"].as_u64()),
        (Some(10001), Some(10004))
    );
    assert_eq!(experiment["masks"], Value::Null);
    // track.par: the sphere around the -15.5..15.5 mm box, dacc, and
    // flagNewParticles as the image-space recovery; the same from the YAML.
    let tracking = &experiment["tracking"];
    let reach = 15.5 * 3f64.sqrt();
    assert!(
        (tracking["max_velocity"].as_f64().unwrap() - reach).abs() < 1e-9,
        "{tracking}"
    );
    assert_eq!(tracking["max_acceleration"], 2.8);
    assert_eq!(tracking["recovery"], true);
    assert_eq!(
        tracking["backward"], true,
        "the run's default (docs/tracking.md)"
    );
    assert_eq!(tracking["first_frame"], 10001);
    assert_eq!(tracking, &file("yaml", "experiment.json")["tracking"]);
}

/// A pyptv YAML for two cameras, with the given `ptv`, `criteria` and
/// extra sections.
fn two_camera_yaml(ptv_extra: &str, criteria: &str, extra: &str) -> String {
    format!(
        "num_cams: 2
ptv:
  allcam_flag: true
  hp_flag: false
  imx: 1280
  imy: 1024
  pix_x: 0.01
  pix_y: 0.014
  mmp_n1: 1.0
  mmp_n2: 1.33
  mmp_n3: 1.46
  mmp_d: 6.0
{ptv_extra}cal_ori:
  img_ori:
  - cal/cam1.tif.ori
  - cal/cam2.tif.ori
criteria:
{criteria}targ_rec:
  gvthres: [20, 30]
  disco: 7
  nnmin: 3
  nnmax: 90
  nxmin: 1
  nxmax: 12
  nymin: 1
  nymax: 13
  sumg_min: 40
  cr_sz: 2
sequence:
  base_name:
  - img/a%05d.tif
  - img/b%05d.tif
  first: 1
  last: 9
{extra}"
    )
}

const SLOPED: &str = "  X_lay: [-30, 50]
  Zmin_lay: [-10, -25]
  Zmax_lay: [20, 35]
  eps0: 0.05
";

/// A directory with the recording's first two .ori files and `yaml`.
fn yaml_experiment(yaml: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("cal")).unwrap();
    for c in 1..=2 {
        for ext in ["ori", "addpar"] {
            let name = format!("cam{c}.tif.{ext}");
            std::fs::copy(
                recording(&format!("cal/{name}")),
                dir.path().join("cal").join(name),
            )
            .unwrap();
        }
    }
    std::fs::write(dir.path().join("parameters_Test.yaml"), yaml).unwrap();
    dir
}

#[test]
fn a_yaml_written_here_maps_every_setting() {
    let yaml = two_camera_yaml(
        "",
        SLOPED,
        "masking:\n  mask_flag: true\n  mask_base_name: masks/m%d.png\ntrack:\n  dvxmin: -2\n  \
         dvxmax: 3\n  dvymin: -1\n  dvymax: 1\n  dvzmin: -1\n  dvzmax: 0.5\n  angle: 90\n  \
         dacc: 3.5\n  flagNewParticles: 0\n",
    );
    let dir = yaml_experiment(&yaml);
    std::fs::create_dir(dir.path().join("masks")).unwrap();
    for c in 1..=2 {
        std::fs::write(dir.path().join(format!("masks/m{c}.png")), b"not read here").unwrap();
    }
    // The directory's one YAML is found.
    let (_, stderr) = run(&["experiment", "import", ".", "-o", "out"], dir.path());
    assert!(stderr.contains("track.angle = 90"), "{stderr}");
    assert!(!stderr.contains("track.dacc"), "{stderr}");
    let tracking = read_json(&dir.path().join("out/experiment.json"))["tracking"].clone();
    // The sphere around the box: its farthest corner (3, 1, 1).
    assert_eq!(tracking["max_velocity"], 11f64.sqrt(), "{tracking}");
    assert_eq!(tracking["max_acceleration"], 3.5, "{tracking}");
    assert_eq!(tracking["recovery"], false, "{tracking}");
    // A track section without its box is refused, naming the key.
    let partial = yaml_experiment(&two_camera_yaml("", SLOPED, "track:\n  dacc: 3.5\n"));
    fails(
        &ptv(&["experiment", "import", "."], partial.path()),
        &["parameters_Test.yaml", "track", "dvxmin"],
    );
    let sequence = read_json(&dir.path().join("out/sequence.json"));
    let detection: DetectionSettings =
        serde_json::from_value(sequence["detection"].clone()).unwrap();
    assert_eq!(
        detection,
        DetectionSettings {
            threshold: Some(20),
            thresholds: Some(vec![20, 30]),
            highpass_radius: Some(0),
            min_pixels: Some(3),
            max_pixels: Some(90),
            min_nx: Some(1),
            max_nx: Some(12),
            min_ny: Some(1),
            max_ny: Some(13),
            min_sumg: Some(41),
            split: Some(true),
            split_depth: Some(7),
            centroid: Some(Centroid::Weighted),
            min_snr: Some(0),
        }
    );
    let matching: MatchingSettings = serde_json::from_value(sequence["matching"].clone()).unwrap();
    // eps0 over the mean pixel size; allcam_flag: both cameras.
    assert!((matching.tolerance.unwrap() - 0.05 / 0.012).abs() < 1e-9);
    assert_eq!(matching.min_cameras, Some(2));
    // The sloped depth range's enclosing box.
    let v = matching.volume.unwrap();
    assert_eq!([v[0], v[1], v[4], v[5]], [-30.0, 50.0, -25.0, 35.0]);
    let experiment = read_json(&dir.path().join("out/experiment.json"));
    assert_eq!(
        experiment["images"],
        serde_json::json!(["img/a%05d.tif", "img/b%05d.tif"])
    );
    let masks = experiment["masks"].as_array().unwrap();
    assert!(
        masks[1].as_str().unwrap().ends_with("masks/m2.png"),
        "{masks:?}"
    );
    // The sensor is the YAML's.
    let cameras = calibration::from_json(
        &std::fs::read_to_string(dir.path().join("out/calibration.json")).unwrap(),
        "import",
    )
    .unwrap();
    assert_eq!(cameras[1].sensor().pixel_size_y, 0.014);
}

#[test]
fn a_splitter_experiment_cuts_one_image_into_the_four_cameras() {
    // The recording's four frames as the quadrants of one image, in pyptv's
    // order: cam1 top-left, cam2 top-right, cam3 bottom-right, cam4
    // bottom-left.
    let dir = tempfile::tempdir().unwrap();
    let views: Vec<Vec<u8>> = (1..=4)
        .map(|c| {
            let image = read_image(&recording(&format!("img/cam{c}.10001")), None).unwrap();
            match image.pixels() {
                GreyPixels::Eight(p) => p.clone(),
                GreyPixels::Sixteen(_) => panic!("the recording is 8-bit"),
            }
        })
        .collect();
    let (w, h) = (1280usize, 1024usize);
    let mut whole = vec![0u8; 4 * w * h];
    for (view, (col, row)) in views.iter().zip([(0, 0), (1, 0), (1, 1), (0, 1)]) {
        for y in 0..h {
            let start = (row * h + y) * 2 * w + col * w;
            whole[start..start + w].copy_from_slice(&view[y * w..(y + 1) * w]);
        }
    }
    image::GrayImage::from_raw(2 * w as u32, 2 * h as u32, whole)
        .unwrap()
        .save(dir.path().join("whole.png"))
        .unwrap();
    let imported = tempfile::tempdir().unwrap();
    run(
        &["experiment", "import", RECORDING, "-o", "."],
        imported.path(),
    );
    let plain = std::fs::read_to_string(imported.path().join("calibration.json")).unwrap();
    let cameras = calibration::from_json(&plain, "import").unwrap();
    std::fs::write(
        dir.path().join("split.json"),
        calibration::to_json_with_splitter(&cameras, Some(Splitter::quadrants())),
    )
    .unwrap();
    std::fs::write(dir.path().join("plain.json"), &plain).unwrap();
    let flags = [
        "--threshold",
        "9",
        "--highpass-radius",
        "25",
        "--min-pixels",
        "4",
        "--min-sumg",
        "150",
        "--split-depth",
        "100",
        "--tolerance",
        "16.7",
    ];
    let mut args = vec![
        "process",
        "--calibration",
        "split.json",
        "--image",
        "whole.png",
    ];
    args.extend(flags);
    let (split, _) = run(&args, dir.path());
    let images: Vec<String> = (1..=4)
        .map(|c| {
            recording(&format!("img/cam{c}.10001"))
                .display()
                .to_string()
        })
        .collect();
    let mut args = vec!["process", "--calibration", "plain.json"];
    for image in &images {
        args.extend(["--image", image.as_str()]);
    }
    args.extend(flags);
    let (separate, _) = run(&args, dir.path());
    assert!(separate.lines().count() > 100, "{separate}");
    assert_eq!(split, separate);

    // A whole image the layout does not divide, one that divides into
    // views of the wrong size, and four images for one sensor.
    image::GrayImage::new(2559, 2048)
        .save(dir.path().join("odd.png"))
        .unwrap();
    fails(
        &ptv(
            &[
                "process",
                "--calibration",
                "split.json",
                "--image",
                "odd.png",
            ],
            dir.path(),
        ),
        &[
            "cannot split odd.png",
            "2559x2048 pixels",
            "does not divide evenly",
        ],
    );
    fails(
        &ptv(
            &[
                "process",
                "--calibration",
                "split.json",
                "--image",
                &images[0],
            ],
            dir.path(),
        ),
        &[
            "cam1.10001 is not an image of camera 0",
            "640x512",
            "1280x1024",
        ],
    );
    let mut args = vec!["process", "--calibration", "split.json"];
    for image in &images {
        args.extend(["--image", image.as_str()]);
    }
    fails(
        &ptv(&args, dir.path()),
        &["--image", "quadrants splitter", "give --image once"],
    );
}

/// `file` with its line `number` (1-based) replaced by `value`; returns
/// the text it had.
fn replace_line(file: &Path, number: usize, value: &str) -> String {
    let text = std::fs::read_to_string(file).unwrap();
    let mut lines: Vec<&str> = text.lines().collect();
    lines[number - 1] = value;
    std::fs::write(file, lines.join("\n")).unwrap();
    text
}

#[test]
fn broken_experiments_are_named_by_file_line_and_key() {
    // A .par value that does not parse.
    let dir = copy_experiment();
    let targ_rec = dir.path().join("parameters/targ_rec.par");
    replace_line(&targ_rec, 5, "lots");
    fails(
        &ptv(&["experiment", "import", ".", "-o", "out"], dir.path()),
        &["targ_rec.par: line 5, targ_rec.disco: expected an integer, got `lots`"],
    );
    // ptv.par goes through the same reader as the calibration import.
    let ptv_par = dir.path().join("parameters/ptv.par");
    let original = replace_line(&ptv_par, 13, "wide");
    fails(
        &ptv(&["experiment", "import", "."], dir.path()),
        &["ptv.par: line 13, ptv.imx: expected an integer, got `wide`"],
    );
    std::fs::write(&ptv_par, original).unwrap();
    // A value out of range.
    replace_line(&targ_rec, 5, "70000");
    fails(
        &ptv(&["experiment", "import", "."], dir.path()),
        &["targ_rec.par: line 5, targ_rec.disco: must be 0..65535, got 70000"],
    );
    // A missing .ori.
    let dir = copy_experiment();
    std::fs::remove_file(dir.path().join("cal/cam3.tif.ori")).unwrap();
    fails(
        &ptv(&["experiment", "import", "."], dir.path()),
        &[
            "cal_ori.par: line 7, cal_ori.img_ori[2]: names",
            "cam3.tif.ori, which does not exist",
        ],
    );
    // A YAML value of the wrong type: file, line and key.
    let yaml = two_camera_yaml("", SLOPED, "").replace("  nnmax: 90", "  nnmax: many");
    let dir = yaml_experiment(&yaml);
    let line = yaml.lines().position(|l| l.contains("nnmax")).unwrap() + 1;
    fails(
        &ptv(
            &["experiment", "import", "parameters_Test.yaml"],
            dir.path(),
        ),
        &[
            &format!("parameters_Test.yaml: line {line}, targ_rec.nnmax: invalid type"),
            "many",
        ],
    );
    // A YAML that is not YAML.
    let dir = yaml_experiment("ptv: [unclosed\n");
    fails(
        &ptv(
            &["experiment", "import", "parameters_Test.yaml"],
            dir.path(),
        ),
        &["parameters_Test.yaml: line "],
    );
    // A contradiction found after parsing is placed by its key's line.
    let yaml = two_camera_yaml("", &SLOPED.replace("[-30, 50]", "[50, -30]"), "");
    let dir = yaml_experiment(&yaml);
    let line = yaml.lines().position(|l| l.contains("X_lay")).unwrap() + 1;
    fails(
        &ptv(
            &["experiment", "import", "parameters_Test.yaml"],
            dir.path(),
        ),
        &[&format!(
            "line {line}, criteria.X_lay: X_lay[0] (50) must be smaller"
        )],
    );
    // Masking on, with a mask that is not there.
    let yaml = two_camera_yaml(
        "",
        SLOPED,
        "masking:\n  mask_flag: true\n  mask_base_name: masks/m%d.png\n",
    );
    let dir = yaml_experiment(&yaml);
    fails(
        &ptv(
            &["experiment", "import", "parameters_Test.yaml"],
            dir.path(),
        ),
        &[
            "masking.mask_base_name: names",
            "m1.png, which does not exist",
        ],
    );
    // A splitter for two cameras.
    let dir = yaml_experiment(&two_camera_yaml("  splitter: true\n", SLOPED, ""));
    fails(
        &ptv(
            &["experiment", "import", "parameters_Test.yaml"],
            dir.path(),
        ),
        &[
            "ptv.splitter: pyptv's splitter makes 4 views",
            "has 2 cameras",
        ],
    );
    // Two YAMLs and no parameters/: which one?
    std::fs::write(dir.path().join("parameters_Other.yaml"), "num_cams: 2\n").unwrap();
    fails(
        &ptv(&["experiment", "import", "."], dir.path()),
        &[
            "several pyptv YAMLs (parameters_Other.yaml, parameters_Test.yaml)",
            "give the path",
        ],
    );
}

/// The count on the first line of an OpenPTV file.
fn first_count(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

#[test]
fn process_sequence_runs_the_recording_with_its_own_parameters() {
    let out = tempfile::tempdir().unwrap();
    let (stdout, stderr) = run(
        &[
            "process-sequence",
            "--experiment",
            RECORDING,
            "-o",
            "res",
            "--frames",
            "10001..10004",
        ],
        out.path(),
    );
    // No terminal here: no progress bar.
    assert!(stderr.is_empty(), "{stderr}");
    let summary: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(summary["frames"], 4);
    let golden: Value = serde_json::from_str(
        &std::fs::read_to_string(Path::new(GOLDEN).join("test_cavity_frames.json")).unwrap(),
    )
    .unwrap();
    let res = out.path().join("res");
    let mut particles = 0;
    for frame in 10001..=10004u64 {
        for c in 1..=4 {
            let ours = first_count(&res.join(format!("cam{c}.{frame}_targets")));
            let theirs = first_count(
                &Path::new(GOLDEN).join(format!("test_cavity_recording/cam{c}.{frame}_targets")),
            );
            let ratio = ours as f64 / theirs as f64;
            assert!(
                (0.9..=1.1).contains(&ratio),
                "cam{c} {frame}: {ours} vs {theirs}"
            );
        }
        // rt_is and the CSV list the same particles.
        let rt_is = first_count(&res.join(format!("rt_is.{frame}")));
        let csv = std::fs::read_to_string(res.join(format!("particles.{frame}.csv"))).unwrap();
        assert_eq!(csv.lines().count(), rt_is + 1);
        let openptv: usize = golden["frames"][frame.to_string()]
            ["counts_quadruplets_triplets_pairs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n.as_u64().unwrap() as usize)
            .sum();
        assert!(
            rt_is as f64 >= 0.6 * openptv as f64 && rt_is as f64 <= 1.1 * openptv as f64,
            "{frame}: {rt_is} particles, OpenPTV {openptv}"
        );
        particles += rt_is;
    }
    assert_eq!(summary["particles"], particles);
    let by_cameras: usize = summary["particles_by_cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_u64().unwrap() as usize)
        .sum();
    assert_eq!(by_cameras, particles);
    // Residuals within the band the experiment allows (eps0 = 16.7 px).
    let median = summary["median_residual_px"].as_f64().unwrap();
    assert!(median > 0.0 && median < 0.2 / 0.012, "{median}");

    fails(
        &ptv(
            &[
                "process-sequence",
                "--experiment",
                RECORDING,
                "-o",
                "res",
                "--frames",
                "9..10002",
            ],
            out.path(),
        ),
        &["--frames: 9..10002 is outside the experiment's frames 10001..10004"],
    );
}

#[test]
fn process_sequence_subtracts_pyptvs_masks_and_the_background() {
    // The recording's YAML with masking on, each camera's "mask" being its
    // own frame 10001 (pyptv subtracts the masking image): frame 10001
    // becomes black and has no targets, frame 10002 keeps its particles.
    let yaml = std::fs::read_to_string(recording("parameters_Run1.yaml"))
        .unwrap()
        .replace("img/cam", &format!("{RECORDING}/img/cam"))
        .replace("cal/cam", &format!("{RECORDING}/cal/cam"))
        .replace(
            "mask_flag: false\n  mask_base_name: ''",
            &format!("mask_flag: true\n  mask_base_name: {RECORDING}/img/cam%d.10001"),
        );
    assert!(yaml.contains("mask_flag: true"));
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("parameters_Masked.yaml"), yaml).unwrap();
    let (stdout, _) = run(
        &[
            "process-sequence",
            "--experiment",
            "parameters_Masked.yaml",
            "-o",
            "res",
            "--frames",
            "10001..10002",
        ],
        dir.path(),
    );
    let summary: Value = serde_json::from_str(&stdout).unwrap();
    for c in 1..=4 {
        let res = dir.path().join("res");
        assert_eq!(first_count(&res.join(format!("cam{c}.10001_targets"))), 0);
        assert!(first_count(&res.join(format!("cam{c}.10002_targets"))) > 500);
    }
    assert!(summary["particles"].as_u64().unwrap() > 300, "{summary}");

    // A median background over the four frames: applied (the counts
    // change) and the particles remain (a sanity bound: a median of four
    // frames also takes away particles that stay in place).
    let out = tempfile::tempdir().unwrap();
    let (stdout, _) = run(
        &[
            "process-sequence",
            "--experiment",
            RECORDING,
            "-o",
            "res",
            "--background",
            "median",
        ],
        out.path(),
    );
    let with: Value = serde_json::from_str(&stdout).unwrap();
    let (stdout, _) = run(
        &["process-sequence", "--experiment", RECORDING, "-o", "plain"],
        out.path(),
    );
    let without: Value = serde_json::from_str(&stdout).unwrap();
    assert_ne!(with["targets_per_camera"], without["targets_per_camera"]);
    let particles = |v: &Value| v["particles"].as_u64().unwrap() as f64;
    assert!(
        particles(&with) >= 0.5 * particles(&without),
        "{with} {without}"
    );
}

/// The command line reads a user's own files where the experiment names
/// them, absolute paths included (the service's confinement is the
/// service's); the YAML limits are the same as the service's.
#[test]
fn the_cli_follows_a_users_own_paths_and_applies_the_yaml_limits() {
    let dir = copy_experiment();
    let elsewhere = tempfile::tempdir().unwrap();
    for ext in ["ori", "addpar"] {
        std::fs::rename(
            dir.path().join(format!("cal/cam1.tif.{ext}")),
            elsewhere.path().join(format!("cam1.tif.{ext}")),
        )
        .unwrap();
    }
    let ori = elsewhere.path().join("cam1.tif.ori");
    replace_line(
        &dir.path().join("parameters/cal_ori.par"),
        3,
        ori.to_str().unwrap(),
    );
    run(&["experiment", "import", ".", "-o", "out"], dir.path());
    let calibration = read_json(&dir.path().join("out/calibration.json"));
    assert_eq!(calibration["cameras"].as_array().map(Vec::len), Some(4));

    let yaml = yaml_experiment(&format!("x: {}1{}\n", "[".repeat(300), "]".repeat(300)));
    fails(
        &ptv(&["experiment", "import", "."], yaml.path()),
        &["line 1: more than 256 `[` and `{`"],
    );
    let yaml = yaml_experiment(&format!("x:\n{}1\n", "- ".repeat(1000)));
    fails(
        &ptv(&["experiment", "import", "."], yaml.path()),
        &["nested more than 16 levels deep"],
    );
}

/// Checks a VTK XML file strictly: well-formed XML (every tag closed, in
/// order; quick-xml's reader with end-name checks), a `VTKFile` of `kind`,
/// every inline binary `DataArray` decoding to exactly `NumberOfPoints`
/// (point data, `Points`), `NumberOfLines`/`NumberOfVerts` (cell data,
/// offsets) or their points (connectivity) values of its components.
/// Returns the arrays by name, as bytes, and the piece's counts.
fn strict_vtk(text: &str, kind: &str) -> (std::collections::BTreeMap<String, Vec<u8>>, [usize; 3]) {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<String> = Vec::new();
    let mut arrays = std::collections::BTreeMap::new();
    let mut counts = [0usize; 3];
    let mut current: Option<(String, usize, usize)> = None;
    let attr = |e: &quick_xml::events::BytesStart, name: &str| -> Option<String> {
        e.try_get_attribute(name)
            .unwrap()
            .map(|a| a.unescape_value().unwrap().into_owned())
    };
    loop {
        match reader.read_event().expect("well-formed XML") {
            Event::Start(e) => {
                let name = String::from_utf8(e.name().as_ref().to_vec()).unwrap();
                match name.as_str() {
                    "VTKFile" => {
                        assert_eq!(attr(&e, "type").as_deref(), Some(kind));
                        assert_eq!(attr(&e, "byte_order").as_deref(), Some("LittleEndian"));
                        assert_eq!(attr(&e, "header_type").as_deref(), Some("UInt32"));
                    }
                    "Piece" => {
                        let n = |k: &str| attr(&e, k).unwrap().parse::<usize>().unwrap();
                        counts = [n("NumberOfPoints"), n("NumberOfVerts"), n("NumberOfLines")];
                    }
                    "DataArray" => {
                        assert_eq!(attr(&e, "format").as_deref(), Some("binary"));
                        let size = match attr(&e, "type").unwrap().as_str() {
                            "Float64" | "Int64" => 8,
                            "UInt32" => 4,
                            other => panic!("type {other}"),
                        };
                        let components: usize =
                            attr(&e, "NumberOfComponents").unwrap().parse().unwrap();
                        current = Some((attr(&e, "Name").unwrap(), size, components));
                    }
                    _ => {}
                }
                stack.push(name);
            }
            Event::Text(t) => {
                if let Some((name, size, components)) = &current {
                    let bytes = vtk::decode_binary(&t.decode().unwrap()).expect("binary array");
                    let parent = stack[stack.len() - 2].as_str();
                    let cells = counts[1] + counts[2];
                    let expected = match (parent, name.as_str()) {
                        ("PointData" | "Points", _) => counts[0],
                        ("CellData", _) | ("Verts" | "Lines", "offsets") => cells,
                        ("Verts" | "Lines", "connectivity") => counts[0],
                        other => panic!("array {other:?}"),
                    };
                    assert_eq!(bytes.len(), expected * size * components, "{parent}/{name}");
                    arrays.insert(format!("{parent}/{name}"), bytes);
                }
            }
            Event::End(e) => {
                let name = String::from_utf8(e.name().as_ref().to_vec()).unwrap();
                assert_eq!(stack.pop().as_deref(), Some(name.as_str()));
                current = None;
            }
            Event::Empty(e) => {
                let name = String::from_utf8(e.name().as_ref().to_vec()).unwrap();
                assert_eq!(
                    name, "DataSet",
                    "only the series' entries are empty elements"
                );
                assert!(attr(&e, "timestep").is_some() && attr(&e, "file").is_some());
            }
            Event::Eof => break,
            _ => {}
        }
    }
    assert!(stack.is_empty(), "{stack:?}");
    (arrays, counts)
}

fn f64s(bytes: &[u8]) -> Vec<f64> {
    bytes
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

fn i64s(bytes: &[u8]) -> Vec<i64> {
    bytes
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

#[test]
fn process_sequence_tracks_the_recording_with_its_track_par_and_exports() {
    let out = tempfile::tempdir().unwrap();
    let (stdout, _) = run(
        &[
            "process-sequence",
            "--experiment",
            RECORDING,
            "-o",
            "res",
            "--track",
            "--ptv-is",
            "--export",
            "vtk",
            "--export",
            "hdf5",
        ],
        out.path(),
    );
    let summary: Value = serde_json::from_str(&stdout).unwrap();
    let tracking = &summary["tracking"];
    assert!(
        (tracking["max_velocity"].as_f64().unwrap() - 15.5 * 3f64.sqrt()).abs() < 1e-9,
        "{tracking}"
    );
    assert_eq!(tracking["max_acceleration"], 2.8);
    assert_eq!(tracking["recovery"], true);
    let res = out.path().join("res");
    let csv = std::fs::read_to_string(res.join("trajectories.csv")).unwrap();
    let points = ptv::formats::csv::parse_trajectories(&csv, "trajectories.csv").expect("a table");
    let trajectories: std::collections::BTreeSet<u64> =
        points.iter().map(|p| p.trajectory).collect();
    assert_eq!(tracking["points"], points.len());
    assert_eq!(tracking["trajectories"], trajectories.len());
    // Four frames of a few hundred particles: most are tracked through.
    let particles = summary["particles"].as_u64().unwrap() as usize;
    assert!(
        points.len() * 2 > particles,
        "{} of {particles}",
        points.len()
    );
    // ptv_is: per frame its particles, with links both ways that agree.
    let links = |frame: u64| -> Vec<(i64, i64)> {
        let text = std::fs::read_to_string(res.join(format!("ptv_is.{frame}"))).unwrap();
        let mut lines = text.lines();
        let n: usize = lines.next().unwrap().trim().parse().unwrap();
        let rows: Vec<(i64, i64)> = lines
            .map(|l| {
                let f: Vec<&str> = l.split_whitespace().collect();
                (f[0].parse().unwrap(), f[1].parse().unwrap())
            })
            .collect();
        assert_eq!(rows.len(), n);
        rows
    };
    let (a, b) = (links(10001), links(10002));
    let forward = a.iter().filter(|(_, next)| *next >= 0).count();
    assert!(forward > 0);
    for (i, (_, next)) in a.iter().enumerate() {
        if *next >= 0 {
            assert_eq!(b[*next as usize].0, i as i64);
        }
    }

    // ParaView: the per-frame files, the series and the polylines.
    let pvd = std::fs::read_to_string(res.join("particles.pvd")).unwrap();
    strict_vtk(&pvd, "Collection");
    for frame in 10001..=10004 {
        assert!(pvd.contains(&format!(
            "timestep=\"{frame}\" group=\"\" part=\"0\" file=\"particles.{frame}.vtp\""
        )));
        let text = std::fs::read_to_string(res.join(format!("particles.{frame}.vtp"))).unwrap();
        let (arrays, counts) = strict_vtk(&text, "PolyData");
        let rt_is = first_count(&res.join(format!("rt_is.{frame}")));
        // The frame's particles and those recovered from its images.
        assert!(
            counts[0] >= rt_is && counts[0] == counts[1],
            "{counts:?} {rt_is}"
        );
        let sigma = f64s(&arrays["PointData/sigma"]);
        assert!(sigma.iter().all(|s| *s > 0.0 && s.is_finite()));
    }
    let text = std::fs::read_to_string(res.join("trajectories.vtp")).unwrap();
    let (arrays, counts) = strict_vtk(&text, "PolyData");
    assert_eq!(counts, [points.len(), 0, trajectories.len()]);
    let offsets = i64s(&arrays["Lines/offsets"]);
    assert_eq!(*offsets.last().unwrap() as usize, points.len());
    // The polylines' points are the table's, trajectory by trajectory.
    let position = f64s(&arrays["Points/position"]);
    let mut sorted = points.clone();
    sorted.sort_by_key(|p| (p.trajectory, p.frame));
    for (i, p) in sorted.iter().enumerate() {
        assert_eq!(&position[3 * i..3 * i + 3], p.position.coords.as_slice());
        let v = f64s(&arrays["PointData/velocity"]);
        assert_eq!(&v[3 * i..3 * i + 3], p.velocity.unwrap().as_slice());
    }

    // HDF5: read back with the writer's own reader (h5py's reading is
    // shown in the docs and the closing note).
    let file = hdf5_pure::File::open(res.join("sequence.h5")).unwrap();
    assert_eq!(
        file.root().attrs().unwrap()["length_unit"],
        hdf5_pure::AttrValue::String("mm".into())
    );
    let column = |name: &str| file.dataset(&format!("trajectories/{name}")).unwrap();
    let ids = column("trajectory").read_i64().unwrap();
    let x = column("x").read_f64().unwrap();
    let u = column("u").read_f64().unwrap();
    assert_eq!(ids.len(), points.len());
    for (i, p) in sorted.iter().enumerate() {
        assert_eq!(ids[i] as u64, p.trajectory);
        assert_eq!(x[i], p.position.x);
        assert_eq!(u[i], p.velocity.unwrap().x);
    }
    assert_eq!(
        column("u").attrs().unwrap()["units"],
        hdf5_pure::AttrValue::String("mm/frame".into())
    );
    let frames = file
        .dataset("particles/frames")
        .unwrap()
        .read_i64()
        .unwrap();
    assert_eq!(frames, vec![10001, 10002, 10003, 10004]);
    let z = file
        .dataset("particles/frame_10002/z")
        .unwrap()
        .read_f64()
        .unwrap();
    assert!(z.len() >= first_count(&res.join("rt_is.10002")));
}

/// pyptv's test_splitter laid out as pyptv ships it (its parameters, YAML
/// and calibration copied unchanged into tests/data; its five 1 MB
/// recordings are not: frames of the same size are written here), run
/// from its folder: the `--` names of sequence.par mean the YAML.
#[test]
fn pyptvs_splitter_experiment_runs_from_its_folder() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/openptv/test_splitter");
    let dir = tempfile::tempdir().unwrap();
    let copy = |from: &Path, to: &Path| {
        std::fs::create_dir_all(to).unwrap();
        for entry in std::fs::read_dir(from).unwrap() {
            let entry = entry.unwrap();
            if entry.file_type().unwrap().is_file() {
                std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
            }
        }
    };
    copy(&fixture, dir.path());
    for sub in ["parameters", "cal"] {
        copy(&fixture.join(sub), &dir.path().join(sub));
    }
    // The recording's cameras' frames, each cut to a 512x512 quadrant of
    // one 1024x1024 sensor image, as the splitter's camera sees it.
    std::fs::create_dir(dir.path().join("img")).unwrap();
    for frame in 1..=2u32 {
        let mut whole = image::GrayImage::new(1024, 1024);
        for (c, (col, row)) in [(0u32, 0u32), (1, 0), (1, 1), (0, 1)].iter().enumerate() {
            let view =
                read_image(&recording(&format!("img/cam{}.1000{frame}", c + 1)), None).unwrap();
            let GreyPixels::Eight(p) = view.pixels() else {
                panic!("8-bit")
            };
            for y in 0..512u32 {
                for x in 0..512u32 {
                    let v = p[((y + 256) * 1280 + x + 384) as usize];
                    whole.put_pixel(col * 512 + x, row * 512 + y, image::Luma([v]));
                }
            }
        }
        whole
            .save(
                dir.path()
                    .join(format!("img/C001H001S000100000{frame}.tif")),
            )
            .unwrap();
    }
    let (stdout, _) = run(
        &[
            "process-sequence",
            "--experiment",
            ".",
            "--frames",
            "1000001..1000002",
            "-o",
            "res",
        ],
        dir.path(),
    );
    let summary: Value = serde_json::from_str(&stdout).unwrap();
    // The YAML was read: one image per frame, cut into four cameras.
    assert_eq!(summary["cameras"].as_array().unwrap().len(), 4, "{summary}");
    for targets in summary["targets_per_camera"].as_array().unwrap() {
        assert!(targets.as_u64().unwrap() > 0, "{summary}");
    }
    // The .par folder alone cannot say so: the error says what to give.
    std::fs::remove_file(dir.path().join("parameters_Run1.yaml")).unwrap();
    fails(
        &ptv(&["process-sequence", "--experiment", "."], dir.path()),
        &[
            "sequence.par",
            "base_name[1]",
            "`--`",
            "splitter",
            "parameters_*.yaml",
        ],
    );
}

#[test]
fn both_forms_that_differ_are_an_error_naming_both_files() {
    let dir = copy_experiment();
    let yaml = std::fs::read_to_string(recording("parameters_Run1.yaml")).unwrap();
    // Without images either form describes the experiment as well: the
    // same settings are one experiment, read once.
    std::fs::write(dir.path().join("parameters_Run1.yaml"), &yaml).unwrap();
    let out = tempfile::tempdir().unwrap();
    run(
        &[
            "experiment",
            "import",
            dir.path().to_str().unwrap(),
            "-o",
            ".",
        ],
        out.path(),
    );
    std::fs::write(
        dir.path().join("parameters_Run1.yaml"),
        yaml.replace("  dacc: 2.8", "  dacc: 1.5"),
    )
    .unwrap();
    fails(
        &ptv(
            &["experiment", "import", dir.path().to_str().unwrap()],
            out.path(),
        ),
        &[
            "parameters/ptv.par (the .par folder)",
            "parameters_Run1.yaml (pyptv's YAML)",
            "the tracking (track)",
            "give",
        ],
    );
    // Either is chosen by its path.
    let legacy = dir.path().join("parameters");
    run(
        &["experiment", "import", legacy.to_str().unwrap(), "-o", "l"],
        out.path(),
    );
    let tracking = read_json(&out.path().join("l/experiment.json"))["tracking"].clone();
    assert_eq!(tracking["max_acceleration"], 2.8);
    // Where only one form's images are there, that one describes it.
    std::fs::create_dir(dir.path().join("img")).unwrap();
    for c in 1..=4 {
        std::fs::copy(
            recording(&format!("img/cam{c}.10001")),
            dir.path().join(format!("img/cam{c}.10001")),
        )
        .unwrap();
    }
    std::fs::write(
        dir.path().join("parameters_Run1.yaml"),
        yaml.replace("  dacc: 2.8", "  dacc: 1.5")
            .replace("img/cam", "elsewhere/cam"),
    )
    .unwrap();
    run(
        &[
            "experiment",
            "import",
            dir.path().to_str().unwrap(),
            "-o",
            "c",
        ],
        out.path(),
    );
    let tracking = read_json(&out.path().join("c/experiment.json"))["tracking"].clone();
    assert_eq!(tracking["max_acceleration"], 2.8);
}
