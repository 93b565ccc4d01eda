//! A bundle problem over rigs: `cam_from_world = (world_from_rig · rig_from_cam)⁻¹`.
//!
//! The same structure serves two stages: the per-scene bundle adjustment of the
//! trajectories (each image its own "rig pose", one identity extrinsic) and the rig
//! bundle adjustment of Lébraly §4 (one rig pose per frame, one extrinsic per camera).
//! Points are free 3-vectors or corners of rigid bodies (6-DOF `world_from_body`).
//!
//! Every 6-DOF block is perturbed in the decoupled form of [`Pose::perturbed`]:
//! `[dt (3, metres, outer frame), dφ (3, radians, outer frame)]`.
//!
//! The linear system of each LM step is reduced by a Schur complement on the points and
//! bodies (their blocks of the normal matrix are block-diagonal), leaving a system over
//! rig poses and extrinsics (or, with many frames, over points and extrinsics), solved by
//! Cholesky: dense when every block couples most of it, sparse (`sparse_pattern`) when
//! it is a band.

use super::lm::{self, Damping, LeastSquares, NormalEquations, Rules, Termination};
use super::loss::Loss;
use super::sparse::SparsePattern;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::Accum;
use nalgebra::{DMatrix, DVector, Matrix2x3, Matrix6, SMatrix, Vector6};
use rayon::prelude::*;
use rigcal_core::geometry::so3::skew;
use rigcal_core::geometry::{Camera, Mat3, Pose, Vec2, Vec3};
use rigcal_core::linalg::symmetric_pseudo_inverse;
use std::cell::RefCell;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};
use std::time::Instant;

type J26 = SMatrix<f64, 2, 6>;

/// Where an observed point lives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PointRef {
    Free(usize),
    Body { body: usize, local: Vec3 },
}

/// One 2D observation: camera `cam` of rig pose `rig` saw `point` at pixel `uv`.
#[derive(Clone, Copy, Debug)]
pub struct Obs {
    pub rig: usize,
    pub cam: usize,
    pub point: PointRef,
    pub uv: Vec2,
}

/// A measured distance between two points; weighted `pixel_sigma / sigma` in the cost.
#[derive(Clone, Copy, Debug)]
pub struct DistanceConstraint {
    pub a: PointRef,
    pub b: PointRef,
    pub distance: f64,
    pub sigma: f64,
}

/// A Gaussian prior on one direction of the extrinsics' tangent space at `origin`:
/// `Σ_c v_c · [t_c − t0_c ; log(R_c R0_cᵀ)] ≈ 0 ± sigma`. It holds directions the data
/// cannot determine (the height under planar motion) at their initial value, so that
/// LM does not fit noise by wandering along them.
#[derive(Clone, Debug)]
pub struct DirectionPrior {
    pub terms: Vec<(usize, Vector6<f64>)>,
    pub origin: Vec<Pose>,
    pub sigma: f64,
}

#[derive(Clone, Debug)]
pub struct BundleProblem {
    pub cameras: Vec<Camera>,
    pub rig_from_cam: Vec<Pose>,
    pub cam_fixed: Vec<bool>,
    pub world_from_rig: Vec<Pose>,
    pub rig_fixed: Vec<bool>,
    pub points: Vec<Vec3>,
    pub world_from_body: Vec<Pose>,
    pub body_fixed: Vec<bool>,
    pub observations: Vec<Obs>,
    pub distances: Vec<DistanceConstraint>,
    pub priors: Vec<DirectionPrior>,
    /// The pixel noise the distance residuals are scaled to (see [`DistanceConstraint`]).
    pub pixel_sigma: f64,
}

#[derive(Clone, Copy, Debug)]
pub struct LmOptions {
    pub max_iterations: usize,
    pub loss: Loss,
    /// Stop when the relative cost decrease of an accepted step is below this.
    pub function_tolerance: f64,
    /// Stop when the step is this small relative to the parameters.
    pub parameter_tolerance: f64,
    pub gradient_tolerance: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            loss: Loss::Squared,
            // Ceres stops at a relative decrease of 1e-6; 1e-9 keeps noise-free problems
            // exact (their cost falls to ~0 first) without crawling on flat directions.
            function_tolerance: 1e-9,
            parameter_tolerance: 1e-12,
            gradient_tolerance: 1e-12,
        }
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct BundleSummary {
    pub iterations: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub converged: bool,
    pub termination: String,
    pub seconds: f64,
    pub reduced_dimension: usize,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Slot {
    Fixed,
    Reduced(usize),
    Elim(usize),
}

/// Which parameter blocks are solved where; built once per solve.
struct Layout {
    rig: Vec<Slot>,
    cam: Vec<Slot>,
    point: Vec<Slot>,
    body: Vec<Slot>,
    n_reduced: usize,
    /// Size (3 or 6) of each eliminated block.
    elim_size: Vec<usize>,
    /// For each eliminated block: the reduced blocks `(offset, size)` it couples with.
    couplings: Vec<Vec<(usize, usize)>>,
    /// Per observation: index of its rig and camera blocks in the coupling list of its
    /// eliminated block (if the point is eliminated and those blocks are reduced).
    obs_coupling: Vec<[Option<usize>; 3]>,
    /// The observations grouped by eliminated block (in block order), those without
    /// one last; `elim_start[e]` is where block `e`'s begin (`elim_start[ne]`: those
    /// without).
    elim_order: Vec<usize>,
    elim_start: Vec<usize>,
    /// The distinct pairs of reduced blocks `(offset a, size a, offset b, size b)` that
    /// observations couple, and per observation the index of each of its pairs of block
    /// positions ([`PAIR_INDEX`]; `u32::MAX`: not a reduced pair). Observations add
    /// their reduced blocks into this compact table, scattered into the reduced matrix
    /// once: added into the matrix directly, in the order of their eliminated blocks,
    /// every observation touched cold cache lines far apart.
    pairs: Vec<(usize, usize, usize, usize)>,
    obs_pairs: Vec<[u32; 6]>,
}

impl Layout {
    /// Nothing to solve (the equations a dropped linearisation leaves behind).
    const EMPTY: Layout = Layout {
        rig: Vec::new(),
        cam: Vec::new(),
        point: Vec::new(),
        body: Vec::new(),
        n_reduced: 0,
        elim_size: Vec::new(),
        couplings: Vec::new(),
        obs_coupling: Vec::new(),
        elim_order: Vec::new(),
        elim_start: Vec::new(),
        pairs: Vec::new(),
        obs_pairs: Vec::new(),
    };
}

/// A hash map keyed by parameter offsets. The standard library's SipHash (resistant to
/// chosen keys, which these are not) was most of the layout's time at K = 200 rig poses.
type OffsetMap<K, V> = HashMap<K, V, BuildHasherDefault<OffsetHasher>>;

/// A multiplicative hash of integers (FxHash's, with rustc-hash 2's final rotation so
/// that the bucket bits depend on every bit of keys that are multiples of 3 or 6).
#[derive(Default)]
struct OffsetHasher(u64);

impl Hasher for OffsetHasher {
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }

    fn write_u64(&mut self, n: u64) {
        self.0 = (self.0 ^ n).wrapping_mul(0xf135_7aea_2e62_a9c5);
    }

    fn write_usize(&mut self, n: usize) {
        self.write_u64(n as u64);
    }

    fn finish(&self) -> u64 {
        self.0.rotate_left(26)
    }
}

/// One residual's Jacobian blocks: slot, size, and the 2×6 (zero-padded) matrix.
type Blocks = [(Slot, usize, J26); 4];

/// Normal equations `H δ = −g`, split into reduced and eliminated parts.
struct Normal {
    hrr: ReducedBlocks,
    gr: DVector<f64>,
    hee: Vec<Matrix6<f64>>,
    ge: Vec<Vector6<f64>>,
    /// Per eliminated block: H_{E,R} with each block it couples with.
    her: Vec<Couplings>,
    cost: f64,
}

/// The coupling blocks `H_{E,R}` of one eliminated block of size `ze` (their rows) with
/// each reduced block it couples with: `ze × 6` each, column-major (the columns beyond a
/// reduced block's size stay zero). A point's take 18 numbers, where a padded 6×6 would
/// take 36: at K = 200 rig poses these are the largest part of the normal equations.
struct Couplings {
    ze: usize,
    data: Vec<f64>,
}

impl Couplings {
    fn zeros(ze: usize, count: usize) -> Self {
        Self {
            ze,
            data: vec![0.0; count * ze * 6],
        }
    }

    /// Coupling `c`, `ze × 6` column-major.
    #[cfg(test)]
    fn block(&self, c: usize) -> &[f64] {
        &self.data[c * self.ze * 6..(c + 1) * self.ze * 6]
    }

    fn block_mut(&mut self, c: usize) -> &mut [f64] {
        &mut self.data[c * self.ze * 6..(c + 1) * self.ze * 6]
    }

    /// The blocks with their coupled reduced blocks `(offset, size)`.
    fn iter<'a>(
        &'a self,
        couplings: &'a [(usize, usize)],
    ) -> impl Iterator<Item = (&'a [f64], (usize, usize))> + 'a {
        self.data
            .chunks_exact(self.ze * 6)
            .zip(couplings.iter().copied())
    }
}

/// A block of `H_RR` outside the layout's pairs: `(offset a, size a, offset b, size b,
/// block)`.
type ExtraBlock = (usize, usize, usize, usize, Matrix6<f64>);

/// `H_RR`, the reduced part of the normal equations, as its nonzero blocks: one per pair
/// of reduced blocks that observations couple ([`Layout::pairs`]), and those of the
/// distance and prior terms. The dense matrix is written only where it is solved
/// ([`ReducedBlocks::write_into`]): kept dense (K = 200 rig poses: 12 MB, nearly all
/// zeros) it was cleared at every linearisation and copied at every damped solve.
struct ReducedBlocks {
    /// Aligned with [`Layout::pairs`].
    pairs: Vec<Matrix6<f64>>,
    /// In the order they were added.
    extra: Vec<ExtraBlock>,
    /// The diagonal of `H_RR` (the damping's scale), once the blocks are complete.
    diag: DVector<f64>,
}

impl ReducedBlocks {
    fn zeros(layout: &Layout) -> Self {
        Self {
            pairs: vec![Matrix6::zeros(); layout.pairs.len()],
            extra: Vec::new(),
            diag: DVector::zeros(layout.n_reduced),
        }
    }

    fn clear(&mut self) {
        self.pairs.fill(Matrix6::zeros());
        self.extra.clear();
        self.diag.fill(0.0);
    }

    fn blocks<'a>(
        &'a self,
        layout: &'a Layout,
    ) -> impl Iterator<Item = ((usize, usize), (usize, usize), &'a Matrix6<f64>)> + 'a {
        let pairs = self
            .pairs
            .iter()
            .zip(&layout.pairs)
            .map(|(h, &(oa, za, ob, zb))| ((oa, za), (ob, zb), h));
        let extra = self
            .extra
            .iter()
            .map(|(oa, za, ob, zb, h)| ((*oa, *za), (*ob, *zb), h));
        pairs.chain(extra)
    }

    /// Sum the diagonal, once every block is in.
    fn finish(&mut self, layout: &Layout) {
        let mut diag = std::mem::take(&mut self.diag);
        diag.fill(0.0);
        for ((oa, za), (ob, _), h) in self.blocks(layout) {
            if oa == ob {
                for i in 0..za {
                    diag[oa + i] += h[(i, i)];
                }
            }
        }
        self.diag = diag;
    }

    /// The dense symmetric matrix (both triangles) into `s`, `n_reduced` square: the
    /// pairs are distinct, so each entry is the same sum, in the same order, as blocks
    /// added into a zero matrix one after another.
    fn write_into(&self, s: &mut DMatrix<f64>, layout: &Layout) {
        s.as_mut_slice()
            .par_chunks_mut(1 << 16)
            .for_each(|c| c.fill(0.0));
        for (a, b, h) in self.blocks(layout) {
            add_symmetric_block(s, a, b, h);
        }
    }

    fn to_dense(&self, layout: &Layout) -> DMatrix<f64> {
        let mut s = DMatrix::zeros(layout.n_reduced, layout.n_reduced);
        self.write_into(&mut s, layout);
        s
    }
}

