//! Camera models: `pinhole`, `radtan` (OpenCV k1,k2,p1,p2[,k3]) and `equidistant`
//! (OpenCV fisheye k1..k4), each with projection, iterative unprojection and the
//! analytic Jacobian of the projection with respect to the point in camera frame.
//!
//! Image coordinates follow OpenCV: pixel centres at integer coordinates, origin at the
//! centre of the top-left pixel.

use super::{Vec2, Vec3};
use nalgebra::{Matrix2, Matrix2x3};
use serde::{Deserialize, Serialize};

/// Lens distortion of a camera, in normalised image coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase")]
pub enum CameraModel {
    Pinhole,
    Radtan {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
        k3: f64,
    },
    Equidistant {
        k1: f64,
        k2: f64,
        k3: f64,
        k4: f64,
    },
}

impl CameraModel {
    pub fn name(&self) -> &'static str {
        match self {
            CameraModel::Pinhole => "pinhole",
            CameraModel::Radtan { .. } => "radtan",
            CameraModel::Equidistant { .. } => "equidistant",
        }
    }

    /// The coefficients in OpenCV order, as they appear in a session's `distortion`.
    pub fn coefficients(&self) -> Vec<f64> {
        match *self {
            CameraModel::Pinhole => vec![],
            CameraModel::Radtan { k1, k2, p1, p2, k3 } => vec![k1, k2, p1, p2, k3],
            CameraModel::Equidistant { k1, k2, k3, k4 } => vec![k1, k2, k3, k4],
        }
    }

    /// Distort normalised coordinates; returns the distorted point and d(distorted)/d(undistorted).
    fn distort(&self, x: f64, y: f64) -> (Vec2, Matrix2<f64>) {
        self.distorted::<true>(x, y)
    }

    /// The distorted point alone, the same bit for bit as [`distort`](Self::distort)'s:
    /// a projection that needs no Jacobian (reprojection costs, a tag's side in pixels)
    /// skips its arithmetic.
    fn distort_point(&self, x: f64, y: f64) -> Vec2 {
        self.distorted::<false>(x, y).0
    }

    /// Both of the above: the point's arithmetic is written once, and with `JACOBIAN`
    /// false the Jacobian is the zero matrix, never computed.
    #[inline(always)]
    fn distorted<const JACOBIAN: bool>(&self, x: f64, y: f64) -> (Vec2, Matrix2<f64>) {
        match *self {
            CameraModel::Pinhole => (Vec2::new(x, y), Matrix2::identity()),
            CameraModel::Radtan { k1, k2, p1, p2, k3 } => {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
                let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
                if !JACOBIAN {
                    return (Vec2::new(xd, yd), Matrix2::zeros());
                }
                let dradial_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
                let (drx, dry) = (dradial_dr2 * 2.0 * x, dradial_dr2 * 2.0 * y);
                let j = Matrix2::new(
                    radial + x * drx + 2.0 * p1 * y + 6.0 * p2 * x,
                    x * dry + 2.0 * p1 * x + 2.0 * p2 * y,
                    y * drx + 2.0 * p1 * x + 2.0 * p2 * y,
                    radial + y * dry + 6.0 * p1 * y + 2.0 * p2 * x,
                );
                (Vec2::new(xd, yd), j)
            }
            CameraModel::Equidistant { k1, k2, k3, k4 } => {
                let r = (x * x + y * y).sqrt();
                if r < 1e-12 {
                    return (Vec2::new(x, y), Matrix2::identity());
                }
                let th = r.atan();
                let t2 = th * th;
                let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
                let thd = th * poly;
                let s = thd / r;
                if !JACOBIAN {
                    return (Vec2::new(x * s, y * s), Matrix2::zeros());
                }
                let dthd_dth =
                    1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)));
                let dth_dr = 1.0 / (1.0 + r * r);
                let ds_dr = (dthd_dth * dth_dr * r - thd) / (r * r);
                let (drdx, drdy) = (x / r, y / r);
                let j = Matrix2::new(
                    s + x * ds_dr * drdx,
                    x * ds_dr * drdy,
                    y * ds_dr * drdx,
                    s + y * ds_dr * drdy,
                );
                (Vec2::new(x * s, y * s), j)
            }
        }
    }
}

