//! Tracking in the service (issue 15): a simulated sequence of moving
//! particles, uploaded out of order by concurrent clients, is tracked as
//! its frames complete and gives exactly the trajectories of `ptv track`
//! on the same targets, the image-space recovery included (particles the
//! correspondences missed, found again in the stored targets); the same
//! after a kill -9 mid-tracking and a restart (the replay recovers
//! identically), and with two `ptv worker` processes one of which is
//! killed while it holds the run (the other takes the run's lease over),
//! and across a failed frame (a gap in both); a re-run with
//! other settings is a new run next to the old one, and without the
//! recovery gives the core's tracker's trajectories over the stored
//! particles; bad settings and queries are refused.
//!
//! Those runs are forward only (`"backward": false`, as `ptv track
//! --no-backward`); a run with `"backward": true` (the default) gives `ptv
//! track`'s trajectories over the stored particles.
//!
//! The comparisons are exact (no tolerance): the service runs the core's
//! deterministic tracker on the particles and targets it stored, and `ptv
//! track` matches the same target files (the uploads' CSV, shortest
//! round-trip float text) with the same parameters and tracks them, or the
//! test reads the stored particles back as CSV and runs the same tracker.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use nalgebra::{Point3, Vector3};
use rand::seq::SliceRandom;
use serde_json::{json, Value};

use ptv::formats;
use ptv::photogrammetry::simulate::{self, TargetFrame};
use ptv::photogrammetry::track::{self, ParticlePosition, TrackingParameters, Trajectory};

use crate::helpers::{
    open_database, rig, sequence_body, status_and_json, targets_form, upload, wait_for_sequence,
    worker_pid, Rig, ServiceProcess, WorkerProcess, PATIENCE,
};

/// Particles per frame.
const PARTICLES: usize = 400;
/// The particles' displacement per frame (mm): about 2.3 mm, 0.3 of the
/// mean spacing of 400 particles in the rig's 80 x 80 x 40 mm volume
/// (8.6 mm), the middle of issue 15's 0.2..0.5.
const VELOCITY: Vector3<f64> = Vector3::new(2.0, 1.0, 0.5);
/// The tracking's velocity limit (mm per frame), above the true speed.
const MAX_VELOCITY: f64 = 3.0;

/// The particles of every frame, moving at [`VELOCITY`] through the
/// volume and re-entering it on the other side (a particle that leaves
/// is a new one), imaged with 0.05 px noise and 5% of images lost.
pub(crate) fn moving_frames(rig: &Rig, frames: usize, seed: u64) -> Vec<TargetFrame> {
    let mut rng = simulate::rng(seed);
    let start = simulate::particles(&rig.volume, PARTICLES, &mut rng);
    let (min, max) = (rig.volume.min, rig.volume.max);
    let size = max - min;
    (0..frames)
        .map(|f| {
            let points: Vec<Point3<f64>> = start
                .iter()
                .map(|p| {
                    let moved = p - min + VELOCITY * f as f64;
                    min + Vector3::from_fn(|i, _| moved[i].rem_euclid(size[i]))
                })
                .collect();
            simulate::target_frame(&rig.cameras, &points, 0.05, 0.05, &mut rng)
        })
        .collect()
}

/// A service to talk to: its address and a client.
struct Api {
    address: String,
    client: reqwest::Client,
}

impl Api {
    /// The API of the server at `address` (an in-process app's, or a
    /// child process's for the crash test: hence not `TestApp`'s helpers).
    fn at(address: &str) -> Api {
        Api {
            address: address.to_owned(),
            client: reqwest::Client::new(),
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}/api/v1{path}", self.address)
    }

