//! `ptv track` run as a real process: particles of a known motion, from
//! `ptv match`'s particle files and from every camera's targets, come out
//! as trajectories with the motion's velocity; bad input gets one clear
//! line.

use nalgebra::{Point3, Rotation3, Vector3};
use ptv::formats;
use ptv::photogrammetry::correspond::Particle;
use ptv::photogrammetry::simulate::{self, RigSpec};

use crate::common::{fails, ptv, text};

/// 200 particles in the simulator's volume turning about the z axis by
/// 0.01 rad a frame (up to 0.57 mm a frame at the volume's corners) and
/// drifting 0.2 mm a frame along x, over 12 frames.
fn motion(frames: i64) -> Vec<Vec<Point3<f64>>> {
    let spec = RigSpec::convergent(4);
    let mut rng = simulate::rng(3);
    let inner = ptv::photogrammetry::Volume {
        min: spec.volume.min + Vector3::repeat(8.0),
        max: spec.volume.max - Vector3::repeat(8.0),
    };
    let starts = simulate::particles(&inner, 200, &mut rng);
    (0..frames)
        .map(|f| {
            let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), 0.01 * f as f64);
            starts
                .iter()
                .map(|p| turn * p + Vector3::new(0.2 * f as f64, 0.0, 0.0))
                .collect()
        })
        .collect()
}

/// One row of the trajectory CSV.
struct Row {
    trajectory: u64,
    frame: i64,
    position: Point3<f64>,
    velocity: Vector3<f64>,
    velocity_sigma: Vector3<f64>,
}

fn rows(csv: &str) -> Vec<Row> {
    let mut lines = csv.lines();
    let header = lines.next().unwrap();
    assert!(
        header.starts_with("trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras"),
        "{header}"
    );
    lines
        .map(|line| {
            let f: Vec<&str> = line.split(',').collect();
            let n = |i: usize| f[i].parse::<f64>().unwrap();
            Row {
                trajectory: f[0].parse().unwrap(),
                frame: f[1].parse().unwrap(),
                position: Point3::new(n(2), n(3), n(4)),
                velocity: Vector3::new(n(5), n(6), n(7)),
                velocity_sigma: Vector3::new(n(11), n(12), n(13)),
            }
        })
        .collect()
}

/// Every particle one trajectory of all frames (`lost` points may be
/// missing, bridged as gaps), and the velocities the motion's
/// (`omega ẑ × (p - drift·f) + drift`) at the scatter the rows' sigmas
/// report: the RMS of the errors over the sigmas at most `t_rms`.
fn check(csv: &str, frames: i64, particles: usize, lost: usize, t_rms: f64) {
    let rows = rows(csv);
    let trajectories = rows.iter().map(|r| r.trajectory).max().map_or(0, |m| m + 1);
    assert_eq!(
        trajectories as usize, particles,
        "one trajectory per particle"
    );
    let all = particles * frames as usize;
    assert!(
        rows.len() <= all && rows.len() + lost >= all,
        "{} of {all} points tracked",
        rows.len()
    );
    check_velocities(&rows, t_rms);
}

/// The velocities the motion's (`omega ẑ × (p - drift·f) + drift`) at
/// the scatter the rows' sigmas report: the RMS of the errors over the
/// sigmas at most `t_rms`.
fn check_velocities(rows: &[Row], t_rms: f64) {
    let drift = Vector3::new(0.2, 0.0, 0.0);
    let mut sum = 0.0;
    let mut worst: f64 = 0.0;
    for r in rows {
        let turned = r.position.coords - drift * r.frame as f64;
        let truth = Vector3::new(-0.01 * turned.y, 0.01 * turned.x, 0.0) + drift;
        let normalised = (r.velocity - truth).component_div(&r.velocity_sigma);
        sum += normalised.norm_squared();
        worst = worst.max(normalised.amax());
    }
    let rms = (sum / (3 * rows.len()) as f64).sqrt();
    println!("velocity errors over their sigmas: RMS {rms:.3}, largest {worst:.2}");
    assert!(rms <= t_rms, "{rms}");
}

