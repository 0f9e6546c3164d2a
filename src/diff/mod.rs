//! Exact gradients through the rasterizer. From the G-buffer's triangle ids, compute
//! shaders shade the compared image (antialiased coverage, or per-vertex attributes
//! interpolated with exact perspective-correct barycentrics, which [`Shading`] can compute
//! on the device from the vertex normals and a light), antialias it analytically
//! across silhouette edges between adjacent pixels (the idea of nvdiffrast's `antialias`,
//! with mesh topology to find silhouette edges and a walk across triangles smaller than a
//! pixel), evaluate the loss, and push dL/dpixel back to every vertex and to each view's
//! pose. A depth image can be compared too ([`ObservedDepth`]): inside the silhouette, as
//! one more interpolated channel (camera-space z, exact with perspective-correct
//! barycentrics), with a robust cost. Every sum that threads add to in parallel is int64 fixed point at a scale chosen
//! from the data, or a reduction in a fixed order (`glsl/include/fixed_point.glsl`), so the
//! same inputs give bit-identical results on the same device, run after run.
//!
//! [`reference`](mod@reference) is the float64 model the tests differentiate by central differences.

#[doc(hidden)] // the float64 model the tests check the device against
pub mod reference;

mod compare;
mod record;
mod topology;
mod upload;

pub use compare::{DepthLoss, ObservedDepth, Shading};
pub use topology::{incident_triangles, neighbours, NO_NEIGHBOUR};

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use bytemuck::{Pod, Zeroable};

use crate::error::{Error, Result};
use crate::gpu::{
    Binding, Buffer, ComputePipeline, Context, Groups, Recorder, Recording, Timestamps,
};
use crate::loss::{DistanceField, Loss};
use crate::mesh::Mesh;
use crate::raster::{Gbuffer, MeshBuffers, Rasterizer, View, ViewBuffers};
use crate::shaders;

/// Depth residuals are clamped to this many metres (as in `glsl/include/diff_pass.glsl`),
/// which bounds the fixed-point loss sums.
pub const MAX_DEPTH_RESIDUAL: f64 = 1000.0;

/// Words of the boxes buffer for `views` views (layout in `glsl/bounds.comp`).
fn box_words(views: u32) -> u64 {
    4 + 8 * views as u64
}

/// The work-count buffer: listed pixels, 3 dispatch arguments, then (at [`LOST_WALKS`])
/// the silhouette searches that gave up since [`Scene::record_prepare`], then the bounds
/// on the camera- and attribute-gradient terms of the fixed-point sums (`CAMERA_MAX`,
/// `ATTRIBUTE_MAX` in `glsl/include/diff_pass.glsl`), then the last evaluation's pixel
/// pairs whose line misses the front triangle ([`Scene::missed_starts`]), then (at
/// [`UNFINISHED`]) the listed pixels a pass never reached since [`Scene::record_prepare`],
/// then the bounds' ingredients and the largest terms the backward added (`CROSSING_MAX`
/// to `ATTRIBUTE_SEEN` there), then the counts of the two pair lists and the pairs pass's
/// dispatch arguments, cleared with the first slots every evaluation.
const WORK_COUNT_WORDS: u64 = 22;
/// The pair lists' counts and the pairs pass's dispatch arguments in the work-count buffer
/// (as `PAIRS_X_COUNT` ... in `glsl/include/diff_pass.glsl`).
const PAIR_DISPATCH: u64 = 19;
/// As `LOST_WALKS` in `glsl/include/diff.glsl`.
const LOST_WALKS: usize = 4;
/// As `CAMERA_MAX`, `ATTRIBUTE_MAX`, `CAMERA_SEEN` and `ATTRIBUTE_SEEN` in
/// `glsl/include/diff_pass.glsl`.
const CAMERA_MAX: u32 = 5;
const ATTRIBUTE_MAX: u32 = 6;
const CAMERA_SEEN: u32 = 15;
const ATTRIBUTE_SEEN: u32 = 16;
/// The most items one invocation of a grid-stride pass loops over (as in
/// `glsl/work_args.comp`): at a few dozen loop iterations an item, far from
/// [`crate::gpu::LOOP_LIMIT`].
const ITEMS_PER_INVOCATION: u32 = 64;
/// What [`Scene::record_marked`] marks: timestamps 0, 1, 2 (start, forward done, backward
/// done), or (a profile) a cut after every pass, each pass its own recording.
enum Marks<'a> {
    Phases(Option<&'a Timestamps>),
    Cuts {
        ctx: &'a Context,
        passes: Vec<(&'static str, Recording)>,
    },
}

impl Marks<'_> {
    fn start(&mut self, rec: &mut Recorder) {
        if let Marks::Phases(Some(t)) = self {
            rec.reset_timestamps(t);
            rec.timestamp(t, 0);
        }
    }

    fn phase(&mut self, rec: &mut Recorder, slot: u32) {
        if let Marks::Phases(Some(t)) = self {
            rec.timestamp(t, slot);
        }
    }

    fn pass(&mut self, rec: &mut Recorder, name: &'static str) -> Result<()> {
        if let Marks::Cuts { ctx, passes } = self {
            let done = std::mem::replace(rec, Recorder::new(ctx)?);
            passes.push((name, done.finish()?));
        }
        Ok(())
    }
}

