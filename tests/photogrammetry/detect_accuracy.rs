//! Detection against the renderer's ground truth (design paper, section 6.1).
//!
//! **Ground truth match.** A rendered particle is *found* when a target lies
//! within 1 px of its exact image position. Matching is one to one: all
//! (particle, target) pairs closer than 1 px are taken in order of
//! increasing distance, each particle and each target at most once. Recall
//! is the share of particles found; a *false target* is one matched to no
//! particle (noise, a merged blob whose centroid lies between its particles,
//! or a second target on one particle); the centroid error is the 2D
//! distance |detected - true| of matched pairs, and "RMS" its root mean
//! square (so per coordinate it is smaller by about sqrt 2).
//!
//! Particles closer than 5 px to the image border are left out of recall
//! (the detector drops targets touching the border by design); targets that
//! close to the border are left out of the false-target count. Run with
//! `cargo test --release --test photogrammetry detect_accuracy -- --nocapture` to see the
//! tables.

use std::collections::HashMap;

use nalgebra::Point2;
use ptv::photogrammetry::detect::{detect_with_pixels, TargetPixels};
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{detect, DetectionParameters, GreyImage, Target};
use rand::Rng;

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 1024;
/// Particles and targets this close to the border are not scored.
const MARGIN: f64 = 5.0;
/// A target within this distance of a particle finds it.
const MATCH_RADIUS: f64 = 1.0;

fn interior(p: Point2<f64>) -> bool {
    p.x >= MARGIN
        && p.y >= MARGIN
        && p.x <= f64::from(WIDTH) - MARGIN
        && p.y <= f64::from(HEIGHT) - MARGIN
}

