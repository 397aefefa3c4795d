//! Speed of the camera model: multimedia projection and spatial intersection.
//!
//! Run with `cargo bench --bench camera_model`. Each iteration handles a
//! batch of 1000 points, so the per-point figure is the reported time / 1000.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ptv::photogrammetry::simulate::{self, RigSpec};
use ptv::photogrammetry::{intersect, Camera, Distortion, Observation};

const POINTS: usize = 1000;

fn rig(cameras: usize) -> (Vec<Camera>, Vec<nalgebra::Point3<f64>>) {
    let mut spec = RigSpec::convergent(cameras);
    spec.distortion = Distortion {
        k1: 1e-4,
        p1: 1e-5,
        scx: 1.001,
        shear: 0.001,
        ..Distortion::default()
    };
    let points = simulate::particles(&spec.volume, POINTS, &mut simulate::rng(11));
    (spec.build().expect("valid rig"), points)
}

fn projection(c: &mut Criterion) {
    let mut group = c.benchmark_group("project");
    group.throughput(Throughput::Elements(POINTS as u64));
    let (cameras, points) = rig(1);
    let camera = &cameras[0];
    group.bench_function("through 1 wall, exact (per 1000 points)", |b| {
        b.iter(|| {
            for point in &points {
                black_box(camera.project(black_box(point)).ok());
            }
        })
    });
    let volume = RigSpec::convergent(1).volume;
    let tabulated = camera.clone().with_refraction_table(&volume);
    group.bench_function("through 1 wall, lookup table (per 1000 points)", |b| {
        b.iter(|| {
            for point in &points {
                black_box(tabulated.project(black_box(point)).ok());
            }
        })
    });
    let mut air = RigSpec::convergent(1);
    air.tank = None;
    let air_camera = &air.build().expect("valid rig")[0];
    group.bench_function("in air (per 1000 points)", |b| {
        b.iter(|| {
            for point in &points {
                black_box(air_camera.project(black_box(point)).ok());
            }
        })
    });
    group.finish();
}

fn intersection(c: &mut Criterion) {
    let mut group = c.benchmark_group("intersect");
    group.throughput(Throughput::Elements(POINTS as u64));
    let (cameras, points) = rig(4);
    let images = simulate::observe(&cameras, &points, 0.05, &mut simulate::rng(12));
    let volume = RigSpec::convergent(4).volume;
    let tabulated: Vec<Camera> = cameras
        .iter()
        .map(|c| c.clone().with_refraction_table(&volume))
        .collect();
    let observations: Vec<Vec<Observation>> = (0..points.len())
        .map(|j| simulate::observations_of(&images, j))
        .collect();
    for (name, rig) in [("exact", &cameras), ("lookup table", &tabulated)] {
        group.bench_function(
            format!("4 cameras, 1 wall, 0.05 px noise, {name} (per 1000 points)"),
            |b| {
                b.iter(|| {
                    for obs in &observations {
                        black_box(intersect(rig, black_box(obs)).ok());
                    }
                })
            },
        );
    }
    group.finish();
}

criterion_group!(benches, projection, intersection);
criterion_main!(benches);
