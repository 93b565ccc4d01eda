//! `rigcal submit`: a capture to a running service, as an end-of-line script calls it —
//! upload (a directory with `session.json` and its images, a tar or zip of one, or a
//! `session.json` of detections), submit the job, optionally wait with the job's stages
//! shown, print the summary, write the result and its exports, and exit like
//! `rigcal calibrate` (0 succeeded, 3 degraded, 1 failed).
//!
//! Both POSTs carry an `Idempotency-Key` derived from the capture's bytes, so a script
//! that retries after a timeout (or runs twice) gets the first session and job back
//! instead of a second job; `--idempotency-key` sets another.

use super::client::{exit_code, print_summary, Client, ServerArgs};
use anyhow::{anyhow, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use reqwest::Method;
use serde_json::{json, Value};
use sha2::Digest;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Exports written beside result.json when the job gives extrinsics.
const EXPORTS: [&str; 5] = ["kalibr", "opencv", "urdf", "colmap", "ros2"];

#[derive(clap::Args)]
pub struct Args {
    /// A capture directory (session.json and the images it names), a .tar or .zip of
    /// one, or a session.json of detections.
    input: PathBuf,
    #[command(flatten)]
    server: ServerArgs,
    /// Wait for the job, show its stages, print the summary and exit with its verdict.
    #[arg(long)]
    wait: bool,
    /// With --wait: write result.json and the exports (kalibr.yaml, opencv.yaml,
    /// urdf.urdf, colmap.json, ros2.launch.xml) into this directory.
    #[arg(long, requires = "wait")]
    out: Option<PathBuf>,
    /// Seconds --wait waits before giving up (the job goes on).
    #[arg(long, default_value_t = 3600, requires = "wait")]
    timeout: u64,
    /// The Idempotency-Key of the upload (the job's is derived from it) [default: from
    /// the capture's SHA-256].
    #[arg(long)]
    idempotency_key: Option<String>,
}

/// What is uploaded: the bytes (a file on disk) and their media type.
struct Upload {
    file: tempfile::NamedTempFile,
    content_type: &'static str,
}

/// Pack or take the input as it will be uploaded.
fn prepare(input: &Path) -> Result<Upload> {
    let copy = |content_type| -> Result<Upload> {
        let mut file = tempfile::NamedTempFile::new()?;
        std::io::copy(&mut std::fs::File::open(input)?, file.as_file_mut())?;
        Ok(Upload { file, content_type })
    };
    let ext = input
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if input.is_dir() {
        if !input.join("session.json").is_file() {
            return Err(anyhow!(
                "INPUT: a capture directory with a session.json at its top, got {}",
                input.display()
            ));
        }
        let file = tempfile::NamedTempFile::new()?;
        let mut tar = tar::Builder::new(file.reopen()?);
        tar.follow_symlinks(false);
        tar.append_dir_all(".", input)?;
        tar.into_inner()?.sync_all()?;
        return Ok(Upload {
            file,
            content_type: "application/x-tar",
        });
    }
    match ext.as_deref() {
        Some("tar") => copy("application/x-tar"),
        Some("zip") => copy("application/zip"),
        Some("json") => copy("application/json"),
        _ => Err(anyhow!(
            "INPUT: a capture directory, a .tar, a .zip or a session.json, got {}",
            input.display()
        )),
    }
}

fn sha256_of(path: &Path) -> Result<String> {
    use std::io::Read;
    let mut h = sha2::Sha256::new();
    let mut f = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 64 << 10];
    loop {
        match f.read(&mut buf)? {
            0 => return Ok(hex::encode(h.finalize())),
            n => h.update(&buf[..n]),
        }
    }
}

pub fn run(a: Args) -> Result<i32> {
    let upload = prepare(&a.input).with_context(|| format!("reading {}", a.input.display()))?;
    let key = match &a.idempotency_key {
        Some(k) => k.clone(),
        None => format!("submit-{}", &sha256_of(upload.file.path())?[..40]),
    };
    let client = Client::new(&a.server)?;
    super::runtime()?.block_on(submit(&a, &client, upload, &key))
}

