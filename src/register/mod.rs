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

use bytemuck::{Pod, Zeroable};
use glam::{DMat3, DVec3};

use crate::cpd::linalg::Matrix;
use crate::diff::{DepthLoss, DiffRenderer, ObservedDepth, Scene, SceneDesc, Shading};
use crate::error::{Error, Result};
use crate::gpu::{
    spans, Binding, Buffer, ComputePipeline, Context, Groups, Recorder, Recording, Timestamps,
    LOOP_LIMIT,
};
use crate::loss::Loss;
use crate::raster::View;
use crate::shaders;
use crate::shape::ShapeSpace;
use crate::{Camera, Pose};

mod nearest;
mod optimizer;
mod region;

pub use optimizer::Optimizer;
use optimizer::{
    optimizer_coordinates, OptimizerConstants, Optimizers, StateLayout, BFGS_MAX_DIMS, MAX_DIMS,
};
use region::Cut;
pub use region::Region;

/// The most iterations (or alignment iterations) one registration may ask for.
pub const MAX_ITERATIONS: usize = 100_000;
/// Vertex coordinates one dispatch of the latent-gradient pass sums (64 invocations a
/// workgroup, each looping over a 64th; see [`LOOP_LIMIT`]).
const LATENT_SPAN: u32 = 64 * (LOOP_LIMIT / 4);

/// How to register.
#[derive(Clone, Copy, Debug)]
pub struct RegisterParams {
    /// Iterations of the registration, besides the pose alignment's `align`.
    pub iterations: usize,
    /// Momentum of SGD (Adam's first-moment decay), in `[0, 1)`.
    pub momentum: f64,
    /// Learning-rate decay per iteration.
    pub decay: f64,
    /// Length of the first latent step, in standard deviations of the training codes
    /// (SGD's learning rate is set from the first gradient so that its step has this length).
    pub latent_step: f64,
    /// Update the pose once every this many iterations (0: the pose stays fixed).
    pub pose_every: usize,
    /// With pose optimisation: iterations before `iterations` that align the pose alone
    /// with `align_loss` (the shape would otherwise bend to explain a misaligned
    /// silhouette, and a distance loss reaches further than a mask loss).
    pub align: usize,
    /// Loss of the pose alignment stage.
    pub align_loss: Loss,
    /// Let the z translation move too (ill-posed with shape from one view).
    pub optimize_z: bool,
    /// First translation and rotation steps of the pose (metres, radians).
    pub translation_step: f64,
    /// First rotation step of the pose, radians.
    pub rotation_step: f64,
    /// How the code (and the pose) are updated.
    pub optimizer: Optimizer,
    /// Loss against each job's mask after the alignment.
    pub loss: Loss,
    /// Compare Lambert shading with each job's `shaded` image instead of the mask (the
    /// pose alignment still compares masks); the loss must be mse.
    pub shading: Option<Shading>,
    /// Compare each job's observed depth too (the pose alignment does not); the loss
    /// must be mse. With depth the z translation is observed: set `optimize_z`.
    pub depth: Option<DepthLoss>,
    /// Weight of a Gaussian prior on the code: `code_prior * |s|^2` joins the loss, s the
    /// code in training standard deviations (each dimension over its spread in the
    /// training set), so a typical training shape costs about the weight times the
    /// dimensions. It decides what the images leave open, such as a shape shifted in its
    /// own frame against a shifted pose. 0 (the default): none.
    pub code_prior: f64,
    /// Fit one uniform scale of the shape too (an instance larger or smaller than the
    /// training set's), within [`SCALE_RANGE`]: observable where depth or a further view
    /// tells the distance; from one mask a scale trades against the distance.
    pub optimize_scale: bool,
    /// Read the loss back every this many iterations; stop when it improved by less than
    /// `plateau` (relative) over the last chunk.
    pub check_every: usize,
    /// Relative improvement over a chunk below which a registration stops, in
    /// `[0, 1)`.
    pub plateau: f64,
    /// The pixels across the object a single view is rendered and compared at, at least:
    /// an object larger in its image is rendered at a coarser whole step (each pixel the
    /// mean of step x step of the image's, [`Region`]), which costs a step squared fewer
    /// pixels. 0 (the default): the image's own pixels, where the loss and gradients are
    /// exactly the whole image's. The schedules use [`DETAIL`].
    pub detail: u32,
}

/// A registration's stage ([`Registration::stages`]): the fit (with the pose known, or the
/// joint fit of pose and shape after an alignment).
pub const STAGE_FIT: &str = "fit";
/// The pose aligned alone (`RegisterParams::align`).
pub const STAGE_ALIGN: &str = "pose alignment";
/// The pose brought to the measured depth ([`RegisterParams::reach`]).
pub const STAGE_REACH: &str = "depth reach";
/// The joint fit again from a turned start that scored better (the registration from
/// starts), in place of the first joint fit.
pub const STAGE_TURNED: &str = "fit from a turn";

/// The detail of the registration schedules ([`RegisterParams::detail`]): an object over
/// 128 pixels across is rendered at a step of 2 or more. On a real 640 x 480 frame (a mug
/// 230 pixels across, a step of 3) a registration from pose noise costs a third of the
/// full resolution's, its error within 1% (docs/evaluation.md).
pub const DETAIL: u32 = 64;

