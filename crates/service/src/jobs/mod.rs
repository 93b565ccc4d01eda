//! Jobs: the queue (claim with lease, heartbeat, retry, cancel) and the worker pool that
//! runs the pipeline off the async runtime.

pub mod acceptance;
pub mod bench;
pub mod detection;
pub mod queue;
pub mod worker;

use rigcal_core::result::DetectionQuality;
use rigcal_core::session::InputError;
use rigcal_engine::pipeline::{CalibOptions, LossKind};
use serde::{Deserialize, Serialize};

/// Options of a job as clients send them (`POST /v1/jobs {options}`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobOptions {
    /// Robust loss of the outlier pass: huber | cauchy | squared.
    #[serde(default)]
    pub loss: LossKind,
    /// Scale of the robust loss, pixels.
    #[serde(default = "default_loss_scale")]
    pub loss_scale: f64,
    /// How the images of a session are detected.
    #[serde(default)]
    pub detection: DetectionOptions,
}

/// The `detection` options of a job.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DetectionOptions {
    /// accurate | fast.
    #[serde(default)]
    pub quality: DetectionQuality,
}

fn default_loss_scale() -> f64 {
    2.0
}

impl Default for JobOptions {
    fn default() -> Self {
        Self {
            loss: LossKind::default(),
            loss_scale: default_loss_scale(),
            detection: DetectionOptions::default(),
        }
    }
}

impl JobOptions {
    /// The engine's options; errors name the field under `options.`.
    pub fn calib(&self) -> Result<CalibOptions, InputError> {
        let opts = CalibOptions::from_loss(self.loss, self.loss_scale)
            .map_err(|e| InputError::new(format!("options.{}", e.field), e.expected))?;
        Ok(CalibOptions {
            detection: self.detection.quality,
            ..opts
        })
    }
}
