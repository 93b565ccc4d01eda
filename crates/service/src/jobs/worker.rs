//! The worker pool: each worker claims a job, runs the pipeline on a blocking thread
//! (so the API keeps answering), reports stages as job events, renews its lease, and
//! honours cancellation between stages.
//!
//! Failure policy: the engine's verdict (including `failed` with reasons) is a result,
//! stored once, never retried. A session that no longer parses is bad input: failed once.
//! Everything else (database or blob I/O, a panic in the engine) is treated as transient
//! and retried with exponential backoff up to the job's attempt limit.

use super::detection::{self, BlobSource};
use super::queue::{FailOutcome, JobRow, JobStatus, Queue, JOBS_CHANNEL};
use super::JobOptions;
use crate::store::db::Db;
use crate::store::{Location, Store};
use crate::telemetry::Metrics;
use rigcal_core::result::DetectionQuality;
use rigcal_core::session::parse_session;
use rigcal_core::verdict::ReasonCode;
use rigcal_engine::pipeline::{run, Cancelled, Progress};
use serde_json::json;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub workers: usize,
    pub lease: Duration,
    /// How often an idle worker looks for work.
    pub poll: Duration,
    /// First retry delay of a job, and of an uploaded image's detection; doubled per
    /// attempt.
    pub backoff: Duration,
    /// Largest image decoded at detection: the same budget the upload was checked
    /// against (`--max-image-pixels`), so an image the API accepted is never skipped.
    pub max_image_pixels: u64,
    /// The quality uploaded images are detected at (`--upload-detect-quality`). An
    /// `accurate` outcome serves jobs of either quality; a `fast` one only `fast` jobs
    /// (an `accurate` job detects those images again).
    pub upload_detect_quality: DetectionQuality,
    /// The webhook dispatcher every process with workers (or an API) runs beside them.
    pub webhooks: crate::webhooks::WebhookConfig,
}

impl Default for WorkerConfig {
    fn default() -> Self {
        Self {
            workers: 1,
            lease: Duration::from_secs(30),
            poll: Duration::from_millis(200),
            backoff: Duration::from_secs(2),
            max_image_pixels: rigcal_engine::pipeline::detection::DEFAULT_MAX_IMAGE_PIXELS,
            upload_detect_quality: DetectionQuality::Accurate,
            webhooks: crate::webhooks::WebhookConfig::default(),
        }
    }
}

/// Start `cfg.workers` workers and a webhook dispatcher on the current runtime. They run until `stop` turns
/// true; then each stops claiming, lets its job reach the next stage boundary (or gives
/// it back, see [`run_job`]) and ends. Await the handles to let them finish.
pub fn spawn(
    store: Store,
    metrics: Arc<Metrics>,
    cfg: WorkerConfig,
    stop: watch::Receiver<bool>,
) -> Vec<tokio::task::JoinHandle<()>> {
    // The host only labels the worker in the queue's lease records (`claimed_by`); a
    // machine without HOSTNAME is labelled "local" rather than refused.
    let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "local".into());
    let wake = Wakeup::start(&store, stop.clone());
    // One webhook dispatcher per process, also in an API-only replica (`--workers 0`).
    let dispatcher = crate::webhooks::spawn(store.clone(), cfg.webhooks.clone(), stop.clone());
    (0..cfg.workers)
        .map(|i| {
            let name = format!(
                "{host}/{}/{i}/{}",
                std::process::id(),
                uuid::Uuid::new_v4().simple()
            );
            let (store, metrics, cfg) = (store.clone(), metrics.clone(), cfg.clone());
            let (wake, stop) = (wake.clone(), stop.clone());
            tokio::spawn(async move { worker_loop(name, store, metrics, cfg, wake, stop).await })
        })
        .chain(std::iter::once(dispatcher))
        .collect()
}

/// What wakes an idle worker before its next poll: on PostgreSQL, a `NOTIFY` of a new
/// or released job from any process on any machine. Polling stays (slower while a
/// listener is connected) because notifications sent while it reconnects are lost.
#[derive(Clone)]
struct Wakeup {
    notify: Arc<tokio::sync::Notify>,
    listening: Arc<AtomicBool>,
}

