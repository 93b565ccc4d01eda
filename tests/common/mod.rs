//! A real `rigcal serve` process on a random port with its own temp data directory,
//! talked to over HTTP with reqwest (the way clients do).
//!
//! The backend is the embedded default (SQLite and blobs in the data directory) unless
//! `RIGCAL_TEST_POSTGRES` (a PostgreSQL server URL, no database) and
//! `RIGCAL_TEST_S3_BUCKET` (an existing bucket; the `AWS_*` settings in the environment
//! reach it) are set, as `scripts/test.sh` does for its second run: then every data
//! directory gets its own database and key prefix, and every `rigcal` the tests start
//! is pointed at them through `RIGCAL_DATABASE_URL` and `RIGCAL_BLOB_URL`.
#![allow(dead_code)]

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_rigcal");

/// The PostgreSQL server and S3 bucket of the remote-backend run, if this is one.
pub fn remote_backend() -> Option<(String, String)> {
    let pg = std::env::var("RIGCAL_TEST_POSTGRES").ok()?;
    let bucket = std::env::var("RIGCAL_TEST_S3_BUCKET").ok()?;
    Some((pg.trim_end_matches('/').to_string(), bucket))
}

pub fn is_remote() -> bool {
    remote_backend().is_some()
}

/// The database URL and blob URL that stand for `data_dir` in the remote run (its
/// database created on first use), or `None` for the embedded default.
pub fn store_urls(data_dir: &Path) -> Option<(String, String)> {
    use sha2::Digest;
    static CREATED: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
    let (pg, bucket) = remote_backend()?;
    let name = format!(
        "t_{}",
        &hex::encode(sha2::Sha256::digest(data_dir.display().to_string()))[..16]
    );
    let mut created = CREATED.lock().unwrap_or_else(|e| e.into_inner());
    if !created.contains(&name) {
        let out = Command::new("psql")
            .arg(format!("{pg}/postgres"))
            .args(["-qXc", &format!("CREATE DATABASE {name}")])
            .output()
            .expect("run psql (scripts/test.sh installs PostgreSQL)");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success() || err.contains("already exists"),
            "creating database {name}: {err}"
        );
        created.push(name.clone());
    }
    Some((format!("{pg}/{name}"), format!("s3://{bucket}/{name}")))
}

/// `rigcal` on the store of `data_dir` (the remote one in the remote run).
pub fn rigcal(data_dir: &Path) -> Command {
    let mut c = Command::new(BIN);
    if let Some((db, blobs)) = store_urls(data_dir) {
        c.env("RIGCAL_DATABASE_URL", db)
            .env("RIGCAL_BLOB_URL", blobs);
    }
    c
}

/// The store of `data_dir`, opened in the test process.
pub async fn open_store(data_dir: &Path) -> rigcal_service::store::Store {
    let urls = store_urls(data_dir);
    let at = rigcal_service::store::Location::new(
        data_dir,
        urls.as_ref().map(|u| u.0.as_str()),
        urls.as_ref().map(|u| u.1.as_str()),
    );
    rigcal_service::store::Store::connect(&at)
        .await
        .expect("open the test store")
}

/// A stored blob's bytes, read (and verified) through the blob store of `data_dir`.
pub async fn read_blob(data_dir: &Path, sha: &str) -> std::io::Result<Vec<u8>> {
    let blobs = open_store(data_dir).await.blobs;
    let sha = sha.to_string();
    tokio::task::spawn_blocking(move || blobs.get(&sha))
        .await
        .expect("blob read task")
}

pub struct Server {
    pub child: Child,
    pub base: String,
    pub data_dir: PathBuf,
}

/// Create an API key for `tenant` in `data_dir` with the CLI.
pub fn api_key(data_dir: &Path, tenant: &str) -> String {
    let out = rigcal(data_dir)
        .args(["apikey", "create", "--tenant", tenant, "--data-dir"])
        .arg(data_dir)
        .output()
        .expect("run rigcal apikey");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap().trim().to_string()
}

