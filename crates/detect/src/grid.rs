//! AprilGrid completion: the board's known layout finds the tags the quad detector
//! missed (Kalibr grids' crossing squares touch every tag corner and break its quad
//! segmentation), and rejects detections that do not sit where the layout says.
//!
//! Prediction is local: a tag's corners come from a homography fitted to the nearest
//! accepted tags (grid distance), in the undistorted plane when the camera is known, so
//! lens distortion and slight board bending do not accumulate across the board.

use super::gray::Gray;
use super::refine::{refine_quad, Lens, Refined};
use super::verify::read_tag;
use super::DetectOptions;
use rigcal_core::geometry::homography::homography_of_general_position as homography;
use rigcal_core::geometry::{Mat3, Vec2, Vec3};
use rigcal_core::target::board::GridLayout;
use std::collections::BTreeMap;

/// How far (px) a predicted side may be from the real one.
const PREDICTION_REACH: f64 = 3.0;
/// Tags used to predict a neighbour.
const NEAREST: usize = 4;

pub struct Found {
    pub refined: Refined,
    pub hamming: u32,
    pub margin: f64,
    pub predicted: bool,
}

/// Homography board → plane from the accepted tags nearest to `(row, col)`.
fn local_homography(
    layout: &GridLayout,
    plane: &BTreeMap<u32, [Vec2; 4]>,
    row: u32,
    col: u32,
    exclude: Option<u32>,
) -> Option<Mat3> {
    let mut near: Vec<(u32, u32)> = plane
        .keys()
        .filter(|&&id| Some(id) != exclude)
        .filter_map(|&id| {
            let (r, c) = layout.cell_of(id)?;
            Some((r.abs_diff(row).max(c.abs_diff(col)), id))
        })
        .collect();
    near.sort();
    near.truncate(NEAREST);
    if near.is_empty() {
        return None;
    }
    let (mut a, mut x) = (Vec::new(), Vec::new());
    for (_, id) in &near {
        for k in 0..4 {
            a.push(layout.corner(*id, k)?);
            x.push(plane[id][k]);
        }
    }
    homography(&a, &x)
}

fn predict(layout: &GridLayout, h: &Mat3, id: u32, lens: Lens, img: &Gray) -> Option<[Vec2; 4]> {
    let mut out = [Vec2::zeros(); 4];
    for (k, o) in out.iter_mut().enumerate() {
        let b = layout.corner(id, k)?;
        let p = h * Vec3::new(b.x, b.y, 1.0);
        if p.z.abs() < 1e-12 {
            return None;
        }
        *o = lens.to_pixel(Vec2::new(p.x / p.z, p.y / p.z))?;
        let margin = 2.0;
        if o.x < margin
            || o.y < margin
            || o.x > img.width as f64 - 1.0 - margin
            || o.y > img.height as f64 - 1.0 - margin
        {
            return None;
        }
    }
    Some(out)
}

/// How far (px) a tag's final corners may be from where its board neighbours put them.
/// Corners are measured to a few hundredths of a pixel and the local homography
/// carries that to well under half a pixel (under a pixel without the camera, where the
/// plane keeps the lens's distortion); a tag several pixels off was measured on the
/// wrong transitions, e.g. a crossing square taken for its corner, while its bits still
/// read right.
pub const CONSISTENT_PX: f64 = 1.5;

/// The tags of one board (final corners, raw pixels) that sit more than
/// [`CONSISTENT_PX`] from where their nearest neighbours' homography puts them, with the
/// deviation. Worst first, one at a time, so one wrong tag does not condemn the correct
/// neighbours it would pull; judged only with at least 3 neighbours to judge by.
pub fn inconsistent(
    layout: &GridLayout,
    corners: &BTreeMap<u32, [Vec2; 4]>,
    lens: Lens,
) -> BTreeMap<u32, f64> {
    let mut plane: BTreeMap<u32, [Vec2; 4]> = corners
        .iter()
        .filter_map(|(id, c)| Some((*id, lens.quad_to_plane(c)?)))
        .collect();
    let mut out = BTreeMap::new();
    while plane.len() >= 4 {
        let worst = plane
            .keys()
            .filter_map(|&id| {
                let (r, c) = layout.cell_of(id)?;
                let h = local_homography(layout, &plane, r, c, Some(id))?;
                let dev = (0..4)
                    .map(|k| {
                        let b = layout.corner(id, k)?;
                        let p = h * Vec3::new(b.x, b.y, 1.0);
                        let q = lens.to_pixel(Vec2::new(p.x / p.z, p.y / p.z))?;
                        Some((q - corners[&id][k]).norm())
                    })
                    .try_fold(0.0f64, |m, d| d.map(|d| m.max(d)))?;
                Some((id, dev))
            })
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match worst {
            Some((id, dev)) if dev > CONSISTENT_PX => {
                plane.remove(&id);
                out.insert(id, dev);
            }
            _ => break,
        }
    }
    out
}

