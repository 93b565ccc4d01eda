//! The job queue: a `jobs` table claimed atomically with a lease.
//!
//! A claim is one `UPDATE … WHERE id = (SELECT …) RETURNING *` statement, so two workers
//! (threads or processes on the same database) never hold the same job. A worker that
//! dies stops renewing its lease; once it expires the job is claimable again. Every
//! transition out of `running` requires the caller to still own the lease, so a job
//! completes exactly once even if a presumed-dead worker wakes up later.

use super::acceptance::ResultSummary;
use crate::store::{now_ms, rfc3339};
use rigcal_core::result::Status;
use serde::Serialize;
use sqlx::sqlite::{SqlitePool, SqliteRow};
use sqlx::Row;

/// Where a job is; stored (and shown) as its snake_case name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, sqlx::Type)]
#[serde(rename_all = "snake_case")]
#[sqlx(rename_all = "snake_case")]
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
    pub created_at: i64,
    pub started_at: Option<i64>,
    pub finished_at: Option<i64>,
}

impl JobRow {
    pub fn is_terminal(&self) -> bool {
        self.status.is_terminal()
    }
}

fn job_from(r: &SqliteRow) -> JobRow {
    JobRow {
        id: r.get("id"),
        tenant_id: r.get("tenant_id"),
        session_id: r.get("session_id"),
        vehicle_id: r.get("vehicle_id"),
        method: r.get("method"),
        options: r.get("options"),
        status: r.get("status"),
        stage: r.get("stage"),
        progress: r.get("progress"),
        attempts: r.get("attempts"),
        max_attempts: r.get("max_attempts"),
        error: r.get("error"),
        lease_owner: r.get("lease_owner"),
        residual_rms_px: r.get("residual_rms_px"),
        worst_sigma_translation_m: r.get("worst_sigma_translation_m"),
        worst_sigma_rotation_deg: r.get("worst_sigma_rotation_deg"),
        created_at: r.get("created_at"),
        started_at: r.get("started_at"),
        finished_at: r.get("finished_at"),
    }
}

fn event_from(r: &SqliteRow, with_job: bool) -> EventRow {
    EventRow {
        id: r.get("id"),
        job_id: with_job.then(|| r.get("job_id")),
        at: rfc3339(r.get("at")),
        kind: r.get("kind"),
        status: r.get("status"),
        stage: r.get("stage"),
        progress: r.get("progress"),
        message: r.get("message"),
    }
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
    pool: SqlitePool,
}

async fn event(
    ex: impl sqlx::SqliteExecutor<'_>,
    job: &str,
    kind: &str,
    status: &str,
    stage: Option<&str>,
    progress: f64,
    message: Option<&str>,
) -> sqlx::Result<()> {
    sqlx::query("INSERT INTO job_events (job_id, at, kind, status, stage, progress, message) VALUES (?, ?, ?, ?, ?, ?, ?)")
        .bind(job)
        .bind(now_ms())
        .bind(kind)
        .bind(status)
        .bind(stage)
        .bind(progress)
        .bind(message)
        .execute(ex)
        .await?;
    Ok(())
}

impl Queue {
    pub fn new(pool: SqlitePool) -> Self {
        Self { pool }
    }

    #[allow(clippy::too_many_arguments)]
    pub async fn enqueue(
        &self,
        tenant_id: &str,
        session_id: &str,
        vehicle_id: Option<&str>,
        method: &str,
        options: &str,
        max_attempts: i64,
    ) -> sqlx::Result<JobRow> {
        let id = uuid::Uuid::new_v4().to_string();
        let now = now_ms();
        let mut tx = self.pool.begin().await?;
        sqlx::query("INSERT INTO jobs (id, tenant_id, session_id, vehicle_id, method, options, status, max_attempts, run_after, created_at) VALUES (?, ?, ?, ?, ?, ?, 'queued', ?, ?, ?)")
            .bind(&id)
            .bind(tenant_id)
            .bind(session_id)
            .bind(vehicle_id)
            .bind(method)
            .bind(options)
            .bind(max_attempts)
            .bind(now)
            .bind(now)
            .execute(&mut *tx)
            .await?;
        event(&mut *tx, &id, "status", "queued", None, 0.0, None).await?;
        tx.commit().await?;
        self.get(&id).await?.ok_or(sqlx::Error::RowNotFound)
    }