/// Per particle, the index of the target that finds it: the one-to-one
/// nearest-first matching described in the module documentation.
fn match_targets(truth: &[Point2<f64>], targets: &[Target]) -> Vec<Option<usize>> {
    let cell = |x: f64, y: f64| {
        (
            (x / MATCH_RADIUS).floor() as i64,
            (y / MATCH_RADIUS).floor() as i64,
        )
    };
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (k, t) in targets.iter().enumerate() {
        grid.entry(cell(t.x, t.y)).or_default().push(k);
    }
    let mut pairs = Vec::new();
    for (i, p) in truth.iter().enumerate() {
        let (cx, cy) = cell(p.x, p.y);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &k in grid.get(&(cx + dx, cy + dy)).into_iter().flatten() {
                    let d = (targets[k].x - p.x).hypot(targets[k].y - p.y);
                    if d <= MATCH_RADIUS {
                        pairs.push((d, i, k));
                    }
                }
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut of_truth = vec![None; truth.len()];
    let mut taken = vec![false; targets.len()];
    for (_, i, k) in pairs {
        if of_truth[i].is_none() && !taken[k] {
            of_truth[i] = Some(k);
            taken[k] = true;
        }
    }
    of_truth
}

/// How well a set of targets reproduces the particles.
#[derive(Clone, Copy, Debug)]
struct Score {
    particles: usize,
    found: usize,
    false_targets: usize,
    rms: f64,
    max_error: f64,
}

impl Score {
    fn recall(&self) -> f64 {
        self.found as f64 / self.particles as f64
    }
}

fn score(truth: &[Point2<f64>], targets: &[Target]) -> (Score, Vec<Option<usize>>) {
    let matched = match_targets(truth, targets);
    let mut taken = vec![false; targets.len()];
    let (mut particles, mut found, mut sum2, mut max_error) = (0, 0, 0.0, 0.0f64);
    for (p, m) in truth.iter().zip(&matched) {
        if let Some(k) = m {
            taken[*k] = true;
        }
        if !interior(*p) {
            continue;
        }
        particles += 1;
        if let Some(k) = m {
            found += 1;
            let e = (targets[*k].x - p.x).hypot(targets[*k].y - p.y);
            sum2 += e * e;
            max_error = max_error.max(e);
        }
    }
    let false_targets = targets
        .iter()
        .zip(&taken)
        .filter(|(t, taken)| !**taken && interior(Point2::new(t.x, t.y)))
        .count();
    let score = Score {
        particles,
        found,
        false_targets,
        rms: (sum2 / found.max(1) as f64).sqrt(),
        max_error,
    };
    (score, matched)
}

/// Particles on a 16 px grid, each shifted by a random sub-pixel amount:
/// isolated, with every sub-pixel phase sampled.
fn isolated_particles(rng: &mut impl Rng) -> Vec<Point2<f64>> {
    let mut positions = Vec::new();
    for j in 1..HEIGHT / 16 {
        for i in 1..WIDTH / 16 {
            positions.push(Point2::new(
                f64::from(i * 16) + rng.random::<f64>(),
                f64::from(j * 16) + rng.random::<f64>(),
            ));
        }
    }
    positions
}

fn uniform_particles(count: usize, rng: &mut impl Rng) -> Vec<Point2<f64>> {
    (0..count)
        .map(|_| {
            Point2::new(
                rng.random_range(0.0..f64::from(WIDTH)),
                rng.random_range(0.0..f64::from(HEIGHT)),
            )
        })
        .collect()
}

fn render(positions: &[Point2<f64>], spec: &RenderSpec, seed: u64) -> GreyImage {
    simulate::render(WIDTH, HEIGHT, positions, spec, &mut simulate::rng(seed))
}

#[test]
fn isolated_particles_are_found_to_a_twentieth_of_a_pixel() {
    println!(
        "isolated particles, 8-bit, read noise 1 grey level + photon noise, default parameters"
    );
    println!("diameter_px  particles  recall    false  rms_px  max_px");
    for (k, diameter) in [2.0, 2.5, 3.0].into_iter().enumerate() {
        let mut rng = simulate::rng(100 + k as u64);
        let truth = isolated_particles(&mut rng);
        let image = render(&truth, &RenderSpec::eight_bit(diameter), 200 + k as u64);
        let targets = detect(&image, &DetectionParameters::default());
        let (s, _) = score(&truth, &targets);
        println!(
            "{diameter:11.1}  {:9}  {:7.4}  {:5}  {:6.4}  {:6.3}",
            s.particles,
            s.recall(),
            s.false_targets,
            s.rms,
            s.max_error
        );
        assert!(s.recall() >= 0.995, "diameter {diameter}: {s:?}");
        assert!(s.rms <= 0.05, "diameter {diameter}: {s:?}");
        assert_eq!(s.false_targets, 0, "diameter {diameter}: {s:?}");
    }
}

#[test]
fn pure_noise_gives_no_targets_at_the_default_threshold() {
    for seed in 0..3 {
        let image = render(&[], &RenderSpec::eight_bit(2.5), seed);
        let targets = detect(&image, &DetectionParameters::default());
        assert!(targets.is_empty(), "seed {seed}: {} targets", targets.len());
    }
}

/// Bins of 0.5 px for the separation of merged pairs, the last open-ended.
const SEPARATION_BINS: usize = 9;

/// Merges made by plain connected components, and how many the splitting
/// detector undoes.
#[derive(Clone, Copy, Debug, Default)]
struct Merges {
    /// Blobs holding exactly two particles' centre pixels.
    pairs: usize,
    /// Of those, pairs whose two particles the splitting detector both finds.
    pairs_recovered: usize,
    /// Pairs and recovered pairs by separation, in bins of 0.5 px.
    by_separation: [(usize, usize); SEPARATION_BINS],
    /// Blobs holding three or more.
    groups: usize,
    /// Particles in merged blobs that plain components do not find...
    lost: usize,
    /// ...and of those, how many splitting finds.
    lost_recovered: usize,
}

fn merges(
    truth: &[Point2<f64>],
    plain: &[TargetPixels],
    plain_matched: &[Option<usize>],
    split_matched: &[Option<usize>],
) -> Merges {
    let mut blob_of = HashMap::new();
    for (k, t) in plain.iter().enumerate() {
        for &pixel in &t.pixels {
            blob_of.insert(pixel, k);
        }
    }
    // The detector's blobs are 4-connected; particles merge where their
    // images touch, at an edge or a corner: join blobs that touch at a
    // corner into the 8-connected components.
    let mut parent: Vec<usize> = (0..plain.len()).collect();
    fn root(parent: &mut [usize], mut k: usize) -> usize {
        while parent[k] != k {
            parent[k] = parent[parent[k]];
            k = parent[k];
        }
        k
    }
    for (k, t) in plain.iter().enumerate() {
        for &(x, y) in &t.pixels {
            for (dx, dy) in [(-1i64, -1i64), (1, -1), (-1, 1), (1, 1)] {
                let q = ((i64::from(x) + dx) as u32, (i64::from(y) + dy) as u32);
                if let Some(&j) = blob_of.get(&q) {
                    let (a, b) = (root(&mut parent, k), root(&mut parent, j));
                    parent[a] = b;
                }
            }
        }
    }
    for k in blob_of.values_mut() {
        *k = root(&mut parent, *k);
    }
    let mut members: HashMap<usize, Vec<usize>> = HashMap::new();
    for (i, p) in truth.iter().enumerate() {
        if !interior(*p) {
            continue;
        }
        if let Some(&k) = blob_of.get(&(p.x as u32, p.y as u32)) {
            members.entry(k).or_default().push(i);
        }
    }
    let mut m = Merges::default();
    for particles in members.values().filter(|v| v.len() >= 2) {
        if particles.len() == 2 {
            let separation = (truth[particles[0]] - truth[particles[1]]).norm();
            let bin = ((separation * 2.0) as usize).min(SEPARATION_BINS - 1);
            let recovered = particles.iter().all(|&i| split_matched[i].is_some());
            m.pairs += 1;
            m.by_separation[bin].0 += 1;
            if recovered {
                m.pairs_recovered += 1;
                m.by_separation[bin].1 += 1;
            }
        } else {
            m.groups += 1;
        }
        for &i in particles {
            if plain_matched[i].is_none() {
                m.lost += 1;
                if split_matched[i].is_some() {
                    m.lost_recovered += 1;
                }
            }
        }
    }
    m
}

/// The particle image diameter of the density experiments (px).
const DENSE_DIAMETER: f64 = 2.5;

/// Overlaps at 0.005, 0.01 and 0.02 particles per pixel.
///
/// Bounds, derived rather than fitted:
/// - Recall: two particles at least one image diameter `d` apart keep two
///   maxima, so every particle without another within `d` can be found.
///   With particles placed uniformly at density `rho` that is a share
///   `exp(-rho pi d^2)` of them (0.906, 0.822, 0.675); recall must reach it.
///   (It is higher: of a closer pair, the brighter one often lies within
///   1 px of the merged centroid.)
/// - Merged pairs: the issue asks that splitting recovers at least half of
///   the pairs plain connected components merge; and by the argument above,
///   at least 95% of those at least `d` apart (noise may flatten a dip).
/// - False targets: one needs a blob whose maxima lie more than 1 px from
///   every particle: three or more overlapping, or a pair just at the limit
///   of resolution. They must stay below 1% of the particles.
/// - Centroid RMS: a neighbour's tail pulls a centroid, so RMS grows with
///   density; splitting must improve on plain components, and matches are
///   within 1 px by definition.
#[test]
fn splitting_recovers_overlapping_particles() {
    println!("uniform particles, {DENSE_DIAMETER} px, 8-bit, {WIDTH}x{HEIGHT}, default parameters");
    println!(
        "density_ppp  particles  method  recall    false  rms_px  | merged_pairs  recovered  groups>=3  lost  lost_recovered"
    );
    let mut by_separation = [[(0, 0); SEPARATION_BINS]; 3];
    for (k, density) in [0.005, 0.01, 0.02].into_iter().enumerate() {
        let count = (density * f64::from(WIDTH * HEIGHT)).round() as usize;
        let mut rng = simulate::rng(300 + k as u64);
        let truth = uniform_particles(count, &mut rng);
        let image = render(
            &truth,
            &RenderSpec::eight_bit(DENSE_DIAMETER),
            400 + k as u64,
        );
        let parameters = DetectionParameters::default();
        let split = detect(&image, &parameters);
        let plain = detect_with_pixels(
            &image,
            &DetectionParameters {
                split: false,
                ..parameters.clone()
            },
        );
        let plain_targets: Vec<Target> = plain.iter().map(|t| t.target).collect();
        let (s_split, split_matched) = score(&truth, &split);
        let (s_plain, plain_matched) = score(&truth, &plain_targets);
        let m = merges(&truth, &plain, &plain_matched, &split_matched);
        by_separation[k] = m.by_separation;
        for (name, s) in [("plain", s_plain), ("split", s_split)] {
            println!(
                "{density:11.3}  {:9}  {name:6}  {:7.4}  {:5}  {:6.4}  |",
                s.particles,
                s.recall(),
                s.false_targets,
                s.rms
            );
        }
        println!(
            "{:>57} {:12}  {:9}  {:9}  {:4}  {:14}",
            "", m.pairs, m.pairs_recovered, m.groups, m.lost, m.lost_recovered
        );
        let resolvable = (-density * std::f64::consts::PI * DENSE_DIAMETER.powi(2)).exp();
        assert!(
            s_split.recall() >= resolvable,
            "density {density}: {s_split:?}"
        );
        assert!(2 * m.pairs_recovered >= m.pairs, "density {density}: {m:?}");
        let apart: (usize, usize) = m.by_separation[(DENSE_DIAMETER * 2.0) as usize..]
            .iter()
            .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        assert!(
            apart.1 as f64 >= 0.95 * apart.0 as f64,
            "density {density}: pairs at least {DENSE_DIAMETER} px apart: {apart:?}"
        );
        assert!(
            (s_split.false_targets as f64) < 0.01 * s_split.particles as f64,
            "density {density}: {s_split:?}"
        );
        assert!(s_split.rms < s_plain.rms, "density {density}");
    }
    println!("merged pairs recovered by splitting, by separation (recovered/merged)");
    println!("separation_px  0.005        0.01         0.02");
    for bin in 0..SEPARATION_BINS {
        let label = if bin + 1 < SEPARATION_BINS {
            format!("{:.1}-{:.1}", bin as f64 / 2.0, (bin + 1) as f64 / 2.0)
        } else {
            format!(">={:.1}", bin as f64 / 2.0)
        };
        let cells: Vec<String> = by_separation
            .iter()
            .map(|bins| format!("{:5}/{:<5}", bins[bin].1, bins[bin].0))
            .collect();
        println!("{label:>13}  {}", cells.join("  "));
    }
}

/// The error function (Abramowitz and Stegun 7.1.26, absolute error below
/// 1.5e-7), for the noise model below.
fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    (1.0 - poly * (-x * x).exp()).copysign(x)
}

