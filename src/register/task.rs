//! A registration's device buffers, its progress, and what one stage returns.

use std::time::Instant;

use glam::{DMat3, DVec3};

use crate::cpd::linalg::Matrix;
use crate::diff::{DepthLoss, ObservedDepth, Scene, SceneDesc};
use crate::error::{Error, Result};
use crate::gpu::{Buffer, Context};
use crate::shape::ShapeSpace;
use crate::Pose;

use super::optimizer::{
    self, optimizer_coordinates, CodeCoordinates, StateLayout, BFGS_MAX_DIMS, MAX_DIMS,
};
use super::params::SCALE_BOUND;
use super::{Job, Optimizer, RegisterParams, Registration, SCALE_UNIT, STAGE_FIT};

/// A registration's device buffers and progress.
pub(super) struct Task<'a> {
    pub(super) space: &'a ShapeSpace,
    pub(super) scene: Scene,
    /// The device's coordinates z to latent codes: s = to_code z.
    pub(super) to_code: Matrix,
    /// Each device coordinate's bound (the scale's too, last where it is fitted).
    pub(super) bound: Vec<f64>,
    pub(super) base: Buffer,
    pub(super) basis: Buffer,
    pub(super) state: Buffer,
    pub(super) grad_latent: Buffer,
    /// With several views: each view's pose relative to the first (`glsl/rig.comp`).
    pub(super) rig: Option<Buffer>,
    pub(super) m: usize,
    /// The space's dimensions, and the device's (one more with a scale coordinate, last).
    pub(super) k: usize,
    pub(super) dims: usize,
    pub(super) done: usize,
    pub(super) active: bool,
    pub(super) best: f64,
    pub(super) milliseconds: f64,
}

impl<'a> Task<'a> {
    /// `code`: where the code starts, in the device's coordinates (None: the mean);
    /// `prior`: the code prior's matrix in them (k x k; None: the weak prior's,
    /// [`optimizer::prior_matrix`]).
    pub(super) fn new(
        ctx: &Context,
        job: &Job<'a>,
        params: &RegisterParams,
        code: Option<&[f32]>,
        prior: Option<&Matrix>,
    ) -> Result<Self> {
        let space = job.space;
        let k = space.dims();
        let dims = k + params.optimize_scale as usize;
        if dims > MAX_DIMS {
            return Err(Error::Limit(format!(
                "registration takes at most {MAX_DIMS} latent dimensions, the space has {k}"
            )));
        }
        if params.optimizer == Optimizer::Bfgs && dims > BFGS_MAX_DIMS {
            return Err(Error::InvalidInput(format!(
                "the bfgs optimizer takes at most {BFGS_MAX_DIMS} latent dimensions (a scale \
                 counts as one), the space has {k}"
            )));
        }
        let observed = match (params.shading, job.shaded) {
            (None, _) => job.observed,
            (Some(_), Some(shaded)) => shaded,
            (Some(_), None) => {
                return Err(Error::InvalidInput(
                    "registration with shading needs the observed shading image".into(),
                ))
            }
        };
        let depth = match (params.depth, job.depth) {
            (None, _) => None,
            (Some(loss), Some(depth)) => Some(ObservedDepth {
                depth,
                loss: DepthLoss {
                    weight: loss.weight * (job.depth_every as f64).powi(2),
                    ..loss
                },
            }),
            (Some(_), None) => {
                return Err(Error::InvalidInput(
                    "registration with depth needs the observed depth image".into(),
                ))
            }
        };
        let views = job.views();
        let scene = Scene::new(
            ctx,
            &SceneDesc {
                loss_pixels: job.loss_pixels,
                mesh: &space.canonical,
                views: &views,
                loss: params.loss,
                observed,
                attributes: None,
                shading: params.shading,
                depth,
            },
        )?;
        let rig = if job.others.is_empty() {
            None
        } else {
            let identity = Pose::at([0.0; 3]);
            let rig: Vec<[[f32; 4]; 4]> = std::iter::once(&identity)
                .chain(job.others.iter().map(|o| &o.from_first))
                .map(|p| p.matrix_f32())
                .collect();
            Some(Buffer::from_slice(ctx, "rig", &rig)?)
        };
        let CodeCoordinates { to_code, mut bound } = optimizer_coordinates(space, params.optimizer);
        let base: Vec<f32> = space
            .canonical
            .positions()
            .iter()
            .flatten()
            .zip(&space.offset)
            .map(|(&c, &d)| (c as f64 + d) as f32)
            .collect();
        let mut basis: Vec<f32> = (0..k)
            .flat_map(|c| {
                let to_code = &to_code;
                (0..space.offset.len()).map(move |i| {
                    (0..k)
                        .map(|j| space.deformation_basis[j][i] * to_code.at(j, c))
                        .sum::<f64>() as f32
                })
            })
            .collect();
        // A scale coordinate x moves the vertices by x SCALE_UNIT (C + d0): the positions
        // (1 + a)(C + d0) + B z are the shape (C + d0 + B z / (1 + a)) scaled by 1 + a, so
        // a scaled shape space is this linear space and the optimisers stay as they are.
        if params.optimize_scale {
            basis.extend(base.iter().map(|&b| (b as f64 * SCALE_UNIT) as f32));
            bound.push(SCALE_BOUND);
        }
        let layout = StateLayout::new(dims, params.iterations);
        let mut matrix = optimizer::prior_matrix(space, &to_code, dims);
        if let Some(prior) = prior {
            for i in 0..k {
                for j in 0..k {
                    matrix.set(i, j, prior.at(i, j));
                }
            }
        }
        let mut state = layout.initial(&matrix, &bound, job.gravity.as_ref());
        if let Some(code) = code {
            let at = layout.latent as usize;
            state[at..at + dims].copy_from_slice(&code[..dims]);
        }
        Ok(Self {
            space,
            scene,
            to_code,
            bound,
            base: Buffer::from_slice(ctx, "canonical + offset", &base)?,
            basis: Buffer::from_slice(ctx, "scaled deformation basis", &basis)?,
            state: Buffer::from_slice(ctx, "optimizer state", &state)?,
            grad_latent: Buffer::from_slice(ctx, "latent gradient", &vec![0f32; dims.max(1)])?,
            rig,
            m: space.canonical.vertex_count(),
            k,
            dims,
            done: 0,
            active: true,
            best: f64::INFINITY,
            milliseconds: 0.0,
        })
    }