impl Wakeup {
    fn start(store: &Store, mut stop: watch::Receiver<bool>) -> Wakeup {
        let wake = Wakeup {
            notify: Arc::new(tokio::sync::Notify::new()),
            listening: Arc::new(AtomicBool::new(false)),
        };
        let Db::Postgres(pool) = store.db.clone() else {
            return wake;
        };
        let w = wake.clone();
        tokio::spawn(async move {
            loop {
                let listener = async {
                    let mut l = sqlx::postgres::PgListener::connect_with(&pool).await?;
                    l.listen(JOBS_CHANNEL).await?;
                    Ok::<_, sqlx::Error>(l)
                };
                let mut l = match listener.await {
                    Ok(l) => l,
                    Err(e) => {
                        tracing::warn!("job notifications unavailable, polling: {e}");
                        tokio::select! {
                            _ = tokio::time::sleep(Duration::from_secs(5)) => continue,
                            _ = stop.changed() => return,
                        }
                    }
                };
                w.listening.store(true, Ordering::SeqCst);
                // Whatever was announced while not listening: look now.
                w.notify.notify_waiters();
                loop {
                    tokio::select! {
                        m = l.recv() => match m {
                            // One job, one worker: a permit is kept if none is idle
                            // yet, so a notice that lands between a worker's empty
                            // claim and its wait is not lost.
                            Ok(_) => w.notify.notify_one(),
                            Err(e) => {
                                tracing::warn!("job notifications lost, reconnecting: {e}");
                                break;
                            }
                        },
                        _ = stop.changed() => return,
                    }
                }
                w.listening.store(false, Ordering::SeqCst);
            }
        });
        wake
    }

    /// Sleep until woken, the poll interval passes, or `stop` changes.
    async fn idle(&self, poll: Duration, stop: &mut watch::Receiver<bool>) {
        let poll = if self.listening.load(Ordering::SeqCst) {
            poll * 10
        } else {
            poll
        };
        tokio::select! {
            _ = self.notify.notified() => {}
            _ = tokio::time::sleep(poll) => {}
            _ = stop.changed() => {}
        }
    }
}

async fn worker_loop(
    name: String,
    store: Store,
    metrics: Arc<Metrics>,
    cfg: WorkerConfig,
    wake: Wakeup,
    mut stop: watch::Receiver<bool>,
) {
    let queue = Queue::new(store.db.clone());
    let lease_ms = cfg.lease.as_millis() as i64;
    // Uploaded images first: each is short, and together they make the operator's
    // capture check; but a turn of them at a time, so that jobs are not starved by a
    // stream of uploads. The workers of a process share the cores between them.
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let batch = cores.div_ceil(cfg.workers.max(1));
    let mut refreshes = detection::Refreshes::default();
    while !*stop.borrow() {
        let detected = match detection::run_batch(&name, &store, &cfg, batch, &mut refreshes).await
        {
            Ok(n) => n,
            Err(e) => {
                tracing::warn!(worker = %name, "image detection failed (storage): {e}");
                0
            }
        };
        // After a turn of images, one job if any waits; then the images again.
        match queue.claim(&name, lease_ms).await {
            Ok(Some(job)) => {
                tracing::info!(job = %job.id, attempt = job.attempts, worker = %name, "claimed");
                run_job(&name, &store, &queue, &metrics, &cfg, job, stop.clone()).await;
            }
            Ok(None) if detected > 0 => {}
            Ok(None) => wake.idle(cfg.poll, &mut stop).await,
            Err(e) => {
                tracing::warn!(worker = %name, "claim failed: {e}");
                wake.idle(cfg.poll * 5, &mut stop).await;
            }
        }
    }
    tracing::info!(worker = %name, "stopped");
}

/// Sends stage changes to the async side and reads the cancel flag.
struct ChannelProgress {
    tx: mpsc::UnboundedSender<(String, f64)>,
    stop: Arc<AtomicBool>,
}

impl Progress for ChannelProgress {
    fn stage(&self, stage: &str, fraction: f64) -> bool {
        let _ = self.tx.send((stage.to_string(), fraction));
        !self.stop.load(Ordering::SeqCst)
    }
}

fn problem(code: &str, detail: impl Into<String>, field: Option<&str>) -> serde_json::Value {
    json!({"code": code, "detail": detail.into(), "field": field})
}

