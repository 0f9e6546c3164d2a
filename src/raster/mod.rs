//! The forward rasterizer: a Vulkan graphics pipeline that writes the G-buffer (triangle
//! id + 1, perspective-correct barycentrics, optionally camera-space depth) for several
//! views of one mesh, plus a plain Lambert-shaded colour render for pictures and as the
//! benchmark baseline. [`reference`](mod@reference) is the CPU float64 rasterizer the tests compare to.

#[doc(hidden)] // the float64 model the tests check the device against
pub mod reference;

use bytemuck::{Pod, Zeroable};
use ndarray::{Array3, Array4};

use crate::camera::{Camera, Pose};
use crate::error::{Error, Result};
use crate::gpu::{
    Binding, Buffer, BufferKind, Context, Format, GraphicsPipeline, GraphicsPipelineDesc, Image,
    ImageState, Recorder, RenderTarget,
};
use crate::mesh::Mesh;
use crate::shaders;

/// One camera looking at the mesh from one pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Intrinsics and image size.
    pub camera: Camera,
    /// Object-to-camera transform.
    pub pose: Pose,
}

/// One view as the shaders see it (`glsl/include/views.glsl`): the plain render's push
/// constants and an element of [`ViewBuffers`].
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct ViewData {
    /// Column-major object-to-camera matrix.
    pub object_to_camera: [[f32; 4]; 4],
    intrinsics: [f32; 4],
    size: [f32; 2],
    near: f32,
    first_triangle: u32,
}
const _: () = assert!(shaders::SHADED_VERT.takes::<ViewData>());

impl ViewData {
    /// The shader data of `view` (its triangles start at 0).
    pub fn new(view: &View) -> Self {
        let c = &view.camera;
        Self {
            object_to_camera: view.pose.matrix_f32(),
            intrinsics: [c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32],
            size: [c.width as f32, c.height as f32],
            near: c.near as f32,
            first_triangle: 0,
        }
    }
}

/// Push constants of the G-buffer pass.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GbufferConstants {
    view: u32,
    first_triangle: u32,
}
const _: () = assert!(shaders::GBUFFER_VERT.takes::<GbufferConstants>());

/// The views of one mesh on the device: their camera data, read by the G-buffer pass and
/// by compute passes (which may also update it).
pub struct ViewBuffers {
    views: Buffer,
    count: u32,
    width: u32,
    height: u32,
}

impl ViewBuffers {
    /// Buffers for `views`; all views must share one image size.
    pub fn new(ctx: &Context, views: &[View]) -> Result<Self> {
        let first = views
            .first()
            .ok_or_else(|| Error::InvalidInput("no views to render".into()))?;
        let count = views.len() as u32;
        let mut buffers = Self {
            views: Buffer::new(
                ctx,
                "views",
                count as u64 * std::mem::size_of::<ViewData>() as u64,
                BufferKind::Device,
            )?,
            count,
            width: first.camera.width,
            height: first.camera.height,
        };
        buffers.set(views)?;
        Ok(buffers)
    }

    /// Replaces the camera data of all views (same count and image size).
    pub fn set(&mut self, views: &[View]) -> Result<()> {
        if views.len() as u32 != self.count {
            return Err(Error::InvalidInput(format!(
                "{} views given for buffers of {}",
                views.len(),
                self.count
            )));
        }
        for v in views {
            if (v.camera.width, v.camera.height) != (self.width, self.height) {
                return Err(Error::InvalidInput(format!(
                    "camera of {}x{} does not match the other views' {}x{}",
                    v.camera.width, v.camera.height, self.width, self.height
                )));
            }
        }
        let data: Vec<ViewData> = views.iter().map(ViewData::new).collect();
        self.views.write(0, &data)
    }

    /// Number of views.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Image width of every view, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height of every view, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Reads the views' data back (poses may have been updated on the device).
    pub fn read_data(&self) -> Result<Vec<ViewData>> {
        self.views.read_range::<ViewData>(0, self.count as usize)
    }

    /// The `ViewData` array.
    pub fn views(&self) -> &Buffer {
        &self.views
    }
}

