//! Webhooks over real HTTP: a receiver server in this test gets signed deliveries of job
//! events, a failing receiver is retried with backoff until it answers, a hanging one
//! never holds up a job, every attempt is recorded with its status code, and URLs that
//! reach loopback, private or link-local addresses are refused unless the server runs
//! with `--allow-private-webhooks`.

mod common;

use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::routing::post;
use common::*;
use hmac::{Hmac, KeyInit, Mac};
use serde_json::{json, Value};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What the receiver got: (path, headers, body) in arrival order.
type Log = Arc<Mutex<Vec<(String, HeaderMap, String)>>>;

async fn receiver() -> (String, Log) {
    let log: Log = Arc::default();
    let record = |path: &'static str, answer: fn(usize) -> StatusCode| {
        move |State(log): State<Log>, headers: HeaderMap, body: Bytes| async move {
            let n = {
                let mut l = log.lock().unwrap();
                l.push((
                    path.to_string(),
                    headers,
                    String::from_utf8_lossy(&body).into(),
                ));
                l.iter().filter(|(p, _, _)| p == path).count()
            };
            if path == "/hang" {
                tokio::time::sleep(Duration::from_secs(60)).await;
            }
            answer(n)
        }
    };
    let app = axum::Router::new()
        .route("/ok", post(record("/ok", |_| StatusCode::OK)))
        // Fails twice, then takes it.
        .route(
            "/flaky",
            post(record("/flaky", |n| {
                if n <= 2 {
                    StatusCode::INTERNAL_SERVER_ERROR
                } else {
                    StatusCode::NO_CONTENT
                }
            })),
        )
        .route("/hang", post(record("/hang", |_| StatusCode::OK)))
        .with_state(log.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (base, log)
}

fn received(log: &Log, path: &str) -> Vec<(HeaderMap, String)> {
    log.lock()
        .unwrap()
        .iter()
        .filter(|(p, _, _)| p == path)
        .map(|(_, h, b)| (h.clone(), b.clone()))
        .collect()
}

