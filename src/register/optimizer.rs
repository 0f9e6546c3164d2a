//! The optimisers of the registration loop, with their state and shaders: SGD with
//! momentum or Adam (`glsl/optimizer.comp`) and quasi-Newton BFGS over the code and the
//! pose (`glsl/bfgs.comp`). Each step runs on the device in one invocation, reading the
//! loss and the gradients the loop left; the state's layout is decided here
//! ([`StateLayout`]) and passed to the shaders. The loop (`super`) records the steps and
//! reads the point back; adding an optimiser touches this module and its shader.

use bytemuck::{Pod, Zeroable};
use glam::{DMat3, DVec3};

use super::{Gravity, RegisterParams, CODE_BOUND};
use crate::cpd::linalg::{self, Matrix};
use crate::error::{Error, Result};
use crate::gpu::{Binding, ComputePipeline, Context, Groups, Recorder};
use crate::shaders;
use crate::shape::ShapeSpace;
use crate::Pose;

/// How the latent code (and the pose) are updated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Optimizer {
    /// SGD with momentum and learning-rate decay (the paper's); with pose optimisation the
    /// pose takes its own SGD steps once every `pose_every` iterations.
    Sgd,
    /// Adam for the latent code (the pose as with SGD).
    Adam,
    /// Quasi-Newton (BFGS with a halving backtrack) over the code and the pose together;
    /// momentum, decay and `pose_every` do not apply.
    Bfgs,
}

impl Optimizer {
    /// The lower-case name that `from_str` parses (`sgd`, `adam`, `bfgs`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Sgd => "sgd",
            Self::Adam => "adam",
            Self::Bfgs => "bfgs",
        }
    }
}

impl std::str::FromStr for Optimizer {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "sgd" => Ok(Self::Sgd),
            "adam" => Ok(Self::Adam),
            "bfgs" => Ok(Self::Bfgs),
            other => Err(Error::InvalidInput(format!(
                "unknown optimizer '{other}' (sgd, adam, bfgs)"
            ))),
        }
    }
}

/// The quasi-Newton shader's state size limit (glsl/bfgs.comp MAX_N): code and pose. One
/// invocation runs the whole step, about 3 n^2 + k^3 / 6 loop iterations (n = dims + 6, k
/// codes held on their bound): some 57 000 at 58 dims, within lavapipe's
/// [`LOOP_LIMIT`](crate::gpu::LOOP_LIMIT), which 62 dims would pass.
pub(super) const BFGS_MAX_DIMS: usize = 64 - 6;
/// The most latent dimensions of the other optimisers: their shaders loop over the code
/// a few times in one invocation (and no shape space from a few dozen meshes has more).
pub(super) const MAX_DIMS: usize = 4096;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(super) struct OptimizerConstants {
    dims: u32,
    pose_every: u32,
    optimize_z: u32,
    adam: u32,
    momentum: f32,
    decay: f32,
    latent_step: f32,
    translation_step: f32,
    rotation_step: f32,
    max_iterations: u32,
    pose_only: u32,
    code_prior: f32,
    layout: StateLayout,
}
const _: () = assert!(shaders::OPTIMIZER_COMP.takes::<OptimizerConstants>());
const _: () = assert!(shaders::BFGS_COMP.takes::<OptimizerConstants>());

