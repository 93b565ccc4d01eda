//! Exact projective rendering of printed planar targets and of whole scenes, so
//! detector accuracy can be measured against truth known to ~1e-3 px.
//!
//! The scene is a [`Field`]: the region of constant grey that the ray through an image
//! point meets (ray through the camera model, including distortion). A pixel collects
//! light as a camera's does: its own area `[u − ½, u + ½] × [v − ½, v + ½]` (the
//! pixel-centre convention of architecture §3) blurred by the optics (Gaussian σ), see
//! [`PixelResponse`]. Pixels that one region covers are exact from one sample; pixels an
//! edge crosses are sampled on a fine jittered grid. The rays are unprojected exactly at
//! the pixel corners and interpolated bilinearly between them, where the map is affine
//! to far below 1e-3 px. Then photometry (gain, vignetting, offset), Gaussian sensor
//! noise and rounding to 8 bits.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rigcal_core::geometry::{normal_cdf, Camera, Pose, Vec2, Vec3};

#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Fine cells per side of a pixel an edge crosses (one jittered sample each).
    pub edge_cells: usize,
    /// Gaussian blur σ in pixels (0: none).
    pub blur_sigma: f64,
    /// Gaussian noise σ in grey levels (0: none).
    pub noise_sigma: f64,
    pub seed: u64,
    /// Grey levels of the print's black and white, and of everything off the board.
    pub black: f64,
    pub white: f64,
    pub background: f64,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            edge_cells: EDGE_SUPERSAMPLE,
            blur_sigma: 0.8,
            noise_sigma: 2.0,
            seed: 0,
            black: 25.0,
            white: 230.0,
            background: 120.0,
        }
    }
}

impl RenderOptions {
    /// The defaults with sensor noise `noise_sigma` (grey levels) drawn from `seed`.
    pub fn noisy(seed: u64, noise_sigma: f64) -> Self {
        Self {
            noise_sigma,
            seed,
            ..Self::default()
        }
    }
}

/// The shade of a board point: `Some(white?)` on the print, `None` off it.
pub type Shade<'a> = &'a (dyn Fn(f64, f64) -> Option<bool> + Sync);

/// Render the board seen by `camera` at `board_to_cam` (board `z = 0` plane).
pub fn render(
    camera: &Camera,
    board_to_cam: &Pose,
    shade: Shade,
    opts: &RenderOptions,
) -> image::GrayImage {
    let value = render_values(camera, board_to_cam, shade, opts);
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    quantise(camera, &value, |_, x| x, opts.noise_sigma, &mut rng)
}

/// [`render`]'s grey levels before the sensor (no noise, no rounding), row-major.
pub fn render_values(
    camera: &Camera,
    board_to_cam: &Pose,
    shade: Shade,
    opts: &RenderOptions,
) -> Vec<f64> {
    let rt = board_to_cam.rot.transpose();
    let o = rt * board_to_cam.trans; // camera centre is at −o in board coordinates
    let field = |_: Vec2, ray: Vec3| -> Hit {
        let d = rt * ray;
        let lambda = o.z / d.z;
        let shade = if lambda.is_finite() && lambda > 0.0 {
            let p = d * lambda - o;
            shade(p.x, p.y)
        } else {
            None
        };
        match shade {
            Some(true) => Hit {
                class: 2,
                grey: opts.white as f32,
                exact: true,
            },
            Some(false) => Hit {
                class: 1,
                grey: opts.black as f32,
                exact: true,
            },
            None => Hit {
                class: 0,
                grey: opts.background as f32,
                exact: true,
            },
        }
    };
    render_field(camera, &field, opts.blur_sigma, opts.edge_cells, opts.seed)
}

/// 16-bit pixels from grey levels (0..255 scaled by 257), no noise: a noise-free
/// render whose 8-bit rounding (σ 0.29 grey, ~0.002 px on an edge) would otherwise be
/// the largest error left in it.
pub fn exact_16bit(
    camera: &Camera,
    value: &[f64],
) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
    let pixels: Vec<u16> = value
        .iter()
        .map(|&x| (x * 257.0).round().clamp(0.0, 65535.0) as u16)
        .collect();
    image::ImageBuffer::from_raw(camera.width, camera.height, pixels).expect("buffer is w × h")
}

