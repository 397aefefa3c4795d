//! Load benchmark of the service, end to end: frame sets of 4 cameras at
//! 1280x1024, 8 bits, 2,000 particles each, uploaded over HTTP by several
//! clients at once; a frame counts when its particles are stored (its job
//! succeeded). Reports sustained frame sets per second and the latency
//! from the start of an upload to its particles being stored.
//!
//! ```sh
//! cargo bench --bench service_load                # raw 8-bit images
//! cargo bench --bench service_load -- --png       # PNG images
//! cargo bench --bench service_load -- --real      # test_cavity's real LZW TIFFs
//! cargo bench --bench service_load -- --frames 400 --clients 8 --workers 2
//! cargo bench --bench service_load -- --worker-processes 2 --workers 1
//! cargo bench --bench service_load -- --database postgres://ptv@127.0.0.1:5432/ptv
//! AWS_ENDPOINT_URL=http://127.0.0.1:9014 AWS_ALLOW_HTTP=true AWS_ACCESS_KEY_ID=k \
//!   AWS_SECRET_ACCESS_KEY=s cargo bench --bench service_load -- --object-store s3://ptv/load
//! ```
//!
//! With `--real` the frame sets are the four real ones of
//! `tests/data/openptv/test_cavity_recording` (4 cameras, 1280x1024 8-bit
//! LZW TIFFs as the acquisition PC writes them, ~1,000 particles a set),
//! uploaded in turn, to a sequence the experiment's own files create
//! (`POST /experiments/openptv`: its calibration, detection and matching
//! settings); `--particles` does not apply.
//!
//! Each client polls its job's state every `--poll-ms` (default 2 ms): 4
//! clients make some 2,000 reads a second, cheap in SQLite in this process,
//! a round trip each to a PostgreSQL server competing for the same cores.
//!
//! With `--database URL` the service and the worker processes keep their
//! state and queue in that PostgreSQL database (which must be empty or
//! this bench's own: it is migrated, and the frames added to it) instead
//! of SQLite in the temporary data directory.
//!
//! With `--object-store URL` (or `PTV_OBJECT_STORE`) the images go to that
//! S3-compatible store, in the server and in the worker processes (which
//! inherit the variables), as with `ptv serve --object-store`.
//!
//! With `--worker-processes N` the service in this process serves only
//! (`--workers 0`) and N `ptv worker` processes (each with `--workers`,
//! default 1) on the same data directory process the frames; the job
//! durations are then in those processes, not in this one's metrics.
//!
//! Each client uploads a frame, waits for its job, and uploads the next
//! (closed loop), so the queue never grows without bound and the latency
//! is that of a frame set with `--clients` in flight. The service runs in
//! this process with `--workers` (default: the cores) on a temporary data
//! directory, sharing the machine's cores with the clients as it would
//! with an acquisition PC's uploader.

use std::time::{Duration, Instant};

use image::{ExtendedColorType, ImageEncoder};
use ptv::formats;
use ptv::photogrammetry::simulate::{self, RenderSpec, RigSpec};
use ptv::photogrammetry::GreyPixels;

#[path = "common/server.rs"]
mod server;
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};
use server::Server;

struct Options {
    frames: usize,
    clients: usize,
    workers: Option<usize>,
    particles: usize,
    distinct: usize,
    png: bool,
    real: bool,
    worker_processes: usize,
    database: Option<String>,
    poll_ms: u64,
}

fn options() -> Options {
    let mut options = Options {
        frames: 200,
        clients: 4,
        workers: None,
        particles: 2000,
        distinct: 8,
        png: false,
        real: false,
        worker_processes: 0,
        database: None,
        poll_ms: 2,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut number = |name: &str| -> usize {
            args.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{name} needs a number"))
        };
        match arg.as_str() {
            "--frames" => options.frames = number("--frames"),
            "--clients" => options.clients = number("--clients").max(1),
            "--workers" => options.workers = Some(number("--workers")),
            "--particles" => options.particles = number("--particles"),
            "--png" => options.png = true,
            "--real" => options.real = true,
            "--worker-processes" => options.worker_processes = number("--worker-processes"),
            "--database" => options.database = args.next(),
            // Read where `ptv serve` reads it (and the worker processes
            // inherit it); set before any thread starts.
            "--object-store" => std::env::set_var(
                "PTV_OBJECT_STORE",
                args.next()
                    .expect("--object-store needs s3://bucket/prefix"),
            ),
            "--poll-ms" => options.poll_ms = number("--poll-ms") as u64,
            // cargo bench passes --bench; ignore what we do not know.
            _ => {}
        }
    }
    options
}