    /// Reads the losses so far, stops the task on a plateau or at the last iteration, and
    /// returns the latest loss.
    pub(super) fn check_plateau(&mut self, params: &RegisterParams) -> Result<f64> {
        self.scene.check_walks()?;
        if self.scene.listed_pixels()? == 0 {
            let pose = read_pose(self.scene.views())?;
            return Err(Error::InvalidInput(format!(
                "the registration lost the object after {} iterations: nothing of it is \
                 rendered any more (pose translation {:?} m); start closer to the object or \
                 take smaller steps",
                self.done,
                pose.translation.to_array()
            )));
        }
        let losses = self
            .state
            .read_range::<f32>(StateLayout::new(self.dims, 0).losses as u64 * 4, self.done)?;
        let best = losses.iter().copied().fold(f32::INFINITY, f32::min) as f64;
        let plateau = best.is_finite()
            && self.best.is_finite()
            && self.best - best <= params.plateau * self.best.abs();
        self.best = self.best.min(best);
        if plateau || self.done >= params.iterations {
            self.active = false;
        }
        Ok(*losses.last().unwrap_or(&f32::NAN) as f64)
    }

    /// The latent code and the scale of device coordinates `z` (the shape's code: the
    /// deformation over the scale, see `Task::new`).
    pub(super) fn code(&self, z: &[f32]) -> (Vec<f64>, f64) {
        let scale = match z.get(self.k) {
            Some(&a) if self.dims > self.k => 1.0 + a as f64 * SCALE_UNIT,
            _ => 1.0,
        };
        let code = (0..self.k)
            .map(|j| {
                (0..self.k)
                    .map(|c| self.to_code.at(j, c) * z[c] as f64)
                    .sum::<f64>()
                    / scale
            })
            .collect();
        (code, scale)
    }

    /// The result, and the code in the device's coordinates (where a next stage starts).
    pub(super) fn staged(&self, params: &RegisterParams) -> Result<Staged> {
        let (k, dims) = (self.k, self.dims);
        let layout = StateLayout::new(dims, params.iterations);
        let at = |offset: u32| offset as usize;
        let values = self.state.read_range::<f32>(0, at(layout.len))?;
        let losses: Vec<f64> = values[at(layout.losses)..at(layout.losses) + self.done]
            .iter()
            .map(|&l| l as f64)
            .collect();
        let last_loss = losses.last().copied().unwrap_or(f64::NAN);
        let (coordinates, pose, loss) = match params.optimizer {
            Optimizer::Sgd | Optimizer::Adam => (
                &values[at(layout.latent)..at(layout.latent) + dims],
                read_pose(self.scene.views())?,
                last_loss,
            ),
            // The last accepted point (the current one is a step not yet evaluated).
            Optimizer::Bfgs => {
                let accepted = at(layout.accepted);
                let pose = if params.pose_every > 0 {
                    layout.bfgs_pose(&values, dims)
                } else {
                    read_pose(self.scene.views())?
                };
                let loss = values[at(layout.accepted_loss)] as f64;
                (&values[accepted..accepted + dims], pose, loss)
            }
        };
        let (code, scale) = self.code(coordinates);
        let on_bound = coordinates[..k]
            .iter()
            .zip(&self.bound)
            .filter(|&(z, &b)| z.abs() >= b as f32)
            .count();
        let codes_at = at(layout.codes);
        let (codes, scales) = (0..self.done)
            .map(|t| self.code(&values[codes_at + t * dims..codes_at + (t + 1) * dims]))
            .unzip();
        let vertices = self
            .space
            .vertices(&code)?
            .into_iter()
            .map(|v| v * scale)
            .collect();
        Ok(Staged {
            result: Registration {
                vertices,
                code,
                pose,
                stages: vec![(STAGE_FIT, losses.len())],
                losses,
                codes,
                scales,
                evaluations: self.done,
                milliseconds: self.milliseconds,
                on_bound,
                scale,
                loss,
            },
            coordinates: coordinates.to_vec(),
            inverse_hessian: (params.optimizer == Optimizer::Bfgs).then(|| {
                // The coordinates that moved: the code (and scale), the pose where it is
                // optimised (z where asked for); the others keep their first diagonal.
                let (h, n) = (at(layout.h), dims + 6);
                let values = &values;
                let moved: Vec<usize> = (0..n)
                    .filter(|&i| {
                        i < dims || (params.pose_every > 0 && (i != dims + 2 || params.optimize_z))
                    })
                    .collect();
                Matrix {
                    rows: moved.len(),
                    cols: moved.len(),
                    data: moved
                        .iter()
                        .flat_map(|&i| moved.iter().map(move |&j| values[h + i * n + j] as f64))
                        .collect(),
                }
            }),
        })
    }
}

