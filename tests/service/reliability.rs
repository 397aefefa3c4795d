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
    let sequence = create_rig_sequence(&client, &first_address, &rig).await;
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
    assert!(stored_images(data_dir.path()).await.is_empty());
}

/// The lease in the worker test (s): short, so that the takeover is
/// quick, yet many heartbeats (a third of it) long on a loaded machine.
const LEASE_SECS: u64 = 3;

/// How long each attempt waits before its work in the worker test
/// (`PTV_FAULT_JOB_DELAY_MS`), its lease renewed meanwhile: longer than
/// the lease, so that only renewals keep a live worker's job.
const JOB_DELAY_MS: u64 = 4_000;

/// Frames in the worker test: as many as one worker process has workers,
/// so that the surviving process has a worker free when the lease runs
/// out (a busy one would take the job only after its own).
const WORKER_FRAMES: i64 = 2;

/// `ptv serve --workers 0` takes the uploads and two `ptv worker`
/// processes (2 workers each) the jobs. One worker is killed (-9) in the middle of a job:
/// the other takes the job over once its lease has run out (not before),
/// within the lease plus the idle workers' poll, and it completes exactly
/// once; the job's claims show the takeover; every frame is processed
/// once, by the worker processes only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_process_s_job_is_taken_over_after_its_lease_and_completes_once() {
    let data_dir = tempfile::tempdir().unwrap();
    let lease = LEASE_SECS.to_string();
    let lease_args = ["--lease-secs", lease.as_str()];
    let server = ServiceProcess::start_with(data_dir.path(), 0, &lease_args);
    let delay = JOB_DELAY_MS.to_string();
    let env = [("PTV_FAULT_JOB_DELAY_MS", delay.as_str())];
    let worker_args = ["--lease-secs", lease.as_str(), "--workers", "2"];
    let mut workers = [
        WorkerProcess::start(data_dir.path(), &worker_args, &env),
        WorkerProcess::start(data_dir.path(), &worker_args, &env),
    ];
    let pids: Vec<u32> = workers.iter().map(WorkerProcess::pid).collect();

    let client = reqwest::Client::new();
    let address = server.address.clone();
    let api = |path: &str| format!("{address}/api/v1{path}");
    let rig = rig();
    let sequence = create_rig_sequence(&client, &address, &rig).await;
    let frames: Vec<_> = (0..WORKER_FRAMES)
        .map(|f| rig.targets(200, 900 + f as u64))
        .collect();
    for (frame, targets) in frames.iter().enumerate() {
        let (status, body) = upload(
            &client,
            &address,
            sequence,
            targets_form(frame as i64, targets),
        )
        .await;
        assert_eq!(status, 202, "{body}");
    }

    // Kill the holder of the first job seen running, a second into its
    // attempt (the attempt waits JOB_DELAY_MS before its work).
    let db = open_database(data_dir.path()).await;
    let (job, holder) = loop {
        let running: Option<(i64, String, String)> = sqlx::query_as(
            "SELECT id, locked_by, started_at FROM jobs WHERE state = 'running' \
             ORDER BY id LIMIT 1",
        )
        .fetch_optional(&db)
        .await
        .unwrap();
        // The database's clock is this machine's.
        if let Some((id, holder, started_at)) = running {
            if unix_seconds_now() - unix_seconds(&started_at) >= 1.0 {
                break (id, holder);
            }
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    };
    let pid = worker_pid(&holder).unwrap();
    let index = pids
        .iter()
        .position(|&p| p == pid)
        .unwrap_or_else(|| panic!("job {job} is held by {holder}, not by a worker process"));
    workers[index].kill();
    // The lease it held when it died, from the database's clock.
    let (lease_until,): (String,) = sqlx::query_as("SELECT lease_until FROM jobs WHERE id = $1")
        .bind(job)
        .fetch_one(&db)
        .await
        .unwrap();

    let view = wait_for_sequence(&client, &address, sequence).await;
    assert_eq!(view["frames"]["done"], WORKER_FRAMES, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");

    // The job's claims: the killed worker's expired, the other's succeeded.
    let (status, job_view) = status_and_json(
        client
            .get(api(&format!("/jobs/{job}")))
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_eq!(status, 200, "{job_view}");
    assert_eq!(job_view["state"], "succeeded", "{job_view}");
    assert_eq!(job_view["attempts"], 2, "{job_view}");
    let claims = job_view["claims"].as_array().unwrap();
    assert_eq!(claims.len(), 2, "{job_view}");
    assert_eq!(claims[0]["token"], 1, "{job_view}");
    assert_eq!(claims[0]["worker"], holder.as_str(), "{job_view}");
    assert_eq!(claims[0]["outcome"], "expired", "{job_view}");
    assert_eq!(claims[1]["token"], 2, "{job_view}");
    assert_eq!(claims[1]["outcome"], "succeeded", "{job_view}");
    let taker = claims[1]["worker"].as_str().unwrap();
    assert_eq!(worker_pid(taker), Some(pids[1 - index]), "{job_view}");

    // Taken over after the lease ran out, and within the lease's end plus
    // the idle worker's longest poll (1 s) and 2 s of slack for a loaded
    // machine: the seconds from the dead worker's lease to the takeover.
    let (claimed_at,): (String,) =
        sqlx::query_as("SELECT claimed_at FROM job_claims WHERE job_id = $1 AND token = 2")
            .bind(job)
            .fetch_one(&db)
            .await
            .unwrap();
    let after = unix_seconds(&claimed_at) - unix_seconds(&lease_until);
    assert!(
        (0.0..=3.0).contains(&after),
        "taken over {after:.2} s after the lease ended"
    );

    // Exactly once: one result per frame, and no claim left open.
    assert_eq!(
        count(&db, "SELECT count(*) FROM frames").await,
        WORKER_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs WHERE state = 'succeeded'").await,
        WORKER_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM particles").await,
        WORKER_FRAMES
    );
    assert_eq!(
        count(
            &db,
            "SELECT count(*) FROM job_claims WHERE outcome = 'succeeded'"
        )
        .await,
        WORKER_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM job_claims WHERE outcome IS NULL").await,
        0
    );
    // Only the worker processes claimed: the server has no workers.
    let claimers: Vec<(String,)> = sqlx::query_as("SELECT DISTINCT worker FROM job_claims")
        .fetch_all(&db)
        .await
        .unwrap();
    for (worker,) in &claimers {
        let pid = worker_pid(worker);
        assert!(pid.is_some_and(|p| pids.contains(&p)), "{worker}");
    }
    // The sequence keeps no images: none left behind.
    assert_eq!(count(&db, "SELECT count(*) FROM images").await, 0);
    db.close().await;
    drop(workers);
    drop(server);
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

/// Processes started together on a new data directory (an operator's
/// script, a compose file) open the database one at a time: before, two
/// migrating it at once both applied its first migration and one died
/// ("table job_files already exists", or "database is locked" switching
/// it to WAL). Workers first, then the server, with no wait between.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn processes_started_together_on_a_new_data_directory_all_run() {
    for _ in 0..3 {
        let data_dir = tempfile::tempdir().unwrap();
        let mut workers = [
            WorkerProcess::start(data_dir.path(), &[], &[]),
            WorkerProcess::start(data_dir.path(), &[], &[]),
        ];
        let server = ServiceProcess::start_with(data_dir.path(), 0, &[]);
        let health = reqwest::get(format!("{}/readyz", server.address))
            .await
            .unwrap();
        assert_eq!(health.status(), 200);
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
        for worker in &mut workers {
            assert!(
                worker.child.try_wait().unwrap().is_none(),
                "a worker started beside others exited"
            );
        }
    }
}

/// Claimers in two processes' worth of stores (two pools on one database)
/// claim at once: no job is claimed twice, and every job is claimed. On
/// SQLite the write lock orders the claims; on PostgreSQL each claim locks
/// its row with `FOR UPDATE SKIP LOCKED`, so that claimers pass over each
/// other's rows instead of taking them twice or waiting.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn claimers_at_once_never_get_the_same_job() {
    use std::time::Duration;
    const JOBS: usize = 60;
    const CLAIMERS: usize = 8;
    let data_dir = tempfile::tempdir().unwrap();
    let stores = [
        open_store(data_dir.path()).await,
        open_store(data_dir.path()).await,
    ];
    for _ in 0..JOBS {
        stores[0].enqueue("echo", "{}").await.unwrap();
    }
    let mut tasks = tokio::task::JoinSet::new();
    for claimer in 0..CLAIMERS {
        let store = stores[claimer % 2].clone();
        tasks.spawn(async move {
            let mut claimed = Vec::new();
            let worker = format!("here:{claimer}:aa/0");
            while let Some(job) = store
                .claim(&worker, Duration::from_secs(600))
                .await
                .unwrap()
            {
                claimed.push(job.id.0);
            }
            claimed
        });
    }
    let mut all = Vec::new();
    while let Some(claimed) = tasks.join_next().await {
        all.extend(claimed.unwrap());
    }
    all.sort_unstable();
    let expected: Vec<i64> = (1..=JOBS as i64).collect();
    assert_eq!(all, expected, "each job claimed exactly once");
    let db = open_database(data_dir.path()).await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM job_claims").await,
        JOBS as i64
    );
    assert_eq!(
        count(
            &db,
            "SELECT count(*) FROM jobs WHERE state = 'running' AND attempts = 1"
        )
        .await,
        JOBS as i64
    );
    db.close().await;
    for store in stores {
        store.close().await;
    }
}

