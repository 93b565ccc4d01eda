//! Crash safety: `kill -9` the server mid-job, start it again on the same data directory.
//! Every job ends `succeeded` exactly once (one result, one terminal event), no
//! acknowledged upload is missing, and the database passes `PRAGMA integrity_check`.

mod common;

use common::*;
use serde_json::Value;
use std::time::Duration;

#[tokio::test]
async fn kill_9_mid_job_loses_nothing_and_finishes_every_job_once() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let c = client(&key);
    let args = ["--workers", "1", "--lease-seconds", "2"];
    let mut s = Server::start(dir.path(), &args);

    // Acknowledged uploads before the crash.
    let img = create_session(&c, &s, &image_session(3, 40, 30)).await;
    let img_id = img["id"].as_str().unwrap().to_string();
    let mut acked = Vec::new();
    for k in 0..3 {
        for (cam, seed) in [("front", 10), ("rear", 20)] {
            let r = c
                .put(s.url(&format!("/v1/sessions/{img_id}/images/{cam}/{k}")))
                .body(png(40, 30, seed + k as u8))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 200);
            acked.push(
                r.json::<Value>().await.unwrap()["sha256"]
                    .as_str()
                    .unwrap()
                    .to_string(),
            );
        }
    }
    // Jobs long enough (a 16-pose loop, several seconds each) to be killed mid-way.
    let mut jobs = Vec::new();
    for seed in 0..3 {
        let sess = create_session(
            &c,
            &s,
            &synth_session("car-planar-loop", seed, 0.0, "car-c"),
        )
        .await;
        jobs.push(
            submit(&c, &s, sess["id"].as_str().unwrap()).await["id"]
                .as_str()
                .unwrap()
                .to_string(),
        );
    }
    // Wait until a job is past its first stage, then kill -9. Any of the three will do
    // (one worker runs them in turn): on a loaded machine a poll can take longer than a
    // whole job, and the first may finish between two polls.
    let killed = wait_any_running_past_detection(&c, &s, &jobs).await;
    s.kill9();

    let s = Server::start(dir.path(), &args);
    let c = client(&key);
    for id in &jobs {
        let j = wait_job(&c, &s, id, Duration::from_secs(240)).await;
        assert_eq!(j["status"], "succeeded", "{j}");
    }
    let killed_job = get_job(&c, &s, &killed).await;
    assert_eq!(
        killed_job["attempts"], 2,
        "re-claimed after the lease expired: {killed_job}"
    );
    let sess: Value = c
        .get(s.url(&format!("/v1/sessions/{img_id}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(sess["images_received"], 6);
    for sha in &acked {
        let bytes = read_blob(dir.path(), sha)
            .await
            .expect("acknowledged blob present");
        assert_eq!(&rigcal_service::store::blob::sha256_hex(&bytes), sha);
    }
    drop(s);

    let store = open_store(dir.path()).await;
    assert_eq!(store.integrity_check().await.unwrap(), "ok");
    for id in &jobs {
        assert_eq!(finished_once(&store, id).await, (1, 1), "job {id}");
    }
}

#[tokio::test]
async fn a_separate_worker_process_runs_the_jobs_of_an_api_only_server() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let c = client(&key);
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let mut worker = rigcal(dir.path())
        .args(["worker", "--workers", "1", "--data-dir"])
        .arg(dir.path())
        .env("RUST_LOG", "warn")
        .spawn()
        .unwrap();
    let sess = create_session(&c, &s, &synth_session("lebraly-5.1", 5, 0.3, "car-w")).await;
    let job = submit(&c, &s, sess["id"].as_str().unwrap()).await;
    let done = wait_job(&c, &s, job["id"].as_str().unwrap(), Duration::from_secs(60)).await;
    let _ = worker.kill();
    let _ = worker.wait();
    assert_eq!(done["status"], "succeeded", "{done}");
}
