//! The renderer's structured backgrounds (glare streaks, bright static
//! objects, vignetting, hot pixels, illumination drift), and detection on
//! them against the renderer's truth (issue 13).
//!
//! Scoring as in `detect_accuracy.rs` (`tests/common/target_match.rs`):
//! one-to-one matching within 1 px, nearest first; particles and targets
//! within 5 px of the border are not scored. Background subtraction is done
//! here by hand until the detector has its own: the per-pixel median of the
//! sequence's frames by `BackgroundBuilder` (the frame itself included, as
//! a recording's median is), subtracted from each frame, saturating at 0;
//! then the default detection parameters. Run with
//! `cargo test --test photogrammetry structured_background -- --nocapture`
//! to see the table.

use nalgebra::{Point2, Vector2};
use ptv::photogrammetry::simulate::{self, BackgroundField, RenderSpec, StructuredBackground};
use ptv::photogrammetry::{
    detect, detect_preprocessed, BackgroundBuilder, BackgroundMode, BitDepth, DetectionParameters,
    GreyImage, GreyPixels, Preprocessing,
};
use rand::Rng;

use crate::common::target_match::{score_truth, TruthScore};

const WIDTH: u32 = 640;
const HEIGHT: u32 = 512;
/// Frames per sequence, for the median background.
const FRAMES: usize = 5;

fn eight(image: &GreyImage) -> &[u8] {
    match image.pixels() {
        GreyPixels::Eight(p) => p,
        GreyPixels::Sixteen(_) => panic!("8-bit frames expected"),
    }
}

/// A noise-free spec: what a frame's expected values are.
fn noise_free() -> RenderSpec {
    RenderSpec {
        electrons_per_grey: 0.0,
        read_noise: 0.0,
        ..RenderSpec::eight_bit(2.5)
    }
}

fn uniform(count: usize, rng: &mut impl Rng) -> Vec<Point2<f64>> {
    (0..count)
        .map(|_| {
            Point2::new(
                rng.random_range(0.0..f64::from(WIDTH)),
                rng.random_range(0.0..f64::from(HEIGHT)),
            )
        })
        .collect()
}

#[test]
fn no_background_renders_exactly_what_render_does() {
    let field = StructuredBackground::none().field(WIDTH, HEIGHT);
    let positions = uniform(500, &mut simulate::rng(1));
    let spec = RenderSpec::eight_bit(2.5);
    let plain = simulate::render(WIDTH, HEIGHT, &positions, &spec, &mut simulate::rng(2));
    let scene = simulate::render_scene(&field, 17, &positions, &spec, &mut simulate::rng(2));
    assert_eq!(plain, scene);
}

#[test]
fn static_structure_repeats_from_frame_to_frame() {
    // Without drift and noise, two frames with different particles agree
    // wherever neither has a particle; with drift, they differ by the
    // gain alone; hot pixels sit at 255 in every (noisy) frame.
    let background = StructuredBackground {
        drift: 0.0,
        ..StructuredBackground::lab(5)
    };
    let field = background.field(WIDTH, HEIGHT);
    let empty = |frame: u64, seed: u64| {
        simulate::render_scene(&field, frame, &[], &noise_free(), &mut simulate::rng(seed))
    };
    assert_eq!(empty(0, 1), empty(9, 2));
    let drifting = StructuredBackground::lab(5);
    let field_drift = drifting.field(WIDTH, HEIGHT);
    assert_eq!(
        field_drift.additive(),
        field.additive(),
        "the drift is no structure"
    );
    let (g0, g50) = (drifting.gain(0), drifting.gain(50));
    assert!(
        (g50 - g0 - drifting.drift).abs() < 1e-12,
        "a quarter period"
    );
    let noisy = |frame: u64, seed: u64| {
        let positions = uniform(1000, &mut simulate::rng(seed));
        simulate::render_scene(
            &field_drift,
            frame,
            &positions,
            &RenderSpec::eight_bit(2.5),
            &mut simulate::rng(seed),
        )
    };
    for (frame, seed) in [(0, 3), (50, 4)] {
        let image = noisy(frame, seed);
        assert_eq!(field_drift.hot_pixels().len(), drifting.hot_pixels);
        for &i in field_drift.hot_pixels() {
            assert_eq!(eight(&image)[i], 255, "hot pixel {i} in frame {frame}");
        }
    }
}

#[test]
fn bright_objects_cover_a_quarter_and_outshine_the_particles() {
    let background = StructuredBackground::lab(7);
    let field: BackgroundField = background.field(WIDTH, HEIGHT);
    assert!(
        (0.25..0.35).contains(&field.bright_share()),
        "{}",
        field.bright_share()
    );
    // The brightest pixel any particle of the spec can make, on a zero
    // background: the largest peak centred on a pixel.
    let spec = RenderSpec {
        background: 0.0,
        gradient: Vector2::zeros(),
        peak_min: RenderSpec::eight_bit(2.5).peak_max,
        ..noise_free()
    };
    let particle = simulate::render(9, 9, &[Point2::new(4.5, 4.5)], &spec, &mut simulate::rng(0));
    let brightest = eight(&particle).iter().copied().max().unwrap();
    assert!(
        background.bright_level > f64::from(brightest),
        "objects {} vs particle peak {brightest}",
        background.bright_level
    );
}

