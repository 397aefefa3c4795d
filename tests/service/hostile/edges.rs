//! Slow bodies, aborted uploads, framing, start-up (issue 29, defects 7,
//! 9 and 10): the `ptv` binary as a child process, or the service in
//! process where the raw connection is all that matters.
//!
//! - Uploads trickling a byte at a time past `--max-connections` neither
//!   hold every slot (`/healthz` answers) nor last (408 within the rate
//!   window, `--min-body-rate`).
//! - An upload the client cuts off is a 499 in `/metrics` and a warning,
//!   not a 500 and an error.
//! - `Content-Length` with `Transfer-Encoding: chunked` is a 400.
//! - An empty `--api-token` stops the start, with the reason.
//! - A PostgreSQL that cannot be reached ends the start after
//!   `--database-wait-secs`, naming the server and the cause.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::helpers::*;

/// `host:port` of `http://host:port`.
fn host_port(address: &str) -> &str {
    address.strip_prefix("http://").unwrap()
}

/// How long `/healthz` took on a new connection; `None` if it did not
/// answer 200 within `patience`.
async fn healthz_latency(address: &str, patience: Duration) -> Option<Duration> {
    let client = reqwest::Client::builder()
        .timeout(patience)
        .pool_max_idle_per_host(0)
        .build()
        .unwrap();
    let start = Instant::now();
    let response = client.get(format!("{address}/healthz")).send().await.ok()?;
    (response.status().as_u16() == 200).then(|| start.elapsed())
}

/// What a trickling upload got: the answer, and when its first byte came,
/// from the connect.
struct Trickled {
    answer: String,
    after: Option<Duration>,
}

/// Connects, sends the head of a 100 kB JSON body, then one byte every
/// `pause` until the server answers, and reads the answer until the server
/// closes the connection (or `patience` passes).
async fn trickle(address: String, pause: Duration, patience: Duration) -> Trickled {
    let start = Instant::now();
    let stream = TcpStream::connect(host_port(&address)).await.unwrap();
    let (mut reader, mut writer) = stream.into_split();
    let head = "POST /api/v1/calibrations HTTP/1.1\r\nHost: x\r\n\
                Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n[";
    let _ = writer.write_all(head.as_bytes()).await;
    let sender = tokio::spawn(async move {
        loop {
            tokio::time::sleep(pause).await;
            if writer.write_all(b" ").await.is_err() {
                break;
            }
        }
    });
    let mut answer = Vec::new();
    let mut after = None;
    let mut buffer = [0u8; 4096];
    loop {
        let left = patience.saturating_sub(start.elapsed());
        match tokio::time::timeout(left, reader.read(&mut buffer)).await {
            Ok(Ok(n)) if n > 0 => {
                after.get_or_insert(start.elapsed());
                // A client that got its answer stops sending.
                sender.abort();
                answer.extend_from_slice(&buffer[..n]);
            }
            _ => break,
        }
    }
    sender.abort();
    Trickled {
        answer: String::from_utf8_lossy(&answer).into_owned(),
        after,
    }
}