/// As `MISSED_STARTS` in `glsl/include/diff.glsl`.
const MISSED_STARTS: usize = 7;
/// As `UNFINISHED` in `glsl/include/diff.glsl`.
const UNFINISHED: usize = 8;
/// As `TERMS_PER_LISTED` there.
const TERMS_PER_LISTED: u32 = 3;
/// Triangles a scene can hold: the pair records (`encode_pair` in
/// `glsl/include/diff.glsl`) keep a triangle number in 28 bits.
const MAX_TRIANGLES: usize = 1 << 28;
/// Vertices per bit of the touched-blocks mask (as `VERTEX_BLOCK` in
/// `glsl/include/diff_pass.glsl`): the pose pass visits only the blocks whose bit is set,
/// and small blocks keep a silhouette's few vertices per block from bringing many others
/// along.
const VERTEX_BLOCK: u32 = 8;
/// Workgroups of the pose reduction's partial sums (at most).
const POSE_GROUPS: u32 = 1024;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct LambertConstants {
    vertex_count: u32,
    stage: u32,
    ambient: f32,
    light: [f32; 3],
    stride: u32,
}
const _: () = assert!(shaders::LAMBERT_COMP.takes::<LambertConstants>());

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct DepthConstants {
    vertex_count: u32,
    channels: u32,
    coverage: u32,
}
const _: () = assert!(shaders::DEPTH_COMP.takes::<DepthConstants>());

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct PassConstants {
    vertex_count: u32,
    width: u32,
    height: u32,
    stats_shift: i32,
    stage: u32,
    depth_scale: f32,
    depth_weight: f32,
    occlusion: f32,
    loss_pixels: f32,
}
const _: () = assert!(shaders::CLASSIFY_COMP.takes::<PassConstants>());
const _: () = assert!(shaders::ANTIALIAS_COMP.takes::<PassConstants>());
const _: () = assert!(shaders::ANTIALIAS_BACKWARD_COMP.takes::<PassConstants>());
const _: () = assert!(shaders::BOUNDS_COMP.takes::<PassConstants>());

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct FinalizeConstants {
    loss: u32,
    stats_shift: i32,
}
const _: () = assert!(shaders::LOSS_FINALIZE_COMP.takes::<FinalizeConstants>());

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct ResolveConstants {
    count: u32,
    max_slot: u32,
    seen_slot: u32,
    terms_per_listed: u32,
}
const _: () = assert!(shaders::FIXED_RESOLVE_COMP.takes::<ResolveConstants>());

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct PoseConstants {
    vertex_count: u32,
    view_count: u32,
    groups: u32,
    stage: u32,
    subgroups: u32,
    from_fixed: u32,
    max_slot: u32,
    seen_slot: u32,
    terms_per_listed: u32,
    vertex_block: u32,
}
const _: () = assert!(shaders::POSE_GRADIENT_COMP.takes::<PoseConstants>());