async fn wait_for(log: &Log, path: &str, n: usize, timeout: Duration) -> Vec<(HeaderMap, String)> {
    let t = Instant::now();
    loop {
        let got = received(log, path);
        if got.len() >= n {
            return got;
        }
        assert!(
            t.elapsed() < timeout,
            "{path}: {} of {n} deliveries after {timeout:?}",
            got.len()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Check a delivery's signature as a receiver would: `t=T,v1=HEX`, HEX the HMAC-SHA256
/// of "T.BODY" keyed by the secret, T within five minutes.
fn verify(headers: &HeaderMap, body: &str, secret: &str) {
    let sig = headers["rigcal-signature"].to_str().unwrap();
    let (t, v1) = sig
        .split_once(',')
        .and_then(|(t, v)| Some((t.strip_prefix("t=")?, v.strip_prefix("v1=")?)))
        .unwrap_or_else(|| panic!("signature header {sig:?}"));
    let t: i64 = t.parse().unwrap();
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs() as i64;
    assert!((now - t).abs() < 300, "timestamp {t} vs now {now}");
    let mut mac = <Hmac<sha2::Sha256> as KeyInit>::new_from_slice(secret.as_bytes()).unwrap();
    mac.update(format!("{t}.{body}").as_bytes());
    mac.verify_slice(&hex::decode(v1).unwrap())
        .expect("the signature verifies");
    // A signature under another secret does not.
    let mut other =
        <Hmac<sha2::Sha256> as KeyInit>::new_from_slice(b"not-the-secret-at-all").unwrap();
    other.update(format!("{t}.{body}").as_bytes());
    assert!(other.verify_slice(&hex::decode(v1).unwrap()).is_err());
}

async fn register(c: &reqwest::Client, s: &Server, body: Value) -> reqwest::Response {
    c.post(s.url("/v1/webhooks"))
        .json(&body)
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn deliveries_are_signed_retried_recorded_and_never_block_a_job() {
    let (hooks, log) = receiver().await;
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "factory");
    let s = Server::start(dir.path(), &["--allow-private-webhooks", "--workers", "2"]);
    let c = client(&key);

    // Bad subscriptions name their field.
    for (body, field) in [
        (
            json!({"url": format!("{hooks}/ok"), "events": ["job.exploded"], "secret": "0123456789abcdef"}),
            "events[0]",
        ),
        (
            json!({"url": format!("{hooks}/ok"), "events": [], "secret": "0123456789abcdef"}),
            "events",
        ),
        (
            json!({"url": format!("{hooks}/ok"), "events": ["job.finished"], "secret": "short"}),
            "secret",
        ),
        (
            json!({"url": "ftp://example.com/x", "events": ["job.finished"], "secret": "0123456789abcdef"}),
            "url",
        ),
        (
            json!({"url": "http://user:pw@example.com/", "events": ["job.finished"], "secret": "0123456789abcdef"}),
            "url",
        ),
    ] {
        let p = expect_problem(register(&c, &s, body).await, 422, "invalid-field").await;
        assert_eq!(p["field"], field, "{p}");
    }
    let p = expect_problem(
        register(
            &c,
            &s,
            json!({"url": format!("{hooks}/ok"), "events": ["job.finished"]}),
        )
        .await,
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "secret", "{p}");

    let ok_secret = "whsec-ok-0123456789";
    let flaky_secret = "whsec-flaky-0123456789";
    let r = register(
        &c,
        &s,
        json!({"url": format!("{hooks}/ok"), "events": ["job.finished"], "secret": ok_secret}),
    )
    .await;
    assert_eq!(r.status().as_u16(), 201);
    let ok: Value = r.json().await.unwrap();
    assert!(
        ok.get("secret").is_none(),
        "the secret is never returned: {ok}"
    );
    let flaky: Value = register(&c, &s, json!({"url": format!("{hooks}/flaky"), "events": ["job.succeeded"], "secret": flaky_secret})).await.json().await.unwrap();
    let hang: Value = register(&c, &s, json!({"url": format!("{hooks}/hang"), "events": ["job.finished", "job.failed"], "secret": "whsec-hang-0123456789"})).await.json().await.unwrap();
    let listed = get_json(&c, &s, "/v1/webhooks").await;
    assert_eq!(listed["webhooks"].as_array().unwrap().len(), 3);

    // A job that succeeds: the receivers hear of it; the hanging one holds up nothing.
    let sid = create_session(&c, &s, &synth_session("lebraly-5.1", 3, 0.3, "VIN-HOOK")).await["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job = run_job(&c, &s, &sid, Duration::from_secs(60)).await;
    assert_eq!(job["status"], "succeeded");
    assert!(job["running_seconds"].as_f64().unwrap() < 5.0, "{job}");
    let got = wait_for(&log, "/ok", 1, Duration::from_secs(20)).await;
    let (h, body) = &got[0];
    verify(h, body, ok_secret);
    let v: Value = serde_json::from_str(body).unwrap();
    assert_eq!(v["type"], "job.finished");
    assert_eq!(h["rigcal-event"], "job.finished");
    assert_eq!(
        h["rigcal-delivery"].to_str().unwrap(),
        v["id"].as_str().unwrap()
    );
    assert_eq!(v["data"]["job"]["id"], job["id"]);
    assert_eq!(v["data"]["job"]["status"], "succeeded");
    assert_eq!(
        v["data"]["job"]["acceptance"]["pass"],
        job["acceptance"]["pass"]
    );
    // The flaky receiver: 500, 500, then 204 — after the 1 s and 2 s backoffs.
    let t = Instant::now();
    let got = wait_for(&log, "/flaky", 3, Duration::from_secs(30)).await;
    eprintln!(
        "flaky receiver took its delivery {:.1} s after the first",
        t.elapsed().as_secs_f64()
    );
    for (h, b) in &got {
        verify(h, b, flaky_secret);
        assert_eq!(b, &got[0].1, "every retry sends the same body");
        assert_eq!(h["rigcal-event"], "job.succeeded");
    }
    let fid = flaky["id"].as_str().unwrap();
    let t = Instant::now();
    let d = loop {
        let d = get_json(&c, &s, &format!("/v1/webhooks/{fid}/deliveries")).await;
        if d["deliveries"][0]["status"] == "delivered" {
            break d;
        }
        assert!(t.elapsed() < Duration::from_secs(10), "{d}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let d0 = &d["deliveries"][0];
    assert_eq!(d0["attempts"], 3, "{d0}");
    let codes: Vec<i64> = d0["attempt_log"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["status_code"].as_i64().unwrap())
        .collect();
    assert_eq!(codes, [500, 500, 204]);
    assert_eq!(d0["job_id"], job["id"]);

    // A job that fails: job.finished subscribers hear it, job.succeeded ones do not; the
    // hanging receiver, subscribed to both kinds, gets one delivery per job, not two.
    let blank = image_session(1, 32, 24);
    let archive = tar_archive(&[
        ("session.json", serde_json::to_vec(&blank).unwrap()),
        ("front/0000.png", png(32, 24, 1)),
        ("rear/0000.png", png(32, 24, 2)),
    ]);
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", "application/x-tar")
        .body(archive)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    let bid = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let failed = run_job(&c, &s, &bid, Duration::from_secs(60)).await;
    assert_eq!(failed["status"], "failed");
    let got = wait_for(&log, "/ok", 2, Duration::from_secs(20)).await;
    let v: Value = serde_json::from_str(&got[1].1).unwrap();
    assert_eq!(
        (v["type"].as_str(), v["data"]["job"]["status"].as_str()),
        (Some("job.finished"), Some("failed"))
    );
    let hid = hang["id"].as_str().unwrap();
    let hd = get_json(&c, &s, &format!("/v1/webhooks/{hid}/deliveries")).await;
    let events: Vec<&str> = hd["deliveries"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d["event"].as_str().unwrap())
        .collect();
    assert_eq!(
        events,
        ["job.failed", "job.finished"],
        "newest first, one per job: {hd}"
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(
        received(&log, "/flaky").len(),
        3,
        "no job.succeeded delivery for a failed job"
    );

    // Deleted: no more deliveries; the hanging one's pending deliveries end failed.
    let r = c
        .delete(s.url(&format!("/v1/webhooks/{}", ok["id"].as_str().unwrap())))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 204);
    let r = c
        .delete(s.url(&format!("/v1/webhooks/{hid}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 204);
    let sid = create_session(&c, &s, &synth_session("lebraly-5.1", 4, 0.3, "VIN-HOOK")).await["id"]
        .as_str()
        .unwrap()
        .to_string();
    run_job(&c, &s, &sid, Duration::from_secs(60)).await;
    wait_for(&log, "/flaky", 4, Duration::from_secs(20)).await;
    assert_eq!(
        received(&log, "/ok").len(),
        2,
        "a deleted webhook gets nothing"
    );
    let r = c
        .get(s.url(&format!("/v1/webhooks/{hid}/deliveries")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "not-found").await;
    let r = c
        .get(s.url(&format!("/v1/webhooks/{fid}/deliveries?limit=0")))
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(p["field"], "limit");
}

#[tokio::test(flavor = "multi_thread")]
async fn private_addresses_are_refused_without_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "tenant");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    for url in [
        "http://127.0.0.1:9/hook",
        "http://localhost/hook",
        "http://[::1]:8080/",
        "http://169.254.169.254/latest/meta-data/",
        "http://10.0.0.5/",
        "http://[::ffff:192.168.1.1]/",
    ] {
        let r = register(
            &c,
            &s,
            json!({"url": url, "events": ["job.finished"], "secret": "0123456789abcdef"}),
        )
        .await;
        let p = expect_problem(r, 422, "invalid-field").await;
        assert_eq!(p["field"], "url", "{url}: {p}");
        assert!(
            p["detail"]
                .as_str()
                .unwrap()
                .contains("--allow-private-webhooks"),
            "{url}: {p}"
        );
    }
    // A public address is taken (nothing is sent until a job ends).
    let r = register(&c, &s, json!({"url": "https://93.184.216.34/rigcal", "events": ["job.finished"], "secret": "0123456789abcdef"})).await;
    assert_eq!(r.status().as_u16(), 201);
    // Another tenant never sees it.
    let other = client(&api_key(dir.path(), "other"));
    let id = r.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let r = other
        .get(s.url(&format!("/v1/webhooks/{id}")))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "not-found").await;
    assert_eq!(
        get_json(&other, &s, "/v1/webhooks").await["webhooks"]
            .as_array()
            .unwrap()
            .len(),
        0
    );
}
