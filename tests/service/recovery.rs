//! Recovery: a full disk and a frame whose job failed.
//!
//! The full disk is SQLite's page limit on the writer
//! (`Store::set_max_page_count`), which fails writes with SQLITE_FULL
//! exactly as a full disk does, or a real one (a tmpfs); both SQLite's, so
//! skipped under `PTV_TEST_DATABASE=postgres`, where PostgreSQL's own
//! errors (disk full, shutting down) are raised by the server and mapped
//! to their statuses instead.

use std::time::{Duration, Instant};

use serde_json::Value;

use crate::helpers::*;

/// POSTs a calibration of the rig's cameras: status, `Retry-After` and
/// body.
async fn create_calibration(app: &TestApp, body: &str) -> (u16, Option<String>, Value) {
    let response = app
        .client
        .post(app.api("/calibrations"))
        .header("content-type", "application/json")
        .body(body.to_owned())
        .send()
        .await
        .unwrap();
    let retry_after = response
        .headers()
        .get("retry-after")
        .map(|v| v.to_str().unwrap().to_owned());
    let (status, body) = status_and_json(response).await;
    (status, retry_after, body)
}

/// Creates calibrations until one is refused (the store is full); that
/// answer, after asserting it is a 507 with `Retry-After: 30`.
async fn fill_until_refused(
    app: &TestApp,
    calibration: &str,
    what: &str,
) -> (u16, Option<String>, Value) {
    let mut created = 0;
    let answer = loop {
        let answer = create_calibration(app, calibration).await;
        if answer.0 != 201 {
            break answer;
        }
        created += 1;
        assert!(created < 10_000, "{what} never filled");
    };
    assert_eq!(answer.0, 507, "{}", answer.2);
    assert_eq!(answer.1.as_deref(), Some("30"), "{}", answer.2);
    answer
}

/// Polls the job until `done(view)`; its view.
async fn wait_until(app: &TestApp, job_id: i64, done: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    loop {
        let (status, view) = app.get_json(&format!("/jobs/{job_id}")).await;
        assert_eq!(status, 200, "{view}");
        if done(&view) {
            return view;
        }
        assert!(start.elapsed() < PATIENCE, "job never got there: {view}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Issue 12, defect 2: after one disk-full error every write failed with
/// 500 until a restart (the writer connection was left inside a
/// transaction), and a frame accepted just before failed for good. Now:
/// 507 with Retry-After while full; once space is back, creates and
/// uploads succeed without a restart, and the frame accepted before is
/// processed, its storage-full attempts not counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_is_a_507_and_the_service_recovers_without_a_restart() {
    if crate::postgres::enabled() {
        // The fault injection is SQLite's page limit; PostgreSQL has none
        // (its disk full, SQLSTATE 53100, maps to the same 507: a unit test
        // of the store's error kinds).
        return;
    }
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let files: Vec<Vec<u8>> = rig.render(300, 12).images.iter().map(png).collect();
    let (status, accepted) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 202, "{accepted}");
    let job_id = accepted["job_id"].as_i64().unwrap();

    // The disk fills up while the frame is being processed (its first
    // frame prepares the sequence's pipeline: far longer than this).
    let store = &app.state.store;
    store.set_max_page_count(Some(0)).await.unwrap();
    let calibration = ptv::formats::calibration::to_json(&rig.cameras);
    fill_until_refused(&app, &calibration, "the page limit").await;
    // Every write keeps failing as full (not as a connection stuck in a
    // transaction), uploads too; reads and liveness go on.
    for _ in 0..3 {
        let (status, retry_after, body) = create_calibration(&app, &calibration).await;
        assert_eq!(
            (status, retry_after.as_deref()),
            (507, Some("30")),
            "{body}"
        );
    }
    let targets = rig.targets(200, 3);
    let (status, body) = app.upload(sequence, targets_form(1, &targets)).await;
    assert_eq!(status, 507, "{body}");
    let (status, body) = app.get_json(&format!("/sequences/{sequence}")).await;
    assert_eq!(status, 200, "{body}");
    app.get_text(format!("{}/healthz", app.address)).await;
    assert_eq!(
        app.get_text(format!("{}/readyz", app.address)).await,
        "ready\n"
    );

    // The frame's attempt found the disk full: it is queued again, not
    // failed, its images kept although the sequence keeps none.
    let view = wait_until(&app, job_id, |view| {
        view["error"]
            .as_str()
            .is_some_and(|e| e.contains("disk is full"))
    })
    .await;
    assert_ne!(view["state"], "failed", "{view}");
    assert_ne!(view["state"], "succeeded", "{view}");
    let db = app.database().await;
    assert_eq!(
        count(&db, "SELECT count(*) FROM images WHERE frame = 0").await,
        4
    );

    // Space comes back: no restart.
    store.set_max_page_count(None).await.unwrap();
    for _ in 0..3 {
        let (status, _, body) = create_calibration(&app, &calibration).await;
        assert_eq!(status, 201, "{body}");
    }
    let (status, body) = app.upload(sequence, targets_form(1, &targets)).await;
    assert_eq!(status, 202, "{body}");
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], 2, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");
    let job = app.wait_for_job(job_id).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(
        job["attempts"], 1,
        "storage-full attempts are not counted: {job}"
    );
    let (status, particles) = app
        .get_json(&format!("/sequences/{sequence}/frames/0/particles"))
        .await;
    assert_eq!(status, 200, "{particles}");
    app.stop().await;
}