    /// A POST, sent again after `Retry-After` while the answer is a 503
    /// (the database busy for now: several processes on one SQLite file,
    /// on a loaded machine), as a client does, within [`PATIENCE`].
    async fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        let start = Instant::now();
        loop {
            let response = self
                .client
                .post(self.url(path))
                .json(body)
                .send()
                .await
                .unwrap();
            let retry_after = response
                .headers()
                .get("retry-after")
                .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
            let (status, body) = status_and_json(response).await;
            match retry_after {
                Some(secs) if status == 503 && start.elapsed() < PATIENCE => {
                    tokio::time::sleep(Duration::from_secs(secs.min(5))).await;
                }
                _ => return (status, body),
            }
        }
    }

    async fn get(&self, path: &str) -> (u16, Value) {
        status_and_json(self.client.get(self.url(path)).send().await.unwrap()).await
    }

    async fn text(&self, path: &str) -> String {
        let response = self.client.get(self.url(path)).send().await.unwrap();
        assert_eq!(response.status().as_u16(), 200, "{path}");
        response.text().await.unwrap()
    }

    /// Waits until the sequence's tracking has taken frame `frame`.
    async fn wait_tracked_through(&self, sequence: i64, frame: i64) {
        let start = Instant::now();
        loop {
            let (_, body) = self.get(&format!("/sequences/{sequence}")).await;
            if body["tracking"]["tracked_through"].as_i64().unwrap_or(-1) >= frame {
                return;
            }
            assert!(start.elapsed() < PATIENCE, "tracking did not start: {body}");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }

    /// A calibration of the rig and a sequence on it with `tracking`.
    async fn tracked_sequence(&self, rig: &Rig, tracking: Value) -> i64 {
        let response = self
            .client
            .post(self.url("/calibrations"))
            .body(formats::calibration::to_json(&rig.cameras))
            .send()
            .await
            .unwrap();
        let (status, body) = status_and_json(response).await;
        assert_eq!(status, 201, "{body}");
        let mut request = sequence_body(body["id"].as_i64().unwrap(), &rig.volume, false);
        request["tracking"] = tracking;
        let (status, body) = self.post("/sequences", &request).await;
        assert_eq!(status, 201, "{body}");
        assert_eq!(body["tracking"]["state"], "tracking", "{body}");
        body["id"].as_i64().unwrap()
    }

    /// Uploads `frames` (frame number, targets) with `clients` concurrent
    /// clients, each taking every `clients`-th of them.
    async fn upload_concurrently(
        &self,
        sequence: i64,
        frames: &[(i64, &TargetFrame)],
        clients: usize,
    ) {
        let uploads = (0..clients).map(|c| {
            let client = reqwest::Client::new();
            let mine: Vec<_> = frames.iter().skip(c).step_by(clients).collect();
            async move {
                for (frame, targets) in mine {
                    let (status, body) = upload(
                        &client,
                        &self.address,
                        sequence,
                        targets_form(*frame, targets),
                    )
                    .await;
                    assert_eq!(status, 202, "frame {frame}: {body}");
                }
            }
        });
        futures_util::future::join_all(uploads).await;
    }

    /// Uploads every frame of `frames` (numbered from 0) with 2 concurrent
    /// clients, then [`Api::finish`]es the sequence; the run's view.
    async fn upload_all_and_finish(&self, sequence: i64, frames: &[TargetFrame]) -> Value {
        let order: Vec<(i64, &TargetFrame)> = frames
            .iter()
            .enumerate()
            .map(|(f, t)| (f as i64, t))
            .collect();
        self.upload_concurrently(sequence, &order, 2).await;
        self.finish(sequence).await
    }

    /// The sequence's trajectories as CSV rows, asserted to be `ptv track
    /// --targets`'s on all of `frames` (recovery on), row for row; and
    /// how many particles `ptv track` recovered.
    async fn tracked_as_ptv_track(
        &self,
        sequence: i64,
        rig: &Rig,
        frames: &[TargetFrame],
    ) -> (Vec<String>, usize) {
        let csv = self
            .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
            .await;
        let lines: Vec<String> = csv.lines().map(str::to_owned).collect();
        let all: Vec<Option<&TargetFrame>> = frames.iter().map(Some).collect();
        let (expected, recovered) = ptv_track_targets(rig, &all, MAX_VELOCITY, &["--no-backward"]);
        assert_same_rows(&lines, &expected);
        (lines, recovered)
    }

    /// Says the sequence is complete and waits for its run to finish; the
    /// run's view.
    async fn finish(&self, sequence: i64) -> Value {
        wait_for_sequence(&self.client, &self.address, sequence).await;
        let (status, body) = self
            .post(
                &format!("/sequences/{sequence}/tracking/finish"),
                &json!({}),
            )
            .await;
        assert_eq!(status, 202, "{body}");
        let start = Instant::now();
        loop {
            let (status, body) = self.get(&format!("/sequences/{sequence}")).await;
            assert_eq!(status, 200, "{body}");
            match body["tracking"]["state"].as_str() {
                Some("finished") => return body["tracking"].clone(),
                Some("tracking") => {}
                _ => panic!("tracking did not finish: {body}"),
            }
            assert!(start.elapsed() < PATIENCE, "tracking still runs: {body}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// The stored particles of every frame, as the CSV route gives them.
    async fn particles(&self, sequence: i64, frames: i64) -> Vec<Vec<formats::csv::ParticleRow>> {
        self.particle_tables(sequence, frames)
            .await
            .iter()
            .map(|text| formats::csv::parse_particles(text, "particles").unwrap())
            .collect()
    }

    /// Every frame's particle CSV.
    async fn particle_tables(&self, sequence: i64, frames: i64) -> Vec<String> {
        let mut all = Vec::new();
        for frame in 0..frames {
            all.push(
                self.text(&format!(
                    "/sequences/{sequence}/frames/{frame}/particles?format=csv"
                ))
                .await,
            );
        }
        all
    }
}

/// The core's trajectories over the frames' particles in order.
fn core_trajectories(
    particles: &[Vec<formats::csv::ParticleRow>],
    parameters: TrackingParameters,
) -> Vec<Trajectory> {
    let frames = particles.iter().enumerate().map(|(f, rows)| {
        (
            f as i64,
            rows.iter()
                .map(|r| {
                    ParticlePosition::seen_by(
                        r.position,
                        r.sigma.expect("the service's CSV has sigmas"),
                        r.targets.iter().flatten().count(),
                    )
                })
                .collect(),
        )
    });
    track::track(frames, parameters).unwrap()
}

/// `ptv track --particles` over the frames' particle tables (frames 0..),
/// with `--max-velocity` and `extra` flags: its CSV rows sorted by
/// trajectory and frame, after its header.
fn ptv_track(tables: &[String], max_velocity: f64, extra: &[&str]) -> Vec<String> {
    let dir = tempfile::tempdir().unwrap();
    for (frame, text) in tables.iter().enumerate() {
        std::fs::write(dir.path().join(format!("p.{frame}.csv")), text).unwrap();
    }
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_ptv"))
        .arg("track")
        .arg("--particles")
        .arg(dir.path().join("p.%d.csv"))
        .args(["--frames", &format!("0..{}", tables.len() - 1)])
        .args(["--max-velocity", &max_velocity.to_string()])
        .args(extra)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    sorted_rows(&String::from_utf8(output.stdout).unwrap())
}

/// `ptv track --calibration --targets` (with the image-space recovery, its
/// default) over the frames' targets as the test uploads them (frames 0..;
/// `None`: no files, a gap, with `--allow-gaps`), matched with the
/// sequence's volume and `--max-velocity`, plus `extra` flags: its CSV rows
/// sorted by trajectory and frame after its header, and how many particles
/// it recovered (its summary on stderr).
fn ptv_track_targets(
    rig: &Rig,
    frames: &[Option<&TargetFrame>],
    max_velocity: f64,
    extra: &[&str],
) -> (Vec<String>, usize) {
    let dir = tempfile::tempdir().unwrap();
    let calibration = dir.path().join("calibration.json");
    std::fs::write(&calibration, formats::calibration::to_json(&rig.cameras)).unwrap();
    for (frame, targets) in frames.iter().enumerate() {
        let Some(targets) = targets else { continue };
        for (camera, targets) in targets.targets.iter().enumerate() {
            std::fs::write(
                dir.path().join(format!("cam{camera}.{frame}.csv")),
                formats::csv::format_targets(targets),
            )
            .unwrap();
        }
    }
    let v = &rig.volume;
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_ptv"));
    command.arg("track").arg("--calibration").arg(&calibration);
    for camera in 0..rig.cameras.len() {
        command
            .arg("--targets")
            .arg(dir.path().join(format!("cam{camera}.%d.csv")));
    }
    let output = command
        .args(["--frames", &format!("0..{}", frames.len() - 1)])
        .args(["--max-velocity", &max_velocity.to_string()])
        .arg(format!(
            "--volume={},{},{},{},{},{}",
            v.min.x, v.max.x, v.min.y, v.max.y, v.min.z, v.max.z
        ))
        .args(extra)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    // "... N particles and M recovered from the images; ..."
    let recovered = stderr
        .split(" recovered from the images")
        .next()
        .and_then(|head| head.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no recovered count in {stderr}"));
    (
        sorted_rows(&String::from_utf8(output.stdout).unwrap()),
        recovered,
    )
}

/// A trajectory CSV's lines, its rows sorted by trajectory and frame after
/// its header.
fn sorted_rows(text: &str) -> Vec<String> {
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let header = lines.remove(0);
    lines.sort_by_key(|line| {
        let mut fields = line.split(',');
        (
            fields.next().unwrap().parse::<u64>().unwrap(),
            fields.next().unwrap().parse::<i64>().unwrap(),
        )
    });
    lines.insert(0, header);
    lines
}

/// A trajectory CSV row: trajectory, frame, u and the targets `t0,...`.
struct CsvPoint {
    trajectory: u64,
    frame: i64,
    u: f64,
    targets: String,
}

/// The rows of a trajectory CSV (after its header).
fn csv_points(lines: &[String]) -> Vec<CsvPoint> {
    lines[1..]
        .iter()
        .map(|line| {
            let fields: Vec<&str> = line.split(',').collect();
            CsvPoint {
                trajectory: fields[0].parse().unwrap(),
                frame: fields[1].parse().unwrap(),
                u: fields[5].parse().unwrap(),
                targets: fields[15..].join(","),
            }
        })
        .collect()
}

/// A particle's targets as the CSV's `t0,t1,...` columns.
fn targets_columns(targets: &[Option<usize>]) -> String {
    targets
        .iter()
        .map(|t| t.map_or("-1".to_owned(), |t| t.to_string()))
        .collect::<Vec<_>>()
        .join(",")
}

/// A CSV number, NaN as written by `{:?}`, an empty field as `None`.
/// The service's CSV rows are `ptv track`'s, one for one.
fn assert_same_rows(service: &[impl AsRef<str>], cli: &[String]) {
    assert_eq!(service.len(), cli.len(), "rows: service against ptv track");
    for (k, (service, cli)) in service.iter().zip(cli).enumerate() {
        assert_eq!(service.as_ref(), cli, "row {k}");
    }
}

fn number(field: &str) -> Option<f64> {
    (!field.is_empty()).then(|| field.parse::<f64>().unwrap())
}

/// Two values equal to the bit (NaN equal to NaN).
fn same(a: Option<f64>, b: Option<f64>) -> bool {
    match (a, b) {
        (Some(a), Some(b)) => a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
        (None, None) => true,
        _ => false,
    }
}

/// Checks the service's trajectory CSV against the core's trajectories,
/// field by field, with the targets from the frames' particles.
fn assert_same_trajectories(
    csv: &str,
    expected: &[Trajectory],
    particles: &[Vec<formats::csv::ParticleRow>],
) {
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "trajectory,frame,x,y,z,u,v,w,ax,ay,az,su,sv,sw,cameras,t0,t1,t2,t3"
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let points: Vec<_> = expected.iter().flat_map(|t| &t.points).collect();
    assert_eq!(rows.len(), points.len(), "points: service against core");
    for (row, p) in rows.iter().zip(points) {
        let context = format!("{row:?} against {p:?}");
        assert_eq!(row.len(), 19, "{context}");
        assert_eq!(row[0].parse::<u64>().unwrap(), p.trajectory, "{context}");
        assert_eq!(row[1].parse::<i64>().unwrap(), p.frame, "{context}");
        let d = &p.derivatives;
        let expected_numbers = [
            Some(p.position.x),
            Some(p.position.y),
            Some(p.position.z),
            Some(d.velocity.x),
            Some(d.velocity.y),
            Some(d.velocity.z),
            d.acceleration.map(|a| a.x),
            d.acceleration.map(|a| a.y),
            d.acceleration.map(|a| a.z),
            Some(d.velocity_sigma.x),
            Some(d.velocity_sigma.y),
            Some(d.velocity_sigma.z),
        ];
        for (k, e) in expected_numbers.iter().enumerate() {
            assert!(same(number(row[2 + k]), *e), "column {}: {context}", 2 + k);
        }
        let particle = &particles[p.frame as usize][p.particle];
        let targets: Vec<Option<usize>> = row[15..]
            .iter()
            .map(|t| usize::try_from(t.parse::<i64>().unwrap()).ok())
            .collect();
        assert_eq!(targets, particle.targets, "{context}");
        let seen = particle.targets.iter().flatten().count();
        assert_eq!(row[14].parse::<usize>().unwrap(), seen, "{context}");
    }
}

/// Sanity of the simulated flow's trajectories (CSV rows): most particles
/// are in long trajectories, and the median velocity is the true one
/// within a few of its reported standard deviations.
fn assert_plausible(points: &[CsvPoint], frames: usize) {
    // Particles found per frame are about PARTICLES (4 cameras, 5% of
    // images lost: nearly all are seen in 3 or more); a particle re-enters
    // the volume every 40 frames or so (80 mm at 2 mm per frame), so most
    // trajectories are long.
    assert!(
        points.len() as f64 > 0.8 * (PARTICLES * frames) as f64,
        "{} points in trajectories",
        points.len()
    );
    let trajectories: std::collections::HashSet<u64> =
        points.iter().map(|p| p.trajectory).collect();
    let mean_length = points.len() as f64 / trajectories.len() as f64;
    assert!(mean_length > 10.0, "mean trajectory length {mean_length}");
    let mut u: Vec<f64> = points
        .iter()
        .map(|p| p.u)
        .filter(|u| u.is_finite())
        .collect();
    u.sort_by(f64::total_cmp);
    let median = u[u.len() / 2];
    // The fit's velocity sigma for 0.05 px of image noise is about 0.01
    // mm per frame; 0.05 bounds the median's error with room for the
    // linking's few wrong links.
    assert!(
        (median - VELOCITY.x).abs() < 0.05,
        "median u {median} against {}",
        VELOCITY.x
    );
}

const FRAMES: usize = 200;

#[tokio::test]
async fn a_sequence_uploaded_out_of_order_by_four_clients_is_tracked_as_ptv_track_tracks_it() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let frames = moving_frames(&rig, FRAMES, 15);
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "backward": false}),
        )
        .await;
    let mut order: Vec<(i64, &TargetFrame)> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64, t))
        .collect();
    order.shuffle(&mut simulate::rng(16));
    api.upload_concurrently(sequence, &order, 4).await;
    let run = api.finish(sequence).await;
    assert_eq!(run["tracked_through"], FRAMES as i64 - 1, "{run}");
    assert_eq!(run["settings"]["recovery"], true, "{run}");

    // `ptv track` on the same targets, with its default image-space
    // recovery, writes the same CSV, row for row once its rows (written as
    // they become final) are sorted: the same particles matched, the same
    // particles recovered, the same links, the same numbers to the bit.
    let (lines, recovered) = api.tracked_as_ptv_track(sequence, &rig, &frames).await;
    let points = csv_points(&lines);
    let trajectories = points.iter().map(|p| p.trajectory).max().unwrap() + 1;
    assert_eq!(run["trajectories"], trajectories, "{run}");
    assert_plausible(&points, FRAMES);

    // The recovery ran: `ptv track` recovered particles, and the service's
    // trajectories hold recovered points (numbered from their frame's
    // particle count on), each with its targets, 2 or more, none of them
    // a target of the frame's particles.
    let tables = api.particle_tables(sequence, FRAMES as i64).await;
    let particles: Vec<_> = tables
        .iter()
        .map(|text| formats::csv::parse_particles(text, "particles").unwrap())
        .collect();
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/trajectories"))
        .await;
    assert_eq!(status, 200, "{body}");
    let mut recovered_points = 0;
    for point in body["trajectories"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|t| t["points"].as_array().unwrap())
    {
        let frame = &particles[point["frame"].as_u64().unwrap() as usize];
        let index = point["particle"].as_u64().unwrap() as usize;
        if index < frame.len() {
            continue;
        }
        recovered_points += 1;
        let targets: Vec<Option<usize>> = point["targets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t.as_u64().map(|t| t as usize))
            .collect();
        assert!(targets.iter().flatten().count() >= 2, "{point}");
        for (c, t) in targets.iter().enumerate() {
            assert!(
                t.is_none() || frame.iter().all(|p| p.targets[c] != *t),
                "{point} reuses a particle's target"
            );
        }
    }
    eprintln!("ptv track recovered {recovered} particles; {recovered_points} recovered points in the service's trajectories");
    assert!(recovered > 0, "nothing to recover: the test shows nothing");
    assert!(
        recovered_points > 0 && recovered_points <= recovered,
        "{recovered_points} recovered points, {recovered} recovered"
    );

    // One trajectory, and the per-particle ids of a frame, agree.
    let mut lengths: HashMap<u64, Vec<i64>> = HashMap::new();
    for p in &points {
        lengths.entry(p.trajectory).or_default().push(p.frame);
    }
    let (longest, its_frames) = lengths.iter().max_by_key(|(id, f)| (f.len(), *id)).unwrap();
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/trajectories/{longest}"))
        .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["length"], its_frames.len(), "{body}");
    let frames_of: Vec<i64> = body["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["frame"].as_i64().unwrap())
        .collect();
    assert_eq!(&frames_of, its_frames);
    // A frame's particles name their trajectories (by their targets, which
    // identify a particle within its frame); recovered particles are not
    // the frame's particles, and not listed.
    let frame = 100;
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/frames/{frame}/particles"))
        .await;
    assert_eq!(status, 200, "{body}");
    let by_targets: HashMap<&str, u64> = points
        .iter()
        .filter(|p| p.frame == frame)
        .map(|p| (p.targets.as_str(), p.trajectory))
        .collect();
    let listed = body["particles"].as_array().unwrap();
    assert_eq!(listed.len(), particles[frame as usize].len());
    let mut named = 0;
    for (i, p) in listed.iter().enumerate() {
        let targets = targets_columns(&particles[frame as usize][i].targets);
        let expected = by_targets.get(targets.as_str()).copied();
        assert_eq!(p["trajectory"].as_u64(), expected, "particle {i}");
        named += usize::from(expected.is_some());
    }
    assert!(
        named as f64 > 0.8 * listed.len() as f64,
        "{named} of {}",
        listed.len()
    );

    // The filters: long trajectories in a window of frames.
    let csv = api
        .text(&format!(
            "/sequences/{sequence}/trajectories?format=csv&min_length=20&frames=50..59"
        ))
        .await;
    let filtered: Vec<_> = points
        .iter()
        .filter(|p| lengths[&p.trajectory].len() >= 20 && (50..=59).contains(&p.frame))
        .collect();
    assert_eq!(csv.lines().count() - 1, filtered.len());
    assert!(!filtered.is_empty());
    // JSON: the same trajectories, grouped.
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/trajectories?min_length=20"))
        .await;
    assert_eq!(status, 200, "{body}");
    let listed = body["trajectories"].as_array().unwrap();
    let mut long: Vec<(&u64, &Vec<i64>)> = lengths.iter().filter(|(_, f)| f.len() >= 20).collect();
    long.sort();
    assert_eq!(listed.len(), long.len());
    for (view, (id, its_frames)) in listed.iter().zip(long) {
        assert_eq!(view["id"], *id);
        assert_eq!(view["points"].as_array().unwrap().len(), its_frames.len());
    }
    app.stop().await;
}

