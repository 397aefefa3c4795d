//! Detection on a real recording against OpenPTV: test_cavity_recording's
//! frames 10001-10004 of cameras 1-4 (`tests/data/openptv/`), against the
//! targets optv 0.3.2 finds with the experiment's `targ_rec.par` after its
//! 25-pixel high-pass (`golden/test_cavity_recording/`).
//!
//! **The experiment's parameters in our terms**: thresholds 9/9/9/11,
//! `discont` 100 as `split_depth` 100 (for us the rise of a fainter maximum
//! above the saddle that joins it to a brighter one, in grey levels, below
//! which the two stay one target; and, as in OpenPTV's `targ_rec`, blobs
//! of pixels joined by an edge, not a corner: `detect.rs`, "OpenPTV's
//! segmentation"), 4..500 pixels, extent 2..100 in x and y, sum of
//! grey above 150 (`min_sumg` 151). OpenPTV's high-pass subtracts a box average of
//! `dim_lp = 25` pixels on each side of the pixel (liboptv's
//! `fast_box_blur`: a `(2·25+1)²` window), which is our `highpass_radius`
//! 25.
//!
//! **Pixel convention.** Ours puts pixel `i`'s centre at `i + 0.5`
//! (`detect.rs`). The golden targets turn out to use the same: the mean
//! offset of matched pairs is below 0.02 px in both axes on every image (a
//! convention difference would show as 0.5 px), so no shift is applied.
//!
//! **Comparison** (`tests/common/target_match.rs`): a target of either list
//! is found when the other has one within 0.5 px; targets whose bounding box
//! may touch the border are left out (OpenPTV keeps border-touching
//! targets, we drop them).
//!
//! **Agreement** (measured): counts within 3% of OpenPTV's on every image
//! (0.971..1.016); 88.4% of OpenPTV's targets found within 0.5 px over the
//! 16 images and 88.7% of ours, per image 85.0..93.4% both ways (camera 1
//! 90.5-93.4%, 2 85.0-87.1%, 3 85.3-87.5%, 4 89.3-91.0%): issue 13's goal
//! of 85% is reached on every image. With 8-connected blobs it was 82.7%
//! (79-88% per image). What is left: most of the misses are targets of
//! ours holding one of theirs and more pixels, which `targ_rec` parts by
//! the raster order of its growth (see `detect.rs`); about 1% of theirs
//! are targets whose sum of grey passes OpenPTV's 150 only on its
//! filtered values, which truncate the subtracted mean (up to one grey
//! level more per pixel).
//!
//! Run with `cargo test --test photogrammetry real_recording -- --nocapture`
//! to see the figures; `examples/detection_report.rs` prints the full table.

use std::path::Path;

use ptv::formats::image::read_image;
use ptv::formats::{parse_targets, read_text};
use ptv::photogrammetry::{detect, DetectionParameters, GreyImage, Target};

use crate::common::target_match::{compare, Agreement};

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv");
const FRAMES: [&str; 4] = ["10001", "10002", "10003", "10004"];

/// The detection parameters of camera `k` (1-based) as `ptv experiment
/// import` maps the recording's own `parameters/` folder (thresholds
/// 9/9/9/11, discont 100, 4..500 px, nx/ny 2..100, sum of grey >= 150,
/// high-pass radius 25): the importer is what a lab would use.
fn experiment_parameters(k: usize) -> DetectionParameters {
    let dir = Path::new(DATA).join("test_cavity_recording");
    let experiment = ptv::formats::experiment::read_experiment(&dir)
        .unwrap_or_else(|e| panic!("the recording's experiment does not read: {e}"));
    experiment.detection[k - 1].clone()
}

fn image(k: usize, frame: &str) -> GreyImage {
    read_image(
        &Path::new(DATA).join(format!("test_cavity_recording/img/cam{k}.{frame}")),
        None,
    )
    .expect("the recording's frame")
}

fn openptv_targets(k: usize, frame: &str) -> Vec<Target> {
    let path = Path::new(DATA).join(format!(
        "golden/test_cavity_recording/cam{k}.{frame}_targets"
    ));
    parse_targets(&read_text(&path).unwrap(), &path.display().to_string()).unwrap()
}

/// One image's comparison: within 0.5 px (the goal's radius) and within
/// 1 px (so that a 0.5 px convention difference would still pair up and
/// show in the mean offset).
struct Row {
    camera: usize,
    frame: &'static str,
    half: Agreement,
    one: Agreement,
}

