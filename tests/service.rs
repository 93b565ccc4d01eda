//! The service over real HTTP: a real `rigcal serve` process, a temp data directory,
//! reqwest. The whole path from manifest (+ images, or an archive) to result; idempotent
//! uploads; cancel; tenant isolation; every error kind, and that errors change nothing.

mod common;

use common::*;
use serde_json::{json, Value};
use std::time::Duration;

const MIN: Duration = Duration::from_secs(60);

#[tokio::test]
async fn detections_to_result_matches_the_cli_and_history_shows_drift() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);

    let manifest = synth_session("lebraly-5.1", 3, 0.3, "car-7");
    let sess = create_session(&c, &s, &manifest).await;
    assert_eq!(sess["images_expected"], 0);
    assert_eq!(sess["capture_check"]["verdict"], "ok");
    let sid = sess["id"].as_str().unwrap();
    let check: Value = c
        .get(s.url(&format!("/v1/sessions/{sid}/check")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(check["non_planar_motion"], true);
    assert_eq!(check["cameras"][1]["predicted_dof"]["translation"], 3);

    let job = submit(&c, &s, sid).await;
    assert_eq!(job["status"], "queued");
    let id = job["id"].as_str().unwrap().to_string();

    // Progress as server-sent events, to the terminal status.
    let sse = c
        .get(s.url(&format!("/v1/jobs/{id}/events")))
        .send()
        .await
        .unwrap();
    assert_eq!(
        sse.headers()["content-type"].to_str().unwrap(),
        "text/event-stream"
    );
    let text = tokio::time::timeout(MIN, sse.text())
        .await
        .unwrap()
        .unwrap();
    assert!(text.contains("event: stage"), "{text}");
    assert!(text.contains("rig_bundle_adjustment"), "{text}");
    assert!(text.contains("\"status\":\"succeeded\""), "{text}");

    let done = wait_job(&c, &s, &id, MIN).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["progress"], 1.0);
    assert_eq!(done["attempts"], 1);
    let result: Value = c
        .get(s.url(&format!("/v1/jobs/{id}/result")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    // Exactly what `rigcal calibrate` prints for the same session.
    let path = dir.path().join("session.json");
    std::fs::write(&path, serde_json::to_vec(&manifest).unwrap()).unwrap();
    let cli = std::process::Command::new(BIN)
        .arg("calibrate")
        .arg(&path)
        .output()
        .unwrap();
    let cli: Value = serde_json::from_slice(&cli.stdout).unwrap();
    assert_eq!(without_timings(result.clone()), without_timings(cli));

    for (fmt, needle) in [
        ("kalibr", "T_cn_cnm1"),
        ("opencv", "%YAML"),
        ("urdf", "<joint"),
        ("colmap", "cam_from_rig_rotation"),
        ("ros2", "static_transform_publisher"),
    ] {
        let r = c
            .get(s.url(&format!("/v1/jobs/{id}/result?format={fmt}")))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200, "{fmt}");
        let body = r.text().await.unwrap();
        assert!(body.contains(needle), "{fmt}: {body}");
    }
    // The per-camera export names its camera, and only it takes one.
    let p = expect_problem(
        c.get(s.url(&format!("/v1/jobs/{id}/result?format=camera_info")))
            .send()
            .await
            .unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "camera", "{p}");
    let p = expect_problem(
        c.get(s.url(&format!("/v1/jobs/{id}/result?format=kalibr&camera=cam1")))
            .send()
            .await
            .unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "camera", "{p}");
    let r = c
        .get(s.url(&format!(
            "/v1/jobs/{id}/result?format=camera_info&camera=cam1"
        )))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert!(r.text().await.unwrap().contains("camera_name: \"cam1\""));
    let diag: Value = c
        .get(s.url(&format!("/v1/jobs/{id}/diagnostics")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(diag["residuals"]["per_camera"].is_array(), "{diag}");

    // A second calibration of the same vehicle: the history shows the change (0 here:
    // same data), a different capture shows a small but nonzero change.
    let sess2 = create_session(&c, &s, &synth_session("lebraly-5.1", 4, 0.3, "car-7")).await;
    let j2 = submit(&c, &s, sess2["id"].as_str().unwrap()).await;
    wait_job(&c, &s, j2["id"].as_str().unwrap(), MIN).await;
    let hist: Value = c
        .get(s.url("/v1/vehicles/car-7/calibrations"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let cals = hist["calibrations"].as_array().unwrap();
    assert_eq!(cals.len(), 2);
    assert!(cals[0]["change_from_previous_accepted"].is_null());
    let ch = &cals[1]["change_from_previous_accepted"][1];
    let mm = ch["translation_mm"].as_f64().unwrap();
    assert!(mm > 0.0 && mm < 100.0, "{ch}");

    let list: Value = c
        .get(s.url("/v1/jobs?vehicle_id=car-7&status=succeeded&limit=1"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 2);
    assert_eq!(list["jobs"].as_array().unwrap().len(), 1);
    assert_eq!(list["jobs"][0]["id"], j2["id"], "newest first");

    let metrics = reqwest::get(s.url("/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        metrics.contains("rigcal_jobs{status=\"succeeded\"} 2"),
        "{metrics}"
    );
    assert!(
        metrics.contains("rigcal_stage_duration_seconds_count{stage=\"rig_bundle_adjustment\"}")
    );
    assert!(metrics.contains("route=\"/v1/jobs/{id}\""));
}

#[tokio::test]
async fn a_singular_capture_is_degraded_never_succeeded() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &[]);
    let c = client(&key);
    let sess = create_session(&c, &s, &synth_session("car-planar", 1, 0.3, "car-p")).await;
    assert_eq!(sess["capture_check"]["verdict"], "degraded");
    let job = submit(&c, &s, sess["id"].as_str().unwrap()).await;
    let done = wait_job(&c, &s, job["id"].as_str().unwrap(), MIN).await;
    assert_eq!(done["status"], "degraded");
    let r: Value = c
        .get(s.url(&format!("/v1/jobs/{}/result", done["id"].as_str().unwrap())))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(r["reasons"]
        .as_array()
        .unwrap()
        .iter()
        .any(|x| x["code"] == "planar_motion"));
}

#[tokio::test]
async fn images_upload_idempotently_and_every_bad_image_is_refused_without_damage() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &image_session(2, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    assert_eq!(sess["images_expected"], 4);
    assert_eq!(sess["images_missing"].as_array().unwrap().len(), 4);
    assert!(sess["capture_check"].is_null());
    expect_problem(
        c.get(s.url(&format!("/v1/sessions/{sid}/check")))
            .send()
            .await
            .unwrap(),
        409,
        "check-not-ready",
    )
    .await;
    // Incomplete sessions cannot be submitted.
    let r = c
        .post(s.url("/v1/jobs"))
        .json(&json!({"session_id": sid}))
        .send()
        .await
        .unwrap();
    expect_problem(r, 409, "session-incomplete").await;

    let put = |cam: &str, frame: &str, bytes: Vec<u8>| {
        c.put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/{frame}")))
            .header("content-type", "image/png")
            .body(bytes)
            .send()
    };
    let first = put("front", "0", png(64, 48, 1)).await.unwrap();
    assert_eq!(first.status().as_u16(), 200);
    let first: Value = first.json().await.unwrap();
    let again = put("front", "0", png(64, 48, 1)).await.unwrap();
    assert_eq!(again.status().as_u16(), 200);
    assert_eq!(
        again.json::<Value>().await.unwrap(),
        first,
        "same bytes, same answer"
    );

    // Errors, each leaving the stored image untouched.
    expect_problem(
        put("front", "0", png(64, 48, 2)).await.unwrap(),
        409,
        "image-conflict",
    )
    .await;
    expect_problem(
        put("rear", "0", png(65, 48, 1)).await.unwrap(),
        422,
        "image-size-mismatch",
    )
    .await;
    let p = png(64, 48, 3);
    expect_problem(
        put("rear", "0", p[..p.len() - 20].to_vec()).await.unwrap(),
        422,
        "undecodable-image",
    )
    .await;
    expect_problem(
        put("rear", "0", b"GIF89a\x01\x00\x01\x00".to_vec())
            .await
            .unwrap(),
        415,
        "unsupported-image-format",
    )
    .await;
    let mut bomb = png(1, 1, 0);
    bomb[16..20].copy_from_slice(&60_000u32.to_be_bytes());
    bomb[20..24].copy_from_slice(&60_000u32.to_be_bytes());
    let crc = crc32(&bomb[12..29]);
    bomb[29..33].copy_from_slice(&crc.to_be_bytes());
    let b = expect_problem(
        put("rear", "0", bomb).await.unwrap(),
        422,
        "image-too-large",
    )
    .await;
    assert_eq!(b["field"], "image");
    let b = expect_problem(
        put("side", "0", png(64, 48, 1)).await.unwrap(),
        404,
        "unknown-camera",
    )
    .await;
    assert_eq!(b["field"], "camera");
    expect_problem(
        put("rear", "7", png(64, 48, 1)).await.unwrap(),
        404,
        "unknown-frame",
    )
    .await;
    expect_problem(
        put("rear", "x", png(64, 48, 1)).await.unwrap(),
        404,
        "unknown-frame",
    )
    .await;

    let now: Value = c
        .get(s.url(&format!("/v1/sessions/{sid}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(now["images_received"], 1);
    assert_eq!(now["images_missing"].as_array().unwrap().len(), 3);

    // The rest as a zip archive (with its session.json, equal to the manifest).
    let mut zipped = Vec::new();
    {
        let mut z = zip::ZipWriter::new(std::io::Cursor::new(&mut zipped));
        let o = zip::write::SimpleFileOptions::default();
        z.start_file("session.json", o).unwrap();
        std::io::Write::write_all(
            &mut z,
            &serde_json::to_vec(&image_session(2, 64, 48)).unwrap(),
        )
        .unwrap();
        for (cam, k, seed) in [
            ("front", 0, 1),
            ("front", 1, 4),
            ("rear", 0, 5),
            ("rear", 1, 6),
        ] {
            z.start_file(format!("{cam}/{k:04}.png"), o).unwrap();
            std::io::Write::write_all(&mut z, &png(64, 48, seed)).unwrap();
        }
        z.finish().unwrap();
    }
    let r = c
        .post(s.url(&format!("/v1/sessions/{sid}/archive")))
        .header("content-type", "application/zip")
        .body(zipped)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["images_received"], 4);
    assert_eq!(v["images_missing"].as_array().unwrap().len(), 0);
    // Images are immutable: the first upload of front/0 is still the one stored.
    let blob = read_blob(dir.path(), first["sha256"].as_str().unwrap()).await;
    assert_eq!(blob.unwrap(), png(64, 48, 1));
}

#[tokio::test]
async fn a_tar_archive_creates_a_whole_session_and_the_job_runs_detection_first() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    let manifest = image_session(1, 32, 24);
    let tarred = tar_archive(&[
        (
            "capture/session.json",
            serde_json::to_vec(&manifest).unwrap(),
        ),
        ("capture/front/0000.png", png(32, 24, 1)),
        ("capture/rear/0000.png", png(32, 24, 2)),
    ]);
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", "application/x-tar")
        .body(tarred)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["images_received"], 2);
    let job = submit(&c, &s, v["id"].as_str().unwrap()).await;
    let done = wait_job(&c, &s, job["id"].as_str().unwrap(), MIN).await;
    // The images are gradients with no tag: detection runs, finds nothing, and the job
    // says which camera saw nothing rather than solving from nothing.
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["code"], "camera_not_observed", "{done}");
    // A bad archive: an image of the wrong size refuses the whole archive, no session.
    let bad = tar_archive(&[
        ("session.json", serde_json::to_vec(&manifest).unwrap()),
        ("front/0000.png", png(32, 24, 1)),
        ("rear/0000.png", png(31, 24, 1)),
    ]);
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", "application/x-tar")
        .body(bad)
        .send()
        .await
        .unwrap();
    let p = expect_problem(r, 422, "image-size-mismatch").await;
    assert_eq!(p["field"], "frames[0].images.rear");
}

#[tokio::test]
async fn every_request_error_is_a_problem_with_its_field_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(
        dir.path(),
        &[
            "--workers",
            "0",
            "--max-manifest-bytes",
            "200000",
            "--max-archive-bytes",
            "300000",
        ],
    );
    let c = client(&key);
    let good = synth_session("lebraly-5.1", 1, 0.3, "car-e");
    let sess = create_session(&c, &s, &good).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    let job = submit(&c, &s, &sid).await;
    let before: Value = c
        .get(s.url("/v1/jobs"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let before_session: Value = c
        .get(s.url(&format!("/v1/sessions/{sid}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();

    let post = |body: Vec<u8>| {
        c.post(s.url("/v1/sessions"))
            .header("content-type", "application/json")
            .body(body)
            .send()
    };
    expect_problem(
        post(b"{\"cameras\": [".to_vec()).await.unwrap(),
        400,
        "malformed-json",
    )
    .await;
    let mut m = good.clone();
    m["cameras"][0]["intrinsics"]["fx"] = json!(-5.0);
    let p = expect_problem(
        post(serde_json::to_vec(&m).unwrap()).await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "cameras[0].intrinsics.fx");
    let mut m = good.clone();
    m["frames"][0]["observations"]["cam1"][0]["u"] = json!("left");
    let p = expect_problem(
        post(serde_json::to_vec(&m).unwrap()).await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "frames[0].observations.cam1[0].u");
    let mut m = good.clone();
    m["reference_camera"] = json!("nope");
    let p = expect_problem(
        post(serde_json::to_vec(&m).unwrap()).await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "reference_camera");
    let mut m = good.clone();
    let cam = m["cameras"][0].clone();
    m["cameras"] = Value::Array(
        (0..65)
            .map(|i| {
                let mut c = cam.clone();
                c["id"] = json!(format!("c{i}"));
                c
            })
            .collect(),
    );
    m["frames"] = json!([]);
    m["reference_camera"] = json!("c0");
    let p = expect_problem(
        post(serde_json::to_vec(&m).unwrap()).await.unwrap(),
        422,
        "limit-exceeded",
    )
    .await;
    assert_eq!(p["field"], "cameras");
    // Over the (test-sized) body limit before it is even parsed: refused on the declared
    // length, before the client has sent a byte of the body.
    let (status, p) = head_only_request(
        &s,
        "POST",
        "/v1/sessions",
        &key,
        "application/json",
        64 << 20,
    )
    .await;
    assert_eq!(status, 413, "{p}");
    assert_eq!(p["type"], "urn:rigcal:problem:payload-too-large", "{p}");
    expect_problem(
        c.post(s.url("/v1/sessions"))
            .header("content-type", "text/plain")
            .body("hi")
            .send()
            .await
            .unwrap(),
        415,
        "unsupported-media-type",
    )
    .await;

    // Jobs.
    let pj = |v: Value| c.post(s.url("/v1/jobs")).json(&v).send();
    let p = expect_problem(
        pj(json!({"session_id": "nope"})).await.unwrap(),
        404,
        "unknown-session",
    )
    .await;
    assert_eq!(p["field"], "session_id");
    let p = expect_problem(
        pj(json!({"session_id": sid, "options": {"loss": "l1"}}))
            .await
            .unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "options.loss");
    let p = expect_problem(
        pj(json!({"session_id": sid, "options": {"detection": {"quality": "quick"}}}))
            .await
            .unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "options.detection.quality");
    assert!(p["detail"].as_str().unwrap().contains("fast"), "{p}");
    let p = expect_problem(
        pj(json!({"session_id": sid, "priority": 3})).await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert!(p["detail"].as_str().unwrap().contains("priority"));
    let p = expect_problem(
        c.get(s.url("/v1/jobs?status=done")).send().await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "status");
    let p = expect_problem(
        c.get(s.url("/v1/jobs?limit=0")).send().await.unwrap(),
        422,
        "invalid-field",
    )
    .await;
    assert_eq!(p["field"], "limit");
    expect_problem(
        c.get(s.url("/v1/jobs?colour=red")).send().await.unwrap(),
        400,
        "invalid-query",
    )
    .await;
    let jid = job["id"].as_str().unwrap();
    expect_problem(
        c.get(s.url(&format!("/v1/jobs/{jid}/result")))
            .send()
            .await
            .unwrap(),
        409,
        "result-not-ready",
    )
    .await;
    expect_problem(
        c.get(s.url(&format!("/v1/jobs/{jid}/result?format=pdf")))
            .send()
            .await
            .unwrap(),
        422,
        "invalid-field",
    )
    .await;
    expect_problem(
        c.get(s.url("/v1/jobs/nope")).send().await.unwrap(),
        404,
        "not-found",
    )
    .await;

    // Routing and auth.
    expect_problem(
        c.get(s.url("/v2/everything")).send().await.unwrap(),
        404,
        "not-found",
    )
    .await;
    expect_problem(
        c.patch(s.url("/v1/jobs")).send().await.unwrap(),
        405,
        "method-not-allowed",
    )
    .await;
    expect_problem(
        reqwest::get(s.url("/v1/jobs")).await.unwrap(),
        401,
        "unauthorized",
    )
    .await;
    expect_problem(
        client("rk_wrong")
            .get(s.url("/v1/jobs"))
            .send()
            .await
            .unwrap(),
        401,
        "unauthorized",
    )
    .await;

    let after: Value = c
        .get(s.url("/v1/jobs"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(after["total"], before["total"]);
    let after_session: Value = c
        .get(s.url(&format!("/v1/sessions/{sid}")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(after_session, before_session);
}

#[tokio::test]
async fn cancel_a_queued_job_and_tenants_never_see_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let acme = client(&api_key(dir.path(), "acme"));
    let globex = client(&api_key(dir.path(), "globex"));
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let sess = create_session(&acme, &s, &synth_session("lebraly-5.1", 2, 0.3, "car-a")).await;
    let sid = sess["id"].as_str().unwrap();
    let job = submit(&acme, &s, sid).await;
    let jid = job["id"].as_str().unwrap();

    for path in [
        format!("/v1/sessions/{sid}"),
        format!("/v1/sessions/{sid}/check"),
        format!("/v1/jobs/{jid}"),
        format!("/v1/jobs/{jid}/result"),
        format!("/v1/jobs/{jid}/events"),
        "/v1/vehicles/car-a/calibrations".to_string(),
    ] {
        expect_problem(
            globex.get(s.url(&path)).send().await.unwrap(),
            404,
            "not-found",
        )
        .await;
    }
    expect_problem(
        globex
            .delete(s.url(&format!("/v1/jobs/{jid}")))
            .send()
            .await
            .unwrap(),
        404,
        "not-found",
    )
    .await;
    let r = globex
        .post(s.url("/v1/jobs"))
        .json(&json!({"session_id": sid}))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "unknown-session").await;
    let r = globex
        .put(s.url(&format!("/v1/sessions/{sid}/images/cam1/0")))
        .body(png(8, 8, 0))
        .send()
        .await
        .unwrap();
    expect_problem(r, 404, "not-found").await;
    let list: Value = globex
        .get(s.url("/v1/jobs"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(list["total"], 0);

    // Cancel (no workers: the job is still queued).
    let r = acme
        .delete(s.url(&format!("/v1/jobs/{jid}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 202);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["status"], "cancelled");
    expect_problem(
        acme.delete(s.url(&format!("/v1/jobs/{jid}")))
            .send()
            .await
            .unwrap(),
        409,
        "job-finished",
    )
    .await;
    expect_problem(
        acme.get(s.url(&format!("/v1/jobs/{jid}/result")))
            .send()
            .await
            .unwrap(),
        409,
        "no-result",
    )
    .await;
}

#[tokio::test]
async fn operations_endpoints_answer() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    for (path, ct) in [
        ("/healthz", "application/json"),
        ("/readyz", "application/json"),
        ("/metrics", "text/plain; version=0.0.4; charset=utf-8"),
        ("/openapi.yaml", "application/yaml"),
        ("/docs", "text/html; charset=utf-8"),
    ] {
        let r = reqwest::get(s.url(path)).await.unwrap();
        assert_eq!(r.status().as_u16(), 200, "{path}");
        assert_eq!(r.headers()["content-type"].to_str().unwrap(), ct, "{path}");
    }
    let docs = reqwest::get(s.url("/docs"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(docs.contains("/v1/jobs/{id}/events"));
    assert!(
        !docs.contains("http://") && !docs.contains("https://"),
        "no external assets"
    );
}

#[tokio::test]
async fn cancelling_a_running_job_stops_it_between_stages() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    // A 16-pose loop: several seconds of work in trajectories and the rig BA.
    let sess = create_session(&c, &s, &synth_session("car-planar-loop", 0, 0.5, "car-x")).await;
    let job = submit(&c, &s, sess["id"].as_str().unwrap()).await;
    let id = job["id"].as_str().unwrap().to_string();
    let t = std::time::Instant::now();
    loop {
        let j: Value = c
            .get(s.url(&format!("/v1/jobs/{id}")))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        if j["status"] == "running" {
            break;
        }
        assert!(t.elapsed() < MIN, "{j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let r = c
        .delete(s.url(&format!("/v1/jobs/{id}")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 202);
    let done = wait_job(&c, &s, &id, MIN).await;
    assert_eq!(done["status"], "cancelled", "{done}");
    expect_problem(
        c.get(s.url(&format!("/v1/jobs/{id}/result")))
            .send()
            .await
            .unwrap(),
        409,
        "no-result",
    )
    .await;
}

#[tokio::test]
async fn a_vanishing_ring_calibrates_through_the_service_and_ring_images_are_slots() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);

    // Detections (line points): checked at once, then solved.
    let (m, truth) = rigcal_synth::generate("wu-table2", 11, 0.3).unwrap();
    let sess = create_session(&c, &s, &serde_json::to_value(&m).unwrap()).await;
    assert_eq!(sess["method"], "vanishing");
    assert_eq!(sess["capture_check"]["verdict"], "ok", "{sess}");
    assert_eq!(sess["capture_check"]["ring_closed"], true);
    let sid = sess["id"].as_str().unwrap();
    let job = submit(&c, &s, sid).await;
    let id = job["id"].as_str().unwrap();
    let done = wait_job(&c, &s, id, MIN).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let result: Value = c
        .get(s.url(&format!("/v1/jobs/{id}/result")))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(result["method"], "vanishing");
    assert_eq!(result["vanishing"]["ring_closed"], true);
    assert_eq!(result["vanishing"]["cameras"][4]["chain_transforms"], 4);
    for e in result["extrinsics"].as_array().unwrap() {
        let cam = e["camera"].as_str().unwrap();
        let t = truth.ref_from_cam[cam].trans;
        let got: Vec<f64> = e["translation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let d = ((got[0] - t.x).powi(2) + (got[1] - t.y).powi(2) + (got[2] - t.z).powi(2)).sqrt();
        assert!(d < 3e-3, "{cam}: {d} m");
    }
    let kalibr = c
        .get(s.url(&format!("/v1/jobs/{id}/result?format=kalibr")))
        .send()
        .await
        .unwrap();
    assert_eq!(kalibr.status(), 200);

    // A ring of images: the auxiliary camera's images are slots by ring index, checked
    // against the auxiliary camera's size; an image without the two line targets is
    // skipped with its reason, and the ring calibrates open without that view.
    let mut m2 = m.clone();
    m2.ring[0].lines.clear();
    m2.ring[0].image = Some("aux/ring0.png".into());
    let sess = create_session(&c, &s, &serde_json::to_value(&m2).unwrap()).await;
    let missing = sess["images_missing"].as_array().unwrap();
    assert_eq!(missing.len(), 1, "{sess}");
    assert_eq!(missing[0]["camera"], "aux");
    assert_eq!(missing[0]["field"], "ring[0].image");
    let sid2 = sess["id"].as_str().unwrap();
    let put = |bytes: Vec<u8>| {
        c.put(s.url(&format!("/v1/sessions/{sid2}/images/aux/0")))
            .header("content-type", "image/png")
            .body(bytes)
            .send()
    };
    expect_problem(
        put(png(640, 480, 1)).await.unwrap(),
        422,
        "image-size-mismatch",
    )
    .await;
    let ok = put(png(1024, 768, 1)).await.unwrap();
    assert_eq!(ok.status(), 200, "{:?}", ok.text().await);
    let job = submit(&c, &s, sid2).await;
    let jid = job["id"].as_str().unwrap();
    let done = wait_job(&c, &s, jid, MIN).await;
    assert_ne!(done["status"], "failed", "{done}");
    let doc = get_json(&c, &s, &format!("/v1/jobs/{jid}/result")).await;
    let det = &doc["detection"];
    assert_eq!(det["images_skipped"], 1, "{det}");
    assert_eq!(det["images"][0]["field"], "ring[0].image", "{det}");
    let why = det["images"][0]["error"].as_str().unwrap();
    assert!(why.contains("two line targets"), "{why}");
    assert_eq!(
        doc["vanishing"]["ring_closed"], false,
        "{:#}",
        doc["vanishing"]
    );
}

/// A tenant reads and sets its acceptance thresholds; jobs are judged by the current
/// ones when read, so tightening them turns an old pass into a fail at once.
#[tokio::test]
async fn thresholds_are_set_over_the_api_and_rejudge_old_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&api_key(dir.path(), "line-3"));
    let sid = create_session(&c, &s, &synth_session("lebraly-5.1", 2, 0.3, "car-9")).await;
    let job = submit(&c, &s, sid["id"].as_str().unwrap()).await;
    let id = job["id"].as_str().unwrap();
    let done = wait_job(&c, &s, id, Duration::from_secs(60)).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let defaults = get_json(&c, &s, "/v1/tenant/thresholds").await;
    assert_eq!(defaults["max_rms_px"], 1.0);

    let put = |body: Value| c.put(s.url("/v1/tenant/thresholds")).json(&body).send();
    let loose =
        json!({"max_rms_px": 1.0, "max_sigma_translation_m": 0.05, "max_sigma_rotation_deg": 1.0});
    assert_eq!(put(loose).await.unwrap().status().as_u16(), 200);
    let judged = get_json(&c, &s, &format!("/v1/jobs/{id}")).await;
    assert_eq!(judged["acceptance"]["pass"], true, "{judged}");
    let tight =
        json!({"max_rms_px": 0.01, "max_sigma_translation_m": 0.05, "max_sigma_rotation_deg": 1.0});
    let r = put(tight.clone()).await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert_eq!(get_json(&c, &s, "/v1/tenant/thresholds").await, tight);
    assert_eq!(
        get_json(&c, &s, "/v1/tenant").await["acceptance_thresholds"],
        tight
    );
    let judged = get_json(&c, &s, &format!("/v1/jobs/{id}")).await;
    assert_eq!(judged["acceptance"]["pass"], false, "{judged}");

    // Bad values name their field and change nothing.
    for (body, field) in [
        (
            json!({"max_rms_px": -1.0, "max_sigma_translation_m": 0.005, "max_sigma_rotation_deg": 0.1}),
            "max_rms_px",
        ),
        (
            json!({"max_rms_px": 1.0, "max_sigma_translation_m": 50.0, "max_sigma_rotation_deg": 0.1}),
            "max_sigma_translation_m",
        ),
        (
            json!({"max_rms_px": 1.0, "max_sigma_translation_m": 0.005}),
            "max_sigma_rotation_deg",
        ),
        (
            json!({"max_rms_px": 1.0, "max_sigma_translation_m": 0.005, "max_sigma_rotation_deg": 0.1, "max_rms": 2}),
            "max_rms",
        ),
    ] {
        let p = expect_problem(put(body).await.unwrap(), 422, "invalid-field").await;
        assert!(p["field"].as_str().unwrap().contains(field), "{p}");
    }
    assert_eq!(get_json(&c, &s, "/v1/tenant/thresholds").await, tight);
    // Another tenant's thresholds are its own.
    let other = client(&api_key(dir.path(), "line-4"));
    assert_eq!(
        get_json(&other, &s, "/v1/tenant/thresholds").await,
        defaults
    );
}

/// `rigcal apikey list` shows keys without their secrets; `revoke` shuts a key out of a
/// running server at once and leaves the tenant's other keys working.
#[tokio::test]
async fn a_revoked_key_is_refused_and_the_others_still_work() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let (k1, k2) = (api_key(dir.path(), "line-5"), api_key(dir.path(), "line-5"));
    let apikey = |args: &[&str]| {
        rigcal(dir.path())
            .arg("apikey")
            .args(args)
            .arg("--data-dir")
            .arg(dir.path())
            .output()
            .unwrap()
    };
    let out = apikey(&["list", "--tenant", "line-5"]);
    assert!(out.status.success());
    let listing = String::from_utf8(out.stdout).unwrap();
    assert!(
        !listing.contains(&k1) && !listing.contains(&k2),
        "secrets listed: {listing}"
    );
    let rows: Vec<&str> = listing.lines().skip(1).collect();
    assert_eq!(rows.len(), 2, "{listing}");
    let first = rows
        .iter()
        .find(|r| k1.starts_with(r.split_whitespace().nth(2).unwrap()))
        .unwrap();
    let id = first.split_whitespace().next().unwrap();
    assert!(apikey(&["revoke", id]).status.success());
    let r = client(&k1).get(s.url("/v1/tenant")).send().await.unwrap();
    expect_problem(r, 401, "unauthorized").await;
    let r = client(&k2).get(s.url("/v1/tenant")).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 200);
    // Revoking again, or an unknown id, is an error naming it.
    let again = apikey(&["revoke", id]);
    assert_eq!(again.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&again.stderr).contains(id));
    let listing = String::from_utf8(apikey(&["list"]).stdout).unwrap();
    assert!(
        listing
            .lines()
            .any(|l| l.starts_with(id) && !l.ends_with('-')),
        "{listing}"
    );
}
