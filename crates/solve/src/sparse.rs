//! A symmetric block-sparse matrix stored as its lower triangle in compressed columns,
//! factored by faer's sparse Cholesky (AMD ordering, supernodal or simplicial as faer
//! chooses), for reduced systems whose blocks are mostly zero: a rig with many frames
//! whose points are each seen in a few of them couples only nearby rig poses, and a
//! dense factorisation of its 6K × 6K reduced matrix would cost K³ for a band.
//!
//! The pattern (which blocks may be non-zero) is fixed once; the symbolic factorisation
//! is computed with it and reused by every numeric one.

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, SymbolicCholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, Side};
use nalgebra::{DMatrix, DVector};

/// The pattern of a block-sparse symmetric matrix and its symbolic Cholesky.
pub struct SparsePattern {
    n: usize,
    /// Column pointers of the lower triangle (`n + 1`).
    col_ptr: Vec<usize>,
    /// Per column block offset `ob`, the row blocks below it `(oa, start)`, sorted: the
    /// entry `(oa + i, ob + j)` is at `col_ptr[ob + j] + (zb − j) + start + i`.
    below: Vec<Vec<(usize, usize)>>,
    /// Size of the block starting at each offset (0: no block starts there).
    size: Vec<usize>,
    pattern: SymbolicSparseColMat<usize>,
    symbolic: SymbolicCholesky<usize>,
}

impl SparsePattern {
    /// The pattern of an `n × n` matrix partitioned into `blocks` (`(offset, size)`,
    /// covering `0..n` without overlap) whose non-zero off-diagonal blocks are `pairs`
    /// (either order; the diagonal blocks are always in). `None` when the blocks do
    /// not partition `0..n` or a pair names an offset that starts no block.
    pub fn new(
        n: usize,
        blocks: &[(usize, usize)],
        pairs: impl IntoIterator<Item = (usize, usize)>,
    ) -> Option<Self> {
        let mut sorted = blocks.to_vec();
        sorted.sort_unstable();
        let mut at = 0;
        for &(o, z) in &sorted {
            if o != at || z == 0 {
                return None;
            }
            at += z;
        }
        if at != n {
            return None;
        }
        let mut size = vec![0; n];
        for &(o, z) in &sorted {
            size[o] = z;
        }
        let is_block = |o: usize| size.get(o).is_some_and(|&z| z > 0);
        // For each column block, the row blocks strictly below it, sorted.
        let mut rows: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (a, b) in pairs {
            if !is_block(a) || !is_block(b) {
                return None;
            }
            if a != b {
                rows[a.min(b)].push(a.max(b));
            }
        }
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut below = vec![Vec::new(); n];
        col_ptr.push(0);
        for &(ob, zb) in &sorted {
            let mut under = std::mem::take(&mut rows[ob]);
            under.sort_unstable();
            under.dedup();
            let mut start = 0;
            for &oa in &under {
                below[ob].push((oa, start));
                start += size[oa];
            }
            for j in 0..zb {
                row_idx.extend(ob + j..ob + zb);
                for &oa in &under {
                    row_idx.extend(oa..oa + size[oa]);
                }
                col_ptr.push(row_idx.len());
            }
        }
        let pattern = SymbolicSparseColMat::new_checked(n, n, col_ptr.clone(), None, row_idx);
        let symbolic = factorize_symbolic_cholesky(
            pattern.as_ref(),
            Side::Lower,
            Default::default(),
            Default::default(),
        )
        .ok()?;
        Some(Self {
            n,
            col_ptr,
            below,
            size,
            pattern,
            symbolic,
        })
    }

    /// Stored entries (the lower triangle's possible non-zeros).
    pub fn nnz(&self) -> usize {
        self.col_ptr[self.n]
    }

