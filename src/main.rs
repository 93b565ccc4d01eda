//! The `rigcal` command line: calibrate a session, generate synthetic sessions, compare
//! a result with ground truth.

use anyhow::{anyhow, Context, Result};
use clap::{Parser, Subcommand};
use rigcal::export::{render, Format};
use rigcal::pipeline::{calibrate, CalibOptions};
use rigcal::session::parse_session;
use rigcal::solver::Loss;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "rigcal",
    version,
    about = "Extrinsic calibration of multi-camera rigs with non-overlapping fields of view"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Calibrate a capture session (JSON); prints the result document. Exit code 0
    /// succeeded, 3 degraded, 1 failed or bad input.
    Calibrate {
        session: PathBuf,
        /// json | kalibr | opencv | urdf
        #[arg(long, default_value = "json")]
        format: Format,
        /// Robust loss of the outlier pass: huber | cauchy | squared
        #[arg(long, default_value = "huber")]
        loss: String,
        /// Scale of the robust loss, pixels.
        #[arg(long, default_value_t = 2.0)]
        loss_scale: f64,
    },
    /// Write a synthetic session and its ground truth (session.json, truth.json).
    Synth {
        #[arg(long)]
        preset: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Pixel noise σ.
        #[arg(long, default_value_t = 0.0)]
        noise: f64,
        /// Output directory.
        #[arg(long, default_value = ".")]
        out: PathBuf,
    },
    /// Compare a result document with a synthetic ground truth.
    Compare { result: PathBuf, truth: PathBuf },
    /// Measurements that print tables (accuracy vs truth and the Cramér–Rao bound).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// RMS errors of init and refined extrinsics, CRB and NEES over noisy trials.
    Accuracy {
        #[arg(long, default_value = "lebraly-5.1")]
        preset: String,
        #[arg(long, default_value_t = 50)]
        trials: usize,
        /// Comma-separated pixel noise levels.
        #[arg(long, default_value = "0.1,0.3,0.5,1.0", value_delimiter = ',')]
        noise: Vec<f64>,
        #[arg(long, default_value_t = 1000)]
        seed: u64,
    },
    /// Export per-camera trajectories of noisy trials for hand-eye peers (JSON on stdout;
    /// see benches/peers/handeye.py).
    HandeyeExport {
        #[arg(long, default_value = "lebraly-5.1")]
        preset: String,
        #[arg(long, default_value_t = 50)]
        trials: usize,
        #[arg(long, default_value_t = 0.5)]
        noise: f64,
        #[arg(long, default_value_t = 1000)]
        seed: u64,
    },
    /// Wall time, iterations and final cost of the rig bundle adjustment.
    Speed {
        #[arg(long, default_value_t = 6)]
        cameras: usize,
        /// Comma-separated numbers of rig poses.
        #[arg(long, default_value = "50,200", value_delimiter = ',')]
        poses: Vec<usize>,
        #[arg(long, default_value_t = 100)]
        points: usize,
    },
}

fn main() {
    match run() {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
    }
}

fn check_preset(preset: &str) -> Result<()> {
    if rigcal::synth::PRESETS.contains(&preset) {
        Ok(())
    } else {
        Err(anyhow!(
            "--preset: one of {}, got {preset:?}",
            rigcal::synth::PRESETS.join(", ")
        ))
    }
}