/// A mesh on the device: positions (float x, y, z per vertex, writable by compute passes)
/// and triangle indices, and the index order of the ids-only G-buffer draw
/// ([`provoking_order`]).
pub struct MeshBuffers {
    positions: Buffer,
    triangles: Buffer,
    /// The ids draw's index buffer: triangle t is entries [t, ., .].
    provoking: Buffer,
    /// The mesh vertex of each entry of that draw.
    sources: Buffer,
    vertex_count: u32,
    triangle_count: u32,
}

/// The triangle id without `gl_PrimitiveID`: an index order for one indexed draw in which
/// triangle t's provoking (first) vertex is draw entry t, so a flat attribute `entry + 1`
/// is the id + 1. Returns the draw's indices (3 per triangle, each triangle's corners
/// rotated, never reordered, so the winding and the covered pixels are the mesh's) and the
/// mesh vertex of every entry. Entries 0..triangles are each triangle's provoking corner
/// (greedily one not yet used, so most vertices appear once); a vertex no triangle
/// provokes gets one more entry, and the other two corners of a triangle use the vertex's
/// first entry.
///
/// Why: on CPU drivers (llvmpipe) a fragment shader that reads `gl_PrimitiveID` sends
/// every triangle through the slow primitive pipeline (about 1.5x a plain render at 1e6
/// triangles); a flat attribute costs a plain render plus one vertex shader invocation
/// per extra entry (about twice the vertices), and needs no geometry-shader capability.
pub fn provoking_order(mesh: &Mesh) -> (Vec<u32>, Vec<u32>) {
    let triangles = mesh.triangles();
    let mut entry_of = vec![u32::MAX; mesh.vertex_count()];
    let mut sources = Vec::with_capacity(triangles.len() + triangles.len() / 8);
    let mut first_corner = Vec::with_capacity(triangles.len());
    for (t, tri) in triangles.iter().enumerate() {
        let k = (0..3)
            .find(|&k| entry_of[tri[k] as usize] == u32::MAX)
            .unwrap_or(0);
        if entry_of[tri[k] as usize] == u32::MAX {
            entry_of[tri[k] as usize] = t as u32;
        }
        sources.push(tri[k]);
        first_corner.push(k);
    }
    for (v, entry) in entry_of.iter_mut().enumerate() {
        if *entry == u32::MAX {
            *entry = sources.len() as u32;
            sources.push(v as u32);
        }
    }
    let indices = triangles
        .iter()
        .zip(first_corner)
        .enumerate()
        .flat_map(|(t, (tri, k))| {
            [
                t as u32,
                entry_of[tri[(k + 1) % 3] as usize],
                entry_of[tri[(k + 2) % 3] as usize],
            ]
        })
        .collect();
    (indices, sources)
}

impl MeshBuffers {
    /// Uploads `mesh`; an error when a buffer would exceed the device's storage
    /// buffer range or the mesh has too many triangles.
    pub fn new(ctx: &Context, mesh: &Mesh) -> Result<Self> {
        // A buffer that the vertex stage binds whole must fit one storage-buffer range.
        let limit = ctx.info().max_storage_buffer_range as u64;
        let fits = |what: String, bytes: u64| {
            if bytes > limit {
                Err(Error::Limit(format!(
                    "{what} need {bytes} bytes, over the device's storage buffer range of \
                     {limit} bytes"
                )))
            } else {
                Ok(())
            }
        };
        fits(
            format!("{} vertices", mesh.vertex_count()),
            mesh.vertex_count() as u64 * 12,
        )?;
        let triangle_count = u32::try_from(mesh.triangle_count())
            .ok()
            .filter(|&t| t < u32::MAX / 3)
            .ok_or_else(|| Error::Limit(format!("{} triangles", mesh.triangle_count())))?;
        let (provoking, sources) = provoking_order(mesh);
        fits(
            format!("the ids draw's {} entries", sources.len()),
            sources.len() as u64 * 4,
        )?;
        Ok(Self {
            positions: Buffer::from_slice(ctx, "mesh positions", mesh.positions())?,
            triangles: Buffer::from_slice(ctx, "mesh triangles", mesh.triangles())?,
            provoking: Buffer::from_slice(ctx, "ids draw indices", &provoking)?,
            sources: Buffer::from_slice(ctx, "ids draw sources", &sources)?,
            vertex_count: mesh.vertex_count() as u32,
            triangle_count,
        })
    }

