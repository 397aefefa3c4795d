//! The detector's unit tests, in one file over 800 lines because they share
//! the frames, references and allocation counter above them.

use super::highpass::*;
use super::*;
use crate::photogrammetry::simulate::rng;
use rand::Rng;

/// The filtered, thresholded levels by the definition: every window
/// summed pixel by pixel.
fn reference_levels(
    pixels: &[u16],
    width: usize,
    height: usize,
    r: usize,
    t: u64,
    scale: u64,
) -> Vec<u16> {
    let mut out = vec![0; width * height];
    for y in 0..height {
        for x in 0..width {
            let g = u64::from(pixels[y * width + x]);
            // Radius 0: no filter, a background of 0.
            let (s, c) = if r == 0 {
                (0, 1)
            } else {
                let mut s = 0;
                let mut c = 0;
                for wy in y.saturating_sub(r)..=(y + r).min(height - 1) {
                    for wx in x.saturating_sub(r)..=(x + r).min(width - 1) {
                        s += u64::from(pixels[wy * width + wx]);
                        c += 1;
                    }
                }
                (s, c)
            };
            // filtered = g - s/c > t, times scale, rounded, above t.
            if g * c > s + t * c {
                let d = (g * c - s) * scale;
                out[y * width + x] = ((2 * d + c) / (2 * c)).max(t * scale + 1) as u16;
            }
        }
    }
    out
}

#[test]
fn highpass_matches_its_definition() {
    let mut rng = rng(11);
    for (width, height, r) in [
        (17, 13, 0),
        (17, 13, 1),
        (17, 13, 3),
        (5, 9, 4),
        (9, 5, 7),
        (3, 3, 40),
        (1, 7, 2),
        (8, 1, 2),
        (1, 1, 1),
    ] {
        for max in [255u16, 65535] {
            let pixels: Vec<u16> = (0..width * height)
                .map(|_| rng.random_range(0..=max))
                .collect();
            let t = u64::from(max / 20);
            let parameters = DetectionParameters {
                threshold: t as u16,
                highpass_radius: r as u32,
                ..DetectionParameters::default()
            };
            let scale = if max == 255 { 257 } else { 1 };
            let expected = reference_levels(&pixels, width, height, r, t, scale);
            let got: Vec<u16> = if max == 255 {
                let eight: Vec<u8> = pixels.iter().map(|&v| v as u8).collect();
                let mut d = Detector::new(&eight, width, height, &parameters);
                d.highpass_threshold();
                d.levels
            } else {
                let mut d = Detector::new(&pixels, width, height, &parameters);
                d.highpass_threshold();
                d.levels
            };
            assert_eq!(got, expected, "{width}x{height}, r {r}, max {max}");
        }
    }
}

/// The 32-bit row filter is the 64-bit one wherever it is used: on
/// random rows and column sums within its range, both give the same
/// levels (`highpass_matches_its_definition` reaches the 64-bit one only
/// with windows too large to check pixel by pixel).
#[test]
fn the_narrow_row_filter_is_the_wide_one() {
    let mut rng = rng(12);
    for _ in 0..300 {
        let width = rng.random_range(1..80usize);
        let r = rng.random_range(1..12usize);
        let rows = rng.random_range(1..=(2 * r + 1)) as u64;
        let max: u16 = if rng.random_bool(0.5) { 255 } else { 4095 };
        let threshold = u64::from(rng.random_range(0..max / 4));
        let row: Vec<u16> = (0..width).map(|_| rng.random_range(0..=max)).collect();
        let sums: Vec<u32> = (0..width)
            .map(|_| rng.random_range(0..=rows as u32 * u32::from(max)))
            .collect();
        // The row starts at pixel `start` of a larger image: its
        // blocks' marks are the image's.
        let start = rng.random_range(0..200usize);
        let words = (start + width).div_ceil(64 * 64);
        let (mut wide, mut narrow) = (vec![0u16; width], vec![0u16; width]);
        let (mut marks_wide, mut marks_narrow) = (vec![0u64; words], vec![0u64; words]);
        let (mut above_wide, mut above_narrow) = (0, 0);
        let mut out = RowOut {
            levels: &mut wide,
            start,
            marks: &mut marks_wide,
            above: &mut above_wide,
        };
        filter_row(&row, &sums, r, rows, threshold, &mut out);
        let mut prefix = vec![0u32; width + 1];
        let mut out = RowOut {
            levels: &mut narrow,
            start,
            marks: &mut marks_narrow,
            above: &mut above_narrow,
        };
        filter_row_narrow(
            &row,
            &sums,
            &mut prefix,
            r,
            rows as u32,
            threshold as u32,
            &mut out,
        );
        assert_eq!(narrow, wide, "width {width}, r {r}, rows {rows}");
        assert_eq!(above_narrow, above_wide);
        assert_eq!(marks_narrow, marks_wide);
        // A block is marked exactly when it holds a level.
        for block in 0..words * 64 {
            let held = (block * 64..(block + 1) * 64)
                .any(|p| p >= start && p < start + width && wide[p - start] != 0);
            let marked = marks_wide[block / 64] >> (block % 64) & 1 == 1;
            assert_eq!(marked, held, "block {block}");
        }
    }
}

