//! CPD's M-step without a dense solve, the same from ten points to 1e5.
//!
//! Each iteration solves `(dP1 G + s I) W = PX - dP1 Y` (s = lambda sigma^2) for the
//! M x 3 coefficients W. Dividing row i by P1_i gives a symmetric positive definite system
//!
//! ```text
//! A W = R,   A = G + s D^-1,   R = D^-1 PX - Y,   D = diag(max(P1, floor)),
//! ```
//!
//! solved in two parts. G ~ F F^T is a Nystrom approximation built once (in float64 on
//! the host) by pivoted Cholesky: the kernel's columns at up to [`LANDMARKS`] source
//! points, each chosen where G - F F^T is largest on the diagonal so far (`pivoted_cholesky`).
//! First the system with F F^T in place of G is solved exactly,
//! by the Woodbury identity through the Cholesky factor of the r x r matrix
//! I + F^T (s D^-1)^-1 F (refactored each iteration, as D and s change). What F F^T
//! misses, E = G - F F^T, is positive semi-definite, so the relative error of that
//! solution (in the A-norm) is at most trace(S^-1/2 E S^-1/2) = sum_i E_ii d_i / s, known
//! exactly on the host. A wide kernel's spectrum decays fast: at the default beta = 2 the
//! bound stays below `NYSTROM_EXACT` and that solution is the M-step, with no kernel
//! product at all (it matches a dense float64 solve to 1e-7; `tests/cpd.rs`).
//!
//! Otherwise (a narrow kernel) conjugate gradients refine it, three columns side by side,
//! one product G V on the device per step (`glsl/gauss_product.comp`, never forming G),
//! preconditioned by (F F^T + S + diag E)^-1. G W is carried along, so the moved points
//! Y + G W cost no extra product. Since A >= mu P^-1 with mu = min_i S_i / (S_i + E_ii),
//! an exact step is at most 1 / mu; the device's products are float32, and once sigma^2 is
//! so small that their rounding matters to A a step comes out longer (or the curvature
//! vanishes), and the column stops there. A column also stops when its step no longer
//! moves G W, the displacement the registration uses: W itself is ill-determined along the
//! kernel's smallest eigenvalues, G W is not.
//!
//! Rows with P1_i = 0 (no target near) must get W_i = 0, as the undivided system says; the
//! floor 1e-10 s keeps D invertible, and there s / floor = 1e10 pins W_i near zero.
//!
//! With [`super::CpdParams::rank`] set, G is replaced by its Nystrom approximation from
//! that many landmarks outright: the preconditioner is then the exact inverse, one
//! Woodbury solve, no kernel products (faster, approximate: an explicit option).

use std::cell::OnceCell;

use faer::linalg::solvers::{Llt, Solve};
use faer::{Mat, Side};
use glam::DVec3;

use super::linalg::Matrix;
use super::{Backend, Expectation};
use crate::error::{Error, Result};

/// Landmarks of the Nystrom preconditioner (at most).
pub const LANDMARKS: usize = 200;
/// Conjugate-gradient stopping point: residual below this fraction of the right-hand
/// side's, per column, in the preconditioned norm.
pub const TOLERANCE: f64 = 1e-6;
/// Kernel products per M-step at most (a narrow kernel late in a registration may stop
/// here; the next iteration starts again from its own Nystrom solution).
pub const MAX_PRODUCTS: usize = 40;
/// Conjugate-gradient steps up to this multiple of the longest exact one are taken.
const MAX_STEP: f64 = 2.0;
/// The Nystrom solution is taken as it is when its error bound is below this (a bound
/// from a trace: the true error is orders of magnitude smaller).
const NYSTROM_EXACT: f64 = 1e-2;
/// Relative rounding of a device kernel product: (G v)_i is a float32 sum of M terms,
/// good to about this times sum_j G_ij |v_j| (2^-24 per term, with room for the sum).
const PRODUCT_ROUNDING: f64 = 1e-6;

/// The M-step's fixed part: the Nystrom factor of the source's kernel.
pub struct MStep {
    /// F (M x r): G ~ F F^T.
    features: Matrix,
    /// diag(G - F F^T) = 1 - |F_i|^2.
    missed: Vec<f64>,
    /// G is F F^T (the low-rank option): solve directly, without kernel products.
    low_rank: bool,
    /// max_i sum_j G_ij, from one device product at the first M-step that needs it.
    largest_row_sum: OnceCell<f64>,
}