impl RegisterParams {
    /// An error naming the first parameter out of range: 1 to [`MAX_ITERATIONS`]
    /// iterations (the optimiser's state holds every iteration's loss and code, with f32
    /// indices on the device), steps, momentum, decay and plateau finite and in range, and
    /// a valid depth loss.
    pub fn validate(&self) -> Result<()> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let problem = if self.iterations == 0 {
            Some("registration needs at least one iteration".to_string())
        } else if let Some((what, count)) = [
            ("iterations", self.iterations),
            ("alignment iterations", self.align),
        ]
        .into_iter()
        .find(|&(_, count)| count > MAX_ITERATIONS)
        {
            Some(format!(
                "{count} {what}: at most {MAX_ITERATIONS} are supported"
            ))
        } else if !(positive(self.latent_step) && self.latent_step <= 3.0) {
            Some(format!(
                "latent step {} must be in (0, 3] training standard deviations",
                crate::error::show(self.latent_step)
            ))
        } else if !(positive(self.translation_step) && self.translation_step <= 1.0) {
            Some(format!(
                "translation step {} must be in (0, 1] m",
                crate::error::show(self.translation_step)
            ))
        } else if !(positive(self.rotation_step) && self.rotation_step <= 1.0) {
            Some(format!(
                "rotation step {} must be in (0, 1] rad",
                crate::error::show(self.rotation_step)
            ))
        } else if !(0.0..1.0).contains(&self.momentum)
            || !(0.0..=1.0).contains(&self.decay)
            || self.decay == 0.0
        {
            Some(format!(
                "momentum {} must be in [0, 1) and decay {} in (0, 1]",
                self.momentum, self.decay
            ))
        } else if !(0.0..=1.0).contains(&self.code_prior) {
            Some(format!(
                "code prior {} must be in [0, 1]",
                crate::error::show(self.code_prior)
            ))
        } else if !(0.0..1.0).contains(&self.plateau) {
            Some(format!("plateau {} must be in [0, 1)", self.plateau))
        } else if self.detail != 0 && self.detail < 16 {
            Some(format!(
                "detail {} must be 0 (the image's pixels) or at least 16 pixels",
                self.detail
            ))
        } else {
            None
        };
        if let Some(p) = problem {
            return Err(Error::InvalidInput(p));
        }
        if let Some(depth) = &self.depth {
            depth.validate()?;
        }
        Ok(())
    }

    /// Iterations at most, the pose alignment's included (and with depth and z free, the
    /// stage that brings the aligned pose to the measured depth).
    pub fn total_iterations(&self) -> usize {
        let aligned = self.pose_every > 0 && self.align > 0;
        self.iterations
            + if aligned { self.align } else { 0 }
            + self.reach().map_or(0, |reach| reach.iterations)
    }

    /// The stage after the alignment that brings the pose to the measured depth
    /// ([`REACH`]), where it runs: with an alignment, depth and z free.
    pub fn reach(&self) -> Option<RegisterParams> {
        let depth = self.depth?;
        (self.pose_every > 0 && self.align > 0 && self.optimize_z).then_some(RegisterParams {
            iterations: REACH_ITERATIONS,
            shading: None,
            depth: Some(DepthLoss {
                scale: depth.scale * REACH,
                ..depth
            }),
            ..*self
        })
    }
}

impl RegisterParams {
    /// The schedule `vkdr register` and `vkdr eval` use with the pose known, for views of
    /// `pixels` pixels: 30 BFGS iterations of the code, the prior those pixels imply
    /// ([`observation_prior`]), a large object rendered at [`DETAIL`].
    pub fn known_pose(pixels: usize) -> Self {
        Self {
            iterations: 30,
            optimizer: Optimizer::Bfgs,
            code_prior: observation_prior(pixels),
            detail: DETAIL,
            ..Self::default()
        }
    }

    /// The schedule `vkdr register --optimize-pose` and `vkdr eval` use with the pose
    /// free (chosen on a validation dataset, another seed than the reported one): the pose
    /// aligned alone for 15 iterations with the distance loss (with depth and `optimize_z`
    /// then [`REACH_ITERATIONS`] with mask and depth at a wide scale, [`REACH`]), then 60 of
    /// pose and shape together with BFGS. The z translation stays fixed: set `optimize_z`
    /// where depth or a further view observes it.
    pub fn free_pose(pixels: usize) -> Self {
        Self {
            iterations: 60,
            pose_every: 1,
            align: 15,
            align_loss: Loss::Distance,
            translation_step: 0.01,
            rotation_step: 0.05,
            ..Self::known_pose(pixels)
        }
    }
}

/// The turn between the starts of a registration with the pose free (`vkdr register`
/// turns its starts about the up axis by multiples of it, [`turned_starts`]; `vkdr eval`
/// by its rotation noise, the same 15 degrees by default).
pub const START_TURN: f64 = 15f64.to_radians();

/// Starts of a registration with the pose free unless told otherwise: the start and it
/// turned by +-1 and +-2 [`START_TURN`]s (against a rotation that stops in a local
/// minimum, as a mug's handle; docs/evaluation.md has the cost). `vkdr register`, `vkdr
/// eval`, `eval-frames`, `bench-register` and the Python module take it from here.
pub const DEFAULT_STARTS: usize = 5;
/// The most starts one registration takes (each start's turn is scored on the first
/// start's fit; past +-4 turns of 15 degrees a start is no longer near the first).
pub const MAX_STARTS: usize = 8;

