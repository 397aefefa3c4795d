//! Live progress and the lists the web page reads: a sequence's events
//! (server-sent events) arrive in order as frames are uploaded and
//! processed, an unknown sequence is a 404 before any stream, a stream
//! ends at shutdown; calibrations and sequences listed newest first a page
//! at a time, a sequence's frames with their states and particle counts.

use std::time::Duration;

use futures_util::StreamExt;
use serde_json::Value;

use crate::helpers::*;

/// One server-sent event: `event:`, `id:` and `data:` as JSON.
#[derive(Debug)]
pub struct Sse {
    pub event: String,
    pub id: Option<u64>,
    pub data: Value,
}

/// A `text/event-stream` read event by event.
pub struct EventStream {
    body: std::pin::Pin<
        Box<dyn futures_util::Stream<Item = reqwest::Result<axum::body::Bytes>> + Send>,
    >,
    buffer: String,
}

impl EventStream {
    /// Opens `GET {url}`, which must answer 200 `text/event-stream`.
    pub async fn open(client: &reqwest::Client, url: String) -> EventStream {
        EventStream::request(client.get(url)).await
    }

    /// Sends `request`, which must answer 200 `text/event-stream`.
    pub async fn request(request: reqwest::RequestBuilder) -> EventStream {
        let response = request.send().await.unwrap();
        assert_eq!(response.status(), 200);
        assert_eq!(response.headers()["content-type"], "text/event-stream");
        EventStream {
            body: Box::pin(response.bytes_stream()),
            buffer: String::new(),
        }
    }

    /// The next event (comments, the keep-alives, skipped); None at the
    /// stream's end. Waits at most 60 s (a hang guard).
    pub async fn next(&mut self) -> Option<Sse> {
        loop {
            if let Some(end) = self.buffer.find("\n\n") {
                let block: String = self.buffer.drain(..end + 2).collect();
                let (mut event, mut id, mut data) = ("message".to_owned(), None, String::new());
                for line in block.lines() {
                    if let Some(value) = line.strip_prefix("event:") {
                        event = value.trim().to_owned();
                    } else if let Some(value) = line.strip_prefix("id:") {
                        id = Some(value.trim().parse().unwrap());
                    } else if let Some(value) = line.strip_prefix("data:") {
                        data.push_str(value.trim_start());
                    }
                }
                if data.is_empty() {
                    continue;
                }
                let data = serde_json::from_str(&data).unwrap();
                return Some(Sse { event, id, data });
            }
            let chunk = tokio::time::timeout(Duration::from_secs(60), self.body.next())
                .await
                .expect("an event within 60 s")?
                .unwrap();
            self.buffer.push_str(std::str::from_utf8(&chunk).unwrap());
        }
    }
}

/// Frames uploaded in order are announced accepted, running and processed,
/// each after its change is committed (the particles are there when the
/// event arrives), with rising ids; the stream opens with the frame counts
/// and ends with `closing` when the service shuts down.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sequence_s_events_arrive_in_order() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let (_, other) = app.rig_sequence().await;
    let mut events = EventStream::open(
        &app.client,
        app.api(&format!("/sequences/{sequence}/events")),
    )
    .await;
    let snapshot = events.next().await.unwrap();
    assert_eq!(snapshot.event, "snapshot");
    assert_eq!(snapshot.data["sequence_id"], sequence);
    assert_eq!(snapshot.data["frames"]["done"], 0);

    let mut last_id = 0;
    for frame in 0..3 {
        let (status, body) = app
            .upload(
                sequence,
                targets_form(frame, &rig.targets(100, frame as u64)),
            )
            .await;
        assert_eq!(status, 202, "{body}");
        let job = body["job_id"].as_i64().unwrap();
        for expected in ["frame_accepted", "frame_running", "frame_processed"] {
            let event = events.next().await.unwrap();
            assert_eq!(event.event, expected, "{event:?}");
            assert_eq!(event.data["type"], expected);
            assert_eq!(event.data["sequence_id"], sequence, "{event:?}");
            assert_eq!(event.data["frame"], frame);
            assert_eq!(event.data["job_id"], job);
            let id = event.id.unwrap();
            assert!(id > last_id, "{id} after {last_id}");
            last_id = id;
        }
        // Committed before announced.
        let (status, particles) = app
            .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
            .await;
        assert_eq!(status, 200, "{particles}");
        // Another sequence's frame: not on this stream (uploaded while no
        // frame of this one is pending: a worker that finishes a job
        // claims the next at once, and could take up a frame between its
        // upload's commit and the `frame_accepted` sent right after).
        let (status, body) = app
            .upload(
                other,
                targets_form(frame, &rig.targets(50, 100 + frame as u64)),
            )
            .await;
        assert_eq!(status, 202, "{body}");
        app.wait_for_sequence(other).await;
    }
    let stop = tokio::time::timeout(Duration::from_secs(20), app.stop());
    let (stopped, closing) = tokio::join!(stop, events.next());
    stopped.expect("the service stops with an event stream open");
    assert_eq!(closing.unwrap().event, "closing");
}

