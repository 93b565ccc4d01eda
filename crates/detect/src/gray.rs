//! A grey image in floating point for subpixel measurement, from any decoded PNG/JPEG
//! (8 or 16 bit, grey or colour); 16-bit precision is kept (scaled to 0..255).

use rigcal_core::geometry::Vec2;

#[derive(Clone, Debug)]
pub struct Gray {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Gray {
    pub fn from_dynamic(img: &image::DynamicImage) -> Gray {
        // 8-bit grey (most captures) is read as it is: `to_luma32f` × 255 gives the same
        // levels bit for bit, through a second full-size copy.
        if let image::DynamicImage::ImageLuma8(g) = img {
            return Gray::from_luma8(g);
        }
        let l = img.to_luma32f();
        Gray {
            width: l.width() as usize,
            height: l.height() as usize,
            data: l.into_raw().into_iter().map(|v| v * 255.0).collect(),
        }
    }

    pub fn from_luma8(img: &image::GrayImage) -> Gray {
        Gray {
            width: img.width() as usize,
            height: img.height() as usize,
            data: img.as_raw().iter().map(|&v| v as f32).collect(),
        }
    }

    /// 8-bit copy, rounded, for the AprilTag quad detector.
    pub fn to_u8(&self) -> Vec<u8> {
        let mut out = vec![0u8; self.data.len()];
        rounded_to_u8(&self.data, &mut out);
        out
    }

    /// Robust estimate of the image noise σ (grey levels), from the median response of
    /// Immerkær's mask `[1 −2 1; −2 4 −2; 1 −2 1]` (blind to planes, so shading does not
    /// count; σ of its response to white noise is 6σ) on every other pixel. The median
    /// ignores edges and texture as long as they cover under half the image.
    ///
    /// Why: the quad detector's segmentation must ignore contrast that noise alone makes,
    /// or it segments flat, noisy background into thousands of components (13× its time
    /// on 1600×1200 renders at σ 2 grey).
    pub fn noise_sigma(&self) -> f64 {
        let (w, h) = (self.width, self.height);
        if w < 3 || h < 3 {
            return 0.0;
        }
        // Median of |response| from a histogram (bins of 1/4 grey level): O(n), where a
        // selection over the 480 000 responses of a 1600×1200 image took 4 ms.
        let mut hist = vec![0u32; RESPONSE_BINS + 1];
        let mut n = 0u32;
        let mut bins = vec![0u16; w - 2];
        for y in (1..h - 1).step_by(2) {
            let row = |r: usize| &self.data[r * w..(r + 1) * w];
            // The whole row's bins first, in vector lanes; the histogram, which does not
            // vectorise, then counts every other one.
            response_bins(row(y - 1), row(y), row(y + 1), &mut bins);
            for &bin in bins.iter().step_by(2) {
                hist[bin as usize] += 1;
                n += 1;
            }
        }
        let half = n as f64 / 2.0;
        let mut below = 0.0;
        for (b, &c) in hist.iter().enumerate() {
            let c = c as f64;
            if below + c >= half && c > 0.0 {
                // Within the bin, linearly (8-bit images give integer responses, all at
                // bin starts: off by under a bin, 0.06 grey levels of σ).
                let bin = RESPONSE_BIN as f64;
                let m = b as f64 * bin + (half - below) / c * bin;
                return m / (0.6745 * 6.0);
            }
            below += c;
        }
        RESPONSE_BINS as f64 * RESPONSE_BIN as f64 / (0.6745 * 6.0)
    }