fn main() {
    let options = options();
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(run(options));
}

/// The percentile `p` (0..100) of sorted values.
/// The real recording of the test data.
fn recording() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/openptv/test_cavity_recording")
}

/// The recording's experiment (its parameter and calibration files) for
/// `POST /experiments/openptv`.
fn experiment_form() -> Form {
    let mut form = Form::new().text("name", "test_cavity");
    let mut paths: Vec<String> = [
        "ptv.par",
        "criteria.par",
        "targ_rec.par",
        "sequence.par",
        "cal_ori.par",
        "track.par",
        "detect_plate.par",
    ]
    .iter()
    .map(|name| format!("parameters/{name}"))
    .collect();
    for camera in 1..=4 {
        for ext in ["ori", "addpar"] {
            paths.push(format!("cal/cam{camera}.tif.{ext}"));
        }
    }
    for path in paths {
        let bytes = std::fs::read(recording().join(&path)).unwrap();
        form = form.part("file", Part::bytes(bytes).file_name(path));
    }
    form
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let index = ((p / 100.0) * (sorted.len() - 1) as f64).round() as usize;
    sorted[index.min(sorted.len() - 1)]
}

async fn run(options: Options) {
    let spec = RigSpec::convergent(4);
    let cameras = spec.build().unwrap();
    eprintln!(
        "rendering {} distinct frame sets of 4 x 1280x1024 with {} particles...",
        options.distinct, options.particles
    );
    let frame_sets: Vec<Vec<Vec<u8>>> = if options.real {
        (10001..=10004)
            .map(|frame| {
                (1..=4)
                    .map(|camera| {
                        std::fs::read(recording().join(format!("img/cam{camera}.{frame}"))).unwrap()
                    })
                    .collect()
            })
            .collect()
    } else {
        (0..options.distinct)
            .map(|k| {
                let mut rng = simulate::rng(9000 + k as u64);
                let points = simulate::particles(&spec.volume, options.particles, &mut rng);
                simulate::render_frame(&cameras, &points, &RenderSpec::eight_bit(2.5), &mut rng)
                    .into_iter()
                    .map(|rendered| {
                        let GreyPixels::Eight(samples) = rendered.image.pixels() else {
                            unreachable!("8-bit rendering")
                        };
                        if options.png {
                            let mut bytes = Vec::new();
                            image::codecs::png::PngEncoder::new(&mut bytes)
                                .write_image(samples, 1280, 1024, ExtendedColorType::L8)
                                .unwrap();
                            bytes
                        } else {
                            samples.clone()
                        }
                    })
                    .collect()
            })
            .collect()
    };

    let data_dir = tempfile::tempdir().unwrap();
    let (server, worker_processes) = if options.worker_processes == 0 {
        (
            Server::start(
                data_dir.path(),
                options.workers,
                options.database.as_deref(),
            )
            .await,
            Vec::new(),
        )
    } else {
        let per_process = options.workers.unwrap_or(1).max(1).to_string();
        let processes: Vec<WorkerProcess> = (0..options.worker_processes)
            .map(|_| {
                WorkerProcess(
                    std::process::Command::new(env!("CARGO_BIN_EXE_ptv"))
                        .args(["worker", "--workers", &per_process, "--data-dir"])
                        .arg(data_dir.path())
                        .args(options.database.iter().flat_map(|url| ["--database", url]))
                        .stdout(std::process::Stdio::null())
                        .stderr(std::process::Stdio::null())
                        .spawn()
                        .expect("ptv worker starts"),
                )
            })
            .collect();
        (
            Server::start(data_dir.path(), Some(0), options.database.as_deref()).await,
            processes,
        )
    };
    let address = server.address.clone();
    let workers = if worker_processes.is_empty() {
        format!("{}", server.workers)
    } else {
        format!(
            "0 in the server + {} ptv worker processes x {}",
            worker_processes.len(),
            options.workers.unwrap_or(1).max(1)
        )
    };

    let client = reqwest::Client::new();
    let api = |path: &str| format!("{address}/api/v1{path}");
    let calibration: Value = client
        .post(api("/calibrations"))
        .body(formats::calibration::to_json(&cameras))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let v = &spec.volume;
    let sequence = if options.real {
        let imported: Value = client
            .post(api("/experiments/openptv"))
            .multipart(experiment_form())
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        imported["sequence_id"]
            .as_i64()
            .unwrap_or_else(|| panic!("the experiment imports: {imported}"))
    } else {
        let sequence: Value = client
            .post(api("/sequences"))
            .json(&json!({
                "calibration_id": calibration["id"],
                "name": "load",
                "matching": {"volume": [v.min.x, v.max.x, v.min.y, v.max.y, v.min.z, v.max.z]},
                "keep_images": false,
            }))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        sequence["id"].as_i64().unwrap()
    };
    eprintln!(
        "{} frame sets ({}), {} clients, {workers} workers",
        options.frames,
        if options.real {
            "test_cavity's real LZW TIFFs"
        } else if options.png {
            "PNG"
        } else {
            "raw 8-bit"
        },
        options.clients
    );

    let frame_sets = std::sync::Arc::new(frame_sets);
    let next = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let started = Instant::now();
    let mut tasks = tokio::task::JoinSet::new();
    for _ in 0..options.clients {
        let (frame_sets, next, address) = (frame_sets.clone(), next.clone(), address.clone());
        let total = options.frames;
        let raw = !options.png && !options.real;
        let poll_ms = options.poll_ms;
        tasks.spawn(async move {
            let client = reqwest::Client::new();
            let mut latencies = Vec::new();
            let mut particles = 0u64;
            loop {
                let frame = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if frame >= total {
                    return (latencies, particles);
                }
                let files = &frame_sets[frame % frame_sets.len()];
                let mut form = Form::new().text("frame", frame.to_string());
                if raw {
                    form = form
                        .text("width", "1280")
                        .text("height", "1024")
                        .text("bits", "8");
                }
                for (camera, bytes) in files.iter().enumerate() {
                    form = form.part(format!("cam{camera}"), Part::bytes(bytes.clone()));
                }
                let t0 = Instant::now();
                let response = client
                    .post(format!("{address}/api/v1/sequences/{sequence}/frames"))
                    .multipart(form)
                    .send()
                    .await
                    .unwrap();
                assert_eq!(response.status(), 202);
                let accepted: Value = response.json().await.unwrap();
                let job = format!("{address}{}", accepted["job"].as_str().unwrap());
                loop {
                    let state: Value = client.get(&job).send().await.unwrap().json().await.unwrap();
                    match state["state"].as_str() {
                        Some("succeeded") => break,
                        Some("failed") => panic!("frame {frame} failed: {state}"),
                        _ => tokio::time::sleep(Duration::from_millis(poll_ms)).await,
                    }
                }
                latencies.push(t0.elapsed().as_secs_f64());
                let result: Value = client
                    .get(format!(
                        "{address}/api/v1/sequences/{sequence}/frames/{frame}/particles?format=rt_is"
                    ))
                    .send()
                    .await
                    .unwrap()
                    .text()
                    .await
                    .map(|t| json!(t.lines().next().unwrap_or("0").parse::<u64>().unwrap_or(0)))
                    .unwrap();
                particles += result.as_u64().unwrap_or(0);
            }
        });
    }
    let mut latencies = Vec::new();
    let mut particles = 0;
    while let Some(result) = tasks.join_next().await {
        let (l, p) = result.unwrap();
        latencies.extend(l);
        particles += p;
    }
    let elapsed = started.elapsed().as_secs_f64();
    latencies.sort_by(f64::total_cmp);
    let metrics = client
        .get(format!("{address}/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let job_line = |suffix: &str| {
        metrics
            .lines()
            .find(|l| {
                l.starts_with(&format!("ptv_job_duration_seconds_{suffix}{{"))
                    && l.contains("succeeded")
            })
            .and_then(|l| l.rsplit(' ').next())
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    let mean_job = job_line("sum") / job_line("count");
    // With worker processes the jobs' durations are in their metrics.
    let mean_job = if mean_job.is_finite() {
        format!("{:.0} ms", 1e3 * mean_job)
    } else {
        "not measured here".to_owned()
    };
    println!(
        "service_load: {} frame sets in {elapsed:.1} s: {:.2} frame sets/s; latency \
         p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms, max {:.0} ms; job (read, decode, detect, \
         match, store) mean {mean_job}; {:.0} particles per frame set",
        latencies.len(),
        latencies.len() as f64 / elapsed,
        1e3 * percentile(&latencies, 50.0),
        1e3 * percentile(&latencies, 90.0),
        1e3 * percentile(&latencies, 99.0),
        1e3 * latencies.last().copied().unwrap_or(f64::NAN),
        particles as f64 / latencies.len() as f64,
    );
    server.stop().await;
    drop(worker_processes);
}

/// A `ptv worker` child process, stopped (SIGKILL: the bench is over)
/// when dropped.
struct WorkerProcess(std::process::Child);

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
