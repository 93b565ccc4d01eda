//! Jobs: the queue (claim with lease, heartbeat, retry, cancel) and the worker pool that
//! runs the pipeline off the async runtime.

pub mod acceptance;
pub mod queue;
pub mod worker;

use crate::pipeline::CalibOptions;
use crate::session::InputError;
use serde::{Deserialize, Serialize};

/// Options of a job as clients send them (`POST /v1/jobs {options}`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobOptions {
    /// Robust loss of the outlier pass: huber | cauchy | squared.
    #[serde(default = "default_loss")]
    pub loss: String,
    /// Scale of the robust loss, pixels.
    #[serde(default = "default_loss_scale")]
    pub loss_scale: f64,
}

fn default_loss() -> String {
    "huber".into()
}

fn default_loss_scale() -> f64 {
    2.0
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            loss: default_loss(),
            loss_scale: default_loss_scale(),
        }
    }
}

impl JobOptions {
    /// The engine's options; errors name the field under `options.`.
    pub fn calib(&self) -> Result<CalibOptions, InputError> {
        CalibOptions::from_loss(&self.loss, self.loss_scale)
            .map_err(|e| InputError::new(format!("options.{}", e.field), e.expected))
    }
}