#[test]
fn particle_files_become_trajectories() {
    let dir = tempfile::tempdir().unwrap();
    let frames = motion(12);
    let sigma = 0.002;
    for (f, points) in frames.iter().enumerate() {
        // Reverse the order every other frame: indices tell nothing.
        let mut ordered: Vec<Particle> = points
            .iter()
            .map(|p| Particle {
                position: *p,
                sigma: Vector3::repeat(sigma),
                rms_px: 0.1,
                targets: vec![Some(0), None],
            })
            .collect();
        if f % 2 == 1 {
            ordered.reverse();
        }
        std::fs::write(
            dir.path().join(format!("p.{f:03}.csv")),
            formats::csv::format_particles(&ordered, 2),
        )
        .unwrap();
    }
    let out = ptv(
        &[
            "track",
            "--particles",
            "p.%03d.csv",
            "--frames",
            "0..11",
            "--max-velocity",
            "1",
            "--ptv-is",
            "res",
        ],
        dir.path(),
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
    // OpenPTV's linkage files: every particle linked both ways between
    // adjacent frames, to the row of the same particle (the files' rows
    // follow each frame's input order, reversed every other frame, so the
    // same particle is row 199 - i next door), none
    // before the first frame (-1) or after the last (-2).
    let linkage = |f: usize| -> Vec<(i64, i64, Point3<f64>)> {
        let text = std::fs::read_to_string(dir.path().join(format!("res/ptv_is.{f}"))).unwrap();
        let mut lines = text.lines();
        assert_eq!(lines.next(), Some("200"));
        lines
            .map(|l| {
                let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
                (v[0] as i64, v[1] as i64, Point3::new(v[2], v[3], v[4]))
            })
            .collect()
    };
    let files: Vec<_> = (0..12).map(linkage).collect();
    for (f, rows) in files.iter().enumerate() {
        for (i, &(prev, next, _)) in rows.iter().enumerate() {
            // The order flips between adjacent frames: row 199 - i there.
            let same = 199 - i as i64;
            assert_eq!(prev, if f == 0 { -1 } else { same }, "frame {f} row {i}");
            assert_eq!(next, if f == 11 { -2 } else { same }, "frame {f} row {i}");
        }
    }
    let stderr = text(&out.stderr);
    assert!(stderr.contains("200 trajectories"), "{stderr}");
    // Exact positions with a declared sigma: the errors are the fit's
    // bias on the circle (omega³ r / 6 · 34/10 ~ 3e-5 mm per frame at
    // r = 57 mm), a twentieth of the sigmas (0.002 / sqrt(10) = 6e-4).
    check(text(&out.stdout), 12, 200, 0, 0.1);
}

#[test]
fn targets_are_matched_then_tracked() {
    let dir = tempfile::tempdir().unwrap();
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().unwrap();
    std::fs::write(
        dir.path().join("cal.json"),
        formats::calibration::to_json(&cameras),
    )
    .unwrap();
    let frames = motion(10);
    let mut rng = simulate::rng(5);
    for (f, points) in frames.iter().enumerate() {
        let frame = simulate::target_frame(&cameras, points, 0.05, 0.0, &mut rng);
        for (c, targets) in frame.targets.iter().enumerate() {
            std::fs::write(
                dir.path().join(format!("cam{}.{f}.csv", c + 1)),
                formats::csv::format_targets(targets),
            )
            .unwrap();
        }
    }
    let mut args = vec!["track", "--calibration", "cal.json"];
    let patterns: Vec<String> = (1..=4).map(|k| format!("cam{k}.%d.csv")).collect();
    for p in &patterns {
        args.extend(["--targets", p.as_str()]);
    }
    args.extend([
        "--frames",
        "0..9",
        "--max-velocity",
        "1",
        "--min-cameras",
        "4",
        "--no-recovery",
    ]);
    let out = ptv(&args, dir.path());
    assert!(out.status.success(), "{}", text(&out.stderr));
    let csv = text(&out.stdout);
    // Every row names its particle's 4 targets (no particle is recovered
    // from fewer: `--no-recovery`).
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        assert_eq!(f.len(), 15 + 4, "{line}");
        assert_eq!(f[14], "4", "{line}");
    }
    // Matching in all 4 cameras loses a few particles a frame (26 of
    // 2,000 points here: near the edges of the fields of view, or in
    // crowded bands); every loss is a one-frame gap the tracker bridges,
    // so each particle is still one trajectory. 2% may be lost.
    // The intersection's sigmas are a posteriori, from 8 image coordinates
    // and 3 unknowns: a normalised error is then Student's t with 5
    // degrees of freedom, whose RMS is sqrt(5/3) = 1.29 (the fit's
    // averaging over 5 points brings it nearer 1).
    check(csv, 10, 200, 40, 5f64.sqrt() / 3f64.sqrt());

    // One camera's file of frame 4 gone: the range is refused, naming the
    // file; with --allow-gaps frame 4 is a gap the trajectories bridge.
    std::fs::remove_file(dir.path().join("cam3.4.csv")).unwrap();
    fails(
        &ptv(&args, dir.path()),
        &[
            "--frames",
            "0..9",
            "frame 4 misses",
            "cam3.4.csv",
            "--allow-gaps",
        ],
    );
    args.push("--allow-gaps");
    let out = ptv(&args, dir.path());
    assert!(out.status.success(), "{}", text(&out.stderr));
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("1 without files") && stderr.contains("cam3.4.csv"),
        "{stderr}"
    );
    let rows = rows(text(&out.stdout));
    assert!(rows.iter().all(|r| r.frame != 4));
    // The gap is bridged: a particle breaks only where matching also lost
    // it next to the gap (frame 3 or 5, a gap of 2 frames over
    // --max-gap 1). With up to 2% of points lost (above), that is about
    // 200 x 2 x 2% = 8 breaks; twice that at most.
    let trajectories = rows.iter().map(|r| r.trajectory).max().unwrap() + 1;
    assert!((200..=216).contains(&trajectories), "{trajectories}");
}

