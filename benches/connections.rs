//! `/healthz` latency while the service holds many connections: 20,000
//! idle ones (more than its connection limit below the open-file limit),
//! and 200 slowloris clients sending a byte a second. Loopback only; about
//! a minute.
//!
//! ```sh
//! cargo bench --bench connections
//! cargo bench --bench connections -- --idle 5000 --slowloris 100 --requests 100
//! ```
//!
//! The service is the release `ptv` binary in its own process (its file
//! descriptors are its own), started with its default `--max-connections`
//! and a header timeout of 300 s, so that idle connections are not closed
//! by the timeout while measuring: only the connection limit keeps the
//! service reachable. The idle connections are held by two child processes
//! of this bench (each needs a file descriptor per connection); each makes
//! one request first (so it is known to be accepted, not left in the listen
//! backlog) and then stays idle, kept alive, while the next ones arrive;
//! past the limit the service closes the longest idle ones. Each
//! `/healthz` request is made on a new connection (connect, request,
//! answer, close), one at a time, and timed as a whole; a request that
//! fails or takes over 10 s counts as failed.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

struct Options {
    idle: usize,
    slowloris: usize,
    requests: usize,
}

fn options() -> Options {
    let mut options = Options {
        idle: 20_000,
        slowloris: 200,
        requests: 200,
    };
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut number = |name: &str| -> usize {
            args.next()
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("{name} needs a number"))
        };
        match arg.as_str() {
            "--idle" => options.idle = number("--idle"),
            "--slowloris" => options.slowloris = number("--slowloris"),
            "--requests" => options.requests = number("--requests").max(1),
            // cargo bench passes --bench; ignore what we do not know.
            _ => {}
        }
    }
    options
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