    /// The positions buffer (3 floats per vertex), for passes that deform the mesh.
    pub fn positions(&self) -> &Buffer {
        &self.positions
    }

    /// The triangle buffer (3 vertex indices, u32, per triangle).
    pub fn triangles(&self) -> &Buffer {
        &self.triangles
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> u32 {
        self.vertex_count
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> u32 {
        self.triangle_count
    }
}

/// Which G-buffer outputs a pass writes (besides the depth test): only what the consumer
/// reads is rendered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outputs {
    /// Triangle ids only (what the differentiable passes read).
    Ids,
    /// Ids and barycentrics.
    IdsBary,
    /// Ids, barycentrics and camera-space depth.
    IdsBaryDepth,
}

/// The G-buffer images, one layer per view: ids (`R32_UINT`, triangle id + 1, 0 =
/// background), optionally barycentrics (`RG32_SFLOAT`, weights of corners 0 and 1) and
/// camera-space depth (`R32_SFLOAT`, 0 = background), and the depth-test buffer.
pub struct Gbuffer {
    /// Triangle id + 1 per pixel (`R32_UINT`), 0 = background.
    pub ids: Image,
    /// Barycentric weights of corners 0 and 1 (`RG32_SFLOAT`); `None` with
    /// [`Outputs::Ids`].
    pub bary: Option<Image>,
    /// Camera-space depth (`R32_SFLOAT`), 0 = background; only with
    /// [`Outputs::IdsBaryDepth`].
    pub depth: Option<Image>,
    depth_test: Image,
    outputs: Outputs,
}

impl Gbuffer {
    /// Images for `views` views of `width` x `height`.
    pub fn new(
        ctx: &Context,
        width: u32,
        height: u32,
        views: u32,
        outputs: Outputs,
    ) -> Result<Self> {
        let image = |name, format| {
            Image::new(
                ctx,
                name,
                format,
                width,
                height,
                views,
                format != Format::D32Float,
            )
        };
        Ok(Self {
            ids: image("gbuffer ids", Format::R32Uint)?,
            bary: (outputs != Outputs::Ids)
                .then(|| image("gbuffer bary", Format::Rg32Float))
                .transpose()?,
            depth: (outputs == Outputs::IdsBaryDepth)
                .then(|| image("gbuffer depth", Format::R32Float))
                .transpose()?,
            depth_test: image("gbuffer depth test", Format::D32Float)?,
            outputs,
        })
    }

    /// Image width, pixels.
    pub fn width(&self) -> u32 {
        self.ids.width()
    }

    /// Image height, pixels.
    pub fn height(&self) -> u32 {
        self.ids.height()
    }

    /// Number of views (image layers).
    pub fn views(&self) -> u32 {
        self.ids.layers()
    }

    /// Which outputs the G-buffer holds.
    pub fn outputs(&self) -> Outputs {
        self.outputs
    }

    /// The output images (not the depth test), in attachment order.
    pub fn images(&self) -> Vec<&Image> {
        std::iter::once(&self.ids)
            .chain(self.bary.as_ref())
            .chain(self.depth.as_ref())
            .collect()
    }

