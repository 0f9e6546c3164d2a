//! Render-and-compare registration on the device. The latent code (in units of each
//! dimension's training standard deviation) and the pose live in device buffers; one
//! iteration — deform (C + d0 + B s), rasterize, antialias, loss, backward, reduce to
//! dL/ds and dL/dpose, optimiser step — is recorded once and replayed; a chunk of
//! iterations goes in one submission, and the host reads the loss history between chunks
//! to stop on a plateau. Codes are kept within 3 training standard deviations
//! (projected steps).

use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use glam::{DMat3, DVec3};

use crate::diff::{DiffRenderer, Scene, SceneDesc};
use crate::error::{Error, Result};
use crate::gpu::{spirv, Binding, BindingKind, Buffer, ComputePipeline, Context, Recorder};
use crate::loss::Loss;
use crate::raster::View;
use crate::shape::ShapeSpace;
use crate::Pose;

const DEFORM: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/deform.comp.spv"));
const LATENT_GRADIENT: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/latent_gradient.comp.spv"));
const OPTIMIZER: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/optimizer.comp.spv"));

/// How to register.
#[derive(Clone, Copy, Debug)]
pub struct RegisterParams {
    pub iterations: usize,
    pub momentum: f64,
    /// Learning-rate decay per iteration.
    pub decay: f64,
    /// Length of the first latent step, in standard deviations of the training codes
    /// (SGD's learning rate is set from the first gradient so that its step has this length).
    pub latent_step: f64,
    /// Update the pose once every this many iterations (0: the pose stays fixed).
    pub pose_every: usize,
    /// With pose optimisation: iterations at the start that move the pose alone (the
    /// shape would otherwise bend to explain a misaligned silhouette).
    pub pose_first: usize,
    /// Let the z translation move too (ill-posed with shape from one view).
    pub optimize_z: bool,
    /// First translation and rotation steps of the pose (metres, radians).
    pub translation_step: f64,
    pub rotation_step: f64,
    pub adam: bool,
    pub loss: Loss,
    /// Read the loss back every this many iterations; stop when it improved by less than
    /// `plateau` (relative) over the last chunk.
    pub check_every: usize,
    pub plateau: f64,
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            momentum: 0.9,
            decay: 0.95,
            latent_step: 0.5,
            pose_every: 0,
            pose_first: 0,
            optimize_z: false,
            translation_step: 0.004,
            rotation_step: 0.02,
            adam: false,
            loss: Loss::Mse,
            check_every: 10,
            plateau: 1e-4,
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct DeformConstants {
    vertex_count: u32,
    dims: u32,
    latent_at: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct OptimizerConstants {
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
    shape_after: u32,
}

/// Offsets of the optimiser state (mirrors `glsl/optimizer.comp`).
struct State;
impl State {
    const LATENT: usize = 8;
    fn losses(dims: usize) -> usize {
        Self::LATENT + 3 * dims + 6
    }
    fn codes(dims: usize, iterations: usize) -> usize {
        Self::losses(dims) + iterations
    }
}

/// The registration pipelines (besides the differentiable renderer's).
pub struct Registrar {
    renderer: DiffRenderer,
    deform: ComputePipeline,
    latent_gradient: ComputePipeline,
    optimizer: ComputePipeline,
}

/// What a registration found.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Latent code in the shape space's units (as `ShapeSpace::vertices` takes it).
    pub code: Vec<f64>,
    pub pose: Pose,
    pub vertices: Vec<DVec3>,
    /// Loss before each iteration.
    pub losses: Vec<f64>,
    /// Latent code after each iteration (shape space units).
    pub codes: Vec<Vec<f64>>,
    pub iterations: usize,
    pub milliseconds: f64,
}

impl Registrar {
    pub fn new(ctx: &Context) -> Result<Self> {
        let b = BindingKind::StorageBuffer;
        Ok(Self {
            renderer: DiffRenderer::new(ctx)?,
            deform: ComputePipeline::new(ctx, "deform", &spirv(DEFORM)?, &[b; 4], 12)?,
            latent_gradient: ComputePipeline::new(
                ctx,
                "latent gradient",
                &spirv(LATENT_GRADIENT)?,
                &[b; 3],
                8,
            )?,
            optimizer: ComputePipeline::new(ctx, "optimizer", &spirv(OPTIMIZER)?, &[b; 5], 44)?,
        })
    }

    pub fn renderer(&self) -> &DiffRenderer {
        &self.renderer
    }