/// A count from `/metrics`: the sum of the `ptv_http_requests_total` lines
/// whose labels contain `labels`.
async fn requests_counted(address: &str, labels: &str) -> (u64, String) {
    let text = reqwest::get(format!("{address}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let count = text
        .lines()
        .filter(|l| l.starts_with("ptv_http_requests_total{") && l.contains(labels))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum();
    (count, text)
}

/// 30 uploads trickling a byte every 250 ms (4 bytes/s) against a limit of
/// 20 connections, a rate window of 2 s and the default minimum of 1 KiB/s
/// (so a window needs 2 KiB and gets 8 bytes).
///
/// Bounds, from the rules (`src/service/connections.rs`): a new connection
/// at the limit waits at most until a trickling body has been waited for
/// [`EVICTION_GRACE`] (1 s) and is then let in by ending it; the accept
/// loop looks again every 100 ms; so `/healthz` answers within 1.1 s plus
/// a request's own time and the scheduling of a debug build on 2 cores
/// shared with the rest of the suite, taken as 3 s (a slack against a
/// loaded machine, not a measured figure: the property is that it answers
/// at all, where before it did not for 300 s). Each trickler is ended by a 408 at the end of its first
/// window (2 s of waiting for its body) or earlier by an eviction; one
/// kept in the listen backlog waits for a slot at most until the first
/// trickler becomes evictable (1 s): so every 408 comes within grace +
/// window + the same slack = 6 s of its connect.
///
/// Before issue 29 nothing ended a request in flight: `/healthz` did not
/// answer at all while the tricklers held the slots (300 s, the request
/// timeout).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trickling_uploads_get_408_and_healthz_stays_reachable() {
    const GRACE: Duration = Duration::from_secs(1);
    const WINDOW: Duration = Duration::from_secs(2);
    const SLACK: Duration = Duration::from_secs(3);
    let dir = tempfile::tempdir().unwrap();
    let server = ServiceProcess::start_with(
        dir.path(),
        0,
        &["--max-connections", "20", "--body-rate-window-secs", "2"],
    );
    let address = server.address.clone();
    // Idle, after one request.
    assert!(healthz_latency(&address, Duration::from_secs(5))
        .await
        .is_some());
    let idle_mib = server.peak_memory_mib();
    let patience = Duration::from_secs(15);
    let tricklers: Vec<_> = (0..30)
        .map(|_| {
            tokio::spawn(trickle(
                address.clone(),
                Duration::from_millis(250),
                patience,
            ))
        })
        .collect();
    // /healthz on a new connection every 200 ms while they trickle.
    let healthz_bound = GRACE + Duration::from_millis(100) + SLACK;
    let mut latencies = Vec::new();
    let start = Instant::now();
    while start.elapsed() < 2 * (GRACE + WINDOW) {
        let latency = healthz_latency(&address, Duration::from_secs(10)).await;
        latencies.push(latency);
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let worst = latencies.iter().max().copied().flatten();
    assert!(
        latencies.iter().all(Option::is_some) && worst.is_some_and(|w| w < healthz_bound),
        "/healthz latencies {latencies:?}, bound {healthz_bound:?}"
    );
    for trickler in tricklers {
        let trickled = trickler.await.unwrap();
        assert!(
            trickled.answer.starts_with("HTTP/1.1 408 "),
            "after {:?}: {}",
            trickled.after,
            trickled.answer
        );
        assert!(
            trickled.answer.contains("--min-body-rate"),
            "{}",
            trickled.answer
        );
        assert!(
            trickled.after.is_some_and(|t| t < GRACE + WINDOW + SLACK),
            "408 after {:?}",
            trickled.after
        );
    }
    // Memory: each trickler costs at most hyper's largest read buffer
    // (HYPER_MAX_HEAD_BYTES, 128 KiB), the lingering close's 64 KiB buffer
    // and an allowance of 64 KiB for its task, request and answer: 256 KiB
    // each, 7.5 MiB for the 30, over the idle server's peak.
    let peak_mib = server.peak_memory_mib();
    assert!(
        peak_mib <= idle_mib + 30.0 * 0.25,
        "peak {peak_mib:.1} MiB, idle {idle_mib:.1} MiB"
    );
    let (timeouts, metrics) = requests_counted(&address, "status=\"408\"").await;
    assert_eq!(timeouts, 30, "{metrics}");
    assert!(!metrics.contains("status=\"5"), "{metrics}");
    println!(
        "healthz worst {:?} over {} probes",
        worst.unwrap(),
        latencies.len()
    );
}

/// `ptv serve` with its log in `dir/serve.log`.
fn start_logged(dir: &std::path::Path, more: &[&str]) -> (ServiceProcess, std::path::PathBuf) {
    let log = dir.join("serve.log");
    let data = dir.join("data");
    let mut child = Command::new(env!("CARGO_BIN_EXE_ptv"))
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--workers",
            "0",
            "--data-dir",
        ])
        .arg(&data)
        .args(database_args(&data))
        .args(object_store_flags(&data))
        .args(more)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .expect("the ptv binary starts");
    let mut stdout = child.stdout.take().unwrap();
    let mut line = Vec::new();
    let mut byte = [0u8; 1];
    while stdout.read(&mut byte).unwrap() == 1 && byte[0] != b'\n' {
        line.push(byte[0]);
    }
    let line = String::from_utf8(line).unwrap();
    let address = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected first line `{line}`"))
        .to_owned();
    (ServiceProcess { child, address }, log)
}

