//! Non-rigid Coherent Point Drift (Myronenko & Song 2010): moves source points Y onto a
//! target set X as T = Y + G W, G_ij = exp(-|y_i - y_j|^2 / (2 beta^2)).
//!
//! The E-step (P1, Pt1, and per source point the pull sum_n P (x - t) and spread
//! sum_n P |x - t|^2) runs on the device without forming the M x N matrix: one pass
//! per target point accumulates a log-sum-exp denominator, one pass per source point the
//! sums (`glsl/cpd_*.comp`). The M-step ([`m_step`]) solves for W by preconditioned
//! conjugate gradients whose products G V run on the device (`glsl/gauss_product.comp`),
//! never forming G either: one path from ten points to 1e5. [`reference`](mod@reference) runs the same
//! algorithm with a float64 E-step and kernel products.
//!
//! The iterations stop on the objective (negative log-likelihood plus the smoothness
//! term, relative change below the tolerance) once the points have stopped moving too
//! (mean movement below the tolerance, in source radii), at sigma^2's floor, or where an iteration
//! raises the objective: exact EM never does, so the device's float32 precision has been
//! reached, and that iteration is undone ([`Stop`]). In the fine phase, SQUAREM jumps
//! along the iterates where that lowers the objective more than a plain step.
//!
//! As in Myronenko's reference code, both sets are normalised before registration, here
//! jointly by the source's centroid and RMS radius (so that differences of size between
//! targets survive): beta and lambda are in those units, and results are mapped back, so
//! millimetres and metres give the same answer.

mod gpu;
#[doc(hidden)] // CPD's internals, public for its tests and benchmarks
pub mod linalg;
#[doc(hidden)]
pub mod m_step;
#[doc(hidden)]
pub mod neighbours;
#[doc(hidden)] // the float64 model the tests check the device against
pub mod reference;

use std::time::Instant;

use glam::DVec3;

use crate::error::{show, Error, Result};
use crate::gpu::{Context, LOOP_LIMIT};
use crate::mesh::centroid;
use linalg::Matrix;
use m_step::MStep;

pub use gpu::{CpdPipelines, GpuBackend};

/// Points served per invocation by the passes above (`ROWS` in `glsl/include/cpd.glsl`).
const ROWS: u32 = 8;
const _: () = assert!(neighbours::POINTS_PER_GROUP == 64 * ROWS as usize);
/// Points of the other set one dispatch of those passes loops over (see
/// [`LOOP_LIMIT`]): on lavapipe an invocation runs about 10 loop iterations per 8 points
/// and loop (two loops in the denominator pass), some 2e4 in all.
pub const SPAN: u32 = 8192;
const _: () = assert!(2 * (SPAN / 8) * 10 < LOOP_LIMIT / 2);

/// CPD settings (defaults as in the paper and pycpd: beta = 2, lambda = 2, w = 0.1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CpdParams {
    /// Width of the Gaussian kernel of the displacement field, in units of the source's
    /// RMS radius.
    pub beta: f64,
    /// Smoothness weight. The data term grows with the number of points and this one
    /// does not, so one lambda smooths a dense set less than a sparse one: on the peers'
    /// noise-free surface sets, lambda = 2 let regions of 2e4 points and more lock in off
    /// their correspondences while sigma^2 collapsed (1e5 points: mean error 7.6e-3
    /// source radii), where a larger one did not (1e5 points with lambda = 5000: 8.4e-6,
    /// in 229 s instead of 602 s on lavapipe), while 5000 stops 5e3 points early,
    /// oversmoothed (2.8e-2 against 1.1e-5 at 2), and 2e4 points with 10% missing and 2%
    /// outliers (1.4e-3 against 2.1e-5 at 2): the table in docs/method.md, "Dense sets want a larger lambda".
    pub lambda: f64,
    /// Weight of the uniform outlier component, in (0, 1).
    pub w: f64,
    /// Most EM iterations to run (1 to 100 000).
    pub max_iterations: usize,
    /// Stop when an iteration lowers the objective (the negative log-likelihood plus the
    /// smoothness term) by less than this fraction of it, as Myronenko's reference code
    /// does, and moves the points by less than this (on average, in units of the source's
    /// RMS radius), which keeps dense sets sliding into place.
    pub tolerance: f64,
    /// Replace G by its Nystrom approximation from this many landmarks (a faster,
    /// approximate M-step); `None`: the exact G by conjugate gradients ([`m_step`]).
    pub rank: Option<usize>,
    /// Extrapolate along the EM iterates (SQUAREM) where that lowers the objective more
    /// than a plain step; `false`: plain EM, as pycpd and Myronenko's code.
    pub accelerate: bool,
    /// Above twice this many source points (and without `rank`), register subsets of this
    /// many source points (and as large a share of the target) first, and start the full
    /// sets from that displacement field ([`coarse_start`]); `None` (the default): one
    /// stage. 2-3x faster from 2e4 points on; see [`COARSE_POINTS`] for its accuracy.
    pub coarse: Option<usize>,
}