#[tokio::test]
async fn a_rerun_with_other_settings_is_a_new_run_and_the_old_one_stays() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let frames = moving_frames(&rig, 30, 21);
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "backward": false}),
        )
        .await;
    let first = api.upload_all_and_finish(sequence, &frames).await;
    assert_eq!(first["settings"]["recovery"], true, "{first}");
    let old_csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;

    let (status, second) = api
        .post(
            &format!("/sequences/{sequence}/tracking"),
            &json!({"max_velocity": MAX_VELOCITY, "min_length": 10, "recovery": false, "backward": false}),
        )
        .await;
    assert_eq!(status, 201, "{second}");
    assert_ne!(second["run_id"], first["run_id"]);
    assert_eq!(second["settings"]["min_length"], 10);
    assert_eq!(second["settings"]["recovery"], false);
    // The finish request carries over: the new run ends by itself.
    let second = api.finish(sequence).await;
    let particles = api.particles(sequence, 30).await;
    let expected = core_trajectories(
        &particles,
        TrackingParameters {
            min_length: 10,
            ..TrackingParameters::new(MAX_VELOCITY)
        },
    );
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    // Without recovery: the core's tracker over the stored particles, and
    // `ptv track --particles` (which has no targets to recover from).
    assert_same_trajectories(&csv, &expected, &particles);
    let tables = api.particle_tables(sequence, 30).await;
    assert_eq!(
        csv.lines().collect::<Vec<_>>(),
        ptv_track(
            &tables,
            MAX_VELOCITY,
            &["--min-length", "10", "--no-backward"]
        )
    );
    // The old run is still there, unchanged.
    let old_again = api
        .text(&format!(
            "/sequences/{sequence}/trajectories?format=csv&run={}",
            first["run_id"]
        ))
        .await;
    assert_eq!(old_again, old_csv);
    crate::plots::check_trajectories_picture(&app, sequence, first["run_id"].as_i64().unwrap())
        .await;
    let (status, runs) = api.get(&format!("/sequences/{sequence}/tracking")).await;
    assert_eq!(status, 200, "{runs}");
    let ids: Vec<&Value> = runs
        .as_array()
        .unwrap()
        .iter()
        .map(|r| &r["run_id"])
        .collect();
    assert_eq!(ids, vec![&first["run_id"], &second["run_id"]]);
    app.stop().await;
}