/// Sends the head of a `length`-byte upload and `sent` bytes of it, then
/// closes the connection: with a FIN, or (`reset`) a reset.
async fn abort_upload(address: &str, head: &str, sent: usize, reset: bool) {
    let stream = TcpStream::connect(host_port(address)).await.unwrap();
    stream.set_nodelay(true).unwrap();
    let mut stream = stream;
    stream.write_all(head.as_bytes()).await.unwrap();
    stream.write_all(&vec![b'x'; sent]).await.unwrap();
    stream.flush().await.unwrap();
    // Let the server start reading the body before the connection goes.
    tokio::time::sleep(Duration::from_millis(200)).await;
    if reset {
        stream.set_zero_linger().unwrap();
    }
    drop(stream);
}

/// Uploads cut off by their client (a closed or reset connection in the
/// middle of the body), to the frames route (multipart) and to the
/// calibrations route (JSON), count as 499 in `/metrics`, none as a 5xx,
/// and leave a warning in the log, no error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_aborted_upload_is_a_client_abort_not_a_server_error() {
    let dir = tempfile::tempdir().unwrap();
    let (server, log) = start_logged(dir.path(), &[]);
    let client = reqwest::Client::new();
    let sequence = create_rig_sequence(&client, &server.address, &rig()).await;
    let frames = format!(
        "POST /api/v1/sequences/{sequence}/frames HTTP/1.1\r\nHost: x\r\n\
         Content-Type: multipart/form-data; boundary=XYZ\r\nContent-Length: 1000000\r\n\r\n\
         --XYZ\r\nContent-Disposition: form-data; name=\"frame\"\r\n\r\n0\r\n--XYZ\r\n\
         Content-Disposition: form-data; name=\"cam0\"; filename=\"a.png\"\r\n\r\n"
    );
    let calibration = "POST /api/v1/calibrations HTTP/1.1\r\nHost: x\r\n\
                       Content-Type: application/json\r\nContent-Length: 1000000\r\n\r\n";
    for reset in [false, true] {
        abort_upload(&server.address, &frames, 20_000, reset).await;
        abort_upload(&server.address, calibration, 20_000, reset).await;
    }
    // The server notices each abort when it reads on: wait for all four.
    let deadline = Instant::now() + Duration::from_secs(10);
    let (aborted, metrics) = loop {
        let (aborted, metrics) = requests_counted(&server.address, "status=\"499\"").await;
        if aborted >= 4 || Instant::now() > deadline {
            break (aborted, metrics);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(aborted, 4, "{metrics}");
    assert!(!metrics.contains("status=\"5"), "{metrics}");
    assert!(!metrics.contains("status=\"4xx\""), "{metrics}");
    drop(server);
    let log = std::fs::read_to_string(log).unwrap();
    assert!(!log.contains("ERROR"), "{log}");
    let warnings = log
        .lines()
        .filter(|l| l.contains("WARN") && l.contains("before its request body was complete"))
        .count();
    assert_eq!(warnings, 4, "{log}");
}

/// Sends `wire` on a new connection and reads until the server closes it
/// (at most 5 s).
async fn raw_exchange(address: &str, wire: &str) -> String {
    let mut stream = TcpStream::connect(host_port(address)).await.unwrap();
    stream.write_all(wire.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), stream.read_to_end(&mut answer)).await;
    String::from_utf8_lossy(&answer).into_owned()
}