/// The scale (2^shift) of the fixed-point loss sums: every sum of a view's per-pixel terms
/// stays below 2^61 for any image the scene can render, from a bound on the terms (images
/// between 0 and the largest attribute, observed values as given, distances at most the
/// image's diagonal in pixels).
fn stats_shift(desc: &SceneDesc, width: u32, height: u32) -> i32 {
    let largest = |values: &[f32]| values.iter().fold(0f64, |m, v| m.max(v.abs() as f64));
    let observed = largest(desc.observed);
    let rendered = desc.attributes.map_or(1.0, |(values, _)| largest(values));
    let pixels = width as f64 * height as f64;
    // Loss sums are per-pixel terms over N pixels divided by N; intersection and union
    // are not divided.
    let mut bound = match desc.loss {
        Loss::Mse => (rendered + observed).powi(2),
        Loss::Iou => pixels * (1.0 + observed).powi(2),
        Loss::Distance => (width as f64).hypot(height as f64),
    };
    if let Some(depth) = &desc.depth {
        bound += depth.loss.weight * (2.0 * MAX_DEPTH_RESIDUAL / depth.loss.scale + 1.0);
    }
    (61 - bound.max(1e-30).log2().ceil() as i32).clamp(-60, 120)
}

/// What a scene's per-pixel passes compare, compiled into them as the specialization
/// constants of `glsl/include/diff_pass.glsl` (ids 1 to 4): a CPU driver runs both sides
/// of every branch, so one pipeline for all scenes made every pixel pay for every loss and
/// channel layout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
struct PassVariant {
    loss: u32,
    channels: u32,
    depth: u32,
    coverage: u32,
}

/// The per-pixel passes of one [`PassVariant`].
struct PassPipelines {
    /// `glsl/classify.comp` stage 0 (the box's pixels, every evaluation) and stage 1 (the
    /// background terms, once per observation).
    classify: ComputePipeline,
    background: ComputePipeline,
    /// `glsl/antialias.comp` stage 0 (the pairs) and stage 1 (the antialiased image).
    pairs: ComputePipeline,
    antialias: ComputePipeline,
    backward: ComputePipeline,
}

impl PassPipelines {
    fn new(ctx: &Context, v: PassVariant) -> Result<Self> {
        // Constant 0 is the stage where a shader has one (a pipeline per stage).
        let pipeline = |shader, stage: u32| {
            let constants = [stage, v.loss, v.channels, v.depth, v.coverage];
            ComputePipeline::specialized(ctx, shader, &constants)
        };
        Ok(Self {
            classify: pipeline(&shaders::CLASSIFY_COMP, 0)?,
            background: pipeline(&shaders::CLASSIFY_COMP, 1)?,
            pairs: pipeline(&shaders::ANTIALIAS_COMP, 0)?,
            antialias: pipeline(&shaders::ANTIALIAS_COMP, 1)?,
            backward: pipeline(&shaders::ANTIALIAS_BACKWARD_COMP, 0)?,
        })
    }
}

/// The pipelines of the differentiable renderer (create once, use for many scenes).
pub struct DiffRenderer {
    ctx: Context,
    rasterizer: Rasterizer,
    /// The per-pixel passes for each variant met so far, compiled when first needed.
    passes: Mutex<HashMap<PassVariant, Arc<PassPipelines>>>,
    work_args: ComputePipeline,
    finalize: ComputePipeline,
    pose: ComputePipeline,
    resolve: ComputePipeline,
    lambert: ComputePipeline,
    bounds: ComputePipeline,
    depth: ComputePipeline,
    distance: DistanceField,
}

// work_args.comp takes the largest workgroup count alone.
const _: () = assert!(shaders::WORK_ARGS_COMP.takes::<u32>());