#[tokio::test]
async fn bad_tracking_settings_and_queries_are_refused_saying_why() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    for (tracking, says) in [
        (
            json!({"max_velocity": 0.0}),
            "max_velocity must be a positive",
        ),
        (
            json!({"max_velocity": -2.0}),
            "max_velocity must be a positive",
        ),
        (
            json!({"max_velocity": 1.0, "max_gap": 5}),
            "max_gap must be 0..=2",
        ),
        (
            json!({"max_velocity": 1.0, "first_frame": -1}),
            "first_frame",
        ),
        (json!({"max_velocity": "fast"}), "tracking.max_velocity"),
        (json!({}), "max_velocity"),
        (json!({"max_velocity": 1.0, "speed": 2}), "speed"),
        (
            json!({"max_velocity": 1.0, "recovery": "yes"}),
            "tracking.recovery",
        ),
    ] {
        let mut request = sequence_body(calibration, &rig.volume, false);
        request["tracking"] = tracking.clone();
        let (status, body) = api.post("/sequences", &request).await;
        assert_eq!(status, 422, "{tracking}: {body}");
        let detail = body["detail"].as_str().unwrap();
        assert!(detail.contains(says), "{tracking}: {detail}");
    }
    // Nothing was stored by the refused requests.
    let db = app.database().await;
    assert_eq!(
        crate::helpers::count(&db, "SELECT count(*) FROM sequences").await,
        0
    );
    db.close().await;

    // An untracked sequence: its trajectories are a 409 that says how to
    // track it; tracking settings given later are checked alike.
    let sequence = app.create_sequence(calibration, &rig.volume, false).await;
    let (status, body) = api.get(&format!("/sequences/{sequence}")).await;
    assert_eq!(status, 200);
    assert_eq!(body["tracking"], Value::Null, "{body}");
    for path in [
        format!("/sequences/{sequence}/trajectories"),
        format!("/sequences/{sequence}/trajectories/0"),
    ] {
        let (status, body) = api.get(&path).await;
        assert_eq!(status, 409, "{path}: {body}");
        assert!(
            body["detail"].as_str().unwrap().contains("/tracking"),
            "{body}"
        );
    }
    let (status, body) = api
        .post(
            &format!("/sequences/{sequence}/tracking/finish"),
            &json!({}),
        )
        .await;
    assert_eq!(status, 409, "{body}");
    let (status, body) = api
        .post(
            &format!("/sequences/{sequence}/tracking"),
            &json!({"max_velocity": -1}),
        )
        .await;
    assert_eq!(status, 422, "{body}");
    let (status, body) = api
        .post(
            &format!("/sequences/{sequence}/tracking"),
            &json!({"max_velocity": 1.0, "recovery": 1}),
        )
        .await;
    assert_eq!(status, 422, "{body}");
    assert!(
        body["detail"].as_str().unwrap().contains("recovery"),
        "{body}"
    );
    let response = api
        .client
        .post(api.url(&format!("/sequences/{sequence}/tracking")))
        .header("content-type", "application/json")
        .body("{\"max_velocity\": ")
        .send()
        .await
        .unwrap();
    assert_eq!(response.status().as_u16(), 400);
    let (status, body) = api
        .post(
            &format!("/sequences/{sequence}/tracking"),
            &json!({"max_velocity": 2.0}),
        )
        .await;
    assert_eq!(status, 201, "{body}");
    // Bad queries of a tracked sequence.
    for (query, expected) in [
        ("frames=9..2", 400),
        ("frames=a..b", 400),
        ("format=xml", 400),
        ("min_length=-1", 400),
        ("colour=red", 400),
        ("run=999", 404),
    ] {
        let (status, body) = api
            .get(&format!("/sequences/{sequence}/trajectories?{query}"))
            .await;
        assert_eq!(status, expected, "{query}: {body}");
    }
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/trajectories/7"))
        .await;
    assert_eq!(status, 404, "{body}");
    let (status, _) = api.get("/sequences/999/trajectories").await;
    assert_eq!(status, 404);
    app.stop().await;
}

