//! Tag candidates from the AprilTag 3 C detector (bundled with `apriltag-sys`, built
//! statically): ids, corners, Hamming distance and decision margin.
//!
//! The C library puts pixel `(i, j)`'s centre at `(i + ½, j + ½)`; rigcal puts it at
//! `(i, j)` (architecture §3). [`C_PIXEL_OFFSET`] is the one place that converts.

use super::gray::Gray;
use rigcal_core::geometry::Vec2;

/// Subtract from the C detector's coordinates to get rigcal's pixel-centre convention.
pub const C_PIXEL_OFFSET: f64 = 0.5;

/// A tag as the quad detector found it; corners `k = 0..4` counter-clockwise from the
/// tag's bottom-left as printed (the `tag:<id>:<k>` numbering).
#[derive(Clone, Debug)]
pub struct Candidate {
    pub id: u32,
    pub hamming: u32,
    pub margin: f64,
    pub corners: [Vec2; 4],
}

#[derive(Clone, Debug)]
pub struct QuadOptions {
    /// Quad search on an image decimated by this factor (bits are decoded at full
    /// resolution, corners are refined by rigcal anyway).
    pub decimate: f32,
    /// Bit errors the decoder may correct (tag36h11 has distance 11; 2 keeps false
    /// positives negligible).
    pub max_hamming: u32,
    /// Smallest black/white difference (grey levels) the segmentation treats as an edge;
    /// `None`: [`NOISE_CONTRAST`] × the image's noise σ, within
    /// [`MIN_CONTRAST_RANGE`]. The C library's fixed 5 lets σ 2 grey noise segment flat
    /// background into thousands of components.
    pub min_contrast: Option<u8>,
    /// Search a copy of the image whose bright areas are grown by one pixel (maximum
    /// over the 4-neighbourhood): it cuts the corner-to-corner contact between an
    /// AprilGrid's tags and its crossing squares, which otherwise joins every tag's border
    /// to its neighbours' and leaves no quad to find. It also thins black bits, so it is a
    /// second pass for boards, never the first.
    pub grow_bright: bool,
    /// Search the image upsampled 2× (bilinear) instead, grown bright by one pixel
    /// *there* (half a pixel of the image) when `grow_bright`, with `decimate` applied
    /// to the upsampled copy: boards of 14-18 px tags (1.7-2.2 px per cell) keep their
    /// corner contacts on the image and lose their black bits on the image grown by a
    /// whole pixel; half a pixel cuts the one and keeps the other.
    pub upsample: bool,
}

/// Segmentation contrast per unit of noise σ: the grey range over a 3×3-tile window of
/// the decimated image (~150 samples) of pure noise reaches ~6σ.
pub const NOISE_CONTRAST: f64 = 7.0;
/// Bounds of the segmentation contrast: the C library's default, and a ceiling that
/// keeps tags of modest contrast (40 grey levels) findable in very noisy images.
pub const MIN_CONTRAST_RANGE: (u8, u8) = (5, 40);

impl Default for QuadOptions {
    fn default() -> Self {
        Self {
            decimate: 2.0,
            max_hamming: 2,
            min_contrast: None,
            grow_bright: false,
            upsample: false,
        }
    }
}

impl QuadOptions {
    /// The segmentation contrast used on `img`.
    pub fn contrast_for(&self, img: &Gray) -> u8 {
        self.min_contrast.unwrap_or_else(|| {
            let (lo, hi) = MIN_CONTRAST_RANGE;
            (NOISE_CONTRAST * img.noise_sigma())
                .ceil()
                .clamp(lo as f64, hi as f64) as u8
        })
    }
}

/// Run the quad detector for tag36h11 on `img` (single-threaded: callers parallelise
/// over images).
pub fn detect(img: &Gray, opts: &QuadOptions) -> Result<Vec<Candidate>, String> {
    let opts = QuadOptions {
        min_contrast: Some(opts.contrast_for(img)),
        ..opts.clone()
    };
    detect_pixels(&img.to_u8(), img.width, img.height, &opts)
}

