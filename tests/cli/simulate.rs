//! `ptv simulate --frames N --flow ...`: a simulated sequence, then `ptv
//! track` on its targets, whose velocities must agree with the truth's
//! within the noise; bad sequence flags get one clear line.

use std::collections::HashMap;
use std::path::Path;

use nalgebra::Vector3;

use crate::common::{fails, ptv, succeeds, text};

/// One frame's truth: per camera, target row -> particle id; per id, its
/// velocity and acceleration.
struct Truth {
    id_of_target: Vec<HashMap<i64, u64>>,
    velocity: HashMap<u64, Vector3<f64>>,
    acceleration: HashMap<u64, Vector3<f64>>,
}

fn read_truth(path: &Path, cameras: usize) -> Truth {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let mut header = String::from("id,x,y,z,u,v,w,ax,ay,az");
    for c in 0..cameras {
        header.push_str(&format!(",t{c}"));
    }
    assert_eq!(lines.next(), Some(header.as_str()));
    let mut truth = Truth {
        id_of_target: vec![HashMap::new(); cameras],
        velocity: HashMap::new(),
        acceleration: HashMap::new(),
    };
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        let n = |i: usize| f[i].parse::<f64>().unwrap();
        let id: u64 = f[0].parse().unwrap();
        assert!(
            truth
                .velocity
                .insert(id, Vector3::new(n(4), n(5), n(6)))
                .is_none(),
            "id {id} twice in {}",
            path.display()
        );
        truth
            .acceleration
            .insert(id, Vector3::new(n(7), n(8), n(9)));
        for (c, map) in truth.id_of_target.iter_mut().enumerate() {
            let row: i64 = f[10 + c].parse().unwrap();
            if row >= 0 {
                map.insert(row, id);
            }
        }
    }
    truth
}

