//! Invariances of detection (design paper, section 6.1), as properties over
//! random particle images.
//!
//! - Translating an image by whole pixels moves every centroid by exactly
//!   that: the filter, the segmentation and the splitting look only at grey
//!   values and relative positions (equal grey values are ordered in raster
//!   order, which translation keeps). "Exactly" is up to the rounding of one
//!   floating-point division and addition, 1e-9 px.
//! - A 16-bit image and its 8-bit copy (the 16-bit image holding the 8-bit
//!   grey values times 257, so scaling down loses nothing) give the same
//!   targets to 0.01 px, with threshold and split depth scaled by 257 too.
//!   The detector keeps filtered values of 8-bit images in 16-bit grey
//!   levels (times 257), so both images have the same levels and make the
//!   same decisions; the centroids agree to rounding (checked to 1e-9 px,
//!   far inside 0.01 px). Where a real 16-bit frame is rounded to 8 bits,
//!   the rounding (1/sqrt(12) grey level per pixel) moves centroids by
//!   about 0.005 px for a faint particle, and a pixel whose two brighter
//!   neighbours differ by less than a grey level may change particle; the
//!   exact copy isolates the detector from that loss of information.
//!
//! - Both hold for either sub-pixel estimator ([`Centroid`]): the Gaussian
//!   fit reads the same grey values at the same relative positions.
//! - The Gaussian estimator changes positions only: the same targets (pixel
//!   counts, extents, sums of grey) as the weighted centroid, each finite
//!   and inside its pixels' bounding box.
//!
//! The translated images keep the content at least `MARGIN` pixels from the
//! border, so that no high-pass window is clipped differently and the noise
//! level's sample sees the same empty background.

use nalgebra::Point2;
use proptest::prelude::*;
use ptv::photogrammetry::detect::detect_with_pixels;
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{detect, Centroid, DetectionParameters, GreyImage, GreyPixels, Target};

/// The side of the rendered patch.
const PATCH: u32 = 48;
/// Free border around the patch: at least the default high-pass radius,
/// 25, plus the largest shift, 8, plus 2; and so wide that the pixels within
/// a filter radius of the patch, whose filtered values are negative, are
/// fewer than a quarter of the image (98² of 248²), so that the noise level
/// (estimated from the lower half of a sample on fixed rows of the image,
/// wherever the patch lies) is that of the empty background, 0, for every
/// shift.
const MARGIN: u32 = 100;

/// A patch of particles (possibly overlapping) with noise, on a zero
/// background so that its edges are not a step.
fn patch(particles: &[(f64, f64)], diameter: f64, seed: u64) -> Vec<u8> {
    let spec = RenderSpec {
        background: 0.0,
        gradient: nalgebra::Vector2::zeros(),
        ..RenderSpec::eight_bit(diameter)
    };
    let positions: Vec<Point2<f64>> = particles.iter().map(|&(x, y)| Point2::new(x, y)).collect();
    let image = simulate::render(PATCH, PATCH, &positions, &spec, &mut simulate::rng(seed));
    match image.pixels() {
        GreyPixels::Eight(p) => p.clone(),
        GreyPixels::Sixteen(_) => unreachable!("an 8-bit render"),
    }
}

/// The patch placed with its corner at (`x0`, `y0`) in a zero image.
fn placed(patch: &[u8], x0: u32, y0: u32) -> GreyImage {
    let side = PATCH + 2 * MARGIN;
    let mut pixels = vec![0u8; (side * side) as usize];
    for y in 0..PATCH {
        for x in 0..PATCH {
            pixels[((y0 + y) * side + x0 + x) as usize] = patch[(y * PATCH + x) as usize];
        }
    }
    GreyImage::from_u8(side, side, pixels).expect("the samples fill the image")
}

