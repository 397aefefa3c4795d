//! The store's lease rules (issue 17), on the engine under test: SQLite,
//! or under `PTV_TEST_DATABASE=postgres` a real PostgreSQL, where the
//! claim, the lease expiry and the fences run as different SQL (`FOR
//! UPDATE SKIP LOCKED`, PostgreSQL's clock) and must keep the same rules:
//! a held job is not claimed until its lease runs out, a renewal keeps it,
//! a fenced-out worker writes nothing, the third expiry fails a job, the
//! token grows at every claim, the reaper ends only this host's dead
//! processes' leases, a tracking run has one holder at a time.

use std::time::Duration;

use ptv::service::model::parameters::SequenceParameters;
use ptv::service::store::{
    ClaimOutcome, CompleteError, FrameNumber, JobResult, JobState, LeaseToken, Store, MAX_ATTEMPTS,
};

use crate::helpers::open_database;

/// A lease that has run out by the time the next statement runs.
const SHORT: Duration = Duration::from_millis(100);
/// A lease that does not run out during a test.
const LONG: Duration = Duration::from_secs(600);

/// Waits until a lease of [`SHORT`] has run out: twice its length, so
/// that the database's clock (millisecond text) is past it.
async fn outlive_short_lease() {
    tokio::time::sleep(SHORT * 2).await;
}

/// A store on a fresh database of the engine under test: SQLite in a
/// temporary directory, or under `PTV_TEST_DATABASE=postgres` a fresh
/// PostgreSQL database.
async fn store() -> (tempfile::TempDir, Store) {
    let dir = tempfile::tempdir().unwrap();
    let store = match crate::postgres::database_url(dir.path()) {
        Some(url) => Store::open_postgres(&url.parse().unwrap(), 2)
            .await
            .unwrap(),
        None => Store::open(dir.path(), 1).await.unwrap(),
    };
    (dir, store)
}

