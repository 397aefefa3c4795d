//! Tracking in the service, end to end: a sequence of moving particles
//! (targets of 4 cameras, 0.05 px noise, 5% of images lost, a uniform
//! motion of 0.3 mean spacings a frame) uploaded out of order by several
//! clients to a tracked sequence; reports how fast frames are processed
//! and tracked, how far tracking lags behind the processing, and how long
//! a restarted service takes to rebuild the tracker by replay and finish.
//!
//! ```sh
//! cargo bench --bench service_tracking
//! cargo bench --bench service_tracking -- --frames 200 --particles 2000 --clients 4 --workers 2
//! cargo bench --bench service_tracking -- --no-recovery
//! cargo bench --bench service_tracking -- --untracked          # the same frames, no tracking
//! cargo bench --bench service_tracking -- --database postgres://postgres@127.0.0.1:5432/ptv
//! cargo bench --bench service_tracking -- --log 2>log.txt             # the service's log, as ptv serve's
//! ```
//!
//! The run tracks with the image-space recovery (the service's default),
//! or without it with `--no-recovery` (`"recovery": false`). With
//! `--untracked` the sequence has no tracking: the time to process the
//! same frames without it, the yardstick of what tracking adds (issue 30:
//! a tracked frame should cost at most 1.5 times an untracked one). With
//! `--database URL` the service keeps its state in that PostgreSQL
//! database (empty or created by `ptv serve`), else SQLite in the
//! temporary data directory. With `--log` the service logs to standard
//! error as `ptv serve` does (the level and format of its log), to see
//! what a run writes there (issue 30: sqlx's slow-statement warnings
//! quoted every trajectory-point insert whole).
//!
//! The service runs in this process on a temporary data directory; the
//! uploads are open loop (every client sends its frames as fast as the
//! service takes them).

use std::time::{Duration, Instant};

use nalgebra::{Point3, Vector3};
use ptv::formats;
use ptv::photogrammetry::simulate::{self, RigSpec};

#[path = "common/server.rs"]
mod server;
use rand::seq::SliceRandom;
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};
use server::Server;

struct Options {
    frames: usize,
    particles: usize,
    clients: usize,
    workers: Option<usize>,
    recovery: bool,
    tracked: bool,
    database: Option<String>,
    log: bool,
}

fn options() -> Options {
    let mut options = Options {
        frames: 200,
        particles: 2000,
        clients: 4,
        workers: None,
        recovery: true,
        tracked: true,
        database: None,
        log: false,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut number = |name: &str| -> usize {
            args.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{name} needs a number"))
        };
        match arg.as_str() {
            "--frames" => options.frames = number("--frames").max(3),
            "--particles" => options.particles = number("--particles"),
            "--clients" => options.clients = number("--clients").max(1),
            "--workers" => options.workers = Some(number("--workers")),
            "--no-recovery" => options.recovery = false,
            "--untracked" => options.tracked = false,
            "--database" => options.database = args.next(),
            "--log" => options.log = true,
            _ => {}
        }
    }
    options
}