/// 8-bit pixels from grey levels: `photometry(pixel index, grey)` (gain, vignetting,
/// offset: what happens before the sensor), then Gaussian sensor noise σ `noise_sigma`,
/// rounded and clamped.
pub fn quantise(
    camera: &Camera,
    value: &[f64],
    photometry: impl Fn(usize, f64) -> f64,
    noise_sigma: f64,
    rng: &mut ChaCha8Rng,
) -> image::GrayImage {
    let noise = Normal::new(0.0, noise_sigma.max(0.0)).ok();
    let pixels: Vec<u8> = value
        .iter()
        .enumerate()
        .map(|(k, &x)| {
            let e = noise.map_or(0.0, |d| d.sample(rng));
            (photometry(k, x) + e).round().clamp(0.0, 255.0) as u8
        })
        .collect();
    image::GrayImage::from_raw(camera.width, camera.height, pixels).expect("buffer is w × h")
}

/// What a ray meets: a region of constant grey. `class` names the region (a board's
/// black, its white, one tile of a floor), so a pixel whose samples all meet one class
/// is uniform and its grey is exact without sub-sampling. `exact`: the region's edges
/// are measured (a print's), so pixels they cross get the fine grid; edges between
/// other regions (clutter) get a coarse one.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Hit {
    pub class: u64,
    pub grey: f32,
    pub exact: bool,
}

/// Cells per side of an edge pixel that only clutter crosses.
const CLUTTER_CELLS: usize = 4;

/// The scene as the camera sees it: the region met by the ray through image point
/// `(x, y)`, whose camera-frame direction is `ray` (`z = 1`).
pub type Field<'a> = &'a (dyn Fn(Vec2, Vec3) -> Hit + Sync);

