//! Detection at upload: the image detections workers run as images arrive, the capture
//! check they keep current, and the session's event stream.
//!
//! A detection row is written in the transaction that records its image (see
//! [`Store::insert_image`]), so no uploaded image is ever left without one. Workers
//! claim pending rows with a lease, as they claim jobs: a worker that dies mid-image
//! lets its lease expire and another takes the row. Outcomes are kept with the detector
//! version that produced them; a job reuses only those of its own build's detector for
//! the same bytes.

use super::db::{sql, Rec};
use super::{now_ms, Store};
use serde::Serialize;

/// A detection a worker holds.
#[derive(Clone, Debug)]
pub struct DetectionTask {
    pub id: String,
    pub session_id: String,
    pub camera: String,
    pub frame: i64,
    pub sha256: String,
    pub attempts: i64,
}

/// A finished detection of a session's image.
#[derive(Clone, Debug)]
pub struct StoredDetection {
    pub camera: String,
    pub frame: i64,
    pub sha256: String,
    pub detector: String,
    /// The outcome as JSON (`rigcal_engine::pipeline::detection::ImageDetection`), or
    /// why the detector gave none (`failed`: given up after repeated attempts).
    pub outcome: Result<String, String>,
}

/// How far a session's detection at upload has come.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DetectionCounts {
    /// Rows written (one per uploaded image awaiting detection).
    pub queued: i64,
    /// Of those, detected (`done`).
    pub done: i64,
    /// Of those, given up after repeated failures (the job detects them itself).
    pub failed: i64,
}

/// One event of a session's stream.
#[derive(Clone, Debug, Serialize)]
pub struct SessionEvent {
    pub id: i64,
    pub session_id: String,
    pub at: String,
    /// `image` (one image's detection landed) or `check` (the capture check changed).
    pub kind: String,
    pub data: serde_json::Value,
}

/// Attempts at one image before it is given up (each attempt that ends without an
/// outcome: a panic of the detector or a blob that could not be read).
pub const MAX_DETECTION_ATTEMPTS: i64 = 3;

/// When a detection that gave no outcome may be claimed again: `backoff_ms` after the
/// first attempt, doubling after each next one, as jobs back off (a blob store that
/// failed a read a moment ago is given time to recover, not hit again at once).
fn retry_at(now: i64, attempts: i64, backoff_ms: i64) -> i64 {
    now.saturating_add(backoff_ms.saturating_mul(1 << (attempts - 1).clamp(0, 16)))
}

const CLAIM_SQLITE: &str = "UPDATE image_detections SET lease_owner = $1, lease_expires_at = NOW_MS + $2, attempts = attempts + 1
     WHERE id IN (SELECT id FROM image_detections WHERE status = 'pending'
                  AND (lease_expires_at IS NULL OR lease_expires_at < NOW_MS)
                  ORDER BY created_at LIMIT $3)
     RETURNING id, session_id, camera, frame, sha256, attempts";
// The rows are picked once, in a materialised CTE: as `id IN (SELECT … LIMIT n FOR
// UPDATE SKIP LOCKED)` PostgreSQL evaluated the subquery again for each row the update
// scanned (its clock is volatile), and each evaluation skipped the rows the previous
// had locked, so a claim of one leased every pending row. The outer conditions are
// checked again on the locked rows: a row another worker claimed between the pick and
// the lock is skipped.
const CLAIM_POSTGRES: &str = "WITH picked AS MATERIALIZED (
        SELECT id FROM image_detections WHERE status = 'pending'
          AND (lease_expires_at IS NULL OR lease_expires_at < NOW_MS)
        ORDER BY created_at LIMIT $3 FOR UPDATE SKIP LOCKED)
     UPDATE image_detections d SET lease_owner = $1, lease_expires_at = NOW_MS + $2, attempts = d.attempts + 1
     FROM picked WHERE d.id = picked.id
       AND d.status = 'pending' AND (d.lease_expires_at IS NULL OR d.lease_expires_at < NOW_MS)
     RETURNING d.id, d.session_id, d.camera, d.frame, d.sha256, d.attempts";

