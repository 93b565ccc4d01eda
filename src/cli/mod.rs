//! The `rigcal` commands, one file each: its arguments (`Args`, validated by clap where
//! a range says it) and its `run`, which returns the process exit code.

pub mod apikey;
pub mod bench;
pub mod calibrate;
pub mod compare;
pub mod demo;
pub mod detect;
pub mod serve;
pub mod synth;
pub mod worker;

use anyhow::{anyhow, Context, Result};

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
