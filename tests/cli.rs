//! The `rigcal` binary as a user runs it: synth → calibrate → exit codes and output.

use std::process::Command;

fn rigcal() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rigcal"))
}

#[test]
fn synth_then_calibrate_prints_the_result_document() {
    let dir = tempfile::tempdir().unwrap();
    let st = rigcal()
        .args([
            "synth",
            "--preset",
            "lebraly-5.1",
            "--seed",
            "3",
            "--noise",
            "0.3",
            "--out",
        ])
        .arg(dir.path())
        .status()
        .unwrap();
    assert!(st.success());
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(doc["status"], "succeeded");
    assert_eq!(doc["extrinsics"].as_array().unwrap().len(), 2);
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .args(["--format", "kalibr"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stdout).contains("cam1:"));
}

#[test]
fn degraded_exit_code_and_bad_input_errors() {
    let dir = tempfile::tempdir().unwrap();
    rigcal()
        .args(["synth", "--preset", "car-planar", "--out"])
        .arg(dir.path())
        .status()
        .unwrap();
    let out = rigcal()
        .arg("calibrate")
        .arg(dir.path().join("session.json"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(3));
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, r#"{"reference_camera":"a","cameras":[{"id":"a","model":"fisheye","width":10,"height":10,"intrinsics":{"fx":5,"fy":5,"cx":5,"cy":5}}]}"#).unwrap();
    let out = rigcal().arg("calibrate").arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("cameras[0].model"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = rigcal()
        .args(["synth", "--preset", "nope"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
}