/// How a registration uses several starting poses ([`Registrar::register_starts`]).
#[derive(Clone, Copy, Debug)]
pub enum Starts<'a> {
    /// Every pose registered in full (one batch), the least final loss kept.
    Poses(&'a [Pose]),
    /// The first pose registered, then the turns that take it to the others tried on its
    /// fit ([`Registrar::register_with_turns`]; [`turned_starts`] makes such poses).
    Turns(&'a [Pose]),
}

impl<'a> Starts<'a> {
    /// The schedules' rule: turns where `params` align the pose first (the pose free),
    /// every pose in full otherwise.
    pub fn for_params(poses: &'a [Pose], params: &RegisterParams) -> Self {
        if params.pose_every > 0 && params.align > 0 {
            Starts::Turns(poses)
        } else {
            Starts::Poses(poses)
        }
    }
}

/// One job per starting pose: `job` from each of `poses`.
fn jobs_from<'a>(job: Job<'a>, poses: &[Pose]) -> Vec<Job<'a>> {
    poses
        .iter()
        .map(|&pose| Job {
            view: View { pose, ..job.view },
            ..job
        })
        .collect()
}

/// An error unless `count` is 1 to [`MAX_STARTS`].
pub fn check_starts(count: usize) -> Result<()> {
    if (1..=MAX_STARTS).contains(&count) {
        return Ok(());
    }
    Err(Error::InvalidInput(format!(
        "starts must be 1 to {MAX_STARTS}, not {count}"
    )))
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            momentum: 0.9,
            decay: 0.95,
            latent_step: 0.5,
            pose_every: 0,
            align: 0,
            align_loss: Loss::Distance,
            optimize_z: false,
            translation_step: 0.004,
            rotation_step: 0.02,
            optimizer: Optimizer::Sgd,
            loss: Loss::Mse,
            shading: None,
            depth: None,
            code_prior: 0.0,
            optimize_scale: false,
            check_every: 10,
            plateau: 1e-4,
            detail: 0,
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
const _: () = assert!(shaders::DEFORM_COMP.takes::<DeformConstants>());

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
    /// ([`STAGE_FIT`], [`STAGE_ALIGN`], [`STAGE_REACH`], [`STAGE_TURNED`]) and how many
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
    /// (fewer than asked where the loss reached its plateau), and with several starts
    /// the turns' checks and any joint fit that a turned one replaced. The time,
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

/// With depth and an occlusion tolerance: the job's mask (and shading) with the pixels
/// that its depth shows in front of the object marked unknown
/// ([`crate::loss::in_front_of_mask`], per view); None where nothing is.
fn unknown_in_front(job: &Job, params: &RegisterParams) -> Result<Option<Marked>> {
    let (Some(loss), Some(depth)) = (params.depth, job.depth) else {
        return Ok(None);
    };
    let pixels = (job.view.camera.width * job.view.camera.height) as usize;
    if depth.len() != job.observed.len() || depth.len() % pixels.max(1) != 0 {
        return Ok(None); // Scene::new names the mismatch.
    }
    let hidden: Vec<f32> = job
        .observed
        .chunks(pixels)
        .zip(depth.chunks(pixels))
        .flat_map(|(mask, depth)| crate::loss::in_front_of_mask(mask, 1, depth, loss.occlusion))
        .collect();
    if hidden.iter().all(|&h| h == 0.0) {
        return Ok(None);
    }
    let mut observed = job.observed.to_vec();
    crate::loss::mark_unknown(&mut observed, 1, &hidden)?;
    let shaded = match job.shaded {
        Some(shaded) if shaded.len() == hidden.len() => {
            let mut shaded = shaded.to_vec();
            crate::loss::mark_unknown(&mut shaded, 1, &hidden)?;
            Some(shaded)
        }
        other => other.map(<[f32]>::to_vec),
    };
    Ok(Some(Marked { observed, shaded }))
}

/// `job` with its start moved onto the observed mask where the mean shape, projected at
/// the start, lands on none of the mask's pixels: across the line of sight (x and y at the
/// start's distance), so that the centre of its projected vertices lies on the centre of
/// the mask's pixels (first view). Where what surrounds the mask is unknown (an occluder
/// found in the depth, or an ignore mask), a silhouette wholly inside the unknown pixels
/// costs nothing and has no gradient: the registration would stay where it started. A
/// start that lands on the mask is kept as it is.
fn onto_mask<'a>(job: &Job<'a>) -> Result<Job<'a>> {
    let camera = &job.view.camera;
    let (width, height) = (camera.width as usize, camera.height as usize);
    let Some(mask) = job.observed.get(..width * height) else {
        return Ok(*job); // Scene::new names the mismatch.
    };
    let pose = job.view.pose;
    let rotation = pose.rotation_matrix();
    let mut centre = (0.0, 0.0, 0usize);
    let mut lands = false;
    for vertex in job.space.vertices(&vec![0.0; job.space.dims()])? {
        let p = rotation * vertex + pose.translation;
        if p.z <= camera.near {
            continue;
        }
        let (u, v) = camera.project(p);
        centre = (centre.0 + u, centre.1 + v, centre.2 + 1);
        let (column, row) = (u.floor(), v.floor());
        lands |= column >= 0.0
            && row >= 0.0
            && (column as usize) < width
            && (row as usize) < height
            && mask[row as usize * width + column as usize] > 0.0;
    }
    let mut seen = (0.0, 0.0, 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m > 0.0) {
        let (column, row) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
        seen = (seen.0 + column, seen.1 + row, seen.2 + 1);
    }
    if lands || centre.2 == 0 || seen.2 == 0 {
        return Ok(*job);
    }
    let (du, dv) = (
        seen.0 / seen.2 as f64 - centre.0 / centre.2 as f64,
        seen.1 / seen.2 as f64 - centre.1 / centre.2 as f64,
    );
    let z = pose.translation.z;
    let translation = pose.translation + DVec3::new(du * z / camera.fx, dv * z / camera.fy, 0.0);
    Ok(Job {
        view: View {
            pose: Pose {
                translation,
                ..pose
            },
            ..job.view
        },
        ..*job
    })
}