/// Blobs are searched for while the filter is still running, a few
/// rows behind it: a blob far taller than that gap (here 300 rows, and
/// a second one beside it, and particles below) is still found whole,
/// and once.
#[test]
fn a_blob_taller_than_the_filter_lead_is_found_whole() {
    let (width, height) = (40usize, 400usize);
    let mut pixels = vec![0u8; width * height];
    for y in 20..320 {
        for x in 10..13 {
            pixels[y * width + x] = 200;
        }
        // A second bar, starting lower and leaning right (two pixels
        // wide, so that its steps join by an edge), then a spot.
        if y >= 30 {
            pixels[y * width + 25 + (y - 30) / 100] = 150;
            pixels[y * width + 26 + (y - 30) / 100] = 150;
        }
    }
    for (x, y) in [(5, 350), (30, 380)] {
        pixels[y * width + x] = 120;
    }
    let image = GreyImage::from_u8(width as u32, height as u32, pixels).unwrap();
    let parameters = DetectionParameters {
        highpass_radius: 0,
        min_pixels: 1,
        max_pixels: 10_000,
        max_nx: 100,
        max_ny: 1000,
        split: false,
        ..DetectionParameters::default()
    };
    let targets = detect(&image, &parameters);
    let sizes: Vec<(u32, u32)> = targets.iter().map(|t| (t.n, t.ny)).collect();
    assert_eq!(
        sizes,
        [(900, 300), (580, 290), (1, 1), (1, 1)],
        "{targets:?}"
    );
}

fn image(width: u32, rows: &[&[u8]]) -> GreyImage {
    let pixels: Vec<u8> = rows.iter().flat_map(|r| r.iter().copied()).collect();
    GreyImage::from_u8(width, rows.len() as u32, pixels).unwrap()
}

fn unfiltered() -> DetectionParameters {
    DetectionParameters {
        threshold: 10,
        highpass_radius: 0,
        min_pixels: 1,
        split_depth: Some(5),
        ..DetectionParameters::default()
    }
}

/// A `width` x `height` frame of Gaussian noise of `sigma` grey levels
/// around `mean`, 8-bit, and its 16-bit copy (times 257).
fn noise_frame(width: u32, height: u32, mean: f64, sigma: f64, seed: u64) -> [GreyImage; 2] {
    use rand_distr::{Distribution, Normal};
    let normal = Normal::new(mean, sigma).unwrap();
    let mut rng = rng(seed);
    let pixels: Vec<u8> = (0..width * height)
        .map(|_| normal.sample(&mut rng).round().clamp(0.0, 255.0) as u8)
        .collect();
    let wide: Vec<u16> = pixels.iter().map(|&v| u16::from(v) * 257).collect();
    [
        GreyImage::from_u8(width, height, pixels).unwrap(),
        GreyImage::from_u16(width, height, wide).unwrap(),
    ]
}

/// The noise level (grey levels) the detector estimates for `image`.
fn estimated_noise(image: &GreyImage, parameters: &DetectionParameters) -> f64 {
    let (w, h) = (image.width() as usize, image.height() as usize);
    match image.pixels() {
        GreyPixels::Eight(p) => {
            let mut d = Detector::new(p, w, h, parameters);
            d.highpass_threshold();
            f64::from(d.noise) / 257.0
        }
        GreyPixels::Sixteen(p) => {
            let mut d = Detector::new(p, w, h, parameters);
            d.highpass_threshold();
            f64::from(d.noise) / 257.0
        }
    }
}

#[test]
fn the_noise_level_is_estimated_after_the_filter() {
    // Gaussian noise of sigma around a constant: the filtered value
    // is the noise less its window mean, of standard deviation sigma
    // sqrt(1 + 1/c) (c = 21² pixels: sigma within 0.2%). The estimate
    // uses 8,192 samples of a 1024² frame; a quantile-based sigma from
    // N samples has a relative standard error of about 1.2/sqrt(N)
    // (1.3%), and rounding to whole grey levels adds 1/12 grey level²
    // of variance (at sigma 3, 0.5%): 6% is over 4 standard errors.
    for sigma in [3.0, 6.0, 20.0] {
        let [eight, sixteen] = noise_frame(1024, 1024, 100.0, sigma, 5);
        let parameters = DetectionParameters::default();
        let a = estimated_noise(&eight, &parameters);
        let b = estimated_noise(&sixteen, &parameters);
        assert!((a / sigma - 1.0).abs() < 0.06, "sigma {sigma}: {a}");
        // An 8-bit frame and its 16-bit copy have the same levels.
        assert_eq!(a, b, "sigma {sigma}");
        // Without the filter, the same (the mean is far from 0).
        let unfiltered = DetectionParameters {
            highpass_radius: 0,
            ..parameters.clone()
        };
        let c = estimated_noise(&eight, &unfiltered);
        assert!(
            (c / sigma - 1.0).abs() < 0.06,
            "sigma {sigma}, no filter: {c}"
        );
    }
}

