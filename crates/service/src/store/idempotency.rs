//! Idempotency-Key records: the first successful answer to a POST under a client's key.

use super::Store;
use sqlx::Row;

/// How long a key is remembered.
pub const KEY_LIFETIME_MS: i64 = 24 * 3600 * 1000;
/// A request in flight this long under a key is taken for abandoned (its server died):
/// longer than any upload the body timeout lets live, short enough not to lock a key.
const IN_FLIGHT_MS: i64 = 15 * 60 * 1000;

/// A stored answer.
#[derive(Clone, Debug)]
pub struct StoredAnswer {
    pub route: String,
    pub fingerprint: String,
    pub status: u16,
    pub content_type: Option<String>,
    pub location: Option<String>,
    pub body: Vec<u8>,
}

/// What a key means for a new request.
#[derive(Debug)]
pub enum Claim {
    /// First use (or expired, or abandoned): the request runs, then [`Store::idempotency_finish`].
    Fresh,
    /// Another request under the key is still running.
    InFlight,
    /// Answered before.
    Answered(StoredAnswer),
}

impl Store {
    /// Claim `key` for a request to `route` at `now` (ms).
    pub async fn idempotency_claim(
        &self,
        tenant_id: &str,
        key: &str,
        route: &str,
        now: i64,
    ) -> sqlx::Result<Claim> {
        let mut tx = self.pool.begin().await?;
        sqlx::query("DELETE FROM idempotency_keys WHERE created_at < ? OR (fingerprint IS NULL AND created_at < ?)")
            .bind(now - KEY_LIFETIME_MS)
            .bind(now - IN_FLIGHT_MS)
            .execute(&mut *tx)
            .await?;
        let inserted = sqlx::query("INSERT INTO idempotency_keys (tenant_id, key, route, created_at) VALUES (?, ?, ?, ?) ON CONFLICT DO NOTHING")
            .bind(tenant_id)
            .bind(key)
            .bind(route)
            .bind(now)
            .execute(&mut *tx)
            .await?
            .rows_affected();
        let claim = if inserted == 1 {
            Claim::Fresh
        } else {
            let r = sqlx::query("SELECT route, fingerprint, status, content_type, location, body FROM idempotency_keys WHERE tenant_id = ? AND key = ?")
                .bind(tenant_id)
                .bind(key)
                .fetch_one(&mut *tx)
                .await?;
            match r.get::<Option<String>, _>("fingerprint") {
                None => Claim::InFlight,
                Some(fingerprint) => Claim::Answered(StoredAnswer {
                    route: r.get("route"),
                    fingerprint,
                    status: r.get::<i64, _>("status") as u16,
                    content_type: r.get("content_type"),
                    location: r.get("location"),
                    body: r.get("body"),
                }),
            }
        };
        tx.commit().await?;
        Ok(claim)
    }

    /// Keep the answer to the request that claimed `key`.
    pub async fn idempotency_finish(
        &self,
        tenant_id: &str,
        key: &str,
        answer: &StoredAnswer,
    ) -> sqlx::Result<()> {
        sqlx::query("UPDATE idempotency_keys SET fingerprint = ?, status = ?, content_type = ?, location = ?, body = ? WHERE tenant_id = ? AND key = ? AND fingerprint IS NULL")
            .bind(&answer.fingerprint)
            .bind(answer.status as i64)
            .bind(&answer.content_type)
            .bind(&answer.location)
            .bind(&answer.body)
            .bind(tenant_id)
            .bind(key)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Release `key` after a request that created nothing (an error): the client may
    /// retry under it.
    pub async fn idempotency_release(&self, tenant_id: &str, key: &str) -> sqlx::Result<()> {
        sqlx::query(
            "DELETE FROM idempotency_keys WHERE tenant_id = ? AND key = ? AND fingerprint IS NULL",
        )
        .bind(tenant_id)
        .bind(key)
        .execute(&self.pool)
        .await?;
        Ok(())
    }
}