/// Writes the calibration and each frame's targets of `motion(frames)`,
/// each image lost with probability `drop`, into `dir`; returns the
/// arguments of `ptv track` on them.
fn lossy_targets(dir: &std::path::Path, frames: i64, drop: f64) -> Vec<String> {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().unwrap();
    std::fs::write(
        dir.join("cal.json"),
        formats::calibration::to_json(&cameras),
    )
    .unwrap();
    let mut rng = simulate::rng(7);
    for (f, points) in motion(frames).iter().enumerate() {
        let frame = simulate::target_frame(&cameras, points, 0.05, drop, &mut rng);
        for (c, targets) in frame.targets.iter().enumerate() {
            std::fs::write(
                dir.join(format!("cam{}.{f}.csv", c + 1)),
                formats::csv::format_targets(targets),
            )
            .unwrap();
        }
    }
    let mut args: Vec<String> = ["track", "--calibration", "cal.json"]
        .map(String::from)
        .to_vec();
    for k in 1..=4 {
        args.extend(["--targets".into(), format!("cam{k}.%d.csv")]);
    }
    args.extend(
        [
            "--frames",
            &format!("0..{}", frames - 1),
            "--max-velocity",
            "1",
        ]
        .map(String::from),
    );
    args
}

#[test]
fn particles_the_matching_missed_are_recovered_from_the_images() {
    // 10% of the images lost, and the correspondences asked for all 4
    // cameras: a third of the particles (1 - 0.9^4) are not matched in a
    // frame, and two frames in a row (one in nine) end a trajectory.
    // The image-space recovery finds a particle again from its 3 (or 2)
    // images near the trajectory's prediction.
    let dir = tempfile::tempdir().unwrap();
    let mut args = lossy_targets(dir.path(), 12, 0.1);
    args.extend(["--min-cameras", "4", "--max-gap", "0"].map(String::from));
    let run = |extra: &[&str]| {
        let mut args: Vec<&str> = args.iter().map(String::as_str).collect();
        args.extend(extra);
        let out = ptv(&args, dir.path());
        assert!(out.status.success(), "{}", text(&out.stderr));
        (rows(text(&out.stdout)), text(&out.stderr).to_string())
    };
    let (plain, plain_log) = run(&["--no-recovery"]);
    let (recovered, log) = run(&[]);
    let trajectories = |rows: &[Row]| rows.iter().map(|r| r.trajectory).max().map_or(0, |m| m + 1);
    println!("{plain_log}{log}");
    assert!(plain_log.contains(" 0 recovered"), "{plain_log}");
    // Without recovery and without gap bridging, the particles break into
    // pieces, most too short to report (measured: 236 trajectories of 3
    // points or more hold 1,067 of the 1,578 particles matched, 4.5 points
    // each); with it, 388 particles are recovered and 174 trajectories
    // hold 1,667 points, 9.6 each of 12 frames.
    let mean = |rows: &[Row]| rows.len() as f64 / trajectories(rows) as f64;
    assert!(
        recovered.len() as f64 > 1.4 * plain.len() as f64,
        "{} points with recovery, {} without",
        recovered.len(),
        plain.len()
    );
    assert!(
        mean(&recovered) > 1.6 * mean(&plain),
        "mean length {} with recovery, {} without",
        mean(&recovered),
        mean(&plain)
    );
    // Velocities at the scatter their sigmas say. A normalised error is
    // Student's t: RMS sqrt(5/3) = 1.29 for a 4-camera point (5 degrees of
    // freedom), sqrt(3) = 1.73 for a recovered 3-camera one (3); a
    // quarter of the points recovered gives an RMS of about 1.4, which
    // the fit's averaging over 5 points brings nearer 1 (measured 0.98).
    check_velocities(&recovered, 1.5);
}