fn task_from(r: &Rec) -> sqlx::Result<DetectionTask> {
    Ok(DetectionTask {
        id: r.get("id")?,
        session_id: r.get("session_id")?,
        camera: r.get("camera")?,
        frame: r.get("frame")?,
        sha256: r.get("sha256")?,
        attempts: r.get("attempts")?,
    })
}

impl Store {
    /// Claim up to `limit` pending detections (oldest upload first) for `lease_ms`.
    pub async fn claim_detections(
        &self,
        owner: &str,
        lease_ms: i64,
        limit: i64,
    ) -> sqlx::Result<Vec<DetectionTask>> {
        let rows = self
            .db
            .fetch_all(
                self.db
                    .pick(CLAIM_SQLITE, CLAIM_POSTGRES)
                    .bind(owner)
                    .bind(lease_ms)
                    .bind(limit),
            )
            .await?;
        rows.iter().map(task_from).collect()
    }

    /// Record what a held detection gave: its outcome (JSON, of `detector`), or the
    /// error of an attempt that gave none (retried after a backoff — [`retry_at`], from
    /// `backoff_ms` — until [`MAX_DETECTION_ATTEMPTS`], then `failed`). Then records the
    /// `image` event. `false` when the lease was lost (another worker has the row now;
    /// nothing written).
    pub async fn finish_detection(
        &self,
        task: &DetectionTask,
        owner: &str,
        detector: &str,
        outcome: Result<&str, &str>,
        event: &serde_json::Value,
        backoff_ms: i64,
    ) -> sqlx::Result<bool> {
        let mut tx = self.db.begin().await?;
        let n = match outcome {
            Ok(doc) => tx.execute(sql("UPDATE image_detections SET status = 'done', detector = $1, outcome = $2, error = NULL, finished_at = $3, lease_owner = NULL, lease_expires_at = NULL WHERE id = $4 AND lease_owner = $5")
                .bind(detector)
                .bind(doc)
                .bind(now_ms())
                .bind(&task.id)
                .bind(owner)).await?,
            Err(why) => {
                let failed = task.attempts >= MAX_DETECTION_ATTEMPTS;
                let now = now_ms();
                // A retry waits out its backoff as an expired lease would: the claim
                // takes rows whose `lease_expires_at` has passed.
                tx.execute(sql("UPDATE image_detections SET status = $1, error = $2, finished_at = $3, lease_owner = NULL, lease_expires_at = $6 WHERE id = $4 AND lease_owner = $5")
                    .bind(if failed { "failed" } else { "pending" })
                    .bind(why)
                    .bind(failed.then_some(now))
                    .bind(&task.id)
                    .bind(owner)
                    .bind((!failed).then(|| retry_at(now, task.attempts, backoff_ms)))).await?
            }
        };
        if n != 1 {
            return Ok(false);
        }
        if outcome.is_ok() || task.attempts >= MAX_DETECTION_ATTEMPTS {
            insert_event(&mut tx, &task.session_id, "image", event).await?;
        }
        tx.commit().await?;
        Ok(true)
    }

    /// A session's finished detections (`done` and `failed`), by (camera, frame).
    pub async fn detections(&self, session_id: &str) -> sqlx::Result<Vec<StoredDetection>> {
        let rows = self.db.fetch_all(sql("SELECT camera, frame, sha256, status, detector, outcome, error FROM image_detections WHERE session_id = $1 AND status IN ('done', 'failed') ORDER BY frame, camera")
            .bind(session_id))
            .await?;
        rows.iter()
            .map(|r| {
                let status: String = r.get("status")?;
                let detector: Option<String> = r.get("detector")?;
                let outcome: Option<String> = r.get("outcome")?;
                let error: Option<String> = r.get("error")?;
                Ok(StoredDetection {
                    camera: r.get("camera")?,
                    frame: r.get("frame")?,
                    sha256: r.get("sha256")?,
                    detector: detector.unwrap_or_default(),
                    outcome: match (status.as_str(), outcome) {
                        ("done", Some(doc)) => Ok(doc),
                        _ => Err(error.unwrap_or_else(|| "the detector gave no outcome".into())),
                    },
                })
            })
            .collect()
    }

