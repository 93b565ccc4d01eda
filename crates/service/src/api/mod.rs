//! The HTTP service: axum routers over the store, the queue and the engine.
//! `build_app` assembles the app once; `serve` binds it (and starts embedded workers).

mod archive;
pub mod auth;
mod bundle;
pub mod error;
mod events;
mod figures;
mod idempotency;
mod jobs;
mod listen;
mod ops;
mod sessions;
mod tenant;
mod vehicle_models;
mod vehicles;
mod webhooks;

use crate::jobs::queue::Queue;
use crate::jobs::worker::{self, WorkerConfig};
use crate::store::{Location, Store};
use crate::telemetry::Metrics;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::middleware::{self, Next};
use axum::response::Response;
use axum::routing::{get, post, put};
use axum::Router;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Everything `rigcal serve` can be told (flags and environment variables).
#[derive(Clone, Debug)]
pub struct ServeConfig {
    pub bind: String,
    /// The database, the blob store and the local working directory.
    pub store: Location,
    pub insecure_no_auth: bool,
    /// The embedded workers (`workers: 0` for an API-only replica). Its
    /// `max_image_pixels` is also the upload's limit, so an image the API accepts is
    /// one detection decodes.
    pub worker: WorkerConfig,
    pub max_attempts: i64,
    pub max_manifest_bytes: usize,
    pub max_image_bytes: usize,
    pub max_archive_bytes: usize,
    /// Archive uploads read at once (each holds a spool file and a blocking thread).
    pub max_concurrent_archives: usize,
    /// From waiting for a request to having its headers (also the idle keep-alive).
    pub header_timeout: Duration,
    /// Longest pause between two chunks of a request body.
    pub body_timeout: Duration,
    /// Whole-request limit for routes that neither upload nor stream.
    pub request_timeout: Duration,
    /// Event streams one tenant may hold open.
    pub max_streams_per_tenant: usize,
}

impl Default for ServeConfig {
    fn default() -> Self {
        Self {
            bind: "127.0.0.1:8080".into(),
            store: Location::new(std::path::Path::new("rigcal-data"), None, None),
            insecure_no_auth: false,
            worker: WorkerConfig::default(),
            max_attempts: 3,
            max_manifest_bytes: 64 << 20,
            max_image_bytes: 64 << 20,
            max_archive_bytes: 1 << 30,
            max_concurrent_archives: 4,
            header_timeout: Duration::from_secs(30),
            body_timeout: Duration::from_secs(60),
            request_timeout: Duration::from_secs(120),
            max_streams_per_tenant: 32,
        }
    }
}

#[derive(Clone)]
pub struct AppState {
    pub store: Store,
    pub queue: Queue,
    pub metrics: Arc<Metrics>,
    pub config: Arc<ServeConfig>,
    /// Turns `true` when the server starts shutting down: endless streams end then.
    pub shutdown: tokio::sync::watch::Receiver<bool>,
    /// Slots for archive uploads (`max_concurrent_archives`).
    pub archive_slots: Arc<tokio::sync::Semaphore>,
    /// The shared event poller and the per-tenant stream counts.
    pub events: Arc<events::EventHub>,
}

async fn record_latency(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or("(unmatched)".to_string(), |p| p.as_str().to_string());
    let method = req.method().to_string();
    let t = Instant::now();
    let resp = next.run(req).await;
    state.metrics.request(
        &method,
        &route,
        resp.status().as_u16(),
        t.elapsed().as_secs_f64(),
    );
    resp
}

/// A route's body limit: refused up front when the declared `Content-Length` exceeds it
/// (tower-http: the client learns before uploading, and never sees a reset connection
/// instead of the 413), and while reading otherwise (axum's extractor limit, for chunked
/// bodies). `problem_fallback` turns the bare 413 into problem+json.
fn body_limit(
    max: usize,
) -> tower::ServiceBuilder<
    tower::layer::util::Stack<
        DefaultBodyLimit,
        tower::layer::util::Stack<
            tower_http::limit::RequestBodyLimitLayer,
            tower::layer::util::Identity,
        >,
    >,
> {
    tower::ServiceBuilder::new()
        .layer(tower_http::limit::RequestBodyLimitLayer::new(max))
        .layer(DefaultBodyLimit::max(max))
}

