//! The device's side of a registration: a stage of iterations (in the region of interest
//! where that is a small part of the image; chunks of iterations in one submission, each
//! job stopped on its plateau), one iteration's passes as recorded, and their profile.

use bytemuck::{Pod, Zeroable};

use crate::error::{Error, Result};
use crate::gpu::{spans, Binding, Context, Groups, Recorder, Recording, Timestamps, LOOP_LIMIT};
use crate::shaders;

use super::optimizer::{OptimizerConstants, StateLayout};
use super::region::{Cut, Region};
use super::task::{Stage, Staged, Task};
use super::{Job, OnChunk, RegisterParams, Registrar};

/// Vertex coordinates one dispatch of the latent-gradient pass sums (64 invocations a
/// workgroup, each looping over a 64th; see [`LOOP_LIMIT`]).
const LATENT_SPAN: u32 = 64 * (LOOP_LIMIT / 4);

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct DeformConstants {
    vertex_count: u32,
    dims: u32,
    latent_at: u32,
}
const _: () = assert!(shaders::DEFORM_COMP.takes::<DeformConstants>());

impl Registrar {
    /// One stage of `register_batch` ([`Stage`]).
    pub(super) fn run(
        &self,
        ctx: &Context,
        jobs: &[Job],
        stage: Stage,
        on_chunk: &mut impl OnChunk,
    ) -> Result<Vec<Staged>> {
        // Only the region around the mask and the jobs' silhouettes is rendered and
        // compared where that is a small part of the image ([`Region`]); a stage whose fit
        // ended at the region's border (where the whole image would have compared pixels
        // the region has not) runs again on the whole image, at the region's step.
        let mut run_in = |region: Option<&Region>| {
            let Some(region) = region else {
                return self.run_whole(ctx, jobs, stage, on_chunk);
            };
            let cut: Vec<Cut> = jobs.iter().map(|job| region.cut(job)).collect();
            let cut_jobs: Vec<Job> = jobs.iter().zip(&cut).map(|(j, c)| c.job(j)).collect();
            self.run_whole(ctx, &cut_jobs, stage, on_chunk)
        };
        let (detail, depth_detail) = (stage.params.detail, stage.params.depth_detail);
        let Some(region) = Region::of_interest(jobs, detail, depth_detail)? else {
            return run_in(None);
        };
        let staged = run_in(Some(&region))?;
        if staged
            .iter()
            .zip(jobs)
            .all(|(s, job)| region.holds(job, &s.result))
        {
            return Ok(staged);
        }
        run_in(region.whole(&jobs[0].view.camera).as_ref())
    }

    /// [`Registrar::run`] on the jobs' whole images.
    fn run_whole(
        &self,
        ctx: &Context,
        jobs: &[Job],
        stage: Stage,
        on_chunk: &mut impl OnChunk,
    ) -> Result<Vec<Staged>> {
        let Stage {
            params,
            pose_only,
            codes,
            started,
            first,
            priors,
        } = stage;
        if jobs.is_empty() {
            return Ok(Vec::new());
        }
        let mut tasks = jobs
            .iter()
            .enumerate()
            .map(|(i, job)| {
                let prior = priors.map(|p| &p[i]);
                Task::new(ctx, job, params, codes.map(|c| &c[i][..]), prior)
            })
            .collect::<Result<Vec<_>>>()?;
        let mut rec = Recorder::new(ctx)?;
        for task in &tasks {
            task.scene.record_prepare(&self.renderer, &mut rec)?;
        }
        ctx.submit_and_wait(rec)?;

        let chunk = params.check_every.clamp(1, params.iterations);
        // The last recording, replayed while the same jobs run chunks of the same length.
        let mut cached: Option<(Vec<usize>, usize, Recording)> = None;
        loop {
            let active: Vec<usize> = (0..tasks.len()).filter(|&i| tasks[i].active).collect();
            if active.is_empty() {
                break;
            }
            let n = active
                .iter()
                .map(|&i| chunk.min(params.iterations - tasks[i].done))
                .min()
                .unwrap_or(chunk);
            let reusable = matches!(&cached, Some((a, c, _)) if *a == active && *c == n);
            if !reusable {
                let mut rec = Recorder::new(ctx)?;
                for _ in 0..n {
                    for &i in &active {
                        self.record_iteration(&mut rec, &tasks[i], params, pose_only, None)?;
                    }
                }
                cached = Some((active.clone(), n, rec.finish()?));
            }
            if let Some((_, _, recording)) = &cached {
                ctx.replay(recording)?;
            }
            let mut latest = 0.0;
            for &i in &active {
                let task = &mut tasks[i];
                task.done += n;
                latest += task.check_plateau(params)? / active.len() as f64;
                if !task.active {
                    task.milliseconds = started.elapsed().as_secs_f64() * 1e3;
                }
            }
            let most = tasks.iter().map(|t| t.done).max().unwrap_or(0);
            if on_chunk.chunk(first + most, latest).is_break() {
                return Err(Error::Stopped);
            }
        }
        tasks.iter().map(|task| task.staged(params)).collect()
    }