/// With `ptv serve --workers 0` and a `ptv worker` process on one data
/// directory, the frames the worker processes are announced on the
/// server's stream (through the event log, as workers on other hosts'
/// would be); a client that reconnects with `Last-Event-ID` is sent the
/// events it missed instead of a snapshot, and one with a bad id gets a
/// 400.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_process_s_changes_reach_the_stream_and_a_reconnect_gets_what_it_missed() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServiceProcess::start(dir.path(), 0);
    let _worker = WorkerProcess::start(dir.path(), &[], &[]);
    let (client, address) = (reqwest::Client::new(), server.address.clone());
    let rig = rig();
    let sequence = create_rig_sequence(&client, &address, &rig).await;
    let url = format!("{address}/api/v1/sequences/{sequence}/events");
    let mut events = EventStream::open(&client, url.clone()).await;
    assert_eq!(events.next().await.unwrap().event, "snapshot");
    let (status, body) = upload(
        &client,
        &address,
        sequence,
        targets_form(0, &rig.targets(100, 0)),
    )
    .await;
    assert_eq!(status, 202, "{body}");
    // Accepted and running in either order (a worker may take the frame
    // up before the server's `frame_accepted` is logged, see
    // `service::events`), then processed.
    let mut seen = Vec::new();
    let mut last = 0;
    for _ in 0..3 {
        let event = events.next().await.unwrap();
        assert_eq!(event.data["frame"], 0, "{event:?}");
        seen.push(event.event);
        last = event.id.unwrap();
    }
    assert_eq!(seen[2], "frame_processed", "{seen:?}");
    seen.sort_unstable();
    assert_eq!(
        seen,
        ["frame_accepted", "frame_processed", "frame_running"],
        "{seen:?}"
    );
    drop(events);

    // Missed while away: frames 1 and 2, processed by the worker.
    for frame in 1..3 {
        let (status, body) = upload(
            &client,
            &address,
            sequence,
            targets_form(frame, &rig.targets(100, frame as u64)),
        )
        .await;
        assert_eq!(status, 202, "{body}");
    }
    wait_for_sequence(&client, &address, sequence).await;
    let mut events =
        EventStream::request(client.get(&url).header("Last-Event-ID", last.to_string())).await;
    let mut processed = Vec::new();
    while processed.len() < 2 {
        let event = events.next().await.unwrap();
        assert_ne!(event.event, "snapshot", "replayed, not a snapshot");
        let id = event.id.unwrap();
        assert!(id > last, "{id} after {last}");
        last = id;
        if event.event == "frame_processed" {
            processed.push(event.data["frame"].as_i64().unwrap());
        }
    }
    // The worker's two threads may finish them in either order.
    processed.sort_unstable();
    assert_eq!(processed, [1, 2]);

    // An id past the log's end: nothing missed, no snapshot either; the
    // next frame's events follow.
    drop(events);
    let mut events =
        EventStream::request(client.get(&url).header("Last-Event-ID", last.to_string())).await;
    let (status, body) = upload(
        &client,
        &address,
        sequence,
        targets_form(3, &rig.targets(100, 3)),
    )
    .await;
    assert_eq!(status, 202, "{body}");
    // Frame 3's first event (accepted; or running, where the worker took
    // it up first, see `service::events`), nothing older.
    let event = events.next().await.unwrap();
    assert_eq!(event.data["frame"], 3, "{event:?}");
    assert!(
        ["frame_accepted", "frame_running"].contains(&event.event.as_str()),
        "{event:?}"
    );

    let response = client
        .get(&url)
        .header("Last-Event-ID", "yesterday")
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 400, "{body}");
    assert!(
        body["detail"].as_str().unwrap().contains("Last-Event-ID"),
        "{body}"
    );
}

