//! `rigcal jobs`: a tenant's jobs on a running service — list, show, cancel.

use super::client::{Client, ServerArgs};
use anyhow::Result;
use reqwest::Method;

#[derive(clap::Subcommand)]
pub enum Command {
    /// The newest jobs: id, status, stage, vehicle, created, residual RMS.
    List {
        #[command(flatten)]
        server: ServerArgs,
        /// Only jobs of this status (queued, running, succeeded, degraded, failed, cancelled).
        #[arg(long)]
        status: Option<String>,
        /// Only this vehicle's jobs.
        #[arg(long)]
        vehicle: Option<String>,
        #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(1..=500))]
        limit: u32,
    },
    /// One job as JSON (status, stage, attempts, error, acceptance, links).
    Show {
        id: String,
        #[command(flatten)]
        server: ServerArgs,
    },
    /// Cancel a queued job at once, or a running one at its next stage.
    Cancel {
        id: String,
        #[command(flatten)]
        server: ServerArgs,
    },
}

pub fn run(c: Command) -> Result<i32> {
    let rt = super::runtime()?;
    match c {
        Command::List {
            server,
            status,
            vehicle,
            limit,
        } => {
            let client = Client::new(&server)?;
            let mut query = vec![("limit", limit.to_string())];
            query.extend(status.map(|s| ("status", s)));
            query.extend(vehicle.map(|v| ("vehicle_id", v)));
            let query: Vec<String> = query
                .iter()
                .map(|(k, v)| format!("{k}={}", encode(v)))
                .collect();
            let path = format!("/v1/jobs?{}", query.join("&"));
            let page =
                rt.block_on(client.json("listing jobs", client.request(Method::GET, &path)))?;
            println!(
                "{:<36}  {:<10}  {:<14}  {:<16}  {:<24}  rms (px)",
                "id", "status", "stage", "vehicle", "created"
            );
            for j in page["jobs"].as_array().into_iter().flatten() {
                let s = |k: &str| j[k].as_str().unwrap_or("-").to_string();
                println!(
                    "{:<36}  {:<10}  {:<14}  {:<16}  {:<24}  {}",
                    s("id"),
                    s("status"),
                    s("stage"),
                    s("vehicle_id"),
                    s("created_at"),
                    j["residual_rms_px"]
                        .as_f64()
                        .map_or("-".into(), |r| format!("{r:.3}"))
                );
            }
            Ok(0)
        }
        Command::Show { id, server } => {
            let client = Client::new(&server)?;
            let path = format!("/v1/jobs/{}", encode(&id));
            let j =
                rt.block_on(client.json("reading the job", client.request(Method::GET, &path)))?;
            println!("{}", serde_json::to_string_pretty(&j)?);
            Ok(0)
        }
        Command::Cancel { id, server } => {
            let client = Client::new(&server)?;
            let path = format!("/v1/jobs/{}", encode(&id));
            let j = rt.block_on(
                client.json("cancelling the job", client.request(Method::DELETE, &path)),
            )?;
            eprintln!(
                "job {id}: {}",
                match j["status"].as_str() {
                    Some("cancelled") => "cancelled",
                    _ => "cancel requested; it stops at its next stage",
                }
            );
            Ok(0)
        }
    }
}

/// Percent-encoded for one path segment or query value (job ids are UUIDs; anything
/// else is escaped, not spliced).
fn encode(id: &str) -> String {
    id.bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'-' | b'_' | b'.' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}