/// Where each part of the optimiser state lives (float offsets into the state buffer),
/// decided here once and passed to `glsl/optimizer.comp` and `glsl/bfgs.comp` with their
/// push constants. Slots 0-7 are the shaders' own scalars (iteration count, step lengths);
/// the code, then each optimiser's vectors, the loss and code of every iteration, and the
/// quasi-Newton region follow.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(super) struct StateLayout {
    /// The latent code (dims).
    pub(super) latent: u32,
    /// SGD momentum or Adam's first moment (dims), Adam's second moment (dims), the
    /// pose's momentum (6).
    pub(super) velocity: u32,
    pub(super) second_moment: u32,
    pub(super) pose_velocity: u32,
    /// The loss before each iteration (iterations), the code after it (iterations x dims).
    pub(super) losses: u32,
    pub(super) codes: u32,
    /// Quasi-Newton: the accepted loss, halvings in a row, R0 (9), t0 (3), the pose part of
    /// x (6), the accepted x (n = dims + 6), its gradient (n), H (n x n), scratch for the
    /// active set's factor (n x n).
    pub(super) accepted_loss: u32,
    pub(super) halvings: u32,
    pub(super) r0: u32,
    pub(super) t0: u32,
    pub(super) pose_x: u32,
    pub(super) accepted: u32,
    pub(super) accepted_grad: u32,
    pub(super) h: u32,
    pub(super) scratch: u32,
    /// What the optimisers add to the images' loss (`glsl/include/objective.glsl`): the
    /// code prior's matrix P (dims x dims, row-major); each code coordinate's bound (dims,
    /// [`CodeCoordinates::bound`]); and gravity (up axis, direction, tolerance, on: 8
    /// floats). Written by [`StateLayout::initial`].
    pub(super) prior: u32,
    pub(super) bound: u32,
    pub(super) gravity: u32,
    /// Floats in all.
    pub(super) len: u32,
}

impl StateLayout {
    pub(super) fn new(dims: usize, iterations: usize) -> Self {
        let (d, it, n) = (dims as u32, iterations as u32, dims as u32 + 6);
        let latent = 8;
        let losses = latent + 3 * d + 6;
        let codes = losses + it;
        let qn = codes + it * d;
        let accepted = qn + 20;
        let h = accepted + 2 * n;
        Self {
            latent,
            velocity: latent + d,
            second_moment: latent + 2 * d,
            pose_velocity: latent + 3 * d,
            losses,
            codes,
            accepted_loss: qn,
            halvings: qn + 1,
            r0: qn + 2,
            t0: qn + 11,
            pose_x: qn + 14,
            accepted,
            accepted_grad: accepted + n,
            h,
            scratch: h + n * n,
            prior: h + 2 * n * n,
            bound: h + 2 * n * n + d * d,
            gravity: h + 2 * n * n + d * d + d,
            len: h + 2 * n * n + d * d + d + 8,
        }
    }

    /// The state before the first iteration: zeros, but for the code prior's matrix
    /// (`prior`, dims x dims), the code coordinates' bounds (`bound`, dims) and gravity.
    pub(super) fn initial(
        &self,
        prior: &Matrix,
        bound: &[f64],
        gravity: Option<&Gravity>,
    ) -> Vec<f32> {
        let mut state = vec![0f32; self.len as usize];
        let at = self.prior as usize;
        for (i, v) in prior.data.iter().enumerate() {
            state[at + i] = *v as f32;
        }
        let at = self.bound as usize;
        for (i, v) in bound.iter().enumerate() {
            state[at + i] = *v as f32;
        }
        if let Some(g) = gravity {
            let (up, direction) = (g.up.normalize(), g.direction.normalize());
            let values = [
                up.x,
                up.y,
                up.z,
                direction.x,
                direction.y,
                direction.z,
                g.tolerance,
                1.0,
            ];
            let at = self.gravity as usize;
            for (i, v) in values.into_iter().enumerate() {
                state[at + i] = v as f32;
            }
        }
        state
    }
}

impl OptimizerConstants {
    /// With `pose_only`, the latent code stays where it is.
    pub(super) fn new(dims: usize, params: &RegisterParams, pose_only: bool) -> Self {
        Self {
            dims: dims as u32,
            pose_every: params.pose_every as u32,
            optimize_z: params.optimize_z as u32,
            adam: (params.optimizer == Optimizer::Adam) as u32,
            momentum: params.momentum as f32,
            decay: params.decay as f32,
            latent_step: params.latent_step as f32,
            translation_step: params.translation_step as f32,
            rotation_step: params.rotation_step as f32,
            max_iterations: params.iterations as u32,
            pose_only: pose_only as u32,
            code_prior: params.code_prior as f32,
            layout: StateLayout::new(dims, params.iterations),
        }
    }
}

/// The optimisers' pipelines.
pub(super) struct Optimizers {
    /// SGD with momentum, or Adam (`adam` in the push constants).
    step: ComputePipeline,
    bfgs: ComputePipeline,
}