/// An unknown sequence's events are a 404 problem, not an empty stream;
/// with a token, a stream needs it as every API route does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_of_an_unknown_sequence_are_404_and_need_the_token() {
    let app = spawn_app_with(Some("s3cret")).await;
    let url = app.api("/sequences/99/events");
    let response = app.client.get(&url).send().await.unwrap();
    assert_eq!(response.status(), 401);
    let response = app
        .client
        .get(&url)
        .bearer_auth("s3cret")
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 404);
    assert!(
        body["detail"]
            .as_str()
            .unwrap()
            .contains("sequence 99 does not exist"),
        "{body}"
    );
    let response = app
        .client
        .get(app.api("/sequences/nine/events"))
        .bearer_auth("s3cret")
        .send()
        .await
        .unwrap();
    assert_eq!(status_and_json(response).await.0, 400);
    app.stop().await;
}

/// Calibrations and sequences newest first, a page at a time, following
/// `next` to the end; a sequence's frames in order with their states and
/// particle counts; bad pages refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lists_go_newest_first_a_page_at_a_time() {
    let app = spawn_app().await;
    let rig = rig();
    let mut calibrations = Vec::new();
    for _ in 0..3 {
        calibrations.push(app.create_calibration(&rig.cameras).await);
    }
    let sequences = [
        app.create_sequence(calibrations[0], &rig.volume, false)
            .await,
        app.create_sequence(calibrations[2], &rig.volume, false)
            .await,
    ];
    let ids = |page: &Value| -> Vec<i64> {
        page["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|i| i["id"].as_i64().unwrap())
            .collect()
    };
    let (status, first) = app.get_json("/calibrations?limit=2").await;
    assert_eq!(status, 200, "{first}");
    assert_eq!(ids(&first), [calibrations[2], calibrations[1]]);
    assert_eq!(first["items"][0]["cameras"], 4);
    assert_eq!(first["items"][0]["has_report"], false);
    let next = first["next"]
        .as_str()
        .unwrap()
        .strip_prefix("/api/v1")
        .unwrap();
    let (_, second) = app.get_json(next).await;
    assert_eq!(ids(&second), [calibrations[0]]);
    assert!(second["next"].is_null(), "{second}");

    for frame in 0..3 {
        let (status, body) = app
            .upload(
                sequences[1],
                targets_form(frame, &rig.targets(80, frame as u64)),
            )
            .await;
        assert_eq!(status, 202, "{body}");
    }
    app.wait_for_sequence(sequences[1]).await;
    let (_, list) = app.get_json("/sequences").await;
    assert_eq!(ids(&list), [sequences[1], sequences[0]]);
    assert_eq!(list["items"][0]["frames"]["done"], 3, "{list}");
    assert_eq!(list["items"][0]["calibration_id"], calibrations[2]);
    assert_eq!(list["items"][1]["frames"]["done"], 0);

    let (status, frames) = app
        .get_json(&format!("/sequences/{}/frames?limit=2", sequences[1]))
        .await;
    assert_eq!(status, 200, "{frames}");
    let items = frames["items"].as_array().unwrap();
    assert_eq!(items.len(), 2);
    for (i, item) in items.iter().enumerate() {
        assert_eq!(item["frame"], i as i64);
        assert_eq!(item["state"], "succeeded");
        let (_, particles) = app
            .get_json(&format!("/sequences/{}/frames/{i}/particles", sequences[1]))
            .await;
        assert_eq!(
            item["particles"].as_u64().unwrap() as usize,
            particles["particles"].as_array().unwrap().len()
        );
    }
    let next = frames["next"]
        .as_str()
        .unwrap()
        .strip_prefix("/api/v1")
        .unwrap();
    let (_, rest) = app.get_json(next).await;
    assert_eq!(rest["items"][0]["frame"], 2);

    for (path, status) in [
        ("/calibrations?limit=0", 400),
        ("/sequences?limit=101", 400),
        ("/sequences?before=x", 400),
        ("/sequences?page=2", 400),
        ("/sequences/999/frames", 404),
        (
            &format!("/sequences/{}/frames?limit=5000", sequences[0]),
            400,
        ),
    ] {
        let (got, body) = app.get_json(path).await;
        assert_eq!(got, status, "{path}: {body}");
    }
    app.stop().await;
}