impl Default for CpdParams {
    fn default() -> Self {
        Self {
            beta: 2.0,
            lambda: 2.0,
            w: 0.1,
            max_iterations: 1000,
            tolerance: 1e-5,
            rank: None,
            accelerate: true,
            coarse: None,
        }
    }
}

impl CpdParams {
    /// An error naming the first parameter out of its range: beta and lambda in
    /// [1e-6, 1e6] (past them the kernel or the smoothness term leaves float range and
    /// the iterations diverge), 0 < w < 1, a tolerance in [0, 1), 1 to 100 000 iterations.
    pub fn validate(&self) -> Result<()> {
        let within = |v: f64| v.is_finite() && (1e-6..=1e6).contains(&v);
        let problem = if !within(self.beta) {
            Some(format!("beta {} must be in [1e-6, 1e6]", show(self.beta)))
        } else if !within(self.lambda) {
            Some(format!(
                "lambda {} must be in [1e-6, 1e6]",
                show(self.lambda)
            ))
        } else if !(self.w > 0.0 && self.w < 1.0) {
            Some(format!("w {} must be in (0, 1)", show(self.w)))
        } else if !(self.tolerance >= 0.0 && self.tolerance < 1.0) {
            Some(format!(
                "tolerance {} must be in [0, 1)",
                show(self.tolerance)
            ))
        } else if !(1..=100_000).contains(&self.max_iterations) {
            Some(format!(
                "max iterations {} must be 1 to 100000",
                self.max_iterations
            ))
        } else if self.rank == Some(0) {
            Some("rank 0: the low-rank kernel needs at least one landmark".into())
        } else if self.coarse.is_some_and(|k| k < 3) {
            Some("coarse stage of fewer than 3 points".into())
        } else {
            None
        };
        match problem {
            None => Ok(()),
            Some(p) => Err(Error::InvalidInput(format!("CPD parameter {p}"))),
        }
    }
}

/// The outcome of one registration.
#[derive(Clone, Debug)]
pub struct CpdResult {
    /// The moved source points T = Y + G W (the Nystrom G with the low-rank option).
    pub deformed: Vec<DVec3>,
    /// The coefficients W (M x 3), in the data's units: deformed = Y + G W.
    pub w: Vec<DVec3>,
    /// sigma^2 of each state the run moved to (the first entry is the initial value), in
    /// normalised units: one per iteration, except that a kept SQUAREM jump replaces the
    /// two iterations it extrapolates.
    pub sigma2: Vec<f64>,
    /// EM iterations run (each step of a SQUAREM jump counts; the coarse
    /// stage's included).
    pub iterations: usize,
    /// Why the iterations ended.
    pub stop: Stop,
    /// Wall time of the registration, seconds.
    pub seconds: f64,
    /// Gaussian-kernel products of the M-steps, all iterations together.
    pub products: usize,
    /// M-steps that kept the Nystrom solution because the device's float32 products were
    /// too coarse to refine it ([`m_step::Solved::limited`]).
    pub limited: usize,
    /// SQUAREM jumps kept ([`CpdParams::accelerate`]).
    pub jumps: usize,
    /// Source points of the coarse stage ([`CpdParams::coarse`]; 0: none ran), and its
    /// iterations (included in `iterations`; `sigma2` starts with its values).
    pub coarse_points: usize,
    /// Iterations of the coarse stage (0: none ran).
    pub coarse_iterations: usize,
}

/// Why a registration ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stop {
    /// The objective changed by less than [`CpdParams::tolerance`] of itself and the
    /// points moved by less than it (on average, in units of the source's RMS radius).
    Converged,
    /// sigma^2 reached its floor (1e-12 of the initial value): the sets fit exactly.
    Exact,
    /// An iteration raised the objective, which exact EM never does: the M-step had
    /// reached the precision of the device's float32 kernel products (noise-free sets
    /// drive sigma^2 towards zero and the system towards singular). That iteration is
    /// undone; the result is the last one that lowered the objective.
    Precision,
    /// [`CpdParams::max_iterations`] ran.
    Iterations,
}

