//! Render-and-compare registration on the device. The latent code (in the optimiser's
//! coordinates) and the pose live in device buffers; one
//! iteration — deform (C + d0 + B s), rasterize, antialias, loss, backward, reduce to
//! dL/ds and dL/dpose, optimiser step — is recorded once and replayed; a chunk of
//! iterations goes in one submission, and the host reads the loss history between chunks
//! to stop on a plateau. Two optimisers: the paper's SGD with momentum (or Adam), and a
//! quasi-Newton BFGS over the code and the pose together (see `glsl/bfgs.comp`), which with
//! the pose known reaches about the oracle's error in the paper's 30 iterations where SGD
//! stays at 2-4 times it. With pose optimisation the pose can
//! first be aligned alone (`RegisterParams::align`). Codes are kept within 3 units of the
//! optimiser's coordinates (projected steps; see `optimizer_coordinates`).

use std::ops::ControlFlow;
use std::time::Instant;

use glam::DVec3;

use crate::cpd::linalg::Matrix;
use crate::diff::DiffRenderer;
use crate::error::{Error, Result};
use crate::gpu::{ComputePipeline, Context};
use crate::raster::View;
use crate::shaders;
use crate::Pose;

mod depth_settle;
mod evidence;
pub use evidence::{HELD_BELOW, HOLD};
mod gravity;
mod iterate;
mod job;
mod nearest;
mod observation;
mod optimizer;
mod params;
mod prepare;
mod region;
mod starts;
mod task;

pub use depth_settle::SETTLE_TOLERANCE;
pub use gravity::{Gravity, GRAVITY_WEIGHT, TILT_TOLERANCE};
pub use iterate::PassTimes;
pub use job::{all_views, Job, OtherView};
pub use observation::{Observation, Plan, PoseMode, ViewImages};
use params::SCALE_UNIT;
pub use params::{
    observation_prior, RegisterParams, CODE_BOUND, DETAIL, MASK_FIRST, MAX_ITERATIONS, REACH,
    REACH_ITERATIONS, SCALE_RANGE, STAGES, STAGE_ALIGN, STAGE_FIT, STAGE_HELD, STAGE_MASK_FIRST,
    STAGE_REACH, STAGE_SETTLED, STAGE_TURNED,
};
use prepare::{onto_mask, unknown_in_front, Marked};
use starts::{at_poses, jobs_from, relative_turns};
pub use starts::{
    check_starts, start_turns, symmetry_pivot, turned_starts, Starts, DEFAULT_STARTS, MAX_STARTS,
    START_TURN, TURN_GAIN, TURN_ITERATIONS,
};
use task::{Stage, Staged};

pub use optimizer::Optimizer;
use optimizer::Optimizers;
pub use region::Region;

/// The registration pipelines (besides the differentiable renderer's).
pub struct Registrar {
    renderer: DiffRenderer,
    deform: ComputePipeline,
    latent_gradient: ComputePipeline,
    optimizers: Optimizers,
    rig: ComputePipeline,
}