/// Frames in the kill -9 test.
const CRASH_FRAMES: usize = 200;

#[tokio::test]
async fn a_kill_during_tracking_then_a_restart_gives_the_same_trajectories() {
    let data_dir = tempfile::tempdir().unwrap();
    let rig = rig();
    let frames = moving_frames(&rig, CRASH_FRAMES, 31);
    // The first two thirds of the frames before the kill, the rest after,
    // each part in random order.
    let mut order: Vec<(i64, &TargetFrame)> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64, t))
        .collect();
    let (before, after) = order.split_at_mut(CRASH_FRAMES * 2 / 3);
    before.shuffle(&mut simulate::rng(32));
    after.shuffle(&mut simulate::rng(33));

    let first = ServiceProcess::start(data_dir.path(), 2);
    let api = Api::at(&first.address);
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "backward": false}),
        )
        .await;
    api.upload_concurrently(sequence, before, 4).await;
    // Kill once tracking is under way (some frames tracked), while frames
    // are still being processed and tracked.
    api.wait_tracked_through(sequence, 3).await;
    first.kill();

    let second = ServiceProcess::start(data_dir.path(), 2);
    let api = Api::at(&second.address);
    api.upload_concurrently(sequence, after, 4).await;
    let run = api.finish(sequence).await;
    assert_eq!(run["tracked_through"], CRASH_FRAMES as i64 - 1, "{run}");
    assert_eq!(run["settings"]["recovery"], true, "{run}");
    // The tracker rebuilt by replay recovered what the one killed had, so
    // the trajectories are `ptv track`'s on the same targets, row for row.
    let (_, recovered) = api.tracked_as_ptv_track(sequence, &rig, &frames).await;
    assert!(
        recovered > 0,
        "nothing recovered: the replay's recovery is not tested"
    );
}

/// Frames of the cross-process test.
const WORKER_FRAMES: usize = 120;