#[test]
fn bad_input_gets_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    let base = ["track", "--frames", "0..3", "--max-velocity", "1"];
    let with = |extra: &[&str]| {
        let mut args = base.to_vec();
        args.extend(extra);
        ptv(&args, dir.path())
    };
    fails(
        &with(&["--particles", "none.%d.csv"]),
        &["--particles", "none.%d.csv", "matches no file"],
    );
    std::fs::write(dir.path().join("p.0.csv"), "x,y,z\n1,2,3\n").unwrap();
    // Frames 1..3 missing: named, and --allow-gaps offered.
    fails(
        &with(&["--particles", "p.%d.csv", "--sigma", "0.01"]),
        &[
            "not contiguous",
            "frames 1..3 miss",
            "p.1.csv",
            "p.3.csv",
            "--allow-gaps",
        ],
    );
    for f in [1, 3] {
        std::fs::write(dir.path().join(format!("p.{f}.csv")), "x,y,z\n1,2,3\n").unwrap();
    }
    fails(
        &with(&["--particles", "p.%d.csv", "--sigma", "0.01"]),
        &["frame 2 misses", "p.2.csv"],
    );
    std::fs::write(dir.path().join("p.2.csv"), "x,y,z\n1,2,3\n").unwrap();
    fails(
        &with(&["--particles", "p.%d.csv"]),
        &["--sigma", "no sx,sy,sz"],
    );
    fails(
        &with(&["--particles", "p.%d.csv", "--max-gap", "3"]),
        &["max_gap", "0..=2"],
    );
    fails(
        &with(&["--particles", "p.%d.csv", "--sigma", "-1"]),
        &["--sigma", "positive"],
    );
}

/// Particles entering mid-sequence whose second point is lost: forward,
/// a trajectory of one point bridges no gap, so each starts at its third
/// point and its first is dropped; backward tracking (the default)
/// takes the first back, and the summary says what it added. With
/// `--no-backward`, the forward pass's rows; `--backward` (kept for
/// scripts) is the default.
#[test]
fn backward_tracking_takes_back_late_starts() {
    let dir = tempfile::tempdir().unwrap();
    let frames = motion(12);
    let sigma = 0.002;
    // Every 10th particle enters at frame 3..=7 and misses the frame after.
    let birth = |i: usize| (i % 10 == 0).then_some(3 + (i / 10) % 5);
    let mut total = 0;
    for (f, points) in frames.iter().enumerate() {
        let particles: Vec<Particle> = points
            .iter()
            .enumerate()
            .filter(|(i, _)| !matches!(birth(*i), Some(b) if f < b || f == b + 1))
            .map(|(_, p)| Particle {
                position: *p,
                sigma: Vector3::repeat(sigma),
                rms_px: 0.1,
                targets: vec![Some(0), None],
            })
            .collect();
        total += particles.len();
        std::fs::write(
            dir.path().join(format!("p.{f:03}.csv")),
            formats::csv::format_particles(&particles, 2),
        )
        .unwrap();
    }
    let entering = (0..200).filter(|&i| birth(i).is_some()).count();
    let run = |extra: &[&str]| {
        let mut args = vec![
            "track",
            "--particles",
            "p.%03d.csv",
            "--frames",
            "0..11",
            "--max-velocity",
            "1",
        ];
        args.extend_from_slice(extra);
        let out = ptv(&args, dir.path());
        assert!(out.status.success(), "{}", text(&out.stderr));
        (rows(text(&out.stdout)), text(&out.stderr).to_string())
    };
    let (forward, stderr) = run(&["--no-backward"]);
    assert!(stderr.contains("backward tracking off"), "{stderr}");
    assert_eq!(forward.len(), total - entering, "the entering points lost");
    let (both, stderr) = run(&[]);
    let (again, again_stderr) = run(&["--backward"]);
    assert_eq!((again.len(), &again_stderr), (both.len(), &stderr));
    assert!(
        stderr.contains(&format!(
            "backward tracking added {entering} points before trajectories' starts ({entering} trajectories lengthened, 0 joined"
        )),
        "{stderr}"
    );
    assert_eq!(both.len(), total, "every point in a trajectory");
    assert!(stderr.contains("200 trajectories"), "{stderr}");
    // The refitted velocities as exact as the others (the bound of
    // particle_files_become_trajectories: the fit's bias on the circle is
    // a small fraction of the sigmas, at the one-sided windows of the new
    // first points too).
    check_velocities(&both, 0.1);
}
