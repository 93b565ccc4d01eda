//! Hostile but honest clients against the real server (issue 24): each finding that
//! was reproduced against a release build, now answered with a clear problem.

mod common;

use common::*;
use serde_json::Value;

/// Finding 8: a JPEG cut to half its bytes is refused on upload like a truncated PNG,
/// and the slot stays missing.
#[tokio::test]
async fn a_truncated_jpeg_is_refused_on_upload() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &image_session(1, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap();
    let img =
        image::GrayImage::from_fn(64, 48, |x, y| image::Luma([((x * 5 + y * 9) % 255) as u8]));
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 92)
        .encode_image(&img)
        .unwrap();
    let half = jpeg[..jpeg.len() / 2].to_vec();
    let r = c
        .put(s.url(&format!("/v1/sessions/{sid}/images/front/0")))
        .header("content-type", "image/jpeg")
        .body(half)
        .send()
        .await
        .unwrap();
    let body = expect_problem(r, 422, "undecodable-image").await;
    assert!(
        body["detail"].as_str().unwrap().contains("cut short"),
        "{body}"
    );
    let view = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(view["images_received"], 0, "{view}");
    // The whole file is taken.
    let r = c
        .put(s.url(&format!("/v1/sessions/{sid}/images/front/0")))
        .header("content-type", "image/jpeg")
        .body(jpeg)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
}

/// Finding 10: the auth scheme is case-insensitive (RFC 9110); `Last-Event-ID` is
/// parsed strictly and the same way on both event streams: garbage, negative numbers and
/// ids beyond the newest event are 400 naming the header.
#[tokio::test]
async fn bearer_is_case_insensitive_and_last_event_id_is_strict() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let plain = reqwest::Client::new();
    for scheme in ["Bearer", "bearer", "BEARER", "bEaReR"] {
        let r = plain
            .get(s.url("/v1/tenant"))
            .header("authorization", format!("{scheme} {key}"))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200, "scheme {scheme}");
    }
    expect_problem(
        plain
            .get(s.url("/v1/tenant"))
            .header("authorization", format!("Basic {key}"))
            .send()
            .await
            .unwrap(),
        401,
        "unauthorized",
    )
    .await;

    let c = client(&key);
    let sess = create_session(&c, &s, &synth_session("lebraly-5.1", 1, 0.5, "car-1")).await;
    let job = submit(&c, &s, sess["id"].as_str().unwrap()).await;
    let jid = job["id"].as_str().unwrap();
    for path in [format!("/v1/jobs/{jid}/events"), "/v1/events".to_string()] {
        for bad in ["garbage", "-1", "1.5", "9223372036854775807", "99999", " "] {
            let r = c
                .get(s.url(&path))
                .header("last-event-id", bad)
                .send()
                .await
                .unwrap();
            let body = expect_problem(r, 400, "invalid-field").await;
            assert_eq!(body["field"], "Last-Event-ID", "{path} {bad:?}: {body}");
        }
        // A valid cursor opens the stream.
        let r = c
            .get(s.url(&path))
            .header("last-event-id", "0")
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200, "{path}");
        drop(r);
    }
}

