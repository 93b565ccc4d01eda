//! How blurred an image's edges are, read off the sides of the tags found in it: the
//! full-resolution quad search loses blurred tags that the decimated one keeps, so the
//! detector runs both on blurred images only.

use super::gray::Gray;
use super::refine::edge_sigma;
use super::verify::cell_px;
use rigcal_core::geometry::Vec2;

/// The blur (σ px, [`edge_blur`]) above which the decimated quad search runs as well as
/// the full-resolution one. A dense 1080p hall (car-hall seed 5 renders, JPEG) reads
/// 0.60-0.64 per image, and the full resolution alone finds all of its 5 531 tags;
/// blurred further it reads 0.93-0.97, 1.19-1.24, 1.56-1.83 and ~2.7, and the full
/// resolution alone loses 1, 11, 3 and 73 tags the decimated search finds.
pub const SHARP_PX: f64 = 0.8;

/// Tags whose cell ([`cell_px`], the border's width) is under this (px) are not read:
/// the profile across a narrower border runs into the bits.
const MIN_CELL_PX: f64 = 5.0;

/// How far (px) the edge may be from the quad's side: the C library's corners are within
/// a pixel or so.
const SEARCH_REACH_PX: f64 = 1.5;

/// Levels are read this far either side of the edge (px) at most, and 0.35 of the
/// border's cell (the edge refinement's rule): the dark level the border's, the bright
/// one the white margin's.
const MAX_LEVELS_PX: f64 = 3.0;

/// Sides read per image at most: the quantile of that many is stable to a few hundredths.
const MAX_SIDES: usize = 64;

/// The Gaussian σ (px) of the optics, the pixel's own area included, at the blurriest
/// tenth of the sides of the tags with corners `quads` (a soft corner of the image
/// counts); `None` when no tag is large enough to read.
///
/// Each side is read at its midpoint by the edge refinement's blurred-step fit
/// ([`edge_sigma`]).
pub fn edge_blur(img: &Gray, quads: &[[Vec2; 4]]) -> Option<f64> {
    let mut sigmas = Vec::new();
    for q in quads {
        let cell = cell_px(q);
        if cell < MIN_CELL_PX {
            continue;
        }
        let centre = (q[0] + q[1] + q[2] + q[3]) / 4.0;
        let d = (0.35 * cell).min(MAX_LEVELS_PX);
        for k in 0..4 {
            let (a, b) = (q[k], q[(k + 1) % 4]);
            let mid = (a + b) / 2.0;
            let along = (b - a).normalize();
            let mut n = Vec2::new(-along.y, along.x);
            if n.dot(&(mid - centre)) < 0.0 {
                n = -n;
            }
            if let Some(s) = edge_sigma(img, mid, n, SEARCH_REACH_PX, d) {
                sigmas.push(s);
            }
        }
        if sigmas.len() >= MAX_SIDES {
            break;
        }
    }
    if sigmas.is_empty() {
        return None;
    }
    let i = (sigmas.len() * 9 / 10).min(sigmas.len() - 1);
    Some(*sigmas.select_nth_unstable_by(i, f64::total_cmp).1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_synth::render::RenderOptions;
    use rigcal_synth::tagscene::{scene, Lens as SceneLens, SceneParams};

    /// One head-on tag of `side` px rendered with optics blur `sigma` and grey noise 2.
    fn rendered(side: f64, sigma: f64) -> (Gray, [Vec2; 4]) {
        let s = scene(&SceneParams {
            grid: false,
            tag_px: side,
            obliquity_deg: 0.0,
            lens: SceneLens::Pinhole,
            width: 640,
            height: 480,
            render: RenderOptions {
                blur_sigma: sigma,
                ..RenderOptions::noisy(7, 2.0)
            },
            seed: 7,
        });
        let (_, c) = s.truth.iter().next().expect("a tag in view");
        (Gray::from_luma8(&s.image), *c)
    }

    /// The optics' σ with the pixel's area (`σ² + 1/12`): read to within 0.15 px from 0.3
    /// to 2 px of blur (the blurriest of the tag's four sides, grey noise 2), and ordered.
    #[test]
    fn the_blur_of_a_rendered_tag_is_read_back() {
        let mut last = 0.0;
        for sigma in [0.3, 0.5, 1.0, 1.5, 2.0] {
            let (img, c) = rendered(80.0, sigma);
            let read = edge_blur(&img, &[c]).expect("a tag large enough to read");
            let expected = (sigma * sigma + 1.0 / 12.0).sqrt();
            assert!(
                (read - expected).abs() < 0.15,
                "σ {sigma}: read {read:.3}, expected {expected:.3}"
            );
            assert!(read > last, "σ {sigma}: read {read:.3} after {last:.3}");
            last = read;
        }
    }

    #[test]
    fn small_tags_are_not_read() {
        let (img, c) = rendered(30.0, 1.0);
        assert_eq!(edge_blur(&img, &[c]), None);
    }
}
