//! Dense linear algebra the estimators share: a symmetric eigen-decomposition that can
//! be trusted, and the pseudo-inverse and null vector built on it.
//!
//! nalgebra's `symmetric_eigen` (0.33) sometimes pairs an eigenvalue with the wrong
//! eigenvector when two eigenvalues are (nearly) equal — dimforge/nalgebra#1109, still
//! open. rigcal met it where it hurts: the rotation axis of a 360° drive (two equal large
//! eigenvalues, one near zero) came out 8.7° off, so a planar loop was classified as
//! general motion and its initialisation failed. Every decomposition is therefore checked
//! (‖M V − V Λ‖ and ‖VᵀV − I‖) and, if nalgebra's is wrong, recomputed by cyclic Jacobi
//! rotations, which are slow for big matrices but accurate for every spectrum.

use nalgebra::{DMatrix, DVector, Dyn, SymmetricEigen};

/// Eigenvalues and orthonormal eigenvectors (columns) of the symmetric part of `m`.
pub fn symmetric_eigen(m: &DMatrix<f64>) -> SymmetricEigen<f64, Dyn> {
    let sym = (m + m.transpose()) * 0.5;
    let eig = sym.clone().symmetric_eigen();
    if is_accurate(&sym, &eig) {
        eig
    } else {
        jacobi(&sym)
    }
}

/// Eigen-decomposition of a 3×3 symmetric matrix (see [`symmetric_eigen`]).
pub fn symmetric_eigen3(
    m: &nalgebra::Matrix3<f64>,
) -> (nalgebra::Vector3<f64>, nalgebra::Matrix3<f64>) {
    let e = symmetric_eigen(&DMatrix::from_column_slice(3, 3, m.as_slice()));
    (
        nalgebra::Vector3::from_column_slice(e.eigenvalues.as_slice()),
        nalgebra::Matrix3::from_column_slice(e.eigenvectors.as_slice()),
    )
}

fn is_accurate(m: &DMatrix<f64>, e: &SymmetricEigen<f64, Dyn>) -> bool {
    let n = m.nrows();
    let scale = m.norm().max(f64::MIN_POSITIVE);
    let v = &e.eigenvectors;
    let residual = m * v - v * DMatrix::from_diagonal(&e.eigenvalues);
    let ortho = v.transpose() * v - DMatrix::<f64>::identity(n, n);
    let tol = 1e-10 * (n as f64).max(1.0);
    residual.iter().all(|x| x.is_finite()) && residual.norm() <= tol * scale && ortho.norm() <= tol
}

/// Cyclic Jacobi eigenvalue algorithm on a symmetric matrix.
fn jacobi(m: &DMatrix<f64>) -> SymmetricEigen<f64, Dyn> {
    let n = m.nrows();
    let mut a = m.clone();
    let mut v = DMatrix::<f64>::identity(n, n);
    let total = a.norm_squared();
    for _ in 0..100 {
        let mut off = 0.0;
        for p in 0..n {
            for q in p + 1..n {
                off += a[(p, q)] * a[(p, q)];
            }
        }
        if off <= 1e-32 * total || off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[(p, q)];
                if apq == 0.0 {
                    continue;
                }
                let theta = (a[(q, q)] - a[(p, p)]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[(k, p)], a[(k, q)]);
                    a[(k, p)] = c * akp - s * akq;
                    a[(k, q)] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[(p, k)], a[(q, k)]);
                    a[(p, k)] = c * apk - s * aqk;
                    a[(q, k)] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[(k, p)], v[(k, q)]);
                    v[(k, p)] = c * vkp - s * vkq;
                    v[(k, q)] = s * vkp + c * vkq;
                }
            }
        }
    }
    SymmetricEigen {
        eigenvalues: DVector::from_fn(n, |i, _| a[(i, i)]),
        eigenvectors: v,
    }
}

/// Pseudo-inverse of a symmetric positive semi-definite matrix; eigenvalues below
/// `rel × λ_max` are treated as zero (their directions carry no information).
pub fn symmetric_pseudo_inverse(m: &DMatrix<f64>, rel: f64) -> DMatrix<f64> {
    let n = m.nrows();
    if n == 0 {
        return m.clone();
    }
    let eig = symmetric_eigen(m);
    let lmax = eig.eigenvalues.amax();
    let mut out = DMatrix::zeros(n, n);
    for k in 0..n {
        let l = eig.eigenvalues[k];
        if l > rel * lmax && l > 0.0 {
            let v = eig.eigenvectors.column(k);
            out += v * v.transpose() / l;
        }
    }
    out
}