impl Server {
    /// Start `rigcal serve --bind 127.0.0.1:0 --data-dir DIR ARGS...` and wait for its
    /// "listening" line.
    pub fn start(data_dir: &Path, args: &[&str]) -> Server {
        let mut child = rigcal(data_dir)
            .args(["serve", "--bind", "127.0.0.1:0", "--data-dir"])
            .arg(data_dir)
            .args(args)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn rigcal serve");
        let stdout = child.stdout.take().unwrap();
        let mut line = String::new();
        BufReader::new(stdout)
            .read_line(&mut line)
            .expect("read listening line");
        let base = line
            .trim()
            .strip_prefix("rigcal listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
            .to_string();
        Server {
            child,
            base,
            data_dir: data_dir.to_path_buf(),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    /// SIGKILL: no chance to clean up, like a power cut of the process.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub fn client(key: &str) -> reqwest::Client {
    let mut h = reqwest::header::HeaderMap::new();
    h.insert(
        reqwest::header::AUTHORIZATION,
        format!("Bearer {key}").parse().unwrap(),
    );
    reqwest::Client::builder()
        .default_headers(h)
        .timeout(Duration::from_secs(120))
        .build()
        .unwrap()
}

/// The session `rigcal synth --preset P --seed S --noise N` writes (detections only for
/// the hall presets), for vehicle `vehicle`.
pub fn synth_session(preset: &str, seed: u64, noise: f64, vehicle: &str) -> Value {
    let mut v = if rigcal_synth::hall::PRESETS.contains(&preset) {
        let dir = tempfile::tempdir().unwrap();
        let hall = rigcal_synth::hall::hall(preset, seed, None).expect("hall preset");
        rigcal_synth::hall::write_capture(&hall, dir.path(), None, noise, seed).unwrap();
        serde_json::from_slice(&std::fs::read(dir.path().join("session.json")).unwrap()).unwrap()
    } else {
        let (m, _) = rigcal_synth::generate(preset, seed, noise).expect("preset");
        serde_json::to_value(&m).unwrap()
    };
    v["vehicle_id"] = Value::String(vehicle.into());
    v
}

/// The design rig of synthetic preset `preset` as a vehicle model (every camera's true
/// `ref_from_cam` as its nominal, 10 mm / 0.5° tolerances) with the reference camera at
/// `vehicle_ref` in the vehicle frame, axes turned from optical (z forward, y down) to a
/// vehicle's (x forward, z up).
pub fn design_rig_model(preset: &str, vehicle_ref: [f64; 3]) -> Value {
    let (_, truth) = rigcal_synth::generate(preset, 1, 0.0).expect("preset");
    let cameras: Vec<Value> = truth
        .ref_from_cam
        .iter()
        .map(|(id, p)| {
            let mut c = serde_json::json!({
                "id": id,
                "translation": [p.trans.x, p.trans.y, p.trans.z],
                "quaternion_wxyz": rigcal_core::geometry::so3::to_quaternion(&p.rot),
            });
            if *id == truth.reference_camera {
                c["translation"] = serde_json::json!([0.0, 0.0, 0.0]);
                c["quaternion_wxyz"] = serde_json::json!([1.0, 0.0, 0.0, 0.0]);
            } else {
                c["tolerance"] = serde_json::json!({"translation_mm": 10.0, "rotation_deg": 0.5});
            }
            c
        })
        .collect();
    serde_json::json!({
        "reference_camera": truth.reference_camera,
        "cameras": cameras,
        "vehicle_from_ref": {"translation": vehicle_ref, "rpy_deg": [-90.0, 0.0, -90.0]},
    })
}

/// Assert a problem+json answer with the given status and type slug; returns the body.
pub async fn expect_problem(resp: reqwest::Response, status: u16, slug: &str) -> Value {
    let got = resp.status().as_u16();
    let ct = resp
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    let body: Value = resp.json().await.unwrap_or(Value::Null);
    assert_eq!(got, status, "status of {body}");
    assert_eq!(ct, "application/problem+json", "content type of {body}");
    assert_eq!(
        body["type"],
        format!("urn:rigcal:problem:{slug}"),
        "type of {body}"
    );
    assert_eq!(body["status"], status);
    assert!(body["detail"].as_str().is_some_and(|d| !d.is_empty()));
    body
}

pub async fn create_session(c: &reqwest::Client, s: &Server, manifest: &Value) -> Value {
    let r = c
        .post(s.url("/v1/sessions"))
        .json(manifest)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    r.json().await.unwrap()
}

/// Create a session from a tar archive of `files` (path, bytes): the manifest and its
/// images in one request.
pub async fn create_archive_session(
    c: &reqwest::Client,
    s: &Server,
    files: &[(String, Vec<u8>)],
) -> Value {
    let entries: Vec<(&str, Vec<u8>)> =
        files.iter().map(|(p, b)| (p.as_str(), b.clone())).collect();
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", "application/x-tar")
        .body(tar_archive(&entries))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    r.json().await.unwrap()
}

pub async fn submit(c: &reqwest::Client, s: &Server, session_id: &str) -> Value {
    let r = c
        .post(s.url("/v1/jobs"))
        .json(&serde_json::json!({"session_id": session_id}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 202);
    r.json().await.unwrap()
}

/// `GET /v1/jobs/{id}` as JSON.
pub async fn get_job(c: &reqwest::Client, s: &Server, id: &str) -> Value {
    c.get(s.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap()
}

/// Poll `ids` until one of them is running a stage after detection, and return it: the
/// moment a test kills a worker mid-solve. Any of several jobs will do because on a
/// loaded machine one poll can take longer than a whole job.
pub async fn wait_any_running_past_detection(
    c: &reqwest::Client,
    s: &Server,
    ids: &[String],
) -> String {
    let t = Instant::now();
    loop {
        for id in ids {
            let j = get_job(c, s, id).await;
            if j["status"] == "running" && !j["stage"].is_null() && j["stage"] != "detection" {
                return id.clone();
            }
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "none of {ids:?} seen running past detection within 120 s"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Poll a job until it ends (or `timeout`).
pub async fn wait_job(c: &reqwest::Client, s: &Server, id: &str, timeout: Duration) -> Value {
    let t = Instant::now();
    loop {
        let j = get_job(c, s, id).await;
        let st = j["status"].as_str().unwrap_or("");
        if ["succeeded", "degraded", "failed", "cancelled"].contains(&st) {
            return j;
        }
        assert!(
            t.elapsed() < timeout,
            "job {id} still {st} after {timeout:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A PNG of `w`×`h` (grey, 8-bit) whose content depends on `seed`.
pub fn png(w: u32, h: u32, seed: u8) -> Vec<u8> {
    let img = image::GrayImage::from_fn(w, h, |x, y| {
        image::Luma([((x * 7 + y * 3) as u8).wrapping_add(seed)])
    });
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

/// An image session: small pinhole cameras, `frames` frames naming one image per camera.
pub fn image_session(frames: usize, w: u32, h: u32) -> Value {
    let cam = |id: &str| {
        serde_json::json!({"id": id, "model": "pinhole", "width": w, "height": h,
            "intrinsics": {"fx": 100.0, "fy": 100.0, "cx": (w as f64 - 1.0) / 2.0, "cy": (h as f64 - 1.0) / 2.0}})
    };
    let frames: Vec<Value> = (0..frames)
        .map(|k| {
            serde_json::json!({"index": k, "images": {"front": format!("front/{k:04}.png"), "rear": format!("rear/{k:04}.png")}})
        })
        .collect();
    serde_json::json!({
        "vehicle_id": "img-car",
        "reference_camera": "front",
        "cameras": [cam("front"), cam("rear")],
        "targets": [{"type": "aprilgrid", "id": "board", "rows": 6, "cols": 6, "tag_size": 0.088, "tag_spacing": 0.3, "first_id": 0}],
        "frames": frames,
    })
}

/// CRC-32 of PNG chunks (to forge a valid header declaring a huge image).
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for b in data {
        c ^= *b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

/// Submit a job for the session and wait for it to end: the finished job.
pub async fn run_job(
    c: &reqwest::Client,
    s: &Server,
    session_id: &str,
    timeout: Duration,
) -> Value {
    let job = submit(c, s, session_id).await;
    wait_job(c, s, job["id"].as_str().unwrap(), timeout).await
}

/// Send only the head of a request announcing `content_length` body bytes, then read the
/// answer: how a server that refuses an oversized body by its declared length is seen
/// without racing the upload against the refusal (a client still writing may see the
/// connection reset instead of the 413). Returns the status and the JSON body.
pub async fn head_only_request(
    s: &Server,
    method: &str,
    path: &str,
    key: &str,
    content_type: &str,
    content_length: usize,
) -> (u16, Value) {
    let addr = s.base.trim_start_matches("http://");
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {key}\r\nContent-Type: {content_type}\r\nContent-Length: {content_length}\r\nConnection: close\r\n\r\n"
    );
    let (status, _, body) = raw_request(s, head.as_bytes()).await;
    (status, body)
}

/// Write `request` as raw bytes on a new connection and read one answer (to its
/// Content-Length, or to the close). Returns the status, the response head and the
/// JSON body (`Null` when the body is not JSON).
pub async fn raw_request(s: &Server, request: &[u8]) -> (u16, String, Value) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let addr = s.base.trim_start_matches("http://");
    let mut sock = tokio::net::TcpStream::connect(addr).await.unwrap();
    // The server may answer (and close) before it has read everything.
    let _ = sock.write_all(request).await;
    let mut buf = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(30), async {
        let mut chunk = [0u8; 4096];
        loop {
            match sock.read(&mut chunk).await {
                Ok(0) | Err(_) => break,
                Ok(n) => {
                    buf.extend_from_slice(&chunk[..n]);
                    let text = String::from_utf8_lossy(&buf);
                    if let Some(i) = text.find("\r\n\r\n") {
                        let len = text[..i]
                            .lines()
                            .find_map(|l| {
                                l.to_ascii_lowercase()
                                    .strip_prefix("content-length:")
                                    .map(|v| v.trim().parse::<usize>().unwrap_or(0))
                            })
                            .unwrap_or(0);
                        if buf.len() >= i + 4 + len {
                            break;
                        }
                    }
                }
            }
        }
    })
    .await;
    assert!(read.is_ok(), "no answer within 30 s");
    let text = String::from_utf8_lossy(&buf).to_string();
    let status: u16 = text
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status line in {text:?}"));
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let body = serde_json::from_str(body).unwrap_or(Value::Null);
    (status, head.to_string(), body)
}

/// Peak resident memory of a process so far (`VmHWM`), bytes.
pub fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .expect("VmHWM in /proc/PID/status")
        * 1024
}

/// A tar archive of `(path, bytes)` entries, as a client would upload it.
pub fn tar_archive(files: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut t = tar::Builder::new(&mut out);
        for (name, bytes) in files {
            let mut h = tar::Header::new_gnu();
            h.set_size(bytes.len() as u64);
            h.set_mode(0o644);
            h.set_cksum();
            t.append_data(&mut h, name, bytes.as_slice()).unwrap();
        }
        t.finish().unwrap();
    }
    out
}

/// `GET path` → 200 and its JSON body.
pub async fn get_json(c: &reqwest::Client, s: &Server, path: &str) -> Value {
    let r = c.get(s.url(path)).send().await.unwrap();
    assert_eq!(r.status(), 200, "GET {path}");
    r.json().await.unwrap()
}

/// (results, terminal status events) of job `id`: (1, 1) when it finished exactly once.
pub async fn finished_once(store: &rigcal_service::store::Store, id: &str) -> (i64, i64) {
    use rigcal_service::store::db::sql;
    let count = |q| async move {
        store
            .db
            .fetch_one(sql(q).bind(id))
            .await
            .unwrap()
            .get::<i64>(0)
            .unwrap()
    };
    (
        count("SELECT COUNT(*) FROM results WHERE job_id = $1").await,
        count("SELECT COUNT(*) FROM job_events WHERE job_id = $1 AND kind = 'status' AND status IN ('succeeded','degraded','failed','cancelled')").await,
    )
}

/// A result document without its timings, which differ between two runs of the same
/// computation.
pub fn without_timings(mut v: Value) -> Value {
    if let Some(o) = v.as_object_mut() {
        o.remove("stages");
    }
    v
}
