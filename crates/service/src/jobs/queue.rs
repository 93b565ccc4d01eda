//! The job queue: a `jobs` table claimed atomically with a lease.
//!
//! A claim is one `UPDATE … WHERE id = (SELECT …) RETURNING *` statement, so two workers
//! (threads or processes, on one machine or many) never hold the same job: SQLite has
//! one writer at a time, and on PostgreSQL the inner select takes the row `FOR UPDATE
//! SKIP LOCKED`, so concurrent claims pass each other instead of queueing on one row.
//! Leases and due times are read from the database's clock (`NOW_MS`), never a
//! worker's, so machines whose clocks disagree still agree on who holds a job. A worker
//! that dies stops renewing its lease; once it expires the job is claimable again. Every
//! transition out of `running` requires the caller to still own the lease, so a job
//! completes exactly once even if a presumed-dead worker wakes up later.
//!
//! On PostgreSQL a new job is announced with `NOTIFY` ([`JOBS_CHANNEL`]) so idle workers
//! wake at once; they poll as well, because a notification sent while a listener
//! reconnects is lost.

use super::acceptance::ResultSummary;
use crate::store::db::{sql, Backend, Db, Rec, Tx};
use crate::store::{now_ms, rfc3339};
use rigcal_core::result::Status;
use serde::Serialize;

/// Where a job is; stored (and shown) as its snake_case name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    Degraded,
    Failed,
    Cancelled,
}

impl JobStatus {
    pub const ALL: [JobStatus; 6] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Degraded,
        JobStatus::Failed,
        JobStatus::Cancelled,
    ];

    pub const fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Degraded => "degraded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<JobStatus> {
        Self::ALL.into_iter().find(|x| x.as_str() == s)
    }

    pub const fn is_terminal(self) -> bool {
        !matches!(self, JobStatus::Queued | JobStatus::Running)
    }
}

impl From<Status> for JobStatus {
    /// A finished calibration's status as the job's.
    fn from(s: Status) -> JobStatus {
        match s {
            Status::Succeeded => JobStatus::Succeeded,
            Status::Degraded => JobStatus::Degraded,
            Status::Failed => JobStatus::Failed,
        }
    }
}

impl From<JobStatus> for crate::store::db::Arg {
    fn from(s: JobStatus) -> Self {
        s.as_str().into()
    }
}

impl std::fmt::Display for JobStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What [`Queue::fail`] did with the job.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailOutcome {
    /// Queued again for another attempt.
    Retried,
    /// Failed for good.
    Failed,
    /// This worker no longer held the job; nothing was written.
    Lost,
}

#[derive(Clone, Debug)]
pub struct JobRow {
    pub id: String,
    pub tenant_id: String,
    pub session_id: String,
    pub vehicle_id: Option<String>,
    /// The session's vehicle model, judged against when the job is read.
    pub vehicle_model: Option<String>,
    pub method: String,
    pub options: String,
    pub status: JobStatus,
    pub stage: Option<String>,
    pub progress: f64,
    pub attempts: i64,
    pub max_attempts: i64,
    pub error: Option<String>,
    pub lease_owner: Option<String>,
    pub residual_rms_px: Option<f64>,
    pub worst_sigma_translation_m: Option<f64>,
    pub worst_sigma_rotation_deg: Option<f64>,
    /// JSON array of the result's extrinsic values (finished jobs with a result).
    pub extrinsics: Option<String>,
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
}

impl JobRow {
    pub fn is_terminal(&self) -> bool {
        self.status.is_terminal()
    }
}

/// The channel a new job is announced on (PostgreSQL).
pub const JOBS_CHANNEL: &str = "rigcal_jobs";