impl Normal {
    /// Normal equations of `layout` to accumulate into: `spare` (equations of the same
    /// layout, from an earlier linearisation) with its reduced rows cleared, or new ones.
    /// The eliminated blocks' rows of `spare` are left to the parts of
    /// [`BundleProblem::normal_equations_in_parts`] that own them, which clear them over
    /// the cores.
    fn zeroed(layout: &Layout, spare: Option<Normal>) -> Normal {
        match spare {
            Some(mut n)
                if n.hee.len() == layout.elim_size.len()
                    && n.gr.len() == layout.n_reduced
                    && n.hrr.pairs.len() == layout.pairs.len() =>
            {
                n.hrr.clear();
                n.gr.fill(0.0);
                n.cost = 0.0;
                n
            }
            _ => Normal::zeros(layout),
        }
    }

    fn zeros(layout: &Layout) -> Normal {
        let nr = layout.n_reduced;
        let ne = layout.elim_size.len();
        Normal {
            hrr: ReducedBlocks::zeros(layout),
            gr: DVector::zeros(nr),
            hee: vec![Matrix6::zeros(); ne],
            ge: vec![Vector6::zeros(); ne],
            her: layout
                .couplings
                .iter()
                .zip(&layout.elim_size)
                .map(|(c, &ze)| Couplings::zeros(ze, c.len()))
                .collect(),
            cost: 0.0,
        }
    }

    /// All of the normal equations as a sink.
    fn sink(&mut self) -> Sink<'_> {
        Sink {
            extra: Some(&mut self.hrr.extra),
            pair: &mut [],
            gr: &mut self.gr,
            hee: &mut self.hee,
            ge: &mut self.ge,
            her: &mut self.her,
            first_elim: 0,
        }
    }
}

/// Where observations accumulate: the reduced rows, and the rows of the eliminated
/// blocks from `first_elim` on (a part of the observations owns a run of them).
struct Sink<'a> {
    /// Blocks of reduced pairs not in the layout's table (distances and priors), or
    /// (observations) the table's blocks `pair`.
    extra: Option<&'a mut Vec<ExtraBlock>>,
    pair: &'a mut [Matrix6<f64>],
    gr: &'a mut DVector<f64>,
    hee: &'a mut [Matrix6<f64>],
    ge: &'a mut [Vector6<f64>],
    her: &'a mut [Couplings],
    first_elim: usize,
}

/// Observations per part of the normal equations at least (fewer are not worth a
/// thread), and parts at most.
const MIN_PART_OBSERVATIONS: usize = 4096;
const MAX_PARTS: usize = 4;

/// Observations per chunk of the cost's sum over the cores.
const COST_CHUNK: usize = 4096;

/// The index in an observation's pair list (`Layout::obs_pairs`) of the pair of its
/// block positions `a ≤ b` (rig 0, camera 1, point 2).
const PAIR_INDEX: [[usize; 4]; 4] = [[0, 1, 2, 6], [6, 3, 4, 6], [6, 6, 5, 6], [6; 4]];

rigcal_core::avx2_or_portable! {
/// Accumulate the observations `obs` (indices) of `problem` into `sink`; their cost, or
/// `None` when a point is behind its camera. The hot loop of the normal equations:
/// compiled for AVX2 too ([`rigcal_core::simd`]), the blocks' products twice as wide.
fn observation_normal(
    problem: &BundleProblem,
    layout: &Layout,
    loss: &Loss,
    obs: &[usize],
    sink: &mut Sink,
) -> Option<f64> {
    problem.observation_normal_portable(layout, loss, obs, sink)
}
}

impl BundleProblem {
    fn point_world(&self, p: &PointRef) -> Vec3 {
        match *p {
            PointRef::Free(i) => self.points[i],
            PointRef::Body { body, local } => self.world_from_body[body].apply(&local),
        }
    }

    /// Reprojection residual (projected − observed, pixels) of one observation.
    pub fn residual(&self, o: &Obs) -> Option<Vec2> {
        self.residual_from(o, &self.cam_from_world(o.rig, o.cam))
    }

    /// Set every observation's pixel to where its point projects now: the exact
    /// observations of a problem built from its truth (tests, synthetic studies).
    /// Returns how many could not be projected (behind their camera); those keep theirs.
    pub fn observe_exactly(&mut self) -> usize {
        let mut behind = 0;
        for i in 0..self.observations.len() {
            match self.residual(&self.observations[i]) {
                Some(r) => self.observations[i].uv += r,
                None => behind += 1,
            }
        }
        behind
    }

    /// Add a free point at `world` that camera `cam` sees from every rig pose (its
    /// pixels set by [`Self::observe_exactly`]); returns its index.
    pub fn add_point_seen_from_every_rig(&mut self, world: Vec3, cam: usize) -> usize {
        self.points.push(world);
        let p = self.points.len() - 1;
        for rig in 0..self.world_from_rig.len() {
            self.observations.push(Obs {
                rig,
                cam,
                point: PointRef::Free(p),
                uv: Vec2::zeros(),
            });
        }
        p
    }

    fn cam_from_world(&self, rig: usize, cam: usize) -> Pose {
        (self.world_from_rig[rig] * self.rig_from_cam[cam]).inverse()
    }

    /// [`Self::residual`], the camera's pose given.
    fn residual_from(&self, o: &Obs, cam_from_world: &Pose) -> Option<Vec2> {
        let x = self.point_world(&o.point);
        self.cameras[o.cam]
            .project(&cam_from_world.apply(&x))
            .map(|uv| uv - o.uv)
    }

    /// Drop the observations whose point is not in front of its camera (they cannot be
    /// linearised); returns which observations were kept, in their original order.
    pub fn drop_unprojectable(&mut self) -> Vec<bool> {
        let keep: Vec<bool> = self
            .observations
            .iter()
            .map(|o| self.point_in_camera(o).z > 0.0)
            .collect();
        let mut it = keep.iter();
        self.observations.retain(|_| *it.next().unwrap_or(&false));
        keep
    }

    /// Point in camera coordinates; positive depth means in front.
    pub fn point_in_camera(&self, o: &Obs) -> Vec3 {
        let x = self.point_world(&o.point);
        (self.world_from_rig[o.rig] * self.rig_from_cam[o.cam])
            .inverse()
            .apply(&x)
    }