/// A count from the store's database.
async fn count(dir: &tempfile::TempDir, sql: &str) -> i64 {
    let db = open_database(dir.path()).await;
    let n = crate::helpers::count(&db, sql).await;
    db.close().await;
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_held_job_is_not_claimed_until_its_lease_runs_out_and_its_renewal_keeps_it() {
    let (_dir, store) = store().await;
    let id = store.enqueue("echo", "{}").await.unwrap();
    let a = store.claim("host:1:aa/0", LONG).await.unwrap().unwrap();
    assert_eq!((a.id, a.attempts, a.token), (id, 1, LeaseToken(1)));
    // Held: nobody else gets it, and its holder renews it.
    assert!(store.claim("host:2:bb/0", LONG).await.unwrap().is_none());
    assert!(!store.claimable().await.unwrap());
    assert!(store.renew(&a, LONG).await.unwrap());
    assert!(store.claim("host:2:bb/0", LONG).await.unwrap().is_none());
    // A renewal to a short lease that then runs out: the job is free.
    assert!(store.renew(&a, SHORT).await.unwrap());
    outlive_short_lease().await;
    assert!(store.claimable().await.unwrap());
    let b = store.claim("host:2:bb/0", LONG).await.unwrap().unwrap();
    assert_eq!((b.id, b.attempts, b.token), (id, 2, LeaseToken(2)));
    // The first holder's renewal now fails: it is fenced out.
    assert!(!store.renew(&a, LONG).await.unwrap());
    assert!(store.renew(&b, LONG).await.unwrap());
    store.close().await;
}

/// A late worker (its lease ran out, another worker took the job)
/// completes, fails, releases, gives back, defers: each is refused and
/// writes nothing; the job completes once, by its holder, and its
/// claims show the takeover.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fenced_out_worker_changes_nothing() {
    let (dir, store) = store().await;
    let id = store.enqueue("solve_calibration", "{}").await.unwrap();
    let late = store.claim("host:1:aa/0", SHORT).await.unwrap().unwrap();
    outlive_short_lease().await;
    let holder = store.claim("host:2:bb/0", LONG).await.unwrap().unwrap();
    assert_eq!(holder.id, id);

    let lost = |result: Result<_, CompleteError>| {
        assert!(
            matches!(result, Err(CompleteError::LostLease(j)) if j == id),
            "{:?}",
            result.err()
        )
    };
    lost(
        store
            .complete_calibration(&late, "{}", 2, "{}", true, 1.0)
            .await
            .map(|_| ()),
    );
    lost(store.succeed(&late, "/late", 1.0).await);
    lost(store.fail(&late, "late", 1.0).await);
    lost(store.release(&late, Some("late")).await);
    lost(store.give_back(&late, "late").await);
    lost(store.defer(&late, "late", 1.0).await);
    assert_eq!(count(&dir, "SELECT count(*) FROM calibrations").await, 0);
    let row = store.job(id).await.unwrap().unwrap();
    assert_eq!(row.state, JobState::Running);
    assert_eq!(row.attempts, 2);
    assert_eq!(row.result, None);

    let (calibration, _) = store
        .complete_calibration(&holder, "{}", 2, "{}", true, 1.0)
        .await
        .unwrap();
    let row = store.job(id).await.unwrap().unwrap();
    assert_eq!(row.state, JobState::Succeeded);
    assert_eq!(row.result, Some(JobResult::Calibration(calibration)));
    assert_eq!(count(&dir, "SELECT count(*) FROM calibrations").await, 1);
    // And after the holder's success, the late worker still writes
    // nothing.
    lost(
        store
            .complete_calibration(&late, "{}", 2, "{}", true, 1.0)
            .await
            .map(|_| ()),
    );
    assert_eq!(count(&dir, "SELECT count(*) FROM calibrations").await, 1);

    let claims = store.job_claims(id, 100).await.unwrap();
    let seen: Vec<_> = claims
        .iter()
        .map(|c| (c.token, c.worker.as_str(), c.outcome))
        .collect();
    assert_eq!(
        seen,
        [
            (LeaseToken(1), "host:1:aa/0", Some(ClaimOutcome::Expired)),
            (LeaseToken(2), "host:2:bb/0", Some(ClaimOutcome::Succeeded)),
        ]
    );
    store.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_lease_runs_out_at_every_attempt_fails_at_the_attempt_limit() {
    let (_dir, store) = store().await;
    let id = store.enqueue("echo", "{}").await.unwrap();
    for attempt in 1..=MAX_ATTEMPTS {
        let job = store.claim("host:1:aa/0", SHORT).await.unwrap().unwrap();
        assert_eq!((job.id, job.attempts), (id, attempt));
        outlive_short_lease().await;
    }
    assert!(store.claim("host:1:aa/0", LONG).await.unwrap().is_none());
    let row = store.job(id).await.unwrap().unwrap();
    assert_eq!(row.state, JobState::Failed);
    assert!(row.error.as_deref().unwrap().contains("3 times"), "{row:?}");
    let claims = store.job_claims(id, 100).await.unwrap();
    assert_eq!(claims.len() as i64, MAX_ATTEMPTS);
    assert!(claims
        .iter()
        .all(|c| c.outcome == Some(ClaimOutcome::Expired)));
    store.close().await;
}

/// The attempts a job gives back uncounted (a full disk, deferred) and
/// its passing failures are claims of their own: the token grows at
/// every claim even where the attempts do not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_grows_at_every_claim_whatever_the_attempts_do() {
    let (_dir, store) = store().await;
    store.enqueue("echo", "{}").await.unwrap();
    let first = store.claim("w/0", LONG).await.unwrap().unwrap();
    store.give_back(&first, "full").await.unwrap();
    let second = store.claim("w/0", LONG).await.unwrap().unwrap();
    assert_eq!((second.attempts, second.token), (1, LeaseToken(2)));
    store.release(&second, Some("passing")).await.unwrap();
    let third = store.claim("w/0", LONG).await.unwrap().unwrap();
    assert_eq!((third.attempts, third.token), (2, LeaseToken(3)));
    // The earlier claims of the same worker are fenced out too.
    assert!(!store.renew(&first, LONG).await.unwrap());
    assert!(matches!(
        store.succeed(&second, "/x", 0.0).await,
        Err(CompleteError::LostLease(_))
    ));
    store.succeed(&third, "/x", 0.0).await.unwrap();
    store.close().await;
}