/// [`detect`] on the image's 8-bit pixels (row-major, `w × h`), so that several passes
/// over one image convert it once. `opts.min_contrast` must be set.
pub fn detect_pixels(
    px: &[u8],
    w: usize,
    h: usize,
    opts: &QuadOptions,
) -> Result<Vec<Candidate>, String> {
    let contrast = opts
        .min_contrast
        .ok_or("detect_pixels: the segmentation contrast is not set")?;
    if px.len() != w * h {
        return Err(format!(
            "detect_pixels: {} pixels for a {w}×{h} image",
            px.len()
        ));
    }
    DETECTOR.with(|cell| {
        let mut cell = cell.borrow_mut();
        if cell.as_ref().is_none_or(|(h, _)| *h != opts.max_hamming) {
            let det = apriltag::Detector::builder()
                .add_family_bits(apriltag::Family::tag_36h11(), opts.max_hamming as usize)
                .build()
                .map_err(|e| format!("AprilTag detector: {e}"))?;
            *cell = Some((opts.max_hamming, det));
        }
        let (hamming, det) = cell.take().ok_or("AprilTag detector unavailable")?;
        let mut det = with_min_contrast(det, contrast);
        let out = detect_with(&mut det, px, w, h, opts);
        *cell = Some((hamming, det));
        out
    })
}

/// [`detect_pixels`] on the crop `rect` of the `w × h` image `px`, corners in the
/// image's pixels.
pub fn detect_pixels_in(
    px: &[u8],
    w: usize,
    h: usize,
    rect: crate::crossings::Rect,
    opts: &QuadOptions,
) -> Result<Vec<Candidate>, String> {
    let inside = rect.x0 < rect.x1 && rect.y0 < rect.y1 && rect.x1 <= w && rect.y1 <= h;
    if px.len() != w * h || !inside {
        return Err(format!(
            "detect_pixels_in: crop {rect:?} of a {w}×{h} image of {} pixels",
            px.len()
        ));
    }
    if rect.area() == w * h {
        return detect_pixels(px, w, h, opts);
    }
    let cw = rect.x1 - rect.x0;
    let crop: Vec<u8> = (rect.y0..rect.y1)
        .flat_map(|y| &px[y * w + rect.x0..y * w + rect.x1])
        .copied()
        .collect();
    let shift = Vec2::new(rect.x0 as f64, rect.y0 as f64);
    let mut found = detect_pixels(&crop, cw, rect.y1 - rect.y0, opts)?;
    for c in &mut found {
        for p in &mut c.corners {
            *p += shift;
        }
    }
    Ok(found)
}

/// Build this thread's detector now (the decoder's table takes tens of milliseconds), so
/// that timing a first image measures detection only.
pub fn warm_up(opts: &QuadOptions) -> Result<(), String> {
    let tiny = Gray {
        width: 8,
        height: 8,
        data: vec![0.0; 64],
    };
    detect(&tiny, opts).map(|_| ())
}

/// Set the segmentation's `min_white_black_diff`. The crate's `set_thresholds` writes
/// every quad parameter and stores the opposite-angle limit in radians where the C code
/// reads its cosine, so the one field is set through the C struct instead.
fn with_min_contrast(det: apriltag::Detector, contrast: u8) -> apriltag::Detector {
    let raw = det.into_raw();
    // SAFETY: `raw` is the live detector just released by `into_raw`, owned here alone;
    // `from_raw` takes it back, so it is freed exactly once.
    unsafe {
        (*raw.as_ptr()).qtp.min_white_black_diff = contrast as std::os::raw::c_int;
        apriltag::Detector::from_raw(raw.as_ptr())
    }
}

