//! Detection from images (issue 3): AprilTag tag36h11 corners with subpixel edge
//! refinement, Kalibr AprilGrids completed through their layout.
//!
//! Pipeline per image: quad candidates from the AprilTag 3 C detector ([`quads`]) →
//! each candidate's corners re-measured from its outer edges ([`refine`]) → candidates
//! assigned to the session's targets by id → each AprilGrid checked and completed
//! through its layout ([`grid`]). Points are measured on the raw image and reported in
//! raw pixels (the calibration models distortion itself); with a camera, the sides are
//! fitted in the undistorted plane so distortion does not bend them. Nothing is
//! resampled.

mod blur;
pub mod crossings;
pub mod gray;
mod grid;
pub mod imageio;
pub mod linegrid;
pub mod linetarget;
pub mod quads;
pub mod refine;
pub mod ridge;
pub mod tagfit;
mod verify;

use gray::Gray;
use refine::{refine_quad, Lens};
use rigcal_core::geometry::{Camera, Vec2};
use rigcal_core::par::par_map;
use rigcal_core::session::TargetSpec;
use rigcal_core::target::board::GridLayout;
use serde::Serialize;
use std::collections::BTreeMap;

/// How far (px) the quad detector's sides may be from the true ones: in AprilGrids its
/// quads often take in the crossing squares and sit 2-4 px out.
const QUAD_REACH: f64 = 4.0;

/// [`Quality::Fast`] fits whole only the tags under this many pixels, where the edge
/// measurement's error grows fastest.
pub const FAST_WHOLE_FIT_BELOW_PX: f64 = 30.0;

pub use rigcal_core::result::DetectionQuality as Quality;

#[derive(Clone, Debug)]
pub struct DetectOptions {
    pub quads: quads::QuadOptions,
    /// Search the full-resolution image as well as the decimated one: for single tags the
    /// decimated search loses (small oblique ones), and, bright-grown, for boards with no
    /// seed. Off, the bright-grown search runs on the decimated image.
    pub full_resolution: bool,
    /// Tags whose shallowest extent is under this many pixels are fitted whole
    /// ([`tagfit`]): their corners come out ~5× more accurate than the edge
    /// measurement's (0.05-0.1 px RMS under ~40 px), at ~1-3 ms per tag. 0: no fits.
    pub whole_fit_below: f64,
    /// Threads for the per-tag work of one image (edge refinement, whole-tag fits). 1
    /// where images are detected in parallel already (a job, `rigcal calibrate`); the
    /// cores for one image on its own (`rigcal detect`).
    pub threads: usize,
    /// Distance (px) between the edge profiles that measure a side
    /// ([`refine::SideSampling::spacing`]): one per pixel, or one per independent fit for
    /// [`Quality::Fast`].
    pub profile_spacing: f64,
}

impl Default for DetectOptions {
    fn default() -> Self {
        Self::of_quality(Quality::Accurate)
    }
}

impl DetectOptions {
    /// The options of a [`Quality`], on one thread.
    pub fn of_quality(quality: Quality) -> Self {
        let accurate = quality == Quality::Accurate;
        Self {
            quads: quads::QuadOptions::default(),
            full_resolution: accurate,
            whole_fit_below: if accurate {
                tagfit::WHOLE_FIT_BELOW_PX
            } else {
                FAST_WHOLE_FIT_BELOW_PX
            },
            threads: 1,
            profile_spacing: if accurate {
                1.0
            } else {
                refine::INDEPENDENT_SPACING
            },
        }
    }
}

/// One tag found in an image.
#[derive(Clone, Debug, Serialize)]
pub struct TagDetection {
    pub target: String,
    pub id: u32,
    /// Raw pixels, corner `k` counter-clockwise from the tag's bottom-left.
    pub corners: [[f64; 2]; 4],
    /// Bit errors corrected when decoding.
    pub hamming: u32,
    /// Decision margin: the quad detector's for `quad` tags, the mean white − black
    /// cell level for `layout` tags.
    pub margin: f64,
    /// Grey-level step across the tag's outer edges.
    pub contrast: f64,
    /// RMS distance (px) of the measured edge points from the fitted sides.
    pub edge_rms: f64,
    /// `quad` (found by the quad detector) or `layout` (predicted from the board
    /// layout, then measured and its bits verified).
    pub source: &'static str,
}