    /// Residual and the Jacobians w.r.t. rig pose, extrinsic and world point.
    #[inline(always)]
    fn linearize_obs(&self, o: &Obs) -> Option<(Vec2, J26, J26, Matrix2x3<f64>)> {
        let x = self.point_world(&o.point);
        let rig = &self.world_from_rig[o.rig];
        let ext = &self.rig_from_cam[o.cam];
        let rkt = rig.rot.transpose();
        let q = rkt * (x - rig.trans);
        let rxt = ext.rot.transpose();
        let p = rxt * (q - ext.trans);
        let (uv, jp) = self.cameras[o.cam].project_with_jacobian(&p)?;
        let jq = jp * rxt;
        let mut j_rig = J26::zeros();
        j_rig.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-jq * rkt));
        j_rig
            .fixed_view_mut::<2, 3>(0, 3)
            .copy_from(&(jq * rkt * skew(&(x - rig.trans))));
        let mut j_cam = J26::zeros();
        j_cam.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-jq));
        j_cam
            .fixed_view_mut::<2, 3>(0, 3)
            .copy_from(&(jp * rxt * skew(&(q - ext.trans))));
        Some((uv - o.uv, j_rig, j_cam, jq * rkt))
    }

    /// d(world point)/d(block) for the block the point belongs to, as a 3×6 (padded).
    fn point_block(&self, p: &PointRef, layout: &Layout) -> (Slot, usize, SMatrix<f64, 3, 6>) {
        match *p {
            PointRef::Free(i) => {
                let mut j = SMatrix::<f64, 3, 6>::zeros();
                j.fixed_view_mut::<3, 3>(0, 0).copy_from(&Mat3::identity());
                (layout.point[i], 3, j)
            }
            PointRef::Body { body, local } => {
                let mut j = SMatrix::<f64, 3, 6>::zeros();
                j.fixed_view_mut::<3, 3>(0, 0).copy_from(&Mat3::identity());
                let rl = self.world_from_body[body].rot * local;
                j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&rl)));
                (layout.body[body], 6, j)
            }
        }
    }

    fn distance_residual(&self, d: &DistanceConstraint) -> f64 {
        ((self.point_world(&d.a) - self.point_world(&d.b)).norm() - d.distance)
            * (self.pixel_sigma / d.sigma)
    }

    fn prior_residual(&self, p: &DirectionPrior) -> f64 {
        let mut r = 0.0;
        for (i, (c, v)) in p.terms.iter().enumerate() {
            let cur = &self.rig_from_cam[*c];
            let o = &p.origin[i];
            let dt = cur.trans - o.trans;
            let dr = rigcal_core::geometry::so3::log(&(cur.rot * o.rot.transpose()));
            r += v.fixed_rows::<3>(0).dot(&dt) + v.fixed_rows::<3>(3).dot(&dr);
        }
        r * (self.pixel_sigma / p.sigma)
    }

    /// Choose what to eliminate. Residuals never couple two rig poses, nor two points
    /// (bar the few in distance constraints), so either set is block-diagonal and can be
    /// Schur-eliminated. Eliminating points leaves rig poses + extrinsics (the paper's
    /// choice, small when frames are few); with many frames it is far cheaper to
    /// eliminate the rig poses and keep points + extrinsics. The smaller system wins.
    fn layout(&self) -> Layout {
        let mut in_distance_pt = vec![false; self.points.len()];
        let mut in_distance_body = vec![false; self.world_from_body.len()];
        for d in &self.distances {
            for p in [d.a, d.b] {
                match p {
                    PointRef::Free(i) => in_distance_pt[i] = true,
                    PointRef::Body { body, .. } => in_distance_body[body] = true,
                }
            }
        }
        let free_rigs = self.rig_fixed.iter().filter(|f| !**f).count();
        let free_bodies = self.body_fixed.iter().filter(|f| !**f).count();
        let dist_dims = 3 * in_distance_pt.iter().filter(|d| **d).count()
            + 6 * in_distance_body.iter().filter(|d| **d).count();
        let dim_keep_rigs = 6 * free_rigs + dist_dims;
        let dim_keep_points = 3 * self.points.len() + 6 * free_bodies;
        let eliminate_rigs = dim_keep_points < dim_keep_rigs;

        let mut n = 0;
        let mut elim_size = Vec::new();
        let mut slot = |fixed: bool, eliminate: bool, size: usize| {
            if fixed {
                Slot::Fixed
            } else if eliminate {
                elim_size.push(size);
                Slot::Elim(elim_size.len() - 1)
            } else {
                n += size;
                Slot::Reduced(n - size)
            }
        };
        let rig: Vec<Slot> = self
            .rig_fixed
            .iter()
            .map(|&f| slot(f, eliminate_rigs, 6))
            .collect();
        let cam: Vec<Slot> = self.cam_fixed.iter().map(|&f| slot(f, false, 6)).collect();
        let point: Vec<Slot> = in_distance_pt
            .iter()
            .map(|&d| slot(false, !eliminate_rigs && !d, 3))
            .collect();
        let body: Vec<Slot> = (0..self.world_from_body.len())
            .map(|b| {
                slot(
                    self.body_fixed[b],
                    !eliminate_rigs && !in_distance_body[b],
                    6,
                )
            })
            .collect();
        let mut layout = Layout {
            rig,
            cam,
            point,
            body,
            n_reduced: n,
            couplings: vec![Vec::new(); elim_size.len()],
            elim_size,
            obs_coupling: Vec::new(),
            elim_order: Vec::new(),
            elim_start: Vec::new(),
            pairs: Vec::new(),
            obs_pairs: Vec::new(),
        };
        let obs_blocks = |o: &Obs| {
            let (pslot, psize) = match o.point {
                PointRef::Free(i) => (layout.point[i], 3),
                PointRef::Body { body, .. } => (layout.body[body], 6),
            };
            [
                (layout.rig[o.rig], 6),
                (layout.cam[o.cam], 6),
                (pslot, psize),
            ]
        };
        // The distinct pairs of reduced blocks. Observations come grouped by frame and
        // camera, so most find their pair where the previous one at the same position
        // did: a one-entry cache per position spares most of the hashing.
        let mut pair_index: OffsetMap<(usize, usize), u32> = Default::default();
        let mut last_pair = [((usize::MAX, usize::MAX), 0u32); 6];
        let mut pairs = Vec::new();
        let mut obs_pairs = Vec::with_capacity(self.observations.len());
        let mut obs_elim = Vec::with_capacity(self.observations.len());
        for o in &self.observations {
            let blocks = obs_blocks(o);
            obs_elim.push(blocks.iter().find_map(|(s, _)| match s {
                Slot::Elim(e) => Some(*e),
                _ => None,
            }));
            let mut own = [u32::MAX; 6];
            for a in 0..3 {
                for b in a..3 {
                    if let ((Slot::Reduced(oa), za), (Slot::Reduced(ob), zb)) =
                        (blocks[a], blocks[b])
                    {
                        let at = PAIR_INDEX[a][b];
                        if last_pair[at].0 != (oa, ob) {
                            let idx = *pair_index.entry((oa, ob)).or_insert_with(|| {
                                pairs.push((oa, za, ob, zb));
                                (pairs.len() - 1) as u32
                            });
                            last_pair[at] = ((oa, ob), idx);
                        }
                        own[at] = last_pair[at].1;
                    }
                }
            }
            obs_pairs.push(own);
        }
        // A counting sort of the observations by eliminated block.
        let ne = layout.elim_size.len();
        let key = |e: &Option<usize>| e.unwrap_or(ne);
        let mut start = vec![0; ne + 2];
        for e in &obs_elim {
            start[key(e) + 1] += 1;
        }
        for k in 0..=ne {
            start[k + 1] += start[k];
        }
        let mut next = start.clone();
        let mut order = vec![0; obs_elim.len()];
        for (oi, e) in obs_elim.iter().enumerate() {
            order[next[key(e)]] = oi;
            next[key(e)] += 1;
        }
        start.pop();
        // Coupling structure, block by eliminated block: for each observation, the index
        // in its eliminated block's coupling list of each of its reduced blocks (rig,
        // camera, point). `seen[offset]`: the last block that listed that reduced block,
        // and where.
        let mut couplings = vec![Vec::new(); ne];
        let mut obs_coupling = vec![[None; 3]; self.observations.len()];
        let mut seen = vec![(usize::MAX, 0); layout.n_reduced];
        for (e, list) in couplings.iter_mut().enumerate() {
            for &oi in &order[start[e]..start[e + 1]] {
                for (k, (s, size)) in obs_blocks(&self.observations[oi]).iter().enumerate() {
                    if let Slot::Reduced(off) = *s {
                        if seen[off].0 != e {
                            list.push((off, *size));
                            seen[off] = (e, list.len() - 1);
                        }
                        obs_coupling[oi][k] = Some(seen[off].1);
                    }
                }
            }
        }
        layout.couplings = couplings;
        layout.obs_coupling = obs_coupling;
        layout.pairs = pairs;
        layout.obs_pairs = obs_pairs;
        layout.elim_order = order;
        layout.elim_start = start;
        layout
    }

    /// Robust cost `½ Σ ρ(|r|²) + ½ Σ r_d²`; infinite if any point falls behind its camera.
    pub fn cost(&self, loss: &Loss) -> f64 {
        // Over the cores in fixed chunks summed in order, so that the value does not
        // depend on the number of threads; each camera's pose in each rig pose once.
        let nc = self.rig_from_cam.len();
        let cam_from_world: Vec<Pose> = (0..self.world_from_rig.len() * nc)
            .map(|i| self.cam_from_world(i / nc, i % nc))
            .collect();
        let chunks: Vec<f64> = self
            .observations
            .par_chunks(COST_CHUNK)
            .map(|chunk| {
                let mut c = 0.0;
                for o in chunk {
                    match self.residual_from(o, &cam_from_world[o.rig * nc + o.cam]) {
                        Some(r) => c += loss.rho(r.norm_squared()),
                        None => return f64::INFINITY,
                    }
                }
                c
            })
            .collect();
        let mut c: f64 = chunks.iter().sum();
        if !c.is_finite() {
            return f64::INFINITY;
        }
        for d in &self.distances {
            c += self.distance_residual(d).powi(2);
        }
        for p in &self.priors {
            c += self.prior_residual(p).powi(2);
        }
        0.5 * c
    }

    #[inline(always)]
    fn observation_normal_portable(
        &self,
        layout: &Layout,
        loss: &Loss,
        obs: &[usize],
        sink: &mut Sink,
    ) -> Option<f64> {
        let zero = (Slot::Fixed, 0, J26::zeros());
        let mut cost = 0.0;
        for &oi in obs {
            let o = &self.observations[oi];
            let (r, j_rig, j_cam, j_x) = self.linearize_obs(o)?;
            let e2 = r.norm_squared();
            cost += 0.5 * loss.rho(e2);
            let w = loss.weight(e2);
            let (pslot, psize, jpb) = self.point_block(&o.point, layout);
            let blocks: Blocks = [
                (layout.rig[o.rig], 6, j_rig),
                (layout.cam[o.cam], 6, j_cam),
                (pslot, psize, j_x * jpb),
                zero,
            ];
            Self::accumulate(
                sink,
                &blocks,
                &r,
                w,
                Some(layout.obs_coupling[oi]),
                Some(&layout.obs_pairs[oi]),
            );
        }
        Some(cost)
    }

    /// The residuals of the distance constraints and direction priors with their
    /// Jacobian blocks, and whether each residual counts in the cost: a prior spanning
    /// more than 4 cameras comes in chunks of 4 blocks with the same residual, counted
    /// once; cross terms between chunks are dropped (a first-order approximation that
    /// only slows convergence along the held direction, never moves the minimum).
    fn constraint_terms(&self, layout: &Layout) -> Vec<(Blocks, Vec2, bool)> {
        let zero = (Slot::Fixed, 0, J26::zeros());
        let mut terms = Vec::with_capacity(self.distances.len() + self.priors.len());
        for d in &self.distances {
            let (xa, xb) = (self.point_world(&d.a), self.point_world(&d.b));
            let diff = xa - xb;
            let len = diff.norm().max(1e-12);
            let s = self.pixel_sigma / d.sigma;
            let r = Vec2::new((len - d.distance) * s, 0.0);
            let u = diff.transpose() * (s / len);
            let (sa, za, ja) = self.point_block(&d.a, layout);
            let (sb, zb, jb) = self.point_block(&d.b, layout);
            let mut j_a = J26::zeros();
            j_a.fixed_view_mut::<1, 6>(0, 0).copy_from(&(u * ja));
            let mut j_b = J26::zeros();
            j_b.fixed_view_mut::<1, 6>(0, 0).copy_from(&(-u * jb));
            terms.push(([(sa, za, j_a), (sb, zb, j_b), zero, zero], r, true));
        }
        for p in &self.priors {
            let r = Vec2::new(self.prior_residual(p), 0.0);
            let s = self.pixel_sigma / p.sigma;
            if p.terms.is_empty() {
                terms.push(([zero; 4], r, true));
            }
            for (k, chunk) in p.terms.chunks(4).enumerate() {
                let mut blocks: Blocks = [zero; 4];
                for (i, (c, v)) in chunk.iter().enumerate() {
                    let mut j = J26::zeros();
                    j.fixed_view_mut::<1, 6>(0, 0)
                        .copy_from(&(v.transpose() * s));
                    blocks[i] = (layout.cam[*c], 6, j);
                }
                terms.push((blocks, r, k == 0));
            }
        }
        terms
    }

    /// The normal equations at this state, written into `spare` when given (equations
    /// of the same layout, reused: see [`Workspace`]).
    fn normal_equations(
        &self,
        layout: &Layout,
        loss: &Loss,
        spare: Option<Normal>,
    ) -> Option<Normal> {
        let parts = (self.observations.len() / MIN_PART_OBSERVATIONS).clamp(1, MAX_PARTS);
        self.normal_equations_in_parts(layout, loss, parts, spare)
    }

    fn normal_equations_in_parts(
        &self,
        layout: &Layout,
        loss: &Loss,
        parts: usize,
        spare: Option<Normal>,
    ) -> Option<Normal> {
        let mut n = Normal::zeroed(layout, spare);
        // The observations in parts over the cores, a part per run of eliminated blocks
        // (their rows are the part's alone), each with its own reduced rows, summed in
        // a fixed order (so the result does not depend on the number of cores). A part
        // costs a copy of the reduced matrix: at most PART_BYTES of them.
        let total = self.observations.len();
        let ne = layout.elim_size.len();
        let nr = layout.n_reduced;
        let np = layout.pairs.len();
        let mut bounds = vec![0];
        for p in 1..parts {
            let e = layout.elim_start[..ne].partition_point(|&s| s < p * total / parts);
            bounds.push(e.max(bounds[p - 1]));
        }
        bounds.push(ne);
        let (mut hee, mut ge, mut her) = (&mut n.hee[..], &mut n.ge[..], &mut n.her[..]);
        let mut jobs = Vec::with_capacity(parts);
        for p in 0..parts {
            let (e0, e1) = (bounds[p], bounds[p + 1]);
            let (h, rest) = std::mem::take(&mut hee).split_at_mut(e1 - e0);
            hee = rest;
            let (g, rest) = std::mem::take(&mut ge).split_at_mut(e1 - e0);
            ge = rest;
            let (c, rest) = std::mem::take(&mut her).split_at_mut(e1 - e0);
            her = rest;
            let end = if p + 1 == parts {
                total
            } else {
                layout.elim_start[e1]
            };
            jobs.push((layout.elim_start[e0]..end, e0, h, g, c));
        }
        type Part = (Vec<Matrix6<f64>>, DVector<f64>, f64);
        let partial: Vec<Option<Part>> = jobs
            .into_par_iter()
            .map(|(range, first_elim, hee, ge, her)| {
                hee.fill(Matrix6::zeros());
                ge.fill(Vector6::zeros());
                for h in her.iter_mut() {
                    h.data.fill(0.0);
                }
                let (mut pair, mut gr) = (vec![Matrix6::zeros(); np], DVector::zeros(nr));
                let mut sink = Sink {
                    extra: None,
                    pair: &mut pair,
                    gr: &mut gr,
                    hee,
                    ge,
                    her,
                    first_elim,
                };
                let obs = &layout.elim_order[range];
                let cost = observation_normal(self, layout, loss, obs, &mut sink)?;
                Some((pair, gr, cost))
            })
            .collect();
        for part in partial {
            let (p, gr, cost) = part?;
            for (a, b) in n.hrr.pairs.iter_mut().zip(&p) {
                *a += b;
            }
            n.gr += gr;
            n.cost += cost;
        }
        for (blocks, r, counted) in self.constraint_terms(layout) {
            if counted {
                n.cost += 0.5 * r.x * r.x;
            }
            Self::accumulate(&mut n.sink(), &blocks, &r, 1.0, None, None);
        }
        n.hrr.finish(layout);
        Some(n)
    }

    #[inline(always)]
    fn accumulate(
        n: &mut Sink,
        blocks: &Blocks,
        r: &Vec2,
        w: f64,
        coupling: Option<[Option<usize>; 3]>,
        pairs: Option<&[u32; 6]>,
    ) {
        for (a, &(sa, za, ja)) in blocks.iter().enumerate() {
            if za == 0 || sa == Slot::Fixed {
                continue;
            }
            // Every product below is `(w·Jₐ)ᵀ J_b`, at the blocks' real sizes.
            let wa = ja * w;
            match sa {
                Slot::Fixed => continue,
                Slot::Reduced(oa) => {
                    for k in 0..za {
                        n.gr[oa + k] += wa[(0, k)] * r.x + wa[(1, k)] * r.y;
                    }
                }
                Slot::Elim(e) => {
                    let ge = &mut n.ge[e - n.first_elim];
                    for k in 0..za {
                        ge[k] += wa[(0, k)] * r.x + wa[(1, k)] * r.y;
                    }
                }
            }
            for (b, &(sb, zb, jb)) in blocks.iter().enumerate().skip(a) {
                if zb == 0 || sb == Slot::Fixed {
                    continue;
                }
                match (sa, sb) {
                    (Slot::Reduced(_), Slot::Reduced(_)) if pairs.is_some() => {
                        if let Some(&idx) = pairs.and_then(|p| p.get(PAIR_INDEX[a][b])) {
                            let h = n.pair[idx as usize].as_mut_slice();
                            add_jtj((h, 6), (&wa, za), (&jb, zb));
                        }
                    }
                    (Slot::Reduced(oa), Slot::Reduced(ob)) => {
                        if let Some(extra) = n.extra.as_deref_mut() {
                            let mut h = Matrix6::zeros();
                            add_jtj((h.as_mut_slice(), 6), (&wa, za), (&jb, zb));
                            extra.push((oa, za, ob, zb, h));
                        }
                    }
                    (Slot::Elim(e), Slot::Elim(f)) if e == f => {
                        let h = n.hee[e - n.first_elim].as_mut_slice();
                        add_jtj((h, 6), (&wa, za), (&jb, zb));
                    }
                    // H_{E,R}, rows of the eliminated block; the coupling index was
                    // precomputed per position of the reduced block in the observation
                    // (rig 0, camera 1, point 2).
                    (Slot::Elim(e), Slot::Reduced(_)) => {
                        if let Some(Some(c)) = coupling.map(|c| c[b]) {
                            let h = n.her[e - n.first_elim].block_mut(c);
                            add_jtj((h, za), (&wa, za), (&jb, zb));
                        }
                    }
                    (Slot::Reduced(_), Slot::Elim(e)) => {
                        if let Some(Some(c)) = coupling.map(|c| c[a]) {
                            let h = n.her[e - n.first_elim].block_mut(c);
                            add_jtj((h, zb), (&jb, zb), (&wa, za));
                        }
                    }
                    _ => {}
                }
            }
        }
    }

    fn apply_step(&self, layout: &Layout, dr: &DVector<f64>, de: &[Vector6<f64>]) -> BundleProblem {
        let mut out = self.clone();
        let get6 = |slot: Slot| -> Option<Vector6<f64>> {
            match slot {
                Slot::Fixed => None,
                Slot::Reduced(o) => Some(Vector6::from_iterator((0..6).map(|k| dr[o + k]))),
                Slot::Elim(e) => Some(de[e]),
            }
        };
        let get3 = |slot: Slot| -> Option<Vec3> {
            match slot {
                Slot::Fixed => None,
                Slot::Reduced(o) => Some(Vec3::new(dr[o], dr[o + 1], dr[o + 2])),
                Slot::Elim(e) => Some(Vec3::new(de[e][0], de[e][1], de[e][2])),
            }
        };
        let perturb = |pose: &mut Pose, d: Vector6<f64>| {
            *pose = pose.perturbed(&Vec3::new(d[0], d[1], d[2]), &Vec3::new(d[3], d[4], d[5]));
        };
        for (i, s) in layout.rig.iter().enumerate() {
            if let Some(d) = get6(*s) {
                perturb(&mut out.world_from_rig[i], d);
            }
        }
        for (i, s) in layout.cam.iter().enumerate() {
            if let Some(d) = get6(*s) {
                perturb(&mut out.rig_from_cam[i], d);
            }
        }
        for (i, s) in layout.body.iter().enumerate() {
            if let Some(d) = get6(*s) {
                perturb(&mut out.world_from_body[i], d);
            }
        }
        for (i, s) in layout.point.iter().enumerate() {
            if let Some(d) = get3(*s) {
                out.points[i] += d;
            }
        }
        out
    }

    /// Levenberg–Marquardt (the driver of [`crate::lm`], Nielsen's damping update, the
    /// points and bodies eliminated by a Schur complement) until convergence.
    pub fn solve(&mut self, opts: &LmOptions) -> BundleSummary {
        let start = Instant::now();
        let layout = self.layout();
        let rules = Rules {
            max_iterations: opts.max_iterations,
            damping: Damping::Nielsen,
            initial_lambda: 1e-4,
            diagonal_floor: 1e-9,
            tries: usize::MAX,
            max_lambda: 1e20,
            function_tolerance: opts.function_tolerance,
            min_step: 0.0,
            gradient_tolerance: opts.gradient_tolerance,
            // Ceres' convergence test (relative decrease < 1e-6): still creeping along a
            // flat direction at the limit is converged, not failed.
            creep_tolerance: 1e-6,
        };
        let workspace = RefCell::new(Workspace::default());
        let mut problem = RigFit {
            layout: &layout,
            loss: opts.loss,
            parameter_tolerance: opts.parameter_tolerance,
            workspace: &workspace,
        };
        let mut summary = BundleSummary {
            iterations: 0,
            initial_cost: f64::NAN,
            final_cost: f64::NAN,
            converged: false,
            termination: String::new(),
            seconds: 0.0,
            reduced_dimension: layout.n_reduced,
        };
        let fit = lm::minimize(&mut problem, self.clone(), &rules);
        match fit {
            Some(fit) if fit.termination != Termination::NotLinearizable => {
                summary.iterations = fit.iterations;
                summary.initial_cost = fit.initial_cost;
                summary.final_cost = fit.cost;
                summary.converged = fit.converged;
                summary.termination = fit.termination.to_string();
                *self = fit.point;
            }
            _ => summary.termination = "a point is behind its camera at the starting point".into(),
        }
        summary.seconds = start.elapsed().as_secs_f64();
        summary
    }

    /// Solve with the robust loss of `opts` annealed from 16× its scale down to 1×.
    /// Far from the solution a tight robust scale treats almost every residual as an
    /// outlier and LM stalls in a bad minimum; a wide scale first avoids that.
    pub fn solve_annealed(&mut self, opts: &LmOptions) -> BundleSummary {
        let mut total: Option<BundleSummary> = None;
        for factor in [16.0, 4.0, 1.0] {
            let loss = match opts.loss {
                Loss::Squared => {
                    if factor > 1.0 {
                        continue;
                    }
                    Loss::Squared
                }
                Loss::Huber { scale } => Loss::Huber {
                    scale: scale * factor,
                },
                Loss::Cauchy { scale } => Loss::Cauchy {
                    scale: scale * factor,
                },
            };
            let s = self.solve(&LmOptions { loss, ..*opts });
            total = Some(match total {
                None => s,
                Some(mut t) => {
                    t.iterations += s.iterations;
                    t.final_cost = s.final_cost;
                    t.converged = s.converged;
                    t.termination = s.termination;
                    t.seconds += s.seconds;
                    t
                }
            });
        }
        total.unwrap_or_else(|| self.solve(opts))
    }

    fn parameter_norm(&self) -> f64 {
        let mut s = 0.0;
        for p in self
            .world_from_rig
            .iter()
            .chain(&self.rig_from_cam)
            .chain(&self.world_from_body)
        {
            s += p.trans.norm_squared();
        }
        for p in &self.points {
            s += p.norm_squared();
        }
        s.sqrt()
    }

    /// Information (inverse covariance, in units of 1/pixel² for unit pixel noise) of
    /// the free extrinsic blocks, every other parameter marginalised out. Rows and
    /// columns follow the free cameras in index order, `[dt, dφ]` each.
    pub fn extrinsic_information(&self, loss: &Loss) -> Option<(Vec<usize>, DMatrix<f64>)> {
        let layout = self.layout();
        let s = self.undamped_reduced(&layout, loss)?;
        let (cams, keep) = self.free_extrinsic_rows(&layout);
        let other: Vec<usize> = (0..layout.n_reduced)
            .filter(|i| !keep.contains(i))
            .collect();
        if other.is_empty() {
            return Some((cams, s.select_rows(&keep).select_columns(&keep)));
        }
        // Jacobi scaling first: rig poses, points and extrinsics differ by orders of
        // magnitude, and unscaled the elimination loses enough precision to produce
        // negative eigenvalues in the marginal information.
        let d: Vec<f64> = (0..s.nrows())
            .map(|i| 1.0 / s[(i, i)].abs().max(1e-300).sqrt())
            .collect();
        let scaled = DMatrix::from_fn(s.nrows(), s.ncols(), |i, j| s[(i, j)] * d[i] * d[j]);
        let skk = scaled.select_rows(&keep).select_columns(&keep);
        let sko = scaled.select_rows(&keep).select_columns(&other);
        let soo = scaled.select_rows(&other).select_columns(&other);
        // faer's blocked Cholesky over the cores (nalgebra's unblocked one took 3 s at
        // 3 000 rig-pose parameters); the pseudo-inverse where it is not positive definite.
        let reduced = match solve_lower_many(&mut soo.clone(), sko.transpose()) {
            Some(x) => &skk - &sko * x,
            None => &skk - &sko * symmetric_pseudo_inverse(&soo, 1e-14) * sko.transpose(),
        };
        let dk: Vec<f64> = keep.iter().map(|&i| d[i]).collect();
        let info = DMatrix::from_fn(keep.len(), keep.len(), |i, j| {
            reduced[(i, j)] / (dk[i] * dk[j])
        });
        Some((cams, (&info + info.transpose()) * 0.5))
    }

    /// How the least-squares solution's free extrinsics move, to first order, when
    /// every observed pixel `o` moves by `shift(k, o)`, for each of `count` shifts:
    /// `(JᵀJ)⁻¹ Jᵀ δz_k` restricted to them, the priors and constraints in as they are.
    /// A systematic error of the measurements, which independent noise does not
    /// describe (a scale of one camera's corners), is propagated with it: its
    /// covariance is `σ² v vᵀ`, however many observations share it. Rows as in
    /// [`Self::extrinsic_information`]; `None` when the state cannot be linearised (a
    /// point behind its camera) or the system is not positive definite even damped.
    ///
    /// Each is the difference of two Gauss–Newton steps, from the observations as they
    /// are and as shifted: the Jacobian does not depend on the observations, so the
    /// difference is exactly the step that the shift alone asks for.
    pub fn extrinsic_sensitivities(
        &self,
        count: usize,
        shift: impl Fn(usize, &Obs) -> Vec2,
    ) -> Option<(Vec<usize>, Vec<DVector<f64>>)> {
        let layout = self.layout();
        let loss = Loss::Squared;
        let base = self.normal_equations(&layout, &loss, None)?;
        let (cams, rows) = self.free_extrinsic_rows(&layout);
        let mut shifted = self.clone();
        let mut out = Vec::with_capacity(count);
        for k in 0..count {
            for (moved, o) in shifted.observations.iter_mut().zip(&self.observations) {
                moved.uv = o.uv + shift(k, o);
            }
            let mut normal = shifted.normal_equations(&layout, &loss, None)?;
            normal.gr -= &base.gr;
            for (g, g0) in normal.ge.iter_mut().zip(&base.ge) {
                *g -= g0;
            }
            let reduced = Reduced {
                layout: &layout,
                normal,
                workspace: None,
            };
            // A block the data leave singular (a point on one ray) has no Cholesky:
            // damping of 10⁻⁹ of the diagonal regularises it and moves the extrinsics'
            // rows by as little.
            let (dr, _) = reduced
                .solve_damped(0.0, 0.0)
                .or_else(|| reduced.solve_damped(1e-9, 1e-9))?;
            out.push(DVector::from_iterator(
                rows.len(),
                rows.iter().map(|&i| dr[i]),
            ));
        }
        Some((cams, out))
    }

    /// The free cameras in index order and their rows in the reduced system.
    fn free_extrinsic_rows(&self, layout: &Layout) -> (Vec<usize>, Vec<usize>) {
        let cams: Vec<usize> = (0..self.rig_from_cam.len())
            .filter(|&c| matches!(layout.cam[c], Slot::Reduced(_)))
            .collect();
        let rows = cams
            .iter()
            .flat_map(|&c| match layout.cam[c] {
                Slot::Reduced(o) => o..o + 6,
                _ => 0..0,
            })
            .collect();
        (cams, rows)
    }

    /// The Schur complement of the eliminated blocks in the undamped normal equations at
    /// this state (pseudo-inverses of the blocks where singular), both triangles.
    fn undamped_reduced(&self, layout: &Layout, loss: &Loss) -> Option<DMatrix<f64>> {
        let n = self.normal_equations(layout, loss, None)?;
        let inv: Vec<Matrix6<f64>> = n
            .hee
            .par_iter()
            .zip(&layout.elim_size)
            .map(|(hee, &size)| pseudo_inverse_block(hee, size))
            .collect();
        // A band is accumulated sparse, over the cores, then written out dense.
        if let Some(p) = sparse_pattern(layout, &n) {
            if let Some(values) = sparse_schur(&p, layout, &n, &inv) {
                return Some(p.to_dense(&values));
            }
        }
        let mut s = n.hrr.to_dense(layout);
        schur_complement(&mut s, None, layout, &n, &inv, &mut Vec::new());
        mirror_lower(&mut s);
        Some(s)
    }
}