/// What a registration found.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Latent code in the shape space's units (as `ShapeSpace::vertices` takes it).
    pub code: Vec<f64>,
    /// Object-to-camera pose of the (first) view at the end; the job's initial pose
    /// when the pose stays fixed.
    pub pose: Pose,
    /// Vertices of the canonical mesh deformed by `code`, in the object frame.
    pub vertices: Vec<DVec3>,
    /// Loss before each iteration, stage after stage ([`Registration::stages`]): each
    /// stage's objective is its own (the pose alignment's distance loss, the depth
    /// reach's wide depth cost, the joint fit's loss).
    pub losses: Vec<f64>,
    /// The stages that `losses`, `codes` and `scales` hold, in order: each one's name
    /// ([`STAGE_FIT`], [`STAGE_ALIGN`], [`STAGE_REACH`], [`STAGE_TURNED`],
    /// [`STAGE_SETTLED`], [`STAGE_HELD`], [`STAGE_MASK_FIRST`]) and how many
    /// entries it holds. Their counts add up to `losses.len()`
    /// ([`Registration::iterations`]); `evaluations` counts every evaluation besides (the
    /// turns' checks, a joint fit that a turned one beat).
    pub stages: Vec<(&'static str, usize)>,
    /// Latent code after each iteration (shape space units).
    pub codes: Vec<Vec<f64>>,
    /// The uniform scale after each iteration (all 1 unless
    /// [`RegisterParams::optimize_scale`]).
    pub scales: Vec<f64>,
    /// Every evaluation of an objective the registration made: its stages' iterations
    /// (fewer than asked where the loss reached its plateau), with several starts the
    /// turns' checks (none for a fitted body of revolution), and any joint fit that a
    /// turned one or one moved to the depth ([`STAGE_SETTLED`]) replaced. The time,
    /// `milliseconds`, is theirs.
    pub evaluations: usize,
    /// Wall time from the start of the call until this registration finished,
    /// milliseconds.
    pub milliseconds: f64,
    /// Code coordinates on the optimiser's bound at the end (+-[`CODE_BOUND`] in its
    /// coordinates).
    pub on_bound: usize,
    /// The uniform scale of the shape (1 unless [`RegisterParams::optimize_scale`]):
    /// `vertices` are the deformed canonical times it.
    pub scale: f64,
    /// The objective at the returned code and pose (for BFGS its last accepted point,
    /// which `losses` may follow with a rejected trial; for SGD and Adam the last loss
    /// evaluated, before the last step).
    pub loss: f64,
}

impl Registration {
    /// The iterations whose losses are kept: the stages' counts, `losses.len()`.
    pub fn iterations(&self) -> usize {
        self.stages.iter().map(|(_, count)| count).sum()
    }
}

/// What a registration calls after each chunk of iterations with the iterations done
/// and the latest loss (progress bars): any `FnMut(usize, f64)`, returning nothing to go
/// on or a [`ControlFlow`] whose `Break` stops the work with [`Error::Stopped`] (a
/// cancelled job, Ctrl-C in a host language). The work stops between submissions, so
/// within one chunk of [`RegisterParams::check_every`] iterations.
pub trait OnChunk {
    /// Called after each chunk; `Break` stops the registration.
    fn chunk(&mut self, done: usize, loss: f64) -> ControlFlow<()>;
}

impl<F, R> OnChunk for F
where
    F: FnMut(usize, f64) -> R,
    R: ChunkReply,
{
    fn chunk(&mut self, done: usize, loss: f64) -> ControlFlow<()> {
        self(done, loss).flow()
    }
}

/// What an [`OnChunk`] closure may return: nothing (go on) or a [`ControlFlow`].
pub trait ChunkReply {
    /// Whether to go on.
    fn flow(self) -> ControlFlow<()>;
}

impl ChunkReply for () {
    fn flow(self) -> ControlFlow<()> {
        ControlFlow::Continue(())
    }
}

impl ChunkReply for ControlFlow<()> {
    fn flow(self) -> ControlFlow<()> {
        self
    }
}

// The latent gradient takes (m, k, first, end), the rig (views, stage).
const _: () = assert!(shaders::LATENT_GRADIENT_COMP.takes::<[u32; 4]>());
const _: () = assert!(shaders::RIG_COMP.takes::<[u32; 2]>());

impl Registrar {
    /// Builds the registration pipelines and a differentiable renderer.
    pub fn new(ctx: &Context) -> Result<Self> {
        Ok(Self {
            renderer: DiffRenderer::new(ctx)?,
            deform: ComputePipeline::new(ctx, &shaders::DEFORM_COMP)?,
            latent_gradient: ComputePipeline::new(ctx, &shaders::LATENT_GRADIENT_COMP)?,
            optimizers: Optimizers::new(ctx)?,
            rig: ComputePipeline::new(ctx, &shaders::RIG_COMP)?,
        })
    }

    /// The differentiable renderer the registrations use.
    pub fn renderer(&self) -> &DiffRenderer {
        &self.renderer
    }

    /// Runs one registration. `on_chunk` sees the iterations done and the latest loss
    /// (progress bars).
    pub fn register(
        &self,
        ctx: &Context,
        job: Job,
        params: &RegisterParams,
        on_chunk: impl OnChunk,
    ) -> Result<Registration> {
        let mut results = self.register_batch(ctx, &[job], params, on_chunk)?;
        Ok(results.remove(0))
    }