/// An intrinsically calibrated camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub model: CameraModel,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

/// Points closer to the image plane than this (in normalised depth) do not project.
const MIN_DEPTH: f64 = 1e-6;

impl Camera {
    pub fn pinhole(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Self {
        Self {
            model: CameraModel::Pinhole,
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// Project a point in camera coordinates to pixels; `None` behind the camera.
    pub fn project(&self, p: &Vec3) -> Option<Vec2> {
        let (x, y, _) = self.normalised(p)?;
        Some(self.to_pixel(self.model.distort_point(x, y)))
    }

    /// `(X/Z, Y/Z)` and `1/Z`; `None` behind the camera.
    #[inline(always)]
    fn normalised(&self, p: &Vec3) -> Option<(f64, f64, f64)> {
        if p.z < MIN_DEPTH {
            return None;
        }
        let iz = 1.0 / p.z;
        Some((p.x * iz, p.y * iz, iz))
    }

    /// Distorted normalised coordinates to pixels.
    #[inline(always)]
    fn to_pixel(&self, d: Vec2) -> Vec2 {
        Vec2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy)
    }

    /// Projection and its Jacobian d(u,v)/d(X,Y,Z).
    pub fn project_with_jacobian(&self, p: &Vec3) -> Option<(Vec2, Matrix2x3<f64>)> {
        let (x, y, iz) = self.normalised(p)?;
        let (d, jd) = self.model.distort(x, y);
        let uv = self.to_pixel(d);
        let jn = Matrix2x3::new(iz, 0.0, -x * iz, 0.0, iz, -y * iz);
        let jk = Matrix2::new(self.fx, 0.0, 0.0, self.fy);
        Some((uv, jk * jd * jn))
    }

    /// Normalised undistorted coordinates `(x, y)` with `(x, y, 1)` along the ray of
    /// pixel `uv`. Newton iterations on the distortion; `None` if they do not converge.
    pub fn unproject(&self, uv: &Vec2) -> Option<Vec2> {
        self.unproject_from(uv, None)
    }

    /// [`unproject`](Self::unproject) with Newton started at `near`, the undistorted
    /// coordinates of a pixel close to `uv` (a few pixels off, on a tag's side): three
    /// steps where a start at the distorted coordinates takes four or five (the test
    /// cameras' strong radtan and fisheye, over the image). The same answer, to the
    /// same tolerance, as long as `near` is near: a distortion polynomial folds back far
    /// out, and Newton from a point beyond the fold finds the other root.
    pub fn unproject_near(&self, uv: &Vec2, near: Vec2) -> Option<Vec2> {
        self.unproject_from(uv, Some(near))
            .or_else(|| self.unproject(uv))
    }

    fn unproject_from(&self, uv: &Vec2, start: Option<Vec2>) -> Option<Vec2> {
        let target = Vec2::new((uv.x - self.cx) / self.fx, (uv.y - self.cy) / self.fy);
        if matches!(self.model, CameraModel::Pinhole) {
            return Some(target);
        }
        let mut xy = start
            .filter(|s| s.x.is_finite() && s.y.is_finite())
            .unwrap_or(target);
        for _ in 0..50 {
            let (d, j) = self.model.distort(xy.x, xy.y);
            let err = d - target;
            if err.norm() < 1e-14 {
                return Some(xy);
            }
            let step = j.try_inverse()? * err;
            xy -= step;
            if !xy.x.is_finite() || !xy.y.is_finite() {
                return None;
            }
        }
        let d = self.model.distort_point(xy.x, xy.y);
        ((d - target).norm() < 1e-9).then_some(xy)
    }

    /// Is the pixel inside the image (with the pixel-centre convention)?
    pub fn in_image(&self, uv: &Vec2) -> bool {
        uv.x >= -0.5
            && uv.y >= -0.5
            && uv.x <= self.width as f64 - 0.5
            && uv.y <= self.height as f64 - 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cameras() -> Vec<Camera> {
        let base = Camera::pinhole(800.0, 810.0, 640.0, 360.0, 1280, 720);
        vec![
            base.clone(),
            Camera {
                model: CameraModel::Radtan {
                    k1: -0.28,
                    k2: 0.08,
                    p1: 1e-3,
                    p2: -5e-4,
                    k3: -0.01,
                },
                ..base.clone()
            },
            Camera {
                model: CameraModel::Equidistant {
                    k1: 0.05,
                    k2: -0.01,
                    k3: 0.003,
                    k4: -0.001,
                },
                ..base
            },
        ]
    }

    #[test]
    fn projection_without_the_jacobian_is_the_same_point_bit_for_bit() {
        for cam in cameras() {
            for i in -12..=12 {
                for j in -8..=8 {
                    // Out to 67° off axis, and the optical axis itself.
                    let p = Vec3::new(0.1 * i as f64, 0.1 * j as f64, 1.0 + 0.05 * j as f64);
                    let (with, _) = cam.project_with_jacobian(&p).unwrap();
                    let alone = cam.project(&p).unwrap();
                    assert_eq!(
                        (alone.x.to_bits(), alone.y.to_bits()),
                        (with.x.to_bits(), with.y.to_bits()),
                        "{:?} at {p:?}",
                        cam.model
                    );
                }
            }
            assert_eq!(cam.project(&Vec3::new(0.1, 0.2, -1.0)), None);
        }
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let points = [
            Vec3::new(0.3, -0.2, 2.0),
            Vec3::new(-0.5, 0.4, 1.0),
            Vec3::new(0.01, 0.02, 5.0),
        ];
        for cam in cameras() {
            for p in points {
                let (_, j) = cam.project_with_jacobian(&p).unwrap();
                for k in 0..3 {
                    let h = 1e-6;
                    let mut pp = p;
                    pp[k] += h;
                    let mut pm = p;
                    pm[k] -= h;
                    let fd = (cam.project(&pp).unwrap() - cam.project(&pm).unwrap()) / (2.0 * h);
                    let an = j.column(k);
                    assert!(
                        (fd - an).norm() < 1e-5 * (1.0 + an.norm()),
                        "{:?} col {k}: fd {fd:?} an {an:?}",
                        cam.model
                    );
                }
            }
        }
    }

    #[test]
    fn unprojection_inverts_projection() {
        for cam in cameras() {
            for p in [
                Vec3::new(0.3, -0.2, 1.0),
                Vec3::new(-0.6, 0.3, 1.0),
                Vec3::new(0.0, 0.0, 1.0),
            ] {
                let uv = cam.project(&p).unwrap();
                let xy = cam.unproject(&uv).unwrap();
                assert!((xy - Vec2::new(p.x, p.y)).norm() < 1e-10, "{:?}", cam.model);
            }
        }
    }

    /// Started at a pixel a few pixels off, or at no point, the unprojection is the one
    /// started at the distorted coordinates, over the whole image.
    #[test]
    fn unprojection_started_nearby_is_the_same() {
        for cam in cameras() {
            for j in 0..=8 {
                for i in 0..=8 {
                    let uv = Vec2::new(
                        cam.width as f64 * i as f64 / 8.0,
                        cam.height as f64 * j as f64 / 8.0,
                    );
                    let Some(xy) = cam.unproject(&uv) else {
                        continue;
                    };
                    let near = cam.unproject(&(uv + Vec2::new(3.0, -2.0))).unwrap();
                    for start in [near, Vec2::new(f64::NAN, 0.0)] {
                        let got = cam.unproject_near(&uv, start).unwrap();
                        assert!((got - xy).norm() < 1e-12, "{:?} at {uv:?}", cam.model);
                    }
                }
            }
        }
    }

    #[test]
    fn behind_camera_does_not_project() {
        assert!(cameras()[0].project(&Vec3::new(0.0, 0.0, -1.0)).is_none());
    }
}