async fn run_job(
    name: &str,
    store: &Store,
    queue: &Queue,
    metrics: &Metrics,
    cfg: &WorkerConfig,
    job: JobRow,
    mut shutdown: watch::Receiver<bool>,
) {
    let backoff = cfg.backoff.as_millis() as i64;
    if job.attempts > job.max_attempts {
        let p = problem(
            "attempts_exhausted",
            format!(
                "the job was claimed {} times without finishing (workers lost mid-job)",
                job.attempts - 1
            ),
            None,
        );
        let _ = queue.fail(&job.id, name, &p, false, backoff).await;
        metrics.job_finished("failed");
        return;
    }
    let session = match store.session_by_id(&job.session_id).await {
        Ok(Some(s)) => s,
        Ok(None) => {
            let p = problem(
                "session_missing",
                "the job's session no longer exists",
                Some("session_id"),
            );
            let _ = queue.fail(&job.id, name, &p, false, backoff).await;
            return;
        }
        Err(e) => {
            let p = problem("storage_error", e.to_string(), None);
            let _ = queue.fail(&job.id, name, &p, true, backoff).await;
            return;
        }
    };
    // The manifest and the options were validated when they were stored; if they no
    // longer parse, the store or this build disagrees with the API that accepted them,
    // which is ours to fix, not the client's.
    let parsed = parse_session(session.manifest.as_bytes()).map_err(|e| {
        format!(
            "the stored session no longer validates ({}: {})",
            e.field, e.expected
        )
    });
    let opts = serde_json::from_str::<JobOptions>(&job.options)
        .map_err(|e| e.to_string())
        .and_then(|o| {
            o.calib()
                .map_err(|e| format!("{}: {}", e.field, e.expected))
        })
        .map_err(|e| format!("the stored job options no longer validate ({e})"));
    let (parsed, opts) = match (parsed, opts) {
        (Ok(p), Ok(o)) => (p, o),
        (Err(why), _) | (_, Err(why)) => {
            let p = problem("internal_error", why, None);
            let _ = queue.fail(&job.id, name, &p, false, backoff).await;
            metrics.job_finished("failed");
            return;
        }
    };

    let images =
        match BlobSource::of(store, &job.session_id, cfg.max_image_pixels, opts.detection).await {
            Ok(source) => source,
            Err(e) => {
                let p = problem("storage_error", e.to_string(), None);
                let _ = queue.fail(&job.id, name, &p, true, backoff).await;
                return;
            }
        };
    let stop = Arc::new(AtomicBool::new(false));
    let lost = Arc::new(AtomicBool::new(false));
    let (tx, mut rx) = mpsc::unbounded_channel::<(String, f64)>();
    let progress = ChannelProgress {
        tx,
        stop: stop.clone(),
    };
    let solve = tokio::task::spawn_blocking(move || {
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            run(&parsed, &images, &opts, &progress)
        }))
    });
    tokio::pin!(solve);
    // The heartbeat renews the lease and reads the cancel flag; twice a second at most
    // so a cancel is seen before the next stage boundary, at the cost of one UPDATE.
    let mut beat = tokio::time::interval((cfg.lease / 3).min(Duration::from_millis(500)));
    beat.tick().await;
    let mut current: Option<(String, Instant)> = None;
    let lease_ms = cfg.lease.as_millis() as i64;
    let record = |stage: String, fraction: f64, current: &mut Option<(String, Instant)>| {
        if let Some((s, t)) = current.take() {
            metrics.stage(&s, t.elapsed().as_secs_f64());
        }
        *current = Some((stage.clone(), Instant::now()));
        let (queue, id, stop, lost) = (queue.clone(), job.id.clone(), stop.clone(), lost.clone());
        async move {
            match queue.progress(&id, name, &stage, fraction).await {
                Ok(Some(cancel)) => {
                    if cancel {
                        stop.store(true, Ordering::SeqCst)
                    }
                }
                Ok(None) => {
                    lost.store(true, Ordering::SeqCst);
                    stop.store(true, Ordering::SeqCst);
                }
                Err(e) => tracing::warn!(job = %id, "progress update failed: {e}"),
            }
        }
    };
    // A shutdown (SIGTERM) stops the pipeline at its next stage boundary, like a cancel;
    // the job is then given back, not cancelled. A stage that does not end within half
    // the lease is abandoned: the job is given back at once and this process exits
    // (its blocking thread with it), well before the lease would have expired.
    let mut stopping: Option<tokio::time::Instant> = None;
    let mut cancel_requested = false;
    let give_back = |why: &'static str| {
        let (queue, id) = (queue.clone(), job.id.clone());
        async move {
            match queue.release(&id, name, why).await {
                Ok(true) => tracing::info!(job = %id, "given back: {why}"),
                Ok(false) => tracing::warn!(job = %id, "lease lost before it was given back"),
                Err(e) => {
                    tracing::warn!(job = %id, "giving the job back failed (its lease will expire): {e}")
                }
            }
        }
    };
    let outcome = loop {
        let deadline = stopping.unwrap_or_else(tokio::time::Instant::now);
        tokio::select! {
            // Stage reports first: a fast solve must not finish the job before the
            // stages it went through are recorded.
            biased;
            Some((stage, fraction)) = rx.recv() => record(stage, fraction, &mut current).await,
            r = &mut solve => break r,
            _ = shutdown.changed(), if stopping.is_none() => {
                tracing::info!(job = %job.id, "shutting down: stopping at the next stage");
                stopping = Some(tokio::time::Instant::now() + cfg.lease / 2);
                stop.store(true, Ordering::SeqCst);
            }
            _ = tokio::time::sleep_until(deadline), if stopping.is_some() => {
                give_back("worker shut down mid-stage").await;
                return;
            }
            _ = beat.tick() => {
                match queue.heartbeat(&job.id, name, lease_ms).await {
                    Ok(Some(cancel)) => if cancel { cancel_requested = true; stop.store(true, Ordering::SeqCst) },
                    Ok(None) => { lost.store(true, Ordering::SeqCst); stop.store(true, Ordering::SeqCst); }
                    Err(e) => tracing::warn!(job = %job.id, "heartbeat failed: {e}"),
                }
            }
        }
    };
    // Stages reported between the last poll and the end of the solve.
    while let Ok((stage, fraction)) = rx.try_recv() {
        record(stage, fraction, &mut current).await;
    }
    if let Some((s, t)) = current.take() {
        metrics.stage(&s, t.elapsed().as_secs_f64());
    }
    if lost.load(Ordering::SeqCst) {
        tracing::warn!(job = %job.id, "lease lost; another worker owns the job now");
        return;
    }
    match outcome {
        // The session's images could not be read (storage): not a verdict on the capture,
        // and perhaps transient, so retried with backoff like other storage failures.
        Ok(Ok(Ok(doc))) if doc.reasons.iter().any(|r| r.is(ReasonCode::InputMissing)) => {
            let message = doc
                .reasons
                .iter()
                .find(|r| r.is(ReasonCode::InputMissing))
                .map(|r| r.message.clone())
                .unwrap_or_default();
            tracing::warn!(job = %job.id, "{message}");
            let p = problem("input_missing", message, None);
            if let Ok(FailOutcome::Failed) = queue.fail(&job.id, name, &p, true, backoff).await {
                metrics.job_finished("failed");
            }
        }
        Ok(Ok(Ok(doc))) => {
            let status = JobStatus::from(doc.status);
            let text = match serde_json::to_string(&doc) {
                Ok(t) => t,
                Err(e) => {
                    let p = problem("internal_error", e.to_string(), None);
                    let _ = queue.fail(&job.id, name, &p, true, backoff).await;
                    return;
                }
            };
            let summary = super::acceptance::ResultSummary::of(&doc);
            let error = (doc.status == rigcal_core::result::Status::Failed).then(|| {
                let first = doc.reasons.first();
                problem(
                    first.map_or("failed", |r| r.code.as_str()),
                    first.map_or(String::new(), |r| r.message.clone()),
                    None,
                )
                .to_string()
            });
            match queue
                .complete(&job.id, name, status, &text, &summary, error.as_deref())
                .await
            {
                Ok(true) => {
                    metrics.job_finished(status.as_str());
                    tracing::info!(job = %job.id, status = status.as_str(), "finished");
                }
                Ok(false) => tracing::warn!(job = %job.id, "lease lost before completion"),
                Err(e) => {
                    tracing::warn!(job = %job.id, "storing the result failed: {e}");
                    let p = problem("storage_error", e.to_string(), None);
                    let _ = queue.fail(&job.id, name, &p, true, backoff).await;
                }
            }
        }
        Ok(Ok(Err(Cancelled(_)))) if stopping.is_some() && !cancel_requested => {
            give_back("worker shut down").await;
        }
        Ok(Ok(Err(Cancelled(stage)))) => {
            if let Ok(true) = queue.mark_cancelled(&job.id, name, &stage).await {
                metrics.job_finished("cancelled");
            }
        }
        Ok(Err(panic)) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "panic".into());
            tracing::error!(job = %job.id, "engine panicked: {what}");
            let p = problem(
                "internal_error",
                format!("the engine failed unexpectedly: {what}"),
                None,
            );
            if let Ok(FailOutcome::Failed) = queue.fail(&job.id, name, &p, true, backoff).await {
                metrics.job_finished("failed");
            }
        }
        Err(e) => {
            let p = problem("internal_error", format!("worker task failed: {e}"), None);
            let _ = queue.fail(&job.id, name, &p, true, backoff).await;
        }
    }
}

/// `rigcal worker`: workers only, against the store at `at`, until SIGINT or SIGTERM;
/// then they stop claiming and finish or give back their jobs before the process ends.
pub async fn run_standalone(at: &Location, cfg: WorkerConfig) -> anyhow::Result<()> {
    let store = Store::connect(at).await?;
    let metrics = Arc::new(Metrics::default());
    eprintln!(
        "rigcal worker: {} worker(s) on {}",
        cfg.workers,
        at.describe()
    );
    let (stop_tx, stop_rx) = watch::channel(false);
    let handles = spawn(store, metrics, cfg, stop_rx);
    crate::signals::shutdown_signal().await;
    // Fails only when every worker has already ended (no receiver left): nothing to stop.
    let _ = stop_tx.send(true);
    for h in handles {
        // A worker task that panicked has nothing left to give back.
        let _ = h.await;
    }
    Ok(())
}