/// What the renderer's noise alone should leave, per estimator: the RMS 2D
/// error (px) of the weighted centroid and of the 3-point Gaussian fit on
/// isolated particles of `spec`, detected with `parameters` (threshold,
/// high-pass radius), by first-order propagation of the pixel noise.
///
/// The model is the renderer's: a pixel holds the background plus the
/// Gaussian of peak `A` averaged over its area (`A` uniform over the
/// spec's range, the centre uniform over the pixel: a 10x10 grid of
/// phases, 13 peaks); its variance is the photon noise (signal over the
/// gain, in grey levels squared), the read noise squared and the rounding's
/// 1/12. The high-pass filter subtracts the window mean, which holds the
/// particle's own light `A 2 pi sigma^2 / (2r+1)^2` (its noise is
/// negligible: a mean over hundreds of pixels). The weighted centroid
/// uses the pixels whose noise-free level exceeds the threshold, with
/// weights `level - threshold`: its error is its bias (the truncated
/// tails) and its propagated noise. The Gaussian fit uses the brightest
/// pixel and its two neighbours per axis: its error is the noise
/// propagated through the logarithms (its bias, below 0.006 px, is
/// `ptv::photogrammetry::centroid`'s, and left out). Left out for both:
/// pixels that noise moves across the threshold, the Gaussian fit's
/// fallbacks, and second-order terms.
fn predicted_rms(spec: &RenderSpec, parameters: &DetectionParameters) -> (f64, f64) {
    let sigma = spec.sigma();
    let t = f64::from(parameters.threshold);
    let window = (2.0 * f64::from(parameters.highpass_radius) + 1.0).powi(2);
    let variance = |signal: f64| {
        (spec.background + signal).max(0.0) / spec.electrons_per_grey
            + spec.read_noise.powi(2)
            + 1.0 / 12.0
    };
    let profile = |i: i64, c: f64| {
        let k = 1.0 / (sigma * std::f64::consts::SQRT_2);
        sigma
            * (std::f64::consts::PI / 2.0).sqrt()
            * (erf((i as f64 + 1.0 - c) * k) - erf((i as f64 - c) * k))
    };
    let (mut weighted, mut gaussian, mut count) = (0.0, 0.0, 0.0);
    for a in 0..13 {
        let peak = spec.peak_min + (spec.peak_max - spec.peak_min) * f64::from(a) / 12.0;
        let mean = peak * 2.0 * std::f64::consts::PI * sigma * sigma / window;
        for phase in 0..100 {
            // The centre in pixel 0: columns and rows -4..=4 hold the image.
            let (cx, cy) = (
                (f64::from(phase % 10) + 0.5) / 10.0,
                (f64::from(phase / 10) + 0.5) / 10.0,
            );
            let signal = |i: i64, j: i64| peak * profile(i, cx) * profile(j, cy);
            let level = |i: i64, j: i64| signal(i, j) - mean;
            // Weighted: x = sum w x / sum w over pixel centres i + 0.5.
            let (mut w, mut wx, mut wy) = (0.0, 0.0, 0.0);
            for j in -4..=4 {
                for i in -4..=4 {
                    let weight = level(i, j) - t;
                    if weight > 0.0 {
                        w += weight;
                        wx += weight * (i as f64 + 0.5);
                        wy += weight * (j as f64 + 0.5);
                    }
                }
            }
            let (x, y) = (wx / w, wy / w);
            let mut noise = 0.0;
            for j in -4..=4 {
                for i in -4..=4 {
                    if level(i, j) - t > 0.0 {
                        let lever = (i as f64 + 0.5 - x).powi(2) + (j as f64 + 0.5 - y).powi(2);
                        noise += lever / (w * w) * variance(signal(i, j));
                    }
                }
            }
            weighted += (x - cx).powi(2) + (y - cy).powi(2) + noise;
            // Gaussian, along x then y: offset (a - c) / 2D, D = a - 2b + c
            // of the logarithms; d/da = (D - (a - c)) / 2D^2, d/db =
            // (a - c) / D^2, d/dc = -(D + (a - c)) / 2D^2; var ln s = var s / s^2.
            for (before, after) in [((-1, 0), (1, 0)), ((0, -1), (0, 1))] {
                let s = [
                    level(before.0, before.1),
                    level(0, 0),
                    level(after.0, after.1),
                ];
                let v = [
                    variance(signal(before.0, before.1)),
                    variance(signal(0, 0)),
                    variance(signal(after.0, after.1)),
                ];
                let [la, lb, lc] = s.map(f64::ln);
                let (d, e) = (la - 2.0 * lb + lc, la - lc);
                let partial = [
                    (d - e) / (2.0 * d * d),
                    e / (d * d),
                    -(d + e) / (2.0 * d * d),
                ];
                gaussian += (0..3)
                    .map(|k| partial[k].powi(2) * v[k] / s[k].powi(2))
                    .sum::<f64>();
            }
            count += 1.0;
        }
    }
    ((weighted / count).sqrt(), (gaussian / count).sqrt())
}

