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

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use bytemuck::{Pod, Zeroable};

use crate::error::{Error, Result};
use crate::gpu::{
    Binding, Buffer, BufferKind, ComputePipeline, Context, Groups, ImageState, Recorder, Recording,
    Timestamps,
};
use crate::loss::{DistanceField, Loss};
use crate::mesh::Mesh;
use crate::raster::{Gbuffer, MeshBuffers, Outputs, Rasterizer, View, ViewBuffers};
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

/// Marks an edge without exactly one neighbouring triangle.
pub const NO_NEIGHBOUR: u32 = u32::MAX;

/// For each triangle t and corner k, the triangle across the edge opposite corner k
/// (`neighbours[3 t + k]`), or [`NO_NEIGHBOUR`] for a boundary edge or one shared by more
/// than two triangles. Edges are matched by vertex index (welded meshes). A triangle that
/// names a vertex twice has no area and no neighbours, and is no triangle's neighbour.
pub fn neighbours(mesh: &Mesh) -> Vec<u32> {
    let triangles = mesh.triangles();
    let mut edges: HashMap<(u32, u32), Vec<(u32, usize)>> =
        HashMap::with_capacity(triangles.len() * 3 / 2);
    for (t, tri) in triangles.iter().enumerate() {
        if tri[0] == tri[1] || tri[1] == tri[2] || tri[2] == tri[0] {
            continue;
        }
        for k in 0..3 {
            let (a, b) = (tri[(k + 1) % 3], tri[(k + 2) % 3]);
            edges
                .entry((a.min(b), a.max(b)))
                .or_default()
                .push((t as u32, k));
        }
    }
    let mut out = vec![NO_NEIGHBOUR; triangles.len() * 3];
    for sharing in edges.values() {
        if let [(t0, k0), (t1, k1)] = sharing[..] {
            out[3 * t0 as usize + k0] = t1;
            out[3 * t1 as usize + k1] = t0;
        }
    }
    out
}

/// For each vertex, its triangles as `3 triangle + corner`: `(start, list)` with vertex v's
/// entries at `list[start[v]..start[v + 1]]` (ascending triangle order).
pub fn incident_triangles(mesh: &Mesh) -> (Vec<u32>, Vec<u32>) {
    let mut count = vec![0u32; mesh.vertex_count() + 1];
    for tri in mesh.triangles() {
        for &v in tri {
            count[v as usize + 1] += 1;
        }
    }
    for v in 0..mesh.vertex_count() {
        count[v + 1] += count[v];
    }
    let start = count.clone();
    let mut list = vec![0u32; start[mesh.vertex_count()] as usize];
    for (t, tri) in mesh.triangles().iter().enumerate() {
        for (corner, &v) in tri.iter().enumerate() {
            list[count[v as usize] as usize] = 3 * t as u32 + corner as u32;
            count[v as usize] += 1;
        }
    }
    (start, list)
}

/// Grey Lambert shading, compared instead of the coverage: one directional light fixed in
/// the camera frame, the smooth (area-weighted) vertex normals, and an ambient term, so
/// that an object pixel has `ambient + (1 - ambient) max(0, n . light)` interpolated from
/// its triangle's vertices and the background 0. Two-sided: where a vertex faces away from
/// the camera, n is flipped, so the inside of an open scan is lit as a camera sees it
/// (`glsl/lambert.comp`). Unlike a silhouette it shows how the
/// surface turns, which one mask leaves open (the tilt of a bottle towards the camera).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shading {
    /// Direction towards the light in the camera frame (x right, y down, z forward;
    /// normalised on use).
    pub light: [f64; 3],
    /// Ambient term in `[0, 1)`: the shade of a surface the light does not reach.
    pub ambient: f64,
}

impl Default for Shading {
    /// A light at the camera (a flash or a ring light): of the directions tried on a
    /// validation set (also above-left of the camera, and from the side) it registered
    /// with pose noise best.
    fn default() -> Self {
        Self {
            light: [0.0, 0.0, -1.0],
            ambient: 0.2,
        }
    }
}