fn job_from(r: &Rec) -> sqlx::Result<JobRow> {
    let status: String = r.get("status")?;
    Ok(JobRow {
        id: r.get("id")?,
        tenant_id: r.get("tenant_id")?,
        session_id: r.get("session_id")?,
        vehicle_id: r.get("vehicle_id")?,
        vehicle_model: r.get("vehicle_model")?,
        method: r.get("method")?,
        options: r.get("options")?,
        status: JobStatus::parse(&status).ok_or_else(|| sqlx::Error::ColumnDecode {
            index: "status".into(),
            source: format!("{status:?} is not a job status").into(),
        })?,
        stage: r.get("stage")?,
        progress: r.get("progress")?,
        attempts: r.get("attempts")?,
        max_attempts: r.get("max_attempts")?,
        error: r.get("error")?,
        lease_owner: r.get("lease_owner")?,
        residual_rms_px: r.get("residual_rms_px")?,
        worst_sigma_translation_m: r.get("worst_sigma_translation_m")?,
        worst_sigma_rotation_deg: r.get("worst_sigma_rotation_deg")?,
        extrinsics: r.get("extrinsics")?,
        created_at: r.get("created_at")?,
        started_at: r.get("started_at")?,
        finished_at: r.get("finished_at")?,
    })
}

fn event_from(r: &Rec, with_job: bool) -> sqlx::Result<EventRow> {
    Ok(EventRow {
        id: r.get("id")?,
        job_id: if with_job {
            Some(r.get("job_id")?)
        } else {
            None
        },
        at: rfc3339(r.get("at")?),
        kind: r.get("kind")?,
        status: r.get("status")?,
        stage: r.get("stage")?,
        progress: r.get("progress")?,
        message: r.get("message")?,
    })
}

#[derive(Clone, Debug, Serialize)]
pub struct EventRow {
    pub id: i64,
    /// Set in the tenant-wide stream, where events of many jobs mix.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub job_id: Option<String>,
    pub at: String,
    pub kind: String,
    pub status: String,
    pub stage: Option<String>,
    pub progress: f64,
    pub message: Option<String>,
}

#[derive(Clone, Debug, Default)]
pub struct JobFilter {
    pub status: Option<JobStatus>,
    pub vehicle_id: Option<String>,
    pub method: Option<String>,
    pub created_after: Option<i64>,
    pub created_before: Option<i64>,
    pub limit: i64,
    pub offset: i64,
}

#[derive(Clone)]
pub struct Queue {
    db: Db,
}

/// Record a job event in `tx` (always last in its transaction: on PostgreSQL it holds
/// the event order lock until commit, see [`Tx::order_events`]).
async fn event(
    tx: &mut Tx,
    job: &str,
    kind: &str,
    status: &str,
    stage: Option<&str>,
    progress: f64,
    message: Option<&str>,
) -> sqlx::Result<()> {
    if kind == "status" && JobStatus::parse(status).is_some_and(JobStatus::is_terminal) {
        // The webhook outbox, in the transaction that ends the job.
        crate::store::webhooks::enqueue(tx, job, status).await?;
    }
    tx.order_events().await?;
    tx.execute(sql("INSERT INTO job_events (job_id, at, kind, status, stage, progress, message) VALUES ($1, $2, $3, $4, $5, $6, $7)")
        .bind(job)
        .bind(now_ms())
        .bind(kind)
        .bind(status)
        .bind(stage)
        .bind(progress)
        .bind(message))
        .await?;
    Ok(())
}

/// Claim statements, the same but for PostgreSQL's `FOR UPDATE SKIP LOCKED`: a job
/// whose lease expired (its worker died) first, else the oldest due queued job; each
/// the first entry of its partial index (migration 0004), so a claim costs the same
/// with ten jobs queued or ten thousand.
const CLAIM_SQLITE: &str =
    "UPDATE jobs SET status = 'running', lease_owner = $1, lease_expires_at = NOW_MS + $2,
        attempts = attempts + 1, started_at = COALESCE(started_at, NOW_MS)
     WHERE id = COALESCE(
        (SELECT id FROM jobs WHERE status = 'running' AND lease_expires_at < NOW_MS
         ORDER BY lease_expires_at LIMIT 1),
        (SELECT id FROM jobs WHERE status = 'queued' AND run_after <= NOW_MS
         ORDER BY run_after, created_at LIMIT 1))
     RETURNING *";