/// What one M-step did.
#[derive(Clone, Copy, Debug, Default)]
pub struct Solved {
    /// Kernel products used.
    pub products: usize,
    /// Every column reached [`TOLERANCE`] (always true for the low-rank option).
    pub converged: bool,
    /// The Nystrom solution was kept although its bound is above `NYSTROM_EXACT`: the
    /// device's float32 products are too coarse for this system to refine it.
    pub limited: bool,
}

impl MStep {
    /// The exact M-step (conjugate gradients on G) with a Nystrom preconditioner from
    /// [`LANDMARKS`] landmarks, or with `rank: Some(k)` G replaced by the Nystrom
    /// approximation from k landmarks.
    pub fn new(source: &[DVec3], beta: f64, rank: Option<usize>) -> Result<Self> {
        let (features, missed) = pivoted_cholesky(source, beta, rank.unwrap_or(LANDMARKS).max(1))?;
        Ok(Self {
            features,
            missed,
            low_rank: rank.is_some(),
            largest_row_sum: OnceCell::new(),
        })
    }

    /// The rank of the Nystrom factor.
    pub fn rank(&self) -> usize {
        self.features.cols
    }

    /// One M-step for the E-step `e` at the moved points `moving` of the source `y`, with
    /// s = lambda sigma^2: writes W to `w` and the displacement G W to `gw` (both M x 3).
    #[allow(clippy::too_many_arguments)]
    pub fn solve(
        &self,
        backend: &mut dyn Backend,
        e: &Expectation,
        y: &[DVec3],
        moving: &[DVec3],
        s: f64,
        w: &mut Matrix,
        gw: &mut Matrix,
    ) -> Result<Solved> {
        let m = y.len();
        let floor = 1e-10 * s;
        let d: Vec<f64> = e.p1.iter().map(|&p| p.max(floor)).collect();
        let mut rhs = Matrix::zeros(m, 3);
        for i in 0..m {
            // PX_i / d_i - y_i, with PX_i = pull_i + P1_i t_i.
            let r = (e.pull[i] + e.p1[i] * moving[i]) / d[i] - y[i];
            rhs.data[3 * i..3 * i + 3].copy_from_slice(&r.to_array());
        }
        let diagonal: Vec<f64> = d.iter().map(|di| s / di).collect();
        let pre = Woodbury::new(&self.features, &diagonal)?;
        // The Nystrom solution, exact for F F^T. Its relative error (in the A-norm) is at
        // most |P E| <= trace(S^-1/2 E S^-1/2) = sum_i E_ii d_i / s.
        *w = pre.apply(&rhs);
        *gw = self.features.mul(&self.features.transpose().mul(w));
        let bound = self
            .missed
            .iter()
            .zip(&d)
            .map(|(e, di)| e * di)
            .sum::<f64>()
            / s;
        if self.low_rank || bound <= NYSTROM_EXACT {
            return Ok(Solved {
                products: 0,
                converged: true,
                limited: false,
            });
        }
        // A float32 product G v is off by up to about PRODUCT_ROUNDING sum_j G_ij |v_j|.
        // Conjugate gradients refine the Nystrom solution along what F F^T misses, where A
        // is no larger than E + S; once even the largest row sum of G times that rounding
        // exceeds the smallest S_i (sigma^2 near zero, as on noise-free sets), a step
        // would follow the rounding, not the system (it threw 5000 noise-free points far
        // off at sigma^2 = 2e-8). The Nystrom solution, exact in float64 for F F^T, is
        // then the best there is.
        let mut products = 0;
        let largest_row_sum = match self.largest_row_sum.get() {
            Some(&sum) => sum,
            None => {
                let ones = Matrix {
                    rows: m,
                    cols: 1,
                    data: vec![1.0; m],
                };
                let sums = backend.kernel_product(&ones)?;
                products += 1;
                let sum = sums.data.iter().copied().fold(0.0, f64::max);
                *self.largest_row_sum.get_or_init(|| sum)
            }
        };
        let smallest = diagonal.iter().copied().fold(f64::INFINITY, f64::min);
        if PRODUCT_ROUNDING * largest_row_sum >= smallest {
            return Ok(Solved {
                products,
                converged: false,
                limited: true,
            });
        }
        *gw = backend.kernel_product(w)?;
        products += 1;

        // Conjugate gradients from there, three independent columns, one product per step,
        // preconditioned with what F F^T misses on the diagonal too: with it,
        // A >= mu P^-1 for mu = min_i S_i / (S_i + E_ii), so an exact step is at most 1 / mu.
        let corrected: Vec<f64> = diagonal
            .iter()
            .zip(&self.missed)
            .map(|(a, b)| a + b)
            .collect();
        let mu = diagonal
            .iter()
            .zip(&corrected)
            .map(|(a, b)| a / b)
            .fold(1.0, f64::min);
        let longest = MAX_STEP / mu;
        let pre = Woodbury::new(&self.features, &corrected)?;
        let a_times = |v: &Matrix, gv: &Matrix| {
            let mut out = gv.clone();
            for (k, x) in out.data.iter_mut().enumerate() {
                *x += diagonal[k / 3] * v.data[k];
            }
            out
        };
        // Residuals are measured in the preconditioned norm r^T P r: rows without targets
        // have S_i ~ 1e10, and the plain norm would be theirs alone.
        let target = column_dot(&rhs, &pre.apply(&rhs)).map(|n| TOLERANCE * TOLERANCE * n);
        let mut residual = rhs;
        let aw = a_times(w, gw);
        for (r, a) in residual.data.iter_mut().zip(&aw.data) {
            *r -= a;
        }
        let mut z = pre.apply(&residual);
        let mut rz = column_dot(&residual, &z);
        let mut direction = z;
        let mut active: [bool; 3] = std::array::from_fn(|c| rz[c] > target[c]);
        while active.contains(&true) && products < MAX_PRODUCTS {
            let g_direction = backend.kernel_product(&direction)?;
            products += 1;
            let a_direction = a_times(&direction, &g_direction);
            let curvature = column_dot(&direction, &a_direction);
            let mut step = [0.0; 3];
            for c in 0..3 {
                // A step past the longest exact one (or a direction without curvature)
                // means the products' float32 rounding has reached the system's own
                // scale. Stop that column where it is.
                let alpha = rz[c] / curvature[c];
                if active[c] && curvature[c] > 0.0 && alpha <= longest {
                    step[c] = alpha;
                } else {
                    active[c] = false;
                }
            }
            for k in 0..3 * m {
                let c = k % 3;
                w.data[k] += step[c] * direction.data[k];
                gw.data[k] += step[c] * g_direction.data[k];
                residual.data[k] -= step[c] * a_direction.data[k];
            }
            z = pre.apply(&residual);
            let next = column_dot(&residual, &z);
            let moved = column_dot(&g_direction, &g_direction);
            let displacement = column_dot(gw, gw);
            for c in 0..3 {
                // Converged in W, or in the displacement G W that the registration uses.
                if next[c] <= target[c]
                    || step[c] * step[c] * moved[c] <= TOLERANCE * TOLERANCE * displacement[c]
                {
                    active[c] = false;
                }
            }
            for k in 0..3 * m {
                let c = k % 3;
                let beta = if rz[c] > 0.0 { next[c] / rz[c] } else { 0.0 };
                direction.data[k] = z.data[k] + beta * direction.data[k];
            }
            rz = next;
        }
        Ok(Solved {
            products,
            converged: !active.contains(&true),
            limited: false,
        })
    }
}

