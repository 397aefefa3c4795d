//! What every request passes through (`src/service/http/layers.rs` and
//! hyper's settings in `src/service/connections.rs`): request ids, gzip,
//! the header, body and request timeouts, the early 413, the bearer token
//! on every path under `/api` before routing, the 414 and 431 problems, and
//! bounded `/metrics` labels. The panic guard, the 503 of a handler past the
//! request timeout and the load shedding of the CPU routes are unit tests
//! beside the layers; the connection limit and the lingering close are in
//! `connections`.

use std::io::Read;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::helpers::*;

/// What a raw connection got: the text the server sent, and after how long
/// it closed the connection (`None`: still open after the patience).
struct Exchange {
    answer: String,
    closed_after: Option<Duration>,
}

/// Connects to the service, sends `head`, then `trickle` (if any) a piece
/// every 200 ms, never ends the request, and reads until the server closes
/// the connection or `patience` passes.
async fn exchange(address: &str, head: &[u8], trickle: &[&[u8]], patience: Duration) -> Exchange {
    let stream = TcpStream::connect(address.strip_prefix("http://").unwrap())
        .await
        .unwrap();
    let (mut reader, mut writer) = stream.into_split();
    let start = Instant::now();
    writer.write_all(head).await.unwrap();
    let pieces: Vec<Vec<u8>> = trickle.iter().map(|p| p.to_vec()).collect();
    let sender = tokio::spawn(async move {
        for piece in pieces {
            tokio::time::sleep(Duration::from_millis(200)).await;
            if writer.write_all(&piece).await.is_err() {
                break;
            }
        }
        // Hold the write side open: a half-closed request is not a stall.
        tokio::time::sleep(Duration::from_secs(3600)).await;
        drop(writer);
    });
    let mut received = Vec::new();
    let mut buffer = [0u8; 4096];
    let closed_after = loop {
        let left = patience.saturating_sub(start.elapsed());
        match tokio::time::timeout(left, reader.read(&mut buffer)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break Some(start.elapsed()),
            Ok(Ok(n)) => received.extend_from_slice(&buffer[..n]),
            Err(_) => break None,
        }
    };
    sender.abort();
    Exchange {
        answer: String::from_utf8_lossy(&received).into_owned(),
        closed_after,
    }
}

/// GETs `url`, with one header if given.
async fn get(app: &TestApp, url: &str, header: Option<(&str, &str)>) -> reqwest::Response {
    let mut request = app.client.get(url);
    if let Some((name, value)) = header {
        request = request.header(name, value);
    }
    request.send().await.unwrap()
}

/// Checks that `exchange` got a `status` problem+json that mentions
/// `needle`, with `Connection: close`, and that the connection was closed
/// within 5 s.
fn assert_refused(exchange: &Exchange, status: u16, needle: &str, case: &str) {
    let answer = &exchange.answer;
    let status_line = format!("HTTP/1.1 {status} ");
    assert!(answer.starts_with(&status_line), "{case}: {answer}");
    let lower = answer.to_ascii_lowercase();
    assert!(
        lower.contains("content-type: application/problem+json"),
        "{case}: {answer}"
    );
    assert!(lower.contains("connection: close"), "{case}: {answer}");
    assert!(answer.contains(needle), "{case}: {answer}");
    assert!(
        exchange
            .closed_after
            .is_some_and(|t| t < Duration::from_secs(5)),
        "{case}: closed after {:?}",
        exchange.closed_after
    );
}