const CLAIM_POSTGRES: &str =
    "UPDATE jobs SET status = 'running', lease_owner = $1, lease_expires_at = NOW_MS + $2,
        attempts = attempts + 1, started_at = COALESCE(started_at, NOW_MS)
     WHERE id = COALESCE(
        (SELECT id FROM jobs WHERE status = 'running' AND lease_expires_at < NOW_MS
         ORDER BY lease_expires_at LIMIT 1 FOR UPDATE SKIP LOCKED),
        (SELECT id FROM jobs WHERE status = 'queued' AND run_after <= NOW_MS
         ORDER BY run_after, created_at LIMIT 1 FOR UPDATE SKIP LOCKED))
     RETURNING *";

impl Queue {
    pub fn new(db: Db) -> Self {
        Self { db }
    }

    pub fn backend(&self) -> Backend {
        self.db.backend()
    }

    #[allow(clippy::too_many_arguments)]
    pub async fn enqueue(
        &self,
        tenant_id: &str,
        session_id: &str,
        vehicle: (Option<&str>, Option<&str>),
        method: &str,
        options: &str,
        max_attempts: i64,
    ) -> sqlx::Result<JobRow> {
        let (vehicle_id, vehicle_model) = vehicle;
        let id = uuid::Uuid::new_v4().to_string();
        let mut tx = self.db.begin().await?;
        let row = tx.fetch_one(sql("INSERT INTO jobs (id, tenant_id, session_id, vehicle_id, vehicle_model, method, options, status, max_attempts, run_after, created_at) VALUES ($1, $2, $3, $4, $5, $6, $7, 'queued', $8, NOW_MS, $9) RETURNING *")
            .bind(&id)
            .bind(tenant_id)
            .bind(session_id)
            .bind(vehicle_id)
            .bind(vehicle_model)
            .bind(method)
            .bind(options)
            .bind(max_attempts)
            .bind(now_ms()))
            .await?;
        let job = job_from(&row)?;
        if self.db.backend() == Backend::Postgres {
            // Delivered at commit, to every listening worker on any machine.
            tx.execute(sql("SELECT pg_notify($1, $2)").bind(JOBS_CHANNEL).bind(&id))
                .await?;
        }
        event(&mut tx, &id, "status", "queued", None, 0.0, None).await?;
        tx.commit().await?;
        // The job as created, not re-read: a worker woken by the notice may have
        // claimed it already, and the answer to the submit is "queued".
        Ok(job)
    }

    pub async fn get(&self, id: &str) -> sqlx::Result<Option<JobRow>> {
        let r = self
            .db
            .fetch_optional(sql("SELECT * FROM jobs WHERE id = $1").bind(id))
            .await?;
        r.as_ref().map(job_from).transpose()
    }

