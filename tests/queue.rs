//! Queue semantics on a real database (SQLite, or PostgreSQL in the remote run): atomic
//! claims, leases, exactly-once completion, retry with backoff, attempt limits,
//! cancellation.

mod common;

use rigcal_service::jobs::acceptance::ResultSummary;
use rigcal_service::jobs::queue::{FailOutcome, JobStatus, Queue};
use rigcal_service::store::Store;
use serde_json::json;

async fn setup() -> (tempfile::TempDir, Store, Queue, String, String) {
    let dir = tempfile::tempdir().unwrap();
    let store = common::open_store(dir.path()).await;
    let t = store.ensure_tenant("acme").await.unwrap();
    let s = store
        .insert_session(&t, Some("car"), "motion", "{}", None)
        .await
        .unwrap();
    let q = Queue::new(store.db.clone());
    (dir, store, q, t.id, s.id)
}

#[tokio::test]
async fn two_workers_never_hold_the_same_job() {
    let (_d, _s, q, t, s) = setup().await;
    for _ in 0..20 {
        q.enqueue(&t, &s, (None, None), "motion", "{}", 3)
            .await
            .unwrap();
    }
    let mut tasks = Vec::new();
    for w in 0..4 {
        let q = q.clone();
        tasks.push(tokio::spawn(async move {
            let mut got = Vec::new();
            while let Some(j) = q.claim(&format!("w{w}"), 60_000).await.unwrap() {
                got.push(j.id);
            }
            got
        }));
    }
    let mut all = Vec::new();
    for t in tasks {
        all.extend(t.await.unwrap());
    }
    let n = all.len();
    all.sort();
    all.dedup();
    assert_eq!((n, all.len()), (20, 20));
}

#[tokio::test]
async fn an_expired_lease_is_reclaimed_and_the_old_owner_cannot_complete() {
    let (_d, _s, q, t, s) = setup().await;
    let job = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 3)
        .await
        .unwrap();
    let a = q.claim("a", 1).await.unwrap().unwrap();
    assert_eq!(a.id, job.id);
    tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    let b = q.claim("b", 60_000).await.unwrap().expect("re-claimed");
    assert_eq!((b.id.as_str(), b.attempts), (job.id.as_str(), 2));
    // The presumed-dead owner wakes up: nothing it does is written.
    assert_eq!(q.heartbeat(&job.id, "a", 60_000).await.unwrap(), None);
    assert!(q
        .progress(&job.id, "a", "trajectories", 0.1)
        .await
        .unwrap()
        .is_none());
    assert!(!q
        .complete(
            &job.id,
            "a",
            JobStatus::Succeeded,
            "{}",
            &ResultSummary::default(),
            None
        )
        .await
        .unwrap());
    assert!(q
        .complete(
            &job.id,
            "b",
            JobStatus::Succeeded,
            "{\"x\":1}",
            &ResultSummary {
                residual_rms_px: Some(0.3),
                ..Default::default()
            },
            None,
        )
        .await
        .unwrap());
    assert!(!q
        .complete(
            &job.id,
            "b",
            JobStatus::Succeeded,
            "{}",
            &ResultSummary::default(),
            None
        )
        .await
        .unwrap());
    assert_eq!(
        q.result(&t, &job.id).await.unwrap().as_deref(),
        Some("{\"x\":1}")
    );
}

#[tokio::test]
async fn transient_failures_back_off_then_fail_at_the_limit() {
    let (_d, _s, q, t, s) = setup().await;
    let job = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 2)
        .await
        .unwrap();
    let p = json!({"code": "storage_error", "detail": "disk full"});
    q.claim("w", 60_000).await.unwrap().unwrap();
    assert_eq!(
        q.fail(&job.id, "w", &p, true, 200).await.unwrap(),
        FailOutcome::Retried
    );
    // Not due yet: the backoff holds it.
    assert!(q.claim("w", 60_000).await.unwrap().is_none());
    tokio::time::sleep(std::time::Duration::from_millis(250)).await;
    let again = q.claim("w", 60_000).await.unwrap().unwrap();
    assert_eq!(again.attempts, 2);
    assert_eq!(
        q.fail(&job.id, "w", &p, true, 200).await.unwrap(),
        FailOutcome::Failed
    );
    let j = q.get(&job.id).await.unwrap().unwrap();
    assert_eq!(j.status, JobStatus::Failed);
    assert!(j.error.unwrap().contains("disk full"));
    // Bad input: failed at once, whatever attempts remain.
    let job2 = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 5)
        .await
        .unwrap();
    q.claim("w", 60_000).await.unwrap().unwrap();
    assert_eq!(
        q.fail(&job2.id, "w", &p, false, 200).await.unwrap(),
        FailOutcome::Failed
    );
}

