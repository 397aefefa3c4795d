//! Sub-pixel particle centres: which estimator detection uses
//! ([`Centroid`]), and the Gaussian one.
//!
//! The design paper (section 6.1) takes the grey value weighted centre of
//! gravity of a particle's pixels; that is [`Centroid::Weighted`], the
//! default, computed in [`super::detect`](mod@super::detect) (step 4) as OpenPTV's `targ_rec`
//! does. [`Centroid::Gaussian`] fits a Gaussian instead, by the 3-point
//! estimator per axis that PIV uses for correlation peaks (Willert &
//! Gharib 1991, Exp. Fluids 10) and that Ouellette, Xu & Bodenschatz
//! (2006, Exp. Fluids 40, "A quantitative study of three-dimensional
//! Lagrangian particle tracking algorithms", section 3) found the most
//! accurate of the common PTV estimators for small particle images.
//!
//! # The estimator
//!
//! A particle image is close to `g(x) = A exp(-(x - x0)² / 2σ²)`, so
//! `ln g` is a parabola in `x` whose vertex is `x0`. Through the particle's
//! brightest pixel `x` and its two neighbours along one axis:
//!
//! ```text
//! x0 = x + (ln g(x-1) - ln g(x+1)) / (2 (ln g(x-1) - 2 ln g(x) + ln g(x+1)))
//! ```
//!
//! ([`log_parabola_offset`]), and the same along `y` (a 2D Gaussian with
//! axes along the rows and columns separates into the two). On a Gaussian
//! sampled at the pixel centres it is exact. A sensor records the Gaussian
//! averaged over each pixel's area, whose logarithm is not exactly a
//! parabola: the error this leaves is at most 0.0053, 0.0018, 0.0007 and
//! 0.0002 px for images of 2, 2.5, 3 and 4 px (e⁻² diameter `4σ`), far
//! below the noise's share (the unit tests check it against the exact
//! pixel integrals). Unlike the weighted centroid it does not depend on
//! which pixels pass the threshold, nor on the threshold itself: the
//! weighted centroid's weights `g - threshold` truncate the Gaussian's
//! tails, which pulls it towards the pixel centre for small images.
//!
//! # The samples
//!
//! The fit needs the three samples relative to the background (a constant
//! added to `g` bends `ln g`), so it uses the high-pass filtered values
//! (the image less the mean of the window around each pixel, section 6.1),
//! not the weights `g - threshold` of the weighted centroid (which would
//! subtract the threshold as if it were background). All three are taken
//! relative to one background, the peak pixel's window mean: a neighbour's
//! value is the peak's filtered value less the difference of the two raw
//! samples (less the subtracted background image, if any). The filtered
//! value of a neighbour would use its own window, a few pixels off, which
//! differs by a fraction of a grey level on a smooth background; one
//! background for the three keeps them consistent, and gives a value also
//! for a neighbour below the threshold, which for 2 px images is usually
//! one of the two (a pixel 1.5 σ-widths from the centre holds about a
//! tenth of the peak, often less than the threshold): without it the
//! estimator would fall back on most of them.
//!
//! # When it applies, and the fallback
//!
//! Per axis, the estimator is used when both neighbours of the peak pixel
//! along that axis are usable and the fit is well formed; otherwise that
//! axis keeps the weighted centroid. A neighbour is not usable when it is
//! outside the image, masked out, or belongs to another particle of the
//! same blob (a blob split at a grey value minimum: that pixel holds
//! mostly the other particle's light, so the fit would be pulled towards
//! it; the weighted centroid, which stops at the saddle, is the better
//! estimate there). The fit is not well formed when a sample is not
//! positive (noise below the background: no logarithm), when the
//! curvature is not negative (a flat or dented top, e.g. a saturated
//! particle), or when the vertex lies more than half a pixel from the
//! peak pixel (the peak pixel would then not be the brightest). A
//! saturated particle (several pixels at the largest grey value) thus
//! falls back on the weighted centroid, which is the right estimator for
//! a flat top.
//!
//! # Which is more accurate
//!
//! Measured, not assumed. On isolated rendered particles (8-bit, peaks
//! 80..200 grey levels, photon and read noise, default parameters;
//! `tests/photogrammetry/detect_accuracy.rs`,
//! `gaussian_and_weighted_centroids_on_isolated_particles`), the 2D RMS
//! error in px, each within 7% of what propagating the renderer's noise
//! through the estimator predicts:
//!
//! | image diameter | weighted | Gaussian |
//! | ---: | ---: | ---: |
//! | 2 px | 0.030 | 0.027 |
//! | 2.5 px | 0.035 | 0.022 |
//! | 3 px | 0.024 | 0.023 |
//! | 4 px | 0.020 | 0.031 |
//!
//! (With the high-pass radius of 25, the default since the detector's
//! defaults were measured on a real recording; at 10 they differed by at
//! most 0.001 px.)
//!
//! The fit reads three pixels per axis where the weighted centroid reads
//! all of the particle's: it wins while the threshold truncates a large
//! share of a small image (2..2.5 px), and loses once the image has many
//! pixels above it (4 px), where its three samples carry less of the
//! light. In crowded frames it wins at every density, as it reads only the
//! particle's core, which a neighbour's tail hardly reaches
//! (`examples/detection_report.rs`, 2.5 px particles in front of a
//! structured background, background subtracted: 0.080 against 0.076 px
//! at 0.001 particles per pixel, 0.141 against 0.104 at 0.005, 0.188
//! against 0.133 at 0.01).
//!
//! The samples' background matters, and was measured with the same test
//! (2 px images): the weights `g - threshold` instead of the filtered
//! values make the fit 2.5 times worse (0.063 px); leaving out neighbours
//! below the threshold (falling back on 48% of the axes) gives 0.027 px
//! instead of 0.026 (0.024 instead of 0.021 at 2.5 px, 6% of the axes);
//! each neighbour's own window mean instead of the peak's changes nothing
//! measurable. With the neighbours below the threshold, the fallback
//! applies on 0.2% of the axes at 2 px and on none from 2.5 px.
//!
//! Cost: one more pass over each particle's pixels for its peak, four
//! samples and four logarithms; about 0.2 ms on a 1280x1024 8-bit frame of
//! 2000 particles of 2.5 px that takes 3.1..3.3 ms (fastest of 400
//! alternating runs on one core of a shared machine), some 100 ns a
//! target. `benches/detect.rs` has both ("8-bit, gaussian centroid"
//! against "8-bit").