/// Where the tags of `layout` not among `found` (its found tags' corners, by id) should
/// be, from their nearest found neighbours: the extent of a board in view, before its
/// missing tags are measured. Predictions whose size is not within a factor 2 of the
/// found tags' are left out (a far extrapolation from a lone seed).
pub fn predicted_rest(
    layout: &GridLayout,
    found: &BTreeMap<u32, [Vec2; 4]>,
    lens: Lens,
    img: &Gray,
) -> Vec<[Vec2; 4]> {
    let plane: BTreeMap<u32, [Vec2; 4]> = found
        .iter()
        .filter_map(|(id, c)| Some((*id, lens.quad_to_plane(c)?)))
        .collect();
    let size = |c: &[Vec2; 4]| (c[2] - c[0]).norm().max((c[3] - c[1]).norm());
    let Some(seed_size) = found.values().map(size).max_by(f64::total_cmp) else {
        return Vec::new();
    };
    layout
        .ids()
        .filter(|id| !found.contains_key(id))
        .filter_map(|id| {
            let (r, c) = layout.cell_of(id)?;
            let h = local_homography(layout, &plane, r, c, None)?;
            predict(layout, &h, id, lens, img)
        })
        .filter(|c| (0.5 * seed_size..=2.0 * seed_size).contains(&size(c)))
        .collect()
}