impl Stop {
    /// Whether the registration ended at a fixed point (not at the iteration limit).
    pub fn converged(self) -> bool {
        self != Stop::Iterations
    }

    /// A few words for a log line.
    pub fn describe(self) -> &'static str {
        match self {
            Stop::Converged => "converged",
            Stop::Exact => "converged: the sets fit exactly",
            Stop::Precision => "converged to the device's float32 precision",
            Stop::Iterations => "iteration limit",
        }
    }
}

/// Sums of the E-step for the moved points t_m: P1_m = sum_n P_mn, Pt1_n = sum_m P_mn,
/// the pull sum_n P_mn (x_n - t_m) and the spread sum_n P_mn |x_n - t_m|^2 (per source
/// point; differences, so that they keep their precision as the sets close in), and
/// sum_n log(sum_m exp(-|x_n - t_m|^2 / (2 sigma^2)) + c), the log-likelihood up to terms
/// in sigma^2 alone.
pub struct Expectation {
    /// P1_m of each source point.
    pub p1: Vec<f64>,
    /// Pt1_n of each target point.
    pub pt1: Vec<f64>,
    /// The pull sum_n P_mn (x_n - t_m) of each source point.
    pub pull: Vec<DVec3>,
    /// The spread sum_n P_mn |x_n - t_m|^2 of each source point.
    pub spread: Vec<f64>,
    /// sum_n log(sum_m exp(-|x_n - t_m|^2 / (2 sigma^2)) + c).
    pub log_denominators: f64,
}

/// Where the E-step and the kernel products run (the device, or the float64 reference).
pub trait Backend {
    /// The E-step for the moved source points `moving` against the target.
    fn expectation(&mut self, moving: &[DVec3], sigma2: f64, log_c: f64) -> Result<Expectation>;
    /// G V for the source points and a block of columns (M x k).
    fn kernel_product(&mut self, v: &Matrix) -> Result<Matrix>;
}

/// The dense kernel matrix G of `points` with width `beta`.
pub fn kernel_matrix(points: &[DVec3], beta: f64) -> Matrix {
    let m = points.len();
    let mut g = Matrix::zeros(m, m);
    let inv = 1.0 / (2.0 * beta * beta);
    for i in 0..m {
        for j in 0..m {
            g.set(
                i,
                j,
                (-(points[i] - points[j]).length_squared() * inv).exp(),
            );
        }
    }
    g
}

fn to_points(m: &Matrix) -> Vec<DVec3> {
    m.data
        .chunks(3)
        .map(|c| DVec3::new(c[0], c[1], c[2]))
        .collect()
}

/// Runs CPD with the given backend (device or reference), from W = 0. `on_iteration` sees
/// each iteration's number and sigma^2 (for progress bars).
pub fn run(
    backend: &mut dyn Backend,
    source: &[DVec3],
    target: &[DVec3],
    params: &CpdParams,
    on_iteration: &mut dyn FnMut(usize, f64),
) -> Result<CpdResult> {
    run_from(backend, source, target, params, None, on_iteration)
}

/// Where a registration starts other than at W = 0 (see [`coarse_start`]).
pub struct Start {
    /// W (M x 3, normalised units).
    pub w: Vec<DVec3>,
    /// Initial sigma^2, normalised units.
    pub sigma2: f64,
}