/// Findings 1 and 3: identifiers follow one grammar (`[A-Za-z0-9][A-Za-z0-9_.-]{0,63}`)
/// at the boundary, so no id can add keys to a YAML export or elements to a URDF, and a
/// 1 MB id is refused without being echoed back; nothing is stored.
#[tokio::test]
async fn hostile_identifiers_are_refused_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let good = synth_session("lebraly-5.1", 1, 0.5, "car-1");
    let long = "x".repeat(1 << 20);
    for (bad, field) in [
        ("cam99\ncamera_model: pwned", "cameras[1].id"),
        ("a\"b", "cameras[1].id"),
        ("<link name='x'/>", "cameras[1].id"),
        ("x-->", "cameras[1].id"),
        ("-front", "cameras[1].id"),
        ("a b", "cameras[1].id"),
        (long.as_str(), "cameras[1].id"),
    ] {
        let mut m = good.clone();
        m["cameras"][1]["id"] = Value::String(bad.into());
        let r = c.post(s.url("/v1/sessions")).json(&m).send().await.unwrap();
        let body = expect_problem(r, 422, "invalid-field").await;
        assert_eq!(body["field"], field, "{bad:?}: {body}");
        assert!(
            body.to_string().len() < 2000,
            "the id was echoed back: {} bytes",
            body.to_string().len()
        );
    }
    let mut m = good.clone();
    m["vehicle_id"] = Value::String(long.clone());
    let r = c.post(s.url("/v1/sessions")).json(&m).send().await.unwrap();
    let body = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(body["field"], "vehicle_id", "{body}");
    // Finding 3: every other string of the manifest is bounded too, and an error about
    // a huge value or key stays small.
    let obs = good["frames"][0]["observations"]["cam1"].clone();
    type Patch<'a> = Box<dyn Fn(&mut Value) + 'a>;
    let patches: Vec<Patch> = vec![
        Box::new(|m| m["scale"][0]["a"] = Value::String(long.clone())),
        Box::new(|m| m["frames"][0]["observations"][long.as_str()] = obs.clone()),
        Box::new(|m| {
            m["frames"][0]["observations"]["cam1"][0]["point"] = Value::String(long.clone())
        }),
        Box::new(|m| m["frames"][0]["images"] = serde_json::json!({"cam1": long.clone()})),
        Box::new(|m| m["reference_camera"] = Value::String(long.clone())),
    ];
    for patch in &patches {
        let mut m = good.clone();
        patch(&mut m);
        let r = c.post(s.url("/v1/sessions")).json(&m).send().await.unwrap();
        assert!([400, 422].contains(&r.status().as_u16()), "{}", r.status());
        let text = r.text().await.unwrap();
        assert!(
            text.len() < 5000,
            "{} bytes echoed: {}",
            text.len(),
            &text[..300]
        );
    }
    let mut m = good.clone();
    m["frames"][0]["observations"]["cam1"][0]["point"] = Value::String("p\"1".into());
    let r = c.post(s.url("/v1/sessions")).json(&m).send().await.unwrap();
    let body = expect_problem(r, 422, "invalid-field").await;
    assert_eq!(
        body["field"], "frames[0].observations.cam1[0].point",
        "{body}"
    );
    // The edge cases of the grammar are accepted.
    let mut m = good.clone();
    m["cameras"][1]["id"] = Value::String("9.a_b-c".into());
    m["frames"] = serde_json::json!([]);
    m["scale"] = serde_json::json!([]);
    let r = c.post(s.url("/v1/sessions")).json(&m).send().await.unwrap();
    assert_eq!(r.status().as_u16(), 201, "{}", r.text().await.unwrap());
    let jobs = get_json(&c, &s, "/v1/jobs").await;
    assert_eq!(jobs["jobs"].as_array().map_or(0, |j| j.len()), 0, "{jobs}");
    // Tenants too.
    let out = std::process::Command::new(BIN)
        .args([
            "apikey",
            "create",
            "--tenant",
            "acme\ninjected",
            "--data-dir",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--tenant"));
}

/// Finding 7: an archive naming one entry twice (two `session.json`, an image twice,
/// in tar and in zip) is refused with 422 naming the entry, and no session is created.
#[tokio::test]
async fn archives_with_duplicate_entries_are_refused() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let manifest = serde_json::to_vec(&image_session(1, 64, 48)).unwrap();
    // The zip writer refuses a name twice: the second image is written as 0001 and
    // renamed in the bytes (local header and central directory; same length).
    let zip_of = |files: &[(&str, Vec<u8>)]| {
        let mut out = std::io::Cursor::new(Vec::new());
        {
            let mut z = zip::ZipWriter::new(&mut out);
            let mut seen = std::collections::HashSet::new();
            for (name, bytes) in files {
                let name = if seen.insert(*name) {
                    name.to_string()
                } else {
                    name.replace("0000", "0001")
                };
                z.start_file(name, zip::write::SimpleFileOptions::default())
                    .unwrap();
                z.write_all(bytes).unwrap();
            }
            z.finish().unwrap();
        }
        let mut bytes = out.into_inner();
        let (from, to) = (b"front/0001.png", b"front/0000.png");
        for i in 0..bytes.len() - from.len() {
            if &bytes[i..i + from.len()] == from {
                bytes[i..i + from.len()].copy_from_slice(to);
            }
        }
        bytes
    };
    let twice_manifest = [
        ("session.json", manifest.clone()),
        ("session.json", manifest.clone()),
    ];
    let twice_image = [
        ("session.json", manifest.clone()),
        ("front/0000.png", png(64, 48, 1)),
        ("rear/0000.png", png(64, 48, 2)),
        ("front/0000.png", png(64, 48, 3)),
    ];
    for (what, body, ct, entry) in [
        (
            "tar manifest",
            tar_archive(&twice_manifest),
            "application/x-tar",
            "session.json",
        ),
        (
            "tar image",
            tar_archive(&twice_image),
            "application/x-tar",
            "front/0000.png",
        ),
        (
            "zip image",
            zip_of(&twice_image),
            "application/zip",
            "front/0000.png",
        ),
    ] {
        let r = c
            .post(s.url("/v1/sessions"))
            .header("content-type", ct)
            .body(body)
            .send()
            .await
            .unwrap();
        let p = expect_problem(r, 422, "invalid-archive").await;
        assert!(p["detail"].as_str().unwrap().contains(entry), "{what}: {p}");
    }
    let jobs = get_json(&c, &s, "/v1/jobs").await;
    assert_eq!(jobs["jobs"].as_array().map_or(0, |j| j.len()), 0);
}

