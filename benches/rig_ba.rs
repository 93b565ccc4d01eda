//! `cargo bench --bench rig_ba`: the rig bundle adjustment of the issue-2 benchmark rig
//! (6 cameras, 100 points per scene) at K rig poses, and the full motion pipeline on the
//! paper's protocol. Medians over samples; see docs/performance.md.

use rigcal_bench::speed::problem;
use rigcal_core::session::parse_session;
use rigcal_engine::pipeline::{calibrate, CalibOptions};
use rigcal_solve::bundle::LmOptions;

fn main() {
    divan::main();
}

#[divan::bench(args = [50, 200], sample_count = 5)]
fn rig_bundle_adjustment(bencher: divan::Bencher, poses: usize) {
    let (p, _) = problem(6, poses, 100, 0, 7);
    bencher.with_inputs(|| p.clone()).bench_values(|mut p| {
        p.solve(&LmOptions {
            max_iterations: 50,
            ..LmOptions::default()
        })
    });
}

#[divan::bench(sample_count = 20)]
fn lebraly_protocol_end_to_end(bencher: divan::Bencher) {
    let (manifest, _) = rigcal_synth::generate("lebraly-5.1", 1, 0.5).expect("preset");
    let session =
        parse_session(serde_json::to_string(&manifest).expect("json").as_bytes()).expect("valid");
    bencher.bench(|| calibrate(&session, &CalibOptions::default()));
}