#[test]
fn pure_noise_gives_no_targets_by_default() {
    // The default threshold (10) at 3.3, 2 and 1.5 sigma of the noise:
    // 0.05%, 2.3% and 6.7% of the pixels are above it, in small
    // clusters. A cluster of n such pixels has a mean level of about
    // threshold + 0.4 sigma, so the signal-to-noise test (12 sigma
    // sqrt n) needs n >= 40 of them connected even at 1.5 sigma, which
    // pure noise so far below the percolation threshold (about 59% of
    // the pixels for 4-connected sites) does not make. Without the test,
    // every cluster of 2 or more pixels is a target. The 16-bit copy
    // with the threshold in its units (times 257) is the same test.
    for (sigma, seed) in [(3.0, 1), (5.0, 2), (6.67, 3)] {
        for (image, scale) in noise_frame(512, 512, 100.0, sigma, seed)
            .into_iter()
            .zip([1, 257])
        {
            let defaults = DetectionParameters {
                threshold: 10 * scale,
                ..DetectionParameters::default()
            };
            let with = detect(&image, &defaults);
            assert!(with.is_empty(), "sigma {sigma}: {} targets", with.len());
            let without = detect(
                &image,
                &DetectionParameters {
                    min_snr: 0,
                    ..defaults
                },
            );
            if sigma > 4.0 {
                assert!(without.len() > 100, "sigma {sigma}: {}", without.len());
            }
        }
    }
}

#[test]
fn centroid_weights_grey_values_above_the_threshold() {
    // Weights 30 - 10 and 50 - 10: x = 1.5 + 40 / 60 = 2.1667 (pixel
    // centres at i + 0.5).
    let targets = detect(
        &image(5, &[&[0, 0, 0, 0, 0], &[0, 30, 50, 0, 0], &[0, 0, 0, 0, 0]]),
        &unfiltered(),
    );
    assert_eq!(targets.len(), 1);
    let t = targets[0];
    assert!((t.x - (1.5 + 40.0 / 60.0)).abs() < 1e-12, "{t:?}");
    assert!((t.y - 1.5).abs() < 1e-12);
    assert_eq!((t.n, t.nx, t.ny, t.sumg), (2, 2, 1, 80));
}

#[test]
fn overlapping_particles_split_at_the_grey_value_minimum() {
    let rows: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0, 0, 0, 0],
        &[0, 20, 40, 20, 15, 30, 60, 30, 0],
        &[0, 40, 90, 40, 25, 50, 120, 50, 0],
        &[0, 20, 40, 20, 15, 30, 60, 30, 0],
        &[0, 0, 0, 0, 0, 0, 0, 0, 0],
    ];
    let split = detect(&image(9, rows), &unfiltered());
    assert_eq!(split.len(), 2, "{split:?}");
    // Column 4 is the valley; its pixels join the brighter neighbour on
    // the right (30/50/30 beats 20/40/20).
    assert_eq!((split[0].n, split[1].n), (9, 12));
    let plain = detect(
        &image(9, rows),
        &DetectionParameters {
            split: false,
            ..unfiltered()
        },
    );
    assert_eq!(plain.len(), 1);
    assert_eq!(plain[0].n, 21);
}

#[test]
fn shallow_dips_are_noise_not_a_second_particle() {
    // The right maximum rises 4 above the saddle (36 at column 3): at
    // depth 5 it is noise on one particle, at depth 3 a second one.
    let rows: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0, 0],
        &[0, 20, 30, 20, 25, 20, 0],
        &[0, 30, 90, 36, 40, 30, 0],
        &[0, 20, 30, 20, 25, 20, 0],
        &[0, 0, 0, 0, 0, 0, 0],
    ];
    assert_eq!(detect(&image(7, rows), &unfiltered()).len(), 1);
    let deep = DetectionParameters {
        split_depth: Some(3),
        ..unfiltered()
    };
    assert_eq!(detect(&image(7, rows), &deep).len(), 2);
}

#[test]
fn blobs_join_pixels_by_their_edges_only() {
    // Two 2x2 spots touching at a corner: two 4-connected blobs, as
    // OpenPTV's targ_rec finds, with either split rule (as one
    // 8-connected blob the dimmer spot's corner pixel would join the
    // brighter one, with no saddle between them).
    let rows: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0],
        &[0, 50, 50, 0, 0, 0],
        &[0, 50, 50, 0, 0, 0],
        &[0, 0, 0, 60, 60, 0],
        &[0, 0, 0, 60, 60, 0],
        &[0, 0, 0, 0, 0, 0],
    ];
    for split_depth in [None, unfiltered().split_depth] {
        let found = detect(
            &image(6, rows),
            &DetectionParameters {
                split_depth,
                ..unfiltered()
            },
        );
        assert_eq!(found.len(), 2, "{split_depth:?}: {found:?}");
        assert_eq!((found[0].x, found[0].y), (2.0, 2.0));
        assert_eq!((found[1].x, found[1].y), (4.0, 4.0));
    }
}