impl DiffRenderer {
    /// Builds the differentiable renderer's pipelines and its rasterizer.
    pub fn new(ctx: &Context) -> Result<Self> {
        let pipeline = |shader| ComputePipeline::new(ctx, shader);
        let renderer = Self {
            ctx: ctx.clone(),
            rasterizer: Rasterizer::new(ctx)?,
            passes: Mutex::new(HashMap::new()),
            work_args: pipeline(&shaders::WORK_ARGS_COMP)?,
            finalize: pipeline(&shaders::LOSS_FINALIZE_COMP)?,
            pose: pipeline(&shaders::POSE_GRADIENT_COMP)?,
            resolve: pipeline(&shaders::FIXED_RESOLVE_COMP)?,
            lambert: pipeline(&shaders::LAMBERT_COMP)?,
            bounds: pipeline(&shaders::BOUNDS_COMP)?,
            depth: pipeline(&shaders::DEPTH_COMP)?,
            distance: DistanceField::new(ctx)?,
        };
        // A mask against its coverage, the most common scene, ready before the first.
        renderer.passes(PassVariant::default())?;
        Ok(renderer)
    }

    /// The per-pixel passes compiled for `variant` (compiled on first use, then kept).
    fn passes(&self, variant: PassVariant) -> Result<Arc<PassPipelines>> {
        let mut passes = self.passes.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(found) = passes.get(&variant) {
            return Ok(found.clone());
        }
        let compiled = Arc::new(PassPipelines::new(&self.ctx, variant)?);
        passes.insert(variant, compiled.clone());
        Ok(compiled)
    }

    /// The forward rasterizer the scenes render with.
    pub fn rasterizer(&self) -> &Rasterizer {
        &self.rasterizer
    }
}

/// What a scene compares: the observed images of every view and how.
pub struct SceneDesc<'a> {
    /// The mesh, in object coordinates.
    pub mesh: &'a Mesh,
    /// The views it is seen in; all share one image size.
    pub views: &'a [View],
    /// How the rendered images are compared with `observed`.
    pub loss: Loss,
    /// Observed images, `[view][row][column][channel]` with `channels` = attribute channels
    /// (1 for a mask: nonzero = object).
    pub observed: &'a [f32],
    /// Per-vertex attributes to interpolate (`[vertex][channel]`, 1 to 4 channels, the same
    /// for every view), or `None` to compare antialiased coverage with a mask.
    pub attributes: Option<(&'a [f32], u32)>,
    /// Compare Lambert shading (one channel, computed on the device for every view)
    /// instead; excludes `attributes`.
    pub shading: Option<Shading>,
    /// Compare depth too (with the mse loss): the compared image gains a last channel,
    /// the rendered depth.
    pub depth: Option<ObservedDepth<'a>>,
    /// The pixel count each view's loss is averaged over; None: the view's own (width x
    /// height). A region of interest cut out of a larger image passes the larger image's,
    /// so that its loss and gradients are the larger image's wherever nothing outside the
    /// region adds to them (`register` cuts such regions).
    pub loss_pixels: Option<u64>,
}