    pub async fn detection_counts(&self, session_id: &str) -> sqlx::Result<DetectionCounts> {
        let r = self.db.fetch_one(sql("SELECT COUNT(*) AS queued, COALESCE(SUM(CASE WHEN status = 'done' THEN 1 ELSE 0 END), 0) AS done, COALESCE(SUM(CASE WHEN status = 'failed' THEN 1 ELSE 0 END), 0) AS failed FROM image_detections WHERE session_id = $1")
            .bind(session_id))
            .await?;
        Ok(DetectionCounts {
            queued: r.get("queued")?,
            done: r.get("done")?,
            failed: r.get("failed")?,
        })
    }

    /// Store a capture check covering `detected` of the `expected` images awaiting
    /// detection, unless one covering more is already stored (two workers finishing
    /// images of one session race; the newer check never loses to the older). Records
    /// the `check` event with it. `false` when an equal or fuller check was there.
    pub async fn store_check(
        &self,
        session_id: &str,
        check: &str,
        detected: i64,
        expected: i64,
        event: &serde_json::Value,
    ) -> sqlx::Result<bool> {
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE sessions SET capture_check = $1, check_detected = $2, check_expected = $3 WHERE id = $4 AND (check_detected IS NULL AND capture_check IS NULL OR check_detected < $2)")
            .bind(check)
            .bind(detected)
            .bind(expected)
            .bind(session_id))
            .await?;
        if n == 1 {
            insert_event(&mut tx, session_id, "check", event).await?;
        }
        tx.commit().await?;
        Ok(n == 1)
    }

    /// A session's events after `after`, oldest first (at most 500).
    pub async fn session_events_after(
        &self,
        session_id: &str,
        after: i64,
    ) -> sqlx::Result<Vec<SessionEvent>> {
        let rows = self.db.fetch_all(sql("SELECT id, session_id, at, kind, data FROM session_events WHERE session_id = $1 AND id > $2 ORDER BY id LIMIT 500")
            .bind(session_id)
            .bind(after))
            .await?;
        rows.iter()
            .map(|r| {
                let data: String = r.get("data")?;
                Ok(SessionEvent {
                    id: r.get("id")?,
                    session_id: r.get("session_id")?,
                    at: super::rfc3339(r.get("at")?),
                    kind: r.get("kind")?,
                    data: serde_json::from_str(&data)
                        .map_err(|e| sqlx::Error::Decode(Box::new(e)))?,
                })
            })
            .collect()
    }

    /// The newest session event id (0 when there is none).
    pub async fn last_session_event_id(&self) -> sqlx::Result<i64> {
        self.db
            .fetch_one(sql("SELECT COALESCE(MAX(id), 0) FROM session_events"))
            .await?
            .get(0)
    }
}

/// Record a session event in `tx`, last in its transaction (on PostgreSQL it takes the
/// event order lock until commit, so streams that read "after id N" never skip one).
async fn insert_event(
    tx: &mut super::db::Tx,
    session_id: &str,
    kind: &str,
    data: &serde_json::Value,
) -> sqlx::Result<()> {
    tx.order_events().await?;
    tx.execute(
        sql("INSERT INTO session_events (session_id, at, kind, data) VALUES ($1, $2, $3, $4)")
            .bind(session_id)
            .bind(now_ms())
            .bind(kind)
            .bind(data.to_string()),
    )
    .await?;
    Ok(())
}