    /// Records copies of the G-buffer (left in the attachment state by
    /// [`Rasterizer::draw`]) into `readback`, which must be [`GbufferReadback::new`]'s.
    pub fn record_readback(&self, rec: &mut Recorder, readback: &GbufferReadback) -> Result<()> {
        rec.transition(
            &self.images(),
            ImageState::Attachment,
            ImageState::TransferSrc,
        );
        for (image, buffer) in self.images().into_iter().zip(readback.buffers()) {
            rec.copy_image_to_buffer(image, buffer)?;
        }
        Ok(())
    }
}

/// Host-visible buffers that receive a G-buffer.
pub struct GbufferReadback {
    ids: Buffer,
    bary: Option<Buffer>,
    depth: Option<Buffer>,
    shape: (usize, usize, usize),
}

impl GbufferReadback {
    /// Readback buffers sized for `gbuffer`'s output images.
    pub fn new(ctx: &Context, gbuffer: &Gbuffer) -> Result<Self> {
        let buffer =
            |name, image: &Image| Buffer::new(ctx, name, image.byte_size(), BufferKind::Readback);
        Ok(Self {
            ids: buffer("readback ids", &gbuffer.ids)?,
            bary: gbuffer
                .bary
                .as_ref()
                .map(|b| buffer("readback bary", b))
                .transpose()?,
            depth: gbuffer
                .depth
                .as_ref()
                .map(|d| buffer("readback depth", d))
                .transpose()?,
            shape: (
                gbuffer.views() as usize,
                gbuffer.height() as usize,
                gbuffer.width() as usize,
            ),
        })
    }

    fn buffers(&self) -> Vec<&Buffer> {
        std::iter::once(&self.ids)
            .chain(self.bary.as_ref())
            .chain(self.depth.as_ref())
            .collect()
    }

    /// The G-buffer on the host (after the recording that filled it has completed).
    pub fn read(&mut self) -> Result<GbufferData> {
        let (v, h, w) = self.shape;
        let n = v * h * w;
        let shape_err = |e: ndarray::ShapeError| Error::InvalidInput(e.to_string());
        let ids = self.ids.read_range::<u32>(0, n)?;
        let bary = match self.bary.as_mut() {
            Some(b) => Some(
                Array4::from_shape_vec((v, h, w, 2), b.read_range::<f32>(0, 2 * n)?)
                    .map_err(shape_err)?,
            ),
            None => None,
        };
        let depth = match self.depth.as_mut() {
            Some(d) => Some(
                Array3::from_shape_vec((v, h, w), d.read_range::<f32>(0, n)?).map_err(shape_err)?,
            ),
            None => None,
        };
        Ok(GbufferData {
            ids: Array3::from_shape_vec((v, h, w), ids).map_err(shape_err)?,
            bary,
            depth,
        })
    }
}

/// A G-buffer on the host, indexed [view, row, column].
#[derive(Clone, Debug)]
pub struct GbufferData {
    /// Triangle id + 1, 0 where no triangle covers the pixel centre.
    pub ids: Array3<u32>,
    /// Barycentric weights of corners 0 and 1 (corner 2: 1 - u - v); 0 on background.
    pub bary: Option<Array4<f32>>,
    /// Camera-space z in metres, 0 on background (when asked for).
    pub depth: Option<Array3<f32>>,
}

/// Views per submission of [`Rasterizer::render`].
pub const RENDER_CHUNK: usize = 8;

/// The forward rasterizer's pipelines.
pub struct Rasterizer {
    gbuffer_ids: GraphicsPipeline,
    gbuffer: GraphicsPipeline,
    gbuffer_with_depth: GraphicsPipeline,
    shaded: GraphicsPipeline,
    /// Triangles per draw, so that each draw's index range fits `maxStorageBufferRange`.
    chunk_triangles: u32,
}

// The ids-only pass takes the view (layer) alone.
const _: () = assert!(shaders::GBUFFER_INDEXED_VERT.takes::<u32>());

impl Rasterizer {
    /// Builds the G-buffer and shaded-render pipelines.
    pub fn new(ctx: &Context) -> Result<Self> {
        let pipeline = |name, vertex, fragment, color_formats: &[Format]| {
            GraphicsPipeline::new(
                ctx,
                &GraphicsPipelineDesc {
                    name,
                    vertex,
                    fragment,
                    color_formats,
                    depth_format: Some(Format::D32Float),
                },
            )
        };
        let gbuffer_ids = pipeline(
            "gbuffer ids",
            &shaders::GBUFFER_INDEXED_VERT,
            &shaders::GBUFFER_INDEXED_IDS_FRAG,
            &[Format::R32Uint],
        )?;
        let gbuffer = pipeline(
            "gbuffer",
            &shaders::GBUFFER_VERT,
            &shaders::GBUFFER_FRAG,
            &[Format::R32Uint, Format::Rg32Float],
        )?;
        let gbuffer_with_depth = pipeline(
            "gbuffer with depth",
            &shaders::GBUFFER_VERT,
            &shaders::GBUFFER_DEPTH_FRAG,
            &[Format::R32Uint, Format::Rg32Float, Format::R32Float],
        )?;
        let shaded = pipeline(
            "shaded",
            &shaders::SHADED_VERT,
            &shaders::SHADED_FRAG,
            &[Format::Rgba8Unorm],
        )?;
        let info = ctx.info();
        // Offsets of chunk ranges must be aligned; 256 triangles = 3 KiB keeps any
        // power-of-two alignment up to 1 KiB.
        let per_chunk = info.max_storage_buffer_range as u64 / 12;
        let chunk_triangles = ((per_chunk / 256) * 256).clamp(256, u32::MAX as u64 / 3) as u32;
        Ok(Self {
            gbuffer_ids,
            gbuffer,
            gbuffer_with_depth,
            shaded,
            chunk_triangles,
        })
    }