/// One measured point, named as the session names it.
#[derive(Clone, Debug, Serialize)]
pub struct PointDetection {
    pub point: String,
    pub u: f64,
    pub v: f64,
    /// Board coordinates (m) for AprilGrid corners.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board: Option<[f64; 3]>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Rejection {
    pub id: u32,
    pub reason: String,
}

/// Everything found in one image.
#[derive(Clone, Debug, Serialize)]
pub struct ImageDetections {
    pub width: usize,
    pub height: usize,
    pub tags: Vec<TagDetection>,
    pub points: Vec<PointDetection>,
    /// Candidates found and then refused, with why.
    pub rejected: Vec<Rejection>,
}

/// What the detector looks for, from the session's targets.
enum Wanted<'a> {
    Grid(&'a str, GridLayout),
    Tags(&'a str, Option<&'a [u32]>),
}

fn wanted(targets: &[TargetSpec]) -> Vec<Wanted<'_>> {
    targets
        .iter()
        .filter_map(|t| match t {
            TargetSpec::Aprilgrid { id, .. } => Some(Wanted::Grid(id, GridLayout::of(t)?)),
            TargetSpec::Apriltags { id, ids, .. } => Some(Wanted::Tags(id, ids.as_deref())),
            _ => None,
        })
        .collect()
}

