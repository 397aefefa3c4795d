//! Self-calibration speed (issue 14's goal: 4 cameras, 10 frames x 2,000
//! particles in 10 s or less on 2 cores). A bench binary, not criterion:
//! one run takes seconds, so it is timed a few times and the figures
//! printed.
//!
//! The rig is the simulator's 4-camera convergent rig through a glass
//! wall; targets with 0.1 px noise. Two cases: its calibration moved by
//! 0.1 mm and 0.1 mrad per camera (about 0.5 px of disparity, a 1 px band:
//! the rounds match), and by 0.7 mm and 1 mrad (about 5 px, an 8 px band:
//! the first round votes, see `photogrammetry::selfcal`).
//!
//! `RAYON_NUM_THREADS=2 cargo bench --bench selfcal` (2 cores). Measured
//! here (release, 3 rounds each): 1.50-1.61 s a run moved 0.1 mm, 2.39-2.70
//! s moved 0.7 mm; the goal is 10 s.

use std::time::Instant;

use nalgebra::Vector3;
use rand::Rng;

use ptv::photogrammetry::camera::{rotation_angles, rotation_matrix};
use ptv::photogrammetry::selfcal::{self_calibrate, SelfCalibrationOptions};
use ptv::photogrammetry::simulate::{self, RigSpec};
use ptv::photogrammetry::{CameraParameters, Cancel};

fn main() {
    println!(
        "self-calibration, 4 cameras, 10 frames x 2,000 particles, {} threads",
        rayon::current_num_threads()
    );
    case("moved 0.1 mm, 0.1 mrad, band 1 px", 0.1, 1e-4, 1.0);
    case("moved 0.7 mm, 1 mrad, band 8 px", 0.7, 1e-3, 8.0);
}

fn case(label: &str, shift_mm: f64, turn_rad: f64, band_px: f64) {
    let spec = RigSpec::convergent(4);
    let truth = spec.build().expect("the simulated rig");
    let mut rng = simulate::rng(3);
    let mut unit = || Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
    let rough: Vec<CameraParameters> = truth
        .iter()
        .map(|c| {
            let mut p = c.parameters().clone();
            p.exterior.position += unit() * shift_mm;
            let e = &p.exterior;
            let r = nalgebra::Rotation3::from_scaled_axis(unit() * turn_rad).matrix()
                * rotation_matrix(e.omega, e.phi, e.kappa);
            (p.exterior.omega, p.exterior.phi, p.exterior.kappa) = rotation_angles(&r);
            p
        })
        .collect();
    let mut rng = simulate::rng(7);
    let frames: Vec<_> = (0..10)
        .map(|_| {
            let points = simulate::particles(&spec.volume, 2000, &mut rng);
            simulate::target_frame(&truth, &points, 0.1, 0.0, &mut rng).targets
        })
        .collect();
    let options = SelfCalibrationOptions {
        start_tolerance_px: band_px,
        ..SelfCalibrationOptions::default()
    };
    for run in 0..3 {
        let start = Instant::now();
        let result = self_calibrate(&rough, &frames, &options, &Cancel::new(), &mut |_| {})
            .expect("self-calibrates");
        println!(
            "{label}, run {run}: {:.2} s, {} rounds, outcome {:?}",
            start.elapsed().as_secs_f64(),
            result.report.rounds.len(),
            result.report.outcome
        );
    }
}
