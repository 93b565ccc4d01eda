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
    super::client::print_summary(&doc);
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