/// Add the block `h` (rows: the `za` parameters at `oa`, columns: the `zb` at `ob`) to
/// the symmetric matrix `hrr`, and its transpose unless it is a diagonal block.
fn add_symmetric_block(
    hrr: &mut DMatrix<f64>,
    (oa, za): (usize, usize),
    (ob, zb): (usize, usize),
    h: &Matrix6<f64>,
) {
    for i in 0..za {
        for j in 0..zb {
            hrr[(oa + i, ob + j)] += h[(i, j)];
            if oa != ob {
                hrr[(ob + j, oa + i)] += h[(i, j)];
            }
        }
    }
}

/// `dst += Aᵀ B` for the `za × zb` block of two residual-row Jacobian blocks (2 rows,
/// zero-padded to 6 columns) into column-major `dst` of leading dimension `ld`: only the
/// blocks' real sizes are computed, a point's being 3 wide. Sizes are 3 or 6; the match
/// gives the compiler fixed loop bounds.
#[inline(always)]
fn add_jtj((dst, ld): (&mut [f64], usize), (a, za): (&J26, usize), (b, zb): (&J26, usize)) {
    #[inline(always)]
    fn fixed<const ZA: usize, const ZB: usize>(d: &mut [f64], ld: usize, a: &J26, b: &J26) {
        // A Jacobian's (r, i) is at 2i + r; the rows of `a` copied out contiguous so that
        // the inner loop vectorises.
        let (a, b) = (a.as_slice(), b.as_slice());
        let a0: [f64; 6] = std::array::from_fn(|i| a[2 * i]);
        let a1: [f64; 6] = std::array::from_fn(|i| a[2 * i + 1]);
        for j in 0..ZB {
            let (b0, b1) = (b[2 * j], b[2 * j + 1]);
            let col = &mut d[ld * j..ld * j + ZA];
            for i in 0..ZA {
                col[i] += a0[i] * b0 + a1[i] * b1;
            }
        }
    }
    match (za, zb) {
        (6, 6) => fixed::<6, 6>(dst, ld, a, b),
        (6, 3) => fixed::<6, 3>(dst, ld, a, b),
        (3, 6) => fixed::<3, 6>(dst, ld, a, b),
        (3, 3) => fixed::<3, 3>(dst, ld, a, b),
        _ => {
            let (a, b) = (a.as_slice(), b.as_slice());
            for j in 0..zb {
                for i in 0..za {
                    dst[ld * j + i] += a[2 * i] * b[2 * j] + a[2 * i + 1] * b[2 * j + 1];
                }
            }
        }
    }
}