    /// Records the G-buffer pass for every view (view k into layer k). Ids alone (the
    /// differentiable passes' input) come from one indexed draw, the id from the
    /// provoking vertex ([`provoking_order`]); barycentrics and depth from non-indexed draws whose vertex k of
    /// triangle t carries the id and a unit barycentric vector (in chunks whose index
    /// range fits `maxStorageBufferRange`). The images end in [`ImageState::Attachment`].
    pub fn draw(
        &self,
        rec: &mut Recorder,
        mesh: &MeshBuffers,
        views: &ViewBuffers,
        target: &Gbuffer,
    ) -> Result<()> {
        if (views.width, views.height) != (target.width(), target.height())
            || views.count > target.views()
        {
            return Err(Error::InvalidInput(format!(
                "{} views of {}x{} do not fit a G-buffer of {} layers of {}x{}",
                views.count,
                views.width,
                views.height,
                target.views(),
                target.width(),
                target.height()
            )));
        }
        let mut images = target.images();
        images.push(&target.depth_test);
        rec.transition(&images, ImageState::Undefined, ImageState::Attachment);
        let pipeline = match target.outputs {
            Outputs::Ids => &self.gbuffer_ids,
            Outputs::IdsBary => &self.gbuffer,
            Outputs::IdsBaryDepth => &self.gbuffer_with_depth,
        };
        for layer in 0..views.count {
            let colors: Vec<_> = target
                .images()
                .into_iter()
                .map(|image| (image, layer, [0.0; 4]))
                .collect();
            rec.begin_rendering(&RenderTarget {
                colors: &colors,
                depth: Some((&target.depth_test, layer, 0.0)),
            })?;
            rec.bind_graphics(pipeline);
            if target.outputs == Outputs::Ids {
                rec.push_graphics_bindings(
                    pipeline,
                    &[
                        Binding::buffer(&mesh.positions),
                        Binding::buffer(&views.views),
                        Binding::buffer(&mesh.sources),
                    ],
                );
                rec.graphics_constants(pipeline, &layer);
                rec.draw_indexed(&mesh.provoking, 0, 3 * mesh.triangle_count);
                rec.end_rendering();
                continue;
            }
            let mut first = 0u32;
            while first < mesh.triangle_count {
                let count = self.chunk_triangles.min(mesh.triangle_count - first);
                rec.push_graphics_bindings(
                    pipeline,
                    &[
                        Binding::buffer(&mesh.positions),
                        Binding::buffer(&views.views),
                        Binding::Buffer {
                            buffer: &mesh.triangles,
                            offset: first as u64 * 12,
                            range: count as u64 * 12,
                        },
                    ],
                );
                rec.graphics_constants(
                    pipeline,
                    &GbufferConstants {
                        view: layer,
                        first_triangle: first,
                    },
                );
                rec.draw(3 * count);
                first += count;
            }
            rec.end_rendering();
        }
        Ok(())
    }

