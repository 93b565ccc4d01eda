//! `rigcal serve`: the HTTP API, the dashboard and embedded workers. Every default is
//! [`ServeConfig::default`]'s, so the flags and the library cannot drift apart.

use super::worker::JobArgs;
use super::StoreArgs;
use anyhow::Result;
use clap::builder::RangedU64ValueParser;
use rigcal_service::api::{serve, ServeConfig};
use std::time::Duration;

fn d() -> ServeConfig {
    ServeConfig::default()
}

/// The service: HTTP API, dashboard and embedded workers (SQLite and blobs in --data-dir,
/// or PostgreSQL and S3 shared by many replicas).
#[derive(clap::Args)]
pub struct Args {
    /// Address to listen on (port 0 picks a free port).
    #[arg(long, env = "RIGCAL_BIND", default_value_t = d().bind)]
    bind: String,
    #[command(flatten)]
    store: StoreArgs,
    /// Embedded workers (0: API only, run `rigcal worker` separately).
    #[arg(long, env = "RIGCAL_WORKERS", value_parser = RangedU64ValueParser::<usize>::new().range(0..=64),
          default_value_t = d().worker.workers)]
    workers: usize,
    /// Serve without API keys, as tenant "local". For local use only.
    #[arg(long, env = "RIGCAL_INSECURE_NO_AUTH")]
    insecure_no_auth: bool,
    #[command(flatten)]
    job: JobArgs,
    /// Attempts per job before a transient failure becomes final.
    #[arg(long, env = "RIGCAL_MAX_ATTEMPTS", value_parser = clap::value_parser!(i64).range(1..=100),
          default_value_t = d().max_attempts)]
    max_attempts: i64,
    /// Largest image upload, bytes.
    #[arg(long, env = "RIGCAL_MAX_IMAGE_BYTES", value_parser = RangedU64ValueParser::<usize>::new().range(1..),
          default_value_t = d().max_image_bytes)]
    max_image_bytes: usize,
    /// Largest archive upload (and its unpacked size), bytes.
    #[arg(long, env = "RIGCAL_MAX_ARCHIVE_BYTES", value_parser = RangedU64ValueParser::<usize>::new().range(1..),
          default_value_t = d().max_archive_bytes)]
    max_archive_bytes: usize,
    /// Largest manifest or JSON body, bytes.
    #[arg(long, env = "RIGCAL_MAX_MANIFEST_BYTES", value_parser = RangedU64ValueParser::<usize>::new().range(1..),
          default_value_t = d().max_manifest_bytes)]
    max_manifest_bytes: usize,
    /// Archive uploads read at once; more are refused with 503 and Retry-After.
    #[arg(long, env = "RIGCAL_MAX_CONCURRENT_ARCHIVES", value_parser = RangedU64ValueParser::<usize>::new().range(1..=1024),
          default_value_t = d().max_concurrent_archives)]
    max_concurrent_archives: usize,
    /// Seconds a connection may take to send a request's headers, counted from when it
    /// starts waiting for the request (so also the idle keep-alive timeout).
    #[arg(long, env = "RIGCAL_HEADER_TIMEOUT_SECONDS", value_parser = RangedU64ValueParser::<u64>::new().range(1..=86_400),
          default_value_t = d().header_timeout.as_secs())]
    header_timeout_seconds: u64,
    /// Seconds a request body may pause between two chunks (a slow link that keeps
    /// sending passes; a client that stops does not).
    #[arg(long, env = "RIGCAL_BODY_TIMEOUT_SECONDS", value_parser = RangedU64ValueParser::<u64>::new().range(1..=86_400),
          default_value_t = d().body_timeout.as_secs())]
    body_timeout_seconds: u64,
    /// Seconds a request that neither uploads nor streams may take from start to answer.
    #[arg(long, env = "RIGCAL_REQUEST_TIMEOUT_SECONDS", value_parser = RangedU64ValueParser::<u64>::new().range(1..=86_400),
          default_value_t = d().request_timeout.as_secs())]
    request_timeout_seconds: u64,
    /// Event streams (`/v1/events`, `/v1/jobs/{id}/events`) one tenant may hold open.
    #[arg(long, env = "RIGCAL_MAX_STREAMS_PER_TENANT", value_parser = RangedU64ValueParser::<usize>::new().range(1..=100_000),
          default_value_t = d().max_streams_per_tenant)]
    max_streams_per_tenant: usize,
}

pub fn run(a: Args) -> Result<i32> {
    let cfg = ServeConfig {
        bind: a.bind,
        store: a.store.location(),
        insecure_no_auth: a.insecure_no_auth,
        worker: a.job.config(a.workers),
        max_attempts: a.max_attempts,
        max_manifest_bytes: a.max_manifest_bytes,
        max_image_bytes: a.max_image_bytes,
        max_archive_bytes: a.max_archive_bytes,
        max_concurrent_archives: a.max_concurrent_archives,
        header_timeout: Duration::from_secs(a.header_timeout_seconds),
        body_timeout: Duration::from_secs(a.body_timeout_seconds),
        request_timeout: Duration::from_secs(a.request_timeout_seconds),
        max_streams_per_tenant: a.max_streams_per_tenant,
    };
    super::runtime()?.block_on(serve(cfg))?;
    Ok(0)
}