use serde::{Deserialize, Serialize};

/// Which sub-pixel estimator gives a target's position.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Centroid {
    /// The grey value weighted centre of gravity of the particle's pixels,
    /// weights `g - threshold` (OpenPTV's; the design paper's section 6.1).
    #[default]
    Weighted,
    /// A Gaussian through the brightest pixel and its neighbours, per axis
    /// (the 3-point log-parabola fit); the weighted centroid on an axis
    /// where it does not apply (see the module documentation).
    Gaussian,
}

impl Centroid {
    /// Its name, as in JSON and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Centroid::Weighted => "weighted",
            Centroid::Gaussian => "gaussian",
        }
    }
}

/// Where, relative to the middle sample, the vertex of the parabola through
/// the logarithms of three equally spaced samples lies (in sample spacings,
/// positive towards `after`): the centre of the Gaussian through them.
/// `None` when the fit is not well formed: a sample is not a positive
/// finite number, the curvature is not negative, or the vertex is more than
/// half a spacing from the middle sample. Never NaN.
pub fn log_parabola_offset(before: f64, centre: f64, after: f64) -> Option<f64> {
    let positive = |v: f64| v > 0.0 && v.is_finite();
    if !(positive(before) && positive(centre) && positive(after)) {
        return None;
    }
    // ln g(x-1) - 2 ln g(x) + ln g(x+1) and ln g(x-1) - ln g(x+1), by two
    // logarithms rather than three. The ratios of positive finite numbers
    // are positive (or overflow to infinity, or underflow to 0): their
    // logarithms are never NaN, though they may be infinite.
    let curvature = ((before / centre) * (after / centre)).ln();
    if curvature >= 0.0 || curvature.is_nan() {
        return None;
    }
    let offset = (before / after).ln() / (2.0 * curvature);
    // Also false for NaN.
    if offset.abs() <= 0.5 {
        Some(offset)
    } else {
        None
    }
}