pub fn build_app(state: AppState) -> Router {
    let cfg = state.config.clone();
    // Uploads are bounded by the body timeout (a slow link that keeps sending passes),
    // event streams by nothing but the client and shutdown; everything else answers
    // within the request timeout.
    // Inside each route's body limit, so a replayed body is held to it too.
    let idempotent = middleware::from_fn_with_state(state.clone(), idempotency::idempotent);
    let uploads = Router::new()
        .route(
            "/sessions",
            post(sessions::create)
                .layer::<_, std::convert::Infallible>(idempotent.clone())
                .layer(body_limit(cfg.max_archive_bytes)),
        )
        .route(
            "/sessions/{id}/images/{camera}/{frame}",
            put(sessions::put_image).layer(body_limit(cfg.max_image_bytes)),
        )
        .route(
            "/sessions/{id}/archive",
            post(sessions::archive)
                .layer::<_, std::convert::Infallible>(idempotent.clone())
                .layer(body_limit(cfg.max_archive_bytes)),
        );
    let streams = Router::new()
        .route("/events", get(jobs::tenant_events))
        .route("/jobs/{id}/events", get(jobs::events))
        .route("/sessions/{id}/events", get(sessions::events));
    let timed = Router::new()
        .route("/sessions/{id}", get(sessions::show))
        .route("/sessions/{id}/check", get(sessions::check))
        .route(
            "/jobs",
            post(jobs::create)
                .layer::<_, std::convert::Infallible>(idempotent)
                .layer(body_limit(cfg.max_manifest_bytes))
                .get(jobs::list),
        )
        .route("/jobs/{id}", get(jobs::show).delete(jobs::cancel))
        .route("/tenant", get(tenant::show))
        .route(
            "/tenant/thresholds",
            get(tenant::thresholds).put(tenant::set_thresholds),
        )
        .route("/jobs/{id}/figures/{name}", get(figures::job))
        .route("/vehicles/{vehicle_id}/drift.svg", get(figures::drift))
        .route("/jobs/{id}/result", get(jobs::result))
        .route("/jobs/{id}/bundle", get(bundle::bundle))
        .route("/jobs/{id}/diagnostics", get(jobs::diagnostics))
        .route(
            "/webhooks",
            post(webhooks::create)
                .layer(body_limit(64 << 10))
                .get(webhooks::list),
        )
        .route(
            "/webhooks/{id}",
            get(webhooks::show).delete(webhooks::delete),
        )
        .route("/webhooks/{id}/deliveries", get(webhooks::deliveries))
        .route("/vehicle-models", get(vehicle_models::list))
        .route(
            "/vehicle-models/{model}",
            put(vehicle_models::put)
                .layer(body_limit(cfg.max_manifest_bytes))
                .get(vehicle_models::show),
        )
        .route("/vehicle-models/{model}/fleet", get(vehicle_models::fleet))
        .route("/vehicle-models/{model}/fleet.svg", get(figures::fleet))
        .route(
            "/vehicles/{vehicle_id}/calibrations",
            get(vehicles::calibrations),
        )
        .layer(tower_http::timeout::TimeoutLayer::with_status_code(
            axum::http::StatusCode::SERVICE_UNAVAILABLE,
            cfg.request_timeout,
        ));
    let v1 = uploads
        .merge(streams)
        .merge(timed)
        .layer(tower_http::timeout::RequestBodyTimeoutLayer::new(
            cfg.body_timeout,
        ))
        .layer(DefaultBodyLimit::max(cfg.max_manifest_bytes));
    Router::new()
        .nest("/v1", v1)
        .route("/", get(crate::dashboard::index))
        .route("/assets/{name}", get(ops::asset))
        .route("/healthz", get(ops::healthz))
        .route("/readyz", get(ops::readyz))
        .route("/metrics", get(ops::metrics))
        .route("/openapi.yaml", get(ops::openapi))
        .route("/docs", get(ops::docs))
        .fallback(ops::not_found)
        .layer(middleware::from_fn_with_state(
            state.clone(),
            record_latency,
        ))
        .layer(middleware::map_response(error::problem_fallback))
        .with_state(state)
}

/// Open the store, start `config.worker.workers` embedded workers and bind. Returns the bound
/// address and the server future (which runs until SIGINT/SIGTERM).
pub async fn start(
    config: ServeConfig,
) -> anyhow::Result<(
    SocketAddr,
    impl std::future::Future<Output = std::io::Result<()>>,
)> {
    if config.insecure_no_auth {
        eprintln!("WARNING: --insecure-no-auth: every request acts as tenant \"local\" without an API key. Never expose this server beyond this machine.");
    }
    let store = Store::connect(&config.store).await?;
    let metrics = Arc::new(Metrics::default());
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let workers = worker::spawn(
        store.clone(),
        metrics.clone(),
        config.worker.clone(),
        stop_rx.clone(),
    );
    let listener = tokio::net::TcpListener::bind(&config.bind)
        .await
        .map_err(|e| anyhow::anyhow!("binding {}: {e}", config.bind))?;
    let addr: SocketAddr = listener.local_addr()?;
    let queue = Queue::new(store.db.clone());
    let state = AppState {
        archive_slots: Arc::new(tokio::sync::Semaphore::new(config.max_concurrent_archives)),
        events: events::EventHub::start(
            store.clone(),
            config.max_streams_per_tenant,
            stop_rx.clone(),
        ),
        queue,
        store,
        metrics,
        config: Arc::new(config),
        shutdown: stop_rx,
    };
    let header_timeout = state.config.header_timeout;
    let app = build_app(state);
    let server = listen::serve(listener, app, header_timeout, async move {
        crate::signals::shutdown_signal().await;
        let _ = stop_tx.send(true);
    });
    // The embedded workers saw the same stop: they finish or give back their jobs
    // before the process ends.
    let server = async move {
        let served = server.await;
        for w in workers {
            // A worker task that panicked has nothing left to give back.
            let _ = w.await;
        }
        served
    };
    Ok((addr, server))
}

/// `rigcal serve`: start, print `rigcal listening on http://ADDR`, serve until a signal.
pub async fn serve(config: ServeConfig) -> anyhow::Result<()> {
    let (addr, server) = start(config).await?;
    println!("rigcal listening on http://{addr}");
    use std::io::Write;
    let _ = std::io::stdout().flush();
    server.await?;
    Ok(())
}