#[tokio::test]
async fn cancel_is_immediate_when_queued_and_flagged_when_running() {
    let (_d, _s, q, t, s) = setup().await;
    let queued = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 3)
        .await
        .unwrap();
    assert_eq!(
        q.cancel(&t, &queued.id).await.unwrap().unwrap().status,
        JobStatus::Cancelled
    );
    let running = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 3)
        .await
        .unwrap();
    q.claim("w", 60_000).await.unwrap().unwrap();
    assert_eq!(
        q.cancel(&t, &running.id).await.unwrap().unwrap().status,
        JobStatus::Running
    );
    assert_eq!(
        q.heartbeat(&running.id, "w", 60_000).await.unwrap(),
        Some(true)
    );
    assert_eq!(
        q.progress(&running.id, "w", "initialisation", 0.4)
            .await
            .unwrap(),
        Some(true)
    );
    assert!(q
        .mark_cancelled(&running.id, "w", "initialisation")
        .await
        .unwrap());
    assert_eq!(
        q.get(&running.id).await.unwrap().unwrap().status,
        JobStatus::Cancelled
    );
    // Another tenant cannot cancel.
    let other = q
        .enqueue(&t, &s, (None, None), "motion", "{}", 3)
        .await
        .unwrap();
    assert!(q.cancel("someone-else", &other.id).await.unwrap().is_none());
    assert_eq!(
        q.get(&other.id).await.unwrap().unwrap().status,
        JobStatus::Queued
    );
}

/// An uploaded image whose detection gives no outcome (its blob could not be read) is
/// not taken again at once: it waits out a backoff that doubles, then is `failed` at
/// the attempt limit, with the `image` event said once, at the end.
#[tokio::test]
async fn detections_without_an_outcome_back_off_then_fail_at_the_limit() {
    use rigcal_service::store::detections::MAX_DETECTION_ATTEMPTS;
    use rigcal_service::store::ImageRow;
    let (_d, store, _q, _t, s) = setup().await;
    let img = ImageRow {
        camera: "front".into(),
        frame: 0,
        sha256: "00".repeat(32),
        bytes: 10,
        format: "png".into(),
        width: 4,
        height: 4,
    };
    store.insert_image(&s, &img, true).await.unwrap();
    let backoff_ms = 150;
    let event = json!({"camera": "front", "frame": 0});
    for attempt in 1..=MAX_DETECTION_ATTEMPTS {
        let task = store
            .claim_detections("w", 60_000, 1)
            .await
            .unwrap()
            .pop()
            .unwrap_or_else(|| panic!("attempt {attempt}: the detection is not claimable"));
        assert_eq!(task.attempts, attempt);
        let recorded = store
            .finish_detection(&task, "w", "v1", Err("blob unreadable"), &event, backoff_ms)
            .await
            .unwrap();
        assert!(recorded);
        if attempt < MAX_DETECTION_ATTEMPTS {
            // Not due yet: the backoff holds it.
            let early = store.claim_detections("w", 60_000, 1).await.unwrap();
            assert!(early.is_empty(), "attempt {attempt}: retried at once");
            let wait = backoff_ms as u64 * (1 << (attempt - 1)) + 50;
            tokio::time::sleep(std::time::Duration::from_millis(wait)).await;
        }
    }
    assert!(store
        .claim_detections("w", 60_000, 1)
        .await
        .unwrap()
        .is_empty());
    let counts = store.detection_counts(&s).await.unwrap();
    assert_eq!((counts.queued, counts.done, counts.failed), (1, 0, 1));
    let events = store.session_events_after(&s, 0).await.unwrap();
    assert_eq!(events.iter().filter(|e| e.kind == "image").count(), 1);
}

/// A claim of one uploaded image's detection leases exactly one, however many are
/// pending: on PostgreSQL the limited `IN (… FOR UPDATE SKIP LOCKED)` subquery was
/// evaluated again for each row the update scanned (its clock is volatile), so a claim
/// of one leased two or three rows, returned them all, and the worker, which ran the
/// one it asked for, left the others to wait out their lease (30 s).
#[tokio::test]
async fn a_claim_of_one_detection_leases_exactly_one() {
    use rigcal_service::store::ImageRow;
    let (_d, store, _q, _t, s) = setup().await;
    let images = 6;
    for frame in 0..images {
        let img = ImageRow {
            camera: "front".into(),
            frame,
            sha256: format!("{frame:064x}"),
            bytes: 10,
            format: "png".into(),
            width: 4,
            height: 4,
        };
        store.insert_image(&s, &img, true).await.unwrap();
    }
    let mut frames = Vec::new();
    for k in 0..images {
        let got = store
            .claim_detections(&format!("w{k}"), 60_000, 1)
            .await
            .unwrap();
        let leased: Vec<i64> = got.iter().map(|t| t.frame).collect();
        assert_eq!(leased.len(), 1, "claim {k} leased frames {leased:?}");
        frames.push(got[0].frame);
    }
    frames.sort();
    assert_eq!(
        frames,
        (0..images).collect::<Vec<_>>(),
        "oldest first, each once"
    );
    assert!(store
        .claim_detections("late", 60_000, 1)
        .await
        .unwrap()
        .is_empty());
}