/// A tracked sequence's stream: a frame past its time limit is announced
/// failed with the reason, every frame (the failed one as a gap) tracked
/// after its job's outcome, and the run's end after the finish request.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tracked_sequence_announces_failures_and_its_tracking() {
    // Frames past 0.2 s fail: 100 targets per camera take milliseconds,
    // 4 x 40,000 far longer (as in `job_bounds`).
    let app = spawn_app_configured(|args| {
        args.job_limits = ptv::service::JobLimits {
            floor_secs: 0.2,
            factor: 0.0,
            ..Default::default()
        };
    })
    .await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let mut body = sequence_body(calibration, &rig.volume, false);
    body["tracking"] = serde_json::json!({"max_velocity": 3.0});
    let (status, created) = app.post_json("/sequences", &body).await;
    assert_eq!(status, 201, "{created}");
    let sequence = created["id"].as_i64().unwrap();
    let mut events = EventStream::open(
        &app.client,
        app.api(&format!("/sequences/{sequence}/events")),
    )
    .await;
    assert_eq!(events.next().await.unwrap().event, "snapshot");
    let run = created["tracking"]["run_id"].as_i64().unwrap();
    for frame in 0..3 {
        let targets = rig.targets(if frame == 1 { 40_000 } else { 100 }, frame as u64);
        let (status, body) = app.upload(sequence, targets_form(frame, &targets)).await;
        assert_eq!(status, 202, "{body}");
        let outcome = if frame == 1 {
            "frame_failed"
        } else {
            "frame_processed"
        };
        for expected in ["frame_accepted", "frame_running", outcome, "tracked"] {
            let event = events.next().await.unwrap();
            assert_eq!(event.event, expected, "frame {frame}: {event:?}");
            if expected == "tracked" {
                assert_eq!(event.data["run_id"], run);
                assert_eq!(event.data["tracked_through"], frame);
            } else {
                assert_eq!(event.data["frame"], frame, "{event:?}");
            }
            if expected == "frame_failed" {
                let error = event.data["error"].as_str().unwrap();
                assert!(error.contains("time limit"), "{error}");
            }
        }
    }
    let (status, body) = app
        .post_json(
            &format!("/sequences/{sequence}/tracking/finish"),
            &Value::Null,
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let ended = events.next().await.unwrap();
    assert_eq!(ended.event, "tracking_ended", "{ended:?}");
    assert_eq!(ended.data["finished"], true);
    assert_eq!(ended.data["run_id"], run);
    app.stop().await;
}