/// `ptv serve --workers 0` and two `ptv worker` processes: the frames are
/// processed by both, one process tracks the run under its lease; killed
/// (-9) once tracking is under way, the other takes the run over when the
/// lease runs out, rebuilds the tracker by replay, and the trajectories are
/// still `ptv track`'s, row for row.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn worker_processes_track_in_frame_order_and_one_takes_over_a_killed_ones_run() {
    let data_dir = tempfile::tempdir().unwrap();
    let rig = rig();
    let frames = moving_frames(&rig, WORKER_FRAMES, 51);
    let mut order: Vec<(i64, &TargetFrame)> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64, t))
        .collect();
    let (before, after) = order.split_at_mut(WORKER_FRAMES / 2);
    before.shuffle(&mut simulate::rng(52));
    after.shuffle(&mut simulate::rng(53));

    let lease = ["--lease-secs", "3"];
    let server = ServiceProcess::start_with(data_dir.path(), 0, &lease);
    let worker_args = ["--lease-secs", "3", "--workers", "1"];
    let mut workers = [
        WorkerProcess::start(data_dir.path(), &worker_args, &[]),
        WorkerProcess::start(data_dir.path(), &worker_args, &[]),
    ];
    let pids: Vec<u32> = workers.iter().map(WorkerProcess::pid).collect();
    let api = Api::at(&server.address);
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "backward": false}),
        )
        .await;
    api.upload_concurrently(sequence, before, 4).await;
    api.wait_tracked_through(sequence, 3).await;
    let db = open_database(data_dir.path()).await;
    let (owner, token): (String, i64) = sqlx::query_as(
        "SELECT lease_owner, lease_token FROM tracking_runs ORDER BY id DESC LIMIT 1",
    )
    .fetch_one(&db)
    .await
    .unwrap();
    let holder = pids
        .iter()
        .position(|&p| Some(p) == worker_pid(&owner))
        .unwrap_or_else(|| panic!("the run is held by {owner}, not by a worker process"));
    workers[holder].kill();

    api.upload_concurrently(sequence, after, 4).await;
    let run = api.finish(sequence).await;
    assert_eq!(run["tracked_through"], WORKER_FRAMES as i64 - 1, "{run}");
    let (taken_over,): (i64,) =
        sqlx::query_as("SELECT lease_token FROM tracking_runs ORDER BY id DESC LIMIT 1")
            .fetch_one(&db)
            .await
            .unwrap();
    assert!(taken_over > token, "the run's lease never changed hands");
    db.close().await;
    let (_, recovered) = api.tracked_as_ptv_track(sequence, &rig, &frames).await;
    assert!(recovered > 0, "nothing recovered");
    drop(workers);
    drop(server);
}

#[tokio::test]
async fn a_failed_frame_is_a_gap_the_trajectories_bridge() {
    // Frames past 0.2 s fail: the test's 400-particle frames take
    // milliseconds, a frame of 4 x 40,000 targets far longer (as in
    // `job_bounds`).
    let app = crate::helpers::spawn_app_configured(|args| {
        args.job_limits = ptv::service::JobLimits {
            floor_secs: 0.2,
            factor: 0.0,
            ..Default::default()
        };
    })
    .await;
    let api = Api::at(&app.address);
    let rig = rig();
    const GAP_FRAMES: usize = 30;
    const GAP: i64 = 12;
    let frames = moving_frames(&rig, GAP_FRAMES, 41);
    let crowded = rig.targets(40_000, 42);
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "backward": false}),
        )
        .await;
    // Every frame but the gap's, last first: tracking waits at the gap's
    // frame number, not uploaded yet (nothing else competes with the
    // crowded frame's time limit afterwards).
    let order: Vec<(i64, &TargetFrame)> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64, t))
        .filter(|(f, _)| *f != GAP)
        .rev()
        .collect();
    api.upload_concurrently(sequence, &order, 3).await;
    wait_for_sequence(&api.client, &api.address, sequence).await;
    let start = Instant::now();
    loop {
        let (_, body) = api.get(&format!("/sequences/{sequence}")).await;
        let through = &body["tracking"]["tracked_through"];
        if through == GAP - 1 {
            break;
        }
        assert!(
            through.as_i64().unwrap_or(-1) < GAP,
            "tracked past a missing frame: {body}"
        );
        assert!(start.elapsed() < PATIENCE, "tracking stalled: {body}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    api.upload_concurrently(sequence, &[(GAP, &crowded)], 1)
        .await;
    let run = api.finish(sequence).await;
    assert_eq!(run["tracked_through"], GAP_FRAMES as i64 - 1, "{run}");
    let (status, body) = api.get(&format!("/sequences/{sequence}")).await;
    assert_eq!(status, 200);
    assert_eq!(body["frames"]["failed"], 1, "{body}");

    // The core over the same frames, the failed one empty.
    let mut particles = Vec::new();
    for frame in 0..GAP_FRAMES as i64 {
        let response = api
            .client
            .get(api.url(&format!(
                "/sequences/{sequence}/frames/{frame}/particles?format=csv"
            )))
            .send()
            .await
            .unwrap();
        let status = response.status().as_u16();
        let text = response.text().await.unwrap();
        if frame == GAP {
            assert_eq!(status, 409, "{text}");
            particles.push(Vec::new());
        } else {
            assert_eq!(status, 200, "{text}");
            particles.push(formats::csv::parse_particles(&text, "particles").unwrap());
        }
    }
    // `ptv track` over the same targets, the failed frame's missing (a gap
    // there too), with the recovery.
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    let lines: Vec<String> = csv.lines().map(str::to_owned).collect();
    let inputs: Vec<Option<&TargetFrame>> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64 != GAP).then_some(t))
        .collect();
    let (expected, _) = ptv_track_targets(
        &rig,
        &inputs,
        MAX_VELOCITY,
        &["--allow-gaps", "--no-backward"],
    );
    assert_eq!(lines, expected);
    // Most trajectories across the gap are bridged, not cut.
    let mut by_trajectory: HashMap<u64, Vec<i64>> = HashMap::new();
    for p in csv_points(&lines) {
        by_trajectory.entry(p.trajectory).or_default().push(p.frame);
    }
    let across = by_trajectory
        .values()
        .filter(|frames| frames.contains(&(GAP - 1)) && frames.contains(&(GAP + 1)))
        .count();
    let at_gap = particles[GAP as usize - 1].len();
    assert!(
        across as f64 > 0.7 * at_gap as f64,
        "{across} of {at_gap} trajectories bridge the gap"
    );
    app.stop().await;
}

/// A `.vtp` read with a strict XML reader (end names checked): its
/// `VTKFile` type and its `Piece`'s counts (points, verts, lines).
fn vtp_counts(text: &str) -> (String, [usize; 3]) {
    use quick_xml::events::Event;
    let mut reader = quick_xml::Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let attr = |e: &quick_xml::events::BytesStart, name: &str| -> String {
        e.try_get_attribute(name)
            .unwrap()
            .map(|a| a.unescape_value().unwrap().into_owned())
            .unwrap_or_default()
    };
    let (mut kind, mut counts) = (String::new(), [usize::MAX; 3]);
    loop {
        match reader.read_event().expect("well-formed XML") {
            Event::Start(e) if e.name().as_ref() == b"VTKFile" => kind = attr(&e, "type"),
            Event::Start(e) if e.name().as_ref() == b"Piece" => {
                let n = |k: &str| attr(&e, k).parse::<usize>().unwrap();
                counts = [n("NumberOfPoints"), n("NumberOfVerts"), n("NumberOfLines")];
            }
            Event::Eof => return (kind, counts),
            _ => {}
        }
    }
}