#[test]
fn the_automatic_rule_splits_particles_but_not_ripples_on_a_streak() {
    // A streak at 200 with a ripple rising 20 above a saddle at 180:
    // 20 is less than a fifth of the ripple's 190 above the threshold,
    // so one target (an absolute depth of 4 cuts it in two).
    let streak: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0, 0],
        &[0, 150, 150, 150, 150, 150, 0],
        &[0, 200, 180, 200, 150, 100, 0],
        &[0, 150, 150, 150, 150, 150, 0],
        &[0, 0, 0, 0, 0, 0, 0],
    ];
    let auto = DetectionParameters {
        split_depth: None,
        ..unfiltered()
    };
    assert_eq!(detect(&image(7, streak), &auto).len(), 1);
    let absolute = DetectionParameters {
        split_depth: Some(4),
        ..unfiltered()
    };
    assert_eq!(detect(&image(7, streak), &absolute).len(), 2);
    // Two touching particles: the fainter (120) rises 95 above the
    // saddle (25), more than a fifth of its 110 above the threshold.
    let rows: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0, 0, 0, 0],
        &[0, 20, 40, 20, 15, 30, 60, 30, 0],
        &[0, 40, 90, 40, 25, 50, 120, 50, 0],
        &[0, 20, 40, 20, 15, 30, 60, 30, 0],
        &[0, 0, 0, 0, 0, 0, 0, 0, 0],
    ];
    assert_eq!(detect(&image(9, rows), &auto).len(), 2);
}

#[test]
fn a_blob_whole_at_the_lower_floor_may_part_at_the_higher_and_is_split_again() {
    // A blob (levels, noise level 10) that is one particle with the 3
    // sigma floor and two with 25 sigma. At 3 sigma the maxima X (400)
    // and X' (200) stay apart at their saddle (150); each then fails
    // the cap test alone where it meets the ridge of P1 (5000) and
    // merges into it. At 25 sigma X' merges into X first, and their
    // union passes the cap test at the ridge. So a structured frame
    // cannot keep the first split's target of every blob that came out
    // whole: only of those where no saddle kept particles apart
    // (`kept_apart`), which this one did.
    let (width, height) = (52usize, 3usize);
    let mut levels = vec![0u16; width * height];
    let mut set = |x: usize, y: usize, level: u16| levels[y * width + x] = level;
    (1..45).for_each(|x| set(x, 0, 140)); // X's shelf
    set(45, 0, 400); // X
    set(46, 0, 150); // the saddle of X and X'
    set(47, 0, 200); // X'
    (48..51).for_each(|x| set(x, 0, 130)); // X''s shelf
    set(1, 1, 140); // where X's shelf meets the ridge
    set(49, 1, 130); // where X''s shelf meets it
    (0..52).for_each(|x| set(x, 2, 1000)); // P1's ridge
    set(25, 2, 5000); // P1
    let pixels = vec![0u8; width * height];
    let parameters = DetectionParameters {
        threshold: 0,
        ..DetectionParameters::default()
    };
    let particles = |floor: u64| {
        let mut detector = Detector::new(&pixels[..], width, height, &parameters);
        detector.levels = levels.clone();
        detector.above = width * height;
        detector.noise = 10;
        detector.split_noise = floor;
        detector.reserve_blob(None);
        detector.flood(2 * width + 25); // P1
        let (corner, size) = detector.blob_box();
        let maxima = detector.count_maxima(usize::MAX);
        detector.split(corner, size, maxima);
        let mut roots: Vec<u32> = (0..detector.blob.len())
            .map(|i| {
                let (x, y) = detector.position(key_index(detector.blob[i]));
                let cell = detector.cell((x, y), corner, size.0 + 2);
                detector.find(detector.grid[cell])
            })
            .collect();
        roots.sort_unstable();
        roots.dedup();
        (roots.len(), detector.kept_apart)
    };
    assert_eq!(particles(AUTO_SPLIT_NOISE), (1, true));
    assert_eq!(particles(AUTO_SPLIT_NOISE_STRUCTURED).0, 2);
}

#[test]
fn rings_stay_whole_where_overlaps_cannot_explain_their_maxima() {
    // 300 out-of-focus particle images, rings of radius 2.5..4.5 px
    // with two bumps on opposite sides (75 grey levels on the bumps, 45
    // between them, added to a background of 20 with noise of sigma 2),
    // spread 40 px apart: no two touch. Each ring's second bump rises
    // 30 grey levels (about 15 sigma) above the saddle, which the 3
    // sigma floor splits (as an absolute depth of 10 does: 600
    // targets) and the structured frame's 25 sigma does not.
    let (width, height) = (800usize, 600usize);
    let [noise, _] = noise_frame(width as u32, height as u32, 20.0, 2.0, 7);
    let GreyPixels::Eight(mut pixels) = noise.pixels().clone() else {
        unreachable!("an 8-bit frame")
    };
    let mut rings = 0;
    for cy in (20..height - 20).step_by(40) {
        for cx in (20..width - 20).step_by(40) {
            if rings == 300 {
                break;
            }
            rings += 1;
            for y in cy - 5..=cy + 5 {
                for x in cx - 5..=cx + 5 {
                    let (dx, dy) = (x as f64 - cx as f64, y as f64 - cy as f64);
                    let r = dx.hypot(dy);
                    if (2.5..=4.5).contains(&r) {
                        let cos2 = (dx * dx - dy * dy) / (r * r);
                        let level = 60.0 + 15.0 * cos2;
                        pixels[y * width + x] = pixels[y * width + x].saturating_add(level as u8);
                    }
                }
            }
        }
    }
    let image = GreyImage::from_u8(width as u32, height as u32, pixels).unwrap();
    let found = detect(&image, &DetectionParameters::default());
    assert_eq!(found.len(), rings, "the defaults");
    let split = detect(
        &image,
        &DetectionParameters {
            split_depth: Some(10),
            ..DetectionParameters::default()
        },
    );
    assert_eq!(split.len(), 2 * rings, "an absolute depth of 10");
}