/// [`run`] from `start` (or from W = 0 and sigma^2 the mean squared distance of all pairs).
pub fn run_from(
    backend: &mut dyn Backend,
    source: &[DVec3],
    target: &[DVec3],
    params: &CpdParams,
    start: Option<Start>,
    on_iteration: &mut dyn FnMut(usize, f64),
) -> Result<CpdResult> {
    params.validate()?;
    check_points(source, "source")?;
    check_points(target, "target")?;
    let started = Instant::now();
    let (m, n) = (source.len(), target.len());
    let m_step = MStep::new(source, params.beta, params.rank)?;
    // The convergence test's unit of movement.
    let radius = Normalization::of(source).scale;

    // Initial sigma^2: mean squared distance over all pairs, in closed form.
    let sum_x: DVec3 = target.iter().sum();
    let sum_y: DVec3 = source.iter().sum();
    let sum_xx: f64 = target.iter().map(|x| x.length_squared()).sum();
    let sum_yy: f64 = source.iter().map(|p| p.length_squared()).sum();
    let initial = ((m as f64 * sum_xx + n as f64 * sum_yy - 2.0 * sum_x.dot(sum_y))
        / (3.0 * m as f64 * n as f64))
        .max(0.0);
    let floor = 1e-12 * initial.max(1e-300);
    let sigma2 = if initial > 0.0 { initial } else { 1.0 };

    let mut em = Em {
        backend,
        m_step: &m_step,
        params,
        source,
        n,
        floor,
        products: 0,
        limited: 0,
    };
    let first = match start {
        None => State {
            w: Matrix::zeros(m, 3),
            gw: Matrix::zeros(m, 3),
            moving: source.to_vec(),
            sigma2,
        },
        Some(start) => {
            if start.w.len() != m || start.sigma2.is_nan() || start.sigma2 <= 0.0 {
                return Err(Error::InvalidInput(format!(
                    "a CPD start needs {m} coefficients and sigma^2 > 0, not {} and {}",
                    start.w.len(),
                    show(start.sigma2)
                )));
            }
            let w = Matrix {
                rows: m,
                cols: 3,
                data: start.w.iter().flat_map(|p| p.to_array()).collect(),
            };
            let gw = em.backend.kernel_product(&w)?;
            em.products += 1;
            let moving = moved(source, &gw);
            State {
                w,
                gw,
                moving,
                sigma2: start.sigma2,
            }
        }
    };
    let mut history = vec![first.sigma2];
    let mut at = em.evaluate(first)?;
    let mut stop = Stop::Iterations;
    let (mut iterations, mut jumps) = (0, 0);
    // The longest extrapolation tried (SQUAREM's step bound), grown while jumps pay off.
    let mut longest = 4.0;
    loop {
        if at.state.sigma2 <= floor {
            stop = Stop::Exact;
            break;
        }
        if iterations == params.max_iterations {
            break;
        }
        // A plain EM step: E-step (done), M-step, and the E-step at the result.
        let next = em.update(&at)?;
        let first = em.evaluate(next)?;
        iterations += 1;
        on_iteration(iterations, first.state.sigma2);
        match Progress::of(&at, &first, params.tolerance, radius) {
            Progress::Rose => {
                iterations -= 1;
                stop = Stop::Precision;
                break;
            }
            Progress::Converged => {
                (at, stop) = (first, Stop::Converged);
                history.push(at.state.sigma2);
                break;
            }
            Progress::Lowered => {}
        }
        // Jumps only in the fine phase (sigma below about 3% of the radius): while sigma^2
        // is large the correspondences change wholesale, and a jump there can settle in
        // another optimum than plain EM's (it did, at 2x the error, on 300 points in a cube).
        let fine = first.state.sigma2 < FINE * initial;
        if !params.accelerate || !fine || iterations == params.max_iterations {
            at = first;
            history.push(at.state.sigma2);
            continue;
        }
        // A second step, and SQUAREM's jump from both (Varadhan & Roland 2008): with
        // r = t1 - t0 and v = t2 - 2 t1 + t0 over the displacements G W, to
        // t0 - 2 a r + a^2 v, a = -|r| / |v| (at most -1: a = -1 is t2 itself). EM crawls
        // where the sets slide along each other (dense surfaces: 240 iterations at 2e4
        // points); the jump follows that slide many steps at once. It is kept only if it
        // lowers the objective below t1's; else the plain second step stands.
        let second = em.update(&first)?;
        iterations += 1;
        let jump = extrapolate(&at.state, &first.state, &second, longest, source)
            .filter(|jump| jump.state.sigma2.is_finite() && jump.state.sigma2 > floor);
        if let Some(jump) = jump {
            let jumped = em.evaluate(jump.state)?;
            if jumped.objective < first.objective {
                jumps += 1;
                if jump.alpha <= -longest {
                    longest = (4.0 * longest).min(LONGEST_JUMP);
                }
                at = jumped;
                history.push(at.state.sigma2);
                on_iteration(iterations, at.state.sigma2);
                continue;
            }
            longest = (longest / 4.0).max(1.0);
        }
        history.push(first.state.sigma2);
        let second = em.evaluate(second)?;
        on_iteration(iterations, second.state.sigma2);
        match Progress::of(&first, &second, params.tolerance, radius) {
            Progress::Rose => {
                iterations -= 1;
                (at, stop) = (first, Stop::Precision);
                break;
            }
            Progress::Converged => {
                (at, stop) = (second, Stop::Converged);
                history.push(at.state.sigma2);
                break;
            }
            Progress::Lowered => {
                at = second;
                history.push(at.state.sigma2);
            }
        }
    }
    let (products, limited) = (em.products, em.limited);
    let state = at.state;
    let State { w, moving, .. } = state;
    if moving.iter().any(|p| !p.is_finite()) {
        return Err(Error::InvalidInput(
            "CPD diverged to non-finite points".into(),
        ));
    }
    Ok(CpdResult {
        deformed: moving,
        w: to_points(&w),
        sigma2: history,
        iterations,
        stop,
        seconds: started.elapsed().as_secs_f64(),
        products,
        limited,
        jumps,
        coarse_points: 0,
        coarse_iterations: 0,
    })
}