/// PostgreSQL stopped for 10 s (`pg_ctl stop -m fast`, then started again
/// on the same port) while a client uploads frames: every upload is
/// accepted (202, perhaps after waiting for the database) or refused with
/// a 503 and `Retry-After` (then sent again), the service recovers by
/// itself, no accepted frame is lost and
/// every accepted frame ends processed. PostgreSQL only: the test stops a
/// server of its own (the other tests' server runs on).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_survive_postgres_stopped_for_ten_seconds() {
    use std::time::{Duration, Instant};
    if !crate::postgres::enabled() {
        // SQLite lives in the service's process: there is no server to stop.
        return;
    }
    const FRAMES: i64 = 40;
    const OUTAGE: Duration = Duration::from_secs(10);
    let server = std::sync::Arc::new(crate::postgres::Server::start("outage"));
    let url = server.create_database();
    let app = spawn_app_configured(|args| args.storage.database = Some(url.parse().unwrap())).await;
    let (rig, sequence) = app.rig_sequence().await;
    let frames: Vec<_> = (0..FRAMES)
        .map(|f| rig.targets(150, 4000 + f as u64))
        .collect();

    let stopper = server.clone();
    let outage = tokio::spawn(async move {
        tokio::time::sleep(Duration::from_secs(1)).await;
        let s = stopper.clone();
        tokio::task::spawn_blocking(move || s.stop()).await.unwrap();
        let stopped = Instant::now();
        tokio::time::sleep(OUTAGE).await;
        let s = stopper.clone();
        tokio::task::spawn_blocking(move || s.start_again())
            .await
            .unwrap();
        stopped.elapsed()
    });

    let mut accepted = 0;
    let mut refused = 0;
    let mut longest = Duration::ZERO;
    let started = Instant::now();
    for (frame, targets) in frames.iter().enumerate() {
        loop {
            let sent = Instant::now();
            let response = app
                .client
                .post(app.api(&format!("/sequences/{sequence}/frames")))
                .multipart(targets_form(frame as i64, targets))
                .send()
                .await
                .unwrap();
            let retry_after = response.headers().get("retry-after").cloned();
            let (status, body) = status_and_json(response).await;
            longest = longest.max(sent.elapsed());
            match status {
                202 => {
                    accepted += 1;
                    break;
                }
                503 => {
                    let seconds: u64 = retry_after
                        .unwrap_or_else(|| panic!("a 503 without Retry-After: {body}"))
                        .to_str()
                        .unwrap()
                        .parse()
                        .unwrap();
                    assert!(seconds > 0, "{body}");
                    refused += 1;
                    // A client waits as asked (capped: the test's patience).
                    tokio::time::sleep(Duration::from_secs(seconds.min(2))).await;
                }
                other => panic!("frame {frame}: {other} {body}"),
            }
            assert!(started.elapsed() < PATIENCE, "uploads did not recover");
        }
        // Spread the uploads over the outage.
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let down_for = outage.await.unwrap();
    assert!(down_for >= OUTAGE, "{down_for:?}");
    assert_eq!(accepted, FRAMES);
    eprintln!(
        "PostgreSQL down for {down_for:.1?}: {refused} uploads refused with 503, \
         the longest upload took {longest:.1?}"
    );
    // An upload that met the outage was refused (503), or waited for the
    // database (the pool's connection wait, up to 10 s) and then got in.
    assert!(
        refused > 0 || longest >= Duration::from_secs(5),
        "no upload met the outage (longest {longest:?})"
    );

    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], FRAMES, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");
    let db = {
        sqlx::any::install_default_drivers();
        sqlx::any::AnyPoolOptions::new()
            .max_connections(1)
            .connect(&url)
            .await
            .unwrap()
    };
    assert_eq!(count(&db, "SELECT count(*) FROM frames").await, FRAMES);
    assert_eq!(count(&db, "SELECT count(*) FROM particles").await, FRAMES);
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs WHERE state = 'succeeded'").await,
        FRAMES
    );
    db.close().await;
    app.stop().await;
    tokio::task::spawn_blocking(move || server.stop())
        .await
        .unwrap();
}

