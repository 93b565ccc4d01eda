//! The dashboard end to end in real headless Chromium (Debian's `chromium`, driven by
//! `playwright-core` from `tests/browser`, see `tests/browser/dashboard.mjs`).
//!
//! This side starts the real servers and prepares their data; the browser script does
//! what an operator does and checks what the page shows against the API. The script
//! prints `START_WORKER` once it has seen the uploaded job queued on the page: only
//! then is a worker started, so "queued → succeeded without reload" is really watched.
//!
//! Needs `chromium` (or `RIGCAL_CHROMIUM`), `node` and `npm ci --prefix tests/browser`;
//! `.ci/run` installs them. Without them the test fails and says what is missing, unless
//! `RIGCAL_SKIP_BROWSER=1` is set deliberately.

mod common;

use common::*;
use rigcal_service::store::db::sql;
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn browser_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/browser")
}

/// What the browser test needs, or why it cannot run.
fn prerequisites() -> Result<String, String> {
    let chromium = std::env::var("RIGCAL_CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    if !Path::new(&chromium).exists() {
        return Err(format!("{chromium} not found (apt-get install chromium)"));
    }
    if Command::new("node").arg("--version").output().is_err() {
        return Err("node not found".into());
    }
    if !browser_dir().join("node_modules/playwright-core").exists() {
        return Err("playwright-core not installed (npm ci --prefix tests/browser)".into());
    }
    Ok(chromium)
}

struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// 10 000 jobs of one tenant over 30 days, in one transaction (the API would take
/// minutes to accept that many): statuses, vehicles and methods mixed, finished ones
/// with a residual RMS. Returns how many of them are `failed`.
async fn fill_with_jobs(dir: &Path, tenant: &str, n: usize) -> i64 {
    let store = open_store(dir).await;
    let t = store.ensure_tenant(tenant).await.unwrap();
    let session = store
        .insert_session(&t, Some("fleet-0"), "motion", "{}", None)
        .await
        .unwrap();
    let now = rigcal_service::store::now_ms();
    let statuses = ["succeeded", "succeeded", "degraded", "failed", "succeeded"];
    let mut failed = 0;
    let mut tx = store.db.begin().await.unwrap();
    for k in 0..n {
        let status = statuses[k % statuses.len()];
        failed += (status == "failed") as i64;
        let created = now - (k as i64) * 259_200; // 30 days over 10 000 jobs
        tx.execute(sql("INSERT INTO jobs (id, tenant_id, session_id, vehicle_id, method, options, status, progress, attempts, max_attempts, run_after, residual_rms_px, worst_sigma_translation_m, worst_sigma_rotation_deg, created_at, started_at, finished_at) VALUES ($1, $2, $3, $4, $5, '{}', $6, 1, 1, 3, $7, $8, $9, $10, $11, $12, $13)")
            .bind(uuid::Uuid::new_v4().to_string())
            .bind(&t.id)
            .bind(&session.id)
            .bind(format!("fleet-{}", k % 37))
            .bind(if k % 9 == 0 { "vanishing" } else { "motion" })
            .bind(status)
            .bind(created)
            .bind((status != "failed").then_some(0.3 + (k % 50) as f64 * 0.02))
            .bind((status != "failed").then_some(0.001))
            .bind((status != "failed").then_some(0.02))
            .bind(created)
            .bind(created + 1000)
            .bind(created + 4000))
            .await
            .unwrap();
    }
    tx.commit().await.unwrap();
    failed
}