/// 300 particles in the Burgers vortex over 12 frames, 4 cameras, 0.1 px
/// of noise: `ptv track` on the targets must follow the true particles
/// (links between the same ids) with the true velocities.
///
/// The tolerance: the rows' `su,sv,sw` propagate the intersection's a
/// posteriori sigmas (8 image coordinates, 3 unknowns: 5 degrees of
/// freedom) through the quadratic fit over 5 frames, so a velocity error
/// over its sigma is Student's t with 5 degrees of freedom at worst, whose
/// RMS is sqrt(5/3) = 1.29. The fit's own bias on the curved paths, the
/// cubic term's 34/60 x''' (x''' ~ K³ r ≈ 1.1e-3 mm per frame³ in the
/// core, for the swirl of 0.3 mm a frame here, K = 0.047 rad a frame), is
/// 6e-4 mm per frame, a twentieth of the sigmas (about 0.015 mm per frame
/// per component here), so it adds under 1% to that RMS.
///
/// The accelerations: a quadratic fit over 5 frames has `σ_a = 2σ/√14`
/// where the velocity's `σ_v = σ/√10`, so `σ_a = 1.69 σ_v`; their RMS
/// error is at most 1.69 x 1.29 the velocities' sigmas' RMS. (The truth's
/// accelerations, under 0.01 mm per frame², are below that noise at this
/// speed: what a fit of 0.1 px positions can give.)
#[test]
fn a_simulated_sequence_is_tracked_with_its_true_velocities() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let frames = 12;
    let out = ptv(
        &[
            "simulate",
            "--cameras",
            "4",
            "--particles",
            "300",
            "--out",
            "sim",
            "--frames",
            &frames.to_string(),
            "--flow",
            "burgers",
            "--displacement",
            "0.3",
            "--noise",
            "0.1",
            "--no-images",
            "--seed",
            "4",
        ],
        d,
    );
    succeeds(&out);
    let stderr = text(&out.stderr);
    for name in [
        "cam1_targets.%05d.csv",
        "cam4_targets.%05d.csv",
        "truth.%05d.csv",
    ] {
        assert!(stderr.contains(name), "{name} not in {stderr}");
    }
    for f in 0..frames {
        assert!(d.join(format!("sim/cam4_targets.{f:05}.csv")).is_file());
        assert!(d.join(format!("sim/truth.{f:05}.csv")).is_file());
        assert!(!d.join(format!("sim/cam1.{f:05}.png")).exists());
    }
    // The largest speed the simulator reports is the tracker's limit.
    let max_velocity = stderr
        .split("speed at most ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap_or_else(|| panic!("no speed in {stderr}"))
        .to_owned();
    let speed: f64 = max_velocity.parse().unwrap();
    // Some particles left through the z faces (strain 0.00375 a frame)
    // and were replaced by new ids, which the links below must not join.
    let replaced: usize = stderr
        .split("; ")
        .last()
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no replaced count in {stderr}"));
    assert!(replaced > 0, "{stderr}");
    // The swirl (0.3) plus the strain's radial and axial speeds at the
    // volume's corners: a bound, loose by at most their sum.
    assert!((0.3..0.45).contains(&speed), "{speed}");

    let truths: Vec<Truth> = (0..frames)
        .map(|f| read_truth(&d.join(format!("sim/truth.{f:05}.csv")), 4))
        .collect();
    let patterns: Vec<String> = (1..=4)
        .map(|k| format!("sim/cam{k}_targets.%05d.csv"))
        .collect();
    let mut args = vec!["track", "--calibration", "sim/calibration.json"];
    for p in &patterns {
        args.extend(["--targets", p.as_str()]);
    }
    let range = format!("0..{}", frames - 1);
    args.extend([
        "--frames",
        range.as_str(),
        "--max-velocity",
        max_velocity.as_str(),
        "--min-cameras",
        "4",
    ]);
    let out = ptv(&args, d);
    let csv = succeeds(&out);

    // Per row: the true particle (all 4 targets of one id), the error of
    // its velocity over the sigma.
    let mut ids_of_trajectory: HashMap<u64, Vec<Option<u64>>> = HashMap::new();
    let (mut sum, mut count) = (0.0, 0usize);
    let (mut error_sq, mut speed_sq) = (0.0, 0.0);
    let (mut a_error_sq, mut a_sq, mut sigma_sq, mut a_count) = (0.0, 0.0, 0.0, 0usize);
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let n = |i: usize| f[i].parse::<f64>().unwrap();
        let trajectory: u64 = f[0].parse().unwrap();
        let frame: usize = f[1].parse().unwrap();
        let truth = &truths[frame];
        // The cameras that have a target (a particle recovered from the
        // images may have 3 of them, or 2).
        let ids: Vec<Option<u64>> = (0..4)
            .filter_map(|c| {
                let t = f[15 + c].parse::<i64>().unwrap();
                (t >= 0).then(|| truth.id_of_target[c].get(&t).copied())
            })
            .collect();
        let id = ids[0].filter(|_| ids.len() >= 2 && ids.iter().all(|i| *i == ids[0]));
        ids_of_trajectory.entry(trajectory).or_default().push(id);
        let Some(id) = id else { continue };
        let velocity = Vector3::new(n(5), n(6), n(7));
        let sigma = Vector3::new(n(11), n(12), n(13));
        let error = velocity - truth.velocity[&id];
        sum += error.component_div(&sigma).norm_squared();
        count += 3;
        error_sq += error.norm_squared();
        speed_sq += truth.velocity[&id].norm_squared();
        if let (Ok(ax), Ok(ay), Ok(az)) = (f[8].parse(), f[9].parse(), f[10].parse()) {
            let a = Vector3::new(ax, ay, az);
            a_error_sq += (a - truth.acceleration[&id]).norm_squared();
            a_sq += truth.acceleration[&id].norm_squared();
            sigma_sq += sigma.norm_squared();
            a_count += 1;
        }
    }
    let rms = (sum / count as f64).sqrt();
    let relative = (error_sq / speed_sq).sqrt();
    println!(
        "{} points, velocity errors over their sigmas: RMS {rms:.3}; RMS error {:.2}% of the RMS speed",
        count / 3,
        100.0 * relative
    );
    let a_rms = (a_error_sq / a_count as f64).sqrt();
    let sigma_rms = (sigma_sq / a_count as f64).sqrt();
    println!(
        "{a_count} accelerations: RMS error {a_rms:.2e} mm/frame², truth's RMS {:.2e}, velocity sigma RMS {sigma_rms:.2e}",
        (a_sq / a_count as f64).sqrt()
    );
    assert!(count / 3 > 300 * frames * 8 / 10, "{} points", count / 3);
    assert!(rms <= 1.3, "{rms}");
    assert!(
        a_rms <= 1.69 * 1.29 * sigma_rms,
        "{a_rms} against {sigma_rms}"
    );
    // Links: consecutive points of a trajectory are the same particle.
    let (mut links, mut wrong) = (0usize, 0usize);
    for ids in ids_of_trajectory.values() {
        for pair in ids.windows(2) {
            links += 1;
            if pair[0].is_none() || pair[0] != pair[1] {
                wrong += 1;
            }
        }
    }
    println!("{wrong} wrong links of {links}");
    assert!(wrong * 200 <= links, "{wrong} of {links} links wrong");
}