/// Frames uploaded in the object store fault test.
const OUTAGE_FRAMES: i64 = 16;

/// How long the S3 server is down in the fault test.
const OUTAGE: std::time::Duration = std::time::Duration::from_secs(10);

/// Under `PTV_TEST_OBJECT_STORE=s3` only (the local directory has no
/// server to stop): the S3 server is killed (-9) for 10 s while frames are
/// uploaded and processed, then started again on its port and directory.
/// Uploads meanwhile get 503 with `Retry-After` (or wait in
/// `object_store`'s retries and succeed) and succeed again afterwards;
/// every accepted (202) frame ends processed, none failed, none lost;
/// `/readyz` is 503 during the outage and 200 after it.
/// This test has an S3 server of its own, so that the outage does not
/// touch the other tests running in the same process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_object_store_outage_during_uploads_loses_no_accepted_frame() {
    if !s3_tests() {
        // Specific to the S3 backend: no server to stop otherwise. CI's
        // second service run (PTV_TEST_OBJECT_STORE=s3) runs it.
        eprintln!("skipped: needs PTV_TEST_OBJECT_STORE=s3");
        return;
    }
    let _ = s3_server(); // the AWS variables
    let server = std::sync::Arc::new(std::sync::Mutex::new(S3Server::launch()));
    let endpoint = server.lock().unwrap().endpoint.clone();
    let app = spawn_app_configured(|args| {
        args.storage.objects.url = Some(format!("s3://{TEST_BUCKET}/outage").parse().unwrap());
        args.storage.objects.s3_endpoint = Some(endpoint);
    })
    .await;
    let (rig, sequence) = app.rig_sequence().await;
    let files: Vec<Vec<u8>> = rig.render(300, 78).images.iter().map(png).collect();

    let uploads = {
        let (client, address) = (app.client.clone(), app.address.clone());
        tokio::spawn(async move {
            let mut unavailable = 0;
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(300);
            for frame in 0..OUTAGE_FRAMES {
                loop {
                    assert!(
                        std::time::Instant::now() < deadline,
                        "uploads never recovered"
                    );
                    let response = client
                        .post(format!("{address}/api/v1/sequences/{sequence}/frames"))
                        .multipart(image_form(frame, &files))
                        .send()
                        .await
                        .unwrap();
                    let status = response.status().as_u16();
                    let retry_after = response.headers().get("retry-after").cloned();
                    let body = response.text().await.unwrap();
                    match status {
                        202 => break,
                        503 => {
                            let seconds: u64 = retry_after
                                .expect("a 503 says when to retry")
                                .to_str()
                                .unwrap()
                                .parse()
                                .unwrap();
                            assert!(body.contains("object store"), "{body}");
                            unavailable += 1;
                            tokio::time::sleep(std::time::Duration::from_secs(seconds.min(2)))
                                .await;
                        }
                        other => panic!("frame {frame}: {other} {body}"),
                    }
                }
            }
            unavailable
        })
    };
    // The outage starts once a few frames are in.
    loop {
        let (_, view) = app.get_json(&format!("/sequences/{sequence}")).await;
        let counts = &view["frames"];
        let total: i64 = ["queued", "running", "done", "failed"]
            .iter()
            .map(|state| counts[state].as_i64().unwrap_or(0))
            .sum();
        if total >= 3 {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    {
        let server = server.clone();
        tokio::task::spawn_blocking(move || server.lock().unwrap().stop())
            .await
            .unwrap();
    }
    let started = std::time::Instant::now();
    // Readiness says so meanwhile.
    let ready = app
        .client
        .get(format!("{}/readyz", app.address))
        .send()
        .await
        .unwrap();
    assert_eq!(ready.status().as_u16(), 503);
    let detail = ready.text().await.unwrap();
    assert!(detail.contains("object store"), "{detail}");
    tokio::time::sleep(OUTAGE.saturating_sub(started.elapsed())).await;
    {
        let server = server.clone();
        tokio::task::spawn_blocking(move || server.lock().unwrap().start())
            .await
            .unwrap();
    }
    let unavailable = uploads.await.unwrap();
    // 10 s is longer than `object_store`'s retries of one request (6
    // retries, 1.6 s of backoff against a refused connection here, at most
    // 15 s), so the uploads during the outage were answered 503.
    assert!(unavailable > 0, "no upload saw the outage");

    assert_eq!(
        app.get_text(format!("{}/readyz", app.address)).await,
        "ready\n"
    );
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], OUTAGE_FRAMES, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");
    let db = app.database().await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM particles").await,
        OUTAGE_FRAMES
    );
    assert_eq!(
        count(&db, "SELECT count(*) FROM jobs WHERE state = 'succeeded'").await,
        OUTAGE_FRAMES
    );
    app.stop().await;
    drop(server);
}

