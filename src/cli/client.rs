//! The HTTP client side of the CLI (`submit`, `jobs`, `demo`): one server and key, errors
//! that carry the server's problem (status, type, detail, field), and the summary of a
//! result document as the demo prints it.

use anyhow::{anyhow, Context, Result};
use serde_json::Value;

/// Where the server is and who we are, shared by the client commands.
#[derive(clap::Args, Clone, Debug)]
pub struct ServerArgs {
    /// Base URL of a `rigcal serve`, e.g. http://calib.factory.lan:8080.
    #[arg(long, env = "RIGCAL_SERVER", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// API key (`rigcal apikey create`); none for a server run with --insecure-no-auth.
    #[arg(long, env = "RIGCAL_API_KEY", hide_env_values = true)]
    pub key: Option<String>,
}

pub struct Client {
    pub http: reqwest::Client,
    base: String,
    key: Option<String>,
}

impl Client {
    pub fn new(a: &ServerArgs) -> Result<Client> {
        let base = a.server.trim_end_matches('/').to_string();
        if !(base.starts_with("http://") || base.starts_with("https://")) {
            return Err(anyhow!(
                "--server: an http:// or https:// URL, got {:?}",
                a.server
            ));
        }
        Ok(Client {
            http: reqwest::Client::new(),
            base,
            key: a.key.clone(),
        })
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    /// A request to `path` with the key attached.
    pub fn request(&self, method: reqwest::Method, path: &str) -> reqwest::RequestBuilder {
        let r = self.http.request(method, self.url(path));
        match &self.key {
            Some(k) => r.bearer_auth(k),
            None => r,
        }
    }

    /// Send and return the body of a 2xx answer; any other answer is an error that says
    /// what the server said (its problem document's detail and field).
    pub async fn send(&self, what: &str, r: reqwest::RequestBuilder) -> Result<reqwest::Response> {
        let resp = r
            .send()
            .await
            .with_context(|| format!("{what}: no answer from {}", self.base))?;
        if resp.status().is_success() {
            return Ok(resp);
        }
        let status = resp.status();
        let body = resp.text().await.unwrap_or_default();
        let problem: Value = serde_json::from_str(&body).unwrap_or(Value::Null);
        let detail = problem["detail"].as_str().unwrap_or(body.trim());
        let field = problem["field"]
            .as_str()
            .map_or(String::new(), |f| format!(" (field {f})"));
        Err(anyhow!("{what}: {status}: {detail}{field}"))
    }

    pub async fn json(&self, what: &str, r: reqwest::RequestBuilder) -> Result<Value> {
        self.send(what, r)
            .await?
            .json()
            .await
            .with_context(|| format!("{what}: the answer is not JSON"))
    }
}

/// The exit code of a finished job, as `rigcal calibrate` gives it for the same
/// verdict: 0 succeeded, 3 degraded, 1 failed or cancelled.
pub fn exit_code(status: &str) -> i32 {
    match status {
        "succeeded" => 0,
        "degraded" => 3,
        _ => 1,
    }
}

/// The verdict's reasons, the extrinsics with their σ, and the residuals.
pub fn print_summary(doc: &Value) {
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
}