/// Copy the lower triangle of a square matrix onto its upper one.
fn mirror_lower(s: &mut DMatrix<f64>) {
    for j in 0..s.ncols() {
        for i in 0..j {
            s[(i, j)] = s[(j, i)];
        }
    }
}

/// Solve `S x = b` for a symmetric positive definite `S` of which only the lower
/// triangle is read, factored in place (its lower triangle is overwritten): faer's
/// blocked Cholesky over the cores (nalgebra's is unblocked, 30 % of the bundle's
/// instructions at K = 200). `None` when `S` is not positive definite.
fn solve_lower(s: &mut DMatrix<f64>, b: DVector<f64>) -> Option<DVector<f64>> {
    let n = b.nrows();
    let x = solve_lower_many(s, DMatrix::from_column_slice(n, 1, b.as_slice()))?;
    Some(DVector::from_column_slice(x.as_slice()))
}

/// [`solve_lower`] for several right-hand sides (the columns of `b`).
fn solve_lower_many(s: &mut DMatrix<f64>, b: DMatrix<f64>) -> Option<DMatrix<f64>> {
    use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
    use faer::linalg::cholesky::llt;
    use faer::reborrow::{Reborrow, ReborrowMut};
    let n = s.nrows();
    let par = faer::get_global_parallelism();
    let mut l = faer::MatMut::from_column_major_slice_mut(s.as_mut_slice(), n, n);
    let mut mem = MemBuffer::new(llt::factor::cholesky_in_place_scratch::<f64>(
        n,
        par,
        Default::default(),
    ));
    llt::factor::cholesky_in_place(
        l.rb_mut(),
        Default::default(),
        par,
        MemStack::new(&mut mem),
        Default::default(),
    )
    .ok()?;
    let mut x = b;
    let k = x.ncols();
    let rhs = faer::MatMut::from_column_major_slice_mut(x.as_mut_slice(), n, k);
    llt::solve::solve_in_place(
        l.rb(),
        rhs,
        par,
        MemStack::new(&mut MemBuffer::new(StackReq::EMPTY)),
    );
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// A step of the rig bundle: the reduced blocks, then each eliminated block.
type RigStep = (DVector<f64>, Vec<Vector6<f64>>);

/// The rig bundle as a problem of the LM driver: a point is a whole bundle state.
struct RigFit<'a> {
    layout: &'a Layout,
    loss: Loss,
    parameter_tolerance: f64,
    workspace: &'a RefCell<Workspace>,
}

/// The large buffers of one rig bundle solve, kept across its linearisations and damped
/// solves: allocated afresh each time (K = 200: 35 MB of coupling blocks per
/// linearisation, 12 MB per reduced matrix) they cost more in page faults than the
/// arithmetic that fills them.
#[derive(Default)]
struct Workspace {
    /// Normal equations of linearisations the driver has let go of.
    normals: Vec<Normal>,
    /// The reduced matrix, factored in place.
    reduced: Option<DMatrix<f64>>,
    /// The dense rows of the Schur complement ([`DenseRows`]), all zero between uses.
    rows: Vec<f64>,
    /// The reduced system's pattern when it is factored sparse ([`sparse_pattern`]),
    /// decided at the first damped solve (`Some(None)`: dense).
    sparse: Option<Option<SparsePattern>>,
}

impl<'a> LeastSquares for RigFit<'a> {
    type Point = BundleProblem;
    type Normal = Reduced<'a>;

    fn linearize(&mut self, x: &BundleProblem) -> Option<Reduced<'a>> {
        let spare = self.workspace.borrow_mut().normals.pop();
        let normal = x.normal_equations(self.layout, &self.loss, spare)?;
        Some(Reduced {
            layout: self.layout,
            normal,
            workspace: Some(self.workspace),
        })
    }

    fn cost(&mut self, x: &BundleProblem) -> Option<f64> {
        Some(x.cost(&self.loss))
    }

    fn retract(&self, x: &BundleProblem, step: &RigStep) -> BundleProblem {
        x.apply_step(self.layout, &step.0, &step.1)
    }

    /// A point behind a camera has an infinite cost, and the normal equations sum the
    /// same robust cost (in another order).
    fn linearizable_where_finite(&self) -> bool {
        true
    }

    /// A step small against the parameters (relative, as Ceres' parameter tolerance).
    fn settled(&self, x: &BundleProblem, step: &RigStep) -> bool {
        Reduced::step_norm(step) < self.parameter_tolerance * (1.0 + x.parameter_norm())
    }
}

/// The rig bundle's normal equations, solved by eliminating the points and rigid
/// bodies (Schur complement) and factoring the reduced system of the rig and camera
/// poses.
struct Reduced<'a> {
    layout: &'a Layout,
    normal: Normal,
    /// Where the buffers go back when these equations are done with.
    workspace: Option<&'a RefCell<Workspace>>,
}

impl Drop for Reduced<'_> {
    fn drop(&mut self) {
        if let Some(w) = self.workspace {
            let n = std::mem::replace(&mut self.normal, Normal::zeros(&Layout::EMPTY));
            w.borrow_mut().normals.push(n);
        }
    }
}