    pub async fn get(&self, id: &str) -> sqlx::Result<Option<JobRow>> {
        let r = sqlx::query("SELECT * FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(r.as_ref().map(job_from))
    }

    /// A tenant's job; `None` for another tenant's.
    pub async fn get_for(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<JobRow>> {
        let r = sqlx::query("SELECT * FROM jobs WHERE id = ? AND tenant_id = ?")
            .bind(id)
            .bind(tenant_id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(r.as_ref().map(job_from))
    }

    /// A page of a tenant's jobs, newest first, and the total matching the filter.
    pub async fn list(&self, tenant_id: &str, f: &JobFilter) -> sqlx::Result<(Vec<JobRow>, i64)> {
        // Optional filters as `(?n IS NULL OR …)`: one static statement for every filter
        // combination (sqlx refuses SQL assembled at run time, and rightly so).
        const ROWS: &str = "SELECT * FROM jobs WHERE tenant_id = ?1 AND (?2 IS NULL OR status = ?2) AND (?3 IS NULL OR vehicle_id = ?3) AND (?4 IS NULL OR method = ?4) AND (?5 IS NULL OR created_at >= ?5) AND (?6 IS NULL OR created_at < ?6) ORDER BY created_at DESC, id DESC LIMIT ?7 OFFSET ?8";
        const COUNT: &str = "SELECT COUNT(*) FROM jobs WHERE tenant_id = ?1 AND (?2 IS NULL OR status = ?2) AND (?3 IS NULL OR vehicle_id = ?3) AND (?4 IS NULL OR method = ?4) AND (?5 IS NULL OR created_at >= ?5) AND (?6 IS NULL OR created_at < ?6)";
        let rows = sqlx::query(ROWS)
            .bind(tenant_id)
            .bind(f.status.map(JobStatus::as_str))
            .bind(&f.vehicle_id)
            .bind(&f.method)
            .bind(f.created_after)
            .bind(f.created_before)
            .bind(f.limit)
            .bind(f.offset)
            .fetch_all(&self.pool)
            .await?;
        let total: i64 = sqlx::query(COUNT)
            .bind(tenant_id)
            .bind(f.status.map(JobStatus::as_str))
            .bind(&f.vehicle_id)
            .bind(&f.method)
            .bind(f.created_after)
            .bind(f.created_before)
            .fetch_one(&self.pool)
            .await?
            .get(0);
        Ok((rows.iter().map(job_from).collect(), total))
    }

    /// Claim the oldest runnable job: queued and due, or running with an expired lease.
    pub async fn claim(&self, worker: &str, lease_ms: i64) -> sqlx::Result<Option<JobRow>> {
        let now = now_ms();
        let r = sqlx::query(
            "UPDATE jobs SET status = 'running', lease_owner = ?1, lease_expires_at = ?2 + ?3,
                attempts = attempts + 1, started_at = COALESCE(started_at, ?2)
             WHERE id = (SELECT id FROM jobs
                         WHERE (status = 'queued' AND run_after <= ?2)
                            OR (status = 'running' AND lease_expires_at < ?2)
                         ORDER BY run_after, created_at LIMIT 1)
             RETURNING *",
        )
        .bind(worker)
        .bind(now)
        .bind(lease_ms)
        .fetch_optional(&self.pool)
        .await?;
        let Some(job) = r.as_ref().map(job_from) else {
            return Ok(None);
        };
        let msg = format!(
            "attempt {} of {} by {worker}",
            job.attempts, job.max_attempts
        );
        event(
            &self.pool,
            &job.id,
            "status",
            "running",
            None,
            job.progress,
            Some(&msg),
        )
        .await?;
        Ok(Some(job))
    }

    /// Renew the lease. `Ok(None)` if the lease was lost; else whether cancel was requested.
    pub async fn heartbeat(
        &self,
        id: &str,
        worker: &str,
        lease_ms: i64,
    ) -> sqlx::Result<Option<bool>> {
        let r = sqlx::query("UPDATE jobs SET lease_expires_at = ? WHERE id = ? AND lease_owner = ? AND status = 'running' RETURNING cancel_requested")
            .bind(now_ms() + lease_ms)
            .bind(id)
            .bind(worker)
            .fetch_optional(&self.pool)
            .await?;
        Ok(r.map(|r| r.get::<i64, _>(0) != 0))
    }

    /// Record a stage change. `Ok(None)` if the lease was lost; else whether cancel was requested.
    pub async fn progress(
        &self,
        id: &str,
        worker: &str,
        stage: &str,
        fraction: f64,
    ) -> sqlx::Result<Option<bool>> {
        let mut tx = self.pool.begin().await?;
        let r = sqlx::query("UPDATE jobs SET stage = ?, progress = ? WHERE id = ? AND lease_owner = ? AND status = 'running' RETURNING cancel_requested")
            .bind(stage)
            .bind(fraction)
            .bind(id)
            .bind(worker)
            .fetch_optional(&mut *tx)
            .await?;
        if r.is_some() {
            event(
                &mut *tx,
                id,
                "stage",
                "running",
                Some(stage),
                fraction,
                None,
            )
            .await?;
        }
        tx.commit().await?;
        Ok(r.map(|r| r.get::<i64, _>(0) != 0))
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
        let mut tx = self.pool.begin().await?;
        let n = sqlx::query("UPDATE jobs SET status = ?, progress = 1, stage = NULL, lease_owner = NULL, lease_expires_at = NULL, finished_at = ?, residual_rms_px = ?, worst_sigma_translation_m = ?, worst_sigma_rotation_deg = ?, error = ? WHERE id = ? AND lease_owner = ? AND status = 'running'")
            .bind(status)
            .bind(now)
            .bind(summary.residual_rms_px)
            .bind(summary.worst_sigma_translation_m)
            .bind(summary.worst_sigma_rotation_deg)
            .bind(error)
            .bind(id)
            .bind(worker)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if n != 1 {
            return Ok(false);
        }
        sqlx::query(
            "INSERT INTO results (job_id, status, document, created_at) VALUES (?, ?, ?, ?)",
        )
        .bind(id)
        .bind(status)
        .bind(document)
        .bind(now)
        .execute(&mut *tx)
        .await?;
        event(&mut *tx, id, "status", status.as_str(), None, 1.0, None).await?;
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
        let now = now_ms();
        let mut tx = self.pool.begin().await?;
        // A write first (a no-op one) so the transaction holds the write lock before it
        // reads: a deferred read-then-write transaction can fail with SQLITE_BUSY.
        let r = sqlx::query("UPDATE jobs SET attempts = attempts WHERE id = ? AND lease_owner = ? AND status = 'running' RETURNING attempts, max_attempts")
            .bind(id)
            .bind(worker)
            .fetch_optional(&mut *tx)
            .await?;
        let Some(r) = r else {
            return Ok(FailOutcome::Lost);
        };
        let (attempts, max): (i64, i64) = (r.get(0), r.get(1));
        let text = problem.to_string();
        let status = if transient && attempts < max {
            let delay = backoff_ms.saturating_mul(1 << (attempts - 1).clamp(0, 16));
            sqlx::query("UPDATE jobs SET status = 'queued', lease_owner = NULL, lease_expires_at = NULL, run_after = ?, error = ? WHERE id = ?")
                .bind(now + delay)
                .bind(&text)
                .bind(id)
                .execute(&mut *tx)
                .await?;
            event(
                &mut *tx,
                id,
                "retry",
                "queued",
                None,
                0.0,
                Some(&format!(
                    "retry in {} ms: {}",
                    delay,
                    problem["detail"].as_str().unwrap_or("")
                )),
            )
            .await?;
            FailOutcome::Retried
        } else {
            sqlx::query("UPDATE jobs SET status = 'failed', stage = NULL, lease_owner = NULL, lease_expires_at = NULL, finished_at = ?, error = ? WHERE id = ?")
                .bind(now)
                .bind(&text)
                .bind(id)
                .execute(&mut *tx)
                .await?;
            event(
                &mut *tx,
                id,
                "status",
                "failed",
                None,
                1.0,
                problem["detail"].as_str(),
            )
            .await?;
            FailOutcome::Failed
        };
        tx.commit().await?;
        Ok(status)
    }

    /// Request cancellation. A queued job is cancelled at once; a running one is marked
    /// and its worker stops between stages. Returns the job after the request.
    pub async fn cancel(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<JobRow>> {
        let mut tx = self.pool.begin().await?;
        let n = sqlx::query("UPDATE jobs SET status = 'cancelled', finished_at = ?, lease_owner = NULL, lease_expires_at = NULL WHERE id = ? AND tenant_id = ? AND status = 'queued'")
            .bind(now_ms())
            .bind(id)
            .bind(tenant_id)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if n == 1 {
            event(
                &mut *tx,
                id,
                "status",
                "cancelled",
                None,
                0.0,
                Some("cancelled while queued"),
            )
            .await?;
        } else {
            sqlx::query("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND tenant_id = ? AND status = 'running'")
                .bind(id)
                .bind(tenant_id)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        self.get_for(tenant_id, id).await
    }

    /// The worker saw the cancel request and stopped.
    pub async fn mark_cancelled(&self, id: &str, worker: &str, stage: &str) -> sqlx::Result<bool> {
        let mut tx = self.pool.begin().await?;
        let n = sqlx::query("UPDATE jobs SET status = 'cancelled', finished_at = ?, lease_owner = NULL, lease_expires_at = NULL WHERE id = ? AND lease_owner = ? AND status = 'running'")
            .bind(now_ms())
            .bind(id)
            .bind(worker)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if n == 1 {
            event(
                &mut *tx,
                id,
                "status",
                "cancelled",
                Some(stage),
                0.0,
                Some(&format!("cancelled before {stage}")),
            )
            .await?;
        }
        tx.commit().await?;
        Ok(n == 1)
    }

    /// The newest event id (0 when there is none): where a new tenant stream starts.
    pub async fn last_event_id(&self) -> sqlx::Result<i64> {
        Ok(sqlx::query("SELECT COALESCE(MAX(id), 0) FROM job_events")
            .fetch_one(&self.pool)
            .await?
            .get(0))
    }

    /// Events of any of a tenant's jobs after `after`, oldest first, at most `limit`.
    pub async fn tenant_events_after(
        &self,
        tenant_id: &str,
        after: i64,
        limit: i64,
    ) -> sqlx::Result<Vec<EventRow>> {
        let rows = sqlx::query("SELECT e.* FROM job_events e JOIN jobs j ON j.id = e.job_id WHERE e.id > ? AND j.tenant_id = ? ORDER BY e.id LIMIT ?")
            .bind(after)
            .bind(tenant_id)
            .bind(limit)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows.iter().map(|r| event_from(r, true)).collect())
    }

    pub async fn events_after(&self, id: &str, after: i64) -> sqlx::Result<Vec<EventRow>> {
        let rows = sqlx::query(
            "SELECT * FROM job_events WHERE job_id = ? AND id > ? ORDER BY id LIMIT 500",
        )
        .bind(id)
        .bind(after)
        .fetch_all(&self.pool)
        .await?;
        Ok(rows.iter().map(|r| event_from(r, false)).collect())
    }

    pub async fn result(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<String>> {
        let r = sqlx::query("SELECT r.document FROM results r JOIN jobs j ON j.id = r.job_id WHERE r.job_id = ? AND j.tenant_id = ?")
            .bind(id)
            .bind(tenant_id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(r.map(|r| r.get(0)))
    }

    /// Jobs per status (all tenants), every status in [`JobStatus::ALL`] order, zeros
    /// included, for metrics.
    pub async fn counts(&self) -> sqlx::Result<Vec<(String, i64)>> {
        let rows = sqlx::query("SELECT status, COUNT(*) FROM jobs GROUP BY status")
            .fetch_all(&self.pool)
            .await?;
        let found: Vec<(String, i64)> = rows.iter().map(|r| (r.get(0), r.get(1))).collect();
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
        let rows = sqlx::query("SELECT j.*, r.document FROM jobs j JOIN results r ON r.job_id = j.id WHERE j.tenant_id = ? AND j.vehicle_id = ? ORDER BY j.finished_at, j.created_at")
            .bind(tenant_id)
            .bind(vehicle)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows
            .iter()
            .map(|r| (job_from(r), r.get("document")))
            .collect())
    }
}
