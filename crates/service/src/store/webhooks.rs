//! Webhooks, their delivery outbox and the record of every attempt (migration 0006).

use super::db::{sql, Rec, Tx};
use super::{now_ms, Store};

/// A webhook as listed: never its secret.
#[derive(Clone, Debug)]
pub struct WebhookRow {
    pub id: String,
    pub url: String,
    pub events: Vec<String>,
    pub created_at: i64,
}

/// A claimed delivery with what sending it needs.
#[derive(Clone, Debug)]
pub struct DeliveryRow {
    pub id: String,
    pub webhook_id: String,
    pub event: String,
    pub job_id: String,
    pub body: Option<String>,
    pub attempts: i64,
    pub created_at: i64,
    pub url: String,
    pub secret: String,
}

/// A delivery as listed, with its attempts.
#[derive(Clone, Debug, serde::Serialize)]
pub struct DeliveryView {
    pub id: String,
    pub event: String,
    pub job_id: String,
    pub status: String,
    pub attempts: i64,
    pub last_status_code: Option<i64>,
    pub last_error: Option<String>,
    pub created_at: String,
    pub next_attempt_at: Option<String>,
    pub finished_at: Option<String>,
    pub attempt_log: Vec<AttemptView>,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct AttemptView {
    pub attempt: i64,
    pub at: String,
    pub status_code: Option<i64>,
    pub error: Option<String>,
    pub duration_ms: i64,
}

fn webhook_from(r: &Rec) -> sqlx::Result<WebhookRow> {
    let events: String = r.get("events")?;
    Ok(WebhookRow {
        id: r.get("id")?,
        url: r.get("url")?,
        events: events
            .split(',')
            .filter(|e| !e.is_empty())
            .map(str::to_string)
            .collect(),
        created_at: r.get("created_at")?,
    })
}

/// Queue a delivery to every live webhook of the job's tenant subscribed to its end
/// (`job.finished`, or `job.<status>`), in the transaction that ends the job. The
/// delivery's type is `job.<status>` when subscribed to, else `job.finished`.
pub async fn enqueue(tx: &mut Tx, job_id: &str, status: &str) -> sqlx::Result<()> {
    let specific = format!("job.{status}");
    let hooks = tx
        .fetch_all(sql("SELECT w.id, w.tenant_id, w.events FROM webhooks w JOIN jobs j ON j.tenant_id = w.tenant_id WHERE j.id = $1 AND w.deleted_at IS NULL AND (w.events LIKE '%,job.finished,%' OR w.events LIKE $2)")
            .bind(job_id)
            .bind(format!("%,{specific},%")))
        .await?;
    let now = now_ms();
    for h in hooks {
        let events: String = h.get("events")?;
        let event = if events.contains(&format!(",{specific},")) {
            specific.clone()
        } else {
            "job.finished".to_string()
        };
        let hook: String = h.get("id")?;
        let tenant: String = h.get("tenant_id")?;
        tx.execute(sql("INSERT INTO webhook_deliveries (id, webhook_id, tenant_id, event, job_id, status, attempts, next_attempt_at, created_at) VALUES ($1, $2, $3, $4, $5, 'pending', 0, $6, $6)")
            .bind(uuid::Uuid::new_v4().to_string())
            .bind(hook)
            .bind(tenant)
            .bind(event)
            .bind(job_id)
            .bind(now))
            .await?;
    }
    Ok(())
}

impl Store {
    pub async fn create_webhook(
        &self,
        tenant_id: &str,
        url: &str,
        events: &[String],
        secret: &str,
    ) -> sqlx::Result<WebhookRow> {
        let row = WebhookRow {
            id: uuid::Uuid::new_v4().to_string(),
            url: url.to_string(),
            events: events.to_vec(),
            created_at: now_ms(),
        };
        self.db.execute(sql("INSERT INTO webhooks (id, tenant_id, url, events, secret, created_at) VALUES ($1, $2, $3, $4, $5, $6)")
            .bind(&row.id)
            .bind(tenant_id)
            .bind(url)
            .bind(format!(",{},", events.join(",")))
            .bind(secret)
            .bind(row.created_at))
            .await?;
        Ok(row)
    }

    pub async fn webhooks(&self, tenant_id: &str) -> sqlx::Result<Vec<WebhookRow>> {
        let rows = self.db.fetch_all(sql("SELECT * FROM webhooks WHERE tenant_id = $1 AND deleted_at IS NULL ORDER BY created_at, id").bind(tenant_id)).await?;
        rows.iter().map(webhook_from).collect()
    }

    pub async fn webhook(&self, tenant_id: &str, id: &str) -> sqlx::Result<Option<WebhookRow>> {
        let row = self.db.fetch_optional(sql("SELECT * FROM webhooks WHERE tenant_id = $1 AND id = $2 AND deleted_at IS NULL").bind(tenant_id).bind(id)).await?;
        row.as_ref().map(webhook_from).transpose()
    }

    /// Delete a webhook: no new deliveries, and its pending ones end `failed`.
    pub async fn delete_webhook(&self, tenant_id: &str, id: &str) -> sqlx::Result<bool> {
        let mut tx = self.db.begin().await?;
        let n = tx
            .execute(sql("UPDATE webhooks SET deleted_at = $1 WHERE tenant_id = $2 AND id = $3 AND deleted_at IS NULL").bind(now_ms()).bind(tenant_id).bind(id))
            .await?;
        tx.execute(sql("UPDATE webhook_deliveries SET status = 'failed', last_error = 'the webhook was deleted', finished_at = $1, lease_owner = NULL WHERE webhook_id = $2 AND status = 'pending'").bind(now_ms()).bind(id))
            .await?;
        tx.commit().await?;
        Ok(n == 1)
    }