    /// A tenant's job; `None` for another tenant's.
    pub async fn get_for(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<JobRow>> {
        let r = self
            .db
            .fetch_optional(
                sql("SELECT * FROM jobs WHERE id = $1 AND tenant_id = $2")
                    .bind(id)
                    .bind(tenant_id),
            )
            .await?;
        r.as_ref().map(job_from).transpose()
    }

    /// A page of a tenant's jobs, newest first, and the total matching the filter.
    pub async fn list(&self, tenant_id: &str, f: &JobFilter) -> sqlx::Result<(Vec<JobRow>, i64)> {
        // Optional filters as `($n IS NULL OR …)`: one static statement for every filter
        // combination (sqlx refuses SQL assembled at run time, and rightly so).
        const ROWS: &str = "SELECT * FROM jobs WHERE tenant_id = $1 AND ($2 IS NULL OR status = $2) AND ($3 IS NULL OR vehicle_id = $3) AND ($4 IS NULL OR method = $4) AND ($5 IS NULL OR created_at >= $5) AND ($6 IS NULL OR created_at < $6) ORDER BY created_at DESC, id DESC LIMIT $7 OFFSET $8";
        const COUNT: &str = "SELECT COUNT(*) FROM jobs WHERE tenant_id = $1 AND ($2 IS NULL OR status = $2) AND ($3 IS NULL OR vehicle_id = $3) AND ($4 IS NULL OR method = $4) AND ($5 IS NULL OR created_at >= $5) AND ($6 IS NULL OR created_at < $6)";
        let filtered = |text| {
            sql(text)
                .bind(tenant_id)
                .bind(f.status.map(JobStatus::as_str))
                .bind(&f.vehicle_id)
                .bind(&f.method)
                .bind(f.created_after)
                .bind(f.created_before)
        };
        let rows = self
            .db
            .fetch_all(filtered(ROWS).bind(f.limit).bind(f.offset))
            .await?;
        let total: i64 = self.db.fetch_one(filtered(COUNT)).await?.get(0)?;
        let jobs = rows.iter().map(job_from).collect::<sqlx::Result<_>>()?;
        Ok((jobs, total))
    }

    /// Claim the oldest runnable job: queued and due, or running with an expired lease.
    pub async fn claim(&self, worker: &str, lease_ms: i64) -> sqlx::Result<Option<JobRow>> {
        let mut tx = self.db.begin().await?;
        let r = tx
            .fetch_optional(
                self.db
                    .pick(CLAIM_SQLITE, CLAIM_POSTGRES)
                    .bind(worker)
                    .bind(lease_ms),
            )
            .await?;
        let Some(job) = r.as_ref().map(job_from).transpose()? else {
            return Ok(None);
        };
        let msg = format!(
            "attempt {} of {} by {worker}",
            job.attempts, job.max_attempts
        );
        event(
            &mut tx,
            &job.id,
            "status",
            "running",
            None,
            job.progress,
            Some(&msg),
        )
        .await?;
        tx.commit().await?;
        Ok(Some(job))
    }

    /// Renew the lease. `Ok(None)` if the lease was lost; else whether cancel was requested.
    pub async fn heartbeat(
        &self,
        id: &str,
        worker: &str,
        lease_ms: i64,
    ) -> sqlx::Result<Option<bool>> {
        let r = self.db.fetch_optional(sql("UPDATE jobs SET lease_expires_at = NOW_MS + $1 WHERE id = $2 AND lease_owner = $3 AND status = 'running' RETURNING cancel_requested")
            .bind(lease_ms)
            .bind(id)
            .bind(worker))
            .await?;
        r.map(|r| Ok(r.get::<i64>(0)? != 0)).transpose()
    }

    /// Record a stage change. `Ok(None)` if the lease was lost; else whether cancel was requested.
    pub async fn progress(
        &self,
        id: &str,
        worker: &str,
        stage: &str,
        fraction: f64,
    ) -> sqlx::Result<Option<bool>> {
        let mut tx = self.db.begin().await?;
        let r = tx.fetch_optional(sql("UPDATE jobs SET stage = $1, progress = $2 WHERE id = $3 AND lease_owner = $4 AND status = 'running' RETURNING cancel_requested")
            .bind(stage)
            .bind(fraction)
            .bind(id)
            .bind(worker))
            .await?;
        if r.is_some() {
            event(&mut tx, id, "stage", "running", Some(stage), fraction, None).await?;
        }
        tx.commit().await?;
        r.map(|r| Ok(r.get::<i64>(0)? != 0)).transpose()
    }

    /// Finish a job with the engine's verdict and its result document. `false` if this
    /// worker no longer owns the job (nothing is written then).
    pub async fn complete(
        &self,
        id: &str,
        worker: &str,
        status: JobStatus,
        document: &str,
        summary: &ResultSummary,
        error: Option<&str>,
    ) -> sqlx::Result<bool> {
        let now = now_ms();
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE jobs SET status = $1, progress = 1, stage = NULL, lease_owner = NULL, lease_expires_at = NULL, finished_at = $2, residual_rms_px = $3, worst_sigma_translation_m = $4, worst_sigma_rotation_deg = $5, error = $6, extrinsics = $9 WHERE id = $7 AND lease_owner = $8 AND status = 'running'")
            .bind(status)
            .bind(now)
            .bind(summary.residual_rms_px)
            .bind(summary.worst_sigma_translation_m)
            .bind(summary.worst_sigma_rotation_deg)
            .bind(error)
            .bind(id)
            .bind(worker)
            .bind(summary.extrinsics_json()))
            .await?;
        if n != 1 {
            return Ok(false);
        }
        tx.execute(
            sql("INSERT INTO results (job_id, status, document, created_at) VALUES ($1, $2, $3, $4)")
                .bind(id)
                .bind(status)
                .bind(document)
                .bind(now),
        )
        .await?;
        event(&mut tx, id, "status", status.as_str(), None, 1.0, None).await?;
        tx.commit().await?;
        Ok(true)
    }

