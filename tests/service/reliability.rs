//! A crash while jobs run, and many uploaders at once.

use std::collections::BTreeMap;

use serde_json::Value;

use crate::helpers::*;

/// Frames uploaded before the kill.
const CRASH_FRAMES: i64 = 12;

/// Kill -9 while a worker processes frames, restart on the same data
/// directory: every accepted frame is processed exactly once, with the
/// same result as any other attempt would give.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_service_processes_every_accepted_frame_exactly_once() {
    let data_dir = tempfile::tempdir().unwrap();
    let rig = rig();
    // One frame's images, uploaded as every frame: the same result is
    // expected for each, whichever attempt produced it.
    let files: Vec<Vec<u8>> = rig.render(300, 77).images.iter().map(png).collect();
    let client = reqwest::Client::new();

    let first = ServiceProcess::start(data_dir.path(), 1);
    let first_address = first.address.clone();
    let api = |path: &str| format!("{first_address}/api/v1{path}");
    let response = client
        .post(api("/calibrations"))
        .body(ptv::formats::calibration::to_json(&rig.cameras))
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 201, "{body}");
    let calibration = body["id"].as_i64().unwrap();
    let response = client
        .post(api("/sequences"))
        .json(&sequence_body(calibration, &rig.volume, false))
        .send()
        .await
        .unwrap();
    let (status, body) = status_and_json(response).await;
    assert_eq!(status, 201, "{body}");
    let sequence = body["id"].as_i64().unwrap();
    for frame in 0..CRASH_FRAMES {
        let (status, body) =
            upload(&client, &first_address, sequence, image_form(frame, &files)).await;
        assert_eq!(status, 202, "{body}");
    }
    // Kill as soon as a frame is done and the worker is busy with the next.
    let done_at_kill = loop {
        let (_, body) = status_and_json(
            client
                .get(api(&format!("/sequences/{sequence}")))
                .send()
                .await
                .unwrap(),
        )
        .await;
        let done = body["frames"]["done"].as_i64().unwrap();
        if done >= 1 && body["frames"]["running"] == 1 {
            first.kill();
            break done;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    };
    assert!(
        done_at_kill < CRASH_FRAMES,
        "all frames were done before the kill; the test saw no crash"
    );
    // The job the status showed running may have finished between that
    // poll and the kill; what the database says decides whether one was
    // interrupted.
    let interrupted = {
        let db = open_database(data_dir.path()).await;
        let n = count(&db, "SELECT count(*) FROM jobs WHERE state = 'running'").await;
        db.close().await;
        n
    };

    let second = ServiceProcess::start(data_dir.path(), 2);
    let view = wait_for_sequence(&client, &second.address, sequence).await;
    assert_eq!(view["frames"]["done"], CRASH_FRAMES, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");

    let mut counts = Vec::new();
    for frame in 0..CRASH_FRAMES {
        let (status, body) = status_and_json(
            client
                .get(format!(
                    "{}/api/v1/sequences/{sequence}/frames/{frame}/particles",
                    second.address
                ))
                .send()
                .await
                .unwrap(),
        )
        .await;
        assert_eq!(status, 200, "{body}");
        counts.push(body["particles"].as_array().unwrap().len());
    }
    assert!(counts[0] > 250, "{counts:?}");
    assert!(counts.iter().all(|&c| c == counts[0]), "{counts:?}");
    drop(second);

    let db = open_database(data_dir.path()).await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM frames").await,
        CRASH_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs WHERE state = 'succeeded'").await,
        CRASH_FRAMES
    );
    assert_eq!(count(&db, "SELECT count(*) FROM jobs").await, CRASH_FRAMES);
    assert_eq!(
        count(&db, "SELECT count(*) FROM particles").await,
        CRASH_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM targets").await,
        4 * CRASH_FRAMES
    );
    // The job the kill interrupted, if it did, ran again.
    if interrupted > 0 {
        assert!(count(&db, "SELECT max(attempts) FROM jobs").await >= 2);
    }
    // No image rows are left (the sequence keeps none), and no files.
    assert_eq!(count(&db, "SELECT count(*) FROM images").await, 0);
    assert!(crate::api::walk(&data_dir.path().join("images")).is_empty());
}

/// Uploaders at once.
const CLIENTS: usize = 32;
/// Frames each uploader sends (all of them send the same frames).
const SHARED_FRAMES: usize = 16;

/// 32 clients upload the same 16 frames in different orders: each frame
/// is accepted exactly once, every other attempt is a 409, nothing is a
/// 5xx, and every frame is processed once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_uploads_lose_and_duplicate_nothing() {
    let app = spawn_app().await;
    let rig = rig();
    let calibration = app.create_calibration(&rig.cameras).await;
    let sequence = app.create_sequence(calibration, &rig.volume, true).await;
    let frames: Vec<_> = (0..SHARED_FRAMES)
        .map(|f| rig.targets(200, 500 + f as u64))
        .collect();
    let frames = std::sync::Arc::new(frames);

    let mut tasks = tokio::task::JoinSet::new();
    for client_index in 0..CLIENTS {
        let frames = frames.clone();
        let address = app.address.clone();
        tasks.spawn(async move {
            let client = reqwest::Client::new();
            let mut statuses = Vec::new();
            for k in 0..SHARED_FRAMES {
                let frame = (k + client_index) % SHARED_FRAMES;
                let form = targets_form(frame as i64, &frames[frame]);
                let (status, body) = upload(&client, &address, sequence, form).await;
                statuses.push((frame, status, body));
            }
            statuses
        });
    }
    let mut accepted: BTreeMap<usize, Vec<Value>> = BTreeMap::new();
    let mut conflicts = 0;
    while let Some(result) = tasks.join_next().await {
        for (frame, status, body) in result.unwrap() {
            match status {
                202 => accepted.entry(frame).or_default().push(body),
                409 => conflicts += 1,
                other => panic!("frame {frame}: {other} {body}"),
            }
        }
    }
    assert_eq!(accepted.len(), SHARED_FRAMES);
    assert!(accepted.values().all(|a| a.len() == 1), "{accepted:?}");
    assert_eq!(conflicts, CLIENTS * SHARED_FRAMES - SHARED_FRAMES);

    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], SHARED_FRAMES as i64, "{view}");
    let db = app.database().await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM frames").await,
        SHARED_FRAMES as i64
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs").await,
        SHARED_FRAMES as i64
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM particles").await,
        SHARED_FRAMES as i64
    );
    // Uploaded targets come back as uploaded, and nearly all particles
    // (200 per frame, 0.05 px noise) are found.
    for (frame, targets) in frames.iter().enumerate() {
        let (status, body) = app
            .get_json(&format!(
                "/sequences/{sequence}/frames/{frame}/targets?camera=2"
            ))
            .await;
        assert_eq!(status, 200, "{body}");
        assert_eq!(
            body["targets"].as_array().unwrap().len(),
            targets.targets[2].len()
        );
        let (_, body) = app
            .get_json(&format!("/sequences/{sequence}/frames/{frame}/particles"))
            .await;
        let found = body["particles"].as_array().unwrap().len();
        assert!((190..=200).contains(&found), "frame {frame}: {found}");
    }
    app.stop().await;
}