/// Every answer carries an `x-request-id` (the client's, if it sent one);
/// the token check answers 401 problem+json with `WWW-Authenticate` and
/// takes the scheme in any case.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_answer_has_a_request_id_and_the_token_check_holds() {
    let app = spawn_app_with(Some("s3cret")).await;
    let id = |response: &reqwest::Response| {
        response.headers()["x-request-id"]
            .to_str()
            .unwrap()
            .to_owned()
    };
    let health = format!("{}/healthz", app.address);
    let first = get(&app, &health, None).await;
    let second = get(&app, &health, None).await;
    assert_eq!(id(&first).len(), 36, "a UUID: {}", id(&first));
    assert_ne!(id(&first), id(&second));
    let mine = get(
        &app,
        &health,
        Some(("x-request-id", "acquisition-7/frame-42")),
    )
    .await;
    assert_eq!(id(&mine), "acquisition-7/frame-42");

    let job = app.api("/jobs/1");
    let refused = get(&app, &job, None).await;
    assert_eq!(refused.headers()["www-authenticate"], "Bearer");
    assert!(!id(&refused).is_empty());
    let (status, body) = status_and_json(refused).await;
    assert_eq!(status, 401, "{body}");
    assert!(
        body["detail"].as_str().unwrap().contains("Bearer"),
        "{body}"
    );
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let token = format!("{scheme} s3cret");
        let response = get(&app, &job, Some(("authorization", &token))).await;
        assert_eq!(response.status().as_u16(), 404, "{scheme}");
        assert!(!id(&response).is_empty());
    }
    let unknown = get(&app, &format!("{}/nowhere", app.address), None).await;
    assert!(!id(&unknown).is_empty());
    assert_eq!(status_and_json(unknown).await.0, 404);
    app.stop().await;
}

/// With `Accept-Encoding: gzip` the streamed particle CSV and the JSON come
/// compressed, and decode to the plain answer.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn answers_are_gzipped_when_the_client_accepts_it() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    for frame in 0..3 {
        let targets = rig.targets(300, 100 + frame as u64);
        let (status, body) = app.upload(sequence, targets_form(frame, &targets)).await;
        assert_eq!(status, 202, "{body}");
    }
    app.wait_for_sequence(sequence).await;

    let urls = [
        app.api(&format!("/sequences/{sequence}/particles?format=csv")),
        format!("{}/openapi.json", app.address),
    ];
    for url in urls {
        let plain = get(&app, &url, None).await;
        assert!(!plain.headers().contains_key("content-encoding"), "{url}");
        let plain = plain.bytes().await.unwrap();
        let zipped = get(&app, &url, Some(("accept-encoding", "gzip"))).await;
        assert_eq!(zipped.status().as_u16(), 200, "{url}");
        assert_eq!(zipped.headers()["content-encoding"], "gzip", "{url}");
        let zipped = zipped.bytes().await.unwrap();
        let mut decoded = Vec::new();
        flate2::read::GzDecoder::new(&zipped[..])
            .read_to_end(&mut decoded)
            .unwrap();
        assert_eq!(decoded, plain, "{url}");
        assert!(
            zipped.len() * 2 < plain.len(),
            "{url}: {} bytes gzipped from {}",
            zipped.len(),
            plain.len()
        );
    }
    app.stop().await;
}

/// A client that sends half a header line and stalls, one that sends
/// nothing, and a kept-alive connection left idle are all disconnected
/// once the header timeout (1 s here) passes; the service goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_headers_and_idle_connections_are_closed_after_the_header_timeout() {
    let app = spawn_app_configured(|args| args.timeouts.header_secs = 1).await;
    let patience = Duration::from_secs(10);
    let cases: [(&str, &[u8]); 3] = [
        (
            "half a header",
            b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: 1",
        ),
        ("nothing", b""),
        (
            "idle after a request",
            b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n",
        ),
    ];
    for (case, head) in cases {
        let Exchange {
            answer,
            closed_after,
        } = exchange(&app.address, head, &[], patience).await;
        let closed_after = closed_after.unwrap_or_else(|| panic!("{case}: still open"));
        assert!(
            closed_after >= Duration::from_millis(900) && closed_after < Duration::from_secs(5),
            "{case}: closed after {closed_after:?}"
        );
        if case == "idle after a request" {
            assert!(answer.starts_with("HTTP/1.1 200"), "{case}: {answer}");
        } else {
            assert!(
                answer.is_empty() || answer.starts_with("HTTP/1.1 408"),
                "{case}: {answer}"
            );
        }
    }
    app.get_text(format!("{}/healthz", app.address)).await;
    app.stop().await;
}