/// A request with both `Content-Length` and `Transfer-Encoding: chunked`
/// (in either order, first on its connection or after a kept-alive
/// request) is refused with a 400 problem that names both, and the
/// connection closed; a request whose body merely contains those names,
/// and a plain chunked one, are served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn content_length_with_chunked_is_refused_with_400() {
    let app = spawn_app().await;
    let post =
        "POST /api/v1/calibrations HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n";
    let length_first =
        format!("{post}Content-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n");
    let coding_first =
        format!("{post}transfer-encoding: chunked\r\ncontent-length: 5\r\n\r\n0\r\n\r\n");
    let kept_alive = format!("GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n{length_first}");
    for (case, wire) in [
        ("length first", &length_first),
        ("coding first", &coding_first),
        ("after a kept-alive request", &kept_alive),
    ] {
        let answer = raw_exchange(&app.address, wire).await;
        let refused = answer
            .find("HTTP/1.1 400 ")
            .map(|at| &answer[at..])
            .unwrap_or_else(|| panic!("{case}: {answer}"));
        assert!(
            refused.contains("application/problem+json"),
            "{case}: {answer}"
        );
        assert!(
            refused.contains("both Content-Length and Transfer-Encoding"),
            "{case}: {answer}"
        );
        assert!(
            refused.to_ascii_lowercase().contains("connection: close"),
            "{case}: {answer}"
        );
        if case == "after a kept-alive request" {
            assert!(answer.starts_with("HTTP/1.1 200 "), "{answer}");
        }
    }
    // A JSON body that holds the names, then a chunked request, on one
    // connection: both answered for what they are (not JSON of a
    // calibration: 422 and 400), neither for their framing.
    let body = "{\"Transfer-Encoding\": \"chunked\",\r\n\"Content-Length\": 5}";
    let wire = format!(
        "{post}Content-Length: {}\r\n\r\n{body}{post}Transfer-Encoding: chunked\r\n\
         Connection: close\r\n\r\n2\r\n[1\r\n0\r\n\r\n",
        body.len()
    );
    let answer = raw_exchange(&app.address, &wire).await;
    assert_eq!(answer.matches("HTTP/1.1 4").count(), 2, "{answer}");
    assert!(!answer.contains("both Content-Length"), "{answer}");
    app.stop().await;
}

/// The framing scan fails closed (issue 29): a request with an `Upgrade:`
/// header is answered as plain HTTP (the service never switches
/// protocols) and the scan goes on following the connection, so a
/// request with both `Content-Length` and `Transfer-Encoding` after it is
/// still refused (before, the scan stopped at the upgrade and the second
/// request was served); a `CONNECT` is refused and its connection closed,
/// so nothing after it is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn framing_is_followed_past_upgrades_and_connect_is_refused() {
    let app = spawn_app().await;
    let smuggled = "POST /api/v1/calibrations HTTP/1.1\r\nHost: x\r\n\
        Content-Type: application/json\r\nContent-Length: 5\r\n\
        Transfer-Encoding: chunked\r\n\r\n0\r\n\r\n";
    let upgrade = format!(
        "GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n\r\n\
         {smuggled}"
    );
    let answer = raw_exchange(&app.address, &upgrade).await;
    assert!(answer.starts_with("HTTP/1.1 200 "), "{answer}");
    let second = answer
        .find("HTTP/1.1 400 ")
        .map(|at| &answer[at..])
        .unwrap_or_else(|| panic!("the request after the upgrade was served: {answer}"));
    assert!(
        second.contains("both Content-Length and Transfer-Encoding"),
        "{answer}"
    );
    let connect = format!("CONNECT x:443 HTTP/1.1\r\nHost: x:443\r\n\r\n{smuggled}");
    let answer = raw_exchange(&app.address, &connect).await;
    assert!(answer.starts_with("HTTP/1.1 400 "), "{answer}");
    assert!(answer.contains("does not take CONNECT"), "{answer}");
    assert!(
        answer.to_ascii_lowercase().contains("connection: close"),
        "{answer}"
    );
    assert_eq!(answer.matches("HTTP/1.1 ").count(), 1, "{answer}");
    app.stop().await;
}

