//! Behaviour is unchanged by refactoring: every synthetic preset (seed 7, 0.3 px of
//! corner noise, detections only) calibrates to the result document stored in
//! `tests/golden/`, field by field — strings, counts and flags exactly, numbers within
//! 1e-6 relative (1e-9 absolute near zero), so a change of linear solver or summation
//! order passes and a change of result does not. Stage timings are not compared.
//!
//! After a deliberate change of results, regenerate with `RIGCAL_BLESS=1 cargo test
//! --release --test golden` and say why in the commit.

use rigcal_core::session::parse_session;
use rigcal_engine::pipeline::{run, CalibOptions, LossKind, NoImages, Silent};
use serde_json::Value;
use std::path::Path;

/// Every preset `rigcal synth` knows: the classic ones and the hall captures.
fn presets() -> impl Iterator<Item = &'static str> {
    rigcal_synth::PRESETS
        .iter()
        .chain(rigcal_synth::hall::PRESETS)
        .copied()
}

/// The session the CLI's `rigcal synth --preset P --seed 7 --noise 0.3` writes.
fn session_bytes(preset: &str) -> Vec<u8> {
    if rigcal_synth::hall::PRESETS.contains(&preset) {
        let dir = tempfile::tempdir().unwrap();
        let hall = rigcal_synth::hall::hall(preset, 7, None).unwrap();
        rigcal_synth::hall::write_capture(&hall, dir.path(), None, 0.3, 7).unwrap();
        std::fs::read(dir.path().join("session.json")).unwrap()
    } else {
        let (manifest, _) = rigcal_synth::generate(preset, 7, 0.3).unwrap();
        serde_json::to_vec_pretty(&manifest).unwrap()
    }
}

fn result_of(preset: &str) -> Value {
    let session = parse_session(&session_bytes(preset)).unwrap();
    let opts = CalibOptions::from_loss(LossKind::Huber, 2.0).unwrap(); // the CLI's defaults
    let doc = run(&session, &NoImages, &opts, &Silent).unwrap();
    let mut v = serde_json::to_value(&doc).unwrap();
    v.as_object_mut().unwrap().remove("stages");
    v
}

/// Differences between `got` and `want`, as `path: got vs want`.
fn diff(path: &str, got: &Value, want: &Value, out: &mut Vec<String>) {
    match (got, want) {
        (Value::Number(a), Value::Number(b)) => {
            let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
            if (a - b).abs() > 1e-9 + 1e-6 * b.abs() {
                out.push(format!("{path}: {a} vs {b}"));
            }
        }
        (Value::Object(a), Value::Object(b)) => {
            for k in a.keys().chain(b.keys().filter(|k| !a.contains_key(*k))) {
                match (a.get(k), b.get(k)) {
                    (Some(x), Some(y)) => diff(&format!("{path}.{k}"), x, y, out),
                    (x, y) => out.push(format!("{path}.{k}: {x:?} vs {y:?}")),
                }
            }
        }
        (Value::Array(a), Value::Array(b)) if a.len() == b.len() => {
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                diff(&format!("{path}[{i}]"), x, y, out);
            }
        }
        _ if got == want => {}
        _ => out.push(format!("{path}: {got} vs {want}")),
    }
}

#[test]
fn every_preset_calibrates_to_its_golden_result() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
    let bless = std::env::var_os("RIGCAL_BLESS").is_some();
    let mut failures = Vec::new();
    for preset in presets() {
        let got = result_of(preset);
        let file = dir.join(format!("{preset}.json"));
        if bless {
            let text = serde_json::to_string_pretty(&got).unwrap();
            std::fs::write(&file, text + "\n").unwrap();
            continue;
        }
        let want: Value = serde_json::from_slice(&std::fs::read(&file).unwrap()).unwrap();
        let mut out = Vec::new();
        diff(preset, &got, &want, &mut out);
        failures.extend(out.into_iter().take(10));
    }
    assert!(
        failures.is_empty(),
        "results differ from tests/golden:\n{}",
        failures.join("\n")
    );
}

#[test]
fn the_comparison_sees_a_changed_number() {
    let want = serde_json::json!({"a": [1.0, {"b": 2.0, "s": "x"}]});
    let mut out = Vec::new();
    diff("", &want, &want, &mut out);
    assert!(out.is_empty());
    for got in [
        serde_json::json!({"a": [1.0, {"b": 2.00001, "s": "x"}]}),
        serde_json::json!({"a": [1.0, {"b": 2.0, "s": "y"}]}),
        serde_json::json!({"a": [1.0, {"b": 2.0}]}),
        serde_json::json!({"a": [1.0]}),
    ] {
        let mut out = Vec::new();
        diff("", &got, &want, &mut out);
        assert!(!out.is_empty(), "{got} passed as {want}");
    }
}