fn main() {
    let options = options();
    if options.log {
        // As `ptv serve` logs (`service::runtime`).
        tracing_subscriber::fmt()
            .with_writer(std::io::stderr)
            .with_target(false)
            .init();
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(run(options));
}

async fn view(client: &reqwest::Client, address: &str, sequence: i64) -> Value {
    client
        .get(format!("{address}/api/v1/sequences/{sequence}"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap()
}

async fn run(options: Options) {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().unwrap();
    let volume = spec.volume;
    let size = volume.max - volume.min;
    let spacing = (size.x * size.y * size.z / options.particles as f64).cbrt();
    let velocity = Vector3::new(2.0, 1.0, 0.5).normalize() * 0.3 * spacing;
    eprintln!(
        "simulating {} frames of {} particles (spacing {spacing:.2} mm, {:.2} mm a frame)...",
        options.frames,
        options.particles,
        velocity.norm()
    );
    let mut rng = simulate::rng(2024);
    let first = simulate::particles(&volume, options.particles, &mut rng);
    let mut forms: Vec<(usize, Vec<String>)> = (0..options.frames)
        .map(|f| {
            let points: Vec<Point3<f64>> = first
                .iter()
                .map(|p| {
                    let moved = p - volume.min + velocity * f as f64;
                    volume.min + Vector3::from_fn(|i, _| moved[i].rem_euclid(size[i]))
                })
                .collect();
            let frame = simulate::target_frame(&cameras, &points, 0.05, 0.05, &mut rng);
            (
                f,
                frame
                    .targets
                    .iter()
                    .map(|t| formats::csv::format_targets(t))
                    .collect(),
            )
        })
        .collect();
    forms.shuffle(&mut rng);

    let data_dir = tempfile::tempdir().unwrap();
    let database = options.database.as_deref();
    let server = Server::start(data_dir.path(), options.workers, database).await;
    let address = server.address.clone();
    let client = reqwest::Client::new();
    let api = |address: &str, path: &str| format!("{address}/api/v1{path}");
    let calibration: Value = client
        .post(api(&address, "/calibrations"))
        .body(formats::calibration::to_json(&cameras))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let v = &volume;
    let mut settings = json!({
        "calibration_id": calibration["id"],
        "matching": {"volume": [v.min.x, v.max.x, v.min.y, v.max.y, v.min.z, v.max.z]},
    });
    if options.tracked {
        settings["tracking"] =
            json!({"max_velocity": 1.5 * velocity.norm(), "recovery": options.recovery});
    }
    let sequence: Value = client
        .post(api(&address, "/sequences"))
        .json(&settings)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let sequence = sequence["id"].as_i64().unwrap();

    let started = Instant::now();
    let forms = std::sync::Arc::new(forms);
    let mut tasks = tokio::task::JoinSet::new();
    for c in 0..options.clients {
        let (forms, address, clients) = (forms.clone(), address.clone(), options.clients);
        tasks.spawn(async move {
            let client = reqwest::Client::new();
            for (frame, tables) in forms.iter().skip(c).step_by(clients) {
                let mut form = Form::new().text("frame", frame.to_string());
                for (camera, text) in tables.iter().enumerate() {
                    form = form.part(
                        format!("targets{camera}"),
                        Part::text(text.clone()).file_name("t.csv"),
                    );
                }
                let response = client
                    .post(format!("{address}/api/v1/sequences/{sequence}/frames"))
                    .multipart(form)
                    .send()
                    .await
                    .unwrap();
                assert_eq!(response.status().as_u16(), 202);
            }
        });
    }
    while tasks.join_next().await.is_some() {}
    let uploaded = started.elapsed();
    let last = options.frames as i64 - 1;
    let (mut processed, mut tracked) = (None, None);
    while tracked.is_none() {
        let body = view(&client, &address, sequence).await;
        if processed.is_none() && body["frames"]["done"] == options.frames as i64 {
            processed = Some(started.elapsed());
            if !options.tracked {
                tracked = processed;
            }
        }
        if body["tracking"]["tracked_through"] == last {
            tracked = Some(started.elapsed());
        }
        assert_eq!(body["frames"]["failed"], 0, "{body}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let processed = processed.unwrap_or(tracked.unwrap());
    let tracked = tracked.unwrap();
    let n = options.frames as f64;
    if !options.tracked {
        let workers = server.workers;
        server.stop().await;
        println!(
            "{} frames of {} particles, {} clients, {} workers, untracked, on {}",
            options.frames,
            options.particles,
            options.clients,
            workers,
            if database.is_some() {
                "PostgreSQL"
            } else {
                "SQLite"
            }
        );
        println!("uploaded in {:.2} s", uploaded.as_secs_f64());
        println!(
            "all processed after {:.2} s ({:.1} frames/s)",
            processed.as_secs_f64(),
            n / processed.as_secs_f64()
        );
        return;
    }
    // Stop before finishing: the restarted service rebuilds the tracker.
    server.stop().await;

    let server = Server::start(data_dir.path(), options.workers, database).await;
    let address = server.address.clone();
    let restarted = Instant::now();
    let response = client
        .post(api(
            &address,
            &format!("/sequences/{sequence}/tracking/finish"),
        ))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status().as_u16(), 202);
    let finished = loop {
        let body = view(&client, &address, sequence).await;
        if body["tracking"]["state"] == "finished" {
            break (
                restarted.elapsed(),
                body["tracking"]["trajectories"].clone(),
            );
        }
        assert_eq!(body["tracking"]["state"], "tracking", "{body}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    let csv_started = Instant::now();
    let csv = client
        .get(api(
            &address,
            &format!("/sequences/{sequence}/trajectories?format=csv"),
        ))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let csv_time = csv_started.elapsed();
    let workers = server.workers;
    server.stop().await;

    println!(
        "{} frames of {} particles, {} clients, {} workers, {}, on {}",
        options.frames,
        options.particles,
        options.clients,
        workers,
        if options.recovery {
            "with the image-space recovery"
        } else {
            "without the image-space recovery"
        },
        if database.is_some() {
            "PostgreSQL"
        } else {
            "SQLite"
        }
    );
    println!("uploaded in {:.2} s", uploaded.as_secs_f64());
    println!(
        "all processed after {:.2} s ({:.1} frames/s)",
        processed.as_secs_f64(),
        n / processed.as_secs_f64()
    );
    println!(
        "all tracked after {:.2} s ({:.1} frames/s); tracking ended {:.0} ms after the last frame was processed",
        tracked.as_secs_f64(),
        n / tracked.as_secs_f64(),
        (tracked.saturating_sub(processed)).as_secs_f64() * 1e3
    );
    println!(
        "after a restart: replay of {} frames and finish in {:.2} s ({:.1} ms a frame); {} trajectories",
        options.frames,
        finished.0.as_secs_f64(),
        finished.0.as_secs_f64() * 1e3 / n,
        finished.1
    );
    println!(
        "trajectory CSV: {} rows, {:.1} MB in {:.2} s",
        csv.lines().count() - 1,
        csv.len() as f64 / 1e6,
        csv_time.as_secs_f64()
    );
}