async fn submit(a: &Args, client: &Client, upload: Upload, key: &str) -> Result<i32> {
    let len = upload.file.as_file().metadata()?.len();
    let bar = progress(len, "upload {bar:30} {bytes}/{total_bytes} {bytes_per_sec}");
    let file = tokio::fs::File::open(upload.file.path()).await?;
    let counted = {
        let bar = bar.clone();
        // 64 KiB chunks off the disk, counted on the bar as they go; a read error ends
        // the body (the server then refuses the truncated upload).
        futures::stream::unfold(Some(file), move |f| {
            let bar = bar.clone();
            async move {
                use tokio::io::AsyncReadExt;
                let mut f = f?;
                let mut buf = vec![0u8; 64 << 10];
                match f.read(&mut buf).await {
                    Ok(0) => None,
                    Ok(n) => {
                        buf.truncate(n);
                        bar.inc(n as u64);
                        Some((Ok::<_, std::io::Error>(buf), Some(f)))
                    }
                    Err(e) => Some((Err(e), None)),
                }
            }
        })
    };
    let session = client
        .json(
            "uploading the capture",
            client
                .request(Method::POST, "/v1/sessions")
                .header("content-type", upload.content_type)
                .header("content-length", len)
                .header("idempotency-key", key)
                .body(reqwest::Body::wrap_stream(counted)),
        )
        .await?;
    bar.finish_and_clear();
    let sid = session["id"]
        .as_str()
        .ok_or_else(|| anyhow!("the server's session has no id: {session}"))?
        .to_string();
    let missing = session["images_missing"].as_array().map_or(0, Vec::len);
    eprintln!(
        "session {sid}: {} image(s) received, {missing} missing; capture check: {}",
        session["images_received"],
        session["capture_check"]["verdict"].as_str().unwrap_or("-")
    );
    let job = client
        .json(
            "submitting the job",
            client
                .request(Method::POST, "/v1/jobs")
                .header("idempotency-key", format!("{key}-job"))
                .json(&json!({"session_id": sid})),
        )
        .await?;
    let jid = job["id"]
        .as_str()
        .ok_or_else(|| anyhow!("the server's job has no id: {job}"))?
        .to_string();
    println!("job {jid}");
    if !a.wait {
        return Ok(0);
    }
    let status = follow(client, &jid, Duration::from_secs(a.timeout)).await?;
    let doc = client
        .json(
            "reading the result",
            client.request(Method::GET, &format!("/v1/jobs/{jid}/result")),
        )
        .await?;
    println!("\njob {jid}: {status}");
    print_summary(&doc);
    if let Some(dir) = &a.out {
        write_outputs(client, &jid, &doc, dir).await?;
    }
    Ok(exit_code(&status))
}

/// A progress bar of `len` steps drawn with `template` (on stderr, hidden when it is not
/// a terminal). The templates are this file's constants; should one not parse, the bar
/// is drawn in indicatif's default style rather than failing an upload over its looks.
fn progress(len: u64, template: &str) -> ProgressBar {
    let style =
        ProgressStyle::with_template(template).unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::new(len).with_style(style)
}

/// Poll the job to its end, its stage and progress on a bar; the final status.
async fn follow(client: &Client, jid: &str, timeout: Duration) -> Result<String> {
    let bar = progress(100, "job {bar:30} {pos:>3}% {msg}");
    let start = std::time::Instant::now();
    loop {
        let j = client
            .json(
                "following the job",
                client.request(Method::GET, &format!("/v1/jobs/{jid}")),
            )
            .await?;
        let status = j["status"].as_str().unwrap_or("").to_string();
        bar.set_position((j["progress"].as_f64().unwrap_or(0.0) * 100.0) as u64);
        bar.set_message(j["stage"].as_str().unwrap_or(&status).to_string());
        if !matches!(status.as_str(), "queued" | "running") {
            bar.finish_and_clear();
            return Ok(status);
        }
        if start.elapsed() > timeout {
            bar.abandon();
            return Err(anyhow!(
                "--timeout: job {jid} still {status} after {} s (it goes on; `rigcal jobs show {jid}`)",
                timeout.as_secs()
            ));
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// result.json and, when there are extrinsics, every export.
async fn write_outputs(client: &Client, jid: &str, doc: &Value, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).with_context(|| format!("writing {}", p.display()))
    };
    write("result.json", &serde_json::to_vec_pretty(doc)?)?;
    if doc["status"] == "failed" {
        eprintln!(
            "wrote result.json to {} (a failed calibration has no exports)",
            dir.display()
        );
        return Ok(());
    }
    for format in EXPORTS {
        let f: rigcal_engine::export::Format = format.parse().map_err(|e: String| anyhow!(e))?;
        let resp = client
            .send(
                &format!("exporting {format}"),
                client.request(
                    Method::GET,
                    &format!("/v1/jobs/{jid}/result?format={format}"),
                ),
            )
            .await?;
        write(&format!("{format}.{}", f.media().1), &resp.bytes().await?)?;
    }
    eprintln!(
        "wrote result.json and {} exports to {}",
        EXPORTS.len(),
        dir.display()
    );
    Ok(())
}
