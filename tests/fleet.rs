//! Many processes on one store, as a fleet deployment runs them: two API replicas and
//! three worker processes (on PostgreSQL + S3 in the remote run of scripts/test.sh, on
//! one SQLite file otherwise). Jobs go in through both replicas; a worker is `kill -9`ed
//! mid-job and a replica restarted; every job still ends exactly once with the result a
//! single process gives, uploads through one replica are read through the other, and a
//! job's events reach a client of the replica that did not run it. A worker told to stop
//! (SIGTERM) finishes or gives back its job and exits within its lease.

mod common;

use common::*;
use rigcal_service::store::db::sql;
use serde_json::Value;
use std::process::Child;
use std::time::{Duration, Instant};

struct Worker(Child);

impl Worker {
    fn start(dir: &std::path::Path, lease_seconds: &str) -> Worker {
        Worker(
            rigcal(dir)
                .args(["worker", "--workers", "1", "--lease-seconds", lease_seconds])
                .arg("--data-dir")
                .arg(dir)
                .env("RUST_LOG", "warn")
                .spawn()
                .expect("spawn rigcal worker"),
        )
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The server-sent events of job `id` on `s`, until the stream ends.
async fn job_events(c: &reqwest::Client, s: &Server, id: &str) -> Vec<Value> {
    let mut r = c
        .get(s.url(&format!("/v1/jobs/{id}/events")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let mut text = String::new();
    let t = Instant::now();
    while let Some(chunk) = tokio::time::timeout(Duration::from_secs(120), r.chunk())
        .await
        .expect("event stream stalled")
        .unwrap()
    {
        text.push_str(&String::from_utf8_lossy(&chunk));
        assert!(t.elapsed() < Duration::from_secs(180), "stream never ended");
    }
    text.lines()
        .filter_map(|l| l.strip_prefix("data:"))
        .map(|d| serde_json::from_str(d.trim()).unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn replicas_and_workers_on_one_store_finish_every_job_exactly_once() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "fleet");
    let c = client(&key);
    let api = ["--workers", "0"];
    let a = Server::start(dir.path(), &api);
    let mut b = Server::start(dir.path(), &api);
    let mut workers: Vec<Worker> = (0..3).map(|_| Worker::start(dir.path(), "2")).collect();

    // An upload acknowledged by A is there for B.
    let img = create_session(&c, &a, &image_session(1, 40, 30)).await;
    let img_id = img["id"].as_str().unwrap();
    for (cam, seed) in [("front", 1u8), ("rear", 2)] {
        let r = c
            .put(a.url(&format!("/v1/sessions/{img_id}/images/{cam}/0")))
            .body(png(40, 30, seed))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);
    }
    let seen_by_b = get_json(&c, &b, &format!("/v1/sessions/{img_id}")).await;
    assert_eq!(seen_by_b["images_received"], 2, "{seen_by_b}");

    // 30 jobs through both replicas: three slow ones (a 16-pose loop, seconds each) to be
    // caught mid-way, the rest quick; the same sessions for many jobs, so their results
    // must agree.
    let slow = synth_session("car-planar-loop", 0, 0.0, "car-slow");
    let quick = synth_session("lebraly-5.1", 3, 0.3, "car-quick");
    let mut jobs = Vec::new();
    for k in 0..30 {
        let s = if k % 2 == 0 { &a } else { &b };
        let manifest = if k % 10 == 0 { &slow } else { &quick };
        let sess = create_session(&c, s, manifest).await;
        let job = submit(&c, s, sess["id"].as_str().unwrap()).await;
        jobs.push((k % 10 == 0, job["id"].as_str().unwrap().to_string()));
    }
    // kill -9 the worker that runs a slow job, mid-stage; restart replica B.
    // Any of the three slow jobs will do: on a loaded machine the first may be over
    // before the first poll.
    let slow_ids: Vec<String> = jobs
        .iter()
        .filter(|(is_slow, _)| *is_slow)
        .map(|(_, id)| id.clone())
        .collect();
    let caught = wait_any_running_past_detection(&c, &a, &slow_ids).await;
    let store = open_store(dir.path()).await;
    let owner: Option<String> = store
        .db
        .fetch_one(sql("SELECT lease_owner FROM jobs WHERE id = $1").bind(&caught))
        .await
        .unwrap()
        .get(0)
        .unwrap();
    // Worker names are HOST/PID/INDEX/UUID.
    let owner = owner.unwrap_or_default();
    let victim = workers
        .iter()
        .position(|w| owner.contains(&format!("/{}/", w.0.id())))
        .unwrap_or(0);
    workers.remove(victim);
    b.kill9();
    let b = Server::start(dir.path(), &api);

    // A client of A follows a job submitted through B, run by a worker process.
    let followed = jobs[1].1.clone();
    let events = {
        let (c, a) = (c.clone(), &a);
        job_events(&c, a, &followed).await
    };
    assert!(
        events
            .last()
            .is_some_and(|e| e["kind"] == "status" && e["status"] == "succeeded"),
        "{events:?}"
    );
    assert!(events.iter().any(|e| e["kind"] == "stage"), "{events:?}");

    let mut quick_results = Vec::new();
    let mut slow_results = Vec::new();
    for (k, (is_slow, id)) in jobs.iter().enumerate() {
        let s = if k % 2 == 0 { &a } else { &b };
        let j = wait_job(&c, s, id, Duration::from_secs(300)).await;
        assert_eq!(j["status"], "succeeded", "{j}");
        let r = get_json(&c, s, &format!("/v1/jobs/{id}/result")).await;
        if *is_slow {
            slow_results.push(without_timings(r));
        } else {
            quick_results.push(without_timings(r));
        }
    }
    for (_, id) in &jobs {
        assert_eq!(finished_once(&store, id).await, (1, 1), "job {id}");
    }
    // The same answer as one process gives (`rigcal calibrate`), whatever ran the job.
    for (manifest, results) in [(&quick, &quick_results), (&slow, &slow_results)] {
        let path = dir.path().join("session.json");
        std::fs::write(&path, serde_json::to_vec(manifest).unwrap()).unwrap();
        let out = std::process::Command::new(BIN)
            .arg("calibrate")
            .arg(&path)
            .output()
            .unwrap();
        let single = without_timings(serde_json::from_slice(&out.stdout).unwrap());
        for r in results {
            assert_eq!(r, &single);
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_worker_told_to_stop_gives_back_or_finishes_its_job_within_the_lease() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "fleet");
    let c = client(&key);
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let lease = 20;
    let mut w = Worker::start(dir.path(), &lease.to_string());
    let sess = create_session(&c, &s, &synth_session("car-planar-loop", 1, 0.0, "car-t")).await;
    let id = submit(&c, &s, sess["id"].as_str().unwrap()).await["id"]
        .as_str()
        .unwrap()
        .to_string();
    wait_any_running_past_detection(&c, &s, std::slice::from_ref(&id)).await;
    let t = Instant::now();
    assert!(std::process::Command::new("kill")
        .args(["-TERM", &w.0.id().to_string()])
        .status()
        .unwrap()
        .success());
    let code = loop {
        if let Some(st) = w.0.try_wait().unwrap() {
            break st;
        }
        assert!(
            t.elapsed() < Duration::from_secs(lease),
            "the worker outlived its lease after SIGTERM"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert!(code.success(), "{code:?}");
    let j = get_json(&c, &s, &format!("/v1/jobs/{id}")).await;
    assert!(
        j["status"] == "queued" || j["status"] == "succeeded",
        "neither given back nor finished: {j}"
    );
    // Another worker takes it at once (no lease to wait for), and the attempt the
    // stopped worker gave back is not counted.
    let _w2 = Worker::start(dir.path(), &lease.to_string());
    let done = wait_job(&c, &s, &id, Duration::from_secs(120)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    if j["status"] == "queued" {
        let events = job_events(&c, &s, &id).await;
        assert!(
            events.iter().any(|e| e["status"] == "queued"
                && e["message"]
                    .as_str()
                    .is_some_and(|m| m.contains("shut down"))),
            "the give-back is recorded: {events:?}"
        );
        eprintln!("the stopped worker gave its job back");
    }
    assert_eq!(done["attempts"], 1, "{done}");
    assert!(
        t.elapsed() < Duration::from_secs(lease + 60),
        "re-run waited for the lease"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn replicas_migrating_a_new_database_together_apply_each_migration_once() {
    let dir = tempfile::tempdir().unwrap();
    let migrators: Vec<_> = (0..4)
        .map(|_| {
            rigcal(dir.path())
                .arg("migrate")
                .arg("--data-dir")
                .arg(dir.path())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for m in migrators {
        let out = m.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let store = open_store(dir.path()).await;
    let applied: Vec<i64> = store
        .db
        .fetch_all(sql("SELECT version FROM _sqlx_migrations ORDER BY version"))
        .await
        .unwrap()
        .iter()
        .map(|r| r.get(0).unwrap())
        .collect();
    // Every migration of the tree (both backends have the same versions), once each.
    let mut want: Vec<i64> =
        std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/migrations/sqlite"))
            .unwrap()
            .filter_map(|e| {
                let name = e.unwrap().file_name().into_string().unwrap();
                name.split('_').next()?.parse().ok()
            })
            .collect();
    want.sort_unstable();
    assert!(want.len() >= 6, "{want:?}");
    assert_eq!(applied, want);
}
