//! Event streams share one poller: a single task reads the newest event ids (of job
//! and of session events) from the database every [`POLL`] and publishes their sum, a
//! counter that grows whenever either does; every open stream sleeps on that value and
//! queries its own events only when something new was stored. So a thousand open
//! dashboards cost one cheap query per tick, and events written by workers in other
//! processes (which only the database connects) still arrive. Each tenant may hold at
//! most `max_streams_per_tenant` streams; the next is 429.

use super::error::ApiError;
use crate::jobs::queue::Queue;
use crate::store::Store;
use axum::http::StatusCode;
use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::watch;

/// How often the poller reads the newest event id.
pub const POLL: Duration = Duration::from_millis(250);

pub struct EventHub {
    latest: watch::Receiver<i64>,
    open: Mutex<HashMap<String, usize>>,
    cap: usize,
}

/// An open stream's place in its tenant's count, given back when the stream ends.
pub struct StreamSlot {
    hub: Arc<EventHub>,
    tenant: String,
    latest: watch::Receiver<i64>,
    /// The newest id the poller had published when this stream last looked.
    seen: i64,
}

impl EventHub {
    /// Start the poller; it stops when `shutdown` turns true.
    pub fn start(store: Store, cap: usize, mut shutdown: watch::Receiver<bool>) -> Arc<Self> {
        let (tx, rx) = watch::channel(0i64);
        let queue = Queue::new(store.db.clone());
        tokio::spawn(async move {
            loop {
                let ids = tokio::try_join!(queue.last_event_id(), store.last_session_event_id());
                if let Ok((jobs, sessions)) = ids {
                    let id = jobs + sessions;
                    tx.send_if_modified(|v| {
                        let newer = id > *v;
                        *v = (*v).max(id);
                        newer
                    });
                }
                tokio::select! {
                    _ = tokio::time::sleep(POLL) => {}
                    _ = shutdown.changed() => {}
                }
                if *shutdown.borrow() {
                    break;
                }
            }
        });
        Arc::new(Self {
            latest: rx,
            open: Mutex::new(HashMap::new()),
            cap,
        })
    }

    /// A slot for one more stream of `tenant`, or 429 when it holds `cap` already.
    pub fn open(self: &Arc<Self>, tenant: &str) -> Result<StreamSlot, ApiError> {
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        let n = open.entry(tenant.to_string()).or_insert(0);
        if *n >= self.cap {
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                "too-many-streams",
                format!(
                    "at most {} open event streams per tenant; close one (or use /v1/events, one stream for every job)",
                    self.cap
                ),
            ));
        }
        *n += 1;
        let latest = self.latest.clone();
        let seen = *latest.borrow();
        Ok(StreamSlot {
            hub: self.clone(),
            tenant: tenant.to_string(),
            latest,
            seen,
        })
    }
}

impl StreamSlot {
    /// Wait until the poller has seen an event newer than any this stream looked for
    /// (events up to `seen` were committed before the stream's last query), or a minute
    /// passes (the stream then looks anyway).
    pub async fn changed(&mut self) {
        let seen = self.seen;
        let wait = self.latest.wait_for(|&v| v > seen);
        let _ = tokio::time::timeout(Duration::from_secs(60), wait).await;
        self.seen = *self.latest.borrow();
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        let mut open = self.hub.open.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = open.get_mut(&self.tenant) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                open.remove(&self.tenant);
            }
        }
    }
}

/// One stored event of a resource's stream (a job's, a session's).
pub trait StreamEvent: serde::Serialize {
    fn id(&self) -> i64;
    fn kind(&self) -> &str;
    /// The resource's last event: its stream ends after it.
    fn ends_stream(&self) -> bool;
}

impl StreamEvent for crate::jobs::queue::EventRow {
    fn id(&self) -> i64 {
        self.id
    }
    fn kind(&self) -> &str {
        &self.kind
    }
    /// The job's terminal status.
    fn ends_stream(&self) -> bool {
        use crate::jobs::queue::JobStatus;
        self.kind == "status" && JobStatus::parse(&self.status).is_some_and(JobStatus::is_terminal)
    }
}

impl StreamEvent for crate::store::detections::SessionEvent {
    fn id(&self) -> i64 {
        self.id
    }
    fn kind(&self) -> &str {
        &self.kind
    }
    /// The complete capture check.
    fn ends_stream(&self) -> bool {
        self.kind == "check" && self.data["complete"] == serde_json::Value::Bool(true)
    }
}

/// Where a stream reads one resource's events (a job's, a session's).
pub trait EventSource {
    type Event: StreamEvent;
    /// The resource's events stored after `last`, oldest first.
    fn after(&self, last: i64) -> impl Future<Output = sqlx::Result<Vec<Self::Event>>> + Send;
    /// Whether the resource has ended (its last event is stored).
    fn ended(&self) -> impl Future<Output = bool> + Send;
}

/// A resource's events as server-sent events: those stored after `last`, then each as
/// it is stored, until one [`ends_stream`](StreamEvent::ends_stream), the resource
/// turns out to have ended before the stream began (nothing left after `last`), or the
/// server shuts down.
pub fn follow<S: EventSource>(
    mut slot: StreamSlot,
    mut shutdown: watch::Receiver<bool>,
    mut last: i64,
    source: S,
) -> impl futures::Stream<Item = Result<axum::response::sse::Event, std::convert::Infallible>> {
    async_stream::stream! {
        loop {
            let Ok(events) = source.after(last).await else { break };
            let mut ended = false;
            for e in events {
                last = e.id();
                ended |= e.ends_stream();
                let data = serde_json::to_string(&e).unwrap_or_default();
                yield Ok(axum::response::sse::Event::default().id(last.to_string()).event(e.kind()).data(data));
            }
            if ended || *shutdown.borrow() {
                break;
            }
            // Ended before we subscribed: its last event was sent already.
            if source.ended().await && source.after(last).await.is_ok_and(|e| e.is_empty()) {
                break;
            }
            tokio::select! {
                _ = slot.changed() => {},
                _ = shutdown.changed() => {},
            }
        }
    }
}