/// Render `field` through `camera`'s optics and pixels: grey levels before sensor
/// noise, row-major. `edge_cells` fine cells per side sample a pixel an edge crosses
/// (one jittered sample each); `seed` draws the jitter.
pub fn render_field(
    camera: &Camera,
    field: Field,
    blur_sigma: f64,
    edge_cells: usize,
    seed: u64,
) -> Vec<f64> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    // Normalised ray (x, y) at each pixel corner (u − ½, v − ½); NaN where the model
    // does not unproject.
    let rays: Vec<[f64; 2]> = (0..=h)
        .flat_map(|j| (0..=w).map(move |i| (i, j)))
        .map(|(i, j)| {
            camera
                .unproject(&Vec2::new(i as f64 - 0.5, j as f64 - 0.5))
                .map_or([f64::NAN; 2], |r| [r.x, r.y])
        })
        .collect();
    // The region met at image point (x, y): the ray through it (bilinear in the corner
    // grid, where the map is affine to far below 1e-3 px).
    let hit = |x: f64, y: f64| -> Hit {
        let (fi, fj) = ((x + 0.5).floor(), (y + 0.5).floor());
        let (i, j) = (
            (fi.max(0.0) as usize).min(w - 1),
            (fj.max(0.0) as usize).min(h - 1),
        );
        let (fx, fy) = (x + 0.5 - i as f64, y + 0.5 - j as f64);
        let c = |di: usize, dj: usize| rays[(j + dj) * (w + 1) + i + di];
        let (r00, r10, r01, r11) = (c(0, 0), c(1, 0), c(0, 1), c(1, 1));
        let mix = |q: usize| {
            (1.0 - fy) * ((1.0 - fx) * r00[q] + fx * r10[q])
                + fy * ((1.0 - fx) * r01[q] + fx * r11[q])
        };
        field(Vec2::new(x, y), Vec3::new(mix(0), mix(1), 1.0))
    };
    // Pass 1: the region at every half-pixel point (pixel corners, side midpoints and
    // centres, shared between neighbours). A pixel is uniform when its 9 points meet one
    // region; it is an edge pixel when it or a 4-neighbour is not (a corner of a region
    // can poke into a pixel between its points, but then it reaches a neighbour's).
    let (sw, sh) = (2 * w + 1, 2 * h + 1);
    let samples: Vec<Hit> = per_pixel(sw, sh, |i, j| {
        hit(i as f64 / 2.0 - 0.5, j as f64 / 2.0 - 0.5)
    });
    let points = |u: usize, v: usize| {
        (0..3).flat_map(move |b| (0..3).map(move |a| (2 * v + b) * sw + 2 * u + a))
    };
    let mixed: Vec<bool> = per_pixel(w, h, |u, v| {
        let first = samples[2 * v * sw + 2 * u].class;
        points(u, v).any(|k| samples[k].class != first)
    });
    let edge: Vec<bool> = per_pixel(w, h, |u, v| {
        let at = |i: usize, j: usize| mixed[j * w + i];
        at(u, v)
            || (u > 0 && at(u - 1, v))
            || (u + 1 < w && at(u + 1, v))
            || (v > 0 && at(u, v - 1))
            || (v + 1 < h && at(u, v + 1))
    });
    let flat: Vec<f64> = per_pixel(w, h, |u, v| {
        samples[(2 * v + 1) * sw + 2 * u + 1].grey as f64
    });
    // Pass 2: edge pixels on a grid of m × m cells (`edge_cells` where a print's edge
    // crosses, a coarse one for clutter), one jittered sample each. A regular grid would
    // quantise an edge's position (a near-vertical edge in steps of 1/m px, the same on
    // every row: a bias along the whole edge); jitter makes the error small and random.
    let response = PixelResponse::new(blur_sigma);
    let reach = response.reach();
    let span = 2 * reach + 1;
    let per_px: Vec<f64> = (0..span)
        .map(|i| {
            let d = i as f64 - reach as f64;
            response.mass(d - 0.5, d + 0.5)
        })
        .collect();
    let cell_mass = |m: usize| -> Vec<f64> {
        (0..span * m)
            .map(|k| {
                let lo = (k / m) as f64 - reach as f64 - 0.5 + (k % m) as f64 / m as f64;
                response.mass(lo, lo + 1.0 / m as f64)
            })
            .collect()
    };
    let (fine_m, clutter_m) = (edge_cells.max(2), CLUTTER_CELLS.min(edge_cells.max(2)));
    let (fine_mass, clutter_mass) = (cell_mass(fine_m), cell_mass(clutter_m));
    // Each edge pixel's light as received at every offset of the response's reach
    // (`span × span`, separable: rows of cells weighted across, then down), so the
    // pixels around it gather it with one lookup.
    let spread: Vec<Vec<f32>> = per_pixel(w, h, |u, v| {
        if !edge[v * w + u] {
            return Vec::new();
        }
        let exact = points(u, v).any(|k| samples[k].exact);
        let (m, per_cell) = if exact {
            (fine_m, &fine_mass)
        } else {
            (clutter_m, &clutter_mass)
        };
        let mut state = ((v * w + u) as u64) ^ seed.rotate_left(32);
        let mut cells = Vec::with_capacity(m * m);
        for b in 0..m {
            for a in 0..m {
                let dx = (a as f64 + unit(&mut state)) / m as f64 - 0.5;
                let dy = (b as f64 + unit(&mut state)) / m as f64 - 0.5;
                cells.push(hit(u as f64 + dx, v as f64 + dy).grey as f64);
            }
        }
        let mut across = vec![0.0; m * span];
        for b in 0..m {
            let row = &cells[b * m..(b + 1) * m];
            for di in 0..span {
                let wx = &per_cell[di * m..(di + 1) * m];
                across[b * span + di] = row.iter().zip(wx).map(|(c, w)| c * w).sum();
            }
        }
        let mut out = vec![0.0f32; span * span];
        for dj in 0..span {
            for di in 0..span {
                out[dj * span + di] = (0..m)
                    .map(|b| per_cell[dj * m + b] * across[b * span + di])
                    .sum::<f64>() as f32;
            }
        }
        out
    });
    // Pass 3: each pixel collects light from its neighbours' areas through its response:
    // a flat neighbour at offset (i, j) contributes its level times the response's mass
    // over its square, an edge pixel its spread at that offset.
    let total = per_px.iter().sum::<f64>().powi(2);
    let rows_near: Vec<bool> = per_pixel(w, h, |u, v| {
        (u.saturating_sub(reach)..=(u + reach).min(w - 1)).any(|i| edge[v * w + i])
    });
    let edge_near: Vec<bool> = per_pixel(w, h, |u, v| {
        (v.saturating_sub(reach)..=(v + reach).min(h - 1)).any(|j| rows_near[j * w + u])
    });
    per_pixel(w, h, |u, v| {
        let (i0, j0) = (u as isize - reach as isize, v as isize - reach as isize);
        if !edge_near[v * w + u] {
            return flat[v * w + u];
        }
        let mut acc = 0.0;
        for dj in 0..span {
            // Outside the image: the nearest border pixel (clamped).
            let j = (j0 + dj as isize).clamp(0, h as isize - 1) as usize;
            for di in 0..span {
                let i = (i0 + di as isize).clamp(0, w as isize - 1) as usize;
                let k = j * w + i;
                acc += if edge[k] {
                    spread[k][dj * span + di] as f64
                } else {
                    flat[k] * per_px[di] * per_px[dj]
                };
            }
        }
        acc / total
    })
}

