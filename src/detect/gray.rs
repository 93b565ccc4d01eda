//! A grey image in floating point for subpixel measurement, from any decoded PNG/JPEG
//! (8 or 16 bit, grey or colour); 16-bit precision is kept (scaled to 0..255).

use crate::geometry::Vec2;

#[derive(Clone, Debug)]
pub struct Gray {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl Gray {
    pub fn from_dynamic(img: &image::DynamicImage) -> Gray {
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
        self.data
            .iter()
            .map(|v| v.round().clamp(0.0, 255.0) as u8)
            .collect()
    }

    /// Bilinear sample at `p` (pixel-centre convention: pixel `(i, j)` is at `(i, j)`);
    /// `None` outside the pixel centres' hull.
    pub fn sample(&self, p: Vec2) -> Option<f64> {
        if !(p.x >= 0.0 && p.y >= 0.0) {
            return None;
        }
        let (x0, y0) = (p.x.floor() as usize, p.y.floor() as usize);
        if x0 + 1 >= self.width || y0 + 1 >= self.height {
            return None;
        }
        let (fx, fy) = (p.x - x0 as f64, p.y - y0 as f64);
        let at = |x: usize, y: usize| self.data[y * self.width + x] as f64;
        Some(
            (1.0 - fy) * ((1.0 - fx) * at(x0, y0) + fx * at(x0 + 1, y0))
                + fy * ((1.0 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1)),
        )
    }
}