impl Optimizers {
    pub(super) fn new(ctx: &Context) -> Result<Self> {
        Ok(Self {
            step: ComputePipeline::new(ctx, &shaders::OPTIMIZER_COMP)?,
            bfgs: ComputePipeline::new(ctx, &shaders::BFGS_COMP)?,
        })
    }

    /// Records one step of `optimizer`: bindings state, dL/dz, the pose gradient, the loss
    /// stats and the views (whose first pose the step moves).
    pub(super) fn record_step(
        &self,
        rec: &mut Recorder,
        constants: &OptimizerConstants,
        optimizer: Optimizer,
        bindings: [Binding; 5],
    ) {
        let pipeline = match optimizer {
            Optimizer::Sgd | Optimizer::Adam => &self.step,
            Optimizer::Bfgs => &self.bfgs,
        };
        rec.run_compute(pipeline, &bindings, constants, Groups::Count(1, 1, 1));
    }
}

impl StateLayout {
    /// The pose of BFGS's last accepted point, from the state's values: t = t0 + x_t,
    /// R = exp([w]x) R0.
    pub(super) fn bfgs_pose(&self, values: &[f32], k: usize) -> Pose {
        let at = |offset: u32| offset as usize;
        let x = &values[at(self.accepted)..at(self.accepted) + k + 6];
        let r0 = at(self.r0);
        let t0 = at(self.t0);
        let initial = DMat3::from_cols_array(&std::array::from_fn(|i| values[r0 + i] as f64));
        let t0 = DVec3::from_array(std::array::from_fn(|i| values[t0 + i] as f64));
        let w = DVec3::new(x[k + 3] as f64, x[k + 4] as f64, x[k + 5] as f64);
        let rotation = DMat3::from_quat(glam::DQuat::from_scaled_axis(w)) * initial;
        Pose {
            translation: t0 + DVec3::new(x[k] as f64, x[k + 1] as f64, x[k + 2] as f64),
            rotation: glam::DQuat::from_mat3(&rotation).to_scaled_axis(),
        }
    }
}

/// The optimiser's coordinates z of the latent code (s = `to_code` z) and each one's
/// bound.
pub(super) struct CodeCoordinates {
    /// A: the latent code s = A z.
    pub(super) to_code: Matrix,
    /// The largest |z| of each coordinate ([`CODE_BOUND`] of its units).
    pub(super) bound: Vec<f64>,
}

/// The optimiser's coordinates of the latent code. For SGD and Adam each z is one
/// dimension's training standard deviation (the paper's units). For BFGS the columns of
/// B A are orthogonal in vertex space and all of one length, the RMS of the training
/// deformations, so that the quasi-Newton steps start well conditioned: the latent
/// dimensions of a PCA over W can be strongly correlated in vertex space (0.97 for two of a
/// bottle's). They are the eigenvectors of the vertex-space Gram matrix of the code in
/// standard deviations (u = s / sd: D B^T B D), so that they are orthogonal in u too and
/// the code prior is diagonal in them. A BFGS coordinate on its bound is 3 RMS deformations
/// along it: 3 training standard deviations or more (more where the direction moves the
/// surface little per standard deviation). A bound of 3 standard deviations held fits
/// short of their test instances, whose own codes lie up to 8.8 out; one of 10 let the
/// depth fits run away (docs/method.md).
pub(super) fn optimizer_coordinates(space: &ShapeSpace, optimizer: Optimizer) -> CodeCoordinates {
    let k = space.dims();
    let sd = space.code_deviations();
    let mut to_code = Matrix::zeros(k, k);
    if optimizer != Optimizer::Bfgs {
        for (j, &d) in sd.iter().enumerate() {
            to_code.set(j, j, d);
        }
        return CodeCoordinates {
            to_code,
            bound: vec![CODE_BOUND; k],
        };
    }
    let basis = &space.deformation_basis;
    let mut gram = Matrix::zeros(k, k);
    for i in 0..k {
        for j in 0..k {
            let dot: f64 = basis[i].iter().zip(&basis[j]).map(|(a, b)| a * b).sum();
            gram.set(i, j, sd[i] * dot * sd[j]);
        }
    }
    // The mean squared training deformation |B s|^2.
    let t = (space.training_codes.len() as f64 - 1.0).max(1.0);
    let spread = space
        .training_codes
        .iter()
        .map(|c| {
            let u: Vec<f64> = c.iter().zip(&sd).map(|(s, d)| s / d).collect();
            (0..k)
                .flat_map(|i| (0..k).map(move |j| (i, j)))
                .map(|(i, j)| u[i] * gram.at(i, j) * u[j])
                .sum::<f64>()
        })
        .sum::<f64>()
        / t;
    let (values, vectors) = linalg::symmetric_eigen(&gram);
    let floor = 1e-12 * values.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let mut bound = Vec::with_capacity(k);
    for c in 0..k {
        // z_c is `scale` training standard deviations along the direction.
        let scale = spread.sqrt() / values[c].max(floor).sqrt();
        for j in 0..k {
            to_code.set(j, c, sd[j] * vectors.at(j, c) * scale);
        }
        bound.push(CODE_BOUND);
    }
    CodeCoordinates { to_code, bound }
}

