//! Tracking in the service (issue 15): a simulated sequence of moving
//! particles, uploaded out of order by concurrent clients, is tracked as
//! its frames complete and gives exactly the trajectories of the core's
//! tracker run over the same particles in frame order; the same after a
//! kill -9 mid-tracking and a restart; a re-run with other settings is a
//! new run next to the old one; bad settings and queries are refused.
//!
//! The comparison is exact (no tolerance): the service runs the core's
//! deterministic tracker on the particles it stored, and the test reads
//! those particles back as CSV (shortest round-trip float text) and runs
//! the same tracker on them.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use nalgebra::{Point3, Vector3};
use rand::seq::SliceRandom;
use serde_json::{json, Value};

use ptv::formats;
use ptv::photogrammetry::simulate::{self, TargetFrame};
use ptv::photogrammetry::track::{self, ParticlePosition, TrackingParameters, Trajectory};

use crate::helpers::{
    rig, sequence_body, status_and_json, targets_form, upload, wait_for_sequence, Rig,
    ServiceProcess, PATIENCE,
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
fn moving_frames(rig: &Rig, frames: usize, seed: u64) -> Vec<TargetFrame> {
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

    async fn post(&self, path: &str, body: &Value) -> (u16, Value) {
        let response = self
            .client
            .post(self.url(path))
            .json(body)
            .send()
            .await
            .unwrap();
        status_and_json(response).await
    }

    async fn get(&self, path: &str) -> (u16, Value) {
        status_and_json(self.client.get(self.url(path)).send().await.unwrap()).await
    }

    async fn text(&self, path: &str) -> String {
        let response = self.client.get(self.url(path)).send().await.unwrap();
        assert_eq!(response.status().as_u16(), 200, "{path}");
        response.text().await.unwrap()
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
/// with `--max-velocity`: its CSV rows sorted by trajectory and frame,
/// after its header.
fn ptv_track(tables: &[String], max_velocity: f64) -> Vec<String> {
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
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let text = String::from_utf8(output.stdout).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let header = lines.remove(0);
    let key = |line: &String| -> (u64, i64) {
        let mut fields = line.split(',');
        (
            fields.next().unwrap().parse().unwrap(),
            fields.next().unwrap().parse().unwrap(),
        )
    };
    lines.sort_by_key(key);
    lines.insert(0, header);
    lines
}

/// A CSV number, NaN as written by `{:?}`, an empty field as `None`.
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

/// Sanity of the simulated flow's trajectories: most particles are in
/// long trajectories, and the median velocity is the true one within a
/// few of its reported standard deviations.
fn assert_plausible(expected: &[Trajectory], frames: usize) {
    let points: usize = expected.iter().map(|t| t.points.len()).sum();
    // Particles found per frame are about PARTICLES (4 cameras, 5% of
    // images lost: nearly all are seen in 3 or more); a particle re-enters
    // the volume every 40 frames or so (80 mm at 2 mm per frame), so most
    // trajectories are long.
    assert!(
        points as f64 > 0.8 * (PARTICLES * frames) as f64,
        "{points} points in trajectories"
    );
    let mean_length = points as f64 / expected.len() as f64;
    assert!(mean_length > 10.0, "mean trajectory length {mean_length}");
    let mut u: Vec<f64> = expected
        .iter()
        .flat_map(|t| &t.points)
        .map(|p| p.derivatives.velocity.x)
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
async fn a_sequence_uploaded_out_of_order_by_four_clients_is_tracked_as_the_core_tracks_it() {
    let app = crate::helpers::spawn_app().await;
    let api = Api::at(&app.address);
    let rig = rig();
    let frames = moving_frames(&rig, FRAMES, 15);
    let sequence = api
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
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

    let tables = api.particle_tables(sequence, FRAMES as i64).await;
    let particles: Vec<_> = tables
        .iter()
        .map(|text| formats::csv::parse_particles(text, "particles").unwrap())
        .collect();
    let expected = core_trajectories(&particles, TrackingParameters::new(MAX_VELOCITY));
    assert_plausible(&expected, FRAMES);
    assert_eq!(run["trajectories"], expected.len(), "{run}");
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    assert_same_trajectories(&csv, &expected, &particles);
    // And `ptv track` on the same particles writes the same CSV, row for
    // row once its rows (written as they become final) are sorted.
    assert_eq!(
        csv.lines().collect::<Vec<_>>(),
        ptv_track(&tables, MAX_VELOCITY)
    );

    // One trajectory, and the per-particle ids of a frame, agree.
    let longest = expected.iter().max_by_key(|t| t.points.len()).unwrap();
    let (status, body) = api
        .get(&format!(
            "/sequences/{sequence}/trajectories/{}",
            longest.id
        ))
        .await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(body["length"], longest.points.len(), "{body}");
    let frames_of: Vec<i64> = body["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["frame"].as_i64().unwrap())
        .collect();
    assert_eq!(
        frames_of,
        longest.points.iter().map(|p| p.frame).collect::<Vec<_>>()
    );
    let frame = 100;
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/frames/{frame}/particles"))
        .await;
    assert_eq!(status, 200, "{body}");
    let mut by_particle: HashMap<usize, u64> = HashMap::new();
    for p in expected.iter().flat_map(|t| &t.points) {
        if p.frame == frame {
            by_particle.insert(p.particle, p.trajectory);
        }
    }
    for (i, p) in body["particles"].as_array().unwrap().iter().enumerate() {
        assert_eq!(
            p["trajectory"].as_u64(),
            by_particle.get(&i).copied(),
            "particle {i}"
        );
    }

    // The filters: long trajectories in a window of frames.
    let csv = api
        .text(&format!(
            "/sequences/{sequence}/trajectories?format=csv&min_length=20&frames=50..59"
        ))
        .await;
    let filtered: Vec<_> = expected
        .iter()
        .filter(|t| t.points.len() >= 20)
        .flat_map(|t| &t.points)
        .filter(|p| (50..=59).contains(&p.frame))
        .collect();
    assert_eq!(csv.lines().count() - 1, filtered.len());
    assert!(!filtered.is_empty());
    // JSON: the same trajectories, grouped.
    let (status, body) = api
        .get(&format!("/sequences/{sequence}/trajectories?min_length=20"))
        .await;
    assert_eq!(status, 200, "{body}");
    let listed = body["trajectories"].as_array().unwrap();
    let long: Vec<_> = expected.iter().filter(|t| t.points.len() >= 20).collect();
    assert_eq!(listed.len(), long.len());
    for (view, t) in listed.iter().zip(long) {
        assert_eq!(view["id"], t.id);
        assert_eq!(view["points"].as_array().unwrap().len(), t.points.len());
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
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
        .await;
    let order: Vec<(i64, &TargetFrame)> = frames
        .iter()
        .enumerate()
        .map(|(f, t)| (f as i64, t))
        .collect();
    api.upload_concurrently(sequence, &order, 2).await;
    let first = api.finish(sequence).await;
    let old_csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;

    let (status, second) = api
        .post(
            &format!("/sequences/{sequence}/tracking"),
            &json!({"max_velocity": MAX_VELOCITY, "min_length": 10}),
        )
        .await;
    assert_eq!(status, 201, "{second}");
    assert_ne!(second["run_id"], first["run_id"]);
    assert_eq!(second["settings"]["min_length"], 10);
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
    assert_same_trajectories(&csv, &expected, &particles);
    // The old run is still there, unchanged.
    let old_again = api
        .text(&format!(
            "/sequences/{sequence}/trajectories?format=csv&run={}",
            first["run_id"]
        ))
        .await;
    assert_eq!(old_again, old_csv);
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
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
        .await;
    api.upload_concurrently(sequence, before, 4).await;
    // Kill once tracking is under way (some frames tracked), while frames
    // are still being processed and tracked.
    let start = Instant::now();
    loop {
        let (_, body) = api.get(&format!("/sequences/{sequence}")).await;
        if body["tracking"]["tracked_through"].as_i64().unwrap_or(-1) >= 3 {
            break;
        }
        assert!(start.elapsed() < PATIENCE, "tracking did not start: {body}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    first.kill();

    let second = ServiceProcess::start(data_dir.path(), 2);
    let api = Api::at(&second.address);
    api.upload_concurrently(sequence, after, 4).await;
    let run = api.finish(sequence).await;
    assert_eq!(run["tracked_through"], CRASH_FRAMES as i64 - 1, "{run}");
    let particles = api.particles(sequence, CRASH_FRAMES as i64).await;
    let expected = core_trajectories(&particles, TrackingParameters::new(MAX_VELOCITY));
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    assert_same_trajectories(&csv, &expected, &particles);
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
        .tracked_sequence(&rig, json!({"max_velocity": MAX_VELOCITY}))
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
    let expected = core_trajectories(&particles, TrackingParameters::new(MAX_VELOCITY));
    let csv = api
        .text(&format!("/sequences/{sequence}/trajectories?format=csv"))
        .await;
    assert_same_trajectories(&csv, &expected, &particles);
    // Most trajectories across the gap are bridged, not cut.
    let across = expected
        .iter()
        .filter(|t| {
            let frames: Vec<i64> = t.points.iter().map(|p| p.frame).collect();
            frames.contains(&(GAP - 1)) && frames.contains(&(GAP + 1))
        })
        .count();
    let at_gap = particles[GAP as usize - 1].len();
    assert!(
        across as f64 > 0.7 * at_gap as f64,
        "{across} of {at_gap} trajectories bridge the gap"
    );
    app.stop().await;
}