    /// Registers `job` from several starting poses and keeps what the images prefer,
    /// where one start may stop in a local minimum of the rotation ([`turned_starts`]
    /// makes such starts, turned about the up axis), as `starts` says: [`Starts::Turns`]
    /// ([`Registrar::register_with_turns`]) or [`Starts::Poses`] (every start in full, one
    /// [`Registrar::register_batch`], the least final loss kept). The result's
    /// `milliseconds` is the wall time and its `evaluations` count every evaluation. An
    /// error unless 1 to [`MAX_STARTS`] starts are given ([`check_starts`]).
    pub fn register_starts(
        &self,
        ctx: &Context,
        job: Job,
        starts: Starts,
        params: &RegisterParams,
        on_chunk: impl OnChunk,
    ) -> Result<Registration> {
        let poses = match starts {
            Starts::Turns(poses) => {
                return self.register_with_turns(ctx, job, poses, params, on_chunk)
            }
            Starts::Poses(poses) => poses,
        };
        check_starts(poses.len())?;
        let runs = self.register_batch(ctx, &jobs_from(job, poses), params, on_chunk)?;
        let milliseconds = runs.iter().map(|r| r.milliseconds).fold(0.0, f64::max);
        let evaluations = runs.iter().map(|r| r.evaluations).sum();
        let best = runs
            .into_iter()
            .min_by(|a, b| a.loss.total_cmp(&b.loss))
            .expect("at least one start");
        Ok(Registration {
            milliseconds,
            evaluations,
            ..best
        })
    }

    /// Registers `job` from the first of `starts`, then turns the fitted shape as each
    /// further start was turned from the first and scores it by one evaluation; from a
    /// turn that scores [`TURN_GAIN`] lower the joint fit runs again and the lower final
    /// loss is kept (`Registrar::check_turns`, private): k starts cost one registration, k
    /// evaluations and a second joint fit where a turn wins (`vkdr bench-register` times
    /// it); none of those where the fitted shape is a body of revolution about the up
    /// axis, or where every start is the first (its turns all the identity). Needs the
    /// pose free with an alignment stage (`params.pose_every` and `params.align` > 0): the
    /// turns are tried on the aligned fit. An error otherwise,
    /// and unless 1 to [`MAX_STARTS`] starts are given.
    pub fn register_with_turns(
        &self,
        ctx: &Context,
        job: Job,
        starts: &[Pose],
        params: &RegisterParams,
        on_chunk: impl OnChunk,
    ) -> Result<Registration> {
        check_starts(starts.len())?;
        if !(params.pose_every > 0 && params.align > 0) {
            return Err(Error::InvalidInput(
                "turns are tried on the fit after a pose alignment: the parameters need the \
                 pose free (pose_every) and an alignment stage (align); for every start run \
                 in full, give Starts::Poses"
                    .into(),
            ));
        }
        let mut best = self.register_jobs(ctx, &jobs_from(job, starts), params, true, on_chunk)?;
        Ok(best.remove(0))
    }

    /// Runs several independent registrations together: each chunk of iterations of all
    /// of them goes in one submission, and a registration that reached its plateau drops
    /// out of the next chunks. With pose optimisation and `params.align`, every job's pose
    /// is first aligned alone. `on_chunk` sees the most iterations done by any job and the
    /// mean of the latest losses. Each result's `milliseconds` is the batch's wall time
    /// until it finished; its losses and codes start with the alignment's.
    pub fn register_batch(
        &self,
        ctx: &Context,
        jobs: &[Job],
        params: &RegisterParams,
        on_chunk: impl OnChunk,
    ) -> Result<Vec<Registration>> {
        self.register_jobs(ctx, jobs, params, false, on_chunk)
    }