    /// A failure without a result document: retried with exponential backoff while
    /// attempts remain and the failure is transient, else `failed` with the problem kept.
    pub async fn fail(
        &self,
        id: &str,
        worker: &str,
        problem: &serde_json::Value,
        transient: bool,
        backoff_ms: i64,
    ) -> sqlx::Result<FailOutcome> {
        let mut tx = self.db.begin().await?;
        // A write first (a no-op one) so the transaction holds the write lock before it
        // reads: on SQLite a deferred read-then-write transaction can fail with
        // SQLITE_BUSY; on PostgreSQL it locks the row.
        let r = tx.fetch_optional(sql("UPDATE jobs SET attempts = attempts WHERE id = $1 AND lease_owner = $2 AND status = 'running' RETURNING attempts, max_attempts")
            .bind(id)
            .bind(worker))
            .await?;
        let Some(r) = r else {
            return Ok(FailOutcome::Lost);
        };
        let (attempts, max): (i64, i64) = (r.get(0)?, r.get(1)?);
        let text = problem.to_string();
        let detail = problem["detail"].as_str();
        let status = if transient && attempts < max {
            let delay = backoff_ms.saturating_mul(1 << (attempts - 1).clamp(0, 16));
            tx.execute(sql("UPDATE jobs SET status = 'queued', lease_owner = NULL, lease_expires_at = NULL, run_after = NOW_MS + $1, error = $2 WHERE id = $3")
                .bind(delay)
                .bind(&text)
                .bind(id))
                .await?;
            let msg = format!("retry in {} ms: {}", delay, detail.unwrap_or(""));
            event(&mut tx, id, "retry", "queued", None, 0.0, Some(&msg)).await?;
            FailOutcome::Retried
        } else {
            tx.execute(sql("UPDATE jobs SET status = 'failed', stage = NULL, lease_owner = NULL, lease_expires_at = NULL, finished_at = $1, error = $2 WHERE id = $3")
                .bind(now_ms())
                .bind(&text)
                .bind(id))
                .await?;
            event(&mut tx, id, "status", "failed", None, 1.0, detail).await?;
            FailOutcome::Failed
        };
        tx.commit().await?;
        Ok(status)
    }