    /// Bilinear sample at `p` (pixel-centre convention: pixel `(i, j)` is at `(i, j)`);
    /// `None` outside the pixel centres' hull.
    #[inline]
    pub fn sample(&self, p: Vec2) -> Option<f64> {
        if !(p.x >= 0.0 && p.y >= 0.0) {
            return None;
        }
        // Non-negative here, so truncation is the floor, without a libm call (x86-64's
        // baseline has no rounding instruction). Through `i64`: fewer instructions each
        // way than `usize` (x86-64 converts signed integers only), and a coordinate far
        // out (or infinite) saturates at `i64::MAX`, which the bounds below refuse
        // without overflowing.
        let (xi, yi) = (p.x as i64, p.y as i64);
        let (x0, y0) = (xi as usize, yi as usize);
        if x0 + 1 >= self.width || y0 + 1 >= self.height {
            return None;
        }
        let (fx, fy) = (p.x - xi as f64, p.y - yi as f64);
        // The 2×2 neighbourhood as two row pairs: two bounds checks instead of four.
        let i = y0 * self.width + x0;
        let (top, bottom) = (
            &self.data[i..i + 2],
            &self.data[i + self.width..i + self.width + 2],
        );
        let row = |r: &[f32]| r[0] as f64 + fx * (r[1] as f64 - r[0] as f64);
        let (a, b) = (row(top), row(bottom));
        Some(a + fy * (b - a))
    }
}

/// Width of a bin of the noise estimate's histogram of mask responses (grey levels),
/// and the number of bins (responses beyond the last count in it).
const RESPONSE_BIN: f32 = 0.25;
const RESPONSE_BINS: usize = 4096;

/// `x` clamped to `0..=hi` (a NaN to 0) and truncated: in vector lanes where a
/// saturating `as` conversion runs a value at a time on x86. `hi` must be below 2³¹.
#[inline(always)]
fn truncated_within(x: f32, hi: f32) -> i32 {
    // `max` returns 0 for a NaN, so the value is finite and in 0..=hi (`clamp` would
    // keep the NaN, which the unchecked conversion must not see).
    #[allow(clippy::manual_clamp)]
    let x = x.max(0.0).min(hi);
    // SAFETY: `x` is finite and within `i32`'s range (just above, `hi` < 2³¹).
    unsafe { x.to_int_unchecked::<i32>() }
}

rigcal_core::avx2_or_portable! {
/// Immerkær's mask on three rows `a`, `b`, `c`: `out[x]` is the histogram bin of its
/// response centred on `b[x + 1]` (`out` is two shorter than the rows).
fn response_bins(a: &[f32], b: &[f32], c: &[f32], out: &mut [u16]) {
    let n = out.len();
    // Cut to the length used, so the loop has no bounds check and vectorises.
    let (a, b, c) = (&a[..n + 2], &b[..n + 2], &c[..n + 2]);
    for x in 0..n {
        let v = a[x] + a[x + 2] + c[x] + c[x + 2]
            - 2.0 * (a[x + 1] + b[x] + b[x + 2] + c[x + 1])
            + 4.0 * b[x + 1];
        out[x] = truncated_within(v.abs() / RESPONSE_BIN, RESPONSE_BINS as f32) as u16;
    }
}
}

rigcal_core::avx2_or_portable! {
/// `v` rounded half up and clamped to 0..=255, into `out`: +½ then truncate
/// (`f32::round` is a libm call per pixel). The clamp comes first and the conversion is
/// the unchecked one, so the loop is four vector instructions a lane; the saturating
/// `as` casts (to `u8` or `i32`) kept it a pixel at a time, 8.5 instructions a pixel and
/// 4 % of `fast` detection on a 1080p hall image.
fn rounded_to_u8(v: &[f32], out: &mut [u8]) {
    for (o, v) in out.iter_mut().zip(v) {
        *o = truncated_within(v + 0.5, 255.0) as u8;
    }
}
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    #[test]
    fn the_8_bit_copy_rounds_half_up_and_clamps() {
        let data: Vec<f32> = (-2000..300_000)
            .map(|i| i as f32 / 1000.0)
            .chain([-1e9, -0.5, 0.49999997, 0.5, 254.5, 255.49998, 255.5, 1e9])
            .chain([f32::NAN, f32::INFINITY, f32::NEG_INFINITY])
            .collect();
        let g = Gray {
            width: data.len(),
            height: 1,
            data: data.clone(),
        };
        let want: Vec<u8> = data
            .iter()
            .map(|v| (v + 0.5).clamp(0.0, 255.0) as u8)
            .collect();
        assert_eq!(g.to_u8(), want);
    }

    /// An 8-bit grey image read directly has the levels of the general conversion.
    #[test]
    fn grey_images_are_read_at_the_general_conversions_levels() {
        let g = image::GrayImage::from_fn(256, 3, |x, y| {
            image::Luma([(x as u8).wrapping_add(y as u8 * 7)])
        });
        let dynamic = image::DynamicImage::ImageLuma8(g);
        let general: Vec<f32> = dynamic
            .to_luma32f()
            .into_raw()
            .into_iter()
            .map(|v| v * 255.0)
            .collect();
        let read = Gray::from_dynamic(&dynamic);
        assert_eq!((read.width, read.height), (256, 3));
        assert_eq!(read.data, general);
    }

    /// Bilinear inside the pixel centres' hull, `None` outside it, whatever the point: a
    /// degenerate homography can put one at 1e300 or at infinity (once the cell index
    /// was taken as `usize`, such a point overflowed `x0 + 1` and panicked on the
    /// slice).
    #[test]
    fn samples_are_bilinear_inside_and_none_anywhere_outside() {
        let (w, h) = (5, 4);
        let g = Gray {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| ((i % w) * 10 + (i / w) * 100) as f32)
                .collect(),
        };
        let at = |x: f64, y: f64| g.sample(Vec2::new(x, y));
        assert_eq!(at(0.0, 0.0), Some(0.0));
        assert_eq!(at(1.25, 2.5), Some(12.5 + 250.0));
        assert_eq!(
            at(3.999, 2.0).map(|v| (v * 1e3).round() / 1e3),
            Some(239.99)
        );
        for (x, y) in [
            (4.0, 1.0),
            (1.0, 3.0),
            (-0.001, 1.0),
            (1e300, 0.5),
            (0.5, 1e300),
            (f64::INFINITY, 0.5),
            (0.5, f64::INFINITY),
            (f64::NEG_INFINITY, 0.5),
            (f64::NAN, 0.5),
            (0.5, f64::NAN),
            (9.3e18, 9.3e18),
        ] {
            assert_eq!(at(x, y), None, "({x}, {y})");
        }
    }

    #[test]
    fn noise_sigma_is_recovered_on_shaded_images_with_edges() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for sigma in [0.0f64, 1.0, 2.0, 5.0, 10.0] {
            let noise = Normal::new(0.0, sigma.max(1e-12)).unwrap();
            let (w, h) = (400, 300);
            let data = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f64, (i / w) as f64);
                    // A shading ramp and a bright square: neither is noise.
                    let base = 60.0 + 0.3 * x + 0.1 * y;
                    let square =
                        if (100..200).contains(&(x as i32)) && (50..150).contains(&(y as i32)) {
                            120.0
                        } else {
                            0.0
                        };
                    (base + square + noise.sample(&mut rng)) as f32
                })
                .collect();
            let g = Gray {
                width: w,
                height: h,
                data,
            };
            let est = g.noise_sigma();
            // 5 % plus the histogram's bin (¼ grey level of response, 0.06 of σ).
            assert!(
                (est - sigma).abs() <= 0.05 * sigma + 0.07,
                "σ {sigma}: estimated {est}"
            );
        }
    }
}