/// Complete and check one board. `seeds` are the refined quad-detector tags whose ids
/// belong to the board (at most one per id); predicted tags are measured and read as
/// `opts` says (its profile spacing and bit errors).
pub fn complete(
    img: &Gray,
    layout: &GridLayout,
    seeds: BTreeMap<u32, Found>,
    lens: Lens,
    opts: &DetectOptions,
    rejected: &mut Vec<(u32, String)>,
) -> BTreeMap<u32, Found> {
    let mut found = BTreeMap::new();
    let mut plane = BTreeMap::new();
    for (id, f) in seeds {
        if let Some(p) = lens.quad_to_plane(&f.refined.corners) {
            plane.insert(id, p);
            found.insert(id, f);
        }
    }
    // Each seed must sit where its neighbours put it (with at least 2 other tags to judge).
    if found.len() >= 3 {
        let ids: Vec<u32> = found.keys().copied().collect();
        for id in ids {
            let Some((r, c)) = layout.cell_of(id) else {
                continue;
            };
            let Some(h) = local_homography(layout, &plane, r, c, Some(id)) else {
                continue;
            };
            let Some(pred) = predict(layout, &h, id, lens, img) else {
                continue;
            };
            let got = &found[&id].refined.corners;
            let side = (got[1] - got[0]).norm().max((got[2] - got[1]).norm());
            let err = (0..4)
                .map(|k| (pred[k] - got[k]).norm())
                .fold(0.0, f64::max);
            // Refined corners are good to hundredths of a pixel; a seed pixels off its
            // neighbours was refined on the wrong transitions. Dropped here, the growth
            // below measures it again from where the layout puts it.
            if err > (0.03 * side).max(CONSISTENT_PX) {
                rejected.push((
                    id,
                    format!("tag {id} lies {err:.1} px from where the board layout puts it"),
                ));
                found.remove(&id);
                plane.remove(&id);
            }
        }
    }
    // Grow from the accepted tags to their neighbours until nothing more is found. A tag
    // is tried again when it has gained found neighbours: a prediction extrapolated from
    // two tags (a board cut by the border, found a corner at a time) can miss by more
    // than the reach of a 12 px tag's sides, and the same tag predicted from the
    // neighbours found since lands on it.
    let mut tried: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
    let neighbours = |found: &BTreeMap<u32, Found>, id: u32| -> usize {
        let Some((r, c)) = layout.cell_of(id) else {
            return 0;
        };
        found
            .keys()
            .filter(|&&o| {
                layout
                    .cell_of(o)
                    .is_some_and(|(ro, co)| ro.abs_diff(r) <= 1 && co.abs_diff(c) <= 1)
            })
            .count()
    };
    loop {
        let mut added = false;
        let frontier: Vec<(u32, usize)> = layout
            .ids()
            .filter(|id| !found.contains_key(id))
            .map(|id| (id, neighbours(&found, id)))
            .filter(|&(id, n)| n > 0 && tried.get(&id).is_none_or(|&m| n > m))
            .collect();
        for (id, n) in frontier {
            tried.insert(id, n);
            let Some((r, c)) = layout.cell_of(id) else {
                continue;
            };
            let Some(h) = local_homography(layout, &plane, r, c, None) else {
                continue;
            };
            let Some(pred) = predict(layout, &h, id, lens, img) else {
                continue;
            };
            let Some(refined) =
                refine_quad(img, &pred, lens, PREDICTION_REACH, opts.profile_spacing)
            else {
                continue;
            };
            let Some(reading) = read_tag(img, &refined.corners, lens, id) else {
                continue;
            };
            let strong = reading.margin >= (0.3 * refined.contrast).max(10.0);
            if reading.hamming <= opts.quads.max_hamming && reading.border_black >= 26 && strong {
                if let Some(p) = lens.quad_to_plane(&refined.corners) {
                    plane.insert(id, p);
                    found.insert(
                        id,
                        Found {
                            refined,
                            hamming: reading.hamming,
                            margin: reading.margin,
                            predicted: true,
                        },
                    );
                    added = true;
                }
            }
        }
        if !added {
            break;
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rest_of_a_seeded_board_is_predicted_where_it_lies() {
        // A 6 × 6 board seen in perspective (a homography board → pixels), three seeds
        // in one corner: every other tag inside the image is predicted exactly, the
        // ones across the image border are left out, the seeds are not repeated.
        let layout = GridLayout {
            rows: 6,
            cols: 6,
            tag_size: 0.088,
            spacing: 0.3,
            first_id: 0,
        };
        let h = Mat3::new(500.0, 60.0, 40.0, -40.0, 540.0, 30.0, 0.3, 0.5, 1.0);
        let to_px = |id: u32| {
            [0, 1, 2, 3].map(|k| {
                let b = layout.corner(id, k).unwrap();
                let p = h * Vec3::new(b.x, b.y, 1.0);
                Vec2::new(p.x / p.z, p.y / p.z)
            })
        };
        let img = Gray {
            width: 240,
            height: 220,
            data: vec![0.0; 240 * 220],
        };
        let inside = |c: &[Vec2; 4]| {
            c.iter()
                .all(|p| p.x > 2.0 && p.y > 2.0 && p.x < 237.0 && p.y < 217.0)
        };
        let seeds: BTreeMap<u32, [Vec2; 4]> = [0, 1, 6].map(|id| (id, to_px(id))).into();
        let rest = predicted_rest(&layout, &seeds, Lens(None), &img);
        let expected: Vec<[Vec2; 4]> = layout
            .ids()
            .filter(|id| !seeds.contains_key(id))
            .map(to_px)
            .filter(inside)
            .collect();
        assert!(
            expected.len() > 10 && expected.len() < 33,
            "{}",
            expected.len()
        );
        assert_eq!(rest.len(), expected.len());
        for (p, e) in rest.iter().zip(&expected) {
            for k in 0..4 {
                assert!((p[k] - e[k]).norm() < 1e-6, "{p:?} {e:?}");
            }
        }
        assert!(predicted_rest(&layout, &BTreeMap::new(), Lens(None), &img).is_empty());
    }
}