/// Device buffers of one differentiable scene: mesh, views, G-buffer, observation and
/// gradient accumulators. [`Scene::record`] records one forward and backward pass.
pub struct Scene {
    mesh: MeshBuffers,
    views: ViewBuffers,
    gbuffer: Gbuffer,
    neighbours: Buffer,
    /// `[view][vertex][channel]`
    attributes: Buffer,
    /// With shading: the incident triangles of every vertex, dL/d(normal) scratch, the
    /// unit light.
    lambert: Option<LambertBuffers>,
    observed: Buffer,
    distance: Buffer,
    distance_scratch: Option<[Buffer; 2]>,
    antialiased: Buffer,
    stats: Buffer,
    /// int64 fixed-point loss sums at `stats_shift`, [view][3].
    stats_fixed: Buffer,
    /// The background's loss sums (`loss_terms(pixel, 0)` over the whole image, in the
    /// fixed point of stats_fixed): written by [`Scene::record_prepare`], copied into
    /// stats_fixed to start every evaluation.
    background: Buffer,
    /// Per view, the box of pixels that classify.comp visits (`glsl/bounds.comp`).
    boxes: Buffer,
    stats_shift: i32,
    work: Buffer,
    /// The pixel pairs that matter, along x and along y (`glsl/classify.comp`).
    pair_work_x: Buffer,
    pair_work_y: Buffer,
    work_count: Buffer,
    grad_camera: Buffer,
    grad_attributes: Buffer,
    /// int64 fixed-point sums of the two above, resolved to them after the backward.
    grad_camera_fixed: Buffer,
    grad_attributes_fixed: Buffer,
    grad_object: Buffer,
    grad_pose: Buffer,
    pose_partials: Buffer,
    /// A bit per block of [`VERTEX_BLOCK`] vertices, set where the backward added a camera
    /// gradient term to one of them: the pose pass skips the other blocks.
    touched: Buffer,
    pose_groups: u32,
    /// [`DeviceInfo::grid_groups`](crate::gpu::DeviceInfo::grid_groups).
    grid_groups: u32,
    /// Subgroups per 64-wide workgroup.
    subgroups: u32,
    ids: Buffer,
    /// Each listed pixel's pairs with its right and lower neighbours, one word each
    /// (`encode_pair` in `glsl/include/diff.glsl`), `[view][y][x]`.
    pairs_x: Buffer,
    pairs_y: Buffer,
    /// Each valid pair's crossing parameter alpha, beside its record.
    alphas_x: Buffer,
    alphas_y: Buffer,
    loss: Loss,
    /// Channels of every vertex's attributes (0: coverage without attributes).
    channels: u32,
    /// With depth: how it is compared (its channel is the last).
    depth: Option<DepthLoss>,
    /// With depth and a mask: channel 0 is coverage, a constant attribute 1.
    coverage: bool,
    /// The pixel count each view's loss is averaged over ([`SceneDesc::loss_pixels`]).
    loss_pixels: u64,
}

/// Results of one evaluation, read back to the host.
#[derive(Clone, Debug)]
pub struct Evaluation {
    /// Loss of each view (the total is their sum).
    pub loss: Vec<f32>,
    /// dL/d(object-space vertex position), summed over views, in the mesh's vertex order.
    pub vertex_gradient: Vec<[f32; 3]>,
    /// Per view: dL/dt (camera frame) then dL/dd for a rotation increment d applied on the
    /// left, `x_camera = exp([d]x) R x + t`.
    pub pose_gradient: Vec<[f32; 6]>,
    /// dL/d(attribute), `[vertex][channel]`, summed over views (empty without attributes;
    /// with shading, dL/d(shade)). With depth, 0 for the depth channel (its gradient is in
    /// the vertex gradient: the attribute is the vertex's camera-space z) and for a mask's
    /// coverage channel (1 at every vertex, not interpolated).
    pub attribute_gradient: Vec<f32>,
    /// The antialiased compared image, `[view][row][column][channel]` (with depth, the last
    /// channel is the rendered depth at each covered pixel centre, not antialiased;
    /// against a mask only where the observed depth can count, measured and known, and 0
    /// elsewhere: it is not interpolated there).
    pub antialiased: Vec<f32>,
    /// Triangle id + 1 per pixel, `[view][row][column]`.
    pub ids: Vec<u32>,
}

struct LambertBuffers {
    start: Buffer,
    incident: Buffer,
    grad_normal: Buffer,
    light: [f32; 3],
    ambient: f32,
}

/// Refuses a scene whose per-pixel or per-vertex buffers the device could not address
/// (they are bound whole): `n` views of `w` x `h` compared in `image_channels` channels,
/// `vertices` vertices with `channels` interpolated channels. Callers can check before
/// they allocate images of that size; [`Scene::new`] checks again.
pub fn check_scene_fits(
    ctx: &Context,
    (w, h, n): (u32, u32, u32),
    image_channels: u64,
    vertices: u64,
    channels: u32,
) -> Result<()> {
    let range = ctx.info().max_storage_buffer_range as u64;
    let product = |factors: &[u64]| factors.iter().fold(1u64, |a, &b| a.saturating_mul(b));
    let (w64, h64, n64) = (w as u64, h as u64, n as u64);
    let per_vertex = format!("{vertices} vertices in {n} view(s)");
    let largest = [
        (
            format!("the compared image of {n} view(s) of {w} x {h}"),
            product(&[w64, h64, n64, image_channels, 4]),
            "a smaller image or fewer views",
        ),
        (
            format!("the camera-space vertex gradients of {per_vertex}"),
            product(&[n64, vertices, 24]),
            "a smaller mesh or fewer views",
        ),
        (
            format!("the attribute gradients of {per_vertex}"),
            product(&[n64, vertices, channels as u64, 8]),
            "a smaller mesh, fewer channels or fewer views",
        ),
    ];
    for (what, bytes, hint) in largest {
        if bytes > range {
            return Err(Error::Limit(format!(
                "{what} need {bytes} bytes ({:.1} MiB) in one buffer, more than the \
                 device's maxStorageBufferRange of {range} bytes ({:.1} MiB); use {hint}",
                bytes as f64 / 1048576.0,
                range as f64 / 1048576.0
            )));
        }
    }
    Ok(())
}