/// A job's observed images with what stands in front of the object marked unknown.
struct Marked {
    observed: Vec<f32>,
    shaded: Option<Vec<f32>>,
}

/// The turns (radians) of [`turned_starts`]: 0, +`step`, -`step`, +2 `step`, -2 `step`,
/// ..., `count` of them.
pub fn start_turns(count: usize, step: f64) -> Vec<f64> {
    (0..count)
        .map(|j| {
            let turns = j.div_ceil(2) as f64 * step;
            if j % 2 == 1 {
                turns
            } else {
                -turns
            }
        })
        .collect()
}

/// `count` starting poses for [`Registrar::register_starts`]: `pose`, then `pose`
/// with the object first turned about its own `up` axis (through its origin) by each
/// further [`start_turns`], so that a start lies on either side of a minimum next to
/// `pose`'s.
pub fn turned_starts(pose: Pose, up: DVec3, count: usize, step: f64) -> Vec<Pose> {
    start_turns(count, step)
        .into_iter()
        .map(|angle| {
            let turn = DMat3::from_axis_angle(up.normalize(), angle);
            Pose {
                translation: pose.translation,
                rotation: glam::DQuat::from_mat3(&(pose.rotation_matrix() * turn)).to_scaled_axis(),
            }
        })
        .collect()
}

/// The code prior's weight ([`RegisterParams::code_prior`]) that an observation of
/// `pixels` pixels per view implies. The loss is a mean of per-pixel squared residuals
/// over the N pixels; with pixel noise of variance sigma^2 its negative log-likelihood is
/// N loss / (2 sigma^2), and the Gaussian prior's is |s|^2 / 2 in training standard
/// deviations, so the posterior's is (N / 2 sigma^2) (loss + sigma^2 / N |s|^2): weight
/// sigma^2 / N. sigma = 1/8: a mask's boundary placed to an eighth of a pixel's coverage
/// (calibrated on the generated set: with sigma^2 = 1/4, a binary pixel's largest variance,
/// known-pose errors of the seed-1 bottles rose from 0.30 to 0.47 mm; at 1/64 they stay).
/// Weak where the images decide, it makes the far tails of the training distribution cost:
/// a code 30 SD out in one dimension costs as much as 14 wrong pixels.
pub fn observation_prior(pixels: usize) -> f64 {
    1.0 / (64.0 * pixels.max(1) as f64)
}

/// The range of [`RegisterParams::optimize_scale`]'s scale: its optimiser coordinate is
/// bounded as a code coordinate is (+-[`CODE_BOUND`]), one unit a quarter of the size: 0.25
/// to 1.75 (a real master chef can is 1.55 times the mean of the two training cans whose
/// space registers it; at 0.5 to 1.5 it ended on the bound, 4% small and 10 mm off in z).
pub const SCALE_RANGE: (f64, f64) = (1.0 - CODE_BOUND * SCALE_UNIT, 1.0 + CODE_BOUND * SCALE_UNIT);
/// The relative scale of one optimiser unit of the scale coordinate.
const SCALE_UNIT: f64 = 0.25;

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

/// Per squared radian of tilt past [`Gravity::tolerance`], as the optimisers add it to the
/// loss (`glsl/include/objective.glsl`, GRAVITY_WEIGHT).
pub const GRAVITY_WEIGHT: f64 = 100.0;

/// Which way is up: a robot knows it from its table plane or its IMU. The registration
/// keeps the object's up axis within `tolerance` of `direction` (a loss of
/// [`GRAVITY_WEIGHT`] per squared radian beyond it), and starts levelled; the rotation
/// about the up axis stays free.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gravity {
    /// The object's up axis in its own frame (the category's, `info.json`'s `up_axis`).
    pub up: DVec3,
    /// Up in the (first) camera's frame: the support plane's normal, away from it.
    pub direction: DVec3,
    /// Radians of tilt that cost nothing.
    pub tolerance: f64,
}

impl Gravity {
    /// An error for a zero or non-finite axis or direction, or a tolerance outside
    /// [0, pi/2).
    pub fn validate(&self) -> Result<()> {
        for (what, v) in [("up axis", self.up), ("gravity direction", self.direction)] {
            if !(v.is_finite() && v.length() > 0.0) {
                return Err(Error::InvalidInput(format!(
                    "the {what} must be a nonzero direction, not {v}"
                )));
            }
        }
        if !(self.tolerance.is_finite()
            && (0.0..std::f64::consts::FRAC_PI_2).contains(&self.tolerance))
        {
            return Err(Error::InvalidInput(format!(
                "the tilt tolerance must be in [0, 90) degrees, not {} rad",
                crate::error::show(self.tolerance)
            )));
        }
        Ok(())
    }