/// A coarse stage's size that works ([`CpdParams::coarse`], `vkdr cpd --coarse`).
/// Measured on the peers' noise-free sets (mean error in source radii, seconds, one stage
/// against a coarse stage of 5000 points, lavapipe): 2e4 points 5.7e-4 / 19 s against
/// 5.8e-5 / 5.6 s, and on another seed 5.4e-5 / 21 s against 4.4e-5 / 9.7 s; 5e4 points
/// 4.4e-6 / 138 s against 1.0e-4 / 50 s, and 3.3e-4 / 164 s against 3.7e-3 / 54 s; 1e5
/// points 7.6e-3 / 602 s against 9.4e-3 / 214 s. Faster every time, more accurate at 2e4,
/// less at 5e4: the subsets' points do not correspond (the coarse field is right only to
/// a few of the full sets' spacings, 0.06 radii at 1e5), so the full sets still slide
/// into place, and on noise-free sets a region that is still sliding when most points
/// match exactly (sigma^2 collapses) sees no target within reach and freezes. Hence an
/// option, not the default.
pub const COARSE_POINTS: usize = 5000;

/// The coarse stage: CPD of `k` source points and as large a share of the target (fixed
/// pseudo-random subsets), then that field as the full registration's start: W is the
/// coarse W on the chosen source points and 0 elsewhere, so G W is the coarse field
/// exactly; sigma^2 starts at the larger of the coarse end and (a third of the target's
/// median point spacing)^2, near enough for every point to find its own target first.
pub fn coarse_start<B: Backend>(
    make_backend: &impl Fn(&[DVec3], &[DVec3]) -> Result<B>,
    source: &[DVec3],
    target: &[DVec3],
    params: &CpdParams,
    k: usize,
    on_iteration: &mut dyn FnMut(usize, f64),
) -> Result<(Start, CpdResult)> {
    let (m, n) = (source.len(), target.len());
    let chosen_y = subset(m, k);
    let chosen_x = subset(n, (n * k).div_ceil(m).clamp(1, n));
    let y: Vec<DVec3> = chosen_y.iter().map(|&i| source[i]).collect();
    let x: Vec<DVec3> = chosen_x.iter().map(|&i| target[i]).collect();
    let mut backend = make_backend(&y, &x)?;
    let one_stage = CpdParams {
        coarse: None,
        ..*params
    };
    let coarse = run(&mut backend, &y, &x, &one_stage, on_iteration)?;
    let mut w = vec![DVec3::ZERO; m];
    for (&i, &c) in chosen_y.iter().zip(&coarse.w) {
        w[i] = c;
    }
    let end = coarse.sigma2.last().copied().unwrap_or(0.0);
    let sigma2 = end.max((median_spacing(target) / 3.0).powi(2));
    Ok((Start { w, sigma2 }, coarse))
}

/// `k` of the indices 0..n (all when k >= n), a fixed pseudo-random choice, ascending.
fn subset(n: usize, k: usize) -> Vec<usize> {
    let mut order: Vec<(u64, usize)> = (0..n).map(|i| (splitmix(i as u64), i)).collect();
    order.sort_unstable();
    let mut chosen: Vec<usize> = order.into_iter().take(k).map(|(_, i)| i).collect();
    chosen.sort_unstable();
    chosen
}