fn run() -> Result<i32> {
    match Cli::parse().command {
        Command::Calibrate {
            session,
            format,
            loss,
            loss_scale,
        } => {
            let bytes = std::fs::read(&session)
                .with_context(|| format!("reading {}", session.display()))?;
            let session = parse_session(&bytes).map_err(|e| anyhow!("{}: {e}", "session"))?;
            if !(loss_scale.is_finite() && loss_scale > 0.0) {
                return Err(anyhow!(
                    "--loss-scale: a positive number of pixels, got {loss_scale}"
                ));
            }
            let loss = match loss.as_str() {
                "huber" => Loss::Huber { scale: loss_scale },
                "cauchy" => Loss::Cauchy { scale: loss_scale },
                "squared" => Loss::Squared,
                other => {
                    return Err(anyhow!(
                        "--loss: one of huber, cauchy, squared, got {other:?}"
                    ))
                }
            };
            let mut opts = CalibOptions::default();
            opts.rig_ba.loss = loss;
            let doc = calibrate(&session, &opts);
            match render(&doc, &session, format) {
                Some(text) => println!("{text}"),
                None => {
                    println!("{}", serde_json::to_string_pretty(&doc)?);
                    eprintln!("error: nothing to export: the calibration {:?}", doc.status);
                }
            }
            Ok(doc.exit_code())
        }
        Command::Synth {
            preset,
            seed,
            noise,
            out,
        } => {
            if !(noise.is_finite() && noise >= 0.0) {
                return Err(anyhow!("--noise: a non-negative pixel σ, got {noise}"));
            }
            let (session, truth) =
                rigcal::synth::generate(&preset, seed, noise).ok_or_else(|| {
                    anyhow!(
                        "--preset: one of {}, got {preset:?}",
                        rigcal::synth::PRESETS.join(", ")
                    )
                })?;
            std::fs::create_dir_all(&out)?;
            std::fs::write(
                out.join("session.json"),
                serde_json::to_string_pretty(&session)?,
            )?;
            std::fs::write(
                out.join("truth.json"),
                serde_json::to_string_pretty(&truth)?,
            )?;
            eprintln!(
                "wrote {} and {}",
                out.join("session.json").display(),
                out.join("truth.json").display()
            );
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::Accuracy {
                    preset,
                    trials,
                    noise,
                    seed,
                },
        } => {
            check_preset(&preset)?;
            if noise.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(anyhow!("--noise: positive pixel σ values, got {noise:?}"));
            }
            let rows = rigcal::bench::accuracy::accuracy(&preset, &noise, trials, seed);
            rigcal::bench::accuracy::print_table(&preset, &rows);
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::Speed {
                    cameras,
                    poses,
                    points,
                },
        } => {
            if cameras < 2 || points < 10 || poses.iter().any(|k| *k < 3) {
                return Err(anyhow!(
                    "--cameras ≥ 2, --points ≥ 10 and every --poses ≥ 3"
                ));
            }
            let rows = rigcal::bench::speed::run(cameras, &poses, points);
            rigcal::bench::speed::print_table(cameras, points, &rows);
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::HandeyeExport {
                    preset,
                    trials,
                    noise,
                    seed,
                },
        } => {
            check_preset(&preset)?;
            if !(noise.is_finite() && noise >= 0.0) {
                return Err(anyhow!("--noise: a non-negative pixel σ, got {noise}"));
            }
            let t = rigcal::bench::accuracy::handeye_trials(&preset, noise, trials, seed);
            println!("{}", serde_json::to_string(&t)?);
            Ok(0)
        }
        Command::Compare { result, truth } => {
            let doc: rigcal::result::ResultDocument =
                serde_json::from_slice(&std::fs::read(&result)?).context("result document")?;
            let truth: rigcal::synth::Truth =
                serde_json::from_slice(&std::fs::read(&truth)?).context("truth")?;
            println!("{:<10} {:>14} {:>14}", "camera", "dt (mm)", "dR (deg)");
            for e in &doc.extrinsics {
                let Some(t) = truth.ref_from_cam.get(&e.value.camera) else {
                    continue;
                };
                let m = e.value.ref_from_cam;
                let est = rigcal::geometry::Pose::new(
                    nalgebra::Matrix3::new(
                        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1],
                        m[2][2],
                    ),
                    nalgebra::Vector3::new(m[0][3], m[1][3], m[2][3]),
                );
                let (dr, dt) = est.distance(t);
                println!(
                    "{:<10} {:>14.4} {:>14.5}",
                    e.value.camera,
                    dt * 1e3,
                    dr.to_degrees()
                );
            }
            Ok(0)
        }
    }
}