fn particles() -> impl Strategy<Value = Vec<(f64, f64)>> {
    prop::collection::vec((4.0..44.0f64, 4.0..44.0f64), 1..12)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn translation_moves_every_centroid_by_exactly_the_shift(
        particles in particles(),
        diameter in 1.5..4.0f64,
        seed in any::<u64>(),
        dx in -8i64..=8,
        dy in -8i64..=8,
        gaussian in any::<bool>(),
    ) {
        let patch = patch(&particles, diameter, seed);
        let parameters = DetectionParameters {
            centroid: if gaussian { Centroid::Gaussian } else { Centroid::Weighted },
            ..DetectionParameters::default()
        };
        let before = detect(&placed(&patch, MARGIN, MARGIN), &parameters);
        let moved = placed(&patch, (i64::from(MARGIN) + dx) as u32, (i64::from(MARGIN) + dy) as u32);
        let after = detect(&moved, &parameters);
        // Particle brightness is random: a lone faint particle may stay
        // below the threshold, which leaves nothing to compare.
        prop_assume!(!before.is_empty());
        prop_assert_eq!(before.len(), after.len());
        for (a, b) in before.iter().zip(&after) {
            prop_assert!((b.x - a.x - dx as f64).abs() < 1e-9, "{:?} -> {:?}", a, b);
            prop_assert!((b.y - a.y - dy as f64).abs() < 1e-9, "{:?} -> {:?}", a, b);
            prop_assert_eq!((a.n, a.nx, a.ny, a.sumg), (b.n, b.nx, b.ny, b.sumg));
        }
    }

    #[test]
    fn sixteen_bit_and_eight_bit_copies_give_the_same_targets(
        particles in particles(),
        diameter in 1.5..4.0f64,
        seed in any::<u64>(),
        gaussian in any::<bool>(),
    ) {
        let eight = placed(&patch(&particles, diameter, seed), MARGIN, MARGIN);
        let GreyPixels::Eight(samples) = eight.pixels() else { unreachable!("8-bit") };
        let sixteen = GreyImage::from_u16(
            eight.width(),
            eight.height(),
            samples.iter().map(|&g| u16::from(g) * 257).collect(),
        )
        .expect("same size");
        let p8 = DetectionParameters {
            centroid: if gaussian { Centroid::Gaussian } else { Centroid::Weighted },
            ..DetectionParameters::default()
        };
        let p16 = DetectionParameters {
            threshold: p8.threshold * 257,
            split_depth: p8.split_depth.map(|d| d * 257),
            min_sumg: p8.min_sumg * 257,
            ..p8.clone()
        };
        let a: Vec<Target> = detect(&eight, &p8);
        let b: Vec<Target> = detect(&sixteen, &p16);
        // As above: a frame of only faint particles has nothing to compare.
        prop_assume!(!a.is_empty());
        prop_assert_eq!(a.len(), b.len());
        for (a, b) in a.iter().zip(&b) {
            prop_assert!((a.x - b.x).abs() < 1e-9 && (a.y - b.y).abs() < 1e-9, "{:?} vs {:?}", a, b);
            prop_assert_eq!((a.n, a.nx, a.ny), (b.n, b.nx, b.ny));
            // sumg scales too, up to the rounding of the 8-bit sum.
            let scaled = a.sumg as f64 * 257.0;
            prop_assert!((b.sumg as f64 - scaled).abs() <= 128.5, "{} vs {}", a.sumg, b.sumg);
        }
    }

    #[test]
    fn the_gaussian_estimator_moves_targets_within_their_pixels(
        particles in particles(),
        diameter in 1.5..4.0f64,
        seed in any::<u64>(),
    ) {
        let image = placed(&patch(&particles, diameter, seed), MARGIN, MARGIN);
        let weighted = detect_with_pixels(&image, &DetectionParameters::default());
        let gaussian = detect_with_pixels(
            &image,
            &DetectionParameters {
                centroid: Centroid::Gaussian,
                ..DetectionParameters::default()
            },
        );
        prop_assert_eq!(weighted.len(), gaussian.len());
        for g in &gaussian {
            // The same pixels as one weighted target (the order may differ:
            // targets are sorted by position).
            let w = weighted.iter().find(|w| w.pixels == g.pixels);
            prop_assert!(w.is_some(), "{:?}", g.target);
            let (w, t) = (w.unwrap().target, g.target);
            prop_assert_eq!((w.n, w.nx, w.ny, w.sumg), (t.n, t.nx, t.ny, t.sumg));
            let (x0, x1) = g.pixels.iter().fold((u32::MAX, 0), |(a, b), p| (a.min(p.0), b.max(p.0)));
            let (y0, y1) = g.pixels.iter().fold((u32::MAX, 0), |(a, b), p| (a.min(p.1), b.max(p.1)));
            prop_assert!(t.x.is_finite() && t.y.is_finite(), "{:?}", t);
            prop_assert!(t.x >= f64::from(x0) && t.x <= f64::from(x1) + 1.0, "{:?}", t);
            prop_assert!(t.y >= f64::from(y0) && t.y <= f64::from(y1) + 1.0, "{:?}", t);
        }
    }
}
