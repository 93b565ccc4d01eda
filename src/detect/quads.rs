//! Tag candidates from the AprilTag 3 C detector (bundled with `apriltag-sys`, built
//! statically): ids, corners, Hamming distance and decision margin.
//!
//! The C library puts pixel `(i, j)`'s centre at `(i + ½, j + ½)`; rigcal puts it at
//! `(i, j)` (architecture §3). [`C_PIXEL_OFFSET`] is the one place that converts.

use super::gray::Gray;
use crate::geometry::Vec2;

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
}

impl Default for QuadOptions {
    fn default() -> Self {
        Self {
            decimate: 2.0,
            max_hamming: 2,
        }
    }
}

/// Run the quad detector for tag36h11 on `img` (single-threaded: callers parallelise
/// over images).
pub fn detect(img: &Gray, opts: &QuadOptions) -> Result<Vec<Candidate>, String> {
    DETECTOR.with(|cell| {
        let mut cell = cell.borrow_mut();
        if cell.as_ref().is_none_or(|(h, _)| *h != opts.max_hamming) {
            let det = apriltag::Detector::builder()
                .add_family_bits(apriltag::Family::tag_36h11(), opts.max_hamming as usize)
                .build()
                .map_err(|e| format!("AprilTag detector: {e}"))?;
            *cell = Some((opts.max_hamming, det));
        }
        match cell.as_mut() {
            Some((_, det)) => detect_with(det, img, opts),
            None => Err("AprilTag detector unavailable".into()),
        }
    })
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
    img: &Gray,
    opts: &QuadOptions,
) -> Result<Vec<Candidate>, String> {
    det.set_thread_number(1);
    det.set_decimation(opts.decimate.max(1.0));
    det.set_refine_edges(true);
    let (w, h) = (img.width, img.height);
    let mut buf = apriltag::Image::zeros_with_stride(w, h, w.div_ceil(96) * 96)
        .map_err(|e| format!("AprilTag image: {e}"))?;
    let stride = buf.stride();
    let px = img.to_u8();
    let dst = buf.as_slice_mut();
    for y in 0..h {
        dst[y * stride..y * stride + w].copy_from_slice(&px[y * w..(y + 1) * w]);
    }
    Ok(det
        .detect(&buf)
        .into_iter()
        .map(|d| {
            let c = d.corners();
            let p = |i: usize| Vec2::new(c[i][0] - C_PIXEL_OFFSET, c[i][1] - C_PIXEL_OFFSET);
            Candidate {
                id: d.id() as u32,
                hamming: d.hamming() as u32,
                margin: d.decision_margin() as f64,
                corners: [p(0), p(1), p(2), p(3)],
            }
        })
        .collect())
}
