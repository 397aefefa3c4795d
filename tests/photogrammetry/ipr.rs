//! Iterative particle reconstruction on rendered 4-camera frames, scored
//! against the renderer's truth by the LPT challenge's 1-voxel rule
//! (`ptv::photogrammetry::score`).
//!
//! The rig is the simulator's convergent 4-camera rig with a 400x320
//! sensor (the volume, 80 x 80 x 40 mm, images onto about 260 px), so a
//! case runs in seconds in the test build; the particles are rendered as
//! `ptv simulate` renders them (`RenderSpec::eight_bit(2.5)`: peaks of
//! 80..200 grey, photon noise at 50 electrons per grey level, 1 grey of
//! read noise). Run with `-- --nocapture` to see the figures.
//!
//! The check is a comparison on the same frame set rather than a fixed
//! figure: IPR exists to do better than the 1993 pipeline (detection,
//! then epipolar matching, `FramePipeline` with `ptv process`'s defaults
//! and a 0.5 px band) where particle images overlap, so at 0.02 particles
//! per pixel of the sensor (more of the volume's footprint, which is what
//! docs/ipr.md's densities count) it must find more particles, with a smaller ghost fraction
//! and a smaller reprojected position error. A broken shaking (no
//! convergence), ghost removal or residual bookkeeping loses at least one
//! of the three. (At 1280x1024 and 0.02 ppp of the sensor the two score 93.8% / 3.2% ghosts
//! and 17% / 64% ghosts, here 93.8% / 2.7% and 19.7% / 60.7%: see
//! docs/ipr.md. The sparse case against the
//! issue's goals, noise-derived, is in `tests/cli/reconstruct.rs`.)

use nalgebra::Point3;
use ptv::photogrammetry::camera::Sensor;
use ptv::photogrammetry::correspond::MatchingParameters;
use ptv::photogrammetry::ipr::{reconstruct, IprParameters};
use ptv::photogrammetry::score::{score_particles, voxel, ParticleScore};
use ptv::photogrammetry::simulate::{self, RenderSpec, RigSpec};
use ptv::photogrammetry::{Camera, DetectionParameters, FrameDetection, FramePipeline, GreyImage};

const WIDTH: u32 = 400;
const HEIGHT: u32 = 320;

fn rig() -> (RigSpec, Vec<Camera>) {
    let spec = RigSpec {
        sensor: Sensor {
            width: WIDTH,
            height: HEIGHT,
            pixel_size_x: 0.012,
            pixel_size_y: 0.012,
        },
        ..RigSpec::convergent(4)
    };
    let cameras = spec.build().expect("the simulator's rig is valid");
    (spec, cameras)
}

/// Renders `ppp` particles per pixel, reconstructs them by IPR and by the
/// classic pipeline, scores both.
fn case(ppp: f64, seed: u64) -> (ParticleScore, ParticleScore) {
    let (spec, cameras) = rig();
    let count = (ppp * f64::from(WIDTH * HEIGHT)).round() as usize;
    let mut rng = simulate::rng(seed);
    let truth = simulate::particles(&spec.volume, count, &mut rng);
    let images: Vec<GreyImage> =
        simulate::render_frame(&cameras, &truth, &RenderSpec::eight_bit(2.5), &mut rng)
            .into_iter()
            .map(|r| r.image)
            .collect();
    let parameters = IprParameters {
        volume: Some(spec.volume),
        ..IprParameters::default()
    };
    let result = reconstruct(&cameras, &images, &[], &parameters, &mut |report| {
        println!("{report:?}")
    })
    .expect("a rendered frame set reconstructs");
    for otf in &result.otf {
        println!("{otf:?}");
    }
    let found: Vec<Point3<f64>> = result.particles.iter().map(|p| p.position).collect();
    let voxel = voxel(&spec.volume, WIDTH, HEIGHT).expect("a bounded volume");
    let ipr = score_particles(&truth, &found, voxel, &cameras);
    println!("ppp {ppp}, IPR: {ipr:?}");
    let pipeline = FramePipeline::new(
        &cameras,
        &FrameDetection::AllCameras(DetectionParameters::default()),
        &MatchingParameters {
            tolerance: 0.5,
            volume: Some(spec.volume),
            ..MatchingParameters::default()
        },
    )
    .expect("valid parameters");
    let classic: Vec<Point3<f64>> = pipeline
        .process(&images)
        .expect("a rendered frame set processes")
        .particles
        .iter()
        .map(|p| p.position)
        .collect();
    let classic = score_particles(&truth, &classic, voxel, &cameras);
    println!("ppp {ppp}, classic: {classic:?}");
    (ipr, classic)
}

#[test]
fn ipr_beats_the_classic_pipeline_on_overlapping_images() {
    let (ipr, classic) = case(0.02, 7);
    assert!(ipr.recall > classic.recall, "{ipr:?}\n{classic:?}");
    assert!(
        ipr.ghost_fraction < classic.ghost_fraction,
        "{ipr:?}\n{classic:?}"
    );
    assert!(ipr.rms_px < classic.rms_px, "{ipr:?}\n{classic:?}");
}