thread_local! {
    /// One detector per thread: building it fills the decoder's table of every code
    /// within `max_hamming` bits (~400 000 entries for 2 bits), tens of milliseconds
    /// that must not be paid per image.
    static DETECTOR: std::cell::RefCell<Option<(u32, apriltag::Detector)>> =
        const { std::cell::RefCell::new(None) };
}

fn detect_with(
    det: &mut apriltag::Detector,
    px: &[u8],
    w: usize,
    h: usize,
    opts: &QuadOptions,
) -> Result<Vec<Candidate>, String> {
    let decimate = opts.decimate.max(1.0);
    let upscale = if opts.upsample { 2 } else { 1 };
    let (sw, sh) = segmented_size(upscale * w, upscale * h, decimate);
    if sw.min(sh) < MIN_SEGMENTED_SIDE {
        return Ok(Vec::new());
    }
    det.set_thread_number(1);
    det.set_decimation(decimate);
    det.set_refine_edges(true);
    // The C detector's input: the pixels, upsampled and/or grown as asked.
    let upsampled;
    let (src, sw, sh, scale) = if opts.upsample {
        upsampled = upsample2(px, w, h);
        (&upsampled[..], 2 * w, 2 * h, 0.5)
    } else {
        (px, w, h, 1.0)
    };
    let mut buf = apriltag::Image::zeros_with_stride(sw, sh, sw.div_ceil(96) * 96)
        .map_err(|e| format!("AprilTag image: {e}"))?;
    let stride = buf.stride();
    let dst = buf.as_slice_mut();
    if opts.grow_bright {
        for y in 0..sh {
            grow_row(src, sw, sh, y, &mut dst[y * stride..y * stride + sw]);
        }
    } else {
        for y in 0..sh {
            dst[y * stride..y * stride + sw].copy_from_slice(&src[y * sw..(y + 1) * sw]);
        }
    }
    Ok(det
        .detect(&buf)
        .into_iter()
        .map(|d| {
            let c = d.corners();
            // Upsampled pixel j (C centre j + ½) is the image's (j + ½)/2 − ½: so scale
            // the C coordinates first, then the one convention shift.
            let p = |i: usize| {
                Vec2::new(
                    c[i][0] * scale - C_PIXEL_OFFSET,
                    c[i][1] * scale - C_PIXEL_OFFSET,
                )
            };
            Candidate {
                id: d.id() as u32,
                hamming: d.hamming() as u32,
                margin: d.decision_margin() as f64,
                corners: [p(0), p(1), p(2), p(3)],
            }
        })
        .collect())
}

/// Fewest pixels across the image the C segmentation is given (after its decimation):
/// a tag36h11's black square is 8 cells, so a narrower image holds no tag; and the C
/// library reads out of bounds (or divides by zero) on images under 3 pixels across,
/// which a 2×2 upload or a thin crop would otherwise reach.
const MIN_SEGMENTED_SIDE: usize = 8;

/// The size of the image the C library segments for a `w × h` input at `decimate`
/// (`image_u8_decimate`: 3 → 2 block averages at 1.5, otherwise every
/// `⌊decimate⌋`-th pixel).
fn segmented_size(w: usize, h: usize, decimate: f32) -> (usize, usize) {
    if decimate == 1.5 {
        (w / 3 * 2, h / 3 * 2)
    } else {
        let f = (decimate as usize).max(1);
        (1 + w.saturating_sub(1) / f, 1 + h.saturating_sub(1) / f)
    }
}