/// The code prior's matrix P in the optimiser's coordinates (s = `to_code` z):
/// A^T diag(1 / sd^2) A, so that z^T P z is |s|^2 in training standard deviations;
/// `dims` rows and columns, those past the space's dimensions (a scale coordinate) zero.
pub(super) fn prior_matrix(space: &ShapeSpace, to_code: &Matrix, dims: usize) -> Matrix {
    let k = space.dims();
    let precision: Vec<f64> = space
        .code_deviations()
        .iter()
        .map(|sd| 1.0 / (sd * sd))
        .collect();
    let mut p = Matrix::zeros(dims, dims);
    for a in 0..k {
        for b in 0..k {
            let v = (0..k)
                .map(|j| to_code.at(j, a) * precision[j] * to_code.at(j, b))
                .sum();
            p.set(a, b, v);
        }
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::Buffer;
    use crate::raster::View;
    use crate::raster::ViewBuffers;
    use crate::rng::Rng;
    use crate::shape::random_space;
    use crate::Camera;

    /// `glsl/bfgs.comp` in float64: the state of one quasi-Newton run over x (code, then
    /// translation and rotation offsets), fed the loss and gradient at each new point.
    struct BfgsReference {
        steps: [f64; 3],
        dims: usize,
        /// Each code coordinate's bound.
        bound: Vec<f64>,
        x: Vec<f64>,
        accepted: Vec<f64>,
        accepted_grad: Vec<f64>,
        accepted_loss: f64,
        h: Vec<Vec<f64>>,
        t: usize,
        /// How often a step was capped, how often one was halved, and how often a
        /// direction held a code coordinate on its bound.
        capped: usize,
        halved: usize,
        held: usize,
    }

    impl BfgsReference {
        fn new(bound: &[f64], steps: [f64; 3]) -> Self {
            let dims = bound.len();
            let n = dims + 6;
            Self {
                steps,
                dims,
                bound: bound.to_vec(),
                x: vec![0.0; n],
                accepted: vec![0.0; n],
                accepted_grad: vec![0.0; n],
                accepted_loss: f64::INFINITY,
                h: vec![vec![0.0; n]; n],
                t: 0,
                capped: 0,
                halved: 0,
                held: 0,
            }
        }

        /// The model's minimum with the code coordinates on their bound (gradient
        /// pushing out) held: d = -u + H[:, A] H_AA^-1 u_A, u = H g_F.
        fn direction(&mut self, g: &[f64]) -> Vec<f64> {
            let n = self.x.len();
            let held: Vec<usize> = (0..self.dims)
                .filter(|&i| {
                    let (x, b) = (self.x[i], self.bound[i]);
                    (x >= b && g[i] < 0.0) || (x <= -b && g[i] > 0.0)
                })
                .collect();
            let free_g: Vec<f64> = (0..n)
                .map(|i| if held.contains(&i) { 0.0 } else { g[i] })
                .collect();
            let u: Vec<f64> = (0..n)
                .map(|i| (0..n).map(|j| self.h[i][j] * free_g[j]).sum())
                .collect();
            let mut d: Vec<f64> = u.iter().map(|v| -v).collect();
            if held.is_empty() {
                return d;
            }
            self.held += 1;
            use crate::cpd::linalg::{solve, Matrix};
            let k = held.len();
            let h_aa = Matrix {
                rows: k,
                cols: k,
                data: held
                    .iter()
                    .flat_map(|&a| held.iter().map(move |&b| (a, b)))
                    .map(|(a, b)| self.h[a][b])
                    .collect(),
            };
            let u_a = Matrix {
                rows: k,
                cols: 1,
                data: held.iter().map(|&i| u[i]).collect(),
            };
            let lambda = solve(h_aa, u_a).unwrap().data;
            for (i, di) in d.iter_mut().enumerate() {
                *di += held
                    .iter()
                    .zip(&lambda)
                    .map(|(&a, l)| self.h[i][a] * l)
                    .sum::<f64>();
            }
            for &a in &held {
                d[a] = 0.0;
            }
            d
        }

        fn part(&self, i: usize) -> usize {
            if i < self.dims {
                0
            } else if i < self.dims + 3 {
                1
            } else {
                2
            }
        }

        /// One iteration with the loss and gradient (z translation masked) at `self.x`.
        fn step(&mut self, loss: f64, mut g: Vec<f64>) {
            let n = self.x.len();
            g[self.dims + 2] = 0.0;
            if self.t == 0 {
                let mut norms = [0.0; 3];
                for (i, gi) in g.iter().enumerate() {
                    norms[self.part(i)] += gi * gi;
                }
                for i in 0..n {
                    if i != self.dims + 2 {
                        let norm = norms[self.part(i)].sqrt();
                        self.h[i][i] = self.steps[self.part(i)] / norm;
                    }
                }
            }
            let s: Vec<f64> = (0..n).map(|i| self.x[i] - self.accepted[i]).collect();
            let predicted: f64 = (0..n).map(|i| self.accepted_grad[i] * s[i]).sum();
            if self.t == 0 || loss <= self.accepted_loss + 1e-4 * predicted {
                let y: Vec<f64> = (0..n).map(|i| g[i] - self.accepted_grad[i]).collect();
                let sy: f64 = (0..n).map(|i| s[i] * y[i]).sum();
                if self.t > 0 && sy > 1e-12 {
                    let hy: Vec<f64> = (0..n)
                        .map(|i| (0..n).map(|j| self.h[i][j] * y[j]).sum())
                        .collect();
                    let yhy: f64 = (0..n).map(|i| y[i] * hy[i]).sum();
                    for i in 0..n {
                        for j in 0..n {
                            self.h[i][j] += (sy + yhy) * s[i] * s[j] / (sy * sy)
                                - (hy[i] * s[j] + s[i] * hy[j]) / sy;
                        }
                    }
                }
                self.accepted = self.x.clone();
                self.accepted_grad = g.clone();
                self.accepted_loss = loss;
                let d = self.direction(&g);
                let mut lengths = [0.0; 3];
                for (i, di) in d.iter().enumerate() {
                    lengths[self.part(i)] += di * di;
                }
                let scale = (0..3)
                    .map(|p| (2.0 * self.steps[p] / f64::sqrt(lengths[p])).min(1.0))
                    .fold(1.0, f64::min);
                self.capped += (scale < 1.0) as usize;
                for i in 0..n {
                    self.x[i] += scale * d[i];
                }
            } else {
                self.halved += 1;
                for i in 0..n {
                    self.x[i] = self.accepted[i] + 0.5 * (self.x[i] - self.accepted[i]);
                }
            }
            for (xi, b) in self.x[..self.dims].iter_mut().zip(&self.bound) {
                *xi = xi.clamp(-b, *b);
            }
            self.t += 1;
        }
    }

    fn skew(w: DVec3) -> DMat3 {
        DMat3::from_cols(
            DVec3::new(0.0, w.z, -w.y),
            DVec3::new(-w.z, 0.0, w.x),
            DVec3::new(w.y, -w.x, 0.0),
        )
    }

    /// The left Jacobian of the rotation exponential.
    fn left_jacobian(w: DVec3) -> DMat3 {
        let a = w.length();
        let k = skew(w);
        DMat3::IDENTITY + (1.0 - a.cos()) / (a * a) * k + (a - a.sin()) / (a * a * a) * (k * k)
    }

    /// The quasi-Newton shader against its float64 reference on a quadratic loss over the
    /// code and the pose offsets (fed to the shader as the renderer would: the rotation
    /// gradient for a left increment of the current rotation), step by step, and the pose
    /// it writes into the view: once with the optimum inside the code bounds, once with
    /// the first code coordinate's optimum past its bound (each coordinate has its own,
    /// [`BOUND`]).
    #[test]
    fn bfgs_shader_matches_a_float64_reference() {
        let inside = bfgs_case(None, 0.0);
        assert!(
            inside.capped > 0 && inside.halved > 0,
            "capped {} and halved {} steps",
            inside.capped,
            inside.halved
        );
        let bounded = bfgs_case(Some(3.4), 0.0);
        assert!(bounded.held > 0, "no step held a coordinate on its bound");
        assert_eq!(bounded.accepted[0], BOUND[0]);
        // With a code prior the shader adds it to the loss and the gradient itself.
        let prior = bfgs_case(None, 0.3);
        assert!(prior.accepted[..3]
            .iter()
            .zip(&inside.accepted)
            .any(|(a, b)| (a - b).abs() > 1e-2));
    }

    /// The code coordinates' bounds of [`bfgs_shader_matches_a_float64_reference`].
    const BOUND: [f64; 3] = [2.5, 3.0, 2.0];

    /// One run of [`bfgs_shader_matches_a_float64_reference`], with the first code
    /// coordinate's optimum at `code_target` if given and a code prior of weight `prior`
    /// (the shader adds it; the reference sees it in the loss it is fed); checks every
    /// step, convergence to the (constrained) minimum and the view, and returns the
    /// reference's final state.
    fn bfgs_case(code_target: Option<f64>, prior: f64) -> BfgsReference {
        let options = crate::gpu::ContextOptions {
            validation: true,
            ..Default::default()
        };
        let ctx = Context::with_options(options).expect("the tests need a Vulkan device");
        let optimizers = Optimizers::new(&ctx).unwrap();
        let (k, iterations) = (3usize, 30usize);
        let n = k + 6;
        let params = RegisterParams {
            iterations,
            pose_every: 1,
            optimizer: Optimizer::Bfgs,
            latent_step: 4.0,
            translation_step: 0.01,
            rotation_step: 0.05,
            code_prior: prior,
            ..RegisterParams::default()
        };
        // f(x) = 0.5 (x - x*)^T Q (x - x*), Q = D (I + 0.3 R R^T) D with unit diagonal
        // scales D per part (codes, metres, radians).
        let mut rng = Rng::new(7);
        let target: Vec<f64> = (0..n)
            .map(|i| match i {
                _ if i < k => rng.range(-0.6, 0.6),
                _ if i < k + 3 => rng.range(-0.06, 0.06),
                _ => rng.range(-0.1, 0.1),
            })
            .collect();
        let target = {
            let mut t = target;
            t[0] = code_target.unwrap_or(t[0]);
            t[k + 2] = 0.0;
            t
        };
        let r: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..n).map(|_| rng.range(-1.0, 1.0)).collect())
            .collect();
        let scale = |i: usize| {
            if i < k {
                1.0
            } else if i < k + 3 {
                30.0
            } else {
                5.0
            }
        };
        let q: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        let rr: f64 = (0..n).map(|c| r[i][c] * r[j][c]).sum();
                        scale(i) * scale(j) * (if i == j { 1.0 } else { 0.0 } + 0.3 * rr)
                    })
                    .collect()
            })
            .collect();
        // Plus a quartic in the code, so that some steps overshoot and are halved.
        let evaluate = |x: &[f64]| -> (f64, Vec<f64>) {
            let e: Vec<f64> = (0..n).map(|i| x[i] - target[i]).collect();
            let mut g: Vec<f64> = (0..n)
                .map(|i| (0..n).map(|j| q[i][j] * e[j]).sum())
                .collect();
            let code: f64 = e[..k].iter().map(|v| v * v).sum();
            for i in 0..k {
                g[i] += 2.0 * code * e[i];
            }
            (
                0.5 * (0..n)
                    .map(|i| e[i] * (0..n).map(|j| q[i][j] * e[j]).sum::<f64>())
                    .sum::<f64>()
                    + 0.5 * code * code,
                g,
            )
        };

        // The objective the shader minimises: the fed loss plus the prior on the code.
        let with_prior = |x: &[f64], loss: f64, mut g: Vec<f64>| -> (f64, Vec<f64>) {
            let mut total = loss;
            for i in 0..k {
                total += prior * x[i] * x[i];
                g[i] += 2.0 * prior * x[i];
            }
            (total, g)
        };
        let start = Pose::new([0.01, -0.02, 0.6], [2.9, 0.3, 0.1]).unwrap();
        let camera = Camera::new(100.0, 100.0, 32.0, 32.0, 64, 64).unwrap();
        let views = ViewBuffers::new(
            &ctx,
            &[View {
                camera,
                pose: start,
            }],
        )
        .unwrap();
        let layout = StateLayout::new(k, iterations);
        // The prior in these coordinates: |z|^2.
        let mut identity = Matrix::zeros(k, k);
        (0..k).for_each(|i| identity.set(i, i, 1.0));
        let mut state =
            Buffer::from_slice(&ctx, "state", &layout.initial(&identity, &BOUND, None)).unwrap();
        state.write(0, &[0f32]).unwrap();
        let mut grad_latent = Buffer::from_slice(&ctx, "grad latent", &vec![0f32; k]).unwrap();
        let mut grad_pose = Buffer::from_slice(&ctx, "grad pose", &[0f32; 6]).unwrap();
        let mut stats = Buffer::from_slice(&ctx, "stats", &[0f32; 4]).unwrap();
        let mut reference = BfgsReference::new(&BOUND, [4.0, 0.01, 0.05]);
        let read_x = |state: &Buffer| -> Vec<f64> {
            let v = state.read::<f32>().unwrap();
            let (latent, pose) = (layout.latent as usize, layout.pose_x as usize);
            (0..k)
                .map(|i| v[latent + i] as f64)
                .chain((0..6).map(|i| v[pose + i] as f64))
                .collect()
        };
        for t in 0..iterations {
            let x = read_x(&state);
            if t > 0 {
                for i in 0..n {
                    let tolerance =
                        2e-3 * (1.0 + reference.x[i].abs()) * if i < k { 1.0 } else { 0.05 };
                    assert!(
                        (x[i] - reference.x[i]).abs() < tolerance,
                        "iteration {t}, x[{i}]: shader {} reference {}",
                        x[i],
                        reference.x[i]
                    );
                }
            }
            // Feed both the loss and gradient at the shader's point; the shader gets the
            // rotation gradient for a left increment, J^-T dL/dw.
            let (loss, g) = evaluate(&x);
            let w = DVec3::new(x[k + 3], x[k + 4], x[k + 5]);
            let left = if w.length() > 1e-9 {
                left_jacobian(w).transpose().inverse() * DVec3::new(g[k + 3], g[k + 4], g[k + 5])
            } else {
                DVec3::new(g[k + 3], g[k + 4], g[k + 5])
            };
            stats.write(0, &[0.0f32, 0.0, 0.0, loss as f32]).unwrap();
            grad_latent
                .write(0, &g[..k].iter().map(|&v| v as f32).collect::<Vec<_>>())
                .unwrap();
            let pose_grad = [g[k], g[k + 1], g[k + 2], left.x, left.y, left.z].map(|v| v as f32);
            grad_pose.write(0, &pose_grad).unwrap();
            let mut rec = Recorder::new(&ctx).unwrap();
            rec.run_compute(
                &optimizers.bfgs,
                &[
                    Binding::buffer(&state),
                    Binding::buffer(&grad_latent),
                    Binding::buffer(&grad_pose),
                    Binding::buffer(&stats),
                    Binding::buffer(views.views()),
                ],
                &OptimizerConstants::new(k, &params, false),
                Groups::Count(1, 1, 1),
            );
            ctx.submit_and_wait(rec).unwrap();
            let (loss, g) = with_prior(&x, loss, g);
            reference.step(loss, g);
        }
        // It converges to the constrained minimum: the projected gradient (zero where a
        // code coordinate's bound holds it, and for the fixed z) vanishes.
        let projected = |x: &[f64]| {
            let (loss, g) = evaluate(x);
            let (_, g) = with_prior(x, loss, g);
            (0..n)
                .filter(|&i| i != k + 2)
                .filter(|&i| {
                    !(i < k && (x[i] >= BOUND[i] && g[i] < 0.0 || x[i] <= -BOUND[i] && g[i] > 0.0))
                })
                .map(|i| g[i] * g[i])
                .sum::<f64>()
                .sqrt()
        };
        let (first, last) = (projected(&vec![0.0; n]), projected(&reference.accepted));
        assert!(last < 1e-3 * first, "projected gradient {first} -> {last}");
        let x = read_x(&state);
        let pose = super::super::task::read_pose(&views).unwrap();
        let w = DVec3::new(x[k + 3], x[k + 4], x[k + 5]);
        let want_r = DMat3::from_quat(glam::DQuat::from_scaled_axis(w)) * start.rotation_matrix();
        let want_t = start.translation + DVec3::new(x[k], x[k + 1], x[k + 2]);
        assert!(
            (pose.translation - want_t).length() < 1e-5,
            "{pose:?} vs {want_t}"
        );
        let dr = pose.rotation_matrix() - want_r;
        let off = dr.x_axis.length() + dr.y_axis.length() + dr.z_axis.length();
        assert!(off < 1e-4, "rotation off by {off}");
        ctx.check_validation().unwrap();
        reference
    }

    /// BFGS's code coordinates: the columns of B A are orthogonal in vertex space, each as
    /// long as the RMS training deformation; SGD's are the training standard deviations.
    /// SGD's coordinate on its bound is a code CODE_BOUND training standard deviations
    /// long (|s / sd| = 3), BFGS's at least as long.
    #[test]
    fn optimizer_coordinates_whiten_the_basis() {
        let space = random_space(&mut Rng::new(2), 6, 4);
        let d = 3 * space.canonical.vertex_count();
        let k = space.dims();
        let basis = &space.deformation_basis;
        let deformation = |s: &[f64]| -> Vec<f64> {
            (0..d)
                .map(|i| (0..k).map(|j| basis[j][i] * s[j]).sum())
                .collect()
        };
        let squared = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>();
        let t = space.training_codes.len() as f64;
        let spread = space
            .training_codes
            .iter()
            .map(|c| squared(&deformation(c)))
            .sum::<f64>()
            / (t - 1.0);

        // The length of a code on each coordinate's bound, in training SD.
        let in_sd = |coordinates: &CodeCoordinates| -> Vec<f64> {
            let (a, bound) = (&coordinates.to_code, &coordinates.bound);
            (0..k)
                .map(|c| {
                    let s: Vec<f64> = (0..k).map(|j| a.at(j, c) * bound[c]).collect();
                    squared(&space.code_in_deviations(&s)).sqrt()
                })
                .collect()
        };
        let coordinates = optimizer_coordinates(&space, Optimizer::Bfgs);
        for (c, sd) in in_sd(&coordinates).into_iter().enumerate() {
            assert!(sd >= CODE_BOUND * (1.0 - 1e-9), "coordinate {c}: {sd} SD");
        }
        let a = coordinates.to_code;
        let columns: Vec<Vec<f64>> = (0..k)
            .map(|c| deformation(&(0..k).map(|j| a.at(j, c)).collect::<Vec<_>>()))
            .collect();
        for (i, ci) in columns.iter().enumerate() {
            for (j, cj) in columns.iter().enumerate() {
                let dot: f64 = ci.iter().zip(cj).map(|(x, y)| x * y).sum();
                let want = if i == j { spread } else { 0.0 };
                assert!(
                    (dot - want).abs() < 1e-9 * spread,
                    "({i}, {j}): {dot} vs {want}"
                );
            }
        }

        let coordinates = optimizer_coordinates(&space, Optimizer::Sgd);
        for (c, sd) in in_sd(&coordinates).into_iter().enumerate() {
            assert!((sd - CODE_BOUND).abs() < 1e-9, "coordinate {c}: {sd} SD");
        }
        let a = coordinates.to_code;
        for j in 0..k {
            let var = space
                .training_codes
                .iter()
                .map(|c| c[j] * c[j])
                .sum::<f64>()
                / (t - 1.0);
            assert!((a.at(j, j) - var.sqrt()).abs() < 1e-12 * var.sqrt());
        }
    }
}