    /// Registers `space` to one observed mask ([row][column], nonzero = object) seen
    /// through `view` (its pose is the initial pose). `on_chunk` sees the iterations done
    /// and the latest loss (progress bars).
    pub fn register(
        &self,
        ctx: &Context,
        space: &ShapeSpace,
        observed: &[f32],
        view: View,
        params: &RegisterParams,
        mut on_chunk: impl FnMut(usize, f64),
    ) -> Result<Registration> {
        let started = Instant::now();
        let k = space.dims();
        let m = space.canonical.vertex_count();
        if params.iterations == 0 {
            return Err(Error::InvalidInput(
                "registration needs at least one iteration".into(),
            ));
        }
        let scene = Scene::new(
            ctx,
            &SceneDesc {
                mesh: &space.canonical,
                views: &[view],
                loss: params.loss,
                observed,
                attributes: None,
            },
        )?;
        // Codes in units of each dimension's training standard deviation.
        let stds: Vec<f64> = (0..k)
            .map(|j| {
                let t = space.training_codes.len() as f64;
                let var = space
                    .training_codes
                    .iter()
                    .map(|c| c[j] * c[j])
                    .sum::<f64>()
                    / (t - 1.0).max(1.0);
                var.sqrt().max(1e-12)
            })
            .collect();
        let base: Vec<f32> = space
            .canonical
            .positions()
            .iter()
            .flatten()
            .zip(&space.offset)
            .map(|(&c, &d)| (c as f64 + d) as f32)
            .collect();
        let basis: Vec<f32> = space
            .deformation_basis
            .iter()
            .zip(&stds)
            .flat_map(|(b, &s)| b.iter().map(move |&v| (v * s) as f32))
            .collect();
        let base = Buffer::from_slice(ctx, "canonical + offset", &base)?;
        let basis = Buffer::from_slice(ctx, "scaled deformation basis", &basis)?;
        let state_len = State::codes(k, params.iterations) + params.iterations * k;
        let state = Buffer::from_slice(ctx, "optimizer state", &vec![0f32; state_len])?;
        let grad_latent = Buffer::from_slice(ctx, "latent gradient", &vec![0f32; k.max(1)])?;

        let deform_constants = DeformConstants {
            vertex_count: m as u32,
            dims: k as u32,
            latent_at: State::LATENT as u32,
        };
        let optimizer_constants = OptimizerConstants {
            dims: k as u32,
            pose_every: params.pose_every as u32,
            optimize_z: params.optimize_z as u32,
            adam: params.adam as u32,
            momentum: params.momentum as f32,
            decay: params.decay as f32,
            latent_step: params.latent_step as f32,
            translation_step: params.translation_step as f32,
            rotation_step: params.rotation_step as f32,
            max_iterations: params.iterations as u32,
            shape_after: if params.pose_every > 0 {
                params.pose_first.min(params.iterations) as u32
            } else {
                0
            },
        };
        let record_iteration = |rec: &mut Recorder| -> Result<()> {
            rec.bind_compute(&self.deform);
            rec.push_compute_bindings(
                &self.deform,
                &[
                    Binding::buffer(&base),
                    Binding::buffer(&basis),
                    Binding::buffer(&state),
                    Binding::buffer(scene.mesh().positions()),
                ],
            );
            rec.compute_constants(&self.deform, &deform_constants);
            rec.dispatch((m as u32).div_ceil(64), 1, 1);
            rec.memory_barrier();
            scene.record(&self.renderer, rec, None)?;
            rec.fill_buffer(&grad_latent, 0);
            rec.memory_barrier();
            rec.bind_compute(&self.latent_gradient);
            rec.push_compute_bindings(
                &self.latent_gradient,
                &[
                    Binding::buffer(&basis),
                    Binding::buffer(scene.vertex_gradient()),
                    Binding::buffer(&grad_latent),
                ],
            );
            rec.compute_constants(&self.latent_gradient, &[m as u32, k as u32]);
            rec.dispatch(1, 1, k as u32);
            rec.memory_barrier();
            rec.bind_compute(&self.optimizer);
            rec.push_compute_bindings(
                &self.optimizer,
                &[
                    Binding::buffer(&state),
                    Binding::buffer(&grad_latent),
                    Binding::buffer(scene.pose_gradient()),
                    Binding::buffer(scene.loss_stats()),
                    Binding::buffer(scene.views().views()),
                ],
            );
            rec.compute_constants(&self.optimizer, &optimizer_constants);
            rec.dispatch(1, 1, 1);
            rec.memory_barrier();
            Ok(())
        };

        let mut rec = Recorder::new(ctx)?;
        scene.record_prepare(&self.renderer, &mut rec)?;
        ctx.submit_and_wait(rec)?;
        let chunk = params.check_every.clamp(1, params.iterations);
        let mut rec = Recorder::new(ctx)?;
        for _ in 0..chunk {
            record_iteration(&mut rec)?;
        }
        let chunk_recording = rec.finish()?;
        let mut done = 0;
        let mut previous_best = f64::INFINITY;
        while done < params.iterations {
            let n = chunk.min(params.iterations - done);
            if n == chunk {
                ctx.replay(&chunk_recording)?;
            } else {
                let mut rec = Recorder::new(ctx)?;
                for _ in 0..n {
                    record_iteration(&mut rec)?;
                }
                ctx.submit_and_wait(rec)?;
            }
            done += n;
            let losses = state.read_range::<f32>(State::losses(k) as u64 * 4, done)?;
            let best = losses.iter().copied().fold(f32::INFINITY, f32::min) as f64;
            on_chunk(done, *losses.last().unwrap_or(&f32::NAN) as f64);
            if best.is_finite()
                && previous_best.is_finite()
                && previous_best - best <= params.plateau * previous_best.abs()
            {
                break;
            }
            previous_best = previous_best.min(best);
        }

        let values = state.read_range::<f32>(0, state_len)?;
        let code: Vec<f64> = (0..k)
            .map(|j| values[State::LATENT + j] as f64 * stds[j])
            .collect();
        let losses = values[State::losses(k)..State::losses(k) + done]
            .iter()
            .map(|&l| l as f64)
            .collect();
        let at = State::codes(k, params.iterations);
        let codes = (0..done)
            .map(|t| {
                (0..k)
                    .map(|j| values[at + t * k + j] as f64 * stds[j])
                    .collect()
            })
            .collect();
        let pose = read_pose(scene.views())?;
        Ok(Registration {
            vertices: space.vertices(&code)?,
            code,
            pose,
            losses,
            codes,
            iterations: done,
            milliseconds: started.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// The first view's pose as the device holds it.
fn read_pose(views: &crate::raster::ViewBuffers) -> Result<Pose> {
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
