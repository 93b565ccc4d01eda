//! The `rigcal` command line: calibrate a session, detect targets, generate synthetic
//! sessions, compare a result with ground truth, run the service or its workers. One
//! file per command under `cli/`.

mod cli;

use clap::{Parser, Subcommand};

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
    Calibrate(cli::calibrate::Args),
    /// Detect AprilTags / AprilGrid corners in images; prints detections as JSON (one
    /// object per image, an array when several are given).
    Detect(cli::detect::Args),
    /// Write a synthetic session and its ground truth (session.json, truth.json; the
    /// realistic hall presets also corners.json, every image's visible tag corners).
    Synth(cli::synth::Args),
    /// Compare a result document with a synthetic ground truth.
    Compare(cli::compare::Args),
    /// The service: HTTP API, dashboard and embedded workers (SQLite in --data-dir, or
    /// PostgreSQL and S3 shared by replicas).
    Serve(cli::serve::Args),
    /// Workers only, on the same database and blobs as a `serve` (any number, any host).
    Worker(cli::worker::Args),
    /// Apply the database migrations and exit (a deployment's one-off step).
    Migrate(cli::migrate::Args),
    /// Upload a capture to a running service and submit its job (--wait: follow it, print
    /// the summary, write the result and exports, exit 0/3/1 like calibrate).
    Submit(cli::submit::Args),
    /// A tenant's jobs on a running service.
    Jobs {
        #[command(subcommand)]
        what: cli::jobs::Command,
    },
    /// API keys.
    Apikey {
        #[command(subcommand)]
        what: cli::apikey::Command,
    },
    /// Newcomer path: start the service, submit the bundled sample session, wait, print
    /// the extrinsics and the dashboard URL (then keep serving unless --exit).
    Demo(cli::demo::Args),
    /// Measurements that print tables (accuracy vs truth and the Cramér–Rao bound).
    Bench {
        #[command(subcommand)]
        what: cli::bench::Command,
    },
}

fn main() {
    let result = match Cli::parse().command {
        Command::Calibrate(a) => cli::calibrate::run(a),
        Command::Detect(a) => cli::detect::run(a),
        Command::Synth(a) => cli::synth::run(a),
        Command::Compare(a) => cli::compare::run(a),
        Command::Serve(a) => cli::serve::run(a),
        Command::Worker(a) => cli::worker::run(a),
        Command::Migrate(a) => cli::migrate::run(a),
        Command::Submit(a) => cli::submit::run(a),
        Command::Jobs { what } => cli::jobs::run(what),
        Command::Apikey { what } => cli::apikey::run(what),
        Command::Demo(a) => cli::demo::run(a),
        Command::Bench { what } => cli::bench::run(what),
    };
    match result {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
    }
}