/// Issue 13's "Centroids": the weighted centroid against the 3-point
/// Gaussian fit (`ptv::photogrammetry::centroid`) on isolated rendered
/// particles of 2..4 px, 8-bit with photon and read noise, default
/// parameters otherwise; both on the same images. Run with `--nocapture`
/// for the table. The "fallback" column is the share of axes where the
/// Gaussian estimate is the weighted one (no fit: a neighbour of another
/// particle, or a degenerate fit).
///
/// Bounds, from the renderer's noise ([`predicted_rms`]): each estimator's
/// measured RMS must lie within 20% of (above or below) what first-order
/// propagation of the noise predicts, plus 0.006 px (the Gaussian fit's
/// largest bias on pixel-integrated images, not in the model; the
/// weighted model includes its bias). 20%: the model leaves out second-order
/// terms (at the faintest neighbours, 2 px images of peak 80, the relative
/// noise of a sample reaches 20%, where the logarithm's curvature adds a
/// few percent), and pixels that noise moves across the threshold. A
/// measured RMS outside that band means the estimator does not do what the
/// model says, in either direction.
#[test]
fn gaussian_and_weighted_centroids_on_isolated_particles() {
    use ptv::photogrammetry::Centroid;
    println!(
        "isolated particles, 8-bit, read noise 1 grey level + photon noise, default parameters"
    );
    println!("diameter_px  particles  weighted_rms  (model)  gaussian_rms  (model)  fallback_axes  recall_w  recall_g");
    for (k, diameter) in [2.0, 2.5, 3.0, 4.0].into_iter().enumerate() {
        let mut rng = simulate::rng(500 + k as u64);
        let truth = isolated_particles(&mut rng);
        let spec = RenderSpec::eight_bit(diameter);
        let image = render(&truth, &spec, 600 + k as u64);
        let weighted_parameters = DetectionParameters::default();
        let gaussian_parameters = DetectionParameters {
            centroid: Centroid::Gaussian,
            ..DetectionParameters::default()
        };
        let weighted = detect(&image, &weighted_parameters);
        let gaussian = detect(&image, &gaussian_parameters);
        // Same targets, in the same order (sorted by position, which the
        // estimators move by less than the 16 px spacing).
        assert_eq!(weighted.len(), gaussian.len());
        let fallback = weighted
            .iter()
            .zip(&gaussian)
            .map(|(w, g)| usize::from(w.x == g.x) + usize::from(w.y == g.y))
            .sum::<usize>() as f64
            / (2 * weighted.len()) as f64;
        let (sw, _) = score(&truth, &weighted);
        let (sg, _) = score(&truth, &gaussian);
        let (model_w, model_g) = predicted_rms(&spec, &weighted_parameters);
        println!(
            "{diameter:11.1}  {:9}  {:12.4}  {model_w:7.4}  {:12.4}  {model_g:7.4}  {fallback:13.4}  {:8.4}  {:8.4}",
            sw.particles,
            sw.rms,
            sg.rms,
            sw.recall(),
            sg.recall()
        );
        assert!(
            sw.recall() >= 0.995 && sg.recall() >= 0.995,
            "{diameter}: {sw:?} {sg:?}"
        );
        for (name, measured, model, bias) in [
            ("weighted", sw.rms, model_w, 0.0),
            ("gaussian", sg.rms, model_g, 0.006),
        ] {
            assert!(
                measured <= 1.2 * model + bias && measured >= model / 1.2 - bias,
                "{diameter} px, {name}: measured RMS {measured:.4} px, model {model:.4} px"
            );
        }
    }
}