/// Vehicle model `rig-e2e` (the lebraly-5.1 design rig) and eight calibrated vehicles of
/// it: seven mounted within 2 mm / 0.1° of design, one with cam2 turned 2°. Returns the
/// knocked vehicle and its job.
async fn fill_fleet(c: &reqwest::Client, s: &Server) -> (String, String) {
    use rigcal_core::geometry::Pose;
    let model = design_rig_model("lebraly-5.1", [1.9, 0.0, 1.4]);
    let r = c
        .put(s.url("/v1/vehicle-models/rig-e2e"))
        .json(&model)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    let mut jobs = Vec::new();
    for i in 0..8u64 {
        let x = i as f64;
        let delta = if i == 5 {
            Pose::from_rotvec(
                nalgebra::Vector3::new(0.0, 2f64.to_radians(), 0.0),
                nalgebra::Vector3::zeros(),
            )
        } else {
            Pose::from_rotvec(
                nalgebra::Vector3::new(x.cos(), (1.7 * x).sin(), (2.9 * x).cos())
                    * 0.1f64.to_radians(),
                nalgebra::Vector3::new(x.sin(), (1.3 * x).cos(), (2.1 * x).sin()) * 2e-3,
            )
        };
        let mounting = [("cam2".to_string(), delta)].into_iter().collect();
        let (m, _) =
            rigcal_synth::generate_mounted("lebraly-5.1", 40 + i, 0.03, &mounting).unwrap();
        let mut v = serde_json::to_value(&m).unwrap();
        v["vehicle_id"] = json!(format!("LINE-{i:02}"));
        v["vehicle_model"] = json!("rig-e2e");
        let session = create_session(c, s, &v).await;
        jobs.push(
            submit(c, s, session["id"].as_str().unwrap()).await["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    for id in &jobs {
        let j = wait_job(c, s, id, Duration::from_secs(120)).await;
        assert_eq!(j["status"], "succeeded", "{j}");
    }
    ("LINE-05".into(), jobs[5].clone())
}

async fn post_session(c: &reqwest::Client, s: &Server, ct: &str, body: Vec<u8>) -> Value {
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", ct)
        .body(body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    r.json().await.unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn dashboard_end_to_end_in_headless_chromium() {
    let chromium = match prerequisites() {
        Ok(c) => c,
        Err(why) if std::env::var("RIGCAL_SKIP_BROWSER").as_deref() == Ok("1") => {
            eprintln!("SKIPPED (RIGCAL_SKIP_BROWSER=1): {why}");
            return;
        }
        Err(why) => panic!("the browser test cannot run: {why}; .ci/run installs everything (or set RIGCAL_SKIP_BROWSER=1 to skip it deliberately)"),
    };
    let artifacts = Path::new(env!("CARGO_TARGET_TMPDIR")).join("dashboard-artifacts");
    let _ = std::fs::remove_dir_all(&artifacts);
    std::fs::create_dir_all(&artifacts).unwrap();

    // The factory's server: API only, the worker comes when the page has seen "queued".
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "factory");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    // Queued before the browser arrives: an earlier calibration of the vehicle (for the
    // drift chart), a singular planar drive, and a session whose images hold no tags.
    let earlier = create_session(&c, &s, &synth_session("lebraly-5.1", 7, 0.3, "VIN-E2E")).await;
    let earlier_job = submit(&c, &s, earlier["id"].as_str().unwrap()).await;
    let planar = create_session(&c, &s, &synth_session("car-planar", 3, 0.5, "VIN-PLANAR")).await;
    let planar_job = submit(&c, &s, planar["id"].as_str().unwrap()).await;
    let blank = image_session(1, 32, 24);
    let archive = tar_archive(&[
        ("session.json", serde_json::to_vec(&blank).unwrap()),
        ("front/0000.png", png(32, 24, 1)),
        ("rear/0000.png", png(32, 24, 2)),
    ]);
    let blank = post_session(&c, &s, "application/x-tar", archive).await;
    let failed_job = submit(&c, &s, blank["id"].as_str().unwrap()).await;
    // What the operator uploads through the form.
    let upload = artifacts.join("session-upload.tar");
    let manifest = synth_session("lebraly-5.1", 8, 0.3, "VIN-E2E");
    std::fs::write(
        &upload,
        tar_archive(&[(
            "capture/session.json",
            serde_json::to_vec(&manifest).unwrap(),
        )]),
    )
    .unwrap();

    // The fleet's server: 10 000 jobs.
    let big_dir = tempfile::tempdir().unwrap();
    let t = Instant::now();
    let failed = fill_with_jobs(big_dir.path(), "fleet", 10_000).await;
    eprintln!("inserted 10000 jobs in {:.1} s", t.elapsed().as_secs_f64());
    let big_key = api_key(big_dir.path(), "fleet");
    let big = Server::start(big_dir.path(), &["--workers", "0"]);

    // A vehicle model's fleet: eight vehicles, one with its cam2 bracket turned 2°.
    let fleet_dir = tempfile::tempdir().unwrap();
    let fleet_key = api_key(fleet_dir.path(), "line");
    let fleet = Server::start(fleet_dir.path(), &["--workers", "2"]);
    let (knocked, knocked_job) = fill_fleet(&client(&fleet_key), &fleet).await;

    let config = json!({
        "chromium": chromium,
        "base": s.base,
        "key": key,
        "upload": upload,
        "vehicle": "VIN-E2E",
        "earlier_job": earlier_job["id"],
        "planar_job": planar_job["id"],
        "failed_job": failed_job["id"],
        "big": {"base": big.base, "key": big_key, "jobs": 10_000, "failed": failed},
        "fleet": {"base": fleet.base, "key": fleet_key, "model": "rig-e2e", "knocked": knocked, "knocked_job": knocked_job, "vehicles": 8},
        "artifacts": artifacts,
    });
    let mut node = KillOnDrop(
        Command::new("node")
            .arg(browser_dir().join("dashboard.mjs"))
            .env("RIGCAL_E2E", config.to_string())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn node"),
    );
    let stdout = node.0.stdout.take().unwrap();
    let mut worker: Option<KillOnDrop> = None;
    let deadline = Instant::now() + Duration::from_secs(600);
    for line in BufReader::new(stdout).lines() {
        let line = line.unwrap();
        println!("browser: {line}");
        if line.trim() == "START_WORKER" && worker.is_none() {
            worker = Some(KillOnDrop(
                rigcal(dir.path())
                    .args(["worker", "--data-dir"])
                    .arg(dir.path())
                    .env("RUST_LOG", "warn")
                    .spawn()
                    .expect("spawn rigcal worker"),
            ));
        }
        assert!(
            Instant::now() < deadline,
            "browser test took over 10 minutes"
        );
    }
    let status = node.0.wait().unwrap();
    assert!(
        status.success(),
        "the browser test failed ({status}); screenshots in {}",
        artifacts.display()
    );
    assert!(
        worker.is_some(),
        "the page never showed the uploaded job queued"
    );
    for shot in [
        "01-key-form",
        "03-jobs-succeeded",
        "04-job",
        "05-planar",
        "09-jobs-10000",
    ] {
        assert!(
            artifacts.join(format!("{shot}.png")).exists(),
            "screenshot {shot} missing"
        );
    }
}
