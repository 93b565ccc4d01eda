//! A factory script that retries after a timeout never creates a second session or job:
//! `Idempotency-Key` on the creating POSTs, through the real server.

mod common;

use common::*;
use serde_json::{json, Value};

async fn post(
    c: &reqwest::Client,
    s: &Server,
    path: &str,
    key: Option<&str>,
    body: &Value,
) -> reqwest::Response {
    let mut r = c.post(s.url(path)).json(body);
    if let Some(k) = key {
        r = r.header("Idempotency-Key", k);
    }
    r.send().await.unwrap()
}

async fn jobs_total(c: &reqwest::Client, s: &Server) -> u64 {
    get_json(c, s, "/v1/jobs").await["total"].as_u64().unwrap()
}

#[tokio::test]
async fn the_same_key_and_body_answer_once_and_create_once() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&api_key(dir.path(), "factory"));
    let manifest = synth_session("lebraly-5.1", 2, 0.3, "car-1");

    // Sessions: the retry gets the first answer, marked as a replay.
    let first = post(
        &c,
        &s,
        "/v1/sessions",
        Some("order-4711-session"),
        &manifest,
    )
    .await;
    assert_eq!(first.status().as_u16(), 201);
    assert!(first.headers().get("idempotent-replayed").is_none());
    let location = first.headers()["location"].clone();
    let first: Value = first.json().await.unwrap();
    let again = post(
        &c,
        &s,
        "/v1/sessions",
        Some("order-4711-session"),
        &manifest,
    )
    .await;
    assert_eq!(again.status().as_u16(), 201);
    assert_eq!(again.headers()["idempotent-replayed"], "true");
    assert_eq!(again.headers()["location"], location);
    let again: Value = again.json().await.unwrap();
    assert_eq!(again["id"], first["id"]);
    let sid = first["id"].as_str().unwrap();

    // Jobs: one job however often the submit is retried.
    let submit = json!({"session_id": sid});
    let j1: Value = post(&c, &s, "/v1/jobs", Some("order-4711-job"), &submit)
        .await
        .json()
        .await
        .unwrap();
    for _ in 0..3 {
        let r = post(&c, &s, "/v1/jobs", Some("order-4711-job"), &submit).await;
        assert_eq!(r.status().as_u16(), 202);
        let j: Value = r.json().await.unwrap();
        assert_eq!(j["id"], j1["id"]);
    }
    assert_eq!(jobs_total(&c, &s).await, 1);

    // The same key with another body, or on another route, is refused and creates nothing.
    let other = json!({"session_id": sid, "options": {"loss": "cauchy"}});
    let p = expect_problem(
        post(&c, &s, "/v1/jobs", Some("order-4711-job"), &other).await,
        422,
        "idempotency-key-reused",
    )
    .await;
    assert_eq!(p["field"], "Idempotency-Key");
    expect_problem(
        post(&c, &s, "/v1/jobs", Some("order-4711-session"), &submit).await,
        422,
        "idempotency-key-reused",
    )
    .await;
    assert_eq!(jobs_total(&c, &s).await, 1);

    // Without a key every submit is a new job; a key is per tenant.
    post(&c, &s, "/v1/jobs", None, &submit).await;
    assert_eq!(jobs_total(&c, &s).await, 2);
    let other_tenant = client(&api_key(dir.path(), "other"));
    let r = post(
        &other_tenant,
        &s,
        "/v1/jobs",
        Some("order-4711-job"),
        &submit,
    )
    .await;
    assert_eq!(
        r.status().as_u16(),
        404,
        "another tenant's key space, and its session is not theirs"
    );

    // A request that failed created nothing: its key is free for the corrected retry.
    let bad = json!({"session_id": "no-such-session"});
    expect_problem(
        post(&c, &s, "/v1/jobs", Some("retry-me"), &bad).await,
        404,
        "unknown-session",
    )
    .await;
    let r = post(&c, &s, "/v1/jobs", Some("retry-me"), &submit).await;
    assert_eq!(r.status().as_u16(), 202);
    assert_eq!(jobs_total(&c, &s).await, 3);

    // A key that is not visible ASCII is a 400 naming the header.
    let r = c
        .post(s.url("/v1/jobs"))
        .header("Idempotency-Key", "")
        .json(&submit)
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 400, "invalid-header").await;
    assert_eq!(p["field"], "Idempotency-Key");
    assert_eq!(jobs_total(&c, &s).await, 3);
}

#[tokio::test]
async fn an_archive_upload_is_replayed_by_its_key() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&api_key(dir.path(), "factory"));
    let manifest = image_session(1, 64, 48);
    let tar = tar_archive(&[
        ("session.json", serde_json::to_vec(&manifest).unwrap()),
        ("front/0000.png", png(64, 48, 1)),
        ("rear/0000.png", png(64, 48, 2)),
    ]);
    let send = |body: Vec<u8>| {
        c.post(s.url("/v1/sessions"))
            .header("content-type", "application/x-tar")
            .header("Idempotency-Key", "archive-1")
            .body(body)
            .send()
    };
    let first = send(tar.clone()).await.unwrap();
    assert_eq!(first.status().as_u16(), 201, "{:?}", first.text().await);
    let first: Value = first.json().await.unwrap();
    let again = send(tar.clone()).await.unwrap();
    assert_eq!(again.headers()["idempotent-replayed"], "true");
    let again: Value = again.json().await.unwrap();
    assert_eq!(again["id"], first["id"]);
    let mut changed = tar.clone();
    let n = changed.len();
    changed[n - 2000] ^= 1;
    expect_problem(send(changed).await.unwrap(), 422, "idempotency-key-reused").await;
}

/// Two identical submits in flight at once (a script that retries before the first
/// answer arrives) give one job: the second is a replay or a 409 to retry, never a job.
#[tokio::test]
async fn concurrent_retries_create_one_job() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&api_key(dir.path(), "factory"));
    let sid = create_session(&c, &s, &synth_session("lebraly-5.1", 2, 0.3, "car-2")).await;
    let submit = json!({"session_id": sid["id"]});
    for round in 0..5 {
        let key = format!("concurrent-{round}");
        let sends = (0..4).map(|_| post(&c, &s, "/v1/jobs", Some(&key), &submit));
        let answers = futures::future::join_all(sends).await;
        let mut ids = std::collections::BTreeSet::new();
        for r in answers {
            match r.status().as_u16() {
                202 => {
                    let j: Value = r.json().await.unwrap();
                    ids.insert(j["id"].as_str().unwrap().to_string());
                }
                409 => {
                    let p: Value = r.json().await.unwrap();
                    assert_eq!(p["type"], "urn:rigcal:problem:request-in-progress", "{p}");
                }
                other => panic!("unexpected {other}: {:?}", r.text().await),
            }
        }
        assert_eq!(ids.len(), 1, "round {round}: {ids:?}");
        assert_eq!(jobs_total(&c, &s).await, round + 1);
    }
}