/// `?format=vtk` and `?format=hdf5` give the files `ptv export` writes,
/// with the points the JSON gives; an unknown format is a 400 naming the
/// accepted ones.
#[tokio::test]
async fn a_tracked_sequence_exports_to_paraview_and_hdf5() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let frames = moving_frames(&rig, 8, 34);
    let sequence = api
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
        .await;
    api.upload_all_and_finish(sequence, &frames).await;
    let (status, json) = api
        .get(&format!("/sequences/{sequence}/trajectories"))
        .await;
    assert_eq!(status, 200, "{json}");
    let trajectories = json["trajectories"].as_array().unwrap();
    let points: usize = trajectories
        .iter()
        .map(|t| t["points"].as_array().unwrap().len())
        .sum();
    assert!(points > 0 && !trajectories.is_empty());
    let get = |path: String| {
        let request = api.client.get(api.url(&path));
        async move { request.send().await.unwrap() }
    };

    // ParaView: the polylines, one per trajectory, with the JSON's points.
    let response = get(format!("/sequences/{sequence}/trajectories?format=vtk")).await;
    assert_eq!(response.status().as_u16(), 200);
    assert_eq!(response.headers()["content-type"], "application/xml");
    assert_eq!(
        response.headers()["content-disposition"],
        "attachment; filename=\"trajectories.vtp\""
    );
    let (kind, counts) = vtp_counts(&response.text().await.unwrap());
    assert_eq!(kind, "PolyData");
    assert_eq!(counts, [points, 0, trajectories.len()]);

    // One frame's particles as vertices, the JSON's count.
    let (status, frame) = api
        .get(&format!("/sequences/{sequence}/frames/3/particles"))
        .await;
    assert_eq!(status, 200, "{frame}");
    let particles = frame["particles"].as_array().unwrap().len();
    assert!(particles > 0);
    let response = get(format!(
        "/sequences/{sequence}/frames/3/particles?format=vtk"
    ))
    .await;
    assert_eq!(response.status().as_u16(), 200);
    assert_eq!(
        response.headers()["content-disposition"],
        "attachment; filename=\"particles.3.vtp\""
    );
    let (kind, counts) = vtp_counts(&response.text().await.unwrap());
    assert_eq!(kind, "PolyData");
    assert_eq!(counts, [particles, particles, 0]);

    // HDF5: the signature, then read back with the writer's own reader.
    let response = get(format!("/sequences/{sequence}/trajectories?format=hdf5")).await;
    assert_eq!(response.status().as_u16(), 200);
    assert_eq!(response.headers()["content-type"], "application/x-hdf5");
    assert_eq!(
        response.headers()["content-disposition"],
        format!("attachment; filename=\"sequence_{sequence}.h5\"").as_str()
    );
    let bytes = response.bytes().await.unwrap().to_vec();
    assert!(bytes.starts_with(b"\x89HDF\r\n\x1a\n"));
    let file = hdf5_pure::File::from_bytes(bytes).unwrap();
    let column = |name: &str| file.dataset(&format!("trajectories/{name}")).unwrap();
    let ids = column("trajectory").read_i64().unwrap();
    let x = column("x").read_f64().unwrap();
    assert_eq!(ids.len(), points);
    let json_x: Vec<f64> = trajectories
        .iter()
        .flat_map(|t| t["points"].as_array().unwrap().iter())
        .map(|p| p["position"][0].as_f64().unwrap())
        .collect();
    // serde_json's default float parsing (no `float_roundtrip`) may be
    // off by an ulp or two; the file's values are the stored f64s.
    assert_eq!(x.len(), json_x.len());
    for (a, b) in x.iter().zip(&json_x) {
        assert!(
            (a - b).abs() <= 4.0 * f64::EPSILON * a.abs().max(1.0),
            "{a} {b}"
        );
    }
    let listed = file
        .dataset("particles/frames")
        .unwrap()
        .read_i64()
        .unwrap();
    assert_eq!(listed, (0..8).collect::<Vec<i64>>());
    let z = file
        .dataset("particles/frame_3/z")
        .unwrap()
        .read_f64()
        .unwrap();
    assert_eq!(z.len(), particles);

    // ParaView's time series as one zip: the .pvd names a .vtp per
    // processed frame, each in the zip with that frame's particles, and
    // the polylines as `?format=vtk` gives them.
    let response = get(format!("/sequences/{sequence}/trajectories?format=pvd")).await;
    assert_eq!(response.status().as_u16(), 200);
    assert_eq!(response.headers()["content-type"], "application/zip");
    assert_eq!(
        response.headers()["content-disposition"],
        format!("attachment; filename=\"sequence_{sequence}_paraview.zip\"").as_str()
    );
    let bytes = response.bytes().await.unwrap().to_vec();
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes)).unwrap();
    let mut read = |name: &str| {
        let mut text = String::new();
        std::io::Read::read_to_string(&mut zip.by_name(name).unwrap(), &mut text).unwrap();
        text
    };
    let series = read("particles.pvd");
    let files: Vec<(i64, String)> = series
        .lines()
        .filter(|l| l.contains("<DataSet"))
        .map(|l| {
            let attribute = |name: &str| {
                let from = l.find(&format!("{name}=\"")).unwrap() + name.len() + 2;
                l[from..from + l[from..].find('"').unwrap()].to_owned()
            };
            (attribute("timestep").parse().unwrap(), attribute("file"))
        })
        .collect();
    assert_eq!(
        files,
        (0..8)
            .map(|f| (f, format!("particles.{f}.vtp")))
            .collect::<Vec<_>>()
    );
    for (frame, file) in &files {
        let (kind, counts) = vtp_counts(&read(file));
        assert_eq!(kind, "PolyData", "{file}");
        if *frame == 3 {
            assert_eq!(counts, [particles, particles, 0]);
        }
    }
    let polylines = get(format!("/sequences/{sequence}/trajectories?format=vtk"))
        .await
        .text()
        .await
        .unwrap();
    assert_eq!(read("trajectories.vtp"), polylines);
    assert_eq!(
        zip.len(),
        files.len() + 2,
        "the .pvd, its frames, the polylines"
    );

    // An unknown format names the accepted ones.
    for path in [
        format!("/sequences/{sequence}/trajectories?format=vtu"),
        format!("/sequences/{sequence}/frames/3/particles?format=h5"),
    ] {
        let (status, body) = api.get(&path).await;
        assert_eq!(status, 400, "{path}: {body}");
        let detail = body["detail"].as_str().unwrap();
        assert!(detail.contains("vtk"), "{path}: {detail}");
    }
    app.stop().await;
}