/// Finding 5: a stored image whose blob is lost is reported: the session view lists it
/// as lost (and missing, not received), and a job over it fails with `input_missing`
/// naming the image after its retries — never with a verdict on the capture
/// (`camera_not_observed`).
#[tokio::test]
async fn a_lost_blob_is_an_input_error_not_a_calibration_verdict() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1", "--max-attempts", "2"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &image_session(1, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    for (cam, seed) in [("front", 1u8), ("rear", 2)] {
        let r = c
            .put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/0")))
            .header("content-type", "image/png")
            .body(png(64, 48, seed))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200);
    }
    let sha = rigcal_service::store::blob::sha256_hex(&png(64, 48, 2));
    std::fs::remove_file(dir.path().join("blobs").join(&sha[..2]).join(&sha)).unwrap();
    let view = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(view["images_received"], 1, "{view}");
    assert_eq!(
        view["images_lost"],
        serde_json::json!(["frames[0].images.rear"]),
        "{view}"
    );
    assert_eq!(
        view["images_missing"][0]["field"], "frames[0].images.rear",
        "{view}"
    );
    let done = run_job(&c, &s, &sid, std::time::Duration::from_secs(60)).await;
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["code"], "input_missing", "{done}");
    assert!(
        done["error"]["detail"]
            .as_str()
            .unwrap()
            .contains("frames[0].images.rear"),
        "{done}"
    );
    assert_eq!(done["attempts"], 2, "{done}");
}

/// Finding 4: storage failures are honest and not sticky. The blob directory removed
/// while the server runs is recreated on the next upload; a blob directory that cannot
/// be written (here a file in its place; root ignores permissions) answers 503
/// `storage-unavailable` with `Retry-After`, and uploads work again once it is back.
#[tokio::test]
async fn storage_failures_are_503_and_recover_without_restart() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&key);
    let sess = create_session(&c, &s, &image_session(2, 64, 48)).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    let put = |cam: &'static str, frame: u32, seed: u8| {
        c.put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/{frame}")))
            .header("content-type", "image/png")
            .body(png(64, 48, seed))
            .send()
    };
    let blobs = dir.path().join("blobs");
    std::fs::remove_dir_all(&blobs).unwrap();
    let r = put("front", 0, 1).await.unwrap();
    assert_eq!(r.status().as_u16(), 200, "{}", r.text().await.unwrap());

    let kept = dir.path().join("blobs.kept");
    std::fs::rename(&blobs, &kept).unwrap();
    std::fs::write(&blobs, b"not a directory").unwrap();
    let r = put("rear", 0, 2).await.unwrap();
    assert_eq!(
        r.headers().get("retry-after").map(|v| v.to_str().unwrap()),
        Some("5")
    );
    let body = expect_problem(r, 503, "storage-unavailable").await;
    assert!(
        !body["detail"].as_str().unwrap().contains("blobs"),
        "paths stay in the log: {body}"
    );

    std::fs::remove_file(&blobs).unwrap();
    std::fs::rename(&kept, &blobs).unwrap();
    let r = put("rear", 0, 2).await.unwrap();
    assert_eq!(r.status().as_u16(), 200, "{}", r.text().await.unwrap());
    let view = get_json(&c, &s, &format!("/v1/sessions/{sid}")).await;
    assert_eq!(view["images_received"], 2, "{view}");
}