impl NormalEquations for Reduced<'_> {
    type Step = RigStep;

    fn cost(&self) -> Option<f64> {
        Some(self.normal.cost)
    }

    fn gradient_max(&self) -> f64 {
        let n = &self.normal;
        n.gr.amax()
            .max(n.ge.iter().map(|g| g.amax()).fold(0.0, f64::max))
    }

    /// The step of the reduced blocks from the Schur complement, then the eliminated
    /// blocks' by back-substitution.
    fn solve_damped(&self, lambda: f64, floor: f64) -> Option<RigStep> {
        let (layout, n) = (self.layout, &self.normal);
        let nr = layout.n_reduced;
        let mut own = Workspace::default();
        let mut shared = self.workspace.map(|w| w.borrow_mut());
        let work = shared.as_deref_mut().unwrap_or(&mut own);
        let einv = damped_inverses(layout, n, lambda, floor)?;
        let pattern = work.sparse.get_or_insert_with(|| sparse_pattern(layout, n));
        if let Some(dr) = pattern
            .as_ref()
            .and_then(|p| sparse_reduced_step(p, layout, n, &einv, lambda, floor))
        {
            let dr = dr?;
            let de = back_substitute(layout, n, &einv, &dr);
            return Some((dr, de));
        }
        let mut s = match work.reduced.take() {
            Some(mut s) if s.nrows() == nr => {
                n.hrr.write_into(&mut s, layout);
                s
            }
            _ => n.hrr.to_dense(layout),
        };
        for i in 0..nr {
            s[(i, i)] += lambda * n.hrr.diag[i].max(floor);
        }
        let mut rhs = -n.gr.clone();
        schur_complement(&mut s, Some(&mut rhs), layout, n, &einv, &mut work.rows);
        let dr = if nr > 0 {
            solve_lower(&mut s, rhs)
        } else {
            Some(DVector::zeros(0))
        };
        work.reduced = Some(s);
        let dr = dr?;
        let de = back_substitute(layout, n, &einv, &dr);
        Some((dr, de))
    }

    fn predicted_decrease(&self, (dr, de): &RigStep, lambda: f64, floor: f64) -> f64 {
        let n = &self.normal;
        let mut pred = 0.0;
        for i in 0..self.layout.n_reduced {
            pred += dr[i] * (lambda * n.hrr.diag[i].max(floor) * dr[i] - n.gr[i]);
        }
        for (e, d) in de.iter().enumerate() {
            for k in 0..self.layout.elim_size[e] {
                pred += d[k] * (lambda * n.hee[e][(k, k)].max(floor) * d[k] - n.ge[e][k]);
            }
        }
        0.5 * pred
    }

    fn step_norm((dr, de): &RigStep) -> f64 {
        (dr.norm_squared() + de.iter().map(|d| d.norm_squared()).sum::<f64>()).sqrt()
    }
}

/// The eliminated blocks' damped inverses; `None` when one is not positive definite.
fn damped_inverses(
    layout: &Layout,
    n: &Normal,
    lambda: f64,
    floor: f64,
) -> Option<Vec<Matrix6<f64>>> {
    n.hee
        .par_iter()
        .zip(&layout.elim_size)
        .map(|(hee, &size)| {
            let mut h = *hee;
            for i in 0..size {
                h[(i, i)] += lambda * hee[(i, i)].max(floor);
            }
            invert_block(&h, size)
        })
        .collect()
}

/// The eliminated blocks' steps from the reduced one: `E⁻¹ (−g_e − H_eR dr)`.
fn back_substitute(
    layout: &Layout,
    n: &Normal,
    einv: &[Matrix6<f64>],
    dr: &DVector<f64>,
) -> Vec<Vector6<f64>> {
    let mut de = Vec::with_capacity(n.hee.len());
    for (e, inv) in einv.iter().enumerate() {
        let mut b = -n.ge[e];
        let ze = layout.elim_size[e];
        for (h, (oa, za)) in n.her[e].iter(&layout.couplings[e]) {
            for k in 0..ze {
                let v: f64 = (0..za).map(|j| h[j * ze + k] * dr[oa + j]).sum();
                b[k] -= v;
            }
        }
        de.push(inv * b);
    }
    de
}

/// Below this reduced dimension the dense Cholesky takes a few milliseconds: no
/// pattern is worth building.
const SPARSE_MIN_REDUCED: usize = 1000;
/// The sparse factorisation is taken when its factor holds at most this share of the
/// dense lower triangle's entries (`rigcal bench speed --window`: sparse 1.25 s against
/// dense 1.56 s at a share of 0.34, dense 1.21 s against 1.44 s at 0.44).
const SPARSE_MAX_FILL: f64 = 0.35;

/// The reduced system's block pattern when it is sparse enough to factor sparse: every
/// pair of reduced blocks an observation, a constraint or a shared eliminated block
/// couples. `None` (dense) when the system is small, when some eliminated block couples
/// half of it or more (the pattern would be dense; not worth enumerating its pairs), or
/// when the factor would fill in.
fn sparse_pattern(layout: &Layout, n: &Normal) -> Option<SparsePattern> {
    sparse_pattern_within(layout, n, SPARSE_MIN_REDUCED, SPARSE_MAX_FILL, 2)
}

fn sparse_pattern_within(
    layout: &Layout,
    n: &Normal,
    min_reduced: usize,
    max_fill: f64,
    dense_row_share: usize,
) -> Option<SparsePattern> {
    let nr = layout.n_reduced;
    if nr < min_reduced {
        return None;
    }
    let coupled = |c: &Vec<(usize, usize)>| c.iter().map(|c| c.1).sum::<usize>();
    if layout
        .couplings
        .iter()
        .any(|c| coupled(c) * dense_row_share >= nr)
    {
        return None;
    }
    let sized = |slots: &[Slot], z: usize| {
        slots
            .iter()
            .filter_map(move |s| match s {
                Slot::Reduced(o) => Some((*o, z)),
                _ => None,
            })
            .collect::<Vec<_>>()
    };
    let mut blocks = sized(&layout.rig, 6);
    blocks.extend(sized(&layout.cam, 6));
    blocks.extend(sized(&layout.point, 3));
    blocks.extend(sized(&layout.body, 6));
    blocks.sort_unstable();
    blocks.dedup();
    let direct = n.hrr.blocks(layout).map(|((oa, _), (ob, _), _)| (oa, ob));
    let shared = layout.couplings.iter().flat_map(|c| {
        c.iter()
            .enumerate()
            .flat_map(move |(i, a)| c[i + 1..].iter().map(move |b| (a.0, b.0)))
    });
    let p = SparsePattern::new(nr, &blocks, direct.chain(shared))?;
    let dense = (nr * (nr + 1) / 2) as f64;
    (p.factor_nnz() as f64 <= max_fill * dense).then_some(p)
}

/// The damped reduced step from the sparse Schur complement: `None` when the pattern
/// does not hold a block of these equations (then the dense path runs), `Some(None)`
/// when the system is not positive definite.
fn sparse_reduced_step(
    p: &SparsePattern,
    layout: &Layout,
    n: &Normal,
    einv: &[Matrix6<f64>],
    lambda: f64,
    floor: f64,
) -> Option<Option<DVector<f64>>> {
    let mut values = sparse_schur(p, layout, n, einv)?;
    for i in 0..layout.n_reduced {
        p.add_diagonal(&mut values, i, lambda * n.hrr.diag[i].max(floor));
    }
    let mut rhs = -n.gr.clone();
    for (e, inv) in einv.iter().enumerate() {
        let (couplings, her, ze) = (&layout.couplings[e], &n.her[e], layout.elim_size[e]);
        schur_rhs(&mut rhs, couplings, her, inv, &n.ge[e], ze);
    }
    Some(p.solve(&values, rhs))
}

/// The Schur complement `H_RR − Σ H_Re E⁻¹ H_eR` (inverses `einv`) in the pattern's
/// values; `None` when the pattern does not hold a block of these equations. The
/// eliminated blocks go in parts over the cores, each into its own copy of the values
/// (a few MB), summed in a fixed order: the same result on any number of cores.
fn sparse_schur(
    p: &SparsePattern,
    layout: &Layout,
    n: &Normal,
    einv: &[Matrix6<f64>],
) -> Option<Vec<f64>> {
    let mut values = p.zeros();
    for (a, b, h) in n.hrr.blocks(layout) {
        if !p.add(&mut values, a, b, |i, j| h[(i, j)]) {
            return None;
        }
    }
    let ne = einv.len();
    let parts = (ne / 256).clamp(1, MAX_PARTS);
    let updates: Vec<Option<Vec<f64>>> = (0..parts)
        .into_par_iter()
        .map(|k| {
            let mut part = p.zeros();
            for e in k * ne / parts..(k + 1) * ne / parts {
                let (couplings, her, ze) = (&layout.couplings[e], &n.her[e], layout.elim_size[e]);
                let mut held = true;
                pairwise_updates(couplings, her, &einv[e], ze, |a, b, v| {
                    held &= p.add(&mut part, a, b, |i, j| -v[(i, j)]);
                });
                if !held {
                    return None;
                }
            }
            Some(part)
        })
        .collect();
    for part in updates {
        for (v, u) in values.iter_mut().zip(part?) {
            *v += u;
        }
    }
    Some(values)
}

/// Rows `B` of pending rank-k updates `S −= BᵀB`, applied by one matrix product per
/// batch: the cache-friendly way to eliminate blocks coupled with most of `S`. Stored
/// transposed (a row of `B` is a contiguous column of `buf`), so that filling a row
/// writes one run of memory and rows fill in parallel.
struct DenseRows<'b> {
    /// `n × BATCH`, column-major; zero beyond the pending rows.
    buf: &'b mut [f64],
    n: usize,
    count: usize,
}

impl<'b> DenseRows<'b> {
    const BATCH: usize = 512;

    /// Rows of length `n` in `buf`, grown (with zeros) to hold a batch.
    fn new(n: usize, buf: &'b mut Vec<f64>) -> Self {
        if buf.len() < n * Self::BATCH {
            buf.resize(n * Self::BATCH, 0.0);
        }
        Self {
            buf: &mut buf[..n * Self::BATCH],
            n,
            count: 0,
        }
    }

    /// Apply the pending updates to the lower triangle of `s` (the upper one is left
    /// as it was: [`solve_lower`] reads the lower one, [`mirror_lower`] completes it),
    /// over the cores: a symmetric rank update costs half a product, and at K = 200
    /// rig poses it was 44 % of the bundle's instructions.
    fn flush(&mut self, s: &mut DMatrix<f64>) {
        if self.count > 0 {
            let n = self.n;
            let bt =
                faer::MatRef::from_column_major_slice(&self.buf[..n * self.count], n, self.count);
            let dst = faer::MatMut::from_column_major_slice_mut(s.as_mut_slice(), n, n);
            triangular::matmul(
                dst,
                BlockStructure::TriangularLower,
                Accum::Add,
                bt,
                BlockStructure::Rectangular,
                bt.transpose(),
                BlockStructure::Rectangular,
                -1.0,
                faer::get_global_parallelism(),
            );
            self.buf[..n * self.count].fill(0.0);
            self.count = 0;
        }
    }
}