    /// [`Registrar::register_batch`]; with `from_starts` (and an alignment stage) the
    /// jobs are one registration's starts: the first is registered, and the turns that
    /// took it to the others are tried on its fit ([`Registrar::check_turns`]); one result
    /// ([`Registrar::register_with_turns`]).
    fn register_jobs(
        &self,
        ctx: &Context,
        jobs: &[Job],
        params: &RegisterParams,
        from_starts: bool,
        mut on_chunk: impl OnChunk,
    ) -> Result<Vec<Registration>> {
        let started = Instant::now();
        params.validate()?;
        let aligning = params.pose_every > 0 && params.align > 0;
        let (jobs, turns) = if from_starts && aligning {
            (&jobs[..1], relative_turns(jobs))
        } else {
            (jobs, Vec::new())
        };
        // With gravity and the pose free, every job's start is levelled first.
        let levelled: Vec<Job> = jobs
            .iter()
            .map(|job| -> Result<Job> {
                let Some(gravity) = job.gravity.filter(|_| params.pose_every > 0) else {
                    return Ok(*job);
                };
                gravity.validate()?;
                Ok(Job {
                    view: View {
                        pose: gravity.level(job.view.pose),
                        ..job.view
                    },
                    ..*job
                })
            })
            .map(|job| match job {
                Ok(job) if params.pose_every > 0 => onto_mask(&job),
                other => other,
            })
            .collect::<Result<_>>()?;
        // With depth, what stands in front of the object outside its mask is unknown from
        // the start (the pose alignment compares masks alone).
        let marked: Vec<Option<Marked>> = levelled
            .iter()
            .map(|job| unknown_in_front(job, params))
            .collect::<Result<_>>()?;
        let levelled: Vec<Job> = levelled
            .iter()
            .zip(&marked)
            .map(|(job, marked)| match marked {
                None => *job,
                Some(marked) => Job {
                    observed: &marked.observed,
                    shaded: marked.shaded.as_deref(),
                    ..*job
                },
            })
            .collect();
        let jobs = &levelled[..];
        if !aligning {
            // With the pose known and depth observed, the mask alone first.
            let masks_first = params.masks_first();
            let first: Option<(Vec<Registration>, Vec<Vec<f32>>)> = match &masks_first {
                None => None,
                Some(first) => Some(
                    self.run(ctx, jobs, Stage::fit(first, None, started), &mut on_chunk)?
                        .into_iter()
                        .map(|s| (s.result, s.coordinates))
                        .unzip(),
                ),
            };
            let fit = Stage {
                first: masks_first.map_or(0, |first| first.iterations),
                ..Stage::fit(params, first.as_ref().map(|(_, codes)| &codes[..]), started)
            };
            let runs = self.run(ctx, jobs, fit, &mut on_chunk)?;
            let fitted = self.hold_unseen(ctx, jobs, runs, fit, &mut on_chunk)?;
            let Some((firsts, _)) = first else {
                return Ok(fitted);
            };
            return Ok(firsts
                .into_iter()
                .zip(fitted)
                .map(|(first, fitted)| {
                    let stages = vec![(STAGE_MASK_FIRST, first.losses.len())];
                    preceded(Registration { stages, ..first }, fitted)
                })
                .collect());
        }
        let align = RegisterParams {
            iterations: params.align,
            loss: params.align_loss,
            shading: None,
            depth: None,
            // One silhouette of the mean shape tells its distance badly (a larger instance
            // looks nearer): the depth, when given, tells it well (the stage below).
            optimize_z: params.optimize_z && params.depth.is_none(),
            ..*params
        };
        let mut aligned: Vec<Registration> = self
            .run(
                ctx,
                jobs,
                Stage::fit(&align, None, started).pose_only(),
                &mut on_chunk,
            )?
            .into_iter()
            .map(|s| Registration {
                stages: vec![(STAGE_ALIGN, s.result.losses.len())],
                ..s.result
            })
            .collect();
        let mut jobs = at_poses(jobs, &aligned);
        // The alignment leaves z where the start put it when depth is observed, and the
        // joint fit's bounded depth cost pulls little from centimetres off (at 5 sigma a
        // pixel's gradient is a fortieth of its largest): the pose first moves by the
        // mask and the depth with a scale REACH times as wide, and the joint fit goes on
        // from there. With the scale free the shape moves too: the mean shape's size is
        // not the instance's, and the pose alone would take the difference for distance.
        let mut done = params.align;
        let mut codes = None;
        if let Some(reach) = params.reach() {
            let pose_only = !params.optimize_scale;
            let reached = self.run(
                ctx,
                &jobs,
                Stage {
                    pose_only,
                    first: done,
                    ..Stage::fit(&reach, None, started)
                },
                &mut on_chunk,
            )?;
            done += reach.iterations;
            let (reached, coordinates): (Vec<Registration>, Vec<Vec<f32>>) = reached
                .into_iter()
                .map(|s| (s.result, s.coordinates))
                .unzip();
            jobs = at_poses(&jobs, &reached);
            codes = Some(coordinates);
            for (a, r) in aligned.iter_mut().zip(reached) {
                a.stages.push((STAGE_REACH, r.losses.len()));
                a.losses.extend(r.losses);
                a.codes.extend(r.codes);
                a.scales.extend(r.scales);
                a.evaluations += r.evaluations;
            }
        }
        let fit = Stage {
            first: done,
            ..Stage::fit(params, codes.as_deref(), started)
        };
        let mut refined = self.run(ctx, &jobs, fit, &mut on_chunk)?;
        if turns.len() > 1 {
            let fitted = refined.remove(0);
            refined = vec![self.check_turns(ctx, &jobs[0], params, fitted, &turns, started)?];
        }
        let refined = self.settle_on_depth(ctx, &jobs, refined, params, started)?;
        let jobs = at_poses(
            &jobs,
            &refined.iter().map(|s| s.result.clone()).collect::<Vec<_>>(),
        );
        let refined = self.hold_unseen(ctx, &jobs, refined, fit, &mut on_chunk)?;
        Ok(aligned
            .into_iter()
            .zip(refined)
            .map(|(a, r)| preceded(a, r))
            .collect())
    }