fn main() {
    ptv::service::infra::connections::raise_open_file_limit();
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("--hold") {
        let count = args[2].parse().unwrap();
        runtime().block_on(hold(args[3].clone(), count));
        return;
    }
    let options = options();
    let data_dir = tempfile::tempdir().unwrap();
    let mut server = Command::new(env!("CARGO_BIN_EXE_ptv"))
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--header-timeout-secs",
            "300",
        ])
        .arg("--data-dir")
        .arg(data_dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("the ptv binary starts");
    let mut lines = BufReader::new(server.stdout.take().unwrap()).lines();
    let address = lines
        .find_map(|line| {
            line.ok()?
                .strip_prefix("listening on http://")
                .map(str::to_owned)
        })
        .expect("the service prints its address");
    let runtime = runtime();
    let mut rows = Vec::new();

    rows.push((
        "no other connections".to_owned(),
        runtime.block_on(measure(&address, options.requests)),
    ));

    // Idle connections, held by two children.
    let start = Instant::now();
    let mut holders: Vec<Child> = (0..2)
        .map(|i| {
            let count = options.idle / 2 + if i == 0 { options.idle % 2 } else { 0 };
            Command::new(std::env::current_exe().unwrap())
                .args(["--hold", &count.to_string(), &address])
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut opened = 0;
    for holder in &mut holders {
        let mut line = String::new();
        BufReader::new(holder.stdout.as_mut().unwrap())
            .read_line(&mut line)
            .unwrap();
        opened += line.trim().parse::<usize>().unwrap_or(0);
    }
    println!(
        "opened {opened} connections, each idle after one request, in {:.1} s",
        start.elapsed().as_secs_f64()
    );
    let before = runtime.block_on(metrics(&address));
    rows.push((
        format!("{opened} idle connections"),
        runtime.block_on(measure(&address, options.requests)),
    ));
    let after = runtime.block_on(metrics(&address));
    println!("service while held: {before}");
    println!("service after measuring: {after}");
    for mut holder in holders {
        drop(holder.stdin.take());
        let _ = holder.wait();
    }

    // Slowloris clients, a byte a second each, never ending their headers.
    let (slowloris, stop) = runtime.block_on(async {
        let stop = tokio::sync::watch::channel(false);
        let mut tasks = Vec::new();
        for _ in 0..options.slowloris {
            let address = address.clone();
            let mut stopped = stop.1.clone();
            tasks.push(tokio::spawn(async move {
                let Ok(mut stream) = TcpStream::connect(&address).await else {
                    return;
                };
                let head = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ";
                for byte in head.iter().chain(std::iter::repeat(&b'a')) {
                    if stream.write_all(&[*byte]).await.is_err() {
                        return;
                    }
                    tokio::select! {
                        () = tokio::time::sleep(Duration::from_secs(1)) => {}
                        _ = stopped.changed() => return,
                    }
                }
            }));
        }
        // Let them all connect and start trickling.
        tokio::time::sleep(Duration::from_secs(3)).await;
        (tasks, stop.0)
    });
    rows.push((
        format!("{} slowloris connections (1 byte/s)", options.slowloris),
        runtime.block_on(measure(&address, options.requests)),
    ));
    println!(
        "service while trickled at: {}",
        runtime.block_on(metrics(&address))
    );
    let _ = stop.send(true);
    runtime.block_on(async {
        for task in slowloris {
            let _ = task.await;
        }
    });

    let _ = server.kill();
    let _ = server.wait();
    println!();
    println!(
        "/healthz on a new connection each, {} requests one at a time:",
        options.requests
    );
    println!(
        "{:<42} {:>9} {:>9} {:>9} {:>7}",
        "while the service holds", "p50 ms", "p99 ms", "max ms", "failed"
    );
    for (case, result) in rows {
        println!(
            "{case:<42} {:>9.2} {:>9.2} {:>9.2} {:>7}",
            result.p50, result.p99, result.max, result.failed
        );
    }
}

/// Opens `count` connections to `address` (200 at a time), each of which
/// makes one request and then stays idle (kept alive), so it is known to
/// have been accepted; prints how many got their answer, and holds them
/// until standard input closes.
async fn hold(address: String, count: usize) {
    let mut held = Vec::with_capacity(count);
    let mut left = count;
    while left > 0 {
        let batch = left.min(200);
        left -= batch;
        let connects: Vec<_> = (0..batch)
            .map(|_| {
                let address = address.clone();
                tokio::spawn(async move {
                    let open = async {
                        let mut stream = TcpStream::connect(address).await?;
                        stream
                            .write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
                            .await?;
                        let mut answer = Vec::new();
                        let mut buffer = [0u8; 512];
                        while !answer.ends_with(b"ok\n") {
                            let n = stream.read(&mut buffer).await?;
                            if n == 0 {
                                return Err(std::io::ErrorKind::UnexpectedEof.into());
                            }
                            answer.extend_from_slice(&buffer[..n]);
                        }
                        Ok::<_, std::io::Error>(stream)
                    };
                    tokio::time::timeout(Duration::from_secs(10), open).await
                })
            })
            .collect();
        for connect in connects {
            if let Ok(Ok(Ok(stream))) = connect.await {
                held.push(stream);
            }
        }
    }
    println!("{}", held.len());
    let _ = std::io::stdout().flush();
    let _ = tokio::task::spawn_blocking(|| {
        let mut sink = String::new();
        let _ = std::io::stdin().read_line(&mut sink);
    })
    .await;
    drop(held);
}

struct Latencies {
    p50: f64,
    p99: f64,
    max: f64,
    failed: usize,
}

/// Times `requests` GET /healthz, each on a new connection.
async fn measure(address: &str, requests: usize) -> Latencies {
    let mut times = Vec::with_capacity(requests);
    let mut failed = 0;
    for _ in 0..requests {
        let start = Instant::now();
        let exchange = async {
            let mut stream = TcpStream::connect(address).await?;
            stream
                .write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
                .await?;
            let mut answer = Vec::new();
            stream.read_to_end(&mut answer).await?;
            Ok::<_, std::io::Error>(answer)
        };
        match tokio::time::timeout(Duration::from_secs(10), exchange).await {
            Ok(Ok(answer)) if answer.starts_with(b"HTTP/1.1 200") => {
                times.push(start.elapsed().as_secs_f64() * 1000.0);
            }
            _ => failed += 1,
        }
    }
    times.sort_by(f64::total_cmp);
    let percentile = |p: f64| {
        if times.is_empty() {
            return f64::NAN;
        }
        times[((p / 100.0) * (times.len() - 1) as f64).round() as usize]
    };
    Latencies {
        p50: percentile(50.0),
        p99: percentile(99.0),
        max: times.last().copied().unwrap_or(f64::NAN),
        failed,
    }
}

/// The service's connection gauges, from `/metrics`.
async fn metrics(address: &str) -> String {
    let fetch = async {
        let mut stream = TcpStream::connect(address).await?;
        stream
            .write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            .await?;
        let mut answer = String::new();
        stream.read_to_string(&mut answer).await?;
        Ok::<_, std::io::Error>(answer)
    };
    let text = match tokio::time::timeout(Duration::from_secs(10), fetch).await {
        Ok(Ok(text)) => text,
        _ => return "(no answer from /metrics)".to_owned(),
    };
    text.lines()
        .filter(|l| l.starts_with("ptv_http_connections"))
        .collect::<Vec<_>>()
        .join(", ")
}