    /// Entries of the Cholesky factor (with its fill-in, after the fill-reducing
    /// ordering): its cost grows with this, not with `n²`.
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.len_val()
    }

    /// Zero values for this pattern.
    pub fn zeros(&self) -> Vec<f64> {
        vec![0.0; self.nnz()]
    }

    /// Add the block `h(i, j)` of rows `oa..oa+za`, columns `ob..ob+zb` (and, being
    /// symmetric, its transpose) into `values`: only its part on or below the diagonal
    /// is stored. `false` (and nothing added) when the pattern has no such block.
    pub fn add(
        &self,
        values: &mut [f64],
        (oa, za): (usize, usize),
        (ob, zb): (usize, usize),
        h: impl Fn(usize, usize) -> f64,
    ) -> bool {
        if oa == ob {
            if self.size.get(oa) != Some(&za) || za != zb {
                return false;
            }
            for j in 0..zb {
                let col = self.col_ptr[ob + j];
                for i in j..za {
                    values[col + (i - j)] += h(i, j);
                }
            }
            return true;
        }
        // Stored with the larger offset as the row block.
        let ((ra, rz), (cb, cz), flip) = if oa > ob {
            ((oa, za), (ob, zb), false)
        } else {
            ((ob, zb), (oa, za), true)
        };
        let Some(under) = self.below.get(cb) else {
            return false;
        };
        let Ok(k) = under.binary_search_by_key(&ra, |u| u.0) else {
            return false;
        };
        let start = under[k].1;
        if self.size[cb] != cz || self.size.get(ra) != Some(&rz) {
            return false;
        }
        for j in 0..cz {
            let col = self.col_ptr[cb + j] + (cz - j) + start;
            for i in 0..rz {
                values[col + i] += if flip { h(j, i) } else { h(i, j) };
            }
        }
        true
    }

    /// The dense symmetric matrix of `values` (both triangles).
    pub fn to_dense(&self, values: &[f64]) -> DMatrix<f64> {
        let mut m = DMatrix::zeros(self.n, self.n);
        let rows = self.pattern.row_idx();
        for j in 0..self.n {
            for k in self.col_ptr[j]..self.col_ptr[j + 1] {
                let i = rows[k];
                m[(i, j)] = values[k];
                m[(j, i)] = values[k];
            }
        }
        m
    }

    /// Add `d[i]` to the diagonal entry `(i, i)`.
    pub fn add_diagonal(&self, values: &mut [f64], i: usize, d: f64) {
        // The diagonal entry heads its column.
        values[self.col_ptr[i]] += d;
    }

    /// Solve `S x = b` for the symmetric positive definite `S` whose lower triangle is
    /// `values`; `None` when it is not positive definite (or the solution not finite).
    pub fn solve(&self, values: &[f64], b: DVector<f64>) -> Option<DVector<f64>> {
        let par = faer::get_global_parallelism();
        let sym = &self.symbolic;
        let mut mem = MemBuffer::try_new(StackReq::any_of(&[
            sym.factorize_numeric_llt_scratch::<f64>(par, Default::default()),
            sym.solve_in_place_scratch::<f64>(1, par),
        ]))
        .ok()?;
        let mut l = vec![0.0; sym.len_val()];
        let mat = SparseColMatRef::new(self.pattern.as_ref(), values);
        let llt = sym
            .factorize_numeric_llt(
                &mut l,
                mat,
                Side::Lower,
                Default::default(),
                par,
                MemStack::new(&mut mem),
                Default::default(),
            )
            .ok()?;
        let mut x = b;
        let n = self.n;
        let rhs = faer::MatMut::from_column_major_slice_mut(x.as_mut_slice(), n, 1);
        llt.solve_in_place_with_conj(Conj::No, rhs, par, MemStack::new(&mut mem));
        x.iter().all(|v| v.is_finite()).then_some(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sparse_solve_is_the_dense_one() {
        // Blocks 6, 3, 6, 6 (n = 21); block 0 couples block 2, block 3 couples block 1;
        // the rest zero. A random SPD matrix of that pattern, added block by block in
        // both orders.
        let blocks = [(0, 6), (6, 3), (9, 6), (15, 6)];
        let n = 21;
        let pairs = [(0, 9), (15, 6)];
        let p = SparsePattern::new(n, &blocks, pairs).expect("pattern");
        let mut seed = 7u64;
        let mut rand = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let mut dense = DMatrix::<f64>::zeros(n, n);
        let mut values = p.zeros();
        let mut put = |dense: &mut DMatrix<f64>,
                       (oa, za): (usize, usize),
                       (ob, zb): (usize, usize),
                       h: &DMatrix<f64>| {
            for i in 0..za {
                for j in 0..zb {
                    dense[(oa + i, ob + j)] += h[(i, j)];
                    if oa != ob {
                        dense[(ob + j, oa + i)] += h[(i, j)];
                    }
                }
            }
            assert!(p.add(&mut values, (oa, za), (ob, zb), |i, j| h[(i, j)]));
        };
        for &(o, z) in &blocks {
            let a = DMatrix::from_fn(z, z, |_, _| rand());
            let spd = &a * a.transpose() + DMatrix::identity(z, z) * 4.0;
            put(&mut dense, (o, z), (o, z), &spd);
        }
        put(
            &mut dense,
            (0, 6),
            (9, 6),
            &DMatrix::from_fn(6, 6, |_, _| rand()),
        );
        put(
            &mut dense,
            (6, 3),
            (15, 6),
            &DMatrix::from_fn(3, 6, |_, _| rand()),
        );
        p.add_diagonal(&mut values, 4, 0.5);
        dense[(4, 4)] += 0.5;
        // A block the pattern does not have is refused, not dropped silently.
        assert!(!p.add(&mut values, (0, 6), (15, 6), |_, _| 1.0));
        let b = DVector::from_fn(n, |i, _| (i as f64).sin());
        assert_eq!(p.to_dense(&values), dense);
        let x = p.solve(&values, b.clone()).expect("positive definite");
        let want = dense.clone().cholesky().expect("spd").solve(&b);
        assert!((&x - &want).amax() < 1e-12 * want.amax(), "{x} vs {want}");
        // Not positive definite: no step.
        let mut bad = values.clone();
        p.add_diagonal(&mut bad, 0, -1e6);
        assert!(p.solve(&bad, b).is_none());
    }

    #[test]
    fn blocks_that_do_not_partition_the_matrix_are_refused() {
        assert!(SparsePattern::new(12, &[(0, 6), (7, 5)], []).is_none());
        assert!(SparsePattern::new(12, &[(0, 6), (6, 6)], [(0, 3)]).is_none());
        assert!(SparsePattern::new(13, &[(0, 6), (6, 6)], []).is_none());
    }
}