impl Scene {
    /// The mesh on the device (its positions may be rewritten by compute passes).
    pub fn mesh(&self) -> &MeshBuffers {
        &self.mesh
    }

    /// The views on the device (poses may be rewritten by compute passes).
    pub fn views(&self) -> &ViewBuffers {
        &self.views
    }

    /// Replaces the views' cameras and poses.
    pub fn set_views(&mut self, views: &[View]) -> Result<()> {
        self.views.set(views)
    }

    /// Records what depends only on the observation (the distance field, the loss of an
    /// empty image); run once, before the first [`Scene::record`].
    pub fn record_prepare(&self, renderer: &DiffRenderer, rec: &mut Recorder) -> Result<()> {
        rec.fill_buffer(&self.work_count, 0);
        let (w, h, n) = (self.views.width(), self.views.height(), self.views.count());
        if let Some([a, b]) = &self.distance_scratch {
            renderer
                .distance
                .record(rec, &self.observed, [a, b], &self.distance, (w, h, n))?;
        }
        rec.fill_buffer(&self.stats_fixed, 0);
        rec.memory_barrier();
        rec.run_compute(
            &renderer.passes(self.pass_variant())?.background,
            &self.pass_bindings(),
            &self.pass_constants(1),
            Groups::Count(self.grid(w * h), 1, n),
        );
        rec.memory_barrier();
        rec.copy_buffer(
            &self.stats_fixed,
            0,
            &self.background,
            0,
            self.background.size(),
        );
        rec.memory_barrier();
        Ok(())
    }

    /// The bindings of the per-pixel passes (`glsl/include/diff_pass.glsl`).
    fn pass_bindings(&self) -> [Binding<'_>; 25] {
        [
            Binding::buffer(self.mesh.positions()),
            Binding::buffer(self.mesh.triangles()),
            Binding::buffer(&self.neighbours),
            Binding::buffer(self.views.views()),
            Binding::buffer(&self.attributes),
            Binding::buffer(&self.ids),
            Binding::buffer(&self.observed),
            Binding::buffer(&self.distance),
            Binding::buffer(&self.antialiased),
            Binding::buffer(&self.stats),
            Binding::buffer(&self.grad_camera),
            Binding::buffer(&self.grad_attributes),
            Binding::buffer(&self.work),
            Binding::buffer(&self.work_count),
            Binding::buffer(&self.stats_fixed),
            Binding::buffer(&self.grad_camera_fixed),
            Binding::buffer(&self.grad_attributes_fixed),
            Binding::buffer(&self.boxes),
            Binding::buffer(&self.pairs_x),
            Binding::buffer(&self.pairs_y),
            Binding::buffer(&self.touched),
            Binding::buffer(&self.alphas_x),
            Binding::buffer(&self.alphas_y),
            Binding::buffer(&self.pair_work_x),
            Binding::buffer(&self.pair_work_y),
        ]
    }

    /// Workgroups of 64 for a grid-stride pass over `items`: at most `grid_groups`, unless
    /// an invocation would then loop over more than [`ITEMS_PER_INVOCATION`] items.
    fn grid(&self, items: u32) -> u32 {
        let fewest = items.div_ceil(64 * ITEMS_PER_INVOCATION);
        items.div_ceil(64).clamp(1, self.grid_groups.max(fewest))
    }

