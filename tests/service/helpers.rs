//! Helpers: the real service on port 0 with a fresh data directory (in
//! this process, or the `ptv` binary as a child process), a synthetic
//! experiment from the simulator, and multipart uploads.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use nalgebra::Point3;
use ptv::formats;
use ptv::photogrammetry::simulate::{self, RenderSpec, RigSpec, TargetFrame};
use ptv::photogrammetry::{Camera, GreyImage, GreyPixels, Volume};
use ptv::service::{Application, JobLimits, ServeArgs, Timeouts};
use reqwest::multipart::{Form, Part};
use serde_json::{json, Value};
use tempfile::TempDir;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// Longest wait for jobs to finish before a test gives up (a hang guard,
/// not a speed requirement).
pub const PATIENCE: Duration = Duration::from_secs(600);

/// A running service in this process.
pub struct TestApp {
    /// `http://127.0.0.1:PORT`.
    pub address: String,
    /// A client.
    pub client: reqwest::Client,
    /// The data directory (removed on drop).
    pub data_dir: TempDir,
    /// What the service's handlers and workers share (its store, for
    /// fault injection).
    pub state: std::sync::Arc<ptv::service::AppState>,
    stop: Option<oneshot::Sender<()>>,
    server: Option<JoinHandle<()>>,
}

/// Settings for a test service: port 0, 2 workers, 64 MiB uploads.
pub fn test_args(data_dir: &Path, api_token: Option<&str>) -> ServeArgs {
    ServeArgs {
        bind: "127.0.0.1:0".parse().unwrap(),
        storage: ptv::service::infra::config::Storage {
            database: crate::postgres::database_url(data_dir).map(|url| url.parse().unwrap()),
            objects: object_store_args(data_dir),
            ..ptv::service::infra::config::Storage::in_directory(data_dir)
        },
        workers: Some(2),
        max_upload_mb: 64,
        api_token: api_token.map(str::to_owned),
        max_cpu_requests: None,
        max_connections: None,
        max_export_points: ptv::service::infra::config::DEFAULT_MAX_EXPORT_POINTS,
        timeouts: Timeouts::default(),
        job_limits: JobLimits::default(),
        lease: Default::default(),
    }
}

/// The S3-compatible server of this test process under
/// `PTV_TEST_OBJECT_STORE=s3`: one `s3s-fs` child process (installed by
/// `.ci/run` into `target/tools`, or named by `PTV_TEST_S3_SERVER`) on a
/// free port, over a temporary directory, started at the first use. Every
/// server a test starts gets its own prefix in its bucket: the name of
/// its data directory (unique per test, and the same across a restart on
/// that directory). Unset: images in the data directory, as by default.
pub struct S3Server {
    /// `http://127.0.0.1:PORT`.
    pub endpoint: String,
    /// The port, kept across a restart.
    pub port: u16,
    /// The directory its buckets live in, kept across a restart.
    pub root: PathBuf,
    /// The running server (a watchdog shell around `s3s-fs`: it ends when
    /// this test process does).
    child: Option<Child>,
}

/// The bucket the tests' servers use.
pub const TEST_BUCKET: &str = "ptv-test";

/// Whether this run stores images in the test S3 server.
pub fn s3_tests() -> bool {
    std::env::var("PTV_TEST_OBJECT_STORE").is_ok_and(|v| v == "s3")
}

/// The test process's S3 server, started at the first call.
pub fn s3_server() -> &'static S3Server {
    static SERVER: std::sync::OnceLock<S3Server> = std::sync::OnceLock::new();
    SERVER.get_or_init(|| {
        // The variables every server reads (in this process, and inherited
        // by `ptv serve` and `ptv worker` children): set once, before the
        // first server of the process is built.
        std::env::set_var("AWS_ACCESS_KEY_ID", "ptv-test");
        std::env::set_var("AWS_SECRET_ACCESS_KEY", "ptv-test-secret");
        std::env::set_var("AWS_REGION", "us-east-1");
        std::env::set_var("AWS_ALLOW_HTTP", "true");
        S3Server::launch()
    })
}

