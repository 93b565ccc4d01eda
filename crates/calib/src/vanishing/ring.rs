//! The ring of targets: pair transforms from auxiliary views (eq. 22), their fusion when a
//! pair was photographed more than once, the chainwise initialisation by the fewest
//! transforms from the reference target (eq. 23), the closure error of the chain, and
//! first-order covariance propagation through compositions of poses.

use nalgebra::DMatrix;
use rigcal_core::geometry::{so3, Pose, Vec3};
use std::collections::{BTreeMap, VecDeque};

/// A pose with the covariance of its `[dt, dφ]` left perturbation (`Pose::perturbed`).
#[derive(Clone, Debug)]
pub struct Uncertain {
    pub pose: Pose,
    pub cov: DMatrix<f64>,
}

/// `[dt, dφ]` taking `from` to `to` in the left-perturbation convention.
pub fn difference(to: &Pose, from: &Pose) -> [f64; 6] {
    let dt = to.trans - from.trans;
    let dphi = so3::log(&(to.rot * from.rot.transpose()));
    [dt.x, dt.y, dt.z, dphi.x, dphi.y, dphi.z]
}

/// Covariance of `f(factors)` from the factors' covariances (independent), by central
/// differences of `f` in each factor's perturbation. First order, like every σ here.
pub fn propagate(factors: &[Uncertain], f: impl Fn(&[Pose]) -> Pose) -> DMatrix<f64> {
    let poses: Vec<Pose> = factors.iter().map(|u| u.pose).collect();
    let out = f(&poses);
    let h = 1e-6;
    let mut cov = DMatrix::zeros(6, 6);
    for (i, u) in factors.iter().enumerate() {
        let mut j = DMatrix::zeros(6, 6);
        for k in 0..6 {
            let mut e = [0.0; 6];
            e[k] = h;
            let shifted = |sign: f64| {
                let mut p = poses.clone();
                p[i] = p[i].perturbed(
                    &(Vec3::new(e[0], e[1], e[2]) * sign),
                    &(Vec3::new(e[3], e[4], e[5]) * sign),
                );
                difference(&f(&p), &out)
            };
            let (plus, minus) = (shifted(1.0), shifted(-1.0));
            for r in 0..6 {
                j[(r, k)] = (plus[r] - minus[r]) / (2.0 * h);
            }
        }
        cov += &j * &u.cov * j.transpose();
    }
    cov
}

/// Information-weighted mean of several estimates of one transform (linearised at the
/// first): the same pair photographed twice counts twice.
pub fn fuse(estimates: &[Uncertain]) -> Option<Uncertain> {
    let first = estimates.first()?;
    if estimates.len() == 1 {
        return Some(first.clone());
    }
    let mut info = DMatrix::zeros(6, 6);
    let mut eta = nalgebra::DVector::zeros(6);
    for e in estimates {
        let w = e.cov.clone().try_inverse()?;
        let d = nalgebra::DVector::from_row_slice(&difference(&e.pose, &first.pose));
        eta += &w * d;
        info += w;
    }
    let cov = info.try_inverse()?;
    let x = &cov * eta;
    Some(Uncertain {
        pose: first
            .pose
            .perturbed(&Vec3::new(x[0], x[1], x[2]), &Vec3::new(x[3], x[4], x[5])),
        cov,
    })
}

/// Pair transforms keyed by `(i, j)` with `i < j`, holding `ti_from_tj`.
pub type Edges = BTreeMap<(usize, usize), Uncertain>;

/// The transform `a_from_b` of an edge in either direction.
fn edge(edges: &Edges, a: usize, b: usize) -> Option<Uncertain> {
    if a < b {
        edges.get(&(a, b)).cloned()
    } else {
        let e = edges.get(&(b, a))?;
        Some(Uncertain {
            pose: e.pose.inverse(),
            cov: propagate(std::slice::from_ref(e), |p| p[0].inverse()),
        })
    }
}

/// Chainwise initialisation: for every target reachable from `reference`, the path of
/// fewest pair transforms (ties broken towards lower target indices, i.e. forward round
/// the ring) and `ref_from_target` composed along it with its covariance.
pub struct Chain {
    /// Per target: the targets from the reference to it (inclusive); empty if unreachable.
    pub path: Vec<Vec<usize>>,
    pub ref_from_target: Vec<Option<Uncertain>>,
    /// Pair edges not used by the chain: each closes a loop.
    pub closing: Vec<(usize, usize)>,
}

pub fn chain(n_targets: usize, reference: usize, edges: &Edges) -> Chain {
    let mut neighbours = vec![Vec::new(); n_targets];
    for &(i, j) in edges.keys() {
        neighbours[i].push(j);
        neighbours[j].push(i);
    }
    for n in &mut neighbours {
        n.sort_unstable();
    }
    let mut parent: Vec<Option<usize>> = vec![None; n_targets];
    let mut seen = vec![false; n_targets];
    let mut queue = VecDeque::from([reference]);
    seen[reference] = true;
    let mut ref_from_target: Vec<Option<Uncertain>> = vec![None; n_targets];
    ref_from_target[reference] = Some(Uncertain {
        pose: Pose::identity(),
        cov: DMatrix::zeros(6, 6),
    });
    while let Some(a) = queue.pop_front() {
        for &b in &neighbours[a] {
            if seen[b] {
                continue;
            }
            seen[b] = true;
            parent[b] = Some(a);
            let (Some(ra), Some(ab)) = (ref_from_target[a].clone(), edge(edges, a, b)) else {
                continue;
            };
            let cov = propagate(&[ra.clone(), ab.clone()], |p| p[0] * p[1]);
            ref_from_target[b] = Some(Uncertain {
                pose: ra.pose * ab.pose,
                cov,
            });
            queue.push_back(b);
        }
    }
    let path = (0..n_targets)
        .map(|t| {
            if !seen[t] {
                return vec![];
            }
            let mut p = vec![t];
            while let Some(q) = parent[*p.last().unwrap_or(&t)] {
                p.push(q);
            }
            p.reverse();
            p
        })
        .collect();
    let closing = edges
        .keys()
        .filter(|(i, j)| seen[*i] && seen[*j] && parent[*i] != Some(*j) && parent[*j] != Some(*i))
        .copied()
        .collect();
    Chain {
        path,
        ref_from_target,
        closing,
    }
}