    /// After a fit (`fitted`, one per job, the jobs at its poses): where a job's views
    /// (two or more) hardly constrain some directions of its code
    /// ([`evidence::held_prior`]), the fit goes on from where it stopped with those
    /// directions held by the strong prior
    /// ([`STAGE_HELD`]); the other jobs keep their fit. `stage`: the fit's (its params,
    /// start time and `first`, the iterations before it; its codes are not used).
    fn hold_unseen(
        &self,
        ctx: &Context,
        jobs: &[Job],
        fitted: Vec<Staged>,
        stage: Stage,
        on_chunk: &mut impl OnChunk,
    ) -> Result<Vec<Registration>> {
        let Stage {
            params,
            started,
            first: done,
            ..
        } = stage;
        let mut results: Vec<Registration> = fitted.iter().map(|s| s.result.clone()).collect();
        let mut held = Vec::new();
        for (i, (job, staged)) in jobs.iter().zip(&fitted).enumerate() {
            if !params.holds_unseen(1 + job.others.len()) {
                continue;
            }
            let Some(inverse_hessian) = &staged.inverse_hessian else {
                continue;
            };
            let coordinates = optimizer::optimizer_coordinates(job.space, params.optimizer);
            let k = job.space.dims();
            let prior = optimizer::prior_matrix(job.space, &coordinates.to_code, k);
            if let Some(matrix) = evidence::held_prior(
                job.space,
                &coordinates.to_code,
                &prior,
                inverse_hessian,
                params.code_prior,
            ) {
                held.push((i, matrix));
            }
        }
        if held.is_empty() {
            return Ok(results);
        }
        let (which, matrices): (Vec<usize>, Vec<Matrix>) = held.into_iter().unzip();
        let held_jobs: Vec<Job> = which.iter().map(|&i| jobs[i]).collect();
        let codes: Vec<Vec<f32>> = which
            .iter()
            .map(|&i| fitted[i].coordinates.clone())
            .collect();
        let first = done + results.iter().map(|r| r.losses.len()).max().unwrap_or(0);
        let again = self.run(
            ctx,
            &held_jobs,
            Stage {
                first,
                priors: Some(&matrices),
                ..Stage::fit(params, Some(&codes), started)
            },
            on_chunk,
        )?;
        for (i, s) in which.into_iter().zip(again) {
            let stages = vec![(STAGE_HELD, s.result.losses.len())];
            results[i] = preceded(results[i].clone(), Registration { stages, ..s.result });
        }
        Ok(results)
    }
}

/// `then` preceded by `first`: its stages, losses, codes and scales first, and its
/// evaluations counted.
fn preceded(first: Registration, mut then: Registration) -> Registration {
    then.stages.splice(0..0, first.stages);
    then.losses.splice(0..0, first.losses);
    then.codes.splice(0..0, first.codes);
    then.scales.splice(0..0, first.scales);
    then.evaluations += first.evaluations;
    then
}