/// A body that stops arriving is cut off after the body timeout (1 s
/// here) with a 408, multipart upload or JSON; one that keeps trickling
/// is cut off by the request timeout (2 s here), also 408. Each closes the
/// connection, nothing is stored, and none counts as a server error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_and_endless_bodies_are_cut_off_with_408() {
    let app = spawn_app_configured(|args| {
        args.timeouts.body_secs = 1;
        args.timeouts.request_secs = 2;
    })
    .await;
    let (_, sequence) = app.rig_sequence().await;
    let upload = format!(
        "POST /api/v1/sequences/{sequence}/frames HTTP/1.1\r\nHost: x\r\n\
         Content-Type: multipart/form-data; boundary=XYZ\r\nContent-Length: 100000\r\n\r\n\
         --XYZ\r\nContent-Disposition: form-data; name=\"frame\"\r\n\r\n0\r\n--XYZ\r\n\
         Content-Disposition: form-data; name=\"cam0\"; filename=\"a.png\"\r\n\r\n\x7fPNG"
    );
    let json = "POST /api/v1/calibrations HTTP/1.1\r\nHost: x\r\n\
                Content-Type: application/json\r\nContent-Length: 10000\r\n\r\n{\"cameras\": [";
    let piece: &[u8] = b" ";
    let cases: [(&str, &str, &[&[u8]], &str); 3] = [
        ("stalled upload", &upload, &[], "--body-timeout-secs"),
        ("stalled JSON", json, &[], "--body-timeout-secs"),
        ("endless JSON", json, &[piece; 20], "--request-timeout-secs"),
    ];
    for (case, head, trickle, flag) in cases {
        let exchange = exchange(
            &app.address,
            head.as_bytes(),
            trickle,
            Duration::from_secs(10),
        )
        .await;
        assert_refused(&exchange, 408, flag, case);
    }
    let metrics = app.get_text(format!("{}/metrics", app.address)).await;
    assert!(!metrics.contains("status=\"5"), "{metrics}");
    let db = app.database().await;
    assert_eq!(count(&db, "SELECT count(*) FROM frames").await, 0);
    assert_eq!(count(&db, "SELECT count(*) FROM calibrations").await, 1);
    app.stop().await;
}

/// A body declared larger than the limit is refused with a 413 while the
/// client has sent nothing of it, and the connection is closed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_declared_body_over_the_limit_is_refused_before_it_is_sent() {
    let app = spawn_app().await;
    let head = "POST /api/v1/sequences/1/frames HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XYZ\r\n\
                Content-Length: 2147483648\r\n\r\n";
    let exchange = exchange(&app.address, head.as_bytes(), &[], Duration::from_secs(10)).await;
    assert_refused(&exchange, 413, "--max-upload-mb", "2 GiB declared");
    let lower = exchange.answer.to_ascii_lowercase();
    assert!(lower.contains("x-request-id: "), "{}", exchange.answer);
    app.stop().await;
}

/// With a token, every path under `/api` answers 401 without it, whether
/// it names a route, takes the method or not (routes cannot be probed);
/// with the token, unknown routes and methods get their 404 and 405.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_the_token_everything_under_api_is_401() {
    let app = spawn_app_with(Some("s3cret")).await;
    let cases = [
        ("GET", "/api/v1/nowhere", 404),
        ("DELETE", "/api/v1/jobs/1", 405),
        ("PUT", "/api/v1/calibrations", 405),
        ("GET", "/api", 404),
        ("GET", "/api/", 404),
        ("GET", "/api/v2/calibrations", 404),
        ("BREW", "/api/v1/sequences", 405),
    ];
    for (method, path, with_token) in cases {
        let method = reqwest::Method::from_bytes(method.as_bytes()).unwrap();
        let url = format!("{}{path}", app.address);
        let refused = app
            .client
            .request(method.clone(), &url)
            .send()
            .await
            .unwrap();
        assert_eq!(
            refused.headers()["www-authenticate"],
            "Bearer",
            "{method} {path}"
        );
        let (status, body) = status_and_json(refused).await;
        assert_eq!(status, 401, "{method} {path}: {body}");
        let allowed = app
            .client
            .request(method.clone(), &url)
            .bearer_auth("s3cret")
            .send()
            .await
            .unwrap();
        assert_eq!(allowed.status().as_u16(), with_token, "{method} {path}");
    }
    // Outside /api nothing needs the token.
    for (path, status) in [("/healthz", 200), ("/apix", 404), ("/nowhere", 404)] {
        let response = get(&app, &format!("{}{path}", app.address), None).await;
        assert_eq!(response.status().as_u16(), status, "{path}");
    }
    app.stop().await;
}