    /// GPU milliseconds of each pass of one iteration, for `repeats` iterations of `job`
    /// (each submitted alone, so that every one is timed from the device's timestamps).
    pub fn profile(
        &self,
        ctx: &Context,
        job: &Job,
        params: &RegisterParams,
        repeats: usize,
    ) -> Result<Vec<PassTimes>> {
        let task = self.prepared(ctx, job, params, false)?;
        let outer = Timestamps::new(ctx, 4)?;
        let inner = Timestamps::new(ctx, 3)?;
        let mut times = Vec::new();
        for _ in 0..repeats.min(params.iterations) {
            let mut rec = Recorder::new(ctx)?;
            self.record_iteration(&mut rec, &task, params, false, Some((&outer, &inner)))?;
            ctx.submit_and_wait(rec)?;
            let (o, i) = (outer.read_ms()?, inner.read_ms()?);
            times.push(PassTimes {
                deform: o[1] - o[0],
                forward: i[1] - i[0],
                backward: i[2] - i[1],
                update: o[3] - o[2],
                total: o[3] - o[0],
            });
        }
        Ok(times)
    }

    /// The renderer's passes of one iteration of `job` (after one iteration at its start),
    /// each submitted alone and timed on the host's clock `repeats` times
    /// ([`crate::diff::Scene::profile`]): their names and milliseconds.
    pub fn pass_profile(
        &self,
        ctx: &Context,
        job: &Job,
        params: &RegisterParams,
        repeats: usize,
    ) -> Result<Vec<(&'static str, Vec<f64>)>> {
        let task = self.prepared(ctx, job, params, true)?;
        task.scene.profile(ctx, &self.renderer, repeats)
    }

    /// `job`'s task with its scene prepared on the device, and with `iterate` one
    /// iteration run from its start: where the profiles begin.
    fn prepared<'a>(
        &self,
        ctx: &Context,
        job: &Job<'a>,
        params: &RegisterParams,
        iterate: bool,
    ) -> Result<Task<'a>> {
        let task = Task::new(ctx, job, params, None, None)?;
        let mut rec = Recorder::new(ctx)?;
        task.scene.record_prepare(&self.renderer, &mut rec)?;
        if iterate {
            self.record_iteration(&mut rec, &task, params, false, None)?;
        }
        ctx.submit_and_wait(rec)?;
        Ok(task)
    }

    /// Records one iteration of one registration; with `timing`, the outer timestamps
    /// mark start, after deform, after the renderer's passes and end, the inner ones the
    /// renderer's own (see [`Scene::record`]).
    fn record_iteration(
        &self,
        rec: &mut Recorder,
        task: &Task,
        params: &RegisterParams,
        pose_only: bool,
        timing: Option<(&Timestamps, &Timestamps)>,
    ) -> Result<()> {
        let (m, k) = (task.m, task.dims);
        let scene = &task.scene;
        if let Some((outer, _)) = timing {
            rec.reset_timestamps(outer);
            rec.timestamp(outer, 0);
        }
        rec.run_compute(
            &self.deform,
            &[
                Binding::buffer(&task.base),
                Binding::buffer(&task.basis),
                Binding::buffer(&task.state),
                Binding::buffer(scene.mesh().positions()),
            ],
            &DeformConstants {
                vertex_count: m as u32,
                dims: k as u32,
                latent_at: StateLayout::new(k, 0).latent,
            },
            Groups::Count((m as u32).div_ceil(64), 1, 1),
        );
        rec.memory_barrier();
        if let Some((outer, _)) = timing {
            rec.timestamp(outer, 1);
        }
        scene.record(&self.renderer, rec, timing.map(|t| t.1))?;
        self.record_rig(rec, task, 0);
        if let Some((outer, _)) = timing {
            rec.timestamp(outer, 2);
        }
        rec.fill_buffer(&task.grad_latent, 0);
        rec.memory_barrier();
        for (first, end) in spans(3 * m as u32, LATENT_SPAN) {
            rec.run_compute(
                &self.latent_gradient,
                &[
                    Binding::buffer(&task.basis),
                    Binding::buffer(scene.vertex_gradient()),
                    Binding::buffer(&task.grad_latent),
                ],
                &[m as u32, k as u32, first, end],
                Groups::Count(1, 1, k as u32),
            );
            rec.memory_barrier();
        }
        self.optimizers.record_step(
            rec,
            &OptimizerConstants::new(k, params, pose_only),
            params.optimizer,
            [
                Binding::buffer(&task.state),
                Binding::buffer(&task.grad_latent),
                Binding::buffer(scene.pose_gradient()),
                Binding::buffer(scene.loss_stats()),
                Binding::buffer(scene.views().views()),
            ],
        );
        rec.memory_barrier();
        self.record_rig(rec, task, 1);
        if let Some((outer, _)) = timing {
            rec.timestamp(outer, 3);
        }
        Ok(())
    }

    /// With several views, one stage of `glsl/rig.comp` (and a barrier after it): 0 sums
    /// the views' pose gradients and losses into the first view's, 1 moves the other views
    /// with the first.
    fn record_rig(&self, rec: &mut Recorder, task: &Task, stage: u32) {
        let Some(rig) = &task.rig else {
            return;
        };
        let scene = &task.scene;
        let views = scene.views().count();
        rec.run_compute(
            &self.rig,
            &[
                Binding::buffer(scene.views().views()),
                Binding::buffer(scene.pose_gradient()),
                Binding::buffer(scene.loss_stats()),
                Binding::buffer(rig),
            ],
            &[views, stage],
            Groups::Count(views.div_ceil(64), 1, 1),
        );
        rec.memory_barrier();
    }
}

/// Device time of one iteration's passes, milliseconds.
#[derive(Clone, Copy, Debug, Default)]
pub struct PassTimes {
    /// C + d0 + B s.
    pub deform: f64,
    /// Rasterize, classify, antialias, loss.
    pub forward: f64,
    /// Backward to the vertices and the pose.
    pub backward: f64,
    /// dL/ds and the optimiser step.
    pub update: f64,
    /// The whole iteration, from the start of deform to the end of the update.
    pub total: f64,
}