/// Detect the AprilTag targets of `targets` in `img`.
pub fn detect_tags(
    img: &Gray,
    targets: &[TargetSpec],
    camera: Option<&Camera>,
    opts: &DetectOptions,
) -> Result<ImageDetections, String> {
    let lens = Lens(camera);
    let wanted = wanted(targets);
    // Every pass below segments with the same contrast floor: the noise is estimated once.
    let base = quads::QuadOptions {
        min_contrast: Some(opts.quads.contrast_for(img)),
        ..opts.quads.clone()
    };
    let px = img.to_u8();
    let (w, h) = (img.width, img.height);
    // Single tags have no layout to complete them from, and the decimated search loses
    // small oblique ones (9 in 10 of those missed among 120 views of 24-40 px tags at up
    // to 60° were found at full resolution): where they are wanted the search is at full
    // resolution. On a sharp image it finds what the decimated one finds besides (the
    // same 5 531 tags on a dense 1080p hall), so that one runs only where the found tags'
    // edges say the image is blurred, or cannot say ([`blur`]): 8 % of a sharp hall
    // image's time.
    let searched_full = opts.full_resolution
        && base.decimate > 1.0
        && wanted.iter().any(|w| matches!(w, Wanted::Tags(..)));
    let full = quads::QuadOptions {
        decimate: 1.0,
        ..base.clone()
    };
    let first = if searched_full { &full } else { &base };
    let mut candidates = quads::detect_pixels(&px, w, h, first)?;
    if searched_full {
        let quads: Vec<[Vec2; 4]> = candidates.iter().map(|c| c.corners).collect();
        if blur::edge_blur(img, &quads).is_none_or(|b| b > blur::SHARP_PX) {
            let seen: std::collections::BTreeSet<u32> = candidates.iter().map(|c| c.id).collect();
            candidates.extend(
                quads::detect_pixels(&px, w, h, &base)?
                    .into_iter()
                    .filter(|c| !seen.contains(&c.id)),
            );
        }
    }
    let mut rejected = Vec::new();
    let mut refined = refine_candidates(img, candidates, lens, opts, &mut rejected);
    // A board with no seed at all gets a second search, at full resolution on a copy
    // whose bright areas are grown by a pixel, for its ids only: Kalibr's crossing
    // squares touch every tag corner, and where blur and decimation keep the contact
    // (small or oblique boards: 1 view in 10 lost the whole board at 30 px tags) the
    // first pass finds no quad at all. The grown copy thins black bits, so every id it
    // decodes is read again from the image itself before it counts.
    let seedless: Vec<&GridLayout> = wanted
        .iter()
        .filter_map(|w| match w {
            Wanted::Grid(_, layout) if !layout.ids().any(|id| refined.contains_key(&id)) => {
                Some(layout)
            }
            _ => None,
        })
        .collect();
    if !seedless.is_empty() {
        let grown = quads::QuadOptions {
            decimate: if opts.full_resolution {
                1.0
            } else {
                base.decimate
            },
            grow_bright: true,
            ..base.clone()
        };
        let max_h = opts.quads.max_hamming;
        // Those searches segment only the crops where an unseeded board may lie (the
        // image's X-junctions that no found tag explains): the whole image costs as much
        // as the first search, and the board is usually out of view.
        // The boards in view explain their own junctions, found tags or not (`fast`'s
        // first search finds a few tags of each board, the layout the rest later): on
        // the dense hall half the crops were the unfound parts of seeded boards.
        let mut found_quads: Vec<[Vec2; 4]> = refined.values().map(|f| f.refined.corners).collect();
        for w in &wanted {
            if let Wanted::Grid(_, layout) = w {
                let seeds: BTreeMap<u32, [Vec2; 4]> = layout
                    .ids()
                    .filter_map(|id| Some((id, refined.get(&id)?.refined.corners)))
                    .collect();
                found_quads.extend(grid::predicted_rest(layout, &seeds, lens, img));
            }
        }
        let floor = base.min_contrast.unwrap_or(quads::MIN_CONTRAST_RANGE.0);
        let crops = crossings::board_crops(&px, w, h, floor, &found_quads);
        let search = |o: &quads::QuadOptions| -> Result<Vec<quads::Candidate>, String> {
            let mut out = Vec::new();
            for r in &crops {
                out.extend(quads::detect_pixels_in(&px, w, h, *r, o)?);
            }
            Ok(out)
        };
        let mut again: Vec<quads::Candidate> = search(&grown)?;
        // Boards of small tags (1.5-2.2 px per cell) keep their corner contacts on the
        // image and lose their black bits on the grown copy: a search of the image
        // upsampled 2× and grown by half a pixel seeds them (boards of 15-18 px tags:
        // none of 36 tags on either, 15-36 there). Its quads are searched at 1.5
        // decimation of the 2× copy (the C library's 3 → 2 block average, 1.33 samples
        // per image pixel): at 2, boards of 12-13 px tags stay unseeded (hand-held
        // fisheye captures: a whole board of 22 such tags in one view). It costs one
        // more segmentation of the crops, at 1.8× their pixels, and runs whenever a
        // board has no seed, which includes every board out of view; so an image pays
        // at most three segmentations: where the session has single tags, their plain
        // full-resolution search (above) stands in for it (it seeds some of those
        // boards, not all: a dense 1080p hall was 23 % slower with both, for no tag
        // more). `fast` runs it too: without it, hand-held fisheye views lost whole
        // boards of 15-19 px tags (95.8 % of the tags found, 98.4 % with it, as in
        // `accurate`), for 1-10 % more instructions on the hall presets.
        let unseeded: Vec<&GridLayout> = if !searched_full {
            seedless
                .iter()
                .copied()
                .filter(|l| !again.iter().any(|c| l.cell_of(c.id).is_some()))
                .collect()
        } else {
            Vec::new()
        };
        if !unseeded.is_empty() {
            let fine = quads::QuadOptions {
                upsample: true,
                decimate: 1.5,
                grow_bright: true,
                ..base.clone()
            };
            again.extend(
                search(&fine)?
                    .into_iter()
                    .filter(|c| unseeded.iter().any(|l| l.cell_of(c.id).is_some())),
            );
        }
        again.retain(|c| seedless.iter().any(|l| l.cell_of(c.id).is_some()));
        // Crops overlap at their margins: an id found twice is kept once.
        let mut ids = std::collections::BTreeSet::new();
        again.retain(|c| ids.insert(c.id));
        let mut second = Vec::new();
        let found: BTreeMap<u32, grid::Found> =
            refine_candidates(img, again, lens, opts, &mut second)
                .into_iter()
                .filter(|(id, f)| {
                    let reading = verify::read_tag(img, &f.refined.corners, lens, *id);
                    let ok = reading
                        .as_ref()
                        .is_some_and(|r| r.hamming <= max_h && r.border_black >= 26);
                    if !ok {
                        second.push(Rejection {
                            id: *id,
                            reason: format!(
                                "tag {id}: found on the bright-grown image but its bits do not read as {id} in the image"
                            ),
                        });
                    }
                    ok
                })
                .collect();
        // Ids refused in the first pass and found now are no longer refused.
        rejected.retain(|r| !found.contains_key(&r.id));
        // (A refusal repeated by the second pass is said once.)
        second.retain(|r| !rejected.iter().any(|q| q.id == r.id));
        rejected.extend(second);
        refined.extend(found);
    }
    let mut tags = Vec::new();
    let mut points = Vec::new();
    let mut dropped_corners = Vec::new();
    // Where a tag fitted whole has no edge blur of its own (its sides too close to its
    // bits for the edge fit), the image's starts the fit.
    let image_blur =
        rigcal_solve::loss::median(refined.values().filter_map(|f| f.refined.blur).collect());
    let finish = |id: u32, f: &grid::Found, layout: Option<&GridLayout>| {
        if opts.whole_fit_below > 0.0 {
            whole_tag_corners(
                img,
                &f.refined,
                lens,
                id,
                layout,
                opts.whole_fit_below,
                image_blur,
            )
        } else {
            (f.refined.corners, [None; 4])
        }
    };
    let mut emit = |target: &str,
                    id: u32,
                    f: &grid::Found,
                    (c, unmeasured): &Measured,
                    layout: Option<&GridLayout>| {
        tags.push(TagDetection {
            target: target.to_string(),
            id,
            corners: [0, 1, 2, 3].map(|k| [c[k].x, c[k].y]),
            hamming: f.hamming,
            margin: f.margin,
            contrast: f.refined.contrast,
            edge_rms: f.refined.edge_rms,
            source: if f.predicted { "layout" } else { "quad" },
        });
        for (k, p) in c.iter().enumerate() {
            if !measured_inside(img, p) {
                dropped_corners.push(Rejection {
                    id,
                    reason: format!(
                        "tag {id} corner {k}: within {BORDER_MARGIN} px of the image border, where its sides cannot be measured"
                    ),
                });
                continue;
            }
            if let Some(why) = unmeasured[k] {
                let reason = match why {
                    Unmeasured::Misfit => format!("tag {id} corner {k}: the image round it does not match the tag's surround (something in front of it?)"),
                    Unmeasured::TooSmall => format!("tag {id} corner {k}: under {MIN_EDGE_CELL_PX} px per cell and the whole-tag fit did not settle, so its edges cannot place it"),
                };
                dropped_corners.push(Rejection { id, reason });
                continue;
            }
            points.push(PointDetection {
                point: format!("tag:{id}:{k}"),
                u: p.x,
                v: p.y,
                board: layout
                    .and_then(|l| l.corner(id, k))
                    .map(|b| [b.x, b.y, 0.0]),
            });
        }
    };
    // Boards first: their ids are theirs.
    for w in &wanted {
        if let Wanted::Grid(name, layout) = w {
            let seeds: BTreeMap<u32, grid::Found> = layout
                .ids()
                .filter_map(|id| refined.remove(&id).map(|f| (id, f)))
                .collect();
            if seeds.is_empty() {
                continue;
            }
            let mut rej = Vec::new();
            let completed: Vec<(u32, grid::Found)> =
                grid::complete(img, layout, seeds, lens, opts, &mut rej)
                    .into_iter()
                    .collect();
            let fitted = par_map(&completed, opts.threads, |(id, f)| {
                finish(*id, f, Some(layout))
            });
            let board: Vec<(u32, grid::Found, Measured)> = completed
                .into_iter()
                .zip(fitted)
                .map(|((id, f), c)| (id, f, c))
                .collect();
            let corners: BTreeMap<u32, [Vec2; 4]> =
                board.iter().map(|(id, _, c)| (*id, c.0)).collect();
            let off = grid::inconsistent(layout, &corners, lens);
            for (id, f, c) in &board {
                match off.get(id) {
                    Some(dev) => rej.push((
                        *id,
                        format!("tag {id}: measured {dev:.1} px from where its neighbours on the board put it (its edges were found on the wrong transitions)"),
                    )),
                    None => emit(name, *id, f, c, Some(layout)),
                }
            }
            rejected.extend(rej.into_iter().map(|(id, reason)| Rejection { id, reason }));
        }
    }
    for w in &wanted {
        if let Wanted::Tags(name, ids) = w {
            let take: Vec<u32> = refined
                .keys()
                .copied()
                .filter(|id| ids.is_none_or(|l| l.contains(id)))
                .collect();
            let found: Vec<(u32, grid::Found)> = take
                .into_iter()
                .filter_map(|id| refined.remove(&id).map(|f| (id, f)))
                .collect();
            let fitted = par_map(&found, opts.threads, |(id, f)| finish(*id, f, None));
            for ((id, f), c) in found.iter().zip(&fitted) {
                emit(name, *id, f, c, None);
            }
        }
    }
    // A candidate refused early and then found through the layout is not refused.
    rejected.retain(|r| !tags.iter().any(|t| t.id == r.id));
    rejected.extend(dropped_corners);
    for id in refined.keys() {
        rejected.push(Rejection {
            id: *id,
            reason: format!("tag {id} belongs to none of the session's targets"),
        });
    }
    Ok(ImageDetections {
        width: img.width,
        height: img.height,
        tags,
        points,
        rejected,
    })
}

