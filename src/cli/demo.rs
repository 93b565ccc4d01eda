//! `rigcal demo`: the newcomer path. Starts the service on 127.0.0.1 without API keys,
//! submits the bundled sample session over HTTP like any client, waits for the job,
//! prints the extrinsics and the dashboard URL.

use anyhow::{anyhow, Context};
use rigcal_service::api::{start, ServeConfig};
use rigcal_service::store::Location;
use serde_json::Value;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A synthetic two-camera rig (Lébraly §5.1: opposite-facing cameras, general motion,
/// 0.5 px noise), vehicle `demo-car-001`.
pub const SAMPLE_SESSION: &str = include_str!("../../examples/sessions/lebraly-5.1.json");

/// Newcomer path: start the service, submit the bundled sample session, wait, print the
/// extrinsics and the dashboard URL (then keep serving unless --exit).
#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value = "rigcal-demo")]
    data_dir: PathBuf,
    #[arg(long, default_value = "127.0.0.1:8080")]
    bind: String,
    /// Stop after printing the summary instead of serving the dashboard.
    #[arg(long)]
    exit: bool,
}

pub fn run(a: Args) -> anyhow::Result<i32> {
    super::runtime()?.block_on(serve_sample(&a.data_dir, &a.bind, a.exit))?;
    Ok(0)
}

async fn serve_sample(data_dir: &Path, bind: &str, exit: bool) -> anyhow::Result<()> {
    let addr: SocketAddr = bind
        .parse()
        .map_err(|_| anyhow!("--bind: an address such as 127.0.0.1:8080, got {bind:?}"))?;
    if !addr.ip().is_loopback() {
        return Err(anyhow!(
            "--bind: the demo runs without API keys and only listens on a loopback address, got {bind}"
        ));
    }
    let cfg = ServeConfig {
        bind: bind.to_string(),
        store: Location::new(data_dir, None, None),
        insecure_no_auth: true,
        ..ServeConfig::default()
    };
    let (addr, server) = start(cfg).await?;
    let server = tokio::spawn(server);
    let base = format!("http://{addr}");
    let http = reqwest::Client::new();
    println!(
        "rigcal demo: service on {base} (data in {})",
        data_dir.display()
    );
    let session: Value = http
        .post(format!("{base}/v1/sessions"))
        .header("content-type", "application/json")
        .body(SAMPLE_SESSION)
        .send()
        .await?
        .error_for_status()
        .context("creating the sample session")?
        .json()
        .await?;
    let sid = session["id"].as_str().unwrap_or_default().to_string();
    println!(
        "session {sid}: capture check says {}",
        session["capture_check"]["verdict"].as_str().unwrap_or("-")
    );
    let job: Value = http
        .post(format!("{base}/v1/jobs"))
        .json(&serde_json::json!({"session_id": sid}))
        .send()
        .await?
        .error_for_status()
        .context("submitting the job")?
        .json()
        .await?;
    let jid = job["id"].as_str().unwrap_or_default().to_string();
    println!("job {jid} queued");
    let mut last_stage = String::new();
    let status = loop {
        let j: Value = http
            .get(format!("{base}/v1/jobs/{jid}"))
            .send()
            .await?
            .error_for_status()?
            .json()
            .await?;
        let stage = j["stage"].as_str().unwrap_or("").to_string();
        if !stage.is_empty() && stage != last_stage {
            println!("  stage {stage}");
            last_stage = stage;
        }
        let status = j["status"].as_str().unwrap_or("").to_string();
        if ["succeeded", "degraded", "failed", "cancelled"].contains(&status.as_str()) {
            break status;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let doc: Value = http
        .get(format!("{base}/v1/jobs/{jid}/result"))
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    println!("\njob {jid}: {status}");
    for r in doc["reasons"].as_array().into_iter().flatten() {
        println!(
            "  reason {}: {}",
            r["code"].as_str().unwrap_or(""),
            r["message"].as_str().unwrap_or("")
        );
    }
    println!(
        "\n{:<8} {:>26} {:>26} {:>10} {:>10}",
        "camera", "translation (mm)", "roll/pitch/yaw (deg)", "σt (mm)", "σR (deg)"
    );
    for e in doc["extrinsics"].as_array().into_iter().flatten() {
        let v = |k: &str, i: usize| e[k][i].as_f64().unwrap_or(f64::NAN);
        let sig = |k: &str, scale: f64| {
            (0..3)
                .filter_map(|i| e[k][i].as_f64())
                .fold(0.0f64, f64::max)
                * scale
        };
        println!(
            "{:<8} {:>8.1} {:>8.1} {:>8.1} {:>8.3} {:>8.3} {:>8.3} {:>10.2} {:>10.4}",
            e["camera"].as_str().unwrap_or(""),
            v("translation", 0) * 1e3,
            v("translation", 1) * 1e3,
            v("translation", 2) * 1e3,
            v("rpy_deg", 0),
            v("rpy_deg", 1),
            v("rpy_deg", 2),
            sig("sigma_translation_m", 1e3),
            sig("sigma_rotation_deg", 1.0),
        );
    }
    if let Some(r) = doc["residuals"].as_object() {
        println!(
            "\nresiduals: RMS {:.3} px, p95 {:.3} px, {} inliers, {} outliers",
            r["rms"].as_f64().unwrap_or(f64::NAN),
            r["p95"].as_f64().unwrap_or(f64::NAN),
            r["inliers"],
            r["outliers"]
        );
    }
    println!(
        "\ndashboard: {base}/   API reference: {base}/docs   result: {base}/v1/jobs/{jid}/result"
    );
    if exit {
        server.abort();
        return Ok(());
    }
    println!("serving until Ctrl-C");
    server.await??;
    Ok(())
}