fn column_dot(a: &Matrix, b: &Matrix) -> [f64; 3] {
    let mut dot = [0.0; 3];
    for (k, (x, y)) in a.data.iter().zip(&b.data).enumerate() {
        dot[k % 3] += x * y;
    }
    dot
}

/// (F F^T + diag(S))^-1 by the Woodbury identity:
/// S^-1 - S^-1 F (I + F^T S^-1 F)^-1 F^T S^-1.
struct Woodbury<'a> {
    features: &'a Matrix,
    inverse: Vec<f64>,
    inner: Llt<f64>,
}

impl<'a> Woodbury<'a> {
    fn new(features: &'a Matrix, diagonal: &[f64]) -> Result<Self> {
        let inverse: Vec<f64> = diagonal.iter().map(|d| 1.0 / d).collect();
        let r = features.cols;
        let mut scaled = features.clone();
        for (i, row) in scaled.data.chunks_mut(r.max(1)).enumerate() {
            let f = inverse[i].sqrt();
            row.iter_mut().for_each(|v| *v *= f);
        }
        let mut inner: Mat<f64> = scaled.view().transpose() * scaled.view();
        for k in 0..r {
            inner[(k, k)] += 1.0;
        }
        let inner = inner
            .llt(Side::Lower)
            .map_err(|e| Error::InvalidInput(format!("CPD's M-step preconditioner: {e:?}")))?;
        Ok(Self {
            features,
            inverse,
            inner,
        })
    }

    fn apply(&self, v: &Matrix) -> Matrix {
        let mut scaled = v.clone();
        for (i, row) in scaled.data.chunks_mut(v.cols).enumerate() {
            row.iter_mut().for_each(|x| *x *= self.inverse[i]);
        }
        if self.features.cols == 0 {
            return scaled;
        }
        let projected: Mat<f64> = self.features.view().transpose() * scaled.view();
        let solved = self.inner.solve(projected.as_ref());
        let back: Mat<f64> = self.features.view() * solved.as_ref();
        for (i, row) in scaled.data.chunks_mut(v.cols).enumerate() {
            for (c, x) in row.iter_mut().enumerate() {
                *x -= self.inverse[i] * back[(i, c)];
            }
        }
        scaled
    }
}