fn splitmix(seed: u64) -> u64 {
    let mut z = seed.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The median distance from a point of `points` to its nearest other point, over up to
/// 1000 of them (brute force; duplicates count as 0).
fn median_spacing(points: &[DVec3]) -> f64 {
    let mut nearest: Vec<f64> = subset(points.len(), 1000)
        .into_iter()
        .map(|i| {
            points
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, q)| q.distance_squared(points[i]))
                .fold(f64::INFINITY, f64::min)
                .sqrt()
        })
        .filter(|d| d.is_finite())
        .collect();
    nearest.sort_by(f64::total_cmp);
    nearest.get(nearest.len() / 2).copied().unwrap_or(0.0)
}

/// One EM iteration's parts, over the device (or the reference).
struct Em<'a> {
    backend: &'a mut dyn Backend,
    m_step: &'a MStep,
    params: &'a CpdParams,
    source: &'a [DVec3],
    /// Target points.
    n: usize,
    /// The least sigma^2 (1e-12 of the initial one).
    floor: f64,
    products: usize,
    limited: usize,
}

/// A state with its E-step and objective.
struct Evaluated {
    state: State,
    e: Expectation,
    objective: f64,
}

impl Em<'_> {
    /// The E-step at `state`, and the objective EM lowers at every iteration: the negative
    /// log-likelihood (up to constants) plus the smoothness term lambda/2 tr(W^T G W).
    fn evaluate(&mut self, state: State) -> Result<Evaluated> {
        let (m, n, w) = (self.source.len() as f64, self.n as f64, self.params.w);
        let log_c = 1.5 * (2.0 * std::f64::consts::PI * state.sigma2).ln()
            + (w / (1.0 - w)).ln()
            + (m / n).ln();
        let e = self
            .backend
            .expectation(&state.moving, state.sigma2, log_c)?;
        check_expectation(&e)?;
        let objective = -e.log_denominators
            + 1.5 * n * state.sigma2.ln()
            + 0.5 * self.params.lambda * frobenius(&state.w, &state.gw);
        Ok(Evaluated {
            state,
            e,
            objective,
        })
    }

    /// The M-step from an evaluated state: W solves (dP1 G + lambda sigma^2 I) W =
    /// PX - dP1 Y, then sigma^2 for the moved points.
    fn update(&mut self, at: &Evaluated) -> Result<State> {
        let (source, e, start) = (self.source, &at.e, &at.state);
        let s = self.params.lambda * start.sigma2;
        let (mut w, mut gw) = (start.w.clone(), start.gw.clone());
        let solved =
            self.m_step
                .solve(self.backend, e, source, &start.moving, s, &mut w, &mut gw)?;
        self.products += solved.products;
        self.limited += usize::from(solved.limited);
        let moving = moved(source, &gw);
        // sigma^2 = sum_mn P_mn |x_n - t'_m|^2 / (3 sum P) at the moved points t' = t + d,
        // from the E-step's differences: |x - t'|^2 = |x - t|^2 - 2 (x - t).d + |d|^2.
        let np: f64 = e.p1.iter().sum();
        let spread: f64 = (0..source.len())
            .map(|i| {
                let d = moving[i] - start.moving[i];
                e.spread[i] - 2.0 * e.pull[i].dot(d) + e.p1[i] * d.length_squared()
            })
            .sum();
        let mut sigma2 = if np > 0.0 {
            spread / (3.0 * np)
        } else {
            start.sigma2
        };
        if !sigma2.is_finite() || sigma2 <= self.floor {
            sigma2 = self.floor.max(f64::MIN_POSITIVE);
        }
        Ok(State {
            w,
            gw,
            moving,
            sigma2,
        })
    }
}

/// How the objective moved from one evaluated state to the next.
enum Progress {
    /// It rose, which exact EM never does: the device's precision is reached.
    Rose,
    /// It fell by less than the tolerance (relative), and the points moved by less than
    /// the tolerance (on average, in units of the source's RMS radius).
    Converged,
    Lowered,
}

impl Progress {
    /// The objective alone stops a dense set too early: where its surface slides along
    /// the target's, each iteration lowers an objective of N terms by a tiny fraction
    /// while every point still moves (1e5 points stopped at a mean error of 0.084 radii
    /// after 50 iterations; run on, 0.0078 after 604). So the points must have stopped
    /// too.
    fn of(before: &Evaluated, after: &Evaluated, tolerance: f64, radius: f64) -> Self {
        let (a, b) = (before.objective, after.objective);
        if b > a {
            return Progress::Rose;
        }
        let (from, to) = (&before.state.moving, &after.state.moving);
        let moved = from
            .iter()
            .zip(to)
            .map(|(p, q)| p.distance(*q))
            .sum::<f64>()
            / from.len().max(1) as f64;
        if a - b <= tolerance * b.abs() && moved <= tolerance * radius {
            Progress::Converged
        } else {
            Progress::Lowered
        }
    }
}

