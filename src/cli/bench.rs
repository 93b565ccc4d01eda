//! `rigcal bench`: the measurement harnesses, printing tables (numbers recorded in
//! docs/accuracy.md and docs/performance.md).

use super::{check_preset, non_negative, parse_size, positive};
use anyhow::{anyhow, Context, Result};
use clap::builder::RangedU64ValueParser;
use std::path::PathBuf;

#[derive(clap::Subcommand)]
pub enum Command {
    /// RMS errors of init and refined extrinsics, CRB and NEES over noisy trials.
    Accuracy {
        #[arg(long, default_value = "lebraly-5.1")]
        preset: String,
        #[arg(long, default_value_t = 50)]
        trials: usize,
        /// Comma-separated pixel noise levels.
        #[arg(long, default_value = "0.1,0.3,0.5,1.0", value_delimiter = ',', value_parser = positive)]
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
        #[arg(long, default_value_t = 0.5, value_parser = non_negative)]
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
        /// accurate | fast
        #[arg(long, default_value = "accurate")]
        detect_quality: rigcal_core::result::DetectionQuality,
    },
    /// Vanishing method on Wu's Table 2 ring: chainwise vs global RMS errors per camera.
    Ring {
        #[arg(long, default_value_t = 50)]
        trials: usize,
        /// Comma-separated noise levels: pixels on the line points, or grey levels of
        /// the rendered images with --images.
        #[arg(long, default_value = "0.2,0.5,1.0", value_delimiter = ',', value_parser = positive)]
        noise: Vec<f64>,
        #[arg(long, default_value_t = 1000)]
        seed: u64,
        /// Render the 16 images of every trial and go through the line-target detector.
        #[arg(long)]
        images: bool,
        /// The print on the targets with --images: `l` (Wu's filled L), `line-grid`
        /// (a "#" of 3 × 3 thin lines, 12 mm strokes, found as ridges) or
        /// `line-grid-marked` (the same with a 60 mm orientation disc in one cell).
        #[arg(long, default_value = "l")]
        target: String,
        /// With --images: render as a real capture shows it (a textured tile floor,
        /// blur, 25 % vignetting, gain and offset, JPEG q 92); --noise is the sensor's.
        #[arg(long, requires = "images")]
        real: bool,
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
        #[arg(long, default_value_t = 40, value_parser = RangedU64ValueParser::<usize>::new().range(1..))]
        views: usize,
        #[arg(long, default_value_t = 1600, value_parser = clap::value_parser!(u32).range(64..=8192))]
        width: u32,
        #[arg(long, default_value_t = 1200, value_parser = clap::value_parser!(u32).range(64..=8192))]
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
        /// accurate | fast
        #[arg(long, default_value = "accurate")]
        detect_quality: rigcal_core::result::DetectionQuality,
    },
    /// Claim latency of the job queue with many jobs waiting, on the store given (run it
    /// against PostgreSQL with --database-url as well as on the SQLite default).
    Queue {
        #[command(flatten)]
        store: super::StoreArgs,
        /// Jobs queued before the claims are timed.
        #[arg(long, default_value_t = 10_000, value_parser = RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
        queued: usize,
        /// Claims timed (each completes its job, as a worker would).
        #[arg(long, default_value_t = 200, value_parser = RangedU64ValueParser::<usize>::new().range(1..=100_000))]
        claims: usize,
    },
    /// Wall time, iterations and final cost of the rig bundle adjustment.
    Speed {
        #[arg(long, default_value_t = 6, value_parser = RangedU64ValueParser::<usize>::new().range(2..))]
        cameras: usize,
        /// Comma-separated numbers of rig poses.
        #[arg(long, default_value = "50,200", value_delimiter = ',', value_parser = RangedU64ValueParser::<usize>::new().range(3..))]
        poses: Vec<usize>,
        #[arg(long, default_value_t = 100, value_parser = RangedU64ValueParser::<usize>::new().range(10..))]
        points: usize,
        /// Each scene seen by this many consecutive rig poses only, a new one every
        /// half window (0: every point in every frame).
        #[arg(long, default_value_t = 0)]
        window: usize,
        /// Also write each problem with rigcal's result as `ba_K.json` here, for
        /// `benches/peers/colmap_ba.py`.
        #[arg(long)]
        export: Option<PathBuf>,
    },
}

