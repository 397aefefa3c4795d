//! Correspondences on real data: OpenPTV's test_cavity frames 10001-10004
//! (four cameras looking into a water-filled cavity, real detections), side
//! by side with OpenPTV 0.3.2's own result in the golden file.
//!
//! The search parameters are OpenPTV's for this experiment
//! (`parameters/criteria.par`): depth Zmin..Zmax = -20..20 mm, unbounded in
//! X and Y as OpenPTV's search is, and an epipolar band of eps0 = 0.2 mm on
//! the image plane, i.e. 16.7 px with its 12 um pixels.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::{Point2, Point3};
use ptv::formats::{openptv, parse_targets, read_text};
use ptv::photogrammetry::correspond::{Matcher, MatchingParameters, Particle};
use ptv::photogrammetry::{intersect, Camera, Observation, Volume};
use serde_json::Value;

use crate::common::json_points;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/openptv");
const FRAMES: [&str; 4] = ["10001", "10002", "10003", "10004"];

fn cameras() -> Vec<Camera> {
    let base = Path::new(DATA).join("test_cavity");
    let oris: Vec<PathBuf> = (1..=4)
        .map(|k| base.join(format!("cal/cam{k}.tif.ori")))
        .collect();
    openptv::import(&base.join("parameters/ptv.par"), &oris).expect("test_cavity calibration")
}

fn matcher(cameras: &[Camera]) -> Matcher {
    let eps0_mm = 0.2;
    let parameters = MatchingParameters {
        tolerance: eps0_mm / cameras[0].sensor().pixel_size_x,
        volume: Some(Volume {
            min: Point3::new(f64::NEG_INFINITY, f64::NEG_INFINITY, -20.0),
            max: Point3::new(f64::INFINITY, f64::INFINITY, 20.0),
        }),
        ..MatchingParameters::default()
    };
    Matcher::new(cameras, &parameters).expect("valid parameters")
}

fn targets(frame: &str) -> Vec<Vec<ptv::photogrammetry::Target>> {
    (1..=4)
        .map(|k| {
            let path = Path::new(DATA).join(format!("test_cavity/img_orig/cam{k}.{frame}_targets"));
            parse_targets(&read_text(&path).unwrap(), &path.display().to_string()).unwrap()
        })
        .collect()
}

fn golden() -> Value {
    let text =
        std::fs::read_to_string(Path::new(DATA).join("golden/test_cavity_frames.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn counts(particles: &[Particle]) -> [usize; 3] {
    let mut counts = [0; 3];
    for p in particles {
        counts[4 - p.camera_count()] += 1;
    }
    counts
}

#[test]
fn test_cavity_frames_agree_with_openptv() {
    let cameras = cameras();
    let matcher = matcher(&cameras);
    let golden = golden();
    let mut all_differences = Vec::new();
    let mut all_sigmas = Vec::new();
    for frame in FRAMES {
        let particles = matcher.match_frame(&targets(frame)).unwrap();
        let expected = &golden["frames"][frame];
        let theirs: Vec<[i64; 4]> = expected["target_pnr_per_camera"]
            .as_array()
            .unwrap()
            .iter()
            .map(|g| std::array::from_fn(|k| g[k].as_i64().unwrap()))
            .collect();
        let their_points = json_points(&expected["xyz_mm"]);
        let ours: HashMap<[i64; 4], &Particle> = particles
            .iter()
            .map(|p| {
                (
                    std::array::from_fn(|k| p.targets[k].map_or(-1, |t| t as i64)),
                    p,
                )
            })
            .collect();
        let mut shared = 0;
        for (group, point) in theirs.iter().zip(&their_points) {
            if let Some(p) = ours.get(group) {
                shared += 1;
                for axis in 0..3 {
                    all_differences.push((p.position[axis] - point[axis]).abs());
                    all_sigmas.push(p.sigma[axis]);
                }
            }
        }
        // Where the two differ on a target, whose group fits the camera
        // model better (reprojection RMS of its least-squares intersection)?
        let frame_targets = targets(frame);
        let rms_of = |group: &[i64; 4]| {
            let observations: Vec<Observation> = (0..4)
                .filter(|&k| group[k] >= 0)
                .map(|k| {
                    let t = frame_targets[k][group[k] as usize];
                    Observation {
                        camera: k,
                        pixel: Point2::new(t.x, t.y),
                    }
                })
                .collect();
            intersect(&cameras, &observations)
                .map(|r| r.rms_px)
                .unwrap_or(f64::INFINITY)
        };
        let (mut conflicts, mut ours_better) = (0, 0);
        for group in &theirs {
            let holder = particles
                .iter()
                .find(|p| (0..4).any(|k| group[k] >= 0 && p.targets[k] == Some(group[k] as usize)));
            if let Some(p) = holder {
                let our_group: [i64; 4] =
                    std::array::from_fn(|k| p.targets[k].map_or(-1, |t| t as i64));
                let compatible =
                    (0..4).all(|k| group[k] < 0 || our_group[k] < 0 || group[k] == our_group[k]);
                if !compatible {
                    conflicts += 1;
                    if rms_of(&our_group) < rms_of(group) {
                        ours_better += 1;
                    }
                }
            }
        }
        println!(
            "frame {frame}: ours (quadruplets, triplets, pairs) {:?}, OpenPTV {}; {shared} of OpenPTV's {} groups found identically; \
             {conflicts} assign a target differently, ours with the lower reprojection RMS in {ours_better}",
            counts(&particles),
            expected["counts_quadruplets_triplets_pairs"],
            theirs.len()
        );
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let within = |k: f64| {
        all_differences
            .iter()
            .zip(&all_sigmas)
            .filter(|(d, s)| **d <= k * **s)
            .count() as f64
            / all_differences.len() as f64
    };
    let (w1, w2, w3) = (within(1.0), within(2.0), within(3.0));
    let (median_difference, median_sigma) = (
        median(&mut all_differences.clone()),
        median(&mut all_sigmas.clone()),
    );
    println!(
        "shared groups: median |difference| {median_difference:.4} mm, median sigma {median_sigma:.4} mm; within 1/2/3 sigma: {:.1}% / {:.1}% / {:.1}%",
        100.0 * w1,
        100.0 * w2,
        100.0 * w3
    );
    assert!(
        median_difference < median_sigma,
        "{median_difference} vs {median_sigma}"
    );
}
