//! The `rigcal` command line: calibrate a session, generate synthetic sessions, compare
//! a result with ground truth.

use anyhow::{anyhow, Context, Result};
use clap::{Parser, Subcommand};
use rigcal::api::ServeConfig;
use rigcal::export::{render, Format};
use rigcal::jobs::worker::WorkerConfig;
use rigcal::pipeline::{CalibOptions, DirSource, Silent};
use rigcal::session::parse_session;
use std::path::PathBuf;
use std::time::Duration;

/// Logs (tracing) to stderr; `RUST_LOG` overrides the default `info` for rigcal.
fn init_logging() {
    let default = || tracing_subscriber::EnvFilter::new("rigcal=info,warn");
    let filter = match std::env::var("RUST_LOG") {
        Err(_) => default(),
        Ok(spec) => tracing_subscriber::EnvFilter::try_new(&spec).unwrap_or_else(|e| {
            // Logging still starts (at the default levels), and says why.
            eprintln!(
                "warning: RUST_LOG={spec:?} is not a log filter ({e}); using rigcal=info,warn"
            );
            default()
        }),
    };
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    init_logging();
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

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
    /// Detect AprilTags / AprilGrid corners in images; prints detections as JSON (one
    /// object per image, an array when several are given).
    Detect {
        #[arg(required = true)]
        images: Vec<PathBuf>,
        /// A target definition as in a session's `targets[]` (aprilgrid or apriltags),
        /// or an array of them.
        #[arg(long)]
        target: PathBuf,
        /// A camera as in a session's `cameras[]`: sides are then fitted in the
        /// undistorted plane (better corners under distortion).
        #[arg(long)]
        camera: Option<PathBuf>,
        /// Threads for the tags of one image (default: the machine's cores; 1 to time a
        /// single core).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Write a synthetic session and its ground truth (session.json, truth.json; the
    /// realistic hall presets also corners.json, every image's visible tag corners).
    Synth {
        #[arg(long)]
        preset: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Pixel noise σ of the observations (sessions of detections).
        #[arg(long, default_value_t = 0.0)]
        noise: f64,
        /// Render the capture's images (hall presets: car-hall, car-hall-planar,
        /// car-hall-isolated, fisheye-handheld) with blur, vignetting, gain, noise, JPEG.
        #[arg(long)]
        images: bool,
        /// Image size of the hall presets, e.g. 1024x768 (intrinsics scale with it).
        #[arg(long, value_parser = parse_size)]
        size: Option<(u32, u32)>,
        /// Sensor noise σ of rendered images, grey levels.
        #[arg(long, default_value_t = 1.0)]
        grey_noise: f64,
        /// Write PNG instead of JPEG (q 92).
        #[arg(long)]
        png: bool,
        /// Hall presets: AprilGrids only, no tags scattered on the walls.
        #[arg(long)]
        boards_only: bool,
        /// Output directory.
        #[arg(long, default_value = ".")]
        out: PathBuf,
    },
    /// Compare a result document with a synthetic ground truth.
    Compare { result: PathBuf, truth: PathBuf },
    /// The service: HTTP API, dashboard and embedded workers on SQLite in --data-dir.
    Serve(ServeArgs),
    /// Workers only, on the same database as a `serve` (several may run).
    Worker {
        #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
        data_dir: PathBuf,
        #[arg(long, env = "RIGCAL_WORKERS", default_value_t = 1)]
        workers: usize,
        /// Lease of a claimed job, seconds (renewed every third of it).
        #[arg(long, env = "RIGCAL_LEASE_SECONDS", default_value_t = 30)]
        lease_seconds: u64,
        /// Largest image decoded at detection, pixels: give the servers' value.
        #[arg(long, env = "RIGCAL_MAX_IMAGE_PIXELS", default_value_t = rigcal::pipeline::detection::DEFAULT_MAX_IMAGE_PIXELS)]
        max_image_pixels: u64,
    },
    /// API keys.
    Apikey {
        #[command(subcommand)]
        what: ApikeyCommand,
    },
    /// Newcomer path: start the service, submit the bundled sample session, wait, print
    /// the extrinsics and the dashboard URL (then keep serving unless --exit).
    Demo {
        #[arg(long, default_value = "rigcal-demo")]
        data_dir: PathBuf,
        #[arg(long, default_value = "127.0.0.1:8080")]
        bind: String,
        /// Stop after printing the summary instead of serving the dashboard.
        #[arg(long)]
        exit: bool,
    },
    /// Measurements that print tables (accuracy vs truth and the Cramér–Rao bound).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(clap::Args)]
struct ServeArgs {
    /// Address to listen on (port 0 picks a free port).
    #[arg(long, env = "RIGCAL_BIND", default_value = "127.0.0.1:8080")]
    bind: String,
    /// SQLite database and image blobs live here.
    #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
    data_dir: PathBuf,
    /// Embedded workers (0: API only, run `rigcal worker` separately).
    #[arg(long, env = "RIGCAL_WORKERS", default_value_t = 1)]
    workers: usize,
    /// Serve without API keys, as tenant "local". For local use only.
    #[arg(long, env = "RIGCAL_INSECURE_NO_AUTH")]
    insecure_no_auth: bool,
    /// Lease of a claimed job, seconds (renewed every third of it).
    #[arg(long, env = "RIGCAL_LEASE_SECONDS", default_value_t = 30)]
    lease_seconds: u64,
    /// Attempts per job before a transient failure becomes final.
    #[arg(long, env = "RIGCAL_MAX_ATTEMPTS", default_value_t = 3)]
    max_attempts: i64,
    /// Largest image upload, bytes.
    #[arg(long, env = "RIGCAL_MAX_IMAGE_BYTES", default_value_t = 64 << 20)]
    max_image_bytes: usize,
    /// Largest archive upload (and its unpacked size), bytes.
    #[arg(long, env = "RIGCAL_MAX_ARCHIVE_BYTES", default_value_t = 1 << 30)]
    max_archive_bytes: usize,
    /// Largest manifest or JSON body, bytes.
    #[arg(long, env = "RIGCAL_MAX_MANIFEST_BYTES", default_value_t = 64 << 20)]
    max_manifest_bytes: usize,
    /// Largest image, pixels (checked from the header, before decoding).
    #[arg(long, env = "RIGCAL_MAX_IMAGE_PIXELS", default_value_t = rigcal::pipeline::detection::DEFAULT_MAX_IMAGE_PIXELS)]
    max_image_pixels: u64,
    /// Archive uploads read at once; more are refused with 503 and Retry-After.
    #[arg(long, env = "RIGCAL_MAX_CONCURRENT_ARCHIVES", default_value_t = 4)]
    max_concurrent_archives: usize,
    /// Seconds a connection may take to send a request's headers, counted from when it
    /// starts waiting for the request (so also the idle keep-alive timeout).
    #[arg(long, env = "RIGCAL_HEADER_TIMEOUT_SECONDS", default_value_t = 30)]
    header_timeout_seconds: u64,
    /// Seconds a request body may pause between two chunks (a slow link that keeps
    /// sending passes; a client that stops does not).
    #[arg(long, env = "RIGCAL_BODY_TIMEOUT_SECONDS", default_value_t = 60)]
    body_timeout_seconds: u64,
    /// Seconds a request that neither uploads nor streams may take from start to answer.
    #[arg(long, env = "RIGCAL_REQUEST_TIMEOUT_SECONDS", default_value_t = 120)]
    request_timeout_seconds: u64,
    /// Event streams (`/v1/events`, `/v1/jobs/{id}/events`) one tenant may hold open.
    #[arg(long, env = "RIGCAL_MAX_STREAMS_PER_TENANT", default_value_t = 32)]
    max_streams_per_tenant: usize,
}

#[derive(Subcommand)]
enum ApikeyCommand {
    /// Create a key for a tenant (created if new). The key is printed once.
    Create {
        #[arg(long)]
        tenant: String,
        #[arg(long, env = "RIGCAL_DATA_DIR", default_value = "rigcal-data")]
        data_dir: PathBuf,
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
    /// Realistic captures end to end: a hall preset rendered (JPEG, blur, vignetting,
    /// gain, noise), detected and calibrated per trial; detection against the true
    /// corners, errors against the truth and in units of the reported σ.
    Capture {
        #[arg(long, default_value = "car-hall")]
        preset: String,
        #[arg(long, default_value_t = 20)]
        trials: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Image size, e.g. 1024x576 (default: the preset's, 1920x1080 for the car).
        #[arg(long, value_parser = parse_size)]
        size: Option<(u32, u32)>,
        /// Also write the trials as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Vanishing method on Wu's Table 2 ring: chainwise vs global RMS errors per camera.
    Ring {
        #[arg(long, default_value_t = 50)]
        trials: usize,
        /// Comma-separated noise levels: pixels on the line points, or grey levels of
        /// the rendered images with --images.
        #[arg(long, default_value = "0.2,0.5,1.0", value_delimiter = ',')]
        noise: Vec<f64>,
        #[arg(long, default_value_t = 1000)]
        seed: u64,
        /// Render the 16 images of every trial and go through the line-target detector.
        #[arg(long)]
        images: bool,
        /// Placement study (sampled points only): ground distance camera → target (m).
        #[arg(long)]
        target_distance: Option<f64>,
        /// Placement study: auxiliary camera distance to the pair's midpoint (m).
        #[arg(long)]
        aux_distance: Option<f64>,
        /// Placement study: auxiliary camera pitch below the horizon (deg).
        #[arg(long)]
        aux_pitch: Option<f64>,
        /// Placement study: auxiliary images per pair (1-5), pitched 8° apart.
        #[arg(long)]
        aux_views: Option<usize>,
        /// Placement study: put the noise on `both`, only the `rig` or only the `aux` images.
        #[arg(long, default_value = "both")]
        noise_on: String,
    },
    /// Detector on rendered tags and AprilGrids: detection rate, wrong ids, corner RMS
    /// error vs truth, time per image.
    Detect {
        /// Views per cell (single tags and grids × pinhole, radtan, equidistant).
        #[arg(long, default_value_t = 40)]
        views: usize,
        #[arg(long, default_value_t = 1600)]
        width: u32,
        #[arg(long, default_value_t = 1200)]
        height: u32,
        #[arg(long, default_value_t = 1000)]
        seed: u64,
        /// Also write each view (PNG) and its truth (JSON) here, for benches/peers.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Head-on tag sizes (px) of the single-tag cells, `MIN,MAX` (default 24,200).
        #[arg(long, value_delimiter = ',')]
        tag_sizes: Option<Vec<f64>>,
        /// Only the single-tag cells (`tags`) or only the AprilGrid cells (`grids`).
        #[arg(long)]
        only: Option<String>,
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
        /// Also write each problem with rigcal's result as `ba_K.json` here, for
        /// `benches/peers/colmap_ba.py`.
        #[arg(long)]
        export: Option<PathBuf>,
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

/// `WxH`, e.g. `1024x768`.
fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once('x')
        .ok_or_else(|| format!("WIDTHxHEIGHT such as 1024x768, got {s:?}"))?;
    let n = |x: &str| {
        x.parse::<u32>()
            .map_err(|_| format!("WIDTHxHEIGHT such as 1024x768, got {s:?}"))
    };
    Ok((n(w)?, n(h)?))
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
        Command::Detect {
            images,
            target,
            camera,
            threads,
        } => {
            let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
            let threads = threads.unwrap_or(cores);
            if !(1..=256).contains(&threads) {
                return Err(anyhow!("--threads: 1 to 256, got {threads}"));
            }
            detect_images(&images, &target, camera.as_deref(), threads)
        }
        Command::Calibrate {
            session,
            format,
            loss,
            loss_scale,
        } => {
            let session_path = session;
            let bytes = std::fs::read(&session_path)
                .with_context(|| format!("reading {}", session_path.display()))?;
            let session = parse_session(&bytes).map_err(|e| anyhow!("{}: {e}", "session"))?;
            let opts = CalibOptions::from_loss(&loss, loss_scale)
                .map_err(|e| anyhow!("--{}: {}", e.field.replace('_', "-"), e.expected))?;
            let dir = session_path
                .parent()
                .map(|p| p.to_path_buf())
                .unwrap_or_default();
            let doc = rigcal::pipeline::run(&session, &DirSource(dir), &opts, &Silent)
                .map_err(|c| anyhow!("cancelled at {}", c.0))?;
            match render(&doc, &session, format) {
                Ok(text) => println!("{text}"),
                Err(rigcal::export::ExportError::NothingToExport) => {
                    println!("{}", serde_json::to_string_pretty(&doc)?);
                    eprintln!("error: nothing to export: the calibration {:?}", doc.status);
                }
                Err(rigcal::export::ExportError::Unrepresentable(why)) => {
                    return Err(anyhow!("--format: {why}"));
                }
            }
            Ok(doc.exit_code())
        }
        Command::Serve(a) => {
            if a.workers > 64 || a.lease_seconds < 1 || a.max_attempts < 1 {
                return Err(anyhow!(
                    "--workers at most 64, --lease-seconds at least 1, --max-attempts at least 1"
                ));
            }
            if a.max_concurrent_archives < 1
                || a.max_streams_per_tenant < 1
                || [
                    a.header_timeout_seconds,
                    a.body_timeout_seconds,
                    a.request_timeout_seconds,
                ]
                .iter()
                .any(|&t| !(1..=86_400).contains(&t))
            {
                return Err(anyhow!(
                    "--max-concurrent-archives and --max-streams-per-tenant at least 1; --header-timeout-seconds, --body-timeout-seconds and --request-timeout-seconds between 1 and 86400"
                ));
            }
            let cfg = ServeConfig {
                bind: a.bind,
                data_dir: a.data_dir,
                workers: a.workers,
                insecure_no_auth: a.insecure_no_auth,
                lease: Duration::from_secs(a.lease_seconds),
                max_attempts: a.max_attempts,
                max_manifest_bytes: a.max_manifest_bytes,
                max_image_bytes: a.max_image_bytes,
                max_archive_bytes: a.max_archive_bytes,
                max_image_pixels: a.max_image_pixels,
                max_concurrent_archives: a.max_concurrent_archives,
                header_timeout: Duration::from_secs(a.header_timeout_seconds),
                body_timeout: Duration::from_secs(a.body_timeout_seconds),
                request_timeout: Duration::from_secs(a.request_timeout_seconds),
                max_streams_per_tenant: a.max_streams_per_tenant,
            };
            runtime()?.block_on(rigcal::api::serve(cfg))?;
            Ok(0)
        }
        Command::Worker {
            data_dir,
            workers,
            lease_seconds,
            max_image_pixels,
        } => {
            if workers == 0 || workers > 64 || lease_seconds < 1 {
                return Err(anyhow!(
                    "--workers from 1 to 64, --lease-seconds at least 1"
                ));
            }
            runtime()?.block_on(rigcal::jobs::worker::run_standalone(
                &data_dir,
                WorkerConfig {
                    workers,
                    lease: Duration::from_secs(lease_seconds),
                    max_image_pixels,
                    ..WorkerConfig::default()
                },
            ))?;
            Ok(0)
        }
        Command::Apikey {
            what: ApikeyCommand::Create { tenant, data_dir },
        } => {
            let name = tenant.as_str();
            rigcal::session::check_identifier("--tenant", name).map_err(|e| anyhow!("{e}"))?;
            if name == rigcal::api::auth::LOCAL_TENANT {
                return Err(anyhow!(
                    "--tenant: a name other than \"local\" (the tenant of --insecure-no-auth)"
                ));
            }
            let key = runtime()?.block_on(async {
                let store = rigcal::store::Store::open(&data_dir).await?;
                anyhow::Ok(store.create_api_key(name).await?)
            })?;
            println!("{key}");
            eprintln!("API key for tenant {name:?} created; it is shown only now (stored hashed).");
            Ok(0)
        }
        Command::Demo {
            data_dir,
            bind,
            exit,
        } => {
            runtime()?.block_on(rigcal::demo::run(&data_dir, &bind, exit))?;
            Ok(0)
        }
        Command::Synth {
            preset,
            seed,
            noise,
            out,
            images,
            size,
            grey_noise,
            png,
            boards_only,
        } => {
            if !(noise.is_finite() && noise >= 0.0) {
                return Err(anyhow!("--noise: a non-negative pixel σ, got {noise}"));
            }
            if rigcal::synth::hall::PRESETS.contains(&preset.as_str()) {
                if !(grey_noise.is_finite() && grey_noise >= 0.0) {
                    return Err(anyhow!(
                        "--grey-noise: a non-negative σ in grey levels, got {grey_noise}"
                    ));
                }
                let mut hall =
                    rigcal::synth::hall::hall(&preset, seed, size).map_err(|e| anyhow!(e))?;
                if boards_only {
                    hall = hall.boards_only();
                }
                let nuisance = rigcal::synth::hall::Nuisance {
                    noise: grey_noise,
                    jpeg_quality: (!png).then_some(92),
                    ..Default::default()
                };
                let w = rigcal::synth::hall::write_capture(
                    &hall,
                    &out,
                    images.then_some(&nuisance),
                    noise,
                    seed,
                )?;
                eprintln!(
                    "wrote {} ({} images, {} fully visible tags)",
                    out.join("session.json").display(),
                    w.images,
                    w.visible_tags
                );
                return Ok(0);
            }
            if images || size.is_some() || boards_only {
                return Err(anyhow!(
                    "--images/--size/--boards-only: only for the hall presets ({})",
                    rigcal::synth::hall::PRESETS.join(", ")
                ));
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
                BenchCommand::Capture {
                    preset,
                    trials,
                    seed,
                    size,
                    json,
                },
        } => {
            let rows = rigcal::bench::capture::capture_trials(&preset, trials, seed, size)
                .map_err(|e| anyhow!(e))?;
            rigcal::bench::capture::print_table(&preset, &rows);
            if let Some(path) = json {
                std::fs::write(&path, serde_json::to_vec_pretty(&rows)?)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::Ring {
                    trials,
                    noise,
                    seed,
                    images,
                    target_distance,
                    aux_distance,
                    aux_pitch,
                    aux_views,
                    noise_on,
                },
        } => {
            use rigcal::bench::ring::NoiseOn;
            if noise.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(anyhow!("--noise: positive σ values, got {noise:?}"));
            }
            let on = match noise_on.as_str() {
                "both" => NoiseOn::Both,
                "rig" => NoiseOn::Rig,
                "aux" => NoiseOn::Aux,
                other => {
                    return Err(anyhow!("--noise-on: both, rig or aux, got {other:?}"));
                }
            };
            let default = rigcal::synth::ring::RingLayout::default();
            let layout = rigcal::synth::ring::RingLayout {
                target_distance: target_distance.unwrap_or(default.target_distance),
                aux_distance: aux_distance.unwrap_or(default.aux_distance),
                aux_pitch_deg: aux_pitch.unwrap_or(default.aux_pitch_deg),
                aux_views: aux_views.unwrap_or(default.aux_views),
            };
            // (`contains` is false for NaN.)
            let in_range = (0.05..=20.0).contains(&layout.target_distance)
                && (0.2..=20.0).contains(&layout.aux_distance)
                && (5.0..=85.0).contains(&layout.aux_pitch_deg)
                && (1..=5).contains(&layout.aux_views);
            if !in_range {
                return Err(anyhow!(
                    "--target-distance in 0.05..=20 m, --aux-distance in 0.2..=20 m, --aux-pitch in 5..=85 deg, --aux-views in 1..=5"
                ));
            }
            let study = layout != default || on != NoiseOn::Both;
            let rows = if images {
                if study {
                    return Err(anyhow!(
                        "--images renders the default placement; the placement flags are for sampled points"
                    ));
                }
                println!("From rendered images through the line-target detector; σ is image noise in grey levels (of 255).");
                rigcal::bench::ring::ring_accuracy_images(&noise, trials, seed)
            } else {
                if study {
                    println!(
                        "Placement: target {:.2} m ahead, auxiliary camera {:.2} m from the pair at {:.0}° pitch, {} view(s) per pair; noise on {noise_on}.",
                        layout.target_distance, layout.aux_distance, layout.aux_pitch_deg, layout.aux_views
                    );
                }
                rigcal::bench::ring::ring_accuracy_layout(&noise, trials, seed, &layout, on)
            };
            rigcal::bench::ring::print_table(&rows);
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::Detect {
                    views,
                    width,
                    height,
                    seed,
                    out,
                    tag_sizes,
                    only,
                },
        } => {
            if views == 0 || !(64..=8192).contains(&width) || !(64..=8192).contains(&height) {
                return Err(anyhow!(
                    "--views ≥ 1, --width and --height in 64..=8192 pixels"
                ));
            }
            let mut cells = rigcal::bench::detect::study(views, width, height);
            if let Some(sizes) = tag_sizes {
                let [lo, hi] = sizes[..] else {
                    return Err(anyhow!("--tag-sizes: MIN,MAX in pixels, got {sizes:?}"));
                };
                if !(8.0..=2000.0).contains(&lo) || !(lo..=2000.0).contains(&hi) {
                    return Err(anyhow!(
                        "--tag-sizes: 8 ≤ MIN ≤ MAX ≤ 2000 px, got {lo},{hi}"
                    ));
                }
                for c in cells.iter_mut().filter(|c| !c.grid) {
                    c.sizes = (lo, hi);
                }
            }
            // Cells left out keep their place (and so every other cell its seed), empty.
            let grids = match only.as_deref() {
                None => None,
                Some("tags") => Some(false),
                Some("grids") => Some(true),
                Some(other) => return Err(anyhow!("--only: tags or grids, got {other:?}")),
            };
            for c in cells.iter_mut() {
                if grids.is_some_and(|g| g != c.grid) {
                    c.n = 0;
                }
            }
            if let Some(dir) = out {
                rigcal::bench::detect::write_views(&cells, seed, &dir)?;
            }
            let rows: Vec<_> = cells
                .iter()
                .enumerate()
                .filter(|(_, c)| c.n > 0)
                .map(|(i, c)| rigcal::bench::detect::run_cell(c, seed + 1000 * i as u64))
                .collect();
            rigcal::bench::detect::print_table(&rows);
            Ok(0)
        }
        Command::Bench {
            what:
                BenchCommand::Speed {
                    cameras,
                    poses,
                    points,
                    export,
                },
        } => {
            if cameras < 2 || points < 10 || poses.iter().any(|k| *k < 3) {
                return Err(anyhow!(
                    "--cameras ≥ 2, --points ≥ 10 and every --poses ≥ 3"
                ));
            }
            let rows = rigcal::bench::speed::run(cameras, &poses, points, export.as_deref())
                .context("writing the exported problems")?;
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
                let est = e.value.pose();
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

/// `rigcal detect`: targets and camera from JSON files, detections as JSON on stdout.
fn detect_images(
    images: &[PathBuf],
    target: &std::path::Path,
    camera: Option<&std::path::Path>,
    threads: usize,
) -> Result<i32> {
    use rigcal::detect::{detect_tags, DetectOptions};
    use rigcal::pipeline::detection::{decode_gray, DEFAULT_MAX_IMAGE_PIXELS};
    use rigcal::session::{camera_from_spec, CameraSpec, TargetSpec};
    let text = std::fs::read(target).with_context(|| format!("reading {}", target.display()))?;
    let targets: Vec<TargetSpec> = match serde_json::from_slice::<Vec<TargetSpec>>(&text) {
        Ok(t) => t,
        Err(_) => vec![serde_json::from_slice::<TargetSpec>(&text).map_err(|e| {
            anyhow!("--target: a target object (aprilgrid | apriltags | line_target) or an array of them: {e}")
        })?],
    };
    let camera = match camera {
        Some(p) => {
            let text = std::fs::read(p).with_context(|| format!("reading {}", p.display()))?;
            let spec: CameraSpec = serde_json::from_slice(&text)
                .map_err(|e| anyhow!("--camera: a camera as in a session's cameras[]: {e}"))?;
            Some(camera_from_spec(&spec, "camera").map_err(|e| anyhow!("--camera: {e}"))?)
        }
        None => None,
    };
    // Line targets (Wu's L) are found by shape, whatever their size; their lines and
    // corners are reported per L found, left to right.
    let lines_only = targets
        .iter()
        .all(|t| matches!(t, TargetSpec::LineTarget { .. }));
    // The detector's decoder table is built once per thread (as a worker keeps it), not
    // inside the first image's `elapsed_ms`.
    rigcal::detect::quads::warm_up(&DetectOptions::default().quads).map_err(|e| anyhow!(e))?;
    let mut out = Vec::new();
    let mut failures = 0;
    for path in images {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let size = camera.as_ref().map(|c| (c.width, c.height));
        let result = decode_gray(&bytes, size, DEFAULT_MAX_IMAGE_PIXELS).and_then(|gray| {
            let start = std::time::Instant::now();
            let v = if lines_only {
                let lens = rigcal::detect::refine::Lens(camera.as_ref());
                let found = rigcal::detect::linetarget::detect_line_targets(&gray, lens);
                serde_json::json!({ "line_targets": found })
            } else {
                let opts = DetectOptions {
                    threads,
                    ..DetectOptions::default()
                };
                let d = detect_tags(&gray, &targets, camera.as_ref(), &opts)?;
                serde_json::to_value(&d).map_err(|e| e.to_string())?
            };
            Ok((v, start.elapsed().as_secs_f64() * 1e3))
        });
        out.push(match result {
            Ok((mut v, ms)) => {
                v["image"] = serde_json::json!(path.display().to_string());
                v["elapsed_ms"] = serde_json::json!(ms);
                v
            }
            Err(e) => {
                failures += 1;
                serde_json::json!({"image": path.display().to_string(), "error": e})
            }
        });
    }
    let doc = if out.len() == 1 {
        out.remove(0)
    } else {
        serde_json::Value::Array(out)
    };
    println!("{}", serde_json::to_string_pretty(&doc)?);
    Ok(if failures > 0 { 1 } else { 0 })
}
