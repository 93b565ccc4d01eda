//! `rigcal compare`: a result document against a synthetic ground truth.

use anyhow::{Context, Result};
use rigcal_core::result::ResultDocument;
use rigcal_synth::Truth;
use std::path::PathBuf;

/// Compare a result document with a synthetic ground truth.
#[derive(clap::Args)]
pub struct Args {
    result: PathBuf,
    truth: PathBuf,
}

pub fn run(a: Args) -> Result<i32> {
    let read = |p: &PathBuf| std::fs::read(p).with_context(|| format!("reading {}", p.display()));
    let doc: ResultDocument =
        serde_json::from_slice(&read(&a.result)?).context("result document")?;
    let truth: Truth = serde_json::from_slice(&read(&a.truth)?).context("truth")?;
    println!("{:<10} {:>14} {:>14}", "camera", "dt (mm)", "dR (deg)");
    for e in &doc.extrinsics {
        let Some(t) = truth.ref_from_cam.get(&e.value.camera) else {
            continue;
        };
        let (dr, dt) = e.value.pose().distance(t);
        println!(
            "{:<10} {:>14.4} {:>14.5}",
            e.value.camera,
            dt * 1e3,
            dr.to_degrees()
        );
    }
    Ok(0)
}