#[test]
fn glare_streaks_have_ripples_that_fragment_them() {
    // Streaks alone (no objects, no particles, no hot pixels): every ripple
    // is a maximum, so the default split depth of 4 grey levels cuts each
    // streak into several targets, and OpenPTV's discont of 100 does not.
    let background = StructuredBackground {
        bright_share: 0.0,
        hot_pixels: 0,
        vignetting: 0.0,
        ..StructuredBackground::lab(11)
    };
    let field = background.field(WIDTH, HEIGHT);
    let image = simulate::render_scene(
        &field,
        0,
        &[],
        &RenderSpec::eight_bit(2.5),
        &mut simulate::rng(3),
    );
    let fine = detect(&image, &DetectionParameters::default()).len();
    let coarse = detect(
        &image,
        &DetectionParameters {
            split_depth: Some(100),
            ..DetectionParameters::default()
        },
    )
    .len();
    println!(
        "{} streaks: {fine} targets at split depth 4, {coarse} at 100",
        background.glare_streaks
    );
    assert!(fine > 3 * background.glare_streaks, "{fine}");
    assert!(coarse < fine / 2, "{coarse} vs {fine}");
}

/// The background of `frames` by the project's own builder (`ptv
/// background`'s core): the exact per-pixel median of the frames.
fn median(frames: &[GreyImage]) -> GreyImage {
    let (w, h) = (frames[0].width(), frames[0].height());
    let mut builder = BackgroundBuilder::new(BackgroundMode::Median, w, h, BitDepth::Eight);
    for frame in frames {
        builder.add(frame).expect("frames of one size");
    }
    builder.finish().expect("frames were added")
}

/// Detection over a sequence of `FRAMES` frames at `ppp` particles per
/// pixel in front of `field`, without and with median subtraction.
fn score_sequence(field: &BackgroundField, ppp: f64, seed: u64) -> [TruthScore; 2] {
    let count = (ppp * f64::from(WIDTH * HEIGHT)) as usize;
    let mut rng = simulate::rng(seed);
    let spec = RenderSpec::eight_bit(2.5);
    let (frames, truths): (Vec<GreyImage>, Vec<Vec<(f64, f64)>>) = (0..FRAMES)
        .map(|frame| {
            let positions = uniform(count, &mut rng);
            let image = simulate::render_scene(field, frame as u64, &positions, &spec, &mut rng);
            (image, positions.iter().map(|p| (p.x, p.y)).collect())
        })
        .unzip();
    let background = median(&frames);
    [false, true].map(|subtracted| {
        let preprocessing = Preprocessing {
            background: subtracted.then(|| background.clone()),
            mask: None,
        };
        let mut total = TruthScore::default();
        let mut sum2 = 0.0;
        for (frame, truth) in frames.iter().zip(&truths) {
            let targets =
                detect_preprocessed(frame, &preprocessing, &DetectionParameters::default())
                    .expect("the background is the frames' size and depth");
            let s = score_truth(truth, &targets, 1.0, 5.0, WIDTH, HEIGHT);
            total.particles += s.particles;
            total.found += s.found;
            total.targets += s.targets;
            total.false_targets += s.false_targets;
            sum2 += s.rms * s.rms * s.found as f64;
        }
        total.rms = (sum2 / total.found.max(1) as f64).sqrt();
        total
    })
}

#[test]
fn median_subtraction_recovers_particles_in_front_of_bright_structure() {
    let field = StructuredBackground::lab(13).field(WIDTH, HEIGHT);
    println!("ppp     subtraction  recall  false   rms_px");
    for (k, ppp) in [0.001, 0.005, 0.01].into_iter().enumerate() {
        let [plain, subtracted] = score_sequence(&field, ppp, 100 + k as u64);
        for (name, s) in [("none", plain), ("median", subtracted)] {
            println!(
                "{ppp:<7} {name:<12} {:.4}  {:5.2}%  {:.3}",
                s.recall(),
                100.0 * s.false_share(),
                s.rms
            );
        }
        // Without subtraction the streaks' ripples and the objects' edges
        // make false targets; the median removes them.
        assert!(plain.false_share() > 0.05, "{ppp}: {plain:?}");
        assert!(subtracted.false_share() < 0.02, "{ppp}: {subtracted:?}");
        // Recall: what overlaps allow. Two particles closer than about one
        // image diameter (2.5 px) have a single maximum and give one target
        // (detect_accuracy.rs), so about half of the particles with a
        // neighbour that close, ppp·π·2.5²/2 of all, are lost; one more
        // percent for the faintest particles in the vignetted corners.
        let floor = 1.0 - ppp * std::f64::consts::PI * 2.5 * 2.5 / 2.0 - 0.01;
        assert!(
            subtracted.recall() >= floor,
            "{ppp}: {subtracted:?} < {floor}"
        );
        if ppp == 0.005 {
            // Issue 13's goal.
            assert!(subtracted.recall() >= 0.95, "{subtracted:?}");
        }
        if ppp == 0.001 {
            // Isolated particles: detect_accuracy.rs finds them to 0.05 px
            // RMS on the plain background, where the noise is
            // sqrt(20/50 + 1) = 1.18 grey levels (photon noise at 50
            // electrons per grey level, read noise 1). Here a quarter of the
            // image sits under the objects, at sqrt(190/50 + 1) = 2.2 grey
            // levels: RMS noise x1.27 over the image; vignetting dims the
            // particles by 15% on average (x1.18); the median of 5 frames
            // adds its own noise, about 1.25/sqrt(5) of a frame's (x1.15).
            // 0.05 x 1.27 x 1.18 x 1.15 = 0.086 px: allow 0.1.
            assert!(subtracted.rms <= 0.1, "{subtracted:?}");
        }
    }
}