#[test]
fn the_automatic_rule_splits_only_at_a_cap_that_stands_out_of_the_noise() {
    // Noise of 5.93 grey levels: its lower quartile lies 0.6745 sigma =
    // 4.0 levels below its median, a whole number, so the estimate
    // (1.4826 times that spread) of 8-bit samples, whose quantiles are
    // whole levels, is 5.93 whatever pixels it samples (with noise of
    // 5 levels the spread, 3.37, rounds to 3 or 4 by the sample, an
    // estimate of 4.45 or 5.93). On it a particle peaking at
    // 240 and, joined to it at a saddle of 190, a second maximum of 212
    // with four more pixels brighter than the saddle. Its peak rises 22
    // above the saddle: more than 3 sigma (17.8) and than a fifth of
    // its 77 above the threshold (15.4), so only the cap test decides.
    // Flat (the four at 196, 192, 196, 196), the cap's volume above the
    // saddle is 22 + 6 + 2 + 6 + 6 = 42, less than 4 sigma sqrt(5) =
    // 53: one target. A full bump (205, 192, 205, 205): 69, two.
    for (cap, expected) in [(196u8, 1), (205, 2)] {
        for (image, scale) in noise_frame(512, 512, 100.0, 5.93, 7)
            .into_iter()
            .zip([1, 257])
        {
            let object: [[u8; 6]; 3] = [
                [170, 190, 170, 150, cap, cap],
                [190, 240, 190, 192, 208, cap],
                [170, 190, 170, 150, 150, 150],
            ];
            let (width, height) = (image.width(), image.height());
            let mut pixels: Vec<u16> = match image.pixels() {
                GreyPixels::Eight(p) => p.iter().map(|&v| u16::from(v)).collect(),
                GreyPixels::Sixteen(p) => p.clone(),
            };
            for (r, row) in object.iter().enumerate() {
                for (c, &v) in row.iter().enumerate() {
                    pixels[(200 + r) * width as usize + 300 + c] = u16::from(v) * scale;
                }
            }
            let image = if scale == 1 {
                let eight = pixels.iter().map(|&v| v as u8).collect();
                GreyImage::from_u8(width, height, eight).unwrap()
            } else {
                GreyImage::from_u16(width, height, pixels).unwrap()
            };
            let parameters = DetectionParameters {
                threshold: 135 * scale,
                highpass_radius: 0,
                min_pixels: 1,
                ..DetectionParameters::default()
            };
            let noise = estimated_noise(&image, &parameters);
            assert!((noise - 5.93).abs() < 0.3, "{noise}");
            let targets = detect(&image, &parameters);
            assert_eq!(
                targets.len(),
                expected,
                "cap {cap}, scale {scale}: {targets:?}"
            );
        }
    }
}

#[test]
fn targets_touching_the_border_and_filtered_ones_are_dropped() {
    let rows: &[&[u8]] = &[
        &[0, 0, 0, 0, 0, 0, 0],
        &[50, 0, 0, 0, 0, 0, 0],
        &[0, 0, 0, 60, 0, 0, 0],
        &[0, 0, 0, 60, 0, 0, 0],
        &[0, 0, 0, 0, 0, 0, 0],
    ];
    assert_eq!(detect(&image(7, rows), &unfiltered()).len(), 1);
    for filter in [
        DetectionParameters {
            min_pixels: 3,
            ..unfiltered()
        },
        DetectionParameters {
            max_ny: 1,
            ..unfiltered()
        },
        DetectionParameters {
            min_nx: 2,
            ..unfiltered()
        },
        DetectionParameters {
            min_sumg: 121,
            ..unfiltered()
        },
    ] {
        assert!(detect(&image(7, rows), &filter).is_empty(), "{filter:?}");
    }
}

#[test]
fn any_parameters_on_any_image_are_safe() {
    let tiny = GreyImage::from_u8(1, 1, vec![255]).unwrap();
    let flat = GreyImage::from_u16(4, 3, vec![65535; 12]).unwrap();
    for parameters in [
        DetectionParameters::default(),
        DetectionParameters {
            threshold: 0,
            highpass_radius: u32::MAX,
            min_pixels: 0,
            ..DetectionParameters::default()
        },
        DetectionParameters {
            threshold: u16::MAX,
            min_pixels: 9,
            max_pixels: 1,
            ..DetectionParameters::default()
        },
    ] {
        assert!(detect(&tiny, &parameters).is_empty());
        assert!(detect(&flat, &parameters).is_empty());
    }
}