/// Issue 12, defect 7: a frame whose job the service died running 3 times
/// was failed for good: its re-upload is a 409 and nothing retried it.
/// Now `POST /jobs/{id}/retry` queues it again and it is processed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_frame_is_processed_after_a_retry() {
    let app = spawn_app().await;
    let (rig, sequence) = app.rig_sequence().await;
    let targets = rig.targets(300, 7);
    let (status, accepted) = app.upload(sequence, targets_form(0, &targets)).await;
    assert_eq!(status, 202, "{accepted}");
    let job_id = accepted["job_id"].as_i64().unwrap();
    app.wait_for_sequence(sequence).await;
    let data_dir = app.stop_keeping_data().await;

    // What three kill -9 while its job runs leave: the frame's inputs, no
    // result, the job running under a dead process, claimed 3 times.
    {
        let db = open_database_writable(data_dir.path()).await;
        sqlx::query("DELETE FROM particles WHERE sequence_id = $1 AND frame = 0")
            .bind(sequence)
            .execute(&db)
            .await
            .unwrap();
        sqlx::query(
            "UPDATE jobs SET state = 'running', attempts = 3, locked_by = 'killed/0', \
             error = NULL, finished_at = NULL WHERE id = $1",
        )
        .bind(job_id)
        .execute(&db)
        .await
        .unwrap();
        db.close().await;
    }

    // The reaper fails it at the next start.
    let app = spawn_app_in(data_dir).await;
    let (_, job) = app.get_json(&format!("/jobs/{job_id}")).await;
    assert_eq!(job["state"], "failed", "{job}");
    let reason = job["error"].as_str().unwrap().to_owned();
    assert!(reason.contains("3 times"), "{job}");
    let (status, body) = app.upload(sequence, targets_form(0, &targets)).await;
    assert_eq!(status, 409, "{body}");

    let retry = |id: i64| {
        let request = app.client.post(app.api(&format!("/jobs/{id}/retry")));
        async move {
            let response = request.send().await.unwrap();
            let location = response
                .headers()
                .get("location")
                .map(|v| v.to_str().unwrap().to_owned());
            let (status, body) = status_and_json(response).await;
            (status, location, body)
        }
    };
    let (status, location, job) = retry(job_id).await;
    assert_eq!(status, 202, "{job}");
    assert_eq!(location, Some(format!("/api/v1/jobs/{job_id}")));
    assert_eq!(job["attempts"], 0, "{job}");
    assert!(
        job["state"] == "queued" || job["state"] == "running",
        "{job}"
    );
    let job = app.wait_for_job(job_id).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    assert_eq!(job["attempts"], 1, "{job}");
    assert_eq!(job["error"], Value::Null, "{job}");
    let (status, particles) = app
        .get_json(&format!("/sequences/{sequence}/frames/0/particles"))
        .await;
    assert_eq!(status, 200, "{particles}");
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], 1, "{view}");
    assert_eq!(view["frames"]["failed"], 0, "{view}");

    // Only a failed job is retried.
    let (status, _, body) = retry(job_id).await;
    assert_eq!(status, 409, "{body}");
    assert!(
        body["detail"].as_str().unwrap().contains("succeeded"),
        "{body}"
    );
    let (status, _, body) = retry(999_999).await;
    assert_eq!(status, 404, "{body}");
    app.stop().await;
}