/// How far inside the image (px) a corner must lie to be reported: the edge measurement
/// reads ±2.5 px across a side ([`refine`]), so closer to the border some of the pixels
/// that would measure it are not in the image, and a corner completed from the layout or
/// extrapolated from the sides may even lie outside it.
pub const BORDER_MARGIN: f64 = 3.0;

/// Is the corner at `p` measured by pixels inside the image?
fn measured_inside(img: &Gray, p: &Vec2) -> bool {
    p.x.is_finite()
        && p.y.is_finite()
        && p.x >= BORDER_MARGIN
        && p.y >= BORDER_MARGIN
        && p.x <= img.width as f64 - 1.0 - BORDER_MARGIN
        && p.y <= img.height as f64 - 1.0 - BORDER_MARGIN
}

/// The corners a tag is reported with, and which are left out: a tag too small for the
/// edge measurement's room is fitted whole ([`tagfit`]), from the edge-refined corners,
/// and corners its surround misfits are left out; where that fit does not settle the
/// edge-refined corners stand, unless the tag is too small for them.
fn whole_tag_corners(
    img: &Gray,
    refined: &refine::Refined,
    lens: Lens,
    id: u32,
    layout: Option<&GridLayout>,
    below: f64,
    image_blur: Option<f64>,
) -> Measured {
    let corners = &refined.corners;
    if tagfit::shallowest_extent(corners) >= below {
        return (*corners, [None; 4]);
    }
    let surround = match layout {
        Some(l) => tagfit::Surround::Grid {
            gap_cells: l.spacing * rigcal_core::target::tag36h11::WIDTH_AT_BORDER as f64,
        },
        None => tagfit::Surround::Single,
    };
    match tagfit::fit_whole_tag(
        img,
        corners,
        lens,
        id,
        surround,
        refined.blur.or(image_blur),
    ) {
        Some(f) => (f.corners, f.misfit.map(|m| m.then_some(Unmeasured::Misfit))),
        // Under 2 px per cell the edges can be a pixel off (a side measured against the
        // bits beside it): without the fit such a tag has no corner worth reporting.
        None if verify::cell_px(corners) < MIN_EDGE_CELL_PX => {
            (*corners, [Some(Unmeasured::TooSmall); 4])
        }
        None => (*corners, [None; 4]),
    }
}