    /// Records the plain colour render (Lambert, one light at the camera; vertices
    /// transformed in the vertex shader) of every view into `target` (view k into layer
    /// k). The images end in [`ImageState::Attachment`].
    pub fn draw_shaded(
        &self,
        rec: &mut Recorder,
        mesh: &MeshBuffers,
        views: &[View],
        target: &ShadedTarget,
    ) -> Result<()> {
        let (w, h, layers) = (
            target.colour.width(),
            target.colour.height(),
            target.colour.layers(),
        );
        if views.is_empty() || views.len() as u32 > layers {
            return Err(Error::InvalidInput(format!(
                "{} views for {layers} layers",
                views.len()
            )));
        }
        if let Some(v) = views
            .iter()
            .find(|v| (v.camera.width, v.camera.height) != (w, h))
        {
            return Err(Error::InvalidInput(format!(
                "camera of {}x{} does not match the target of {w}x{h}",
                v.camera.width, v.camera.height
            )));
        }
        rec.transition(
            &[&target.colour, &target.depth_test],
            ImageState::Undefined,
            ImageState::Attachment,
        );
        for (layer, view) in views.iter().enumerate() {
            let layer = layer as u32;
            rec.begin_rendering(&RenderTarget {
                colors: &[(&target.colour, layer, [1.0; 4])],
                depth: Some((&target.depth_test, layer, 0.0)),
            })?;
            rec.bind_graphics(&self.shaded);
            rec.push_graphics_bindings(&self.shaded, &[Binding::buffer(&mesh.positions)]);
            rec.graphics_constants(&self.shaded, &ViewData::new(view));
            rec.draw_indexed(&mesh.triangles, 0, 3 * mesh.triangle_count);
            rec.end_rendering();
        }
        Ok(())
    }

    /// One-shot convenience: uploads `mesh`, draws every view and reads the G-buffer back:
    /// [`RENDER_CHUNK`] views per submission into one G-buffer reused, each chunk read
    /// straight into the returned arrays, so that the memory touched is the caller's
    /// arrays and one chunk's G-buffer however many views there are (`bindings/python`'s
    /// `benches/batch.py` measures a batch against a loop).
    pub fn render(
        &self,
        ctx: &Context,
        mesh: &Mesh,
        views: &[View],
        outputs: Outputs,
    ) -> Result<GbufferData> {
        let buffers = MeshBuffers::new(ctx, mesh)?;
        let first = views.chunks(RENDER_CHUNK).next().unwrap_or_default();
        let mut view_buffers = ViewBuffers::new(ctx, first)?;
        let target = Gbuffer::new(
            ctx,
            view_buffers.width,
            view_buffers.height,
            view_buffers.count,
            outputs,
        )?;
        let readback = GbufferReadback::new(ctx, &target)?;
        // The host's arrays, filled chunk by chunk (each view's pixels in order).
        let pixels = (target.width() * target.height()) as usize;
        let n = views.len() * pixels;
        let mut ids = vec![0u32; n];
        let mut bary = target.bary.as_ref().map(|_| vec![0f32; 2 * n]);
        let mut depth = target.depth.as_ref().map(|_| vec![0f32; n]);
        for (k, part) in views.chunks(RENDER_CHUNK).enumerate() {
            if part.len() as u32 == view_buffers.count {
                view_buffers.set(part)?;
            } else {
                view_buffers = ViewBuffers::new(ctx, part)?;
            }
            let mut rec = Recorder::new(ctx)?;
            self.draw(&mut rec, &buffers, &view_buffers, &target)?;
            target.record_readback(&mut rec, &readback)?;
            ctx.submit_and_wait(rec)?;
            let span = k * RENDER_CHUNK * pixels..(k * RENDER_CHUNK + part.len()) * pixels;
            readback.ids.read_range_into(0, &mut ids[span.clone()])?;
            if let (Some(all), Some(b)) = (bary.as_mut(), &readback.bary) {
                b.read_range_into(0, &mut all[2 * span.start..2 * span.end])?;
            }
            if let (Some(all), Some(d)) = (depth.as_mut(), &readback.depth) {
                d.read_range_into(0, &mut all[span])?;
            }
        }
        let shape = (
            views.len(),
            target.height() as usize,
            target.width() as usize,
        );
        let err = |e: ndarray::ShapeError| Error::InvalidInput(e.to_string());
        Ok(GbufferData {
            ids: Array3::from_shape_vec(shape, ids).map_err(err)?,
            bary: bary
                .map(|b| Array4::from_shape_vec((shape.0, shape.1, shape.2, 2), b))
                .transpose()
                .map_err(err)?,
            depth: depth
                .map(|d| Array3::from_shape_vec(shape, d))
                .transpose()
                .map_err(err)?,
        })
    }

