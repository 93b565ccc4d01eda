//! The service: the store and blobs, the job queue and its workers, the HTTP API and the
//! dashboard. The engine underneath does no I/O of its own.

pub mod api;
pub mod dashboard;
pub mod fleet;
pub mod jobs;
pub mod signals;
pub mod store;
pub mod telemetry;
pub mod webhooks;