/// One stage of a registration (`Registrar::run`): its parameters, whether the latent
/// code stays where it starts (`pose_only`), where each job's code starts (`codes`, device
/// coordinates as a stage returns them; None: the mean), when the registration started,
/// and the iterations before it (`on_chunk` counts from `first`).
#[derive(Clone, Copy)]
pub(super) struct Stage<'a> {
    pub(super) params: &'a RegisterParams,
    pub(super) pose_only: bool,
    pub(super) codes: Option<&'a [Vec<f32>]>,
    pub(super) started: std::time::Instant,
    pub(super) first: usize,
    /// Each job's code prior matrix in the optimiser's coordinates, in place of the
    /// weak prior's ([`super::evidence::held_prior`]).
    pub(super) priors: Option<&'a [Matrix]>,
}

impl<'a> Stage<'a> {
    /// A stage that fits the code and the pose from `codes` (None: the mean), counting its
    /// iterations from 0, under the weak prior.
    pub(super) fn fit(
        params: &'a RegisterParams,
        codes: Option<&'a [Vec<f32>]>,
        started: Instant,
    ) -> Self {
        Self {
            params,
            pose_only: false,
            codes,
            started,
            first: 0,
            priors: None,
        }
    }

    /// The same stage with the code held where it starts: the pose alone moves.
    pub(super) fn pose_only(self) -> Self {
        Self {
            pose_only: true,
            ..self
        }
    }
}

/// What one stage of a registration (`Registrar::run`) returns.
pub(super) struct Staged {
    pub(super) result: Registration,
    /// The code in the device's coordinates, where a next stage starts it.
    pub(super) coordinates: Vec<f32>,
    /// BFGS: its inverse Hessian estimate at the end over the coordinates that moved (the
    /// device's code coordinates first, then the pose's where it moved).
    pub(super) inverse_hessian: Option<Matrix>,
}

/// `again` (a fit run again from elsewhere, its stage then named `stage`) in place of
/// `fitted` where its final loss is lower, else `fitted`; either way counting both fits'
/// evaluations, and the time since `started`.
pub(super) fn lower_loss(
    fitted: Staged,
    again: Staged,
    stage: &'static str,
    started: Instant,
) -> Staged {
    let evaluations = fitted.result.evaluations + again.result.evaluations;
    let mut kept = if again.result.loss < fitted.result.loss {
        Staged {
            result: Registration {
                stages: vec![(stage, again.result.losses.len())],
                ..again.result
            },
            ..again
        }
    } else {
        fitted
    };
    kept.result.evaluations = evaluations;
    kept.result.milliseconds = started.elapsed().as_secs_f64() * 1e3;
    kept
}

/// The first view's pose as the device holds it.
pub(super) fn read_pose(views: &crate::raster::ViewBuffers) -> Result<Pose> {
    let data = views.read_data()?;
    let m = data[0].object_to_camera;
    let r = DMat3::from_cols(
        DVec3::new(m[0][0] as f64, m[0][1] as f64, m[0][2] as f64),
        DVec3::new(m[1][0] as f64, m[1][1] as f64, m[1][2] as f64),
        DVec3::new(m[2][0] as f64, m[2][1] as f64, m[2][2] as f64),
    );
    let rotation = glam::DQuat::from_mat3(&r).to_scaled_axis();
    Ok(Pose {
        translation: DVec3::new(m[3][0] as f64, m[3][1] as f64, m[3][2] as f64),
        rotation,
    })
}