#[test]
fn parameters_read_partial_json_and_reject_unknown_fields() {
    let p: DetectionParameters =
        serde_json::from_str(r#"{"threshold": 30, "min_pixels": 4}"#).unwrap();
    assert_eq!(p.threshold, 30);
    assert_eq!(p.min_pixels, 4);
    assert_eq!(p.max_pixels, DetectionParameters::default().max_pixels);
    assert!(serde_json::from_str::<DetectionParameters>(r#"{"treshold": 30}"#).is_err());
    let bad = DetectionParameters {
        min_pixels: 9,
        max_pixels: 4,
        ..p
    };
    let message = bad.validate().unwrap_err().to_string();
    assert!(
        message.starts_with("min_pixels: 9 is larger than max_pixels (4)"),
        "{message}"
    );
    assert!(DetectionParameters::default().validate().is_ok());
}

/// Counts the bytes each thread has allocated and not freed, and their
/// peak, so that a test can measure the scratch of what it calls.
pub(crate) mod counting {
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    pub struct Counting;

    thread_local! {
        static LIVE: Cell<isize> = const { Cell::new(0) };
        static PEAK: Cell<isize> = const { Cell::new(0) };
    }

    fn note(change: isize) {
        // Ignored while the thread's locals are being torn down.
        let _ = LIVE.try_with(|live| {
            let now = live.get().wrapping_add(change);
            live.set(now);
            let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
        });
    }

    // SAFETY: every call is forwarded to the system allocator as it is;
    // the counting touches only const-initialised thread locals, which
    // do not allocate.
    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            let p = unsafe { System.alloc(layout) };
            if !p.is_null() {
                note(layout.size() as isize);
            }
            p
        }
        unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
            let p = unsafe { System.alloc_zeroed(layout) };
            if !p.is_null() {
                note(layout.size() as isize);
            }
            p
        }
        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            unsafe { System.dealloc(ptr, layout) };
            note(-(layout.size() as isize));
        }
        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            let p = unsafe { System.realloc(ptr, layout, new_size) };
            if !p.is_null() {
                note(new_size as isize - layout.size() as isize);
            }
            p
        }
    }

    #[global_allocator]
    static COUNTING: Counting = Counting;

    /// The peak of this thread's allocated bytes while `f` runs, above
    /// what it held before, and `f`'s result.
    pub fn peak_of<T>(f: impl FnOnce() -> T) -> (usize, T) {
        let start = LIVE.with(Cell::get);
        PEAK.with(|peak| peak.set(start));
        let result = f();
        let peak = PEAK.with(Cell::get);
        ((peak - start).max(0) as usize, result)
    }
}

/// The worst case the module documents: bytes of scratch per image
/// pixel, whatever the image holds (targets aside), with an absolute
/// split depth and with the automatic rule (which defers the blobs it
/// splits).
const SCRATCH_BYTES_PER_PIXEL: usize = 21;
const SCRATCH_BYTES_PER_PIXEL_AUTO: usize = 33;

#[test]
fn scratch_is_bounded_per_pixel_on_a_hostile_image() {
    // Every pixel above the threshold, all in one blob. Low noise (less
    // than the split depth) makes it one particle, too large to be a
    // target; strong noise makes a local maximum about every 9 pixels,
    // most of them particles. Both are the worst case for the flood and
    // the split; the second also for the targets, which are output, not
    // scratch, and are counted at their own size (40 bytes each, at most
    // twice that for the vector's spare capacity and the stable sort's
    // buffer).
    let (width, height) = (2048usize, 2048usize);
    let mut rng = rng(5);
    // An absolute depth splits at every maximum the noise makes. The
    // automatic rule scales its depth to the noise and keeps the blob
    // whole, but defers it to the end of the frame and floods it with
    // a region and a cap reserved for every one of its maxima all the
    // same: the worst case of the scratch.
    for (noise, split_depth, per_pixel) in [
        (3u16, Some(4), SCRATCH_BYTES_PER_PIXEL),
        (4095, Some(4), SCRATCH_BYTES_PER_PIXEL),
        (4095, None, SCRATCH_BYTES_PER_PIXEL_AUTO),
    ] {
        let pixels: Vec<u16> = (0..width * height)
            .map(|_| 40000 + rng.random_range(0..=noise))
            .collect();
        let image = GreyImage::from_u16(width as u32, height as u32, pixels).unwrap();
        let parameters = DetectionParameters {
            threshold: 100,
            highpass_radius: 0,
            min_pixels: 1,
            split_depth,
            ..DetectionParameters::default()
        };
        let (peak, targets) = counting::peak_of(|| detect(&image, &parameters));
        if noise == 3 {
            assert!(targets.is_empty(), "{} targets", targets.len());
        } else if split_depth.is_some() {
            assert!(targets.len() > width * height / 20, "{}", targets.len());
        }
        let output = 2 * targets.len() * std::mem::size_of::<Target>();
        eprintln!(
            "noise {noise}, split depth {split_depth:?}: peak {peak} bytes for {} targets",
            targets.len()
        );
        let bound = per_pixel * width * height + output;
        assert!(
            peak <= bound,
            "noise {noise}, {split_depth:?}: peak {peak} bytes, {:.1} a pixel besides {} targets; bound {bound}",
            (peak - output.min(peak)) as f64 / (width * height) as f64,
            targets.len()
        );
    }
}

/// A 40x30 8-bit frame: a dim ramp, with 3x3 spots of peak `peak` at
/// `spots` (centre column, row).
fn frame(spots: &[(usize, usize)], peak: u8) -> GreyImage {
    let (width, height) = (40usize, 30usize);
    let mut pixels: Vec<u8> = (0..width * height).map(|i| (i % width) as u8).collect();
    for &(x, y) in spots {
        for (dx, dy, v) in [(0, 0, peak), (1, 0, peak / 2), (0, 1, peak / 2)] {
            for (sx, sy) in [(1, 1), (-1, 1), (1, -1), (-1, -1)] {
                let (px, py) = ((x as i64 + sx * dx) as usize, (y as i64 + sy * dy) as usize);
                let p = &mut pixels[py * width + px];
                *p = (*p).max(v);
            }
        }
    }
    GreyImage::from_u8(width as u32, height as u32, pixels).unwrap()
}