/// A real full disk: the data directory on a 16 MiB tmpfs, filled by
/// another file. Needs the right to mount (root); skipped otherwise.
///
/// The test fills only a file system it has checked to be its own small
/// one: mounted under the build's scratch directory (not the shared
/// `/tmp` every other test's data directory is in), a different device
/// from its parent and at most [`TMPFS_BYTES`] large. Where a sandbox
/// accepts the mount but not its size, or the mount lands elsewhere, the
/// test is skipped rather than fill the disk the other tests run on; and
/// the filler stops at twice that size whatever the file system says.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_full_disk_is_a_507_and_freeing_space_is_enough() {
    const TMPFS_BYTES: u64 = 16 << 20;
    if crate::postgres::enabled() {
        // The disk filled is the data directory's, where SQLite's file is;
        // PostgreSQL's database is on its server's disk, which this test
        // does not fill.
        return;
    }
    let scratch = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    std::fs::create_dir_all(scratch).unwrap();
    let mount = tempfile::tempdir_in(scratch).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", &format!("size={TMPFS_BYTES}")])
        .arg("tmpfs")
        .arg(mount.path())
        .status()
        .is_ok_and(|status| status.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here");
        return;
    }
    /// Unmounts when the test ends, however it ends.
    struct Unmount(std::path::PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount")
                .arg("-l")
                .arg(&self.0)
                .status();
        }
    }
    let _unmount = Unmount(mount.path().to_owned());
    let own_device = {
        use std::os::unix::fs::MetadataExt;
        let here = std::fs::metadata(mount.path()).unwrap().dev();
        let parent = std::fs::metadata(scratch).unwrap().dev();
        here != parent
    };
    let size = rustix::fs::statvfs(mount.path())
        .map(|fs| fs.f_blocks * fs.f_frsize)
        .unwrap_or(u64::MAX);
    if !own_device || size > TMPFS_BYTES {
        eprintln!(
            "skipped: the tmpfs mounted is not a {TMPFS_BYTES}-byte file system of its own \
             ({size} bytes, own device: {own_device})"
        );
        return;
    }
    let data_dir = mount.path().join("data");
    let app = spawn_app_configured(|args| args.storage.data_dir = data_dir.clone()).await;
    let (rig, sequence) = app.rig_sequence().await;
    let calibration = ptv::formats::calibration::to_json(&rig.cameras);

    // Fill the disk.
    let filler = mount.path().join("filler");
    {
        use std::io::Write;
        let mut file = std::fs::File::create(&filler).unwrap();
        let chunk = vec![0u8; 1 << 16];
        let mut written = 0;
        while written < 2 * TMPFS_BYTES && file.write_all(&chunk).is_ok() {
            written += chunk.len() as u64;
        }
        let _ = file.sync_all();
    }
    fill_until_refused(&app, &calibration, "the disk").await;
    let files: Vec<Vec<u8>> = rig.render(100, 4).images.iter().map(png).collect();
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 507, "{body}");

    // Free the space: no restart.
    std::fs::remove_file(&filler).unwrap();
    for _ in 0..5 {
        let (status, _, body) = create_calibration(&app, &calibration).await;
        assert_eq!(status, 201, "{body}");
    }
    let (status, body) = app.upload(sequence, image_form(0, &files)).await;
    assert_eq!(status, 202, "{body}");
    let view = app.wait_for_sequence(sequence).await;
    assert_eq!(view["frames"]["done"], 1, "{view}");
    app.stop().await;
}

/// PostgreSQL's disk full (SQLSTATE 53100) and a server shutting down
/// (57P01) or not accepting connections (57P03), raised by a real server,
/// are told apart as SQLite's full disk is: storage full (507) and
/// unavailable (503). PostgreSQL only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_errors_map_to_their_kinds() {
    use ptv::service::store::{ErrorKind, StoreError};
    let data_dir = tempfile::tempdir().unwrap();
    if !crate::postgres::enabled() {
        // SQLite's full disk is the page-limit test above.
        return;
    }
    let db = open_database_writable(data_dir.path()).await;
    for (code, kind) in [
        ("53100", ErrorKind::StorageFull),
        ("57P01", ErrorKind::Unavailable),
        ("57P03", ErrorKind::Unavailable),
        ("08006", ErrorKind::Unavailable),
        ("23505", ErrorKind::Other),
    ] {
        let error = sqlx::query(&format!(
            "DO $$ BEGIN RAISE EXCEPTION 'raised' USING ERRCODE = '{code}'; END $$"
        ))
        .execute(&db)
        .await
        .unwrap_err();
        assert_eq!(StoreError::from(error).kind(), kind, "{code}");
    }
    db.close().await;
}