impl S3Server {
    /// Starts an S3 server of its own (the shared one: [`s3_server`]) on a
    /// free port over a new directory holding the bucket [`TEST_BUCKET`].
    pub fn launch() -> S3Server {
        static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let root = std::env::temp_dir().join(format!("ptv-test-s3-{}-{n}", std::process::id()));
        std::fs::create_dir_all(root.join(TEST_BUCKET)).unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut server = S3Server {
            endpoint: format!("http://127.0.0.1:{port}"),
            port,
            root,
            child: None,
        };
        server.start();
        server
    }

    /// Starts `s3s-fs` on its port and directory and waits until it
    /// accepts connections.
    pub fn start(&mut self) {
        let binary = std::env::var("PTV_TEST_S3_SERVER")
            .map(PathBuf::from)
            .unwrap_or_else(|_| repository().join("target/tools/bin/s3s-fs"));
        assert!(
            binary.exists(),
            "PTV_TEST_OBJECT_STORE=s3 needs the S3 server {}: cargo install s3s-fs --version \
             0.14.1 --features binary --locked --root target/tools (.ci/run does)",
            binary.display()
        );
        // The shell ends s3s-fs and removes its directory once this test
        // process is gone (a test process's statics are never dropped).
        let script = format!(
            "\"$0\" --host 127.0.0.1 --port {port} --access-key ptv-test \
             --secret-key ptv-test-secret \"$1\" >/dev/null 2>&1 & child=$!; \
             while kill -0 {parent} 2>/dev/null && kill -0 $child 2>/dev/null; do sleep 1; done; \
             kill $child 2>/dev/null; kill -0 {parent} 2>/dev/null || rm -rf \"$1\"",
            port = self.port,
            parent = std::process::id(),
        );
        let child = Command::new("sh")
            .args(["-c", &script])
            .arg(&binary)
            .arg(&self.root)
            .stdin(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("the S3 server starts");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(30);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < deadline, "the S3 server did not start");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Stops the server (SIGKILL to `s3s-fs` through its watchdog, which
    /// then ends), as a crash or a network cut would.
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = Command::new("pkill")
                .args(["-KILL", "-P", &child.id().to_string()])
                .status();
            let _ = child.wait();
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
            assert!(Instant::now() < deadline, "the S3 server did not stop");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// `--object-store` of a server on `data_dir`: under
/// `PTV_TEST_OBJECT_STORE=s3`, `s3://ptv-test/NAME` with NAME the data
/// directory's name; else none (the data directory). The first call starts
/// the test process's S3 server and sets the variables every server reads
/// (in this process, and inherited by `ptv serve` and `ptv worker`
/// children).
pub fn object_store_url(data_dir: &Path) -> Option<String> {
    if !s3_tests() {
        return None;
    }
    let _ = s3_server();
    let name = data_dir.file_name()?.to_string_lossy();
    Some(format!(
        "s3://{TEST_BUCKET}/{}",
        name.trim_start_matches('.')
    ))
}

impl Drop for S3Server {
    fn drop(&mut self) {
        self.stop();
        let _ = std::fs::remove_dir_all(&self.root);
    }
}

/// The object store settings of an in-process server on `data_dir`.
pub fn object_store_args(data_dir: &Path) -> ptv::service::infra::config::ObjectStoreArgs {
    let url = object_store_url(data_dir);
    ptv::service::infra::config::ObjectStoreArgs {
        s3_endpoint: url.as_ref().map(|_| s3_server().endpoint.clone()),
        url: url.map(|url| url.parse().unwrap()),
    }
}

/// The arguments that give a `ptv serve` or `ptv worker` child on
/// `data_dir` the test's object store (none without one).
pub fn object_store_flags(data_dir: &Path) -> Vec<String> {
    match object_store_url(data_dir) {
        Some(url) => vec![
            "--object-store".to_owned(),
            url,
            "--s3-endpoint".to_owned(),
            s3_server().endpoint.clone(),
        ],
        None => Vec::new(),
    }
}

/// The hashes of the images stored for the servers on `data_dir`, in
/// whichever backend the tests run (the data directory's `images/`, or
/// the test bucket's prefix).
pub async fn stored_images(data_dir: &Path) -> Vec<String> {
    let args = object_store_args(data_dir);
    let store = ptv::service::ops::images::ImageStore::open_shared(data_dir, args.location())
        .await
        .expect("the image store opens");
    let mut stored = store.stored().await.expect("the image store lists");
    stored.sort();
    stored
}

/// Starts the service with a fresh data directory.
pub async fn spawn_app() -> TestApp {
    spawn_app_with(None).await
}

/// Starts the service with a fresh data directory and an API token.
pub async fn spawn_app_with(api_token: Option<&str>) -> TestApp {
    spawn(tempfile::tempdir().unwrap(), api_token).await
}

/// Starts the service again on a data directory a stopped one left.
pub async fn spawn_app_in(data_dir: TempDir) -> TestApp {
    spawn(data_dir, None).await
}

/// Starts the service with a fresh data directory and the test settings
/// changed by `configure`.
pub async fn spawn_app_configured(configure: impl FnOnce(&mut ServeArgs)) -> TestApp {
    let data_dir = tempfile::tempdir().unwrap();
    let mut args = test_args(data_dir.path(), None);
    configure(&mut args);
    spawn_with_args(data_dir, args).await
}

async fn spawn(data_dir: TempDir, api_token: Option<&str>) -> TestApp {
    let args = test_args(data_dir.path(), api_token);
    spawn_with_args(data_dir, args).await
}

async fn spawn_with_args(data_dir: TempDir, args: ServeArgs) -> TestApp {
    let app = Application::build(args).await.expect("the service starts");
    let address = format!("http://{}", app.local_addr().unwrap());
    let state = app.state();
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(async move {
        app.run_until(async {
            let _ = stopped.await;
        })
        .await
        .expect("the service stops cleanly");
    });
    TestApp {
        address,
        client: reqwest::Client::new(),
        data_dir,
        state,
        stop: Some(stop),
        server: Some(server),
    }
}

impl TestApp {
    /// `address` + `/api/v1` + `path`.
    pub fn api(&self, path: &str) -> String {
        format!("{}/api/v1{path}", self.address)
    }

    /// Stops the service gracefully and waits for it.
    pub async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(server) = self.server.take() {
            server.await.unwrap();
        }
    }

    /// Stops the service gracefully and hands over its data directory.
    pub async fn stop_keeping_data(mut self) -> TempDir {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(server) = self.server.take() {
            server.await.unwrap();
        }
        let TestApp { data_dir, .. } = self;
        data_dir
    }

    /// POSTs JSON; status and body.
    pub async fn post_json(&self, path: &str, body: &Value) -> (u16, Value) {
        let response = self
            .client
            .post(self.api(path))
            .json(body)
            .send()
            .await
            .unwrap();
        status_and_json(response).await
    }

    /// GETs JSON; status and body.
    pub async fn get_json(&self, path: &str) -> (u16, Value) {
        let response = self.client.get(self.api(path)).send().await.unwrap();
        status_and_json(response).await
    }

    /// GETs `url` (a whole URL: `/metrics` lies outside the API), which
    /// must answer 200; its body as text.
    pub async fn get_text(&self, url: String) -> String {
        let response = self.client.get(url).send().await.unwrap();
        assert_eq!(response.status().as_u16(), 200, "{}", response.url());
        response.text().await.unwrap()
    }

    /// Creates a calibration from cameras; its id.
    pub async fn create_calibration(&self, cameras: &[Camera]) -> i64 {
        let response = self
            .client
            .post(self.api("/calibrations"))
            .header("content-type", "application/json")
            .body(formats::calibration::to_json(cameras))
            .send()
            .await
            .unwrap();
        let (status, body) = status_and_json(response).await;
        assert_eq!(status, 201, "{body}");
        body["id"].as_i64().unwrap()
    }

    /// Creates a sequence; its id.
    pub async fn create_sequence(&self, calibration_id: i64, volume: &Volume, keep: bool) -> i64 {
        let (status, body) = self
            .post_json("/sequences", &sequence_body(calibration_id, volume, keep))
            .await;
        assert_eq!(status, 201, "{body}");
        body["id"].as_i64().unwrap()
    }

    /// The simulator's rig as a calibration, and a sequence on it that
    /// keeps no images; the rig and the sequence's id.
    pub async fn rig_sequence(&self) -> (Rig, i64) {
        let rig = rig();
        let calibration = self.create_calibration(&rig.cameras).await;
        let sequence = self.create_sequence(calibration, &rig.volume, false).await;
        (rig, sequence)
    }

    /// Uploads a frame; status and body.
    pub async fn upload(&self, sequence: i64, form: Form) -> (u16, Value) {
        upload(&self.client, &self.address, sequence, form).await
    }

    /// Waits until no frame of the sequence is queued or running; the
    /// sequence's view.
    pub async fn wait_for_sequence(&self, sequence: i64) -> Value {
        wait_for_sequence(&self.client, &self.address, sequence).await
    }

    /// Opens the service's database (read-only on SQLite) for consistency
    /// checks.
    pub async fn database(&self) -> sqlx::AnyPool {
        open_database(self.data_dir.path()).await
    }
}

/// The body of `POST /sequences` for the synthetic rig.
pub fn sequence_body(calibration_id: i64, volume: &Volume, keep: bool) -> Value {
    json!({
        "calibration_id": calibration_id,
        "name": "synthetic",
        "matching": {"volume": [volume.min.x, volume.max.x, volume.min.y, volume.max.y,
                                volume.min.z, volume.max.z]},
        "keep_images": keep,
    })
}

/// Uploads a frame to the service at `address`.
pub async fn upload(
    client: &reqwest::Client,
    address: &str,
    sequence: i64,
    form: Form,
) -> (u16, Value) {
    let response = client
        .post(format!("{address}/api/v1/sequences/{sequence}/frames"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    status_and_json(response).await
}

/// Creates the rig's calibration and a sequence on it (images not kept)
/// on the service at `address`: the sequence's id.
pub async fn create_rig_sequence(client: &reqwest::Client, address: &str, rig: &Rig) -> i64 {
    let response = client
        .post(format!("{address}/api/v1/calibrations"))
        .body(ptv::formats::calibration::to_json(&rig.cameras))
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 201, "{body}");
    let calibration = body["id"].as_i64().unwrap();
    let response = client
        .post(format!("{address}/api/v1/sequences"))
        .json(&sequence_body(calibration, &rig.volume, false))
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 201, "{body}");
    body["id"].as_i64().unwrap()
}

/// Waits until no frame of the sequence is queued or running.
pub async fn wait_for_sequence(client: &reqwest::Client, address: &str, sequence: i64) -> Value {
    let start = Instant::now();
    loop {
        let response = client
            .get(format!("{address}/api/v1/sequences/{sequence}"))
            .send()
            .await
            .unwrap();
        let (status, body) = status_and_json(response).await;
        assert_eq!(status, 200, "{body}");
        let frames = &body["frames"];
        if frames["queued"] == 0 && frames["running"] == 0 {
            return body;
        }
        assert!(start.elapsed() < PATIENCE, "frames still pending: {body}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Opens the database of the servers on a data directory: its SQLite file
/// read-only, or under `PTV_TEST_DATABASE=postgres` its PostgreSQL
/// database. Queries are written once for both (`$1` parameters).
pub async fn open_database(data_dir: &Path) -> sqlx::AnyPool {
    connect_database(data_dir, "ro").await
}

/// [`open_database`] for writing (a test that stages a state by hand).
pub async fn open_database_writable(data_dir: &Path) -> sqlx::AnyPool {
    connect_database(data_dir, "rw").await
}

/// The database of the servers on `data_dir`, its SQLite file opened in
/// `mode` (`ro`, `rw`).
async fn connect_database(data_dir: &Path, mode: &str) -> sqlx::AnyPool {
    sqlx::any::install_default_drivers();
    let url = crate::postgres::database_url(data_dir).unwrap_or_else(|| {
        format!(
            "sqlite://{}?mode={mode}",
            data_dir.join("ptv.sqlite").display()
        )
    });
    sqlx::any::AnyPoolOptions::new()
        .max_connections(1)
        .connect(&url)
        .await
        .unwrap()
}

/// A count from the database.
pub async fn count(db: &sqlx::AnyPool, sql: &str) -> i64 {
    let (n,): (i64,) = sqlx::query_as(sql).fetch_one(db).await.unwrap();
    n
}

/// Seconds since 1970 of a stored timestamp (UTC RFC 3339 with
/// milliseconds, `2026-11-25T23:53:40.123Z`, as both engines write them).
pub fn unix_seconds(stamp: &str) -> f64 {
    let field = |range: std::ops::Range<usize>| -> i64 {
        stamp
            .get(range)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("not a stored timestamp: `{stamp}`"))
    };
    let (year, month, day) = (field(0..4), field(5..7), field(8..10));
    // Days from civil (Howard Hinnant's algorithm).
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let doy = (153 * ((month + 9) % 12) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    let seconds: f64 = stamp
        .get(17..stamp.len() - 1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("not a stored timestamp: `{stamp}`"));
    (days * 86_400 + field(11..13) * 3600 + field(14..16) * 60) as f64 + seconds
}

/// A memory grant the service logged (`service::budget`: the grants of
/// a quarter of its budget or more), with when it was taken and released
/// (seconds since 1970; `None`: still held).
#[derive(Clone, Debug)]
pub struct LoggedGrant {
    /// Its number in the process.
    pub number: u64,
    /// MiB.
    pub mib: u64,
    /// What it was for.
    pub what: String,
    /// Taken at.
    pub taken: f64,
    /// Released at.
    pub released: Option<f64>,
}

/// The memory grants in a service's log (its standard error).
pub fn logged_grants(log: &str) -> Vec<LoggedGrant> {
    let mut grants: Vec<LoggedGrant> = Vec::new();
    for line in log.lines() {
        // Without the terminal's colours.
        let mut plain = String::with_capacity(line.len());
        let mut chars = line.chars();
        while let Some(c) = chars.next() {
            if c == '\u{1b}' {
                for c in chars.by_ref() {
                    if c == 'm' {
                        break;
                    }
                }
            } else {
                plain.push(c);
            }
        }
        let stamp = plain.split_whitespace().next().unwrap_or("");
        let number_of = |rest: &str| -> (u64, u64, String) {
            // "grant N, M MiB[ of ...], ..., for WHAT"
            let rest = rest.strip_prefix("grant ").unwrap();
            let (number, rest) = rest.split_once(", ").unwrap();
            let (mib, rest) = rest.split_once(" MiB").unwrap();
            let what = rest.split_once(", for ").unwrap().1.to_owned();
            (number.parse().unwrap(), mib.parse().unwrap(), what)
        };
        if let Some((_, rest)) = plain.split_once("memory granted: ") {
            let (number, mib, what) = number_of(rest);
            grants.push(LoggedGrant {
                number,
                mib,
                what,
                taken: unix_seconds(stamp),
                released: None,
            });
        } else if let Some((_, rest)) = plain.split_once("memory released: ") {
            let (number, _, _) = number_of(rest);
            let grant = grants
                .iter_mut()
                .find(|g| g.number == number)
                .unwrap_or_else(|| panic!("grant {number} released but not taken: {plain}"));
            grant.released = Some(unix_seconds(stamp));
        }
    }
    grants
}

/// This machine's clock, in seconds since 1970.
pub fn unix_seconds_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// A response's content type ("" when it has none).
pub fn content_type(response: &reqwest::Response) -> String {
    response
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_owned()
}

/// The status and the JSON body (or the text as a JSON string).
pub async fn status_and_json(response: reqwest::Response) -> (u16, Value) {
    let status = response.status().as_u16();
    let content_type = content_type(&response);
    let text = response.text().await.unwrap();
    if status >= 400 {
        assert_eq!(content_type, "application/problem+json", "{status}: {text}");
    }
    let body = serde_json::from_str(&text).unwrap_or(Value::String(text));
    (status, body)
}

/// The synthetic 4-camera rig of the simulator.
pub struct Rig {
    /// The cameras.
    pub cameras: Vec<Camera>,
    /// The observation volume.
    pub volume: Volume,
}

/// The simulator's convergent 4-camera rig.
pub fn rig() -> Rig {
    let spec = RigSpec::convergent(4);
    Rig {
        cameras: spec.build().unwrap(),
        volume: spec.volume,
    }
}

/// A rendered frame: the particles and the PNG of every camera.
pub struct RenderedFrame {
    /// The true particles.
    pub points: Vec<Point3<f64>>,
    /// Per camera, its image.
    pub images: Vec<GreyImage>,
}

impl Rig {
    /// Renders `count` particles into every camera (8-bit, 2.5 px spots).
    pub fn render(&self, count: usize, seed: u64) -> RenderedFrame {
        let mut rng = simulate::rng(seed);
        let points = simulate::particles(&self.volume, count, &mut rng);
        let images = simulate::render_frame(
            &self.cameras,
            &points,
            &RenderSpec::eight_bit(2.5),
            &mut rng,
        )
        .into_iter()
        .map(|r| r.image)
        .collect();
        RenderedFrame { points, images }
    }

    /// Targets of `count` particles with 0.05 px noise, as a camera-side
    /// detector would send them.
    pub fn targets(&self, count: usize, seed: u64) -> TargetFrame {
        let mut rng = simulate::rng(seed);
        let points = simulate::particles(&self.volume, count, &mut rng);
        simulate::target_frame(&self.cameras, &points, 0.05, 0.0, &mut rng)
    }
}

/// An 8- or 16-bit greyscale PNG (the service's own encoder).
pub fn png(image: &GreyImage) -> Vec<u8> {
    formats::image::encode_png(image, "a test image").unwrap()
}

/// The raw 8-bit samples of an image.
pub fn raw8(image: &GreyImage) -> Vec<u8> {
    match image.pixels() {
        GreyPixels::Eight(samples) => samples.clone(),
        GreyPixels::Sixteen(_) => panic!("an 8-bit image was expected"),
    }
}

/// A frame upload of image files (`cam0`, ...).
pub fn image_form(frame: i64, files: &[Vec<u8>]) -> Form {
    let mut form = Form::new().text("frame", frame.to_string());
    for (camera, bytes) in files.iter().enumerate() {
        form = form.part(
            format!("cam{camera}"),
            Part::bytes(bytes.clone()).file_name(format!("cam{camera}.png")),
        );
    }
    form
}

/// A frame upload of targets (`targets0`, ...) as CSV.
pub fn targets_form(frame: i64, frame_targets: &TargetFrame) -> Form {
    let mut form = Form::new().text("frame", frame.to_string());
    for (camera, targets) in frame_targets.targets.iter().enumerate() {
        form = form.part(
            format!("targets{camera}"),
            Part::text(formats::csv::format_targets(targets)).file_name("t.csv"),
        );
    }
    form
}

/// The `ptv` binary running as a child process.
pub struct ServiceProcess {
    /// The child.
    pub child: Child,
    /// `http://127.0.0.1:PORT`.
    pub address: String,
}

impl ServiceProcess {
    /// Starts `ptv serve` on port 0 with `data_dir` and reads the address it
    /// prints.
    pub fn start(data_dir: &Path, workers: usize) -> ServiceProcess {
        ServiceProcess::start_with(data_dir, workers, &[])
    }

    /// [`ServiceProcess::start`] with more arguments (`--lease-secs 3`).
    pub fn start_with(data_dir: &Path, workers: usize, more: &[&str]) -> ServiceProcess {
        ServiceProcess::start_with_stderr(data_dir, workers, more, Stdio::null())
    }

    /// [`ServiceProcess::start_with`], its log (standard error) written to
    /// the file `log`.
    pub fn start_logged(
        data_dir: &Path,
        workers: usize,
        more: &[&str],
        log: &Path,
    ) -> ServiceProcess {
        let file = std::fs::File::create(log).expect("the log file is created");
        ServiceProcess::start_with_stderr(data_dir, workers, more, Stdio::from(file))
    }

    fn start_with_stderr(
        data_dir: &Path,
        workers: usize,
        more: &[&str],
        stderr: Stdio,
    ) -> ServiceProcess {
        let mut child = Command::new(env!("CARGO_BIN_EXE_ptv"))
            .args(["serve", "--bind", "127.0.0.1:0", "--workers"])
            .arg(workers.to_string())
            .arg("--data-dir")
            .arg(data_dir)
            .args(database_args(data_dir))
            .args(object_store_flags(data_dir))
            .args(more)
            .stdout(Stdio::piped())
            .stderr(stderr)
            .spawn()
            .expect("the ptv binary starts");
        let stdout = child.stdout.take().unwrap();
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line).unwrap();
        let address: SocketAddr = line
            .trim()
            .strip_prefix("listening on http://")
            .unwrap_or_else(|| panic!("unexpected first line `{line}`"))
            .parse()
            .unwrap();
        ServiceProcess {
            child,
            address: format!("http://{address}"),
        }
    }

    /// The process's peak resident memory so far (`VmHWM` in
    /// `/proc/PID/status`), in MiB: the bound the hostile-request tests
    /// (`hostile`) assert, measured on the server alone, not on this test
    /// process and its other tests.
    pub fn peak_memory_mib(&self) -> f64 {
        peak_memory_mib(self.child.id())
    }

    /// Kills the process (SIGKILL: no chance to clean up) and reaps it.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for ServiceProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `ptv worker` as a child process (killed when dropped).
pub struct WorkerProcess {
    /// The child.
    pub child: Child,
}

impl WorkerProcess {
    /// Starts `ptv worker --data-dir DATA_DIR` with `more` arguments and
    /// environment variables `env`.
    pub fn start(data_dir: &Path, more: &[&str], env: &[(&str, &str)]) -> WorkerProcess {
        let child = Command::new(env!("CARGO_BIN_EXE_ptv"))
            .args(["worker", "--data-dir"])
            .arg(data_dir)
            .args(database_args(data_dir))
            .args(object_store_flags(data_dir))
            .args(more)
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("the ptv binary starts");
        WorkerProcess { child }
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Kills the process (SIGKILL) and reaps it.
    pub fn kill(&mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `--database URL` for a child process on `data_dir` under
/// `PTV_TEST_DATABASE=postgres`; nothing on SQLite.
pub fn database_args(data_dir: &Path) -> Vec<String> {
    crate::postgres::database_url(data_dir)
        .map(|url| vec!["--database".to_owned(), url])
        .unwrap_or_default()
}

/// The process id in a worker's name (`HOST:PID:RANDOM/INDEX`).
pub fn worker_pid(worker: &str) -> Option<u32> {
    let instance = worker.split('/').next()?;
    instance.rsplit(':').nth(1)?.parse().ok()
}

/// The repository's root.
pub fn repository() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The parts of a `/calibrations/solve` request for the rig: a setup with
/// sensor and media only (no orientation: zeros, c = 1, no distortion),
/// a 3D target of control points, and their noisy images per camera.
pub struct SolveInput {
    /// The setup JSON.
    pub setup: String,
    /// The calibration block (`id X Y Z`).
    pub control: String,
    /// Per camera, `id x y` lines.
    pub observations: Vec<String>,
    /// The control points.
    pub target: Vec<ptv::photogrammetry::calibrate::ControlPoint>,
}

impl Rig {
    /// A calibration target of `points` control points filling the volume
    /// widened in depth to ±70 mm (a calibration needs depth; the cameras
    /// see all of it), observed with `noise_px` of noise.
    pub fn solve_input(&self, points: usize, noise_px: f64, seed: u64) -> SolveInput {
        let mut rng = simulate::rng(seed);
        let mut volume = self.volume;
        volume.min.z = volume.min.z.min(-70.0);
        volume.max.z = volume.max.z.max(70.0);
        let target =
            simulate::calibration_target(simulate::TargetShape::Volume, &volume, points, &mut rng);
        let observations = simulate::observe_target(&self.cameras, &target, noise_px, &mut rng);
        let mut setup: Value =
            serde_json::from_str(&formats::calibration::to_json(&self.cameras)).unwrap();
        for camera in setup["cameras"].as_array_mut().unwrap() {
            let camera = camera.as_object_mut().unwrap();
            camera.insert("position".into(), json!([0.0, 0.0, 0.0]));
            camera.insert("angles".into(), json!([0.0, 0.0, 0.0]));
            camera.insert("principal_distance".into(), json!(1.0));
            for field in ["principal_point", "radial", "decentering", "affine"] {
                camera.remove(field);
            }
        }
        SolveInput {
            setup: setup.to_string(),
            control: formats::control::format_control_points(&target),
            observations: observations
                .iter()
                .map(|marks| formats::control::format_mark_observations(marks))
                .collect(),
            target,
        }
    }
}

impl SolveInput {
    /// The setup with the orientation fields removed (`position`, `angles`,
    /// `principal_distance`): sensor and media only. With `drop`, that
    /// field of camera 1 goes too.
    pub fn bare_setup(&self, drop: Option<&str>) -> String {
        let mut setup: Value = serde_json::from_str(&self.setup).unwrap();
        for (k, camera) in setup["cameras"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .enumerate()
        {
            let camera = camera.as_object_mut().unwrap();
            for field in ["position", "angles", "principal_distance"] {
                camera.remove(field);
            }
            if k == 1 {
                if let Some(field) = drop {
                    camera.remove(field);
                }
            }
        }
        setup.to_string()
    }

    /// The multipart form, with `options` if given.
    pub fn form(&self, options: Option<&Value>) -> Form {
        let mut form = Form::new()
            .text("setup", self.setup.clone())
            .text("control", self.control.clone());
        for text in &self.observations {
            form = form.text("observations", text.clone());
        }
        if let Some(options) = options {
            form = form.text("options", options.to_string());
        }
        form
    }
}

impl TestApp {
    /// POSTs a solve request; status and body.
    pub async fn solve(&self, form: Form) -> (u16, Value) {
        let response = self
            .client
            .post(self.api("/calibrations/solve"))
            .multipart(form)
            .send()
            .await
            .unwrap();
        status_and_json(response).await
    }

    /// Waits until the job is neither queued nor running; its view.
    pub async fn wait_for_job(&self, job_id: i64) -> Value {
        let start = Instant::now();
        loop {
            let (status, body) = self.get_json(&format!("/jobs/{job_id}")).await;
            assert_eq!(status, 200, "{body}");
            if body["state"] != "queued" && body["state"] != "running" {
                return body;
            }
            assert!(start.elapsed() < PATIENCE, "job still pending: {body}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// The store of the servers on `data_dir`, as a process of theirs opens
/// it: SQLite in the data directory, or under `PTV_TEST_DATABASE=postgres`
/// the data directory's PostgreSQL database.
pub async fn open_store(data_dir: &Path) -> ptv::service::store::Store {
    use ptv::service::store::Store;
    match crate::postgres::database_url(data_dir) {
        Some(url) => Store::open_postgres(&url.parse().unwrap(), 4)
            .await
            .unwrap(),
        None => Store::open(data_dir, 4).await.unwrap(),
    }
}

/// A process's peak resident memory (`VmHWM`), in MiB.
pub fn peak_memory_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_else(|e| panic!("/proc/{pid}/status: {e}"));
    let kib: f64 = status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|rest| rest.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or_else(|| panic!("no VmHWM in /proc/{pid}/status"));
    kib / 1024.0
}