    /// Give a running job back without counting the attempt (a worker shutting down):
    /// queued again at once for any other worker. `false` if this worker no longer held it.
    pub async fn release(&self, id: &str, worker: &str, why: &str) -> sqlx::Result<bool> {
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE jobs SET status = 'queued', lease_owner = NULL, lease_expires_at = NULL, run_after = NOW_MS, attempts = attempts - 1, stage = NULL, progress = 0 WHERE id = $1 AND lease_owner = $2 AND status = 'running'")
            .bind(id)
            .bind(worker))
            .await?;
        if n == 1 {
            if self.db.backend() == Backend::Postgres {
                tx.execute(sql("SELECT pg_notify($1, $2)").bind(JOBS_CHANNEL).bind(id))
                    .await?;
            }
            event(&mut tx, id, "status", "queued", None, 0.0, Some(why)).await?;
        }
        tx.commit().await?;
        Ok(n == 1)
    }

    /// Request cancellation. A queued job is cancelled at once; a running one is marked
    /// and its worker stops between stages. Returns the job after the request.
    pub async fn cancel(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<JobRow>> {
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE jobs SET status = 'cancelled', finished_at = $1, lease_owner = NULL, lease_expires_at = NULL WHERE id = $2 AND tenant_id = $3 AND status = 'queued'")
            .bind(now_ms())
            .bind(id)
            .bind(tenant_id))
            .await?;
        if n == 1 {
            let why = Some("cancelled while queued");
            event(&mut tx, id, "status", "cancelled", None, 0.0, why).await?;
        } else {
            tx.execute(sql("UPDATE jobs SET cancel_requested = 1 WHERE id = $1 AND tenant_id = $2 AND status = 'running'")
                .bind(id)
                .bind(tenant_id))
                .await?;
        }
        tx.commit().await?;
        self.get_for(tenant_id, id).await
    }

    /// The worker saw the cancel request and stopped.
    pub async fn mark_cancelled(&self, id: &str, worker: &str, stage: &str) -> sqlx::Result<bool> {
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE jobs SET status = 'cancelled', finished_at = $1, lease_owner = NULL, lease_expires_at = NULL WHERE id = $2 AND lease_owner = $3 AND status = 'running'")
            .bind(now_ms())
            .bind(id)
            .bind(worker))
            .await?;
        if n == 1 {
            let why = format!("cancelled before {stage}");
            event(
                &mut tx,
                id,
                "status",
                "cancelled",
                Some(stage),
                0.0,
                Some(&why),
            )
            .await?;
        }
        tx.commit().await?;
        Ok(n == 1)
    }

    /// The newest event id (0 when there is none): where a new tenant stream starts.
    pub async fn last_event_id(&self) -> sqlx::Result<i64> {
        self.db
            .fetch_one(sql("SELECT COALESCE(MAX(id), 0) FROM job_events"))
            .await?
            .get(0)
    }

    /// Events of any of a tenant's jobs after `after`, oldest first, at most `limit`.
    pub async fn tenant_events_after(
        &self,
        tenant_id: &str,
        after: i64,
        limit: i64,
    ) -> sqlx::Result<Vec<EventRow>> {
        let rows = self.db.fetch_all(sql("SELECT e.* FROM job_events e JOIN jobs j ON j.id = e.job_id WHERE e.id > $1 AND j.tenant_id = $2 ORDER BY e.id LIMIT $3")
            .bind(after)
            .bind(tenant_id)
            .bind(limit))
            .await?;
        rows.iter().map(|r| event_from(r, true)).collect()
    }

    pub async fn events_after(&self, id: &str, after: i64) -> sqlx::Result<Vec<EventRow>> {
        let rows = self
            .db
            .fetch_all(
                sql("SELECT * FROM job_events WHERE job_id = $1 AND id > $2 ORDER BY id LIMIT 500")
                    .bind(id)
                    .bind(after),
            )
            .await?;
        rows.iter().map(|r| event_from(r, false)).collect()
    }

    pub async fn result(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<String>> {
        let r = self.db.fetch_optional(sql("SELECT r.document FROM results r JOIN jobs j ON j.id = r.job_id WHERE r.job_id = $1 AND j.tenant_id = $2")
            .bind(id)
            .bind(tenant_id))
            .await?;
        r.map(|r| r.get(0)).transpose()
    }

    /// Jobs per status (all tenants), every status in [`JobStatus::ALL`] order, zeros
    /// included, for metrics.
    pub async fn counts(&self) -> sqlx::Result<Vec<(String, i64)>> {
        let rows = self
            .db
            .fetch_all(sql("SELECT status, COUNT(*) FROM jobs GROUP BY status"))
            .await?;
        let found = rows
            .iter()
            .map(|r| Ok((r.get::<String>(0)?, r.get::<i64>(1)?)))
            .collect::<sqlx::Result<Vec<_>>>()?;
        Ok(JobStatus::ALL
            .iter()
            .map(|s| {
                let n = found
                    .iter()
                    .find(|(x, _)| x == s.as_str())
                    .map_or(0, |(_, n)| *n);
                (s.as_str().to_string(), n)
            })
            .collect())
    }

    /// A vehicle's finished jobs with results, oldest first.
    pub async fn vehicle_results(
        &self,
        tenant_id: &str,
        vehicle: &str,
    ) -> sqlx::Result<Vec<(JobRow, String)>> {
        let rows = self.db.fetch_all(sql("SELECT j.*, r.document FROM jobs j JOIN results r ON r.job_id = j.id WHERE j.tenant_id = $1 AND j.vehicle_id = $2 ORDER BY j.finished_at, j.created_at")
            .bind(tenant_id)
            .bind(vehicle))
            .await?;
        rows.iter()
            .map(|r| Ok((job_from(r)?, r.get("document")?)))
            .collect()
    }
}
