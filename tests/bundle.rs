//! A support engineer replays any customer job offline: `GET /v1/jobs/{id}/bundle` is one
//! tar with the session, its images, the job's options and the result, and
//! `rigcal calibrate bundle.tar` reproduces the result field by field.

mod common;

use common::*;
use serde_json::Value;
use std::time::Duration;

async fn bundle_of(c: &reqwest::Client, s: &Server, id: &str) -> Vec<u8> {
    let r = c
        .get(s.url(&format!("/v1/jobs/{id}/bundle")))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 200);
    assert_eq!(r.headers()["content-type"], "application/x-tar");
    r.bytes().await.unwrap().to_vec()
}

fn entries(tar: &[u8]) -> Vec<String> {
    tar::Archive::new(tar)
        .entries()
        .unwrap()
        .map(|e| e.unwrap().path().unwrap().display().to_string())
        .collect()
}

#[tokio::test]
async fn every_preset_replays_from_its_bundle() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "2"]);
    let c = client(&api_key(dir.path(), "support"));
    let presets = rigcal_synth::PRESETS
        .iter()
        .chain(rigcal_synth::hall::PRESETS)
        .copied();
    let mut jobs = Vec::new();
    for p in presets {
        let sid = create_session(&c, &s, &synth_session(p, 3, 0.3, "car-1")).await;
        jobs.push((p, submit(&c, &s, sid["id"].as_str().unwrap()).await));
    }
    for (preset, job) in jobs {
        let id = job["id"].as_str().unwrap();
        wait_job(&c, &s, id, Duration::from_secs(120)).await;
        let tar = bundle_of(&c, &s, id).await;
        let names = entries(&tar);
        for n in ["session.json", "job.json", "result.json"] {
            assert!(names.contains(&n.to_string()), "{preset}: {names:?}");
        }
        let path = dir.path().join(format!("{preset}.tar"));
        std::fs::write(&path, &tar).unwrap();
        let out = std::process::Command::new(BIN)
            .args(["calibrate"])
            .arg(&path)
            .output()
            .unwrap();
        let replayed: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{preset}: {e}: {}", String::from_utf8_lossy(&out.stderr)));
        let stored = get_json(&c, &s, &format!("/v1/jobs/{id}/result")).await;
        assert_eq!(
            without_timings(replayed),
            without_timings(stored),
            "{preset}: the replay differs from the job's result"
        );
    }
}

#[tokio::test]
async fn a_bundle_carries_the_images_at_their_manifest_paths() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(dir.path(), &["--workers", "0"]);
    let c = client(&api_key(dir.path(), "support"));
    let manifest = image_session(1, 64, 48);
    let (front, rear) = (png(64, 48, 1), png(64, 48, 2));
    let tar = tar_archive(&[
        ("session.json", serde_json::to_vec(&manifest).unwrap()),
        ("front/0000.png", front.clone()),
        ("rear/0000.png", rear.clone()),
    ]);
    let r = c
        .post(s.url("/v1/sessions"))
        .header("content-type", "application/x-tar")
        .body(tar)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 201);
    let sid: Value = r.json().await.unwrap();
    let job = submit(&c, &s, sid["id"].as_str().unwrap()).await;
    // Queued (no workers): the bundle is there before the result.
    let tar = bundle_of(&c, &s, job["id"].as_str().unwrap()).await;
    let mut archive = tar::Archive::new(&tar[..]);
    let mut found = std::collections::BTreeMap::new();
    for e in archive.entries().unwrap() {
        let mut e = e.unwrap();
        let name = e.path().unwrap().display().to_string();
        let mut bytes = Vec::new();
        std::io::Read::read_to_end(&mut e, &mut bytes).unwrap();
        found.insert(name, bytes);
    }
    assert_eq!(found["front/0000.png"], front);
    assert_eq!(found["rear/0000.png"], rear);
    assert!(!found.contains_key("result.json"));
    let job_json: Value = serde_json::from_slice(&found["job.json"]).unwrap();
    assert_eq!(job_json["options"]["loss"], "huber");
    assert_eq!(job_json["options"]["detection"]["quality"], "accurate");
    assert_eq!(job_json["status"], "queued");
    // Another tenant does not see it.
    let other = client(&api_key(dir.path(), "other"));
    let r = other
        .get(s.url(&format!("/v1/jobs/{}/bundle", job["id"].as_str().unwrap())))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status().as_u16(), 404);
}