/// The samples around a particle's brightest pixel that the Gaussian
/// estimator reads, relative to the background; `None` for a neighbour
/// that is not usable (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeakSamples {
    /// The brightest pixel (column, row).
    pub peak: (usize, usize),
    /// Its value.
    pub centre: f64,
    /// The pixels left and right of it.
    pub x: [Option<f64>; 2],
    /// The pixels above and below it.
    pub y: [Option<f64>; 2],
}

/// The particle's centre (pixel centres at `i + 0.5`, the camera model's
/// convention) by the 3-point Gaussian fit per axis, with `weighted` (the
/// weighted centroid) on an axis where the fit does not apply.
pub fn gaussian_centre(samples: &PeakSamples, weighted: (f64, f64)) -> (f64, f64) {
    let axis = |[before, after]: [Option<f64>; 2], pixel: usize, fallback: f64| {
        before
            .zip(after)
            .and_then(|(before, after)| log_parabola_offset(before, samples.centre, after))
            .map_or(fallback, |offset| pixel as f64 + 0.5 + offset)
    };
    (
        axis(samples.x, samples.peak.0, weighted.0),
        axis(samples.y, samples.peak.1, weighted.1),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::detect::detect;
    use crate::photogrammetry::simulate::rng;
    use crate::photogrammetry::{DetectionParameters, GreyImage};
    use rand::Rng;

    fn gaussian(u: f64, centre: f64, sigma: f64) -> f64 {
        (-(u - centre).powi(2) / (2.0 * sigma * sigma)).exp()
    }

    /// The mean of the unit Gaussian over pixel `i` (from `i` to `i + 1`).
    fn integrated(i: i64, centre: f64, sigma: f64) -> f64 {
        let erf = |x: f64| libm_erf(x / (sigma * std::f64::consts::SQRT_2));
        (erf(i as f64 + 1.0 - centre) - erf(i as f64 - centre)) / 2.0
    }

    /// The error function to double precision (series and continued
    /// fraction), to test against integrals better than the renderer's
    /// 1.5e-7.
    fn libm_erf(x: f64) -> f64 {
        let a = x.abs();
        let value = if a < 2.5 {
            // Maclaurin series: erf x = 2/sqrt(pi) sum (-1)^n x^(2n+1) / (n! (2n+1)).
            let (mut term, mut sum, mut n) = (a, a, 0.0);
            while term.abs() > 1e-17 * sum.abs() {
                n += 1.0;
                term *= -a * a / n;
                sum += term / (2.0 * n + 1.0);
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // Continued fraction for erfc, by the modified Lentz method.
            let (tiny, mut f) = (1e-300, a);
            let (mut c, mut d) = (a, 0.0);
            for k in 1..200 {
                let an = f64::from(k) / 2.0;
                d = a + an * d;
                d = if d.abs() < tiny { tiny } else { d };
                c = a + an / c;
                c = if c.abs() < tiny { tiny } else { c };
                d = 1.0 / d;
                let delta = c * d;
                f *= delta;
                if (delta - 1.0).abs() < 1e-16 {
                    break;
                }
            }
            1.0 - (-a * a).exp() / (f * std::f64::consts::PI.sqrt())
        };
        value.copysign(x)
    }

    #[test]
    fn erf_is_accurate() {
        for (x, expected) in [
            (0.1, 0.112_462_916_018_284_9),
            (1.0, 0.842_700_792_949_714_9),
            (2.0, 0.995_322_265_018_952_7),
            (3.0, 0.999_977_909_503_001_4),
        ] {
            assert!((libm_erf(x) - expected).abs() < 1e-14, "erf({x})");
            assert!((libm_erf(-x) + expected).abs() < 1e-14, "erf(-{x})");
        }
    }

    #[test]
    fn a_sampled_gaussian_is_recovered_exactly() {
        let mut random = rng(1);
        for _ in 0..1000 {
            let sigma = random.random_range(0.3..3.0);
            let peak = random.random_range(1.0..60000.0);
            // Any centre whose nearest sample is 0.
            let centre = random.random_range(-0.5..0.5);
            let [a, b, c] = [-1.0, 0.0, 1.0].map(|u| peak * gaussian(u, centre, sigma));
            let offset = log_parabola_offset(a, b, c).expect("a Gaussian's fit");
            // Only rounding: a few ulps of the logarithms, over the curvature.
            assert!((offset - centre).abs() < 1e-9, "{sigma} {centre} {offset}");
        }
    }

    #[test]
    fn a_pixel_integrated_gaussian_is_recovered_to_its_documented_bias() {
        // The module documentation's bounds, for images of 2, 2.5, 3, 4 px
        // (4 sigma), with a margin of 1e-4 px for the sampling of centres.
        for (diameter, bound) in [(2.0, 0.0054), (2.5, 0.0019), (3.0, 0.0008), (4.0, 0.0003)] {
            let sigma: f64 = diameter / 4.0;
            let mut worst = 0.0f64;
            for step in 0..=200 {
                // The centre anywhere in pixel 0 (from 0 to 1).
                let centre = f64::from(step) / 200.0;
                let values: Vec<f64> = (-3..=3).map(|i| integrated(i, centre, sigma)).collect();
                let brightest = (0..7)
                    .max_by(|&a, &b| values[a].total_cmp(&values[b]))
                    .unwrap();
                let samples = PeakSamples {
                    peak: (brightest, brightest),
                    centre: values[brightest],
                    x: [Some(values[brightest - 1]), Some(values[brightest + 1])],
                    y: [Some(values[brightest - 1]), Some(values[brightest + 1])],
                };
                let (x, y) = gaussian_centre(&samples, (f64::NAN, f64::NAN));
                assert_eq!(x, y);
                // Pixel -3 is index 0.
                worst = worst.max((x - 3.0 - centre).abs());
            }
            assert!(worst <= bound, "{diameter} px: {worst}");
            assert!(
                worst > bound / 10.0,
                "{diameter} px: the bound is not tight"
            );
        }
    }

    #[test]
    fn degenerate_samples_give_none_never_nan() {
        let values = [
            0.0,
            -1.0,
            1.0,
            2.0,
            1e-300,
            f64::MIN_POSITIVE,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for a in values {
            for b in values {
                for c in values {
                    if let Some(offset) = log_parabola_offset(a, b, c) {
                        assert!(offset.abs() <= 0.5, "{a} {b} {c}: {offset}");
                    }
                }
            }
        }
        // A flat top (saturated) or a dent, and a peak that is not the top.
        assert_eq!(log_parabola_offset(5.0, 5.0, 5.0), None);
        assert_eq!(log_parabola_offset(5.0, 4.0, 5.0), None);
        assert_eq!(log_parabola_offset(10.0, 9.0, 1.0), None);
        assert_eq!(log_parabola_offset(0.0, 9.0, 1.0), None);
        let mut random = rng(2);
        for _ in 0..10000 {
            let mut v = || {
                if random.random_bool(0.1) {
                    0.0
                } else {
                    random.random_range(-1.0..100.0)
                }
            };
            let (a, b, c) = (v(), v(), v());
            if let Some(offset) = log_parabola_offset(a, b, c) {
                assert!(offset.is_finite() && offset.abs() <= 0.5, "{a} {b} {c}");
            }
        }
    }

    #[test]
    fn an_axis_without_usable_neighbours_keeps_the_weighted_centroid() {
        let centre = 100.0 * gaussian(0.0, 0.2, 0.75);
        let left = 100.0 * gaussian(-1.0, 0.2, 0.75);
        let right = 100.0 * gaussian(1.0, 0.2, 0.75);
        let samples = PeakSamples {
            peak: (10, 20),
            centre,
            x: [Some(left), Some(right)],
            y: [None, Some(right)],
        };
        let (x, y) = gaussian_centre(&samples, (10.6, 20.4));
        assert!((x - 10.7).abs() < 1e-9, "{x}");
        assert_eq!(y, 20.4);
        // A degenerate fit (a neighbour brighter than the peak) too.
        let samples = PeakSamples {
            x: [Some(left), Some(2.0 * centre)],
            ..samples
        };
        assert_eq!(gaussian_centre(&samples, (10.6, 20.4)), (10.6, 20.4));
    }

    /// A 16-bit image of Gaussians sampled at the pixel centres (on no
    /// background, rounded), and the parameters that find them unfiltered.
    fn sampled(width: usize, centres: &[(f64, f64)], sigma: f64, peak: f64) -> GreyImage {
        let pixels = (0..width * width)
            .map(|i| {
                let (u, v) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
                let value: f64 = centres
                    .iter()
                    .map(|&(x, y)| peak * gaussian(u, x, sigma) * gaussian(v, y, sigma))
                    .sum();
                value.round().min(65535.0) as u16
            })
            .collect();
        GreyImage::from_u16(width as u32, width as u32, pixels).unwrap()
    }

    fn gaussian_parameters() -> DetectionParameters {
        DetectionParameters {
            threshold: 200,
            highpass_radius: 0,
            min_pixels: 1,
            centroid: Centroid::Gaussian,
            ..DetectionParameters::default()
        }
    }

    #[test]
    fn detection_recovers_sampled_gaussians_to_the_rounding() {
        let mut random = rng(3);
        for _ in 0..50 {
            let sigma = random.random_range(0.5..1.0);
            let (x, y) = (
                random.random_range(10.0..11.0),
                random.random_range(10.0..11.0),
            );
            let image = sampled(21, &[(x, y)], sigma, 50000.0);
            let targets = detect(&image, &gaussian_parameters());
            assert_eq!(targets.len(), 1);
            let t = targets[0];
            // Rounding to whole grey levels moves ln g by at most 0.5/g,
            // g >= 50000 exp(-(1.5/0.5)^2/2) = 555 at the neighbours: the
            // offset by about 1e-3 / 2 over the curvature 1/sigma^2 >= 1.
            assert!(
                (t.x - x).abs() < 1e-3 && (t.y - y).abs() < 1e-3,
                "{sigma} ({x}, {y}): {t:?}"
            );
            let weighted = detect(
                &image,
                &DetectionParameters {
                    centroid: Centroid::Weighted,
                    ..gaussian_parameters()
                },
            )[0];
            // The weighted centroid (weights above the threshold) is worse.
            assert!((weighted.x - x).hypot(weighted.y - y) > (t.x - x).hypot(t.y - y));
        }
    }

    #[test]
    fn a_neighbour_of_another_particle_is_not_used() {
        // Two particles 2.2 px apart along x, peaks in columns 14 and 16:
        // the blob is split, and the saddle column 15 joins the brighter
        // peak's particle (14). The other particle's left neighbour is then
        // not its own, so its x is the weighted centroid's; y is fitted for
        // both (their sum is a Gaussian in y: exact).
        let image = sampled(31, &[(14.5, 15.2), (16.7, 15.2)], 0.6, 50000.0);
        let by_x = |parameters: &DetectionParameters| {
            let mut targets = detect(&image, parameters);
            targets.sort_by(|a, b| a.x.total_cmp(&b.x));
            targets
        };
        let gaussian = by_x(&gaussian_parameters());
        let weighted = by_x(&DetectionParameters {
            centroid: Centroid::Weighted,
            ..gaussian_parameters()
        });
        assert_eq!(gaussian.len(), 2);
        assert_eq!(weighted.len(), 2);
        assert_eq!(gaussian[1].x, weighted[1].x);
        assert_ne!(gaussian[0].x, weighted[0].x);
        for g in &gaussian {
            assert!((g.y - 15.2).abs() < 1e-3, "{g:?}");
        }
    }

    #[test]
    fn serde_names_are_snake_case_and_the_default_is_weighted() {
        assert_eq!(Centroid::default(), Centroid::Weighted);
        for c in [Centroid::Weighted, Centroid::Gaussian] {
            let json = serde_json::to_string(&c).unwrap();
            assert_eq!(json, format!("\"{}\"", c.name()));
            assert_eq!(serde_json::from_str::<Centroid>(&json).unwrap(), c);
        }
        assert!(serde_json::from_str::<Centroid>("\"Gaussian\"").is_err());
    }
}
