//! `rigcal bench queue`: claim latency with many jobs queued, on either backend (numbers
//! in docs/performance.md; a measurement, not a timed test).

use super::queue::Queue;
use crate::store::db::sql;
use crate::store::{now_ms, Store};
use std::time::Instant;

/// Milliseconds of each of `claims` claims (each followed by a completion, as a worker
/// does) with `queued` jobs waiting, in a fresh tenant of `store`.
pub async fn claim_latency(
    store: &Store,
    queued: usize,
    claims: usize,
) -> anyhow::Result<Vec<f64>> {
    let tenant = store
        .ensure_tenant(&format!("bench-{}", uuid::Uuid::new_v4().simple()))
        .await?;
    let session = store
        .insert_session(&tenant, None, "motion", "{}", None)
        .await?;
    // Queued in one transaction: the API would take minutes to accept that many.
    let mut tx = store.db.begin().await?;
    let now = now_ms();
    for k in 0..queued {
        tx.execute(
            sql("INSERT INTO jobs (id, tenant_id, session_id, method, options, status, max_attempts, run_after, created_at) VALUES ($1, $2, $3, 'motion', '{}', 'queued', 3, $4, $4)")
                .bind(uuid::Uuid::new_v4().to_string())
                .bind(&tenant.id)
                .bind(&session.id)
                .bind(now - (queued - k) as i64),
        )
        .await?;
    }
    tx.commit().await?;
    let queue = Queue::new(store.db.clone());
    let summary = super::acceptance::ResultSummary::default();
    let mut ms = Vec::with_capacity(claims);
    for _ in 0..claims {
        let t = Instant::now();
        let job = queue.claim("bench", 60_000).await?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        let Some(job) = job else {
            anyhow::bail!("the queue ran dry after {} claims", ms.len());
        };
        let done = super::queue::JobStatus::Succeeded;
        queue
            .complete(&job.id, "bench", done, "{}", &summary, None)
            .await?;
    }
    Ok(ms)
}