/// Fine cells per side of a pixel an edge crosses (one jittered sample each: the error
/// is random, about 0.008 of the step per pixel of edge before the blur averages it, not
/// a bias along the edge).
pub const EDGE_SUPERSAMPLE: usize = 16;

/// `f(u, v)` for every pixel, rows split over the cores.
fn per_pixel<T: Send + Clone + Default>(
    w: usize,
    h: usize,
    f: impl Fn(usize, usize) -> T + Sync,
) -> Vec<T> {
    let mut out = vec![T::default(); w * h];
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let rows_per = h.div_ceil(threads).max(1);
    std::thread::scope(|s| {
        for (chunk, rows) in out.chunks_mut(rows_per * w).enumerate() {
            let f = &f;
            s.spawn(move || {
                for (k, px) in rows.iter_mut().enumerate() {
                    *px = f(k % w, chunk * rows_per + k / w);
                }
            });
        }
    });
    out
}

/// A uniform number in [0, 1) from a splitmix64 state: deterministic jitter per pixel.
fn unit(state: &mut u64) -> f64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// Where a pixel collects its light from, per axis: its own area (a 1-px box) blurred by
/// the optics (Gaussian σ). Rendering samples this distribution directly, so the blur
/// acts on the continuous image before the pixel integrates it, as in a camera. (Blurring
/// the box-integrated pixel values with a sampled kernel instead moves an edge's
/// mid-level crossing by up to 0.03 px depending on where it falls between pixel
/// centres: the truth would not be known to 1e-3 px.)
struct PixelResponse {
    sigma: f64,
}

impl PixelResponse {
    fn new(sigma: f64) -> Self {
        Self {
            sigma: sigma.max(0.0),
        }
    }

    /// Whole pixels beyond which the response holds under 1e-6 of the light.
    fn reach(&self) -> usize {
        (0..64)
            .find(|&r| 1.0 - Self::cdf(self.sigma, r as f64 + 0.5) < 1e-6)
            .unwrap_or(64)
    }

    /// The fraction of the light from offsets in `[lo, hi]` (px) on one axis.
    fn mass(&self, lo: f64, hi: f64) -> f64 {
        Self::cdf(self.sigma, hi) - Self::cdf(self.sigma, lo)
    }