/// The Schur complement of every eliminated block `e` (inverse `inv[e]`) on the
/// reduced matrix `s` (lower triangle) and, given, the right-hand side:
/// `S_ab −= H_aᵀ E⁻¹ H_b` for every pair of its couplings, `rhs_a += H_aᵀ E⁻¹ g`.
///
/// A block coupled with a large part of `S` (a point seen from every rig pose) becomes
/// `ze` dense rows `B = Mᵀ H` with `M Mᵀ = E⁻¹`, batched into matrix products and
/// filled over the cores; a block with few couplings (a point seen in a few frames) is
/// applied pair by pair.
fn schur_complement(
    s: &mut DMatrix<f64>,
    mut rhs: Option<&mut DVector<f64>>,
    layout: &Layout,
    n: &Normal,
    inv: &[Matrix6<f64>],
    rows_buf: &mut Vec<f64>,
) {
    let nr = s.nrows();
    let mut dense_blocks = Vec::new();
    for (e, inv) in inv.iter().enumerate() {
        let (couplings, her, ze) = (&layout.couplings[e], &n.her[e], layout.elim_size[e]);
        if let Some(rhs) = rhs.as_deref_mut() {
            schur_rhs(rhs, couplings, her, inv, &n.ge[e], ze);
        }
        let coupled: usize = couplings.iter().map(|c| c.1).sum();
        if coupled == 0 {
            // Nothing in the reduced system depends on this block (e.g. a scene whose
            // only free parameters are eliminated ones): no update, and no dense row.
        } else if coupled * 8 >= nr {
            dense_blocks.push(e);
        } else {
            eliminate_pairwise(s, couplings, her, inv, ze);
        }
    }
    if dense_blocks.is_empty() {
        return;
    }
    // M with M Mᵀ = E⁻¹ from the eigen-decomposition (E⁻¹ may be a pseudo-inverse):
    // one dense row per positive eigenvalue.
    let rows: Vec<(usize, Vector6<f64>)> = dense_blocks
        .par_iter()
        .map(|&e| {
            let ze = layout.elim_size[e];
            let sub = DMatrix::from_fn(ze, ze, |i, j| inv[e][(i, j)]);
            let eig = rigcal_core::linalg::symmetric_eigen(&sub);
            (0..ze)
                .filter(|&r| eig.eigenvalues[r] > 0.0)
                .map(|r| {
                    let l = eig.eigenvalues[r].sqrt();
                    let mut m = Vector6::zeros();
                    for k in 0..ze {
                        m[k] = eig.eigenvectors[(k, r)] * l;
                    }
                    (e, m)
                })
                .collect::<Vec<_>>()
        })
        .flatten()
        .collect();
    let mut dense = DenseRows::new(nr, rows_buf);
    for batch in rows.chunks(DenseRows::BATCH) {
        dense
            .buf
            .par_chunks_mut(nr)
            .zip(batch)
            .for_each(|(row, (e, m))| {
                let ze = layout.elim_size[*e];
                for (h, (oa, za)) in n.her[*e].iter(&layout.couplings[*e]) {
                    for j in 0..za {
                        row[oa + j] = (0..ze).map(|k| m[k] * h[j * ze + k]).sum::<f64>();
                    }
                }
            });
        dense.count = batch.len();
        dense.flush(s);
    }
}

/// `rhs_a += H_aᵀ E⁻¹ g` for the couplings `a` of one eliminated block.
fn schur_rhs(
    rhs: &mut DVector<f64>,
    couplings: &[(usize, usize)],
    her: &Couplings,
    inv: &Matrix6<f64>,
    g: &Vector6<f64>,
    ze: usize,
) {
    let ig = inv * g;
    for (h, (oa, za)) in her.iter(couplings) {
        for i in 0..za {
            rhs[oa + i] += (0..ze).map(|k| h[i * ze + k] * ig[k]).sum::<f64>();
        }
    }
}

/// The Schur update of one eliminated block of size `ze` with inverse `inv`, pair by
/// pair of its couplings (both triangles).
fn eliminate_pairwise(
    s: &mut DMatrix<f64>,
    couplings: &[(usize, usize)],
    her: &Couplings,
    inv: &Matrix6<f64>,
    ze: usize,
) {
    let nrows = s.nrows();
    let data = s.as_mut_slice();
    pairwise_updates(couplings, her, inv, ze, |(oa, za), (ob, zb), v| {
        for i in 0..za {
            for j in 0..zb {
                data[(oa + i) + (ob + j) * nrows] -= v[(i, j)];
                if oa != ob {
                    data[(ob + j) + (oa + i) * nrows] -= v[(i, j)];
                }
            }
        }
    });
}

/// `H_aᵀ E⁻¹ H_b` (`za × zb`) for every pair `a ≤ b` of one eliminated block's
/// couplings, handed to `f` with the blocks' `(offset, size)`.
fn pairwise_updates(
    couplings: &[(usize, usize)],
    her: &Couplings,
    inv: &Matrix6<f64>,
    ze: usize,
    mut f: impl FnMut((usize, usize), (usize, usize), &Matrix6<f64>),
) {
    // at_a = H_aᵀ E⁻¹ (za × ze), once per coupling.
    let ats: Vec<Matrix6<f64>> = her
        .iter(couplings)
        .map(|(h, (_, za))| {
            let mut at = Matrix6::zeros();
            for i in 0..za {
                for k in 0..ze {
                    let mut acc = 0.0;
                    for m in 0..ze {
                        acc += h[i * ze + m] * inv[(m, k)];
                    }
                    at[(i, k)] = acc;
                }
            }
            at
        })
        .collect();
    for (a, (at, &(oa, za))) in ats.iter().zip(couplings).enumerate() {
        for (hb, (ob, zb)) in her.iter(couplings).skip(a) {
            let mut v = Matrix6::zeros();
            for i in 0..za {
                for j in 0..zb {
                    let mut acc = 0.0;
                    for k in 0..ze {
                        acc += at[(i, k)] * hb[j * ze + k];
                    }
                    v[(i, j)] = acc;
                }
            }
            f((oa, za), (ob, zb), &v);
        }
    }
}

fn invert_block(h: &Matrix6<f64>, size: usize) -> Option<Matrix6<f64>> {
    let mut out = Matrix6::zeros();
    if size == 3 {
        let inv = h
            .fixed_view::<3, 3>(0, 0)
            .into_owned()
            .cholesky()?
            .inverse();
        out.fixed_view_mut::<3, 3>(0, 0).copy_from(&inv);
    } else {
        out = h.cholesky()?.inverse();
    }
    Some(out)
}

