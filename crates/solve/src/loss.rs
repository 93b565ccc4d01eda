//! Robust losses on residual norms (pixels), applied by iteratively reweighted least
//! squares: each residual block is scaled by `sqrt(w)` with `w = ρ'(e²)`.

use serde::{Deserialize, Serialize};

/// Median residual norm of a 2D Gaussian with per-axis σ is σ·√(2 ln 2).
const MEDIAN_NORM_PER_SIGMA: f64 = 1.177_410_022_515_474_6;

/// Median (upper median for even counts); `None` when empty.
pub fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

/// Robust pixel σ from 2D residual norms: the median norm over √(2 ln 2), so a few gross
/// outliers do not inflate it. Non-finite norms are ignored; `None` when none is left.
pub fn robust_sigma(norms: &[f64]) -> Option<f64> {
    median(norms.iter().copied().filter(|x| x.is_finite()).collect())
        .map(|m| m / MEDIAN_NORM_PER_SIGMA)
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Loss {
    /// Plain least squares.
    Squared,
    /// Quadratic up to `scale` pixels, linear beyond.
    Huber { scale: f64 },
    /// Logarithmic beyond `scale` pixels: outliers far away weigh almost nothing.
    Cauchy { scale: f64 },
}

impl Loss {
    /// ρ(e²): the cost contribution of a residual with squared norm `e2`.
    pub fn rho(&self, e2: f64) -> f64 {
        match *self {
            Loss::Squared => e2,
            Loss::Huber { scale } => {
                let e = e2.sqrt();
                if e <= scale {
                    e2
                } else {
                    2.0 * scale * e - scale * scale
                }
            }
            Loss::Cauchy { scale } => scale * scale * (1.0 + e2 / (scale * scale)).ln(),
        }
    }

    /// ρ'(e²): the IRLS weight.
    pub fn weight(&self, e2: f64) -> f64 {
        match *self {
            Loss::Squared => 1.0,
            Loss::Huber { scale } => {
                let e = e2.sqrt();
                if e <= scale {
                    1.0
                } else {
                    scale / e
                }
            }
            Loss::Cauchy { scale } => 1.0 / (1.0 + e2 / (scale * scale)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weight_is_derivative_of_rho() {
        for loss in [
            Loss::Squared,
            Loss::Huber { scale: 1.5 },
            Loss::Cauchy { scale: 2.0 },
        ] {
            for e2 in [0.1, 1.0, 4.0, 30.0] {
                let h = 1e-6;
                let fd = (loss.rho(e2 + h) - loss.rho(e2 - h)) / (2.0 * h);
                assert!((fd - loss.weight(e2)).abs() < 1e-6, "{loss:?} at {e2}");
            }
        }
    }
}