/// Right singular vector of the smallest singular value (via the 9×9 or 12×12 normal matrix).
pub fn null_vector(m: &DMatrix<f64>) -> Option<nalgebra::DVector<f64>> {
    smallest_by_decomposition(&(m.transpose() * m))
}

/// [`null_vector`] for an `m` whose null space is one-dimensional by construction (a
/// homography from points in general position, as a tag's or a board's corners are): by
/// inverse iteration, a few solves with one LU factorisation, where the checked
/// decomposition of a 9×9 matrix is ~55 000 instructions and the grid completion fits
/// hundreds of homographies per image. The same vector to ~10⁻¹⁰ where the smallest
/// eigenvalue of `mᵀm` stands apart from the next; where the two are close (a ratio over
/// ~0.08) it does not converge and the decomposition answers; where they are equal to
/// working precision it stops at once on some vector of their space. Not for the
/// estimators: some of their problems are ill-conditioned enough that differences under
/// 10⁻⁹ move their results along unobservable directions (docs/performance.md).
pub fn null_vector_of_general_position(m: &DMatrix<f64>) -> Option<nalgebra::DVector<f64>> {
    let ata = m.transpose() * m;
    smallest_by_inverse_iteration(&ata).or_else(|| smallest_by_decomposition(&ata))
}

/// The unit eigenvector of the smallest eigenvalue of the symmetric `s`, from its checked
/// decomposition.
fn smallest_by_decomposition(ata: &DMatrix<f64>) -> Option<nalgebra::DVector<f64>> {
    let eig = symmetric_eigen(ata);
    let k = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?
        .0;
    Some(eig.eigenvectors.column(k).into_owned())
}

/// Successive iterates of [`smallest_by_inverse_iteration`] this close (unit vectors)
/// have converged: the error left is at most this times the eigenvalue ratio.
const INVERSE_ITERATION_TOL: f64 = 1e-11;
/// Iterations before the eigenvalues are taken as too close for inverse iteration (each
/// shrinks the error by the ratio of the two smallest: 10 reach the tolerance from a
/// ratio of 0.08).
const INVERSE_ITERATIONS: usize = 10;