/// Cell size (px) under which a tag's corners come from the whole-tag fit or not at all.
const MIN_EDGE_CELL_PX: f64 = 2.0;

/// Why a detected tag's corner is not reported.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Unmeasured {
    /// The image round it does not match the tag's surround ([`tagfit::WholeFit::misfit`]).
    Misfit,
    /// The tag is too small for its edges, and the whole-tag fit did not settle.
    TooSmall,
}

/// A tag's reported corners, and per corner why it is left out (`None`: reported).
type Measured = ([Vec2; 4], [Option<Unmeasured>; 4]);

/// Refine every candidate whose id appears once in the image (an id seen twice is
/// ambiguous: neither copy is used); refusals go to `rejected` with why.
fn refine_candidates(
    img: &Gray,
    candidates: Vec<quads::Candidate>,
    lens: Lens,
    opts: &DetectOptions,
    rejected: &mut Vec<Rejection>,
) -> BTreeMap<u32, grid::Found> {
    let mut count: BTreeMap<u32, usize> = BTreeMap::new();
    for c in &candidates {
        *count.entry(c.id).or_default() += 1;
    }
    let (unique, repeated): (Vec<_>, Vec<_>) =
        candidates.into_iter().partition(|c| count[&c.id] == 1);
    for c in repeated {
        rejected.push(Rejection {
            id: c.id,
            reason: format!("tag {} appears {} times in the image", c.id, count[&c.id]),
        });
    }
    let results = par_map(&unique, opts.threads, |c| {
        refine_candidate(img, c, lens, opts)
    });
    let mut refined = BTreeMap::new();
    for (c, r) in unique.into_iter().zip(results) {
        match r {
            Some(r) => {
                refined.insert(
                    c.id,
                    grid::Found {
                        refined: r,
                        hamming: c.hamming,
                        margin: c.margin,
                        predicted: false,
                    },
                );
            }
            None => rejected.push(Rejection {
                id: c.id,
                reason: format!(
                    "tag {}: its edges could not be measured (cut by the image border, too small or blurred)",
                    c.id
                ),
            }),
        }
    }
    refined
}