/// Backward tracking at the run's finish (issue 34): particles entering
/// mid-sequence whose second frame is lost (no targets in any camera) are
/// picked up late by the forward pass (a trajectory of one point bridges
/// no gap); a run with `"backward": true` extends its trajectories
/// backwards once it finishes. Its stored trajectories are, row for row,
/// `ptv track --backward`'s over the stored particles (without recovery,
/// which the particle files cannot give: the pass over a stored run sees
/// the particles `ptv track --particles` sees), the run shows what the
/// pass added as the core's summary says, and the points are the forward
/// pass's plus the added ones.
#[tokio::test]
async fn backward_tracking_at_the_finish_is_ptv_track_backwards() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let count = 24;
    let mut frames = moving_frames(&rig, count, 34);
    // Every 8th particle enters at frame 3..=14 and misses the frame after.
    let birth = |i: usize| (i % 8 == 0).then_some(3 + (i / 8) % 12);
    for (f, frame) in frames.iter_mut().enumerate() {
        for (targets, truth) in frame.targets.iter_mut().zip(frame.truth.iter_mut()) {
            let keep: Vec<bool> = truth
                .iter()
                .map(|&i| !matches!(birth(i), Some(b) if f < b || f == b + 1))
                .collect();
            let mut k = keep.iter();
            targets.retain(|_| *k.next().unwrap());
            let mut k = keep.iter();
            truth.retain(|_| *k.next().unwrap());
        }
    }
    let sequence = api
        .tracked_sequence(
            &rig,
            json!({"max_velocity": MAX_VELOCITY, "recovery": false, "backward": true}),
        )
        .await;
    let run = api.upload_all_and_finish(sequence, &frames).await;
    assert_eq!(run["settings"]["backward"], true, "{run}");

    let particles = api.particles(sequence, count as i64).await;
    let positions = |rows: &[formats::csv::ParticleRow]| -> Vec<ParticlePosition> {
        rows.iter()
            .map(|r| {
                ParticlePosition::seen_by(
                    r.position,
                    r.sigma.expect("the service's CSV has sigmas"),
                    r.targets.iter().flatten().count(),
                )
            })
            .collect()
    };
    let input: Vec<(i64, Vec<ParticlePosition>)> = particles
        .iter()
        .enumerate()
        .map(|(f, rows)| (f as i64, positions(rows)))
        .collect();
    let (_, added) =
        track::track_both_ways(input.clone(), TrackingParameters::new(MAX_VELOCITY)).unwrap();
    let forward = track::track(input, TrackingParameters::new(MAX_VELOCITY)).unwrap();
    // The late starts are there to take back (about 50 entering particles;
    // a few of them start right anyway where their third point links
    // back).
    assert!(added.points >= 20, "{added:?}");
    assert_eq!(
        run["backward"],
        json!({"points": added.points, "lengthened": added.lengthened, "joined": added.joined}),
        "{run}"
    );
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    let tables = api.particle_tables(sequence, count as i64).await;
    assert_same_rows(
        &csv.lines().collect::<Vec<_>>(),
        &ptv_track(&tables, MAX_VELOCITY, &["--backward"]),
    );
    let forward_points: usize = forward.iter().map(|t| t.points.len()).sum();
    assert_eq!(csv.lines().count() - 1, forward_points + added.points);
    // The trajectories' extents agree with their points: one joined onto
    // another is gone, the lengthened ones start earlier.
    let (status, list) = api
        .get(&format!("/sequences/{sequence}/trajectories"))
        .await;
    assert_eq!(status, 200, "{list}");
    let list = list["trajectories"]
        .as_array()
        .expect("a list of trajectories");
    assert_eq!(list.len(), forward.len() - added.joined);
    assert_eq!(run["trajectories"].as_u64().unwrap() as usize, list.len());
    let mut points_by_trajectory: HashMap<u64, usize> = HashMap::new();
    for p in csv_points(&csv.lines().map(str::to_owned).collect::<Vec<_>>()) {
        *points_by_trajectory.entry(p.trajectory).or_default() += 1;
    }
    for t in list {
        let points = t["points"].as_array().unwrap();
        assert_eq!(t["length"].as_u64().unwrap() as usize, points.len(), "{t}");
        assert_eq!(
            points.len(),
            points_by_trajectory[&t["id"].as_u64().unwrap()]
        );
        assert_eq!(t["first_frame"], points[0]["frame"], "{t}");
        assert_eq!(t["last_frame"], points[points.len() - 1]["frame"], "{t}");
    }
    app.stop().await;
}

/// An export above the service's `--max-export-points` is refused with
/// 413 before it is built, saying what to do; the frames asked for in
/// part fit. The limit, 2,500 points, is under the 8 frames' particles
/// alone (about 390 a frame: 400 particles, 4 cameras, 5% of images
/// lost) and above 2 frames' particles and trajectory points (at most one
/// point a particle: about 1,560).
#[tokio::test]
async fn an_export_above_the_configured_limit_is_refused_saying_to_cut_it() {
    let app = crate::helpers::spawn_app_configured(|args| args.max_export_points = 2_500).await;
    let api = Api::at(&app.address);
    let rig = rig();
    let frames = moving_frames(&rig, 8, 35);
    let sequence = api
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
        .await;
    api.upload_all_and_finish(sequence, &frames).await;
    for format in ["vtk", "hdf5"] {
        let (status, body) = api
            .get(&format!(
                "/sequences/{sequence}/trajectories?format={format}"
            ))
            .await;
        assert_eq!(status, 413, "{format}: {body}");
        let detail = body["detail"].as_str().unwrap();
        for says in [
            "more than 2500 points",
            "--max-export-points",
            "frames=FIRST..LAST",
        ] {
            assert!(detail.contains(says), "{format}: {detail}");
        }
        let response = api
            .client
            .get(api.url(&format!(
                "/sequences/{sequence}/trajectories?format={format}&frames=0..1"
            )))
            .send()
            .await
            .unwrap();
        assert_eq!(response.status().as_u16(), 200, "{format}, frames 0..1");
    }
    // The JSON and CSV stream: no such limit.
    let (status, _) = api
        .get(&format!("/sequences/{sequence}/trajectories"))
        .await;
    assert_eq!(status, 200);
    app.stop().await;
}