    /// One-shot convenience: the shaded colour pictures (RGBA8, [view, row, column, channel]).
    pub fn render_shaded(&self, ctx: &Context, mesh: &Mesh, views: &[View]) -> Result<Array4<u8>> {
        let first = views
            .first()
            .ok_or_else(|| Error::InvalidInput("no views to render".into()))?;
        let (w, h, n) = (first.camera.width, first.camera.height, views.len() as u32);
        let buffers = MeshBuffers::new(ctx, mesh)?;
        let target = ShadedTarget::new(ctx, w, h, n)?;
        let readback = Buffer::new(
            ctx,
            "readback colour",
            target.colour.byte_size(),
            BufferKind::Readback,
        )?;
        let mut rec = Recorder::new(ctx)?;
        self.draw_shaded(&mut rec, &buffers, views, &target)?;
        rec.transition(
            &[&target.colour],
            ImageState::Attachment,
            ImageState::TransferSrc,
        );
        rec.copy_image_to_buffer(&target.colour, &readback)?;
        ctx.submit_and_wait(rec)?;
        let pixels = readback.read_range::<u8>(0, target.colour.byte_size() as usize)?;
        Array4::from_shape_vec((n as usize, h as usize, w as usize, 4), pixels)
            .map_err(|e| Error::InvalidInput(e.to_string()))
    }
}

/// Colour and depth-test images of the plain shaded render.
pub struct ShadedTarget {
    /// Colour image (`RGBA8_UNORM`), one layer per view.
    pub colour: Image,
    depth_test: Image,
}

impl ShadedTarget {
    /// Images for `views` views of `width` x `height`.
    pub fn new(ctx: &Context, width: u32, height: u32, views: u32) -> Result<Self> {
        Ok(Self {
            colour: Image::new(
                ctx,
                "shaded colour",
                Format::Rgba8Unorm,
                width,
                height,
                views,
                false,
            )?,
            depth_test: Image::new(
                ctx,
                "shaded depth test",
                Format::D32Float,
                width,
                height,
                views,
                false,
            )?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every triangle provokes its own entry, its corners keep their cyclic order (so the
    /// winding is the mesh's), and each vertex has an entry even where no triangle could
    /// give it one.
    #[test]
    fn provoking_order_gives_every_triangle_its_own_first_entry() {
        let sphere = Mesh::uv_sphere(0.1, 9, 13);
        // A vertex that no triangle uses, and a fan whose centre provokes one triangle only.
        let mut positions = sphere.positions().to_vec();
        positions.push([1.0, 1.0, 1.0]);
        let mesh = Mesh::new(positions, sphere.triangles().to_vec()).unwrap();
        let (indices, sources) = provoking_order(&mesh);
        assert_eq!(indices.len(), 3 * mesh.triangle_count());
        for (t, tri) in mesh.triangles().iter().enumerate() {
            let entries: [u32; 3] = indices[3 * t..3 * t + 3].try_into().unwrap();
            assert_eq!(entries[0], t as u32, "triangle {t}");
            let corners = entries.map(|e| sources[e as usize]);
            let rotations = [*tri, [tri[1], tri[2], tri[0]], [tri[2], tri[0], tri[1]]];
            assert!(
                rotations.contains(&corners),
                "triangle {t}: {corners:?} from {tri:?}"
            );
        }
        let mut seen = vec![false; mesh.vertex_count()];
        for &v in &sources {
            seen[v as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
        // Greedy choice keeps the extra vertex work small: one entry per triangle plus few.
        assert!(sources.len() <= mesh.triangle_count() + mesh.vertex_count() / 10 + 1);
    }
}