/// The image upsampled 2× by bilinear interpolation, pixel centres kept: upsampled pixel
/// `j` samples the image at `j/2 − ¼` (¾ of the nearer pixel, ¼ of the other), borders
/// clamped.
fn upsample2(px: &[u8], w: usize, h: usize) -> Vec<u8> {
    // Rows first: each image row to a row of 2w, in quarters (×4, exact in u16).
    let mut rows = vec![0u16; w * 2 * h];
    for y in 0..h {
        let src = &px[y * w..(y + 1) * w];
        let dst = &mut rows[y * 2 * w..(y + 1) * 2 * w];
        for x in 0..w {
            let (l, m, r) = (
                src[x.saturating_sub(1)] as u16,
                src[x] as u16,
                src[(x + 1).min(w - 1)] as u16,
            );
            dst[2 * x] = 3 * m + l;
            dst[2 * x + 1] = 3 * m + r;
        }
    }
    // Then columns, in sixteenths, rounded.
    let w2 = 2 * w;
    let mut out = vec![0u8; w2 * 2 * h];
    for y in 0..h {
        let (up, mid, down) = (y.saturating_sub(1), y, (y + 1).min(h - 1));
        for x in 0..w2 {
            let (u, m, d) = (rows[up * w2 + x], rows[mid * w2 + x], rows[down * w2 + x]);
            out[2 * y * w2 + x] = ((3 * m + u + 8) / 16) as u8;
            out[(2 * y + 1) * w2 + x] = ((3 * m + d + 8) / 16) as u8;
        }
    }
    out
}

/// Maximum over each pixel and its four neighbours (a cross, not the 3×3 square: it
/// cuts diagonal contacts just as well and thins black less; on the 30 grid views of
/// `bench detect --views 10` the quad detector found 988 of 1077 tags on the cross-grown
/// copy against 832, and a seed on every view against 27 of 30). Borders clamped.
#[cfg(test)]
fn grow_bright(px: &[u8], w: usize, h: usize) -> Vec<u8> {
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        grow_row(px, w, h, y, &mut out[y * w..(y + 1) * w]);
    }
    out
}