fn with_background(background: GreyImage) -> Preprocessing {
    Preprocessing {
        background: Some(background),
        mask: None,
    }
}

#[test]
fn a_background_equal_to_the_frame_leaves_nothing() {
    let image = frame(&[(10, 10), (25, 20)], 200);
    let parameters = DetectionParameters::default();
    assert_eq!(detect(&image, &parameters).len(), 2);
    let found = detect_preprocessed(&image, &with_background(image.clone()), &parameters);
    assert_eq!(found, Ok(Vec::new()));
    // Without the filter too: the difference is 0 everywhere.
    let unfiltered = DetectionParameters {
        highpass_radius: 0,
        ..parameters
    };
    let found = detect_preprocessed(&image, &with_background(image.clone()), &unfiltered);
    assert_eq!(found, Ok(Vec::new()));
}

#[test]
fn a_static_bright_object_in_the_background_disappears() {
    // The background holds a bright object at (30, 8); the frame holds it
    // and a particle. Subtracted, only the particle is left, where it is
    // found without the object. (The filter's window, 21 px across,
    // holds the particle and not the object, whose subtraction changes
    // nothing where the particle is.)
    let parameters = DetectionParameters {
        highpass_radius: 10,
        ..DetectionParameters::default()
    };
    let background = frame(&[(30, 8)], 250);
    let image = frame(&[(30, 8), (12, 20)], 250);
    let alone = detect(&frame(&[(12, 20)], 250), &parameters);
    assert_eq!(detect(&image, &parameters).len(), 2);
    let found = detect_preprocessed(&image, &with_background(background), &parameters).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert!((found[0].x - alone[0].x).abs() < 1e-9 && (found[0].y - alone[0].y).abs() < 1e-9);
    assert_eq!((found[0].x.floor(), found[0].y.floor()), (12.0, 20.0));
}

#[test]
fn masked_out_pixels_find_nothing() {
    let image = frame(&[(10, 10), (25, 20)], 200);
    // The mask hides the right half of the frame.
    let mask_image = GreyImage::from_u8(
        40,
        30,
        (0..40 * 30).map(|i| u8::from(i % 40 < 20)).collect(),
    )
    .unwrap();
    let preprocessing = Preprocessing {
        background: None,
        mask: Some(Mask::from_image(&mask_image)),
    };
    let found =
        detect_preprocessed(&image, &preprocessing, &DetectionParameters::default()).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert!(found[0].x < 20.0);
}

#[test]
fn a_background_or_mask_that_does_not_fit_is_an_error() {
    let image = frame(&[(10, 10)], 200);
    let parameters = DetectionParameters::default();
    let small = GreyImage::from_u8(39, 30, vec![0; 39 * 30]).unwrap();
    let error =
        detect_preprocessed(&image, &with_background(small.clone()), &parameters).unwrap_err();
    assert_eq!(
        error.to_string(),
        "the background is 39x30 pixels but the frame is 40x30; \
         use a background recorded with this camera"
    );
    let deep = GreyImage::from_u16(40, 30, vec![0; 40 * 30]).unwrap();
    let error = detect_preprocessed(&image, &with_background(deep), &parameters).unwrap_err();
    assert_eq!(
        error,
        PreprocessError::BackgroundDepth {
            bits: 16,
            expected_bits: 8
        }
    );
    let mask = Preprocessing {
        background: None,
        mask: Some(Mask::from_image(&small)),
    };
    let error = detect_preprocessed(&image, &mask, &parameters).unwrap_err();
    assert!(error
        .to_string()
        .starts_with("the mask is 39x30 pixels but the frame is 40x30"));
}

/// A `side` x `side` 8-bit checkerboard of 1-pixel squares, 255 where
/// `x + y` is even.
fn checkerboard(side: u32) -> GreyImage {
    let pixels = (0..side * side)
        .map(|p| {
            if (p % side + p / side) % 2 == 0 {
                255
            } else {
                0
            }
        })
        .collect();
    GreyImage::from_u8(side, side, pixels).unwrap()
}

#[test]
fn the_target_limit_stops_detection_and_changes_nothing_below_it() {
    let hostile = DetectionParameters {
        threshold: 1,
        min_pixels: 1,
        min_snr: 0,
        ..DetectionParameters::default()
    };
    // Noise at a low threshold: many blobs with several maxima, which
    // the automatic rule defers to the end of the frame (and splits
    // again when the frame is structured), and with a split depth.
    let noisy = DetectionParameters {
        threshold: 8,
        min_snr: 0,
        ..DetectionParameters::default()
    };
    let deep = DetectionParameters {
        split_depth: Some(3),
        ..noisy.clone()
    };
    let [noise, _] = noise_frame(160, 120, 100.0, 20.0, 7);
    for (image, parameters) in [
        (checkerboard(64), &hostile),
        (noise.clone(), &noisy),
        (noise, &deep),
    ] {
        let all = detect(&image, parameters);
        let n = all.len();
        assert!(n > 100, "{n}");
        for limit in [n, n + 1, usize::MAX] {
            let within = detect_within(&image, &NO_PREPROCESSING, parameters, limit);
            assert_eq!(within.as_ref(), Ok(&all), "limit {limit}");
        }
        for limit in [n - 1, n / 2, 1, 0] {
            let error = detect_within(&image, &NO_PREPROCESSING, parameters, limit).unwrap_err();
            assert_eq!(error, DetectError::TooManyTargets(TooManyTargets { limit }));
        }
    }
}

