//! Speed of particle detection (design paper, section 6.1): high-pass
//! filter, threshold segmentation, splitting and centroids of a whole frame.
//!
//! Run with `cargo bench --bench detect`. The frame is the simulator's
//! 1280x1024 image with 2000 particles of 2.5 px (8-bit, noise, a sloping
//! background); OpenPTV's C detector takes about 7 ms on such a frame. The
//! single-frame figures run on one core; `4 cameras` detects four frames with
//! `detect_cameras`, which spreads them over all cores (rayon), against the
//! same four one after another.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nalgebra::Point2;
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{detect, detect_cameras, DetectionParameters, GreyImage};
use rand::Rng;

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 1024;
const PARTICLES: usize = 2000;

fn frame(spec: &RenderSpec, seed: u64) -> GreyImage {
    let mut rng = simulate::rng(seed);
    let positions: Vec<Point2<f64>> = (0..PARTICLES)
        .map(|_| {
            Point2::new(
                rng.random_range(0.0..f64::from(WIDTH)),
                rng.random_range(0.0..f64::from(HEIGHT)),
            )
        })
        .collect();
    simulate::render(WIDTH, HEIGHT, &positions, spec, &mut rng)
}

fn single_frame(c: &mut Criterion) {
    let mut group = c.benchmark_group("detect 1280x1024, 2000 particles");
    group.throughput(Throughput::Elements(u64::from(WIDTH * HEIGHT)));
    let eight = frame(&RenderSpec::eight_bit(2.5), 1);
    let parameters = DetectionParameters::default();
    group.bench_function("8-bit", |b| {
        b.iter(|| black_box(detect(black_box(&eight), &parameters)))
    });
    let plain = DetectionParameters {
        split: false,
        ..parameters.clone()
    };
    group.bench_function("8-bit, no splitting", |b| {
        b.iter(|| black_box(detect(black_box(&eight), &plain)))
    });
    let sixteen = frame(&RenderSpec::sixteen_bit(2.5), 1);
    let parameters16 = DetectionParameters {
        threshold: parameters.threshold * 257,
        split_depth: parameters.split_depth * 257,
        ..parameters.clone()
    };
    group.bench_function("16-bit", |b| {
        b.iter(|| black_box(detect(black_box(&sixteen), &parameters16)))
    });
    group.finish();
}

fn several_cameras(c: &mut Criterion) {
    let mut group = c.benchmark_group("detect 4 cameras");
    let frames: Vec<GreyImage> = (0..4)
        .map(|k| frame(&RenderSpec::eight_bit(2.5), 10 + k))
        .collect();
    let parameters = DetectionParameters::default();
    let jobs: Vec<(&GreyImage, &DetectionParameters)> =
        frames.iter().map(|f| (f, &parameters)).collect();
    group.bench_function("in parallel (detect_cameras)", |b| {
        b.iter(|| black_box(detect_cameras(black_box(&jobs))))
    });
    group.bench_function("one after another", |b| {
        b.iter(|| {
            for frame in &frames {
                black_box(detect(black_box(frame), &parameters));
            }
        })
    });
    group.finish();
}

criterion_group!(benches, single_frame, several_cameras);
criterion_main!(benches);