impl Shading {
    /// The unit light direction, or an error for a zero or non-finite one or an ambient
    /// term outside [0, 1).
    pub fn unit_light(&self) -> Result<[f64; 3]> {
        let [x, y, z] = self.light;
        let norm = (x * x + y * y + z * z).sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(Error::InvalidInput(format!(
                "the light direction {:?} has no length",
                self.light
            )));
        }
        if !(0.0..1.0).contains(&self.ambient) {
            return Err(Error::InvalidInput(format!(
                "the ambient term {} is outside [0, 1)",
                self.ambient
            )));
        }
        Ok([x / norm, y / norm, z / norm])
    }
}

/// How a depth observation is compared (see [`ObservedDepth`]): per pixel where the
/// rendering covers the pixel centre and the observation measured depth (> 0), a bounded
/// (Geman-McClure) cost of the residual r = rendered - observed in units of `scale`,
/// u^2 / (1 + u^2) with u = r / s: about u^2 for small residuals and never more than 1,
/// so that a depth edge inside the silhouette (an open container's rim before its
/// inside), a mixed pixel or a sensor's outlier costs at most a wrong mask pixel; times
/// `weight`, averaged over the image's pixels as the mask term is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthLoss {
    /// Metres: the cost's scale (a residual of it costs half its most).
    pub scale: f64,
    /// Weight against the mask (or shading) term: at 1, a pixel whose depth is off by
    /// `scale` costs as much as a pixel of mask that is wrong.
    pub weight: f64,
    /// Metres (0: off): a rendered pixel that the observation shows as background, with a
    /// measured depth nearer than the rendered surface by more than this, is hidden by
    /// something in front (an occluder outside the instance mask) and counts for nothing,
    /// neither mask nor depth. Pixels the observation shows as object always count.
    pub occlusion: f64,
}

impl Default for DepthLoss {
    /// 1 cm, weight 1: a consumer RGB-D sensor's noise at half a metre is a few mm;
    /// occluders 2 cm in front of the rendered surface.
    fn default() -> Self {
        Self {
            scale: 0.01,
            weight: 1.0,
            occlusion: 0.02,
        }
    }
}

impl DepthLoss {
    /// An error for a scale or weight that is not positive and finite, or an occlusion
    /// tolerance that is negative or not finite.
    pub fn validate(&self) -> Result<()> {
        for (what, value) in [("scale", self.scale), ("weight", self.weight)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(Error::InvalidInput(format!(
                    "the depth loss {what} must be positive and finite, not {value}"
                )));
            }
        }
        if !(self.occlusion.is_finite() && self.occlusion >= 0.0) {
            return Err(Error::InvalidInput(format!(
                "the occlusion tolerance must be >= 0 m (0: off) and finite, not {}",
                self.occlusion
            )));
        }
        Ok(())
    }
}