/// Per camera and frame, ours against OpenPTV's.
fn agreements(parameters: impl Fn(usize) -> DetectionParameters) -> Vec<Row> {
    let mut out = Vec::new();
    for camera in 1..=4 {
        for frame in FRAMES {
            let image = image(camera, frame);
            let ours = detect(&image, &parameters(camera));
            let theirs = openptv_targets(camera, frame);
            let (w, h) = (image.width(), image.height());
            let half = compare(&ours, &theirs, (0.0, 0.0), 0.5, w, h);
            let one = compare(&ours, &theirs, (0.0, 0.0), 1.0, w, h);
            println!(
                "cam{camera}.{frame}: ours {:5}  OpenPTV {:5}  ratio {:.3}  within 0.5 px: theirs found {:5.1}%, ours found {:5.1}%  within 1 px: {:5.1}%, mean offset ({:+.3}, {:+.3})",
                half.ours,
                half.theirs,
                half.count_ratio(),
                100.0 * half.theirs_share(),
                100.0 * half.ours_share(),
                100.0 * one.theirs_share(),
                one.mean_dx,
                one.mean_dy
            );
            out.push(Row {
                camera,
                frame,
                half,
                one,
            });
        }
    }
    out
}

#[test]
fn experiment_parameters_reproduce_openptv_targets() {
    let (mut found, mut scored) = (0, 0);
    for Row {
        camera,
        frame,
        half: a,
        one,
    } in agreements(experiment_parameters)
    {
        // The pixel convention: a half-pixel difference would show here.
        // Today |mean| <= 0.018 px; most pairs (88-95%) take part.
        assert!(
            one.mean_dx.abs() < 0.05 && one.mean_dy.abs() < 0.05 && one.theirs_share() > 0.75,
            "cam{camera}.{frame}: {one:?}"
        );
        // Issue 13's goal, met on every image (today within 3%).
        assert!(
            (a.count_ratio() - 1.0).abs() <= 0.1,
            "cam{camera}.{frame}: {a:?}"
        );
        // Issue 13's goal is 85% both ways, REACHED on every image: today
        // 85.0-93.4% (lowest cam2.10001 and cam2.10004, 85.0%). Asserted
        // with a margin of 2 points, 83%, for the detector's work in
        // progress (centroid options, a faster flood), which moves
        // centroids by hundredths of a pixel, enough to carry a few
        // targets across the 0.5 px radius; the 8-connected blobs of before
        // (79-88%) fail it, a half-pixel shift (about 1%) too.
        assert!(a.theirs_share() >= 0.83, "cam{camera}.{frame}: {a:?}");
        assert!(a.ours_share() >= 0.83, "cam{camera}.{frame}: {a:?}");
        found += a.theirs_found;
        scored += a.theirs_scored;
    }
    // Today 88.4% over the 16 images (82.7% with 8-connected blobs); the
    // same 2-point margin.
    let share = found as f64 / scored as f64;
    assert!(share >= 0.864, "{share}");
}

#[test]
fn default_parameters_on_the_real_recording() {
    // Issue 13's goal with defaults only: at most 1.25x OpenPTV's count and
    // 80% of theirs found within 0.5 px, over the 16 images. Reached by
    // radius 25, 4-connected blobs and the automatic split rule's floor for
    // frames whose particle images have structure of their own (detect.rs,
    // "Structured particle images" and "Defaults on a real recording"):
    // 1.21x and 81.7%; per image 0.96-1.46x and 75.9-88.8%.
    // Asserted: the goal over all 16 images, and per image what a
    // regression to the old defaults (2.31-2.83x, 68.5-78.1%) fails: no
    // more than 1.6x their count and at least 74% of theirs found.
    let (mut ours, mut theirs, mut found, mut scored) = (0, 0, 0, 0);
    for Row {
        camera,
        frame,
        half: a,
        ..
    } in agreements(|_| DetectionParameters::default())
    {
        assert!(a.count_ratio() <= 1.6, "cam{camera}.{frame}: {a:?}");
        assert!(a.theirs_share() >= 0.74, "cam{camera}.{frame}: {a:?}");
        ours += a.ours;
        theirs += a.theirs;
        found += a.theirs_found;
        scored += a.theirs_scored;
    }
    let ratio = ours as f64 / theirs as f64;
    let share = found as f64 / scored as f64;
    println!(
        "defaults, all 16 images: {ratio:.3}x OpenPTV's count, {:.1}% of theirs found",
        100.0 * share
    );
    assert!(ratio <= 1.25, "{ratio}");
    assert!(share >= 0.80, "{share}");
}