#[test]
fn a_hostile_frame_stops_at_the_limit_without_its_targets() {
    // Every other pixel a target: 2 million of them, 80 MB of targets
    // (and as much again while their vector grows) without a limit.
    let image = checkerboard(2048);
    let parameters = DetectionParameters {
        threshold: 1,
        min_pixels: 1,
        min_snr: 0,
        ..DetectionParameters::default()
    };
    let pixels = 2048 * 2048;
    let (peak, found) =
        counting::peak_of(|| detect_within(&image, &NO_PREPROCESSING, &parameters, 10_000));
    assert_eq!(
        found,
        Err(DetectError::TooManyTargets(TooManyTargets {
            limit: 10_000
        }))
    );
    // The levels (2 bytes a pixel) and the rows' scratch before the
    // stop; the targets found, 10,001 of them, are 400 KB.
    assert!(peak < 3 * pixels, "{peak} bytes");
    let (peak, all) = counting::peak_of(|| detect(&image, &parameters));
    assert!(all.len() > 2_000_000 - 2 * 2048, "{}", all.len());
    assert!(peak > 20 * pixels, "{peak} bytes");
}

#[test]
fn cameras_are_detected_with_their_own_parameters() {
    let rows: &[&[u8]] = &[&[0, 0, 0], &[0, 40, 0], &[0, 0, 0]];
    let frame = image(3, rows);
    let low = unfiltered();
    let high = DetectionParameters {
        threshold: 50,
        ..unfiltered()
    };
    let found = detect_cameras(&[(&frame, &low), (&frame, &high)]);
    assert_eq!(found.iter().map(Vec::len).collect::<Vec<_>>(), vec![1, 0]);
}

#[test]
fn blob_keys_sort_by_radix_as_by_comparison() {
    // Blobs' keys as the flood leaves them: distinct pixel indices in a
    // band of rows, with levels over a narrow and over the full range, at
    // sizes below, within and above the radix sort's range (its passes
    // skip the bytes in which every key agrees, so both kinds of spread
    // matter).
    let mut rng = rng(17);
    let mut scratch = Vec::new();
    for (len, levels, spread) in [
        (100usize, 65535u16, 1u64 << 20),
        (256, 40, 5_000),
        (3_000, 2_570, 128_000),
        (3_000, 65535, 1 << 31),
        (50_000, 1, 60_000),
        (split::RADIX_UP_TO + 1, 300, 1 << 24),
    ] {
        let start = rng.random_range(0..(1u64 << 32) - spread);
        let keys: Vec<u64> = if spread as usize >= 4 * len {
            let mut picked = std::collections::HashSet::new();
            while picked.len() < len {
                picked.insert(rng.random_range(0..spread));
            }
            picked.into_iter().collect::<Vec<u64>>()
        } else {
            (0..len as u64).collect()
        }
        .into_iter()
        .map(|i| {
            let level = u16::MAX - rng.random_range(0..=levels);
            key(level, (start + i) as usize)
        })
        .collect();
        let mut expected = keys.clone();
        expected.sort_unstable();
        let mut sorted = keys;
        split::sort_keys(&mut sorted, &mut scratch, usize::MAX);
        assert_eq!(sorted, expected, "{len} keys");
    }
    // The scratch never grows past the radix sort's largest blob.
    assert!(scratch.capacity() <= split::RADIX_UP_TO);
}

/// `Rows::position` is the division it replaces, for every width that
/// matters and at the indices where rounding would show: each side of row
/// starts, up to the largest index a key holds.
#[test]
fn rows_split_indices_as_division_does() {
    let mut random = rng(17);
    let mut widths = vec![1, 2, 3, 5, 7, 640, 1023, 1024, 1279, 1280, 1281, 4093, 8192];
    widths.extend([
        65_535,
        65_536,
        100_003,
        (1 << 31) - 1,
        1 << 31,
        u32::MAX as usize,
    ]);
    widths.extend((0..200).map(|_| random.random_range(1..1usize << 32)));
    for width in widths {
        let rows = Rows::new(width);
        let last = (1usize << 32) - 1;
        let check = |p: usize| {
            if p <= last {
                assert_eq!(
                    rows.position(p),
                    (p % width, p / width),
                    "width {width}, index {p}"
                );
            }
        };
        for y in [
            0,
            1,
            2,
            last / width / 2,
            last / width - 1,
            last / width,
            last / width + 1,
        ] {
            let start = y.saturating_mul(width);
            for p in [start.wrapping_sub(1), start, start + 1, start + width / 2] {
                check(p);
            }
        }
        check(last);
        for _ in 0..1000 {
            check(random.random_range(0..=last));
        }
    }
}
