//! Idempotency-Key records: the first successful answer to a POST under a client's key.

use super::db::sql;
use super::Store;

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
        let mut tx = self.db.begin().await?;
        tx.execute(sql("DELETE FROM idempotency_keys WHERE created_at < $1 OR (fingerprint IS NULL AND created_at < $2)")
            .bind(now - KEY_LIFETIME_MS)
            .bind(now - IN_FLIGHT_MS))
            .await?;
        let inserted = tx.execute(sql("INSERT INTO idempotency_keys (tenant_id, key, route, created_at) VALUES ($1, $2, $3, $4) ON CONFLICT DO NOTHING")
            .bind(tenant_id)
            .bind(key)
            .bind(route)
            .bind(now))
            .await?;
        let claim = if inserted == 1 {
            Claim::Fresh
        } else {
            let r = tx.fetch_one(sql("SELECT route, fingerprint, status, content_type, location, body FROM idempotency_keys WHERE tenant_id = $1 AND key = $2")
                .bind(tenant_id)
                .bind(key))
                .await?;
            match r.get::<Option<String>>("fingerprint")? {
                None => Claim::InFlight,
                Some(fingerprint) => Claim::Answered(StoredAnswer {
                    route: r.get("route")?,
                    fingerprint,
                    // Out of range reads as 0, which the replay reports as a corrupt record.
                    status: u16::try_from(r.get::<i64>("status")?).unwrap_or(0),
                    content_type: r.get("content_type")?,
                    location: r.get("location")?,
                    body: r.get("body")?,
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
        self.db.execute(sql("UPDATE idempotency_keys SET fingerprint = $1, status = $2, content_type = $3, location = $4, body = $5 WHERE tenant_id = $6 AND key = $7 AND fingerprint IS NULL")
            .bind(&answer.fingerprint)
            .bind(answer.status as i64)
            .bind(&answer.content_type)
            .bind(&answer.location)
            .bind(&answer.body)
            .bind(tenant_id)
            .bind(key))
            .await?;
        Ok(())
    }

    /// Release `key` after a request that created nothing (an error): the client may
    /// retry under it.
    pub async fn idempotency_release(&self, tenant_id: &str, key: &str) -> sqlx::Result<()> {
        self.db.execute(sql("DELETE FROM idempotency_keys WHERE tenant_id = $1 AND key = $2 AND fingerprint IS NULL")
        .bind(tenant_id)
        .bind(key))
        .await?;
        Ok(())
    }
}