#[test]
fn bad_sequence_flags_get_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let base = [
        "simulate",
        "--cameras",
        "3",
        "--particles",
        "10",
        "--out",
        "x",
    ];
    let with = |extra: &[&str]| {
        let mut args = base.to_vec();
        args.extend(extra);
        ptv(&args, d)
    };
    fails(
        &with(&["--frames", "0", "--flow", "shear"]),
        &["--frames", "1 to 100000"],
    );
    fails(
        &with(&["--frames", "3", "--flow", "shear", "--displacement", "-1"]),
        &["--displacement", "positive"],
    );
    fails(
        &with(&["--frames", "3", "--flow", "burgers", "--displacement", "11"]),
        &["--displacement", "quarter", "at most 10"],
    );
    // --frames without --flow is a malformed command line (clap: exit 2).
    let out = with(&["--frames", "3"]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("--flow"),
        "{}",
        text(&out.stderr)
    );
}

/// With images: one PNG per camera and frame, of the sensor's size; the
/// truth keeps the particle count, the ids of frame 0 or new ones.
#[test]
fn a_sequence_writes_images_and_keeps_its_ids() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = ptv(
        &[
            "simulate",
            "--cameras",
            "2",
            "--particles",
            "50",
            "--out",
            "s",
            "--frames",
            "3",
            "--flow",
            "shear",
            "--displacement",
            "8",
        ],
        d,
    );
    succeeds(&out);
    for f in 0..3 {
        for c in 1..=2 {
            let image =
                ptv::formats::image::read_image(&d.join(format!("s/cam{c}.{f:05}.png")), None)
                    .unwrap();
            assert_eq!((image.width(), image.height()), (1280, 1024));
        }
        let truth = read_truth(&d.join(format!("s/truth.{f:05}.csv")), 2);
        assert_eq!(truth.velocity.len(), 50);
        let new = truth.velocity.keys().filter(|&&id| id >= 50).count();
        if f == 0 {
            assert_eq!(new, 0);
        }
        // Shear: u = gamma (y - c_y), the rest zero.
        for v in truth.velocity.values() {
            assert!(v.x.abs() <= 8.0 && v.y == 0.0 && v.z == 0.0, "{v}");
        }
    }
    // At 8 mm a frame at the y faces some of the 50 leave within 2 frames.
    let last = read_truth(&d.join("s/truth.00002.csv"), 2);
    assert!(last.velocity.keys().any(|&id| id >= 50), "no newcomer");
}