/// An image the upload accepted under `--max-image-pixels` is decoded at detection with
/// the same budget (the worker used the default 50 MP whatever the server was told, and
/// skipped it as too large).
#[tokio::test]
async fn detection_decodes_what_the_upload_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(
        dir.path(),
        &["--workers", "1", "--max-image-pixels", "60000000"],
    );
    let c = client(&key);
    let (w, h) = (8000u32, 6400u32);
    assert!(u64::from(w) * u64::from(h) > 50_000_000);
    let sess = create_session(&c, &s, &image_session(1, w, h)).await;
    let sid = sess["id"].as_str().unwrap().to_string();
    let flat = image::GrayImage::from_pixel(w, h, image::Luma([128u8]));
    let mut png_bytes = Vec::new();
    image::DynamicImage::ImageLuma8(flat)
        .write_to(
            &mut std::io::Cursor::new(&mut png_bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    for cam in ["front", "rear"] {
        let r = c
            .put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/0")))
            .header("content-type", "image/png")
            .body(png_bytes.clone())
            .send()
            .await
            .unwrap();
        assert_eq!(r.status().as_u16(), 200, "{}", r.text().await.unwrap());
    }
    let done = run_job(&c, &s, &sid, std::time::Duration::from_secs(120)).await;
    let id = done["id"].as_str().unwrap();
    assert_eq!(done["status"], "failed", "{done}");
    let r = c
        .get(s.url(&format!("/v1/jobs/{id}/result")))
        .send()
        .await
        .unwrap();
    let doc = r.text().await.unwrap();
    assert!(
        !doc.contains("pixels"),
        "an accepted image was refused: {doc}"
    );
    assert!(doc.contains("images_skipped\":0"), "{doc}");
}

/// Images too small to hold a tag (a 1×1 or 2×2 camera is a valid camera) are detected
/// with no tags: the AprilTag C library read out of bounds on them, and as the upload
/// detects each image in the server's own process, one such upload took the server down.
#[tokio::test]
async fn images_too_small_for_a_tag_fail_the_job_not_the_server() {
    let dir = tempfile::tempdir().unwrap();
    let key = api_key(dir.path(), "acme");
    let s = Server::start(dir.path(), &["--workers", "1"]);
    let c = client(&key);
    for (w, h) in [(1u32, 1u32), (2, 2), (16, 4)] {
        let sess = create_session(&c, &s, &image_session(2, w, h)).await;
        let sid = sess["id"].as_str().unwrap().to_string();
        let bytes = png(w, h, 0);
        for cam in ["front", "rear"] {
            for k in 0..2 {
                let r = c
                    .put(s.url(&format!("/v1/sessions/{sid}/images/{cam}/{k}")))
                    .header("content-type", "image/png")
                    .body(bytes.clone())
                    .send()
                    .await
                    .unwrap();
                assert_eq!(r.status().as_u16(), 200, "{}", r.text().await.unwrap());
            }
        }
        let done = run_job(&c, &s, &sid, std::time::Duration::from_secs(60)).await;
        assert_eq!(done["status"], "failed", "{w}×{h}: {done}");
        let id = done["id"].as_str().unwrap();
        let result = get_json(&c, &s, &format!("/v1/jobs/{id}/result")).await;
        // Detected on upload, in the server's process, and found empty.
        assert_eq!(result["detection"]["images_reused"], 4, "{w}×{h}: {result}");
        assert_eq!(result["detection"]["points_total"], 0, "{w}×{h}: {result}");
        assert_eq!(
            result["reasons"][0]["code"], "camera_not_observed",
            "{w}×{h}: {result}"
        );
        let health = c.get(s.url("/healthz")).send().await.unwrap();
        assert_eq!(health.status().as_u16(), 200, "after {w}×{h}");
    }
}
