//! `rigcal worker`: workers only, on the same database and blob store as a `serve`
//! (any number, on any machine that reaches them).

use super::StoreArgs;
use anyhow::Result;
use clap::builder::RangedU64ValueParser;
use rigcal_core::result::DetectionQuality;
use rigcal_service::jobs::worker::{run_standalone, WorkerConfig};
use std::time::Duration;

/// The settings a worker shares with `serve`'s embedded workers; their defaults are
/// [`WorkerConfig::default`]'s.
#[derive(clap::Args)]
pub struct JobArgs {
    /// Lease of a claimed job, seconds (renewed every third of it).
    #[arg(long, env = "RIGCAL_LEASE_SECONDS", value_parser = RangedU64ValueParser::<u64>::new().range(1..=86_400),
          default_value_t = WorkerConfig::default().lease.as_secs())]
    pub lease_seconds: u64,
    /// Largest image, pixels: checked from the header before decoding, at upload and at
    /// detection (give a separate worker the servers' value).
    #[arg(long, env = "RIGCAL_MAX_IMAGE_PIXELS", value_parser = RangedU64ValueParser::<u64>::new().range(1..),
          default_value_t = WorkerConfig::default().max_image_pixels)]
    pub max_image_pixels: u64,
    /// Quality uploaded images are detected at: accurate | fast. Jobs reuse an
    /// `accurate` outcome at either quality, a `fast` one only at `fast`.
    #[arg(long, env = "RIGCAL_UPLOAD_DETECT_QUALITY", default_value = "accurate")]
    pub upload_detect_quality: DetectionQuality,
    /// Deliver webhooks to loopback, private and link-local addresses too (refused by
    /// default: a tenant could otherwise make the server call its own network).
    #[arg(long, env = "RIGCAL_ALLOW_PRIVATE_WEBHOOKS")]
    pub allow_private_webhooks: bool,
}

impl JobArgs {
    pub fn config(&self, workers: usize) -> WorkerConfig {
        WorkerConfig {
            workers,
            lease: Duration::from_secs(self.lease_seconds),
            max_image_pixels: self.max_image_pixels,
            upload_detect_quality: self.upload_detect_quality,
            webhooks: rigcal_service::webhooks::WebhookConfig {
                allow_private: self.allow_private_webhooks,
                ..Default::default()
            },
            ..WorkerConfig::default()
        }
    }
}

/// Workers only, on the same database as a `serve` (several may run).
#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    store: StoreArgs,
    #[arg(long, env = "RIGCAL_WORKERS", value_parser = RangedU64ValueParser::<usize>::new().range(1..=64),
          default_value_t = WorkerConfig::default().workers)]
    workers: usize,
    #[command(flatten)]
    job: JobArgs,
}

pub fn run(a: Args) -> Result<i32> {
    super::runtime()?.block_on(run_standalone(&a.store.location(), a.job.config(a.workers)))?;
    Ok(0)
}