/// Runs `ptv` with `args` and `env` until it exits (at most `patience`):
/// its exit code, standard error, and how long it ran.
fn run_ptv(
    args: &[&str],
    env: &[(&str, &str)],
    patience: Duration,
) -> (Option<i32>, String, Duration) {
    let start = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_ptv"))
        .args(args)
        .env_remove("PTV_API_TOKEN")
        .env_remove("PTV_DATABASE_URL")
        .envs(env.iter().copied())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the ptv binary starts");
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if start.elapsed() > patience {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let elapsed = start.elapsed();
    let mut stderr = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut stderr)
        .unwrap();
    (status.and_then(|s| s.code()), stderr, elapsed)
}

/// An empty API token, by flag or variable, or one with spaces around it,
/// stops `ptv serve` at once (exit code 2, clap's usage error) with the
/// reason, without repeating the token.
#[test]
fn an_empty_api_token_is_refused_at_start() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let serve = ["serve", "--bind", "127.0.0.1:0", "--data-dir", data];
    // (case, flags, environment, what the message says)
    type Case<'a> = (&'a str, Vec<&'a str>, Vec<(&'a str, &'a str)>, &'a str);
    let cases: [Case; 4] = [
        ("empty flag", vec!["--api-token", ""], vec![], "empty"),
        (
            "empty variable",
            vec![],
            vec![("PTV_API_TOKEN", "")],
            "empty",
        ),
        (
            "blank variable",
            vec![],
            vec![("PTV_API_TOKEN", "  ")],
            "empty",
        ),
        (
            "spaces around",
            vec!["--api-token", " s3cret-token "],
            vec![],
            "white space",
        ),
    ];
    for (case, flags, env, reason) in cases {
        let args: Vec<&str> = serve.iter().copied().chain(flags).collect();
        let (code, stderr, _) = run_ptv(&args, &env, Duration::from_secs(10));
        assert_eq!(code, Some(2), "{case}: {stderr}");
        assert!(stderr.contains("--api-token"), "{case}: {stderr}");
        assert!(stderr.contains(reason), "{case}: {stderr}");
        assert!(!stderr.contains("s3cret-token"), "{case}: {stderr}");
        assert!(!stderr.contains("listening on"), "{case}: {stderr}");
    }
}

/// `ptv serve` and `ptv worker` against a PostgreSQL port on 127.0.0.1
/// that nobody listens on, with `--database-wait-secs 3`: each logs the
/// server (host and port) and the cause while it tries, then exits with
/// code 1 and the same, the password hidden. Bound: the wait, plus one
/// retry pause of 1 s that may start just before it ends, plus 5 s to
/// start and stop a debug build on a machine the rest of the suite keeps
/// busy (scheduling slack; without the flag the wait was 65 s).
#[test]
fn an_unreachable_database_ends_the_start_with_host_port_and_cause() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("postgres://ptv:hunter2-secret@127.0.0.1:{port}/ptv");
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().to_str().unwrap();
    let wait = Duration::from_secs(3);
    let bound = wait + Duration::from_secs(6);
    for command in ["serve", "worker"] {
        let mut args = vec![command, "--data-dir", data, "--database", &url];
        args.extend(["--database-wait-secs", "3"]);
        if command == "serve" {
            args.extend(["--bind", "127.0.0.1:0"]);
        }
        let (code, stderr, elapsed) = run_ptv(&args, &[], Duration::from_secs(30));
        assert_eq!(code, Some(1), "{command} after {elapsed:?}: {stderr}");
        assert!(
            elapsed >= wait && elapsed < bound,
            "{command} ran {elapsed:?}: {stderr}"
        );
        let server = format!("127.0.0.1:{port}");
        let last = stderr.lines().last().unwrap_or_default();
        assert!(last.starts_with("error: "), "{command}: {stderr}");
        for needle in [&server[..], "Connection refused", "--database-wait-secs"] {
            assert!(last.contains(needle), "{command}: `{needle}` in {stderr}");
        }
        let retries = stderr
            .lines()
            .filter(|l| l.contains("trying again") && l.contains(&server))
            .filter(|l| l.contains("Connection refused"))
            .count();
        assert!(retries >= 2, "{command}: {stderr}");
        assert!(!stderr.contains("hunter2"), "{command}: {stderr}");
    }
}