/// Row `y` of [`grow_bright`] into `out` (`w` pixels): the rows above and below and the
/// row shifted left and right, maxed slice by slice (vectorised; the borders clamp).
fn grow_row(px: &[u8], w: usize, h: usize, y: usize, out: &mut [u8]) {
    let row = |r: usize| &px[r * w..(r + 1) * w];
    let (mid, up, down) = (row(y), row(y.saturating_sub(1)), row((y + 1).min(h - 1)));
    for (((o, &m), &u), &d) in out.iter_mut().zip(mid).zip(up).zip(down) {
        *o = m.max(u).max(d);
    }
    if w > 1 {
        for (o, (&l, &r)) in out[1..w - 1].iter_mut().zip(mid.iter().zip(&mid[2..])) {
            *o = (*o).max(l).max(r);
        }
        out[0] = out[0].max(mid[1]);
        out[w - 1] = out[w - 1].max(mid[w - 2]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_too_small_for_a_tag_have_no_candidates() {
        // The C library crashed on these (1×1 to 16×4 at decimation 2, anything under
        // 6 rows at 1.5, 2 px wide at 1.5 by zero division): every size up to 20×20,
        // every pass rigcal runs, returns, and a tag needs at least 8 segmented pixels.
        for (decimate, upsample, grow_bright) in [
            (1.0, false, false),
            (1.5, true, true),
            (1.5, false, false),
            (2.0, false, false),
            (2.0, false, true),
            (3.0, false, false),
            (4.0, true, false),
        ] {
            let o = QuadOptions {
                decimate,
                upsample,
                grow_bright,
                min_contrast: Some(5),
                ..QuadOptions::default()
            };
            for w in 1..=20 {
                for h in 1..=20 {
                    let px: Vec<u8> = (0..w * h).map(|i| (i * 37 % 256) as u8).collect();
                    let found = detect_pixels(&px, w, h, &o).expect("a detection");
                    assert!(found.is_empty(), "{w}×{h} at {decimate}: {found:?}");
                }
            }
        }
        assert_eq!(segmented_size(1920, 1080, 2.0), (960, 540));
        assert_eq!(segmented_size(1921, 1081, 2.0), (961, 541));
        assert_eq!(segmented_size(10, 5, 1.5), (6, 2));
        assert_eq!(segmented_size(10, 5, 1.0), (10, 5));
    }

    #[test]
    fn upsampling_keeps_levels_and_pixel_centres() {
        // A ramp along x: the upsampled copy is the same ramp at the half-pixel
        // positions j/2 − ¼ (inside the clamped borders), flat rows stay flat.
        let (w, h) = (8, 3);
        let px: Vec<u8> = (0..h)
            .flat_map(|_| (0..w).map(|x| 10 + 20 * x as u8))
            .collect();
        let up = upsample2(&px, w, h);
        for y in 0..2 * h {
            for j in 1..2 * w - 1 {
                let expect = 10.0 + 20.0 * (j as f64 / 2.0 - 0.25);
                let got = up[y * 2 * w + j] as f64;
                assert!((got - expect).abs() <= 0.5, "({j}, {y}): {got} vs {expect}");
            }
        }
    }

    /// A crop finds the tag the whole image finds, at the same image corners; a crop
    /// outside the image, or pixels that are not the image's, are refused.
    #[test]
    fn a_crop_finds_tags_at_image_coordinates() {
        use rigcal_synth::render::RenderOptions;
        use rigcal_synth::tagscene::{scene, Lens, SceneParams};
        let s = scene(&SceneParams {
            grid: false,
            tag_px: 60.0,
            obliquity_deg: 20.0,
            lens: Lens::Pinhole,
            width: 640,
            height: 480,
            render: RenderOptions::default(),
            seed: 3,
        });
        let gray = Gray::from_luma8(&s.image);
        let opts = QuadOptions {
            min_contrast: Some(QuadOptions::default().contrast_for(&gray)),
            ..Default::default()
        };
        let px = gray.to_u8();
        let (w, h) = (gray.width, gray.height);
        let whole = detect_pixels(&px, w, h, &opts).unwrap();
        assert_eq!(whole.len(), 1, "{whole:?}");
        // A crop round the tag, its origin on the segmentation's 8-px tile grid.
        let (mut lo, mut hi) = (whole[0].corners[0], whole[0].corners[0]);
        for p in &whole[0].corners {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        let rect = crate::crossings::Rect {
            x0: ((lo.x as usize).saturating_sub(40)) / 16 * 16,
            y0: ((lo.y as usize).saturating_sub(40)) / 16 * 16,
            x1: (hi.x as usize + 40).min(w),
            y1: (hi.y as usize + 40).min(h),
        };
        assert!(rect.area() < w * h / 2);
        let cropped = detect_pixels_in(&px, w, h, rect, &opts).unwrap();
        assert_eq!(cropped.len(), 1);
        assert_eq!(cropped[0].id, whole[0].id);
        for (a, b) in cropped[0].corners.iter().zip(&whole[0].corners) {
            // (The C library works in single precision: ~1e-5 px apart.)
            assert!((a - b).norm() < 1e-3, "{a} vs {b}");
        }
        let outside = crate::crossings::Rect { x1: w + 1, ..rect };
        assert!(detect_pixels_in(&px, w, h, outside, &opts).is_err());
        assert!(detect_pixels_in(&px[1..], w, h, rect, &opts).is_err());
    }

    #[test]
    fn growing_bright_cuts_a_corner_contact() {
        // Two black squares touching at one corner, on white.
        let (w, h) = (12, 12);
        let mut px = vec![255u8; w * h];
        for y in 2..6 {
            for x in 2..6 {
                px[y * w + x] = 0;
                px[(y + 4) * w + x + 4] = 0;
            }
        }
        let g = grow_bright(&px, w, h);
        // The contact pixels (5,5) and (6,6) turn white; each square's core stays black.
        assert_eq!(g[5 * w + 5], 255);
        assert_eq!(g[6 * w + 6], 255);
        assert_eq!(g[3 * w + 3], 0);
        assert_eq!(g[8 * w + 8], 0);
        assert_eq!(g[4 * w + 4], 0);
    }
}
