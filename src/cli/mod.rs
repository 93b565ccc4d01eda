//! The `rigcal` commands, one file each: its arguments (`Args`, validated by clap where
//! a range says it) and its `run`, which returns the process exit code.

pub mod apikey;
pub mod bench;
pub mod calibrate;
pub mod client;
pub mod compare;
pub mod demo;
pub mod detect;
pub mod jobs;
pub mod migrate;
pub mod serve;
pub mod submit;
pub mod synth;
pub mod worker;

use anyhow::{anyhow, Context, Result};
use rigcal_service::store::{blob::BlobUrl, db::DatabaseUrl, Location};
use std::path::PathBuf;

/// Where the service keeps its state: the embedded default (SQLite and a blob directory
/// in `--data-dir`) or a shared database and object store for replicas and workers on
/// many machines. The same flags on `serve`, `worker`, `apikey` and `migrate`.
#[derive(clap::Args, Clone, Debug)]
pub struct StoreArgs {
    /// Local working directory (upload spools); also holds the embedded default's
    /// database (rigcal.db) and blobs (blobs/).
    #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
    pub data_dir: PathBuf,
    /// sqlite://PATH or postgres://USER[:PASSWORD]@HOST[:PORT]/DB [default:
    /// sqlite://DATA_DIR/rigcal.db].
    #[arg(long, env = "RIGCAL_DATABASE_URL", value_parser = database_url)]
    pub database_url: Option<String>,
    /// file://DIR or s3://BUCKET/PREFIX (credentials, region and endpoint from AWS_*)
    /// [default: file://DATA_DIR/blobs].
    #[arg(long, env = "RIGCAL_BLOB_URL", value_parser = blob_url)]
    pub blob_url: Option<String>,
}

impl StoreArgs {
    pub fn location(&self) -> Location {
        Location::new(
            &self.data_dir,
            self.database_url.as_deref(),
            self.blob_url.as_deref(),
        )
    }
}

fn database_url(s: &str) -> std::result::Result<String, String> {
    DatabaseUrl::parse(s)
        .map(|_| s.to_string())
        .map_err(|e| e.to_string())
}

fn blob_url(s: &str) -> std::result::Result<String, String> {
    BlobUrl::parse(s)
        .map(|_| s.to_string())
        .map_err(|e| e.to_string())
}

/// Logs (tracing) to stderr; `RUST_LOG` overrides the default `info` for rigcal.
fn init_logging() {
    let default = || tracing_subscriber::EnvFilter::new("rigcal=info,warn");
    let filter = match std::env::var("RUST_LOG") {
        Err(_) => default(),
        Ok(spec) => tracing_subscriber::EnvFilter::try_new(&spec).unwrap_or_else(|e| {
            // Logging still starts (at the default levels), and says why.
            eprintln!(
                "warning: RUST_LOG={spec:?} is not a log filter ({e}); using rigcal=info,warn"
            );
            default()
        }),
    };
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The async runtime of the service commands, with logging started.
pub fn runtime() -> Result<tokio::runtime::Runtime> {
    init_logging();
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// `WxH`, e.g. `1024x768`.
pub fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("WIDTHxHEIGHT such as 1024x768, got {s:?}"))?;
    let n = |x: &str| {
        x.parse::<u32>()
            .map_err(|_| format!("WIDTHxHEIGHT such as 1024x768, got {s:?}"))
    };
    Ok((n(w)?, n(h)?))
}

/// A finite σ ≥ 0 (pixels or grey levels).
pub fn non_negative(s: &str) -> std::result::Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("a finite number ≥ 0, got {s:?}")),
    }
}

/// A finite σ > 0.
pub fn positive(s: &str) -> std::result::Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("a finite number > 0, got {s:?}")),
    }
}

/// One of the synthetic presets.
pub fn check_preset(preset: &str) -> Result<()> {
    if rigcal_synth::PRESETS.contains(&preset) {
        Ok(())
    } else {
        Err(anyhow!(
            "--preset: one of {}, got {preset:?}",
            rigcal_synth::PRESETS.join(", ")
        ))
    }
}