    fn pass_variant(&self) -> PassVariant {
        PassVariant {
            loss: self.loss.code(),
            channels: self.channels,
            depth: self.depth.is_some() as u32,
            coverage: self.coverage as u32,
        }
    }

    fn pass_constants(&self, stage: u32) -> PassConstants {
        PassConstants {
            vertex_count: self.mesh.vertex_count(),
            width: self.views.width(),
            height: self.views.height(),
            stats_shift: self.stats_shift,
            stage,
            depth_scale: self.depth.map_or(1.0, |d| d.scale as f32),
            depth_weight: self.depth.map_or(0.0, |d| d.weight as f32),
            occlusion: self.depth.map_or(0.0, |d| d.occlusion as f32),
            loss_pixels: self.loss_pixels as f32,
        }
    }

    /// Records one evaluation: rasterize, shade, antialias, loss, backward, pose
    /// reduction. Results are in the scene's buffers once the submission completes.
    /// With `timing`, timestamps 0, 1, 2 mark the start, the end of the forward pass
    /// (through the loss) and the end of the backward pass (through the pose gradient).
    pub fn record(
        &self,
        renderer: &DiffRenderer,
        rec: &mut Recorder,
        timing: Option<&Timestamps>,
    ) -> Result<()> {
        self.record_marked(renderer, rec, &mut Marks::Phases(timing))
    }