impl Chain {
    /// The loop error a closing edge `(i, j)` reveals: `ref_from_tj` by the chain against
    /// the chain to `i` followed by the edge, as (translation m, rotation rad).
    pub fn closure_error(&self, edges: &Edges, (i, j): (usize, usize)) -> Option<(f64, f64)> {
        let ri = self.ref_from_target[i].as_ref()?;
        let rj = self.ref_from_target[j].as_ref()?;
        let e = edges.get(&(i, j))?;
        let (r, t) = (ri.pose * e.pose).distance(&rj.pose);
        Some((t, r))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(k: f64) -> Pose {
        Pose::from_rotvec(
            Vec3::new(0.0, 0.7 * k, 0.05),
            Vec3::new(0.9, 0.01 * k, -0.3),
        )
    }

    fn cov(s: f64) -> DMatrix<f64> {
        DMatrix::identity(6, 6) * s * s
    }

    #[test]
    fn chain_takes_the_shortest_way_round_and_finds_the_closing_edge() {
        // A ring of 8: edges (k, k+1) and (7, 0).
        let n = 8;
        let mut edges = Edges::new();
        for k in 0..n {
            let (i, j) = (k, (k + 1) % n);
            let p = pose(k as f64);
            let (key, p) = if i < j {
                ((i, j), p)
            } else {
                ((j, i), p.inverse())
            };
            edges.insert(
                key,
                Uncertain {
                    pose: p,
                    cov: cov(1e-3),
                },
            );
        }
        let c = chain(n, 0, &edges);
        let hops: Vec<usize> = c.path.iter().map(|p| p.len() - 1).collect();
        assert_eq!(hops, vec![0, 1, 2, 3, 4, 3, 2, 1]);
        assert_eq!(c.closing.len(), 1);
        // σ grows along the chain.
        let s: Vec<f64> = c
            .ref_from_target
            .iter()
            .map(|u| u.as_ref().unwrap().cov.trace())
            .collect();
        assert!(s[1] < s[2] && s[2] < s[3] && s[3] < s[4] && s[4] > s[5]);
    }

    #[test]
    fn an_exact_ring_has_zero_closure_error_and_a_broken_one_is_unreachable() {
        // Targets on a circle; edges from the true poses.
        let truth: Vec<Pose> = (0..6)
            .map(|k| {
                let a = k as f64 * std::f64::consts::PI / 3.0;
                Pose::from_rotvec(Vec3::new(0.0, a, 0.0), Vec3::new(a.sin(), 0.0, a.cos()))
            })
            .collect();
        let mut edges = Edges::new();
        for k in 0..6 {
            let (i, j) = (k.min((k + 1) % 6), k.max((k + 1) % 6));
            edges.insert(
                (i, j),
                Uncertain {
                    pose: truth[i].inverse() * truth[j],
                    cov: cov(1e-3),
                },
            );
        }
        let c = chain(6, 0, &edges);
        for k in 0..6 {
            let got = c.ref_from_target[k].as_ref().unwrap().pose;
            let (r, t) = got.distance(&(truth[0].inverse() * truth[k]));
            assert!(r < 1e-12 && t < 1e-12);
        }
        let (t, r) = c.closure_error(&edges, c.closing[0]).unwrap();
        assert!(t < 1e-12 && r < 1e-12);
        // Remove two edges: targets 2 and 3 (between them) are cut off from 0.
        edges.remove(&(1, 2));
        edges.remove(&(3, 4));
        let c = chain(6, 0, &edges);
        assert!(c.path[2].is_empty() && c.path[3].is_empty() && !c.path[4].is_empty());
        assert!(c.closing.is_empty());
    }

    #[test]
    fn propagation_matches_the_adjoint_and_fusion_averages() {
        // Translation noise on b_from_c, rotated into a's frame by a_from_b.
        let a_from_b = Pose::from_rotvec(
            Vec3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            Vec3::zeros(),
        );
        let mut c = DMatrix::zeros(6, 6);
        c[(0, 0)] = 1.0;
        let u = [
            Uncertain {
                pose: a_from_b,
                cov: DMatrix::zeros(6, 6),
            },
            Uncertain {
                pose: Pose::identity(),
                cov: c,
            },
        ];
        let out = propagate(&u, |p| p[0] * p[1]);
        assert!((out[(1, 1)] - 1.0).abs() < 1e-6 && out[(0, 0)].abs() < 1e-6);

        let p = Pose::from_rotvec(Vec3::new(0.1, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0));
        let q = p.perturbed(&Vec3::new(0.02, 0.0, 0.0), &Vec3::zeros());
        let f = fuse(&[
            Uncertain {
                pose: p,
                cov: cov(0.1),
            },
            Uncertain {
                pose: q,
                cov: cov(0.1),
            },
        ])
        .unwrap();
        assert!((f.pose.trans.x - 1.01).abs() < 1e-12);
        assert!((f.cov[(0, 0)] - 0.005).abs() < 1e-12);
    }
}