fn pseudo_inverse_block(h: &Matrix6<f64>, size: usize) -> Matrix6<f64> {
    let m = DMatrix::from_fn(size, size, |i, j| h[(i, j)]);
    let inv = symmetric_pseudo_inverse(&m, 1e-12);
    let mut out = Matrix6::zeros();
    for i in 0..size {
        for j in 0..size {
            out[(i, j)] = inv[(i, j)];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigcal_core::geometry::so3;

    fn small_problem() -> BundleProblem {
        problem_with_rigs(4)
    }

    fn problem_with_rigs(n_rigs: usize) -> BundleProblem {
        let cam = Camera::pinhole(700.0, 700.0, 320.0, 240.0, 640, 480);
        let rig_from_cam = vec![
            Pose::identity(),
            Pose::from_rotvec(Vec3::new(0.1, 3.0, 0.05), Vec3::new(0.1, 0.0, -1.5)),
        ];
        // General 3D motion: rotation axes differ between poses (else the extrinsic is singular).
        let axes = [
            Vec3::zeros(),
            Vec3::new(0.2, 0.0, 0.05),
            Vec3::new(0.0, 0.25, -0.1),
            Vec3::new(-0.1, 0.1, 0.3),
        ];
        let world_from_rig: Vec<Pose> = (0..n_rigs)
            .map(|k| {
                let w = axes[k % 4] * (1.0 + 0.1 * (k / 4) as f64);
                Pose::from_rotvec(
                    w,
                    Vec3::new(0.1 * (k % 5) as f64, 0.05, 0.02 * (k % 7) as f64),
                )
            })
            .collect();
        let world_from_body = vec![Pose::from_rotvec(
            Vec3::new(0.2, 0.1, 0.0),
            Vec3::new(0.0, 0.0, 2.5),
        )];
        let mut body_observations = Vec::new();
        for i in 0..4 {
            for k in 0..n_rigs {
                body_observations.push(Obs {
                    rig: k,
                    cam: 0,
                    point: PointRef::Body {
                        body: 0,
                        local: Vec3::new(0.1 * i as f64, 0.05 * (i % 2) as f64, 0.0),
                    },
                    uv: Vec2::zeros(),
                });
            }
        }
        let mut p = BundleProblem {
            cameras: vec![cam.clone(), cam],
            rig_from_cam,
            cam_fixed: vec![true, false],
            world_from_rig,
            rig_fixed: (0..n_rigs).map(|k| k == 0).collect(),
            points: vec![],
            world_from_body,
            body_fixed: vec![false],
            observations: vec![],
            distances: vec![DistanceConstraint {
                a: PointRef::Free(0),
                b: PointRef::Free(3),
                distance: 0.0,
                sigma: 1e-3,
            }],
            priors: vec![],
            pixel_sigma: 1.0,
        };
        for c in 0..2 {
            let world_from_cam = p.world_from_rig[0] * p.rig_from_cam[c];
            for i in 0..8 {
                let p_cam = Vec3::new(
                    -0.4 + 0.11 * i as f64,
                    0.3 * ((i % 3) as f64 - 1.0),
                    2.0 + 0.1 * (i % 4) as f64,
                );
                p.add_point_seen_from_every_rig(world_from_cam.apply(&p_cam), c);
            }
        }
        p.observations.extend(body_observations);
        assert_eq!(p.observe_exactly(), 0, "every point in front of its camera");
        p.distances[0].distance = (p.points[0] - p.points[3]).norm();
        p
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let p = small_problem();
        let o = p.observations[5];
        let (_, j_rig, j_cam, j_x) = p.linearize_obs(&o).unwrap();
        let h = 1e-7;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let pert = |pose: &Pose, s: f64| {
                pose.perturbed(
                    &(Vec3::new(d[0], d[1], d[2]) * s),
                    &(Vec3::new(d[3], d[4], d[5]) * s),
                )
            };
            let mut pp = p.clone();
            pp.world_from_rig[o.rig] = pert(&p.world_from_rig[o.rig], 1.0);
            let mut pm = p.clone();
            pm.world_from_rig[o.rig] = pert(&p.world_from_rig[o.rig], -1.0);
            let fd = (pp.residual(&o).unwrap() - pm.residual(&o).unwrap()) / (2.0 * h);
            assert!(
                (fd - j_rig.column(k)).norm() < 1e-4 * (1.0 + fd.norm()),
                "rig {k}: {fd:?} vs {:?}",
                j_rig.column(k)
            );
            let mut pp = p.clone();
            pp.rig_from_cam[o.cam] = pert(&p.rig_from_cam[o.cam], 1.0);
            let mut pm = p.clone();
            pm.rig_from_cam[o.cam] = pert(&p.rig_from_cam[o.cam], -1.0);
            let fd = (pp.residual(&o).unwrap() - pm.residual(&o).unwrap()) / (2.0 * h);
            assert!(
                (fd - j_cam.column(k)).norm() < 1e-4 * (1.0 + fd.norm()),
                "cam {k}"
            );
        }
        let PointRef::Free(i) = o.point else { panic!() };
        for k in 0..3 {
            let mut pp = p.clone();
            pp.points[i][k] += h;
            let mut pm = p.clone();
            pm.points[i][k] -= h;
            let fd = (pp.residual(&o).unwrap() - pm.residual(&o).unwrap()) / (2.0 * h);
            assert!(
                (fd - j_x.column(k)).norm() < 1e-4 * (1.0 + fd.norm()),
                "point {k}"
            );
        }
        // Body Jacobian through point_block.
        let ob = *p.observations.last().unwrap();
        let layout = p.layout();
        let (_, _, _, jx) = p.linearize_obs(&ob).unwrap();
        let (_, _, jb) = p.point_block(&ob.point, &layout);
        let j = jx * jb;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let mut pp = p.clone();
            pp.world_from_body[0] = p.world_from_body[0]
                .perturbed(&Vec3::new(d[0], d[1], d[2]), &Vec3::new(d[3], d[4], d[5]));
            let mut pm = p.clone();
            pm.world_from_body[0] = p.world_from_body[0]
                .perturbed(&-Vec3::new(d[0], d[1], d[2]), &-Vec3::new(d[3], d[4], d[5]));
            let fd = (pp.residual(&ob).unwrap() - pm.residual(&ob).unwrap()) / (2.0 * h);
            assert!(
                (fd - j.column(k)).norm() < 1e-4 * (1.0 + fd.norm()),
                "body {k}"
            );
        }
    }

    #[test]
    fn recovers_truth_from_perturbed_start() {
        for n_rigs in [4, 40] {
            recovers_truth(n_rigs);
        }
    }

    fn recovers_truth(n_rigs: usize) {
        let truth = problem_with_rigs(n_rigs);
        // 4 rig poses stay in the reduced system; with 40 the rig poses are eliminated.
        assert_eq!(
            truth.layout().elim_size.iter().all(|s| *s == 6),
            n_rigs == 40
        );
        let mut p = truth.clone();
        p.rig_from_cam[1] = p.rig_from_cam[1].perturbed(
            &Vec3::new(0.02, -0.03, 0.01),
            &Vec3::new(0.01, -0.02, 0.015),
        );
        for k in 1..n_rigs {
            p.world_from_rig[k] = p.world_from_rig[k]
                .perturbed(&Vec3::new(0.01, 0.0, -0.01), &Vec3::new(0.0, 0.01, 0.0));
        }
        for x in p.points.iter_mut() {
            *x += Vec3::new(0.01, -0.01, 0.02);
        }
        p.world_from_body[0] =
            p.world_from_body[0].perturbed(&Vec3::new(0.01, 0.01, 0.0), &Vec3::new(0.02, 0.0, 0.0));
        let s = p.solve(&LmOptions::default());
        assert!(s.converged, "{s:?}");
        assert!(s.final_cost < 1e-16, "{s:?}");
        let (dr, dt) = p.rig_from_cam[1].distance(&truth.rig_from_cam[1]);
        assert!(dr < 1e-9 && dt < 1e-9, "{dr} {dt}");
        let (cams, info) = p.extrinsic_information(&Loss::Squared).unwrap();
        assert_eq!(cams, vec![1]);
        assert_eq!(info.nrows(), 6);
    }
    /// The first-order sensitivity of the extrinsic to a scale of one camera's pixels
    /// about its principal point, against solving again with the pixels scaled: exact
    /// without residuals; with 0.3 px of them (on 8 points a camera) the Gauss–Newton
    /// Hessian it rests on, as the covariance does, is a few percent off the true one.
    #[test]
    fn extrinsic_sensitivity_is_the_change_of_the_solution() {
        for (noise, tolerance) in [(0.0, 1e-6), (0.3, 0.06)] {
            for n_rigs in [4, 40] {
                let mut p = problem_with_rigs(n_rigs);
                for (i, o) in p.observations.iter_mut().enumerate() {
                    let k = i as f64;
                    o.uv += Vec2::new((k * 1.7).sin(), (k * 2.3).cos()) * noise;
                }
                p.solve(&LmOptions::default());
                for cam in 0..2 {
                    let (cx, cy) = (p.cameras[cam].cx, p.cameras[cam].cy);
                    let about = move |o: &Obs| {
                        if o.cam == cam {
                            o.uv - Vec2::new(cx, cy)
                        } else {
                            Vec2::zeros()
                        }
                    };
                    let (cams, v) = p.extrinsic_sensitivities(1, |_, o| about(o)).unwrap();
                    assert_eq!(cams, vec![1]);
                    let v = &v[0];
                    // Central differences: the second-order part of the change cancels.
                    let eps = 1e-4;
                    let solved_with = |scale: f64| {
                        let mut q = p.clone();
                        for o in &mut q.observations {
                            o.uv += about(o) * scale;
                        }
                        q.solve(&LmOptions::default());
                        q.rig_from_cam[1]
                    };
                    let (plus, minus) = (solved_with(eps), solved_with(-eps));
                    let fd = Vector6::from_iterator(
                        (plus.trans - minus.trans)
                            .iter()
                            .chain(so3::log(&(plus.rot * minus.rot.transpose())).iter())
                            .map(|x| x / (2.0 * eps)),
                    );
                    let off = (fd - Vector6::from_iterator(v.iter().copied())).norm();
                    assert!(
                        off < tolerance * fd.norm(),
                        "noise {noise}, {n_rigs} rigs, camera {cam}: {fd:?} against {v:?}"
                    );
                }
            }
        }
    }

    /// The full normal matrix and gradient assembled from the blocks (reduced, then
    /// eliminated in order).
    fn assemble(layout: &Layout, n: &Normal) -> (DMatrix<f64>, DVector<f64>) {
        let nr = layout.n_reduced;
        let total = nr + layout.elim_size.iter().sum::<usize>();
        let mut h = DMatrix::zeros(total, total);
        let mut g = DVector::zeros(total);
        h.view_mut((0, 0), (nr, nr))
            .copy_from(&n.hrr.to_dense(layout));
        g.rows_mut(0, nr).copy_from(&n.gr);
        let mut oe = nr;
        for (e, &ze) in layout.elim_size.iter().enumerate() {
            for i in 0..ze {
                g[oe + i] = n.ge[e][i];
                for j in 0..ze {
                    h[(oe + i, oe + j)] = n.hee[e][(i, j)];
                }
            }
            for (c, &(oa, za)) in layout.couplings[e].iter().enumerate() {
                for i in 0..ze {
                    for j in 0..za {
                        let v = n.her[e].block(c)[j * ze + i];
                        h[(oe + i, oa + j)] = v;
                        h[(oa + j, oe + i)] = v;
                    }
                }
            }
            oe += ze;
        }
        (h, g)
    }

    /// The normal equations summed in parts (over the cores) are those summed in one,
    /// and the step of the Schur complement (faer's rank updates of the lower triangle
    /// and Cholesky) is the damped step of the full system, with the points and with
    /// the rig poses eliminated.
    #[test]
    fn the_schur_step_in_parts_is_the_damped_step_of_the_full_system() {
        for n_rigs in [4, 40] {
            let mut p = problem_with_rigs(n_rigs);
            p.rig_from_cam[1] = p.rig_from_cam[1]
                .perturbed(&Vec3::new(0.02, -0.03, 0.01), &Vec3::new(0.01, 0.0, 0.015));
            for x in p.points.iter_mut() {
                *x += Vec3::new(0.01, -0.01, 0.02);
            }
            let layout = p.layout();
            let loss = Loss::Huber { scale: 2.0 };
            let one = p
                .normal_equations_in_parts(&layout, &loss, 1, None)
                .unwrap();
            // Written over the equations of another state (as the solve reuses them).
            let mut other = p.clone();
            other.points[0] += Vec3::new(0.1, 0.2, -0.1);
            let spare = other.normal_equations_in_parts(&layout, &loss, 2, None);
            let three = p
                .normal_equations_in_parts(&layout, &loss, 3, spare)
                .unwrap();
            let (h1, g1) = assemble(&layout, &one);
            let (h3, g3) = assemble(&layout, &three);
            let scale = h1.amax();
            assert!((&h1 - &h3).amax() < 1e-12 * scale, "{n_rigs}");
            assert!((&g1 - &g3).amax() < 1e-12 * g1.amax(), "{n_rigs}");
            assert!((one.cost - three.cost).abs() < 1e-12 * one.cost);

            let (lambda, floor) = (1e-3, 1e-9);
            let mut damped = h1.clone();
            for i in 0..damped.nrows() {
                damped[(i, i)] += lambda * h1[(i, i)].max(floor);
            }
            let full = damped.cholesky().unwrap().solve(&(-&g1));
            let reduced = Reduced {
                layout: &layout,
                normal: three,
                workspace: None,
            };
            let (dr, de) = reduced.solve_damped(lambda, floor).unwrap();
            let nr = layout.n_reduced;
            let mut worst = (&dr - full.rows(0, nr)).amax();
            let mut oe = nr;
            for (e, &ze) in layout.elim_size.iter().enumerate() {
                for i in 0..ze {
                    worst = worst.max((de[e][i] - full[oe + i]).abs());
                }
                oe += ze;
            }
            assert!(
                worst < 1e-9 * full.amax(),
                "{n_rigs}: {worst} of {}",
                full.amax()
            );
        }
    }

    #[test]
    fn the_sparse_schur_complement_and_step_are_the_dense_ones() {
        // Each point seen only by the rig poses within 6 of its own (a drive past the
        // scene): the reduced system is a band, factored sparse.
        let mut p = problem_with_rigs(40);
        let np = p.points.len();
        p.observations.retain(|o| match o.point {
            PointRef::Free(i) => (o.rig as i64 - (i * 40 / np) as i64).abs() <= 6,
            PointRef::Body { .. } => true,
        });
        p.rig_from_cam[1] = p.rig_from_cam[1]
            .perturbed(&Vec3::new(0.02, -0.03, 0.01), &Vec3::new(0.01, 0.0, 0.015));
        for x in p.points.iter_mut() {
            *x += Vec3::new(0.01, -0.01, 0.02);
        }
        let layout = p.layout();
        let n = p
            .normal_equations(&layout, &Loss::Huber { scale: 2.0 }, None)
            .unwrap();
        let pattern = sparse_pattern_within(&layout, &n, 0, 1.0, 1).expect("a sparse pattern");
        // Sparse indeed: under the dense triangle, fill-in included.
        let nr = layout.n_reduced;
        assert!(
            pattern.factor_nnz() < nr * (nr + 1) / 2,
            "{} of {nr}",
            pattern.factor_nnz()
        );
        // The undamped Schur complement (the information's), sparse and dense.
        let inv: Vec<Matrix6<f64>> = n
            .hee
            .iter()
            .zip(&layout.elim_size)
            .map(|(hee, &size)| pseudo_inverse_block(hee, size))
            .collect();
        let sparse_s = pattern.to_dense(&sparse_schur(&pattern, &layout, &n, &inv).unwrap());
        let mut dense_s = n.hrr.to_dense(&layout);
        schur_complement(&mut dense_s, None, &layout, &n, &inv, &mut Vec::new());
        mirror_lower(&mut dense_s);
        let worst = (&sparse_s - &dense_s).amax();
        assert!(
            worst < 1e-12 * dense_s.amax(),
            "{worst} of {}",
            dense_s.amax()
        );
        let dense_work = RefCell::new(Workspace {
            sparse: Some(None),
            ..Workspace::default()
        });
        let reduced = Reduced {
            layout: &layout,
            normal: n,
            workspace: Some(&dense_work),
        };
        let n = &reduced.normal;
        for (lambda, floor) in [(1e-3, 1e-9), (1.0, 1e-9), (1e-9, 1e-6)] {
            let einv = damped_inverses(&layout, n, lambda, floor).unwrap();
            let sparse = sparse_reduced_step(&pattern, &layout, n, &einv, lambda, floor)
                .expect("every block in the pattern")
                .expect("positive definite");
            let (dense, _) = reduced.solve_damped(lambda, floor).unwrap();
            let worst = (&sparse - &dense).amax();
            assert!(
                worst < 1e-9 * dense.amax(),
                "λ {lambda}: {worst} of {}",
                dense.amax()
            );
        }
    }
}