    /// The newest `limit` deliveries of a webhook with their attempts.
    pub async fn deliveries(
        &self,
        webhook_id: &str,
        limit: i64,
    ) -> sqlx::Result<Vec<DeliveryView>> {
        let rows = self.db.fetch_all(sql("SELECT * FROM webhook_deliveries WHERE webhook_id = $1 ORDER BY created_at DESC, id LIMIT $2").bind(webhook_id).bind(limit)).await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in rows {
            let id: String = r.get("id")?;
            let attempts = self
                .db
                .fetch_all(
                    sql("SELECT * FROM webhook_attempts WHERE delivery_id = $1 ORDER BY attempt")
                        .bind(&id),
                )
                .await?;
            let status: String = r.get("status")?;
            out.push(DeliveryView {
                event: r.get("event")?,
                job_id: r.get("job_id")?,
                attempts: r.get("attempts")?,
                last_status_code: r.get("last_status_code")?,
                last_error: r.get("last_error")?,
                created_at: super::rfc3339(r.get("created_at")?),
                next_attempt_at: (status == "pending")
                    .then(|| r.get::<i64>("next_attempt_at").map(super::rfc3339))
                    .transpose()?,
                finished_at: r.get::<Option<i64>>("finished_at")?.map(super::rfc3339),
                status,
                attempt_log: attempts
                    .iter()
                    .map(|a| {
                        Ok(AttemptView {
                            attempt: a.get("attempt")?,
                            at: super::rfc3339(a.get("at")?),
                            status_code: a.get("status_code")?,
                            error: a.get("error")?,
                            duration_ms: a.get("duration_ms")?,
                        })
                    })
                    .collect::<sqlx::Result<_>>()?,
                id,
            });
        }
        Ok(out)
    }

    /// Claim the most overdue pending delivery for `lease_ms`. The lease conditions are
    /// repeated outside the sub-select so that PostgreSQL re-checks them on the row it
    /// locked: of two dispatchers that picked the same row, one updates nothing.
    pub async fn claim_delivery(
        &self,
        owner: &str,
        lease_ms: i64,
    ) -> sqlx::Result<Option<DeliveryRow>> {
        let Some(r) = self.db.fetch_optional(sql("UPDATE webhook_deliveries SET lease_owner = $1, lease_expires_at = NOW_MS + $2 WHERE id = (SELECT id FROM webhook_deliveries WHERE status = 'pending' AND next_attempt_at <= NOW_MS AND (lease_expires_at IS NULL OR lease_expires_at < NOW_MS) ORDER BY next_attempt_at LIMIT 1) AND status = 'pending' AND (lease_expires_at IS NULL OR lease_expires_at < NOW_MS) RETURNING id")
            .bind(owner)
            .bind(lease_ms))
            .await?
        else {
            return Ok(None);
        };
        let id: String = r.get("id")?;
        let row = self.db.fetch_one(sql("SELECT d.id, d.webhook_id, d.event, d.job_id, d.body, d.attempts, d.created_at, w.url, w.secret FROM webhook_deliveries d JOIN webhooks w ON w.id = d.webhook_id WHERE d.id = $1").bind(&id)).await?;
        Ok(Some(DeliveryRow {
            id,
            webhook_id: row.get("webhook_id")?,
            event: row.get("event")?,
            job_id: row.get("job_id")?,
            body: row.get("body")?,
            attempts: row.get("attempts")?,
            created_at: row.get("created_at")?,
            url: row.get("url")?,
            secret: row.get("secret")?,
        }))
    }

    /// Record attempt `attempt` of a delivery this owner holds: delivered, retried at
    /// `next` (ms), or given up (`next` `None` and not delivered).
    #[allow(clippy::too_many_arguments)]
    pub async fn record_attempt(
        &self,
        id: &str,
        owner: &str,
        attempt: i64,
        body: Option<&str>,
        status_code: Option<i64>,
        error: Option<&str>,
        duration_ms: i64,
        delivered: bool,
        next: Option<i64>,
    ) -> sqlx::Result<()> {
        let now = now_ms();
        let status = if delivered {
            "delivered"
        } else if next.is_some() {
            "pending"
        } else {
            "failed"
        };
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("UPDATE webhook_deliveries SET status = $1, attempts = $2, body = COALESCE(body, $3), last_status_code = $4, last_error = $5, next_attempt_at = COALESCE($6, next_attempt_at), finished_at = $7, lease_owner = NULL, lease_expires_at = NULL WHERE id = $8 AND lease_owner = $9")
            .bind(status)
            .bind(attempt)
            .bind(body)
            .bind(status_code)
            .bind(error)
            .bind(next)
            .bind((status != "pending").then_some(now))
            .bind(id)
            .bind(owner))
            .await?;
        if n == 1 {
            tx.execute(sql("INSERT INTO webhook_attempts (delivery_id, attempt, at, status_code, error, duration_ms) VALUES ($1, $2, $3, $4, $5, $6)")
                .bind(id)
                .bind(attempt)
                .bind(now)
                .bind(status_code)
                .bind(error)
                .bind(duration_ms))
                .await?;
        }
        tx.commit().await
    }
}
