//! Speed of the pictures (issue 16: the frame overlay of a 1280x1024 image
//! with 2,000 targets, and the residual plot, 50 ms or less each).
//!
//! Run with `cargo bench --bench plot` (pinned to one core:
//! `taskset -c 1 cargo bench --bench plot`). Figures:
//! - `overlay 1280x1024, 2000 targets`: the simulator's image of 2,000
//!   particles in camera 0 of the convergent 4-camera rig, its 2,000
//!   targets (all matched) and the 2,000 particles reprojected; as PNG
//!   (draw and encode: what `overlay.png` serves, decoding of the stored
//!   image aside), drawn only (the raster, no encoding), and as SVG (the
//!   image embedded as PNG).
//! - `residuals, 200 points`: one camera's residual plot (200 points used,
//!   2 excluded, 30 check points) as PNG and as SVG.
//!
//! Measured on the 2-core development machine, pinned to one core, others
//! building (load average 3-8): overlay 12.3-16.2 ms as PNG, 4.3 ms drawn
//! only, 16 ms as SVG; residuals 2.1-2.8 ms as PNG, 0.56-0.74 ms as SVG.
//! The overlay's PNG is 1.8 MB, its SVG 1.8 MB.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::Point3;
use ptv::photogrammetry::simulate::{self, RenderSpec, RigSpec};
use ptv::plot::overlay::{draw_overlay, overlay_plot, Overlay};
use ptv::plot::residuals::{residual_plot, ResidualReport};
use ptv::plot::{Canvas, PlotFormat};
use rand::Rng;
use rand_distr::{Distribution, Normal};

const PARTICLES: usize = 2000;

fn overlay(c: &mut Criterion) {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().unwrap();
    let mut rng = simulate::rng(16);
    let points = simulate::particles(&spec.volume, PARTICLES, &mut rng);
    let image = simulate::render_frame(
        &cameras[..1],
        &points,
        &RenderSpec::eight_bit(2.5),
        &mut rng,
    )
    .remove(0)
    .image;
    let frame = simulate::target_frame(&cameras, &points, 0.05, 0.0, &mut rng);
    // Per particle, its target in every camera.
    let mut seen = vec![vec![None; cameras.len()]; points.len()];
    for (camera, truth) in frame.truth.iter().enumerate() {
        for (target, &particle) in truth.iter().enumerate() {
            seen[particle][camera] = Some(target);
        }
    }
    let targets = &frame.targets[0];
    assert!(targets.len() > 1900, "{} targets", targets.len());
    let particles: Vec<(Point3<f64>, &[Option<usize>])> = points
        .iter()
        .zip(&seen)
        .map(|(p, s)| (*p, s.as_slice()))
        .collect();
    let make = || {
        let mut o = Overlay::new(
            &cameras[0],
            0,
            targets,
            particles.iter().copied(),
            Some(&image),
        );
        o.title = "FRAME 1 CAMERA 0".to_owned();
        o
    };
    let png = overlay_plot(&make(), PlotFormat::Png).unwrap();
    let svg = overlay_plot(&make(), PlotFormat::Svg).unwrap();
    eprintln!(
        "overlay: {} targets, {} particles; PNG {} kB, SVG {} kB",
        targets.len(),
        particles.len(),
        png.len() / 1000,
        svg.len() / 1000
    );
    let mut group = c.benchmark_group("overlay 1280x1024, 2000 targets");
    group.sample_size(30);
    group.bench_function("PNG (reprojection, drawing, encoding)", |b| {
        b.iter(|| overlay_plot(black_box(&make()), PlotFormat::Png).unwrap())
    });
    group.bench_function("drawn only", |b| {
        b.iter(|| {
            let o = make();
            let (w, h) = o.size().unwrap();
            let mut canvas = Canvas::new(w, h);
            draw_overlay(&mut canvas, black_box(&o));
            canvas.into_image()
        })
    });
    group.bench_function("SVG", |b| {
        b.iter(|| overlay_plot(black_box(&make()), PlotFormat::Svg).unwrap())
    });
    group.finish();
}

fn residuals(c: &mut Criterion) {
    let mut rng = simulate::rng(17);
    let noise = Normal::new(0.0, 0.1).unwrap();
    let mut point = |id: u64, scale: f64| {
        serde_json::json!({
            "id": id,
            "x_px": scale * noise.sample(&mut rng),
            "y_px": scale * noise.sample(&mut rng),
            "image_px": [rng.random_range(0.0..1280.0), rng.random_range(0.0..1024.0)],
            "test": null,
        })
    };
    let used: Vec<_> = (0..200).map(|id| point(id, 1.0)).collect();
    let excluded: Vec<_> = (200..202).map(|id| point(id, 30.0)).collect();
    let check: Vec<_> = (0..30)
        .map(|id| serde_json::json!({"id": id, "dx": 0.01, "dy": -0.02, "dz": 0.03, "cameras": 4}))
        .collect();
    let report = serde_json::json!({
        "cameras": [{"name": "cam1", "sigma0_px": 0.1, "residuals": used, "excluded": excluded}],
        "check_points": {"count": 30, "rmse_x_mm": 0.01, "rmse_y_mm": 0.02, "rmse_z_mm": 0.03,
                         "relative_accuracy": 6000.0, "points": check},
    })
    .to_string();
    let report = ResidualReport::from_json(&report, "bench").unwrap();
    let mut group = c.benchmark_group("residuals, 200 points");
    group.sample_size(30);
    for (name, format) in [("PNG", PlotFormat::Png), ("SVG", PlotFormat::Svg)] {
        group.bench_function(name, |b| {
            b.iter(|| residual_plot(black_box(&report), 0, (1280, 1024), format).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, overlay, residuals);
criterion_main!(benches);
