//! What the dashboard reads, over real HTTP (no browser): the tenant-wide event stream
//! (isolated per tenant, resumable, ended by shutdown), the pass/fail verdict against
//! the tenant's thresholds, the SVG figures, and the embedded page and assets.

mod common;

use common::*;
use serde_json::Value;
use std::time::{Duration, Instant};

const MIN: Duration = Duration::from_secs(60);

/// Read an event stream until `done(text so far)`, its end or the timeout; the text read.
async fn read_until(
    resp: &mut reqwest::Response,
    timeout: Duration,
    done: impl Fn(&str) -> bool,
) -> String {
    let mut text = String::new();
    let end = Instant::now() + timeout;
    while !done(&text) {
        let left = end.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, resp.chunk()).await {
            Ok(Ok(Some(bytes))) => text.push_str(&String::from_utf8_lossy(&bytes)),
            Ok(Ok(None)) => break,
            Ok(Err(e)) => panic!("stream error: {e}"),
            Err(_) => break,
        }
    }
    text
}

#[tokio::test]
async fn tenant_events_verdicts_figures_and_the_page() {
    let dir = tempfile::tempdir().unwrap();
    let key_a = api_key(dir.path(), "acme");
    let key_b = api_key(dir.path(), "globex");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let (a, b) = (client(&key_a), client(&key_b));

    // The tenant stream opens with a `ready` event carrying its cursor.
    let mut stream = a.get(s.url("/v1/events")).send().await.unwrap();
    assert_eq!(stream.status(), 200);
    assert_eq!(
        stream.headers()["content-type"].to_str().unwrap(),
        "text/event-stream"
    );
    let first = read_until(&mut stream, MIN, |t| t.contains("event: ready")).await;
    assert!(first.contains("\"last_event_id\""), "{first}");

    let sa = create_session(&a, &s, &synth_session("lebraly-5.1", 11, 0.3, "VIN-A")).await;
    let job_a = submit(&a, &s, sa["id"].as_str().unwrap()).await;
    let id_a = job_a["id"].as_str().unwrap().to_string();
    let sb = create_session(&b, &s, &synth_session("lebraly-5.1", 12, 0.3, "VIN-B")).await;
    let job_b = submit(&b, &s, sb["id"].as_str().unwrap()).await;
    let id_b = job_b["id"].as_str().unwrap().to_string();
    assert_eq!(job_a["acceptance"]["pass"], Value::Null, "{job_a}");

    // acme sees its job queued, staged and finished; never globex's.
    let text = read_until(&mut stream, MIN, |t| {
        t.contains(&id_a) && t.contains("\"status\":\"succeeded\"")
    })
    .await;
    assert!(text.contains("event: job"), "{text}");
    assert!(text.contains("\"status\":\"queued\""), "{text}");
    assert!(
        text.contains("\"stage\":\"rig_bundle_adjustment\""),
        "{text}"
    );
    wait_job(&b, &s, &id_b, MIN).await;
    let later = read_until(&mut stream, Duration::from_secs(2), |_| false).await;
    assert!(
        !text.contains(&id_b) && !later.contains(&id_b),
        "another tenant's job leaked into the stream"
    );
    drop(stream);

    // Resumable: from the `ready` cursor everything after is replayed.
    let cursor: i64 = first
        .lines()
        .find_map(|l| l.strip_prefix("id: "))
        .and_then(|v| v.trim().parse().ok())
        .expect("ready event id");
    let mut replay = a
        .get(s.url("/v1/events"))
        .header("Last-Event-ID", cursor.to_string())
        .send()
        .await
        .unwrap();
    let again = read_until(&mut replay, MIN, |t| t.contains("\"status\":\"succeeded\"")).await;
    assert!(
        again.contains(&id_a) && again.contains("\"status\":\"queued\""),
        "{again}"
    );
    drop(replay);

    // The verdict against acme's thresholds, and the thresholds themselves.
    let tenant = get_json(&a, &s, "/v1/tenant").await;
    assert_eq!(tenant["name"], "acme");
    let th = &tenant["acceptance_thresholds"];
    let job = get_json(&a, &s, &format!("/v1/jobs/{id_a}")).await;
    let rms = job["residual_rms_px"].as_f64().unwrap();
    let st = job["worst_sigma_translation_m"].as_f64().unwrap();
    let sr = job["worst_sigma_rotation_deg"].as_f64().unwrap();
    let result = get_json(&a, &s, &format!("/v1/jobs/{id_a}/result")).await;
    let worst_t = result["extrinsics"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|e| e["sigma_translation_m"].as_array().unwrap().clone())
        .filter_map(|v| v.as_f64())
        .fold(0.0, f64::max);
    assert!((st - worst_t).abs() < 1e-12, "{st} vs {worst_t}");
    let pass = rms <= th["max_rms_px"].as_f64().unwrap()
        && st <= th["max_sigma_translation_m"].as_f64().unwrap()
        && sr <= th["max_sigma_rotation_deg"].as_f64().unwrap();
    assert_eq!(job["acceptance"]["pass"], Value::Bool(pass), "{job}");
    assert_eq!(
        job["acceptance"]["reasons"].as_array().unwrap().is_empty(),
        pass
    );
    // The drive is in the result: one pose per frame used, the first at the origin.
    let traj = result["trajectory"].as_array().unwrap();
    assert_eq!(traj.len(), 10, "lebraly-5.1 has 10 poses");
    assert_eq!(traj[0]["translation"], serde_json::json!([0.0, 0.0, 0.0]));

    // Figures: SVG for the owner, 404 for another tenant and for unknown names.
    for name in [
        "rig.svg",
        "residual-histogram.svg",
        "residuals-per-camera.svg",
        "residuals-per-frame.svg",
    ] {
        let r = a
            .get(s.url(&format!("/v1/jobs/{id_a}/figures/{name}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 200, "{name}");
        assert_eq!(r.headers()["content-type"], "image/svg+xml");
        let svg = r.text().await.unwrap();
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>"), "{name}");
        assert!(svg.contains("<title"), "{name}: accessible name");
        let r = b
            .get(s.url(&format!("/v1/jobs/{id_a}/figures/{name}")))
            .send()
            .await
            .unwrap();
        expect_problem(r, 404, "not-found").await;
    }
    let r = a
        .get(s.url(&format!("/v1/jobs/{id_a}/figures/secret.png")))
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 404, "not-found").await;
    assert_eq!(p["field"], "name");
    let r = a
        .get(s.url("/v1/vehicles/VIN-A/drift.svg"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    assert!(r.text().await.unwrap().contains("no drift yet"));
    let r = b
        .get(s.url("/v1/vehicles/VIN-A/drift.svg"))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "not-found").await;

    // The page and its assets: no key needed, same-origin only, revalidated by ETag.
    let plain = reqwest::Client::new();
    let r = plain.get(s.url("/")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let csp = r.headers()["content-security-policy"]
        .to_str()
        .unwrap()
        .to_string();
    assert!(
        csp.contains("script-src 'self'") && csp.contains("connect-src 'self'"),
        "{csp}"
    );
    let html = r.text().await.unwrap();
    assert!(
        html.contains("/assets/app.js") && !html.contains("http://") && !html.contains("https://")
    );
    let r = plain.get(s.url("/assets/app.js")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    assert!(r.text().await.unwrap().contains("/v1/events"));
    let r = plain
        .get(s.url("/assets/app.js"))
        .header("If-None-Match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    let r = plain.get(s.url("/assets/nope.js")).send().await.unwrap();
    expect_problem(r, 404, "not-found").await;
    // Without a key the data stays closed.
    let r = plain.get(s.url("/v1/events")).send().await.unwrap();
    expect_problem(r, 401, "unauthorized").await;
}

#[tokio::test]
async fn an_open_tenant_stream_does_not_hold_up_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let mut s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    let mut stream = c.get(s.url("/v1/events")).send().await.unwrap();
    read_until(&mut stream, MIN, |t| t.contains("event: ready")).await;
    let pid = s.child.id().to_string();
    assert!(std::process::Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let t = Instant::now();
    loop {
        if let Some(status) = s.child.try_wait().unwrap() {
            assert!(status.success(), "exit after SIGTERM: {status}");
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "the server is still running 10 s after SIGTERM with a stream open"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The stream ended with the server.
    let rest = tokio::time::timeout(Duration::from_secs(5), stream.chunk()).await;
    assert!(
        matches!(rest, Ok(Ok(None)) | Ok(Err(_))),
        "stream still open"
    );
}