    /// The fraction of the pixel's light from offsets below `x` (px) on one axis: box ⊛
    /// Gaussian, `G(x + ½) − G(x − ½)` with `G(y) = σ(zΦ(z) + φ(z))`, `z = y/σ`.
    fn cdf(sigma: f64, x: f64) -> f64 {
        if sigma <= 0.0 {
            return (x + 0.5).clamp(0.0, 1.0);
        }
        let g = |y: f64| {
            let z = y / sigma;
            sigma * (z * normal_cdf(z) + (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt())
        };
        g(x + 0.5) - g(x - 0.5)
    }
}

/// Where board point `(x, y)` lands in the image, by the same camera model.
pub fn project_board(camera: &Camera, board_to_cam: &Pose, p: Vec2) -> Option<Vec2> {
    camera.project(&board_to_cam.apply(&Vec3::new(p.x, p.y, 0.0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A half-plane edge rendered without blur or noise lands where the model says: the
    /// mean grey of a pixel equals the covered fraction.
    #[test]
    fn coverage_matches_the_edge_position() {
        let cam = Camera::pinhole(100.0, 100.0, 10.0, 10.0, 21, 21);
        // Board plane facing the camera at 1 m: board x maps to u = 100·x + 10.
        let pose = Pose::new(nalgebra::Matrix3::identity(), Vec3::new(0.0, 0.0, 1.0));
        let opts = RenderOptions {
            blur_sigma: 0.0,
            noise_sigma: 0.0,
            black: 0.0,
            white: 250.0,
            ..Default::default()
        };
        // White where x < 0.0025 (u < 10.25): pixel 10 covers [9.5, 10.5], 75 % white.
        let img = render(&cam, &pose, &|x, _| Some(x < 0.0025), &opts);
        assert_eq!(img.get_pixel(10, 10)[0], (0.75f64 * 250.0).round() as u8);
        assert_eq!(img.get_pixel(9, 10)[0], 250);
        assert_eq!(img.get_pixel(11, 10)[0], 0);
    }

    /// With blur, every pixel near an edge 1° off vertical (its position between pixel
    /// centres sweeps all phases down the image) has the grey level of the continuous
    /// model: the step blurred by the optics, integrated over the pixel's area. The old
    /// renderer (box-integrated pixels, then a sampled Gaussian kernel; a regular 6×6
    /// grid) was off by up to 0.04 px in edge position here.
    #[test]
    fn blurred_edges_match_the_continuous_model_at_every_phase() {
        let (f, size) = (100.0, 61u32);
        let c = (size / 2) as f64;
        let cam = Camera::pinhole(f, f, c, c, size, size);
        let pose = Pose::new(nalgebra::Matrix3::identity(), Vec3::new(0.0, 0.0, 1.0));
        let sigma = 0.8;
        let opts = RenderOptions {
            blur_sigma: sigma,
            noise_sigma: 0.0,
            black: 20.0,
            white: 230.0,
            ..Default::default()
        };
        // Board x − tan(1°)·y < 0.0013 is white: image u − c = 100·(0.0013 + tan 1°·(v − c)/100).
        let slope = 1f64.to_radians().tan();
        let img = render(&cam, &pose, &|x, y| Some(x - slope * y < 0.0013), &opts);
        // Exact: the response is separable, so the white fraction is the integral over the
        // vertical offset of the horizontal CDF at the edge's distance (fine quadrature).
        let response = PixelResponse::new(sigma);
        let r = response.reach() as f64 + 0.5;
        let steps = 2000;
        let dys: Vec<(f64, f64)> = (0..steps)
            .map(|k| {
                let lo = -r + 2.0 * r * k as f64 / steps as f64;
                let hi = lo + 2.0 * r / steps as f64;
                (0.5 * (lo + hi), response.mass(lo, hi))
            })
            .collect();
        let (mut worst, mut signed, mut n): (f64, f64, f64) = (0.0, 0.0, 0.0);
        for v in 5..size - 5 {
            for u in 5..size - 5 {
                let (x, y) = (u as f64, v as f64);
                let white_fraction = dys
                    .iter()
                    .map(|(dy, mass)| {
                        mass * PixelResponse::cdf(sigma, c + 0.13 + slope * (y + dy - c) - x)
                    })
                    .sum::<f64>();
                let expected = 20.0 + 210.0 * white_fraction;
                let err = img.get_pixel(u, v)[0] as f64 - expected;
                worst = worst.max(err.abs());
                if (25.0..225.0).contains(&expected) {
                    (signed, n) = (signed + err, n + 1.0);
                }
            }
        }
        // 8-bit rounding (0.5) and the jittered sampling (~0.5 grey σ); a 0.01 px shift
        // of the edge would move the edge pixels' mean by ~1 grey.
        assert!(
            worst < 2.0,
            "worst pixel {worst:.2} grey off the continuous model"
        );
        assert!(
            (signed / n).abs() < 0.2,
            "edge pixels' mean error {:.3} grey",
            signed / n
        );
    }
}