pub fn run(c: Command) -> Result<i32> {
    match c {
        Command::Queue {
            store,
            queued,
            claims,
        } => {
            let at = store.location();
            let mut ms = super::runtime()?.block_on(async {
                let s = rigcal_service::store::Store::connect(&at).await?;
                rigcal_service::jobs::bench::claim_latency(&s, queued, claims.min(queued)).await
            })?;
            ms.sort_by(f64::total_cmp);
            let q = |p: f64| ms[((ms.len() - 1) as f64 * p).round() as usize];
            println!(
                "claim with {queued} queued on {}: {} claims, median {:.2} ms, p90 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
                at.describe(),
                ms.len(),
                q(0.5),
                q(0.9),
                q(0.99),
                q(1.0)
            );
            Ok(0)
        }
        Command::Accuracy {
            preset,
            trials,
            noise,
            seed,
        } => {
            check_preset(&preset)?;
            let rows = rigcal_bench::accuracy::accuracy(&preset, &noise, trials, seed);
            rigcal_bench::accuracy::print_table(&preset, &rows);
            Ok(0)
        }
        Command::Capture {
            preset,
            trials,
            seed,
            size,
            json,
            detect_quality,
        } => {
            let rows =
                rigcal_bench::capture::capture_trials(&preset, trials, seed, size, detect_quality)
                    .map_err(|e| anyhow!(e))?;
            rigcal_bench::capture::print_table(&preset, &rows);
            if let Some(path) = json {
                std::fs::write(&path, serde_json::to_vec_pretty(&rows)?)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            Ok(0)
        }
        Command::Ring {
            trials,
            noise,
            seed,
            images,
            target_distance,
            aux_distance,
            aux_pitch,
            aux_views,
            noise_on,
            target,
            real,
        } => {
            use rigcal_bench::ring::NoiseOn;
            let print = match target.as_str() {
                "l" => rigcal_synth::ring::RingPrint::FilledL,
                "line-grid" => rigcal_synth::ring::RingPrint::GRID,
                "line-grid-marked" => rigcal_synth::ring::RingPrint::GRID_MARKED,
                other => {
                    return Err(anyhow!(
                        "--target: l, line-grid or line-grid-marked, got {other:?}"
                    ))
                }
            };
            if !images && print != rigcal_synth::ring::RingPrint::FilledL {
                return Err(anyhow!("--target line-grid renders images: add --images"));
            }
            let on = match noise_on.as_str() {
                "both" => NoiseOn::Both,
                "rig" => NoiseOn::Rig,
                "aux" => NoiseOn::Aux,
                other => {
                    return Err(anyhow!("--noise-on: both, rig or aux, got {other:?}"));
                }
            };
            let default = rigcal_synth::ring::RingLayout::default();
            let layout = rigcal_synth::ring::RingLayout {
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
                println!("From rendered images{} through the line-target detector; σ is image noise in grey levels (of 255).", if real { " as a real capture shows them" } else { "" });
                let nuisance = real.then(rigcal_synth::hall::Nuisance::default);
                rigcal_bench::ring::ring_accuracy_images(&noise, trials, seed, print, nuisance)
            } else {
                if study {
                    println!(
                        "Placement: target {:.2} m ahead, auxiliary camera {:.2} m from the pair at {:.0}° pitch, {} view(s) per pair; noise on {noise_on}.",
                        layout.target_distance, layout.aux_distance, layout.aux_pitch_deg, layout.aux_views
                    );
                }
                rigcal_bench::ring::ring_accuracy_layout(&noise, trials, seed, &layout, on)
            };
            rigcal_bench::ring::print_table(&rows);
            Ok(0)
        }
        Command::Detect {
            views,
            width,
            height,
            seed,
            out,
            tag_sizes,
            only,
            detect_quality,
        } => {
            let mut cells = rigcal_bench::detect::study(views, width, height);
            for c in cells.iter_mut() {
                c.quality = detect_quality;
            }
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
                rigcal_bench::detect::write_views(&cells, seed, &dir)?;
            }
            let rows: Vec<_> = cells
                .iter()
                .enumerate()
                .filter(|(_, c)| c.n > 0)
                .map(|(i, c)| rigcal_bench::detect::run_cell(c, seed + 1000 * i as u64))
                .collect();
            rigcal_bench::detect::print_table(&rows);
            Ok(0)
        }
        Command::Speed {
            cameras,
            poses,
            points,
            window,
            export,
        } => {
            let rows = rigcal_bench::speed::run(cameras, &poses, points, window, export.as_deref())
                .context("writing the exported problems")?;
            rigcal_bench::speed::print_table(cameras, points, &rows);
            Ok(0)
        }
        Command::HandeyeExport {
            preset,
            trials,
            noise,
            seed,
        } => {
            check_preset(&preset)?;
            let t = rigcal_bench::accuracy::handeye_trials(&preset, noise, trials, seed);
            println!("{}", serde_json::to_string(&t)?);
            Ok(0)
        }
    }
}