/// `/metrics` has as many request series after 300 requests with invented
/// methods as after one: unknown methods count as `OTHER`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invented_methods_do_not_grow_the_metrics() {
    let app = spawn_app().await;
    let series = |text: &str| {
        text.lines()
            .filter(|l| l.starts_with("ptv_http_requests_total{"))
            .count()
    };
    let invented = |i: usize| reqwest::Method::from_bytes(format!("M{i:08X}").as_bytes()).unwrap();
    let metrics_url = format!("{}/metrics", app.address);
    let send = |i: usize| {
        let method = invented(i);
        let client = app.client.clone();
        let urls = [
            format!("{}/healthz", app.address),
            app.api(&format!("/nowhere/{i}")),
        ];
        async move {
            for url in urls {
                let response = client.request(method.clone(), url).send().await.unwrap();
                assert!(response.status().is_client_error(), "{}", response.status());
            }
        }
    };
    send(0).await;
    let after_one = app.get_text(metrics_url.clone()).await;
    for i in 1..300 {
        send(i).await;
    }
    let after_many = app.get_text(metrics_url.clone()).await;
    // The scrape itself adds one series (GET /metrics 200) the first time.
    assert_eq!(series(&after_many), series(&after_one) + 1, "{after_many}");
    assert!(after_many.contains("method=\"OTHER\""), "{after_many}");
    assert!(!after_many.contains("M0000"), "{after_many}");
    assert!(
        after_many.len() < after_one.len() + 200,
        "{} -> {}",
        after_one.len(),
        after_many.len()
    );
    app.stop().await;
}

/// A request target over 8 KiB gets a 414, and header fields over 64 KiB
/// or over 100 a 431, each a problem+json naming the limit (hyper alone
/// answered them with an empty body).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_targets_and_large_heads_are_refused_with_problems() {
    let app = spawn_app().await;
    let long_path = format!("/api/v1/jobs/{}", "1".repeat(20 * 1024));
    let long_query = format!("/healthz?{}", "a=b&".repeat(3000));
    let big_field = format!("X-Big: {}\r\n", "v".repeat(70 * 1024));
    let many_fields: String = (0..150).map(|i| format!("X-F{i}: v\r\n")).collect();
    let cases = [
        (
            "long path",
            long_path.as_str(),
            String::new(),
            414,
            "8192 bytes",
        ),
        (
            "long query",
            long_query.as_str(),
            String::new(),
            414,
            "8192 bytes",
        ),
        ("big field", "/healthz", big_field, 431, "65536 bytes"),
        (
            "150 fields",
            "/healthz",
            many_fields,
            431,
            "at most 100 fields",
        ),
    ];
    for (case, target, fields, status, needle) in cases {
        let head = format!("GET {target} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{fields}\r\n");
        let exchange = exchange(&app.address, head.as_bytes(), &[], Duration::from_secs(10)).await;
        let answer = &exchange.answer;
        assert!(
            answer.starts_with(&format!("HTTP/1.1 {status} ")),
            "{case}: {answer}"
        );
        let lower = answer.to_ascii_lowercase();
        assert!(
            lower.contains("content-type: application/problem+json"),
            "{case}: {answer}"
        );
        assert!(answer.contains(needle), "{case}: {answer}");
        assert!(exchange.closed_after.is_some(), "{case}: still open");
    }
    // Just within the limits: 100 fields, 8 KiB of target.
    let fields: String = (0..98).map(|i| format!("X-F{i}: v\r\n")).collect();
    let target = format!("/healthz?{}", "a".repeat(8192 - 9));
    let head = format!("GET {target} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n{fields}\r\n");
    let exchange = exchange(&app.address, head.as_bytes(), &[], Duration::from_secs(10)).await;
    assert!(
        exchange.answer.starts_with("HTTP/1.1 200 "),
        "{}",
        exchange.answer
    );
    app.stop().await;
}