/// Y + G W.
fn moved(source: &[DVec3], gw: &Matrix) -> Vec<DVec3> {
    source
        .iter()
        .enumerate()
        .map(|(i, y)| *y + DVec3::new(gw.at(i, 0), gw.at(i, 1), gw.at(i, 2)))
        .collect()
}

/// The longest SQUAREM step a (in units of the plain step).
const LONGEST_JUMP: f64 = 256.0;
/// SQUAREM jumps only once sigma^2 is below this fraction of its initial value.
const FINE: f64 = 1e-3;
/// The least cosine between two successive EM steps (over G W) for a jump.
const STRAIGHT: f64 = 0.9;

/// SQUAREM's extrapolated state from three successive ones, and its step a.
struct Jump {
    state: State,
    alpha: f64,
}

/// t0 - 2 a r + a^2 v for W, G W and log sigma^2, with r = t1 - t0, v = t2 - 2 t1 + t0 and
/// a = -|r| / |v| over G W, clamped to [-longest, -1]; `None` where the two steps are not
/// in a linear regime (their directions differ by more than [`STRAIGHT`]: early on, while
/// correspondences change wholesale, a jump can land in another basin) or there is
/// nothing to extrapolate.
fn extrapolate(t0: &State, t1: &State, t2: &State, longest: f64, source: &[DVec3]) -> Option<Jump> {
    let (mut r, mut v, mut r2, mut along) = (0.0, 0.0, 0.0, 0.0);
    for k in 0..t0.gw.data.len() {
        let (a, b, c) = (t0.gw.data[k], t1.gw.data[k], t2.gw.data[k]);
        r += (b - a) * (b - a);
        v += (c - 2.0 * b + a) * (c - 2.0 * b + a);
        r2 += (c - b) * (c - b);
        along += (b - a) * (c - b);
    }
    if !(v > 0.0 && r > 0.0 && along >= STRAIGHT * (r * r2).sqrt()) {
        return None;
    }
    let alpha = -(r / v).sqrt().clamp(1.0, longest);
    let at = |a: f64, b: f64, c: f64| a - 2.0 * alpha * (b - a) + alpha * alpha * (c - 2.0 * b + a);
    let mix = |a: &Matrix, b: &Matrix, c: &Matrix| Matrix {
        rows: a.rows,
        cols: a.cols,
        data: (0..a.data.len())
            .map(|k| at(a.data[k], b.data[k], c.data[k]))
            .collect(),
    };
    let gw = mix(&t0.gw, &t1.gw, &t2.gw);
    let sigma2 = at(t0.sigma2.ln(), t1.sigma2.ln(), t2.sigma2.ln()).exp();
    Some(Jump {
        state: State {
            w: mix(&t0.w, &t1.w, &t2.w),
            moving: moved(source, &gw),
            gw,
            sigma2,
        },
        alpha,
    })
}

/// What one iteration starts from.
#[derive(Clone)]
struct State {
    w: Matrix,
    /// G W.
    gw: Matrix,
    /// Y + G W.
    moving: Vec<DVec3>,
    sigma2: f64,
}

/// sum_ij a_ij b_ij.
fn frobenius(a: &Matrix, b: &Matrix) -> f64 {
    a.data.iter().zip(&b.data).map(|(x, y)| x * y).sum()
}

/// Sum P1 and sum Pt1 both add up every P_mn, once by source and once by target: a
/// device that dropped terms (a driver's loop limit, a lost dispatch) shows as a mismatch.
fn check_expectation(e: &Expectation) -> Result<()> {
    let by_source: f64 = e.p1.iter().sum();
    let by_target: f64 = e.pt1.iter().sum();
    let allowed = 1e-3 * by_source.max(by_target) + 1e-5 * e.pt1.len() as f64;
    if (by_source - by_target).abs() <= allowed {
        return Ok(());
    }
    Err(Error::Limit(format!(
        "CPD's E-step does not add up: sum P1 = {by_source:e} but sum Pt1 = {by_target:e} \
         (the device dropped terms)"
    )))
}