/// The unit eigenvector of the smallest eigenvalue of the symmetric positive
/// semi-definite `s`, by inverse iteration; `None` when it does not converge (two
/// eigenvalues too close for the vector to be defined by them alone).
fn smallest_by_inverse_iteration(s: &DMatrix<f64>) -> Option<DVector<f64>> {
    let n = s.nrows();
    if n == 0 || !s.iter().all(|x| x.is_finite()) {
        return None;
    }
    // Shifted by a hair, so that an exactly singular `s` (exact data) still factorises:
    // the eigenvectors are the same, the ratio of the two smallest eigenvalues barely.
    let shift = 1e-14 * s.diagonal().amax();
    let lu = (s + DMatrix::identity(n, n) * shift).lu();
    let mut v = DVector::from_element(n, 1.0 / (n as f64).sqrt());
    for _ in 0..INVERSE_ITERATIONS {
        let mut x = lu.solve(&v)?;
        let norm = x.norm();
        if !norm.is_finite() || norm == 0.0 {
            return None;
        }
        x /= norm;
        if x.dot(&v) < 0.0 {
            x.neg_mut();
        }
        let change = (&x - &v).norm();
        v = x;
        if change < INVERSE_ITERATION_TOL {
            return Some(v);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The matrix Σ(R−I)ᵀ(R−I) of a noisy 360° drive on which nalgebra 0.33 returned a
    /// null vector 8.7° off (seed 1007 of car-planar-loop at 1 px).
    fn loop_matrix() -> DMatrix<f64> {
        DMatrix::from_row_slice(
            3,
            3,
            &[
                31.925297148774415,
                0.00048380039001323996,
                0.00006466969635093162,
                0.00048380039001323996,
                0.4578617586078432,
                -3.795557654718749,
                0.00006466969635093162,
                -3.795557654718749,
                31.467482441243217,
            ],
        )
    }

    fn check(m: &DMatrix<f64>, e: &SymmetricEigen<f64, Dyn>, tol: f64) {
        let n = m.nrows();
        let v = &e.eigenvectors;
        let r = m * v - v * DMatrix::from_diagonal(&e.eigenvalues);
        assert!(r.norm() <= tol * m.norm().max(1.0), "residual {}", r.norm());
        let o = v.transpose() * v - DMatrix::<f64>::identity(n, n);
        assert!(o.norm() <= tol, "orthonormality {}", o.norm());
    }

    #[test]
    fn the_loop_axis_is_the_true_null_vector() {
        let m = loop_matrix();
        let e = symmetric_eigen(&m);
        check(&m, &e, 1e-9);
        let k = e.eigenvalues.imin();
        let n = e.eigenvectors.column(k);
        // The null vector of this matrix is (0, 0.9928, 0.1197) up to noise: the vertical
        // axis seen from a camera pitched 6.9° down.
        let truth = nalgebra::DVector::from_row_slice(&[0.0, 0.992_808_6, 0.119_712_2]);
        let angle = n.dot(&truth).abs().clamp(-1.0, 1.0).acos().to_degrees();
        assert!(angle < 0.1, "axis {angle}° off");
    }

    #[test]
    fn inverse_iteration_finds_the_eigen_decompositions_null_vector() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut inverse = 0;
        for trial in 0..200 {
            let n = [3usize, 9, 12][trial % 3];
            let q = DMatrix::from_fn(n, n, |_, _| rng.gen_range(-1.0..1.0))
                .qr()
                .q();
            // Spectra from exactly singular to a smallest eigenvalue close to the next.
            let smallest = [0.0, 1e-12, 1e-6, 1e-2, 0.5, 0.9][trial % 6];
            let vals: Vec<f64> = (0..n)
                .map(|i| {
                    if i == 0 {
                        smallest
                    } else {
                        rng.gen_range(1.0..100.0)
                    }
                })
                .collect();
            let s = &q * DMatrix::from_diagonal(&DVector::from_vec(vals)) * q.transpose();
            let truth = q.column(0).into_owned();
            let fast = smallest_by_inverse_iteration(&s);
            // Well apart from the next (a ratio of 10⁻² at most), it always converges.
            assert!(smallest > 1e-2 || fast.is_some(), "trial {trial}");
            if fast.is_some() {
                inverse += 1;
            }
            // Unit vectors, up to sign.
            let off = |v: &DVector<f64>| (v - &truth).norm().min((v + &truth).norm());
            for v in fast.into_iter().chain(smallest_by_decomposition(&s)) {
                assert!(off(&v) < 1e-9, "trial {trial}: {} off", off(&v));
            }
            let m = s.clone().cholesky().map(|c| c.l().transpose());
            if let Some(m) = m {
                let v = null_vector_of_general_position(&m).unwrap();
                assert!(off(&v) < 1e-9, "trial {trial}: {} off", off(&v));
            }
        }
        // Some of the closer spectra converge too (their next eigenvalue far enough).
        assert!(
            inverse >= 134,
            "inverse iteration converged {inverse} times of 200"
        );
    }

    #[test]
    fn close_smallest_eigenvalues_fall_back_to_the_decomposition() {
        // A 2-dimensional near-null space: no vector is singled out, inverse iteration
        // declines and the decomposition answers, as before.
        let s = DMatrix::from_diagonal(&DVector::from_row_slice(&[1e-9, 1.0000001e-9, 3.0, 7.0]));
        assert!(smallest_by_inverse_iteration(&s).is_none());
        let m = s.map(f64::sqrt);
        let v = null_vector_of_general_position(&m).unwrap();
        assert!(v[2].abs() < 1e-9 && v[3].abs() < 1e-9, "{v}");
    }

    #[test]
    fn jacobi_matches_the_definition_on_every_spectrum() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for n in [1usize, 2, 3, 6, 9, 20] {
            for repeated in [false, true] {
                // Random orthonormal basis, chosen spectrum (optionally with repeats).
                let q = DMatrix::from_fn(n, n, |_, _| rng.gen_range(-1.0..1.0))
                    .qr()
                    .q();
                let vals: Vec<f64> = (0..n)
                    .map(|i| {
                        if repeated && i % 2 == 1 {
                            7.0
                        } else {
                            rng.gen_range(-5.0..50.0)
                        }
                    })
                    .collect();
                let m =
                    &q * DMatrix::from_diagonal(&DVector::from_vec(vals.clone())) * q.transpose();
                let e = jacobi(&m);
                check(&m, &e, 1e-9);
                let mut got: Vec<f64> = e.eigenvalues.iter().copied().collect();
                let mut want = vals;
                got.sort_by(f64::total_cmp);
                want.sort_by(f64::total_cmp);
                for (g, w) in got.iter().zip(&want) {
                    assert!((g - w).abs() < 1e-9 * 50.0, "{g} vs {w}");
                }
                check(&m, &symmetric_eigen(&m), 1e-9);
            }
        }
    }
}