/// Refine a quad-detector candidate. In AprilGrids the quad sometimes runs one corner
/// out along a crossing square (10 px and more); then each corner in turn is replaced by
/// the parallelogram completion of the other three, and the variant whose sides measure
/// cleanly and whose bits read as the candidate's id is kept.
fn refine_candidate(
    img: &Gray,
    c: &quads::Candidate,
    lens: Lens,
    opts: &DetectOptions,
) -> Option<refine::Refined> {
    let spacing = opts.profile_spacing;
    if let Some(r) = refine_quad(img, &c.corners, lens, QUAD_REACH, spacing) {
        return Some(r);
    }
    let q = &c.corners;
    (0..4)
        .filter_map(|k| {
            let mut v = *q;
            v[k] = q[(k + 1) % 4] + q[(k + 3) % 4] - q[(k + 2) % 4];
            let r = refine_quad(img, &v, lens, QUAD_REACH, spacing)?;
            let reading = verify::read_tag(img, &r.corners, lens, c.id)?;
            (reading.hamming <= opts.quads.max_hamming && reading.border_black >= 26).then_some(r)
        })
        .min_by(|a, b| a.edge_rms.total_cmp(&b.edge_rms))
}

/// Corner `k` of a detection as a vector.
pub fn corner(t: &TagDetection, k: usize) -> Vec2 {
    Vec2::new(t.corners[k][0], t.corners[k][1])
}