    /// A profile: each pass of [`Scene::record`] timed `repeats` times (after one warm-up)
    /// on the host's clock, each pass submitted alone and waited for; the passes' names and
    /// their times in milliseconds. Timestamps between passes cannot do this on CPU
    /// drivers: lavapipe defers a draw's rasterization to whichever later command needs its
    /// pixels, so its time showed up in the passes after it. Each time includes one
    /// submission's overhead.
    pub fn profile(
        &self,
        ctx: &Context,
        renderer: &DiffRenderer,
        repeats: usize,
    ) -> Result<Vec<(&'static str, Vec<f64>)>> {
        let mut rec = Recorder::new(ctx)?;
        let mut marks = Marks::Cuts {
            ctx,
            passes: Vec::new(),
        };
        self.record_marked(renderer, &mut rec, &mut marks)?;
        let Marks::Cuts { passes, .. } = marks else {
            unreachable!("the marks were made as cuts")
        };
        let mut times = vec![Vec::with_capacity(repeats); passes.len()];
        for repeat in 0..=repeats {
            for ((_, pass), times) in passes.iter().zip(&mut times) {
                let started = std::time::Instant::now();
                ctx.replay(pass)?;
                if repeat > 0 {
                    times.push(started.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
        Ok(passes.iter().map(|(name, _)| *name).zip(times).collect())
    }

    /// The buffer holding each view's loss at float index 4 view + 3.
    pub fn loss_stats(&self) -> &Buffer {
        &self.stats
    }

    /// Object-space vertex gradients, 3 floats per vertex.
    pub fn vertex_gradient(&self) -> &Buffer {
        &self.grad_object
    }

    /// Pose gradients, 6 floats per view.
    pub fn pose_gradient(&self) -> &Buffer {
        &self.grad_pose
    }

    /// Fails with [`Error::Limit`] if a silhouette search gave up (a mesh whose walk
    /// between two pixel centres crossed more triangles than `MAX_WALK` in
    /// `glsl/include/diff.glsl`), or a pass did not reach every listed pixel (a driver
    /// that ended a loop early, [`crate::gpu::LOOP_LIMIT`]), in any evaluation since
    /// [`Scene::record_prepare`]: the gradients would miss those terms.
    pub fn check_walks(&self) -> Result<()> {
        let counts = self
            .work_count
            .read_range::<u32>(0, WORK_COUNT_WORDS as usize)?;
        let (lost, unfinished) = (counts[LOST_WALKS], counts[UNFINISHED]);
        if unfinished > 0 {
            return Err(Error::Limit(format!(
                "{unfinished} listed pixels were never reached by a pass: the device ended \
                 a shader's loop early (lavapipe stops an invocation after {} loop \
                 iterations); the loss and gradients would be wrong",
                crate::gpu::LOOP_LIMIT
            )));
        }
        if lost > 0 {
            return Err(Error::Limit(format!(
                "{lost} silhouette searches could not finish: they crossed more than 65536 \
                 triangles between two pixel centres, or met triangles whose neighbour \
                 table does not match them; the mesh is likely broken (non-manifold or \
                 self-intersecting), and its gradients would be wrong"
            )));
        }
        Ok(())
    }

    /// Pixel pairs of the last evaluation whose front pixel's triangle the line between the
    /// two pixel centres misses (a triangle thinner than the rasterizer's sub-pixel grid
    /// that owns a pixel centre it does not contain): no crossing to differentiate there.
    pub fn missed_starts(&self) -> Result<u32> {
        Ok(self
            .work_count
            .read_range::<u32>(0, WORK_COUNT_WORDS as usize)?[MISSED_STARTS])
    }

    /// How loose the last evaluation's bound on the camera-gradient terms was: the bound
    /// over the largest term the backward added (at least 1; `None` when no term was
    /// added). The fixed-point sums resolve 2^-(62 - headroom) of the bound
    /// (`glsl/include/fixed_point.glsl`), so their resolution relative to the largest term
    /// is that times this.
    pub fn bound_slack(&self) -> Result<Option<f64>> {
        let counts = self
            .work_count
            .read_range::<u32>(0, WORK_COUNT_WORDS as usize)?;
        let bound = f32::from_bits(counts[CAMERA_MAX as usize]) as f64;
        let seen = f32::from_bits(counts[CAMERA_SEEN as usize]) as f64;
        Ok((seen > 0.0).then(|| bound / seen))
    }

    /// Pixels listed next to a silhouette (or covered, with attributes) in the last
    /// evaluation, over all views: 0 when nothing of the mesh is rendered.
    pub fn listed_pixels(&self) -> Result<u32> {
        Ok(self.work_count.read_range::<u32>(0, 1)?[0])
    }

    /// Reads every result back (after the submission completed); fails as
    /// [`Scene::check_walks`] does.
    pub fn read(&mut self) -> Result<Evaluation> {
        self.check_walks()?;
        let n = self.views.count() as usize;
        let v = self.mesh.vertex_count() as usize;
        let pixels = n * self.views.width() as usize * self.views.height() as usize;
        let stats = self.stats.read_range::<f32>(0, 4 * n)?;
        Ok(Evaluation {
            loss: (0..n).map(|k| stats[4 * k + 3]).collect(),
            vertex_gradient: self.grad_object.read_range::<[f32; 3]>(0, v)?,
            pose_gradient: self.grad_pose.read_range::<[f32; 6]>(0, n)?,
            attribute_gradient: {
                let per_view = v * self.channels as usize;
                let all = self.grad_attributes.read_range::<f32>(0, n * per_view)?;
                (0..per_view)
                    .map(|i| (0..n).map(|view| all[view * per_view + i]).sum())
                    .collect()
            },
            antialiased: self
                .antialiased
                .read_range::<f32>(0, pixels * self.channels.max(1) as usize)?,
            ids: self.ids.read_range::<u32>(0, pixels)?,
        })
    }

    /// The signed distance field of the observation, `[view][row][column]` (distance loss
    /// only; after a submission that included [`Scene::record_prepare`]).
    pub fn read_distance_field(&mut self) -> Result<Vec<f32>> {
        if self.loss != Loss::Distance {
            return Err(Error::InvalidInput(
                "only the distance loss has a distance field".into(),
            ));
        }
        let pixels = self.views.count() as usize
            * self.views.width() as usize
            * self.views.height() as usize;
        self.distance.read_range::<f32>(0, pixels)
    }

    /// One-shot convenience: prepare, evaluate once, read everything back.
    pub fn evaluate(&mut self, ctx: &Context, renderer: &DiffRenderer) -> Result<Evaluation> {
        let mut rec = Recorder::new(ctx)?;
        self.record_prepare(renderer, &mut rec)?;
        self.record(renderer, &mut rec, None)?;
        ctx.submit_and_wait(rec)?;
        self.read()
    }
}