fn check_points(points: &[DVec3], what: &str) -> Result<()> {
    if points.is_empty() {
        return Err(Error::InvalidInput(format!(
            "the {what} point set is empty"
        )));
    }
    if let Some(i) = points.iter().position(|p| !p.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "{what} point {i} is not finite: {:?}",
            points[i]
        )));
    }
    // Several points, every one the same (or all within float64 rounding of one): no size
    // to normalise by, no shape to register. (One point alone is a legitimate tiny set.)
    let first = points[0];
    let spread = points
        .iter()
        .map(|p| (*p - first).abs().max_element())
        .fold(0.0, f64::max);
    if points.len() > 1 && spread <= 1e-12 * first.abs().max_element().max(1e-300) {
        return Err(Error::InvalidInput(format!(
            "the {what} points are all the same point {first:?}: CPD needs a shape"
        )));
    }
    Ok(())
}

/// The joint normalisation: centroid and RMS radius of the source.
#[derive(Clone, Copy, Debug)]
pub struct Normalization {
    /// Centroid of the source.
    pub mean: DVec3,
    /// RMS radius of the source about its centroid (1 where that is 0 or not
    /// finite).
    pub scale: f64,
}

impl Normalization {
    /// The normalisation of `source`.
    pub fn of(source: &[DVec3]) -> Self {
        let mean = centroid(source);
        let rms = (source
            .iter()
            .map(|p| (*p - mean).length_squared())
            .sum::<f64>()
            / source.len().max(1) as f64)
            .sqrt();
        Self {
            mean,
            scale: if rms > 0.0 && rms.is_finite() {
                rms
            } else {
                1.0
            },
        }
    }

    /// `points` relative to `mean`, in units of `scale`.
    pub fn apply(&self, points: &[DVec3]) -> Vec<DVec3> {
        points
            .iter()
            .map(|p| (*p - self.mean) / self.scale)
            .collect()
    }
}

/// Normalises, runs CPD with the backend made for the normalised sets, maps back.
pub fn run_normalized<B: Backend>(
    make_backend: impl Fn(&[DVec3], &[DVec3]) -> Result<B>,
    source: &[DVec3],
    target: &[DVec3],
    params: &CpdParams,
    on_iteration: &mut dyn FnMut(usize, f64),
) -> Result<CpdResult> {
    params.validate()?;
    check_points(source, "source")?;
    check_points(target, "target")?;
    let started = Instant::now();
    let norm = Normalization::of(source);
    let (y, x) = (norm.apply(source), norm.apply(target));
    let coarse_k = params
        .coarse
        .filter(|&k| params.rank.is_none() && y.len() > 2 * k);
    let (start, coarse) = match coarse_k {
        Some(k) => {
            let (start, coarse) = coarse_start(&make_backend, &y, &x, params, k, on_iteration)?;
            (Some(start), Some((k, coarse)))
        }
        None => (None, None),
    };
    let mut backend = make_backend(&y, &x)?;
    let offset = coarse.as_ref().map_or(0, |(_, c)| c.iterations);
    let mut result = run_from(&mut backend, &y, &x, params, start, &mut |i, s| {
        on_iteration(offset + i, s)
    })?;
    if let Some((k, coarse)) = coarse {
        result.coarse_points = k;
        result.coarse_iterations = coarse.iterations;
        result.iterations += coarse.iterations;
        result.products += coarse.products;
        result.limited += coarse.limited;
        result.jumps += coarse.jumps;
        result.sigma2.splice(0..0, coarse.sigma2);
        result.seconds = started.elapsed().as_secs_f64();
    }
    for p in &mut result.deformed {
        *p = *p * norm.scale + norm.mean;
    }
    for w in &mut result.w {
        *w *= norm.scale;
    }
    Ok(result)
}

/// Registers `source` onto `target` with the E-step and kernel products on the device.
pub fn register(
    ctx: &Context,
    pipelines: &CpdPipelines,
    source: &[DVec3],
    target: &[DVec3],
    params: &CpdParams,
    on_iteration: &mut dyn FnMut(usize, f64),
) -> Result<CpdResult> {
    let make = |y: &[DVec3], x: &[DVec3]| GpuBackend::new(ctx, pipelines, y, x, params.beta);
    run_normalized(make, source, target, params, on_iteration)
}