/// An observed depth image of every view, compared with the rendered camera-space depth
/// besides the mask (or shading): `[view][row][column]` in metres, 0 where nothing was
/// measured. Depth is compared inside the rendered silhouette only and is not
/// antialiased; the silhouette's own gradient comes from the mask term.
#[derive(Clone, Copy, Debug)]
pub struct ObservedDepth<'a> {
    /// Observed depth, `[view][row][column]` in metres, 0 = not measured.
    pub depth: &'a [f32],
    /// How the depth is compared.
    pub loss: DepthLoss,
}

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
    stage: u32,
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
    /// with shading, dL/d(shade)).
    pub attribute_gradient: Vec<f32>,
    /// The antialiased compared image, `[view][row][column][channel]` (with depth, the last
    /// channel is the rendered depth at each covered pixel centre, not antialiased).
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
    /// Uploads the scene `desc` describes; an error for inconsistent inputs or
    /// buffers past the device's limits.
    pub fn new(ctx: &Context, desc: &SceneDesc) -> Result<Self> {
        let mesh = MeshBuffers::new(ctx, desc.mesh)?;
        let views = ViewBuffers::new(ctx, desc.views)?;
        let (w, h, n) = (views.width(), views.height(), views.count());
        let pixels = w as u64 * h as u64 * n as u64;
        let loss_pixels = desc.loss_pixels.unwrap_or(w as u64 * h as u64);
        if loss_pixels < w as u64 * h as u64 {
            // The fixed-point sums' bound (stats_shift) holds for terms averaged over at
            // least the image's pixels.
            return Err(Error::InvalidInput(format!(
                "the loss averaged over {loss_pixels} pixels: at least the view's {w}x{h}"
            )));
        }
        let vertices = desc.mesh.vertex_count() as u64;
        if desc.mesh.triangle_count() >= MAX_TRIANGLES {
            return Err(Error::Limit(format!(
                "{} triangles: the pixel-pair records hold triangle numbers below {MAX_TRIANGLES}",
                desc.mesh.triangle_count()
            )));
        }
        if desc.shading.is_some() && desc.attributes.is_some() {
            return Err(Error::InvalidInput(
                "a scene compares either attributes or shading, not both".into(),
            ));
        }
        let lambert = match desc.shading {
            None => None,
            Some(shading) => {
                let light = shading.unit_light()?.map(|v| v as f32);
                let (start, incident) = incident_triangles(desc.mesh);
                // lambert.comp loops over a vertex's triangles in one invocation.
                let valence = start.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);
                if valence > crate::gpu::LOOP_LIMIT / 2 {
                    return Err(Error::Limit(format!(
                        "a vertex of the mesh is shared by {valence} triangles; shading \
                         handles at most {} per vertex",
                        crate::gpu::LOOP_LIMIT / 2
                    )));
                }
                Some(LambertBuffers {
                    start: Buffer::from_slice(ctx, "incident triangle starts", &start)?,
                    incident: Buffer::from_slice(ctx, "incident triangles", &incident)?,
                    grad_normal: Buffer::new(
                        ctx,
                        "normal gradients",
                        n as u64 * vertices * 12,
                        BufferKind::Device,
                    )?,
                    light,
                    ambient: shading.ambient as f32,
                })
            }
        };
        if let Some(depth) = &desc.depth {
            depth.loss.validate()?;
        }
        // With depth, every vertex gains a last channel (written on the device), and a mask
        // becomes a constant channel 0 (coverage) so that depth can be interpolated.
        let with_depth = desc.depth.is_some() as u32;
        let coverage = desc.depth.is_some() && desc.attributes.is_none() && lambert.is_none();
        // Every view has its own attributes: given ones repeated, shading's and depth's
        // written on the device.
        let (attributes, channels) = match (desc.attributes, &lambert) {
            (None, None) if !coverage => (Buffer::from_slice(ctx, "attributes", &[0.0f32])?, 0),
            (None, _) => {
                let channels = 1 + with_depth;
                let bytes = n as u64 * vertices * channels as u64 * 4;
                (
                    Buffer::new(ctx, "attributes", bytes, BufferKind::Device)?,
                    channels,
                )
            }
            (Some((values, channels)), _) => {
                if !(1..=4 - with_depth).contains(&channels)
                    || values.len() != desc.mesh.vertex_count() * channels as usize
                {
                    return Err(Error::InvalidInput(format!(
                        "{} attribute values for {} vertices x {channels} channels (1 to {}{})",
                        values.len(),
                        desc.mesh.vertex_count(),
                        4 - with_depth,
                        if with_depth > 0 { " with depth" } else { "" }
                    )));
                }
                let stride = (channels + with_depth) as usize;
                let mut per_view = vec![0f32; desc.mesh.vertex_count() * stride];
                for (row, given) in per_view
                    .chunks_mut(stride)
                    .zip(values.chunks(channels as usize))
                {
                    row[..channels as usize].copy_from_slice(given);
                }
                let repeated = per_view.repeat(n as usize);
                (
                    Buffer::from_slice(ctx, "attributes", &repeated)?,
                    channels + with_depth,
                )
            }
        };
        if channels > 0 && desc.loss != Loss::Mse {
            let compared = if desc.depth.is_some() {
                "depth"
            } else if lambert.is_some() {
                "shading"
            } else {
                "attributes"
            };
            return Err(Error::InvalidInput(format!(
                "the {} loss compares masks; use mse with {compared}",
                desc.loss.name()
            )));
        }
        let image_channels = channels.max(1) as u64;
        let given_channels = image_channels - with_depth as u64;
        if desc.observed.len() as u64 != pixels * given_channels {
            return Err(Error::InvalidInput(format!(
                "observed images hold {} values, expected {n} views x {w} x {h} x {given_channels}",
                desc.observed.len()
            )));
        }
        if desc.observed.iter().any(|v| !v.is_finite()) {
            return Err(Error::InvalidInput(
                "observed images contain NaN or Inf".into(),
            ));
        }
        if let Some(depth) = &desc.depth {
            if depth.depth.len() as u64 != pixels {
                return Err(Error::InvalidInput(format!(
                    "observed depth holds {} values, expected {n} views x {w} x {h}",
                    depth.depth.len()
                )));
            }
            if let Some(bad) = depth.depth.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                return Err(Error::InvalidInput(format!(
                    "observed depth holds {bad}: depths are metres, >= 0 (0: not measured)"
                )));
            }
        }
        check_scene_fits(ctx, (w, h, n), image_channels, vertices, channels)?;
        // The compared image's channels side by side: the given ones, then depth.
        let observed: Vec<f32> = match &desc.depth {
            None => desc.observed.to_vec(),
            Some(depth) => desc
                .observed
                .chunks(given_channels as usize)
                .zip(depth.depth)
                .flat_map(|(given, &d)| given.iter().copied().chain([d]))
                .collect(),
        };
        let device = |name, bytes| Buffer::new(ctx, name, bytes, BufferKind::Device);
        let with_distance = desc.loss == Loss::Distance;
        let subgroups = 64u32.div_ceil(ctx.info().subgroup_size.max(1));
        let stats_shift = stats_shift(desc, w, h);
        let grid_groups = ctx.info().grid_groups.max(1);
        let pose_groups = (vertices as u32)
            .div_ceil(64)
            .clamp(1, POSE_GROUPS.min(grid_groups));
        Ok(Self {
            gbuffer: Gbuffer::new(ctx, w, h, n, Outputs::Ids)?,
            neighbours: Buffer::from_slice(ctx, "neighbours", &neighbours(desc.mesh))?,
            attributes,
            lambert,
            observed: Buffer::from_slice(ctx, "observed", &observed)?,
            distance: device("distance field", if with_distance { pixels * 4 } else { 4 })?,
            distance_scratch: if with_distance {
                let bytes = DistanceField::scratch_bytes(w, h, n);
                Some([
                    device("jump flooding a", bytes)?,
                    device("jump flooding b", bytes)?,
                ])
            } else {
                None
            },
            antialiased: device("antialiased", pixels * image_channels * 4)?,
            stats: device("loss stats", n as u64 * 16)?,
            stats_fixed: device("fixed-point loss stats", n as u64 * 24)?,
            background: device("background loss stats", n as u64 * 24)?,
            boxes: device("pixel boxes", box_words(n) * 4)?,
            stats_shift,
            loss_pixels,
            work: device("work list", pixels * 4)?,
            pair_work_x: device("pairs along x", pixels * 4)?,
            pair_work_y: device("pairs along y", pixels * 4)?,
            work_count: device("work count", WORK_COUNT_WORDS * 4)?,
            grad_camera: device("camera gradients", n as u64 * vertices * 12)?,
            grad_attributes: device(
                "attribute gradients",
                (n as u64 * vertices * channels as u64 * 4).max(4),
            )?,
            grad_camera_fixed: device("fixed-point camera gradients", n as u64 * vertices * 24)?,
            grad_attributes_fixed: device(
                "fixed-point attribute gradients",
                (n as u64 * vertices * channels as u64 * 8).max(8),
            )?,
            grad_object: device("vertex gradients", vertices * 12)?,
            grad_pose: device("pose gradients", n as u64 * 24)?,
            pose_partials: device(
                "pose partial sums",
                n as u64 * pose_groups as u64 * subgroups as u64 * 24,
            )?,
            touched: device(
                "touched vertex blocks",
                (vertices.div_ceil(VERTEX_BLOCK as u64).div_ceil(32) * 4).max(4),
            )?,
            pose_groups,
            grid_groups,
            subgroups,
            ids: device("triangle ids", pixels * 4)?,
            pairs_x: device("pixel pairs along x", pixels * 4)?,
            pairs_y: device("pixel pairs along y", pixels * 4)?,
            alphas_x: device("pixel-pair crossings along x", pixels * 4)?,
            alphas_y: device("pixel-pair crossings along y", pixels * 4)?,
            mesh,
            views,
            loss: desc.loss,
            channels,
            depth: desc.depth.map(|d| d.loss),
            coverage,
        })
    }

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

    fn record_marked(
        &self,
        renderer: &DiffRenderer,
        rec: &mut Recorder,
        marks: &mut Marks,
    ) -> Result<()> {
        let passes = renderer.passes(self.pass_variant())?;
        marks.start(rec);
        // The listed pixels, dispatch arguments, bounds and largest terms; the counts of
        // lost walks and unfinished pixels run on.
        rec.fill_buffer_range(&self.work_count, 0, 4 * LOST_WALKS as u64, 0);
        let after_lost = 4 * (LOST_WALKS as u64 + 1);
        rec.fill_buffer_range(
            &self.work_count,
            after_lost,
            4 * UNFINISHED as u64 - after_lost,
            0,
        );
        let after_unfinished = 4 * (UNFINISHED as u64 + 1);
        rec.fill_buffer_range(
            &self.work_count,
            after_unfinished,
            4 * WORK_COUNT_WORDS - after_unfinished,
            0,
        );
        // The loss sums start from the background's (record_prepare), the image from
        // background: classify.comp only visits the pixels near the object.
        rec.copy_buffer(
            &self.background,
            0,
            &self.stats_fixed,
            0,
            self.background.size(),
        );
        let n = self.views.count();
        // Projecting every vertex to find the box costs more than classifying every pixel
        // once a view has a third as many vertices as pixels: then the box is the image.
        // (lavapipe, 1024 x 1024: a vertex projected 9 ns, a background pixel classified
        // 3.7 ns; 1e6 vertices, 16% of the image in the box: box 9.5 + 5.4 ms, whole image
        // 0.6 + 8.5 ms.)
        let (width, height) = (self.views.width(), self.views.height());
        let whole_image = 3 * self.mesh.vertex_count() as u64 >= width as u64 * height as u64;
        let (lo, hi) = if whole_image {
            (-8i32 as u32, width.max(height) + 8)
        } else {
            (0x7fff_ffff, 0x8000_0001)
        };
        rec.fill_buffer_range(&self.boxes, 16, 8 * n as u64, lo);
        rec.fill_buffer_range(&self.boxes, 16 + 8 * n as u64, 8 * n as u64, hi);
        // The float camera and attribute gradients need no clearing: the resolve below
        // writes every element before the shading and depth passes add to them.
        for buffer in [
            &self.antialiased,
            &self.stats,
            &self.grad_camera_fixed,
            &self.grad_attributes_fixed,
            &self.grad_object,
        ] {
            rec.fill_buffer(buffer, 0);
        }
        // The pose pass visits only the vertex blocks the backward touched, or (when the
        // shading and depth passes add to every covered vertex) all of them.
        let shaded = self.lambert.is_some() || self.depth.is_some();
        rec.fill_buffer(&self.touched, if shaded { u32::MAX } else { 0 });
        marks.pass(rec, "clear")?;
        self.record_lambert(renderer, rec, 0);
        self.record_depth(renderer, rec, 0);
        marks.pass(rec, "shading")?;
        renderer
            .rasterizer
            .draw(rec, &self.mesh, &self.views, &self.gbuffer)?;
        marks.pass(rec, "G-buffer")?;
        // The passes below read ids from a buffer: plain loads are much cheaper than
        // storage-image loads on CPU drivers, and the copy is a memcpy.
        rec.transition(
            &[&self.gbuffer.ids],
            ImageState::Attachment,
            ImageState::TransferSrc,
        );
        rec.copy_image_to_buffer(&self.gbuffer.ids, &self.ids)?;
        let bindings = self.pass_bindings();
        let constants = self.pass_constants(0);
        let vertex_groups = self.grid(self.mesh.vertex_count());
        for (stage, groups) in [vertex_groups, 1].into_iter().enumerate() {
            if stage == 0 && whole_image {
                continue;
            }
            rec.memory_barrier();
            rec.run_compute(
                &renderer.bounds,
                &bindings,
                &self.pass_constants(stage as u32),
                Groups::Count(groups, 1, n),
            );
        }
        rec.memory_barrier();
        marks.pass(rec, "id copy, bounds")?;

        let work = Groups::Indirect(&self.work_count, 4);
        rec.run_compute(
            &passes.classify,
            &bindings,
            &constants,
            Groups::Indirect(&self.boxes, 0),
        );
        rec.memory_barrier();
        marks.pass(rec, "classify")?;

        rec.run_compute(
            &renderer.work_args,
            &[Binding::buffer(&self.work_count)],
            &self.grid_groups,
            Groups::Count(1, 1, 1),
        );
        rec.memory_barrier();
        marks.pass(rec, "work arguments")?;

        // The pairs (one walk each), then the antialiased image and its loss.
        let pairs = Groups::Indirect(&self.work_count, 4 * PAIR_DISPATCH);
        for (pipeline, groups, name) in [
            (&passes.pairs, pairs, "pairs"),
            (&passes.antialias, work, "antialias"),
        ] {
            rec.run_compute(pipeline, &bindings, &constants, groups);
            rec.memory_barrier();
            marks.pass(rec, name)?;
        }

        rec.run_compute(
            &renderer.finalize,
            &[
                Binding::buffer(&self.stats),
                Binding::buffer(&self.stats_fixed),
            ],
            &FinalizeConstants {
                loss: self.loss.code(),
                stats_shift: self.stats_shift,
            },
            Groups::Count(1, 1, n),
        );
        rec.memory_barrier();
        marks.pass(rec, "loss")?;
        marks.phase(rec, 1);

        // The backward: fixed-point sums at the scale the forward's bound on their terms
        // allows (glsl/include/fixed_point.glsl), resolved to floats.
        rec.run_compute(&passes.backward, &bindings, &constants, work);
        rec.memory_barrier();
        marks.pass(rec, "backward")?;
        let vertices = self.mesh.vertex_count();
        let mut resolve = |fixed: &Buffer, floats: &Buffer, count: u32, slots: (u32, u32)| {
            rec.run_compute(
                &renderer.resolve,
                &[
                    Binding::buffer(fixed),
                    Binding::buffer(floats),
                    Binding::buffer(&self.work_count),
                ],
                &ResolveConstants {
                    count,
                    max_slot: slots.0,
                    seen_slot: slots.1,
                    terms_per_listed: TERMS_PER_LISTED,
                },
                Groups::Count(self.grid(count), 1, 1),
            );
        };
        // The camera gradients go to floats here only when the shading or depth passes add
        // to them; otherwise the pose pass reads the fixed-point sums itself.
        if shaded {
            resolve(
                &self.grad_camera_fixed,
                &self.grad_camera,
                n * vertices * 3,
                (CAMERA_MAX, CAMERA_SEEN),
            );
        }
        if self.channels > 0 {
            resolve(
                &self.grad_attributes_fixed,
                &self.grad_attributes,
                n * vertices * self.channels,
                (ATTRIBUTE_MAX, ATTRIBUTE_SEEN),
            );
        }
        rec.memory_barrier();
        marks.pass(rec, "resolve")?;
        self.record_lambert(renderer, rec, 1);
        self.record_lambert(renderer, rec, 2);
        self.record_depth(renderer, rec, 1);
        marks.pass(rec, "shading backward")?;

        let pose_bindings = [
            Binding::buffer(self.mesh.positions()),
            Binding::buffer(self.views.views()),
            Binding::buffer(&self.grad_camera),
            Binding::buffer(&self.grad_object),
            Binding::buffer(&self.grad_pose),
            Binding::buffer(&self.pose_partials),
            Binding::buffer(&self.grad_camera_fixed),
            Binding::buffer(&self.work_count),
            Binding::buffer(&self.touched),
        ];
        let pose = |stage| PoseConstants {
            vertex_count: vertices,
            view_count: n,
            groups: self.pose_groups,
            stage,
            subgroups: self.subgroups,
            from_fixed: !shaded as u32,
            max_slot: CAMERA_MAX,
            seen_slot: CAMERA_SEEN,
            terms_per_listed: TERMS_PER_LISTED,
            vertex_block: VERTEX_BLOCK,
        };
        let per_stage = [
            Groups::Count(self.pose_groups, 1, 1),
            Groups::Count(1, 1, n),
        ];
        for (stage, groups) in per_stage.into_iter().enumerate() {
            rec.run_compute(&renderer.pose, &pose_bindings, &pose(stage as u32), groups);
            rec.memory_barrier();
        }
        marks.pass(rec, "pose gradient")?;
        marks.phase(rec, 2);
        Ok(())
    }

    /// With shading, one stage of `glsl/lambert.comp` (and a barrier after it).
    fn record_lambert(&self, renderer: &DiffRenderer, rec: &mut Recorder, stage: u32) {
        let Some(lambert) = &self.lambert else {
            return;
        };
        let vertices = self.mesh.vertex_count();
        rec.run_compute(
            &renderer.lambert,
            &[
                Binding::buffer(self.mesh.positions()),
                Binding::buffer(self.mesh.triangles()),
                Binding::buffer(self.views.views()),
                Binding::buffer(&lambert.start),
                Binding::buffer(&lambert.incident),
                Binding::buffer(&self.attributes),
                Binding::buffer(&self.grad_attributes),
                Binding::buffer(&lambert.grad_normal),
                Binding::buffer(&self.grad_camera),
            ],
            &LambertConstants {
                vertex_count: vertices,
                stage,
                ambient: lambert.ambient,
                light: lambert.light,
                stride: self.channels,
            },
            Groups::Count(vertices.div_ceil(64), 1, self.views.count()),
        );
        rec.memory_barrier();
    }

    /// With depth, one stage of `glsl/depth.comp` (and a barrier after it).
    fn record_depth(&self, renderer: &DiffRenderer, rec: &mut Recorder, stage: u32) {
        if self.depth.is_none() {
            return;
        }
        let vertices = self.mesh.vertex_count();
        rec.run_compute(
            &renderer.depth,
            &[
                Binding::buffer(self.mesh.positions()),
                Binding::buffer(self.views.views()),
                Binding::buffer(&self.attributes),
                Binding::buffer(&self.grad_attributes),
                Binding::buffer(&self.grad_camera),
            ],
            &DepthConstants {
                vertex_count: vertices,
                stage,
                channels: self.channels,
                coverage: self.coverage as u32,
            },
            Groups::Count(vertices.div_ceil(64), 1, self.views.count()),
        );
        rec.memory_barrier();
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