    /// The angle (radians) between the object's up axis at `pose` and up.
    pub fn tilt(&self, pose: &Pose) -> f64 {
        let v = pose.rotation_matrix() * self.up.normalize();
        v.dot(self.direction.normalize()).clamp(-1.0, 1.0).acos()
    }

    /// `pose` turned by the least rotation (about the object's origin) that makes its up
    /// axis point up; a pose within the tolerance stays as it is.
    pub fn level(&self, pose: Pose) -> Pose {
        if self.tilt(&pose) <= self.tolerance {
            return pose;
        }
        let r = pose.rotation_matrix();
        let turn = glam::DQuat::from_rotation_arc(
            (r * self.up.normalize()).normalize(),
            self.direction.normalize(),
        );
        Pose {
            translation: pose.translation,
            rotation: glam::DQuat::from_mat3(&(DMat3::from_quat(turn) * r)).to_scaled_axis(),
        }
    }
}

/// The optimisers keep each code coordinate (in their own units, see
/// `optimizer_coordinates`) within this many units of the mean shape, as
/// `glsl/optimizer.comp` and `glsl/bfgs.comp` do.
pub const CODE_BOUND: f64 = 3.0;

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
    /// it). Needs the pose free with an alignment stage (`params.pose_every` and
    /// `params.align` > 0): the turns are tried on the aligned fit. An error otherwise,
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
            let runs = self.run(ctx, jobs, params, false, None, started, 0, &mut on_chunk)?;
            return Ok(runs.into_iter().map(|s| s.result).collect());
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
            .run(ctx, jobs, &align, true, None, started, 0, &mut on_chunk)?
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
                &reach,
                pose_only,
                None,
                started,
                done,
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
        let mut refined = self.run(
            ctx,
            &jobs,
            params,
            false,
            codes.as_deref(),
            started,
            done,
            &mut on_chunk,
        )?;
        if turns.len() > 1 {
            let fitted = refined.remove(0);
            refined = vec![self.check_turns(ctx, &jobs[0], params, fitted, &turns, started)?];
        }
        Ok(aligned
            .into_iter()
            .zip(refined.into_iter().map(|s| s.result))
            .map(|(a, mut r)| {
                r.stages.splice(0..0, a.stages);
                r.losses.splice(0..0, a.losses);
                r.codes.splice(0..0, a.codes);
                r.scales.splice(0..0, a.scales);
                r.evaluations += a.evaluations;
                r
            })
            .collect())
    }

    /// After the joint fit from the first start: the fitted shape and pose turned as each
    /// start was turned from the first (`turns`, object frame, the first the identity),
    /// about the fitted shape's own axis, each scored by its loss at one evaluation. A
    /// mask alone cannot choose among the starts before the fit (a mug's handle is a few
    /// pixels against the body's hundreds: aligned starts' losses differ by about 0.1%);
    /// the fitted shape can. Where a turned pose's loss is [`TURN_GAIN`] below the fit's,
    /// the joint fit runs again from it with the fitted code, and the lower final loss is
    /// kept. Costs one evaluation per turn, and a second joint fit only where a turn is
    /// better.
    fn check_turns(
        &self,
        ctx: &Context,
        job: &Job,
        params: &RegisterParams,
        fitted: Staged,
        turns: &[DMat3],
        started: Instant,
    ) -> Result<Staged> {
        let pose = fitted.result.pose;
        let r = pose.rotation_matrix();
        // Turned about the fitted shape's own axis, not the frame's origin: a bounding
        // box centred mug has its body's axis a centimetre or two from the origin.
        let pivot = turns
            .iter()
            .map(|turn| glam::DQuat::from_mat3(turn).to_axis_angle())
            .find(|(_, angle)| angle.abs() > 1e-6)
            .map_or(DVec3::ZERO, |(axis, _)| {
                symmetry_pivot(&fitted.result.vertices, axis)
            });
        let turned: Vec<Job> = turns
            .iter()
            .map(|turn| Job {
                view: View {
                    pose: Pose {
                        translation: pose.translation + r * (pivot - *turn * pivot),
                        rotation: glam::DQuat::from_mat3(&(r * *turn)).to_scaled_axis(),
                    },
                    ..job.view
                },
                ..*job
            })
            .collect();
        let score = RegisterParams {
            iterations: TURN_ITERATIONS,
            ..*params
        };
        let codes = vec![fitted.coordinates.clone(); turned.len()];
        let scored = self.run(
            ctx,
            &turned,
            &score,
            true,
            Some(&codes),
            started,
            0,
            &mut |_, _| {},
        )?;
        let loss = |s: &Staged| s.result.losses.first().copied().unwrap_or(f64::INFINITY);
        let (best, best_loss) = scored
            .iter()
            .enumerate()
            .map(|(i, s)| (i, loss(s)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("at least one turn");
        let mut fitted = fitted;
        fitted.result.evaluations += scored.iter().map(|s| s.result.evaluations).sum::<usize>();
        if best == 0 || best_loss > (1.0 - TURN_GAIN) * loss(&scored[0]) {
            fitted.result.milliseconds = started.elapsed().as_secs_f64() * 1e3;
            return Ok(fitted);
        }
        let again = self
            .run(
                ctx,
                &turned[best..best + 1],
                params,
                false,
                Some(&codes[..1]),
                started,
                0,
                &mut |_, _| {},
            )?
            .remove(0);
        let evaluations = fitted.result.evaluations + again.result.evaluations;
        let mut kept = if again.result.loss < fitted.result.loss {
            Staged {
                result: Registration {
                    stages: vec![(STAGE_TURNED, again.result.losses.len())],
                    ..again.result
                },
                ..again
            }
        } else {
            fitted
        };
        kept.result.evaluations = evaluations;
        kept.result.milliseconds = started.elapsed().as_secs_f64() * 1e3;
        Ok(kept)
    }

    /// One stage of `register_batch` (`pose_only`: the latent code stays where it
    /// starts), each job's code starting at `codes` (device coordinates, as a stage
    /// returns them) or the mean; `on_chunk` counts iterations from `first`.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        ctx: &Context,
        jobs: &[Job],
        params: &RegisterParams,
        pose_only: bool,
        codes: Option<&[Vec<f32>]>,
        started: Instant,
        first: usize,
        on_chunk: &mut impl OnChunk,
    ) -> Result<Vec<Staged>> {
        // Only the region around the mask and the jobs' silhouettes is rendered and
        // compared where that is a small part of the image ([`Region`]); a stage whose fit
        // ended at the region's border (where the whole image would have compared pixels
        // the region has not) runs again on the whole image, at the region's step.
        let mut run_in = |region: Option<&Region>| {
            let Some(region) = region else {
                return self.run_whole(
                    ctx, jobs, params, pose_only, codes, started, first, on_chunk,
                );
            };
            let cut: Vec<Cut> = jobs.iter().map(|job| region.cut(job)).collect();
            let cut_jobs: Vec<Job> = jobs.iter().zip(&cut).map(|(j, c)| c.job(j)).collect();
            self.run_whole(
                ctx, &cut_jobs, params, pose_only, codes, started, first, on_chunk,
            )
        };
        let Some(region) = Region::of_interest(jobs, params.detail)? else {
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
        run_in(Region::whole(&jobs[0].view.camera, region.step).as_ref())
    }

    /// [`Registrar::run`] on the jobs' whole images.
    #[allow(clippy::too_many_arguments)]
    fn run_whole(
        &self,
        ctx: &Context,
        jobs: &[Job],
        params: &RegisterParams,
        pose_only: bool,
        codes: Option<&[Vec<f32>]>,
        started: Instant,
        first: usize,
        on_chunk: &mut impl OnChunk,
    ) -> Result<Vec<Staged>> {
        if jobs.is_empty() {
            return Ok(Vec::new());
        }
        let mut tasks = jobs
            .iter()
            .enumerate()
            .map(|(i, job)| Task::new(ctx, job, params, codes.map(|c| &c[i][..])))
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
        let task = Task::new(ctx, job, params, None)?;
        let mut rec = Recorder::new(ctx)?;
        task.scene.record_prepare(&self.renderer, &mut rec)?;
        ctx.submit_and_wait(rec)?;
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

/// A further camera of a multi-view registration: it sees the same object, from a pose
/// known relative to the first camera (a point x in the first camera's frame is
/// `from_first.apply(x)` in this one's). Its image has the first view's size.
#[derive(Clone, Copy, Debug)]
pub struct OtherView {
    /// Intrinsics and image size of this camera.
    pub camera: Camera,
    /// Transform from the first camera's frame to this camera's frame.
    pub from_first: Pose,
}

/// One registration to run: a shape space, an observed mask (`[row][column]`, nonzero =
/// object), optionally the observed shading (grey, `[row][column]`, background 0; compared
/// when `RegisterParams::shading` is set) and depth (metres, 0 = not measured; compared
/// when `RegisterParams::depth` is set), and the view it was seen through (its pose is
/// the initial pose). With `others`, the object is seen by several cameras at once: one
/// code and one object pose explain every view, and each image holds every view's,
/// `[view][row][column]`, the first view first.
#[derive(Clone, Copy)]
pub struct Job<'a> {
    /// The shape space whose latent code is fitted.
    pub space: &'a ShapeSpace,
    /// Observed mask, `[row][column]` (`[view][row][column]` with `others`),
    /// nonzero = object.
    pub observed: &'a [f32],
    /// Observed grey shading in the mask's layout, background 0.
    pub shaded: Option<&'a [f32]>,
    /// Observed depth in the mask's layout, metres, 0 = not measured.
    pub depth: Option<&'a [f32]>,
    /// The (first) camera and the initial object pose.
    pub view: View,
    /// Further cameras of a multi-view registration (empty: one view).
    pub others: &'a [OtherView],
    /// Which way is up, where known (used when the pose is optimised).
    pub gravity: Option<Gravity>,
    /// The pixel count each view's loss is averaged over (None: the view's own): a job
    /// cut to a region of interest of a larger image keeps the larger image's
    /// ([`SceneDesc::loss_pixels`]).
    pub loss_pixels: Option<u64>,
}

impl<'a> Job<'a> {
    /// A registration of `space` to an observed mask seen through `view`.
    pub fn new(space: &'a ShapeSpace, observed: &'a [f32], view: View) -> Self {
        Self {
            space,
            observed,
            shaded: None,
            depth: None,
            view,
            others: &[],
            gravity: None,
            loss_pixels: None,
        }
    }

    /// The same with the observed shading too.
    pub fn with_shading(self, shaded: &'a [f32]) -> Self {
        Self {
            shaded: Some(shaded),
            ..self
        }
    }

    /// The same with the observed depth too.
    pub fn with_depth(self, depth: &'a [f32]) -> Self {
        Self {
            depth: Some(depth),
            ..self
        }
    }

    /// The same seen by further cameras (the images then hold every view's).
    pub fn with_others(self, others: &'a [OtherView]) -> Self {
        Self { others, ..self }
    }

    /// Every view: the first, then the others at their poses relative to it.
    pub fn views(&self) -> Vec<View> {
        all_views(self.view, self.others)
    }
}

/// The views of a rig: `first`, then each of `others` at its pose relative to it.
pub fn all_views(first: View, others: &[OtherView]) -> Vec<View> {
    std::iter::once(first)
        .chain(others.iter().map(|o| View {
            camera: o.camera,
            pose: first.pose.followed_by(&o.from_first),
        }))
        .collect()
}

/// A registration's device buffers and progress.
struct Task<'a> {
    space: &'a ShapeSpace,
    scene: Scene,
    /// The device's coordinates z to latent codes: s = to_code z.
    to_code: Matrix,
    base: Buffer,
    basis: Buffer,
    state: Buffer,
    grad_latent: Buffer,
    /// With several views: each view's pose relative to the first (`glsl/rig.comp`).
    rig: Option<Buffer>,
    m: usize,
    /// The space's dimensions, and the device's (one more with a scale coordinate, last).
    k: usize,
    dims: usize,
    done: usize,
    active: bool,
    best: f64,
    milliseconds: f64,
}

impl<'a> Task<'a> {
    /// `code`: where the code starts, in the device's coordinates (None: the mean).
    fn new(
        ctx: &Context,
        job: &Job<'a>,
        params: &RegisterParams,
        code: Option<&[f32]>,
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
            (Some(loss), Some(depth)) => Some(ObservedDepth { depth, loss }),
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
        let to_code = optimizer_coordinates(space, params.optimizer);
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
        }
        let layout = StateLayout::new(dims, params.iterations);
        let prior = optimizer::prior_matrix(space, &to_code, dims);
        let mut state = layout.initial(&prior, job.gravity.as_ref());
        if let Some(code) = code {
            let at = layout.latent as usize;
            state[at..at + dims].copy_from_slice(&code[..dims]);
        }
        Ok(Self {
            space,
            scene,
            to_code,
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
    fn check_plateau(&mut self, params: &RegisterParams) -> Result<f64> {
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
    fn code(&self, z: &[f32]) -> (Vec<f64>, f64) {
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
    fn staged(&self, params: &RegisterParams) -> Result<Staged> {
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
            .filter(|z| z.abs() as f64 >= CODE_BOUND)
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
        })
    }
}

/// What one stage of a registration (`Registrar::run`) returns.
struct Staged {
    result: Registration,
    /// The code in the device's coordinates, where a next stage starts it.
    coordinates: Vec<f32>,
}

/// With depth and z free, after the alignment: the pose (with `optimize_scale` the shape
/// too) moves by mask and depth with the depth cost's scale REACH times the joint fit's,
/// for REACH_ITERATIONS iterations, so that a start centimetres off in depth reaches the
/// measured depth before the joint fit (`Registrar::register_batch`).
pub const REACH: f64 = 10.0;
/// See [`REACH`].
pub const REACH_ITERATIONS: usize = 10;

/// The rotations (object frame) that took the first job's pose to each job's: identity
/// first.
fn relative_turns(jobs: &[Job]) -> Vec<DMat3> {
    let first = jobs[0].view.pose.rotation_matrix();
    jobs.iter()
        .map(|job| first.transpose() * job.view.pose.rotation_matrix())
        .collect()
}

/// A point on the axis about which `vertices` are most nearly symmetric, among the axes
/// along `axis`: the shape turned by +-30 degrees about it lies closest to itself, the
/// points that land farther than 1.5 times the median distance from it (a handle) left out.
/// Iterated closest points on at most 1000 vertices (found in a grid: a scan of all made
/// this 200 ms of a 0.9 s registration on lavapipe); the two turns' opposite biases along
/// the turn (the nearest vertex lies behind or ahead of a turned one) cancel. The origin
/// for no finite vertices.
pub fn symmetry_pivot(vertices: &[DVec3], axis: DVec3) -> DVec3 {
    let step = vertices.len().div_ceil(1000).max(1);
    // A non-finite vertex is no one's nearest (the grid needs finite points).
    let points: Vec<DVec3> = vertices
        .iter()
        .step_by(step)
        .copied()
        .filter(|p| p.is_finite())
        .collect();
    let axis = axis.normalize();
    let across = |v: DVec3| v - axis * axis.dot(v);
    let half_turn = 15f64.to_radians();
    if points.is_empty() {
        return DVec3::ZERO;
    }
    let nearest = nearest::Nearest::new(&points);
    let mut pivot = across(crate::mesh::centroid(&points));
    for _ in 0..20 {
        let estimates = [1.0, -1.0].map(|side: f64| {
            let turn = DMat3::from_axis_angle(axis, side * 2.0 * half_turn);
            // Turned about the pivot c, x goes to turn x + (I - turn) c; its nearest point
            // q asks (I - turn) c = q - turn x, across the axis. There I - turn is a turn
            // by side (15 - 90) degrees scaled by 2 sin(15 degrees).
            let mut pairs: Vec<(f64, DVec3)> = points
                .iter()
                .map(|&x| {
                    let moved = turn * x + (pivot - turn * pivot);
                    let q = nearest.nearest(moved);
                    ((q - moved).length_squared(), across(q - turn * x))
                })
                .collect();
            let mut distances: Vec<f64> = pairs.iter().map(|p| p.0).collect();
            distances.sort_by(f64::total_cmp);
            // Squared: 2.25 times the median's square is 1.5 times its distance.
            let far = 2.25 * distances[distances.len() / 2];
            pairs.retain(|p| p.0 <= far);
            let target = pairs.iter().map(|p| p.1).sum::<DVec3>() / pairs.len() as f64;
            let inverse = DMat3::from_axis_angle(axis, side * (90f64.to_radians() - half_turn));
            inverse * target / (2.0 * half_turn.sin())
        });
        pivot = 0.5 * (estimates[0] + estimates[1]);
    }
    pivot
}

/// A turned pose's loss must be this fraction below the fit's for the joint fit to run
/// again from it (the registration from starts).
pub const TURN_GAIN: f64 = 0.05;
/// Pose-only iterations that score a turned pose (the registration from starts).
pub const TURN_ITERATIONS: usize = 1;

/// `jobs` at the poses that `results` reached.
fn at_poses<'a>(jobs: &[Job<'a>], results: &[Registration]) -> Vec<Job<'a>> {
    jobs.iter()
        .zip(results)
        .map(|(job, r)| Job {
            view: View {
                pose: r.pose,
                ..job.view
            },
            ..*job
        })
        .collect()
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The shaders' gravity weight (glsl/include/objective.glsl) is [`GRAVITY_WEIGHT`].
    #[test]
    fn the_gravity_weight_matches_the_shaders() {
        let glsl = include_str!("../../glsl/include/objective.glsl");
        let line = format!("const float GRAVITY_WEIGHT = {GRAVITY_WEIGHT:.1};");
        assert!(glsl.contains(&line), "objective.glsl lacks `{line}`");
    }

    /// A mug-like shape (a ring of points about an axis off the origin, and a handle on
    /// one side) turns about its body's axis: the pivot lands on it, where the centroid
    /// is pulled toward the handle.
    #[test]
    fn the_symmetry_pivot_is_the_body_s_axis() {
        let axis_at = DVec3::new(0.015, 0.0, -0.01);
        let mut points = Vec::new();
        for ring in 0..12 {
            for k in 0..40 {
                let a = k as f64 * std::f64::consts::TAU / 40.0;
                let y = ring as f64 * 0.008;
                points.push(axis_at + DVec3::new(0.04 * a.cos(), y, 0.04 * a.sin()));
            }
        }
        for k in 0..60 {
            let a = k as f64 * std::f64::consts::TAU / 60.0;
            let handle = DVec3::new(0.06 + 0.015 * a.cos(), 0.045 + 0.025 * a.sin(), 0.0);
            points.push(axis_at + handle);
        }
        let centroid = crate::mesh::centroid(&points);
        let across = |v: DVec3| DVec3::new(v.x, 0.0, v.z);
        assert!(across(centroid - axis_at).length() > 4e-3, "{centroid}");
        let pivot = symmetry_pivot(&points, DVec3::new(0.0, 2.0, 0.0));
        assert!(
            across(pivot - axis_at).length() < 5e-4,
            "{pivot} against {axis_at}"
        );
    }

    /// A non-finite vertex (a diverged fit) is left out rather than poisoning the pivot;
    /// with none finite the pivot is the origin.
    #[test]
    fn the_symmetry_pivot_leaves_non_finite_vertices_out() {
        let axis = DVec3::Y;
        let ring: Vec<DVec3> = (0..40)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 40.0;
                DVec3::new(0.02 + 0.04 * a.cos(), 0.0, 0.04 * a.sin())
            })
            .collect();
        let mut with_nan = ring.clone();
        with_nan.insert(7, DVec3::new(f64::NAN, 0.0, 0.0));
        with_nan.push(DVec3::splat(f64::INFINITY));
        assert_eq!(symmetry_pivot(&with_nan, axis), symmetry_pivot(&ring, axis));
        assert_eq!(symmetry_pivot(&[DVec3::NAN], axis), DVec3::ZERO);
    }

    /// The starts alternate sides at growing turns, and a turn about the object's up axis
    /// keeps the position and the axis and moves a point off the axis by the turn.
    #[test]
    fn starts_turn_about_the_up_axis_on_either_side() {
        let r = 0.25;
        assert!(start_turns(0, r).is_empty());
        assert_eq!(start_turns(5, r), vec![0.0, r, -r, 2.0 * r, -2.0 * r]);
        let pose = Pose::new([0.02, -0.01, 0.6], [0.3, -0.2, 0.1]).unwrap();
        let up = DVec3::new(0.0, 2.0, 0.0);
        let starts = turned_starts(pose, up, 3, r);
        assert_eq!(starts.len(), 3);
        assert!((starts[0].rotation - pose.rotation).length() < 1e-12);
        let x = DVec3::X;
        for (turned, angle) in starts.iter().zip([0.0, r, r]) {
            assert!((turned.translation - pose.translation).length() < 1e-12);
            assert!((turned.apply(up) - pose.apply(up)).length() < 1e-12);
            let moved = (turned.apply(x) - pose.apply(x)).length();
            assert!((moved - 2.0 * (angle / 2.0).sin()).abs() < 1e-12, "{moved}");
        }
        // The second and third turn to either side.
        let side = |p: &Pose| pose.inverse().followed_by(p).apply(x).z;
        assert!(side(&starts[1]) * side(&starts[2]) < 0.0);
    }
}
