//! Speed of `ptv background --mode median` (issue 13): the per-pixel
//! median of 100 frames of 1280x1024 8-bit, streamed through a
//! `BackgroundBuilder` (its default sample bound of 32 frames), on one
//! core. Target: 2 s or less, with memory independent of the frame count.
//!
//! Run with `cargo bench --bench background`. Two figures:
//! - `frames in memory`: decode excluded, the builder alone (`add` of 100
//!   decoded frames, then `finish`);
//! - `PNG decode included`: each of the 100 frames decoded from PNG bytes
//!   in memory first, as the command does from files (file reads aside).
//!
//! On the 2-core development machine (shared with other builds, bench
//! pinned to one core): 0.53 s (0.51-0.55) frames in memory, 1.14 s
//! (1.07-1.21) with PNG decoding. Memory of `ptv background --mode
//! median` (`/usr/bin/time -v`, 1280x1024 8-bit PNGs): 34 MB for 20
//! frames (all kept), 50 MB for 100 and for 300 (at most 32 kept);
//! `--mode min`: 10 MB for 20 and 11 MB for 100.
//!
//! The frames are the simulator's 1280x1024 images with 2000 particles of
//! 2.5 px; 25 different frames are cycled (the cost does not depend on
//! the values, and 100 distinct frames would hold 130 MB of PNGs).

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use image::{ExtendedColorType, ImageEncoder};
use nalgebra::Point2;
use ptv::formats::image::decode_image;
use ptv::photogrammetry::simulate::{self, RenderSpec};
use ptv::photogrammetry::{BackgroundBuilder, BackgroundMode, BitDepth, GreyImage, GreyPixels};
use rand::Rng;

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 1024;
const PARTICLES: usize = 2000;
const DISTINCT: usize = 25;
const FRAMES: usize = 100;

fn frame(seed: u64) -> GreyImage {
    let mut rng = simulate::rng(seed);
    let positions: Vec<Point2<f64>> = (0..PARTICLES)
        .map(|_| {
            Point2::new(
                rng.random_range(0.0..f64::from(WIDTH)),
                rng.random_range(0.0..f64::from(HEIGHT)),
            )
        })
        .collect();
    simulate::render(
        WIDTH,
        HEIGHT,
        &positions,
        &RenderSpec::eight_bit(2.5),
        &mut rng,
    )
}

fn png(image: &GreyImage) -> Vec<u8> {
    let GreyPixels::Eight(samples) = image.pixels() else {
        unreachable!("8-bit frames")
    };
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(samples, WIDTH, HEIGHT, ExtendedColorType::L8)
        .unwrap();
    bytes
}

fn median(c: &mut Criterion) {
    let frames: Vec<GreyImage> = (0..DISTINCT as u64).map(frame).collect();
    let pngs: Vec<Vec<u8>> = frames.iter().map(png).collect();
    let mut group = c.benchmark_group("background median, 100 frames of 1280x1024 8-bit");
    group.sample_size(10);
    group.bench_function("frames in memory", |b| {
        b.iter(|| {
            let mut builder =
                BackgroundBuilder::new(BackgroundMode::Median, WIDTH, HEIGHT, BitDepth::Eight);
            for t in 0..FRAMES {
                builder.add(&frames[t % DISTINCT]).unwrap();
            }
            black_box(builder.finish().unwrap())
        })
    });
    group.bench_function("PNG decode included", |b| {
        b.iter(|| {
            let mut builder =
                BackgroundBuilder::new(BackgroundMode::Median, WIDTH, HEIGHT, BitDepth::Eight);
            for t in 0..FRAMES {
                let frame = decode_image(&pngs[t % DISTINCT], "frame").unwrap();
                builder.add(&frame).unwrap();
            }
            black_box(builder.finish().unwrap())
        })
    });
    group.finish();
}

criterion_group!(benches, median);
criterion_main!(benches);
