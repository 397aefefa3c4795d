//! Correspondences on synthetic 4-camera water scenes: quality against the
//! simulator's truth, printed as a table, and the time of one frame's
//! matching on one core.
//!
//! Run with `cargo bench --bench correspond`. The scene: the simulator's
//! convergent 4-camera rig behind a glass wall, image noise 0.1 px, 10% of
//! the targets dropped in each camera (overlap losses), tolerance 0.5 px.
//! A second group matches the 10,000-particle scene in wide bands (2, 4 and
//! 10 px), with the same quality table per band: the matcher accepts only
//! what fits the frame's own noise and narrows a wide band to it, so the
//! figures should stay close to those at 0.5 px.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use ptv::photogrammetry::correspond::{Matcher, MatchingParameters};
use ptv::photogrammetry::simulate::{self, MatchScore, RigSpec, TargetFrame};

const NOISE_PX: f64 = 0.1;
const DROPPED: f64 = 0.1;
const TOLERANCE_PX: f64 = 0.5;

struct Scene {
    matcher: Matcher,
    points: Vec<nalgebra::Point3<f64>>,
    frame: TargetFrame,
}

fn scene(particles: usize, tolerance: f64) -> Scene {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().expect("valid rig");
    let mut rng = simulate::rng(particles as u64);
    let points = simulate::particles(&spec.volume, particles, &mut rng);
    let frame = simulate::target_frame(&cameras, &points, NOISE_PX, DROPPED, &mut rng);
    let parameters = MatchingParameters {
        tolerance,
        volume: Some(spec.volume),
        ..MatchingParameters::default()
    };
    let matcher = Matcher::new(&cameras, &parameters).expect("valid parameters");
    Scene {
        matcher,
        points,
        frame,
    }
}

/// One matching of the scene, timed, as a row of the quality table.
fn table_row(label: &str, scene: &Scene) {
    let start = Instant::now();
    let found = scene
        .matcher
        .match_frame(&scene.frame.targets)
        .expect("matching runs");
    let elapsed = start.elapsed();
    let score = MatchScore::of(&found, &scene.frame, &scene.points);
    eprintln!(
        "{label} | {} | {} | {} | {} | {} | {} | {:.4} | {:.4} | {:.1}",
        scene.frame.targets[0].len(),
        score.correct,
        score.ghosts,
        score.by_cameras[4],
        score.by_cameras[3],
        score.by_cameras[2],
        score.rms_error,
        score.mean_sigma,
        elapsed.as_secs_f64() * 1e3
    );
}

const HEADER: &str = "targets/camera | correct | ghosts | quadruplets | triplets | pairs | 3D RMS error (mm) | mean sigma (mm) | one run (ms)";

fn correspondences(c: &mut Criterion) {
    eprintln!("\nparticles | {HEADER}");
    let mut group = c.benchmark_group("match 4 cameras");
    group.sample_size(10);
    for particles in [2_000usize, 10_000, 20_000, 50_000] {
        let scene = scene(particles, TOLERANCE_PX);
        table_row(&particles.to_string(), &scene);
        group.throughput(Throughput::Elements(particles as u64));
        group.bench_with_input(
            BenchmarkId::from_parameter(particles),
            &scene,
            |b, scene| {
                b.iter(|| black_box(scene.matcher.match_frame(black_box(&scene.frame.targets))))
            },
        );
    }
    group.finish();
}

fn wide_bands(c: &mut Criterion) {
    const PARTICLES: usize = 10_000;
    eprintln!("\n{PARTICLES} particles, band (px) | {HEADER}");
    let mut group = c.benchmark_group("match 4 cameras, 10,000 particles, band (px)");
    group.sample_size(10);
    for band in [2.0, 4.0, 10.0] {
        let scene = scene(PARTICLES, band);
        table_row(&band.to_string(), &scene);
        group.throughput(Throughput::Elements(PARTICLES as u64));
        group.bench_with_input(BenchmarkId::from_parameter(band), &scene, |b, scene| {
            b.iter(|| black_box(scene.matcher.match_frame(black_box(&scene.frame.targets))))
        });
    }
    group.finish();
}

criterion_group!(benches, correspondences, wide_bands);
criterion_main!(benches);