/// Below this residual the kernel's diagonal (1) is resolved to float64's precision and
/// a further landmark adds nothing.
const RESOLVED: f64 = 1e-15;

/// G ~ F F^T (F: M x r, r <= `count`) by pivoted Cholesky, the Nystrom approximation whose
/// landmarks are chosen greedily: each is the point whose diagonal residual
/// (G - F F^T)_ii is largest so far, so the columns are exact at the landmarks and the
/// residual shrinks as fast as a greedy choice can make it. Returns F and that residual
/// diagonal (what F F^T misses, kept as the algorithm goes: no 1 - |F_i|^2 cancellation).
/// At beta = 2 on 1e5 points the residual falls below 1e-15 per point in under 200
/// columns, where farthest-point landmarks with an eigen-truncated inner matrix left 7e-8 in
/// all: the M-step then needs no kernel products down to far smaller sigma^2.
fn pivoted_cholesky(points: &[DVec3], beta: f64, count: usize) -> Result<(Matrix, Vec<f64>)> {
    let m = points.len();
    let inv = 1.0 / (2.0 * beta * beta);
    let mut residual = vec![1.0; m];
    let mut columns: Vec<Vec<f64>> = Vec::new();
    while columns.len() < count.min(m) {
        let (pivot, largest) =
            residual
                .iter()
                .copied()
                .enumerate()
                .fold((0, f64::NEG_INFINITY), |best, (i, r)| {
                    if r > best.1 {
                        (i, r)
                    } else {
                        best
                    }
                });
        if !largest.is_finite() {
            return Err(Error::InvalidInput(
                "CPD: the source's kernel is not finite".into(),
            ));
        }
        if largest <= RESOLVED {
            break;
        }
        let y = points[pivot];
        let mut column: Vec<f64> = points
            .iter()
            .map(|&q| (-(q - y).length_squared() * inv).exp())
            .collect();
        for previous in &columns {
            let at_pivot = previous[pivot];
            for (c, p) in column.iter_mut().zip(previous) {
                *c -= p * at_pivot;
            }
        }
        let scale = 1.0 / largest.sqrt();
        for (c, r) in column.iter_mut().zip(&mut residual) {
            *c *= scale;
            *r = (*r - *c * *c).max(0.0);
        }
        residual[pivot] = 0.0;
        columns.push(column);
    }
    let r = columns.len();
    let mut features = Matrix::zeros(m, r);
    for (c, column) in columns.iter().enumerate() {
        for (i, &v) in column.iter().enumerate() {
            features.data[i * r + c] = v;
        }
    }
    Ok((features, residual))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points(count: usize) -> Vec<DVec3> {
        // A deterministic scatter in the unit cube (a low-discrepancy sequence).
        (0..count)
            .map(|i| {
                let t = i as f64 + 0.5;
                DVec3::new(
                    (t * 0.618_034).fract(),
                    (t * 0.754_878).fract(),
                    (t * 0.569_840).fract(),
                )
            })
            .collect()
    }

    /// F F^T against the kernel, and the residual the algorithm kept against G - F F^T.
    fn check(beta: f64, count: usize) -> (f64, usize) {
        let p = points(60);
        let (f, residual) = pivoted_cholesky(&p, beta, count).unwrap();
        let mut worst: f64 = 0.0;
        for i in 0..p.len() {
            for j in 0..p.len() {
                let g = (-(p[i] - p[j]).length_squared() / (2.0 * beta * beta)).exp();
                let approx: f64 = (0..f.cols).map(|c| f.at(i, c) * f.at(j, c)).sum();
                assert!(approx <= 1.0 + 1e-12);
                if i == j {
                    assert!((g - approx - residual[i]).abs() < 1e-12, "residual {i}");
                }
                worst = worst.max((g - approx).abs());
            }
        }
        (worst, f.cols)
    }

    #[test]
    fn pivoted_cholesky_resolves_a_wide_kernel() {
        let (worst, _) = check(2.0, 200);
        assert!(worst < 1e-12, "G off by {worst}");
    }

    #[test]
    fn pivoted_cholesky_of_a_narrow_kernel_keeps_what_it_misses() {
        let (worst, rank) = check(0.05, 10);
        assert_eq!(rank, 10);
        assert!(
            worst > 1e-3,
            "10 columns cannot resolve a narrow kernel: {worst}"
        );
    }
}