/// The image store's lock (persist and commit against "no row, so
/// delete") excludes every process on the database: on SQLite those of
/// its one data directory (the `flock`), on PostgreSQL those of every
/// host (an advisory lock in the database; here two data directories,
/// whose `flock`s cannot see each other, stand for two hosts). The
/// second process waits until the first lets go.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_image_lock_holds_across_hosts() {
    use ptv::service::ops::images::ImageStore;
    use std::time::Duration;
    let (first_dir, other_dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    // SQLite's processes share one host, and so one data directory.
    let postgres = crate::postgres::database_url(first_dir.path()).is_some();
    let second_dir = if postgres {
        other_dir.path()
    } else {
        first_dir.path()
    };
    // Both on the first's database.
    let open = |dir: std::path::PathBuf| {
        let database = first_dir.path().to_owned();
        async move {
            let store = open_store(&database).await;
            let images = ImageStore::open_shared(&dir, None).await.unwrap();
            (store, images)
        }
    };
    let first = open(first_dir.path().to_owned()).await;
    let second = std::sync::Arc::new(open(second_dir.to_owned()).await);
    let held = first.1.lock(&first.0).await.unwrap();
    let (took, taken) = tokio::sync::oneshot::channel();
    let waiter = {
        let second = second.clone();
        tokio::spawn(async move {
            let _lock = second.1.lock(&second.0).await.unwrap();
            let _ = took.send(());
        })
    };
    let mut taken = taken;
    // Half a second is many times what taking a free lock costs (a few
    // ms); the waiter must not have it while the first holds it.
    assert!(
        tokio::time::timeout(Duration::from_millis(500), &mut taken)
            .await
            .is_err(),
        "a second process took the image lock while the first held it"
    );
    drop(held);
    tokio::time::timeout(Duration::from_secs(10), taken)
        .await
        .expect("the second process takes the lock once it is free")
        .unwrap();
    waiter.await.unwrap();
    first.0.close().await;
    second.0.close().await;
}

/// `ptv serve --fsync` and `ptv worker` with `PTV_FSYNC=1` (every commit
/// and stored file flushed to the disk before the 202: what survives a
/// power loss, which no test can cut) take uploads and process them as
/// without it. (That `--fsync` sets `synchronous = FULL` on every
/// connection is `store::tests::commits_are_flushed_as_asked`.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flushed_uploads_are_stored_and_processed() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServiceProcess::start_with(dir.path(), 0, &["--fsync"]);
    let _worker = WorkerProcess::start(dir.path(), &[], &[("PTV_FSYNC", "1")]);
    let (client, address) = (reqwest::Client::new(), server.address.clone());
    let rig = rig();
    let sequence = create_rig_sequence(&client, &address, &rig).await;
    let rendered = rig.render(200, 7);
    let files: Vec<Vec<u8>> = rendered.images.iter().map(png).collect();
    for frame in 0..3 {
        let (status, body) = upload(&client, &address, sequence, image_form(frame, &files)).await;
        assert_eq!(status, 202, "{body}");
    }
    let body = wait_for_sequence(&client, &address, sequence).await;
    assert_eq!(body["frames"]["done"], 3, "{body}");
}