/// At start-up the leases of this host's processes that are gone end
/// at once; live ones and other hosts' run on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_reaper_ends_the_leases_of_dead_processes_of_this_host_only() {
    let (_dir, store) = store().await;
    for _ in 0..3 {
        store.enqueue("echo", "{}").await.unwrap();
    }
    let dead = store.claim("here:100:aa/0", LONG).await.unwrap().unwrap();
    let alive = store.claim("here:200:bb/1", LONG).await.unwrap().unwrap();
    let elsewhere = store.claim("there:100:cc/0", LONG).await.unwrap().unwrap();
    let (requeued, failed) = store.reap("here", |pid| pid == 200).await.unwrap();
    assert_eq!((requeued, failed), (1, 0));
    let again = store.claim("here:300:dd/0", LONG).await.unwrap().unwrap();
    assert_eq!((again.id, again.token), (dead.id, LeaseToken(2)));
    assert!(store.renew(&alive, LONG).await.unwrap());
    assert!(store.renew(&elsewhere, LONG).await.unwrap());
    assert!(!store.renew(&dead, LONG).await.unwrap());
    store.close().await;
}

/// One tracker per run: the lease is taken, renewed by its owner and
/// refused to others until it runs out or is given up; a change of
/// owner increments the token, and the earlier owner's frame is fenced
/// out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tracking_run_is_held_by_one_owner_and_fenced_on_its_token() {
    let (_dir, store) = store().await;
    let calibration = store.insert_calibration("{}", 2, None).await.unwrap();
    let parameters = SequenceParameters::with_defaults(Default::default(), Default::default());
    let sequence = store
        .insert_sequence(calibration.id, "", &parameters, true, None)
        .await
        .unwrap()
        .unwrap();
    let run = store
        .insert_tracking_run(
            sequence.id,
            &serde_json::from_str(r#"{"max_velocity": 1.0}"#).unwrap(),
        )
        .await
        .unwrap()
        .unwrap();
    let first = store
        .take_tracking_lease(run.id, "here:1:aa", SHORT)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        store
            .take_tracking_lease(run.id, "here:1:aa", SHORT)
            .await
            .unwrap(),
        Some(first),
        "a renewal keeps the token"
    );
    assert_eq!(
        store
            .take_tracking_lease(run.id, "here:2:bb", LONG)
            .await
            .unwrap(),
        None
    );
    assert_eq!(
        store.tracking_runs_to_advance("here:2:bb").await.unwrap(),
        []
    );
    outlive_short_lease().await;
    assert_eq!(
        store.tracking_runs_to_advance("here:2:bb").await.unwrap(),
        [run.id]
    );
    let second = store
        .take_tracking_lease(run.id, "here:2:bb", LONG)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(second.0, first.0 + 1);
    // The first owner's frame is fenced out; the holder's is stored.
    assert!(!store
        .store_tracked_frame((run.id, first), None, FrameNumber(0), Some(0), &[])
        .await
        .unwrap());
    assert!(store
        .store_tracked_frame((run.id, second), None, FrameNumber(0), Some(0), &[])
        .await
        .unwrap());
    assert!(!store
        .finish_tracking_run((run.id, first), Some(FrameNumber(0)), &[])
        .await
        .unwrap());
    // Given up at a shutdown: another owner takes it at once.
    assert_eq!(store.release_tracking_leases("here:2:bb").await.unwrap(), 1);
    let third = store
        .take_tracking_lease(run.id, "here:3:cc", LONG)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(third.0, second.0 + 1);
    assert!(store
        .finish_tracking_run((run.id, third), Some(FrameNumber(0)), &[])
        .await
        .unwrap());
    store.close().await;
}
