//! Command recording: a [`Recorder`] wraps one primary command buffer; capabilities record
//! into a recorder they are handed and never submit on their own. A finished
//! [`Recording`] can be replayed any number of times: it holds a share in every buffer,
//! image, pipeline and query pool it uses, so none of them can be freed before it.

use ash::vk;

use super::pipeline::PipelineCommon;
use super::{
    vk_err, Binding, BindingKind, Buffer, ComputePipeline, Context, GraphicsPipeline, Held, Image,
    ImageState, Timestamps,
};
use crate::error::{Error, Result};

/// Attachments of one dynamic-rendering pass: one layer of each image, cleared first.
pub struct RenderTarget<'a> {
    /// Colour attachments with their clear colour (all-zero bits clear integer formats to 0).
    pub colors: &'a [(&'a Image, u32, [f32; 4])],
    /// Depth attachment and its clear depth (reverse-Z: clear to 0).
    pub depth: Option<(&'a Image, u32, f32)>,
}

/// The workgroups of a compute pass.
#[derive(Clone, Copy)]
pub enum Groups<'a> {
    /// Workgroup counts in x, y and z.
    Count(u32, u32, u32),
    /// Counts (3 x u32) that an earlier pass wrote into the buffer at a byte offset (a
    /// multiple of 4).
    Indirect(&'a Buffer, u64),
}

/// A command buffer being recorded.
pub struct Recorder {
    ctx: Context,
    pub(crate) raw: vk::CommandBuffer,
    /// The first command that exceeded a device limit; it was not recorded, and
    /// [`Recorder::finish`] returns this error instead of a recording.
    refused: Option<Error>,
    /// A share in every resource a recorded command uses.
    held: Vec<Held>,
}

/// A finished command buffer; [`Context::replay`] runs it again and again. It keeps every
/// resource its commands use alive, however their owners drop them.
pub struct Recording {
    ctx: Context,
    raw: vk::CommandBuffer,
    /// Never read: kept so that what the commands use outlives them.
    _held: Vec<Held>,
}

impl Drop for Recording {
    fn drop(&mut self) {
        // The command buffer goes first, then (as the fields drop) the shares in what it
        // used.
        self.ctx.free_command_buffer(self.raw);
    }
}

impl Context {
    /// Ends the recording, submits it and waits (bounded) until the device is done.
    pub fn submit_and_wait(&self, recorder: Recorder) -> Result<()> {
        let recording = recorder.finish()?;
        self.replay(&recording)
    }

    /// Submits a finished recording again and waits (bounded) until it completes.
    pub fn replay(&self, recording: &Recording) -> Result<()> {
        self.submit_command_buffer(recording.raw)
    }
}

impl Recorder {
    /// Allocates a command buffer from the context's pool and begins recording.
    pub fn new(ctx: &Context) -> Result<Self> {
        let raw = ctx.allocate_command_buffer()?;
        let begin = vk::CommandBufferBeginInfo::default();
        // SAFETY: freshly allocated command buffer.
        if let Err(e) = unsafe { ctx.device().begin_command_buffer(raw, &begin) } {
            ctx.free_command_buffer(raw);
            return Err(vk_err("vkBeginCommandBuffer")(e));
        }
        Ok(Self {
            ctx: ctx.clone(),
            raw,
            refused: None,
            held: Vec::new(),
        })
    }

    /// Ends recording; the result can be submitted any number of times.
    pub fn finish(mut self) -> Result<Recording> {
        if let Some(error) = self.refused.take() {
            return Err(error);
        }
        let raw = std::mem::replace(&mut self.raw, vk::CommandBuffer::null());
        let recording = Recording {
            ctx: self.ctx.clone(),
            raw,
            _held: std::mem::take(&mut self.held),
        };
        // SAFETY: the command buffer is in the recording state.
        unsafe { self.ctx.device().end_command_buffer(raw) }
            .map_err(vk_err("vkEndCommandBuffer"))?;
        Ok(recording)
    }

    fn device(&self) -> &ash::Device {
        self.ctx.device()
    }

    /// Keeps a resource a command uses alive as long as the recording.
    fn hold(&mut self, share: Held) {
        self.held.push(share);
    }

    /// Makes all earlier writes (any stage) visible to all later commands.
    pub fn memory_barrier(&mut self) {
        let barrier = [vk::MemoryBarrier2::default()
            .src_stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
            .src_access_mask(vk::AccessFlags2::MEMORY_WRITE)
            .dst_stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
            .dst_access_mask(vk::AccessFlags2::MEMORY_READ | vk::AccessFlags2::MEMORY_WRITE)];
        let dependency = vk::DependencyInfo::default().memory_barriers(&barrier);
        // SAFETY: recording state.
        unsafe { self.device().cmd_pipeline_barrier2(self.raw, &dependency) };
    }

    /// Moves images (all layers) from one state to another, waiting for prior use, in
    /// one batched barrier.
    pub fn transition(&mut self, images: &[&Image], from: ImageState, to: ImageState) {
        for image in images {
            self.hold(image.held());
        }
        let barriers: Vec<_> = images
            .iter()
            .map(|image| {
                let format = image.format();
                let (src_stage, src_access) = from.stage_access(format);
                let (dst_stage, dst_access) = to.stage_access(format);
                vk::ImageMemoryBarrier2::default()
                    .src_stage_mask(src_stage)
                    .src_access_mask(src_access)
                    .dst_stage_mask(dst_stage)
                    .dst_access_mask(dst_access)
                    .old_layout(from.layout(format))
                    .new_layout(to.layout(format))
                    .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                    .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
                    .image(image.raw)
                    .subresource_range(
                        vk::ImageSubresourceRange::default()
                            .aspect_mask(format.aspect())
                            .level_count(1)
                            .layer_count(image.layers()),
                    )
            })
            .collect();
        let dependency = vk::DependencyInfo::default().image_memory_barriers(&barriers);
        // SAFETY: recording state; the images are held by this recorder.
        unsafe { self.device().cmd_pipeline_barrier2(self.raw, &dependency) };
    }

    /// Begins a dynamic-rendering pass over the full extent of the first attachment,
    /// with viewport and scissor set to it. Images must be in [`ImageState::Attachment`].
    pub fn begin_rendering(&mut self, target: &RenderTarget) -> Result<()> {
        let first = target
            .colors
            .first()
            .map(|c| c.0)
            .or(target.depth.map(|d| d.0))
            .ok_or_else(|| Error::InvalidInput("a render pass needs an attachment".into()))?;
        let (width, height) = (first.width(), first.height());
        for image in target
            .colors
            .iter()
            .map(|c| c.0)
            .chain(target.depth.map(|d| d.0))
        {
            self.hold(image.held());
        }
        let colors: Vec<_> = target
            .colors
            .iter()
            .map(|&(image, layer, clear)| {
                vk::RenderingAttachmentInfo::default()
                    .image_view(image.layer_views[layer as usize])
                    .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
                    .load_op(vk::AttachmentLoadOp::CLEAR)
                    .store_op(vk::AttachmentStoreOp::STORE)
                    .clear_value(vk::ClearValue {
                        color: vk::ClearColorValue { float32: clear },
                    })
            })
            .collect();
        let depth = target.depth.map(|(image, layer, clear)| {
            vk::RenderingAttachmentInfo::default()
                .image_view(image.layer_views[layer as usize])
                .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
                .load_op(vk::AttachmentLoadOp::CLEAR)
                .store_op(vk::AttachmentStoreOp::STORE)
                .clear_value(vk::ClearValue {
                    depth_stencil: vk::ClearDepthStencilValue {
                        depth: clear,
                        stencil: 0,
                    },
                })
        });
        let area = vk::Rect2D::default().extent(vk::Extent2D { width, height });
        let mut info = vk::RenderingInfo::default()
            .render_area(area)
            .layer_count(1)
            .color_attachments(&colors);
        if let Some(depth) = depth.as_ref() {
            info = info.depth_attachment(depth);
        }
        let viewport = vk::Viewport::default()
            .width(width as f32)
            .height(height as f32)
            .min_depth(0.0)
            .max_depth(1.0);
        // SAFETY: recording state; views belong to live images.
        unsafe {
            self.device().cmd_begin_rendering(self.raw, &info);
            self.device().cmd_set_viewport(self.raw, 0, &[viewport]);
            self.device().cmd_set_scissor(self.raw, 0, &[area]);
        }
        Ok(())
    }

    /// Ends the pass begun by [`Recorder::begin_rendering`].
    pub fn end_rendering(&mut self) {
        // SAFETY: inside a rendering pass begun by `begin_rendering`.
        unsafe { self.device().cmd_end_rendering(self.raw) };
    }

    /// Binds a graphics pipeline for the draws that follow.
    pub fn bind_graphics(&mut self, pipeline: &GraphicsPipeline) {
        self.hold(pipeline.common.held());
        // SAFETY: recording state; the pipeline is held by this recorder.
        unsafe {
            self.device().cmd_bind_pipeline(
                self.raw,
                vk::PipelineBindPoint::GRAPHICS,
                pipeline.common.pipeline,
            )
        };
    }

    /// Binds a compute pipeline for the dispatches that follow.
    pub fn bind_compute(&mut self, pipeline: &ComputePipeline) {
        self.hold(pipeline.common.held());
        // SAFETY: as above.
        unsafe {
            self.device().cmd_bind_pipeline(
                self.raw,
                vk::PipelineBindPoint::COMPUTE,
                pipeline.common.pipeline,
            )
        };
    }

    /// Pushes the graphics pipeline's bindings (in binding order).
    pub fn push_graphics_bindings(&mut self, pipeline: &GraphicsPipeline, bindings: &[Binding]) {
        self.push_bindings(&pipeline.common, vk::PipelineBindPoint::GRAPHICS, bindings);
    }

    /// Pushes the compute pipeline's bindings (in binding order).
    pub fn push_compute_bindings(&mut self, pipeline: &ComputePipeline, bindings: &[Binding]) {
        self.push_bindings(&pipeline.common, vk::PipelineBindPoint::COMPUTE, bindings);
    }

    fn push_bindings(
        &mut self,
        pipeline: &PipelineCommon,
        bind_point: vk::PipelineBindPoint,
        bindings: &[Binding],
    ) {
        // `bindings` is indexed by binding number; the pipeline takes those its shaders
        // declare (build.rs reflects them), each of the kind they declare.
        let taken: Vec<(u32, &Binding)> = pipeline
            .bindings
            .iter()
            .map(|&(number, kind)| {
                let binding = bindings.get(number as usize).unwrap_or_else(|| {
                    panic!(
                        "no resource for binding {number} ({} given)",
                        bindings.len()
                    )
                });
                let matches = matches!(
                    (binding, kind),
                    (Binding::Buffer { .. }, BindingKind::StorageBuffer)
                        | (Binding::Image(_), BindingKind::StorageImage)
                );
                assert!(matches, "binding {number} takes a {kind:?}");
                (number, binding)
            })
            .collect();
        let max = self.ctx.info().max_storage_buffer_range as u64;
        for (_, binding) in &taken {
            if let Binding::Buffer { buffer, range, .. } = binding {
                if *range > max {
                    self.refused.get_or_insert(Error::Limit(format!(
                        "buffer '{}' is bound with {range} bytes ({:.1} MiB), more than the \
                         device's maxStorageBufferRange of {max} bytes ({:.1} MiB); use a \
                         smaller image, fewer views or a smaller mesh",
                        buffer.name(),
                        *range as f64 / 1048576.0,
                        max as f64 / 1048576.0
                    )));
                }
            }
        }
        if self.refused.is_some() {
            return;
        }
        for (_, binding) in &taken {
            self.hold(match binding {
                Binding::Buffer { buffer, .. } => buffer.held(),
                Binding::Image(image) => image.held(),
            });
        }
        let buffer_infos: Vec<[vk::DescriptorBufferInfo; 1]> = taken
            .iter()
            .map(|(_, b)| match b {
                Binding::Buffer {
                    buffer,
                    offset,
                    range,
                } => [vk::DescriptorBufferInfo::default()
                    .buffer(buffer.raw)
                    .offset(*offset)
                    .range(*range)],
                Binding::Image(_) => [vk::DescriptorBufferInfo::default()],
            })
            .collect();
        let image_infos: Vec<[vk::DescriptorImageInfo; 1]> = taken
            .iter()
            .map(|(_, b)| match b {
                Binding::Image(image) => [vk::DescriptorImageInfo::default()
                    .image_view(image.array_view)
                    .image_layout(vk::ImageLayout::GENERAL)],
                Binding::Buffer { .. } => [vk::DescriptorImageInfo::default()],
            })
            .collect();
        let writes: Vec<_> = taken
            .iter()
            .enumerate()
            .map(|(i, (number, b))| {
                let write = vk::WriteDescriptorSet::default().dst_binding(*number);
                match b {
                    Binding::Buffer { .. } => write
                        .descriptor_type(vk::DescriptorType::STORAGE_BUFFER)
                        .buffer_info(&buffer_infos[i]),
                    Binding::Image(_) => write
                        .descriptor_type(vk::DescriptorType::STORAGE_IMAGE)
                        .image_info(&image_infos[i]),
                }
            })
            .collect();
        // SAFETY: recording state; layout matches the pipeline; the resources are held by
        // this recorder.
        unsafe {
            self.ctx.shared.push_descriptor.cmd_push_descriptor_set(
                self.raw,
                bind_point,
                pipeline.layout,
                0,
                &writes,
            )
        };
    }

    /// Sets the graphics pipeline's push constants.
    pub fn graphics_constants<T: bytemuck::Pod>(&mut self, pipeline: &GraphicsPipeline, value: &T) {
        self.push_constants(&pipeline.common, bytemuck::bytes_of(value));
    }

    /// Sets the compute pipeline's push constants.
    pub fn compute_constants<T: bytemuck::Pod>(&mut self, pipeline: &ComputePipeline, value: &T) {
        self.push_constants(&pipeline.common, bytemuck::bytes_of(value));
    }

    fn push_constants(&mut self, pipeline: &PipelineCommon, bytes: &[u8]) {
        assert_eq!(
            bytes.len() as u32,
            pipeline.push_constant_bytes,
            "push constants must match the pipeline's declared size"
        );
        if bytes.is_empty() {
            return; // a pipeline without push constants
        }
        // SAFETY: recording state; size matches the layout's range.
        unsafe {
            self.device()
                .cmd_push_constants(self.raw, pipeline.layout, pipeline.stages, 0, bytes)
        };
    }

    /// Non-indexed draw of `vertex_count` vertices (vertex pulling).
    pub fn draw(&mut self, vertex_count: u32) {
        if self.refused.is_some() {
            return;
        }
        // SAFETY: inside a rendering pass with a bound graphics pipeline.
        unsafe { self.device().cmd_draw(self.raw, vertex_count, 1, 0, 0) };
    }

    /// Indexed draw of `index_count` 32-bit indices from `indices`, starting at index
    /// `first_index`; `gl_PrimitiveID` counts from 0 in each draw. The index buffer is
    /// bound at the first index (lavapipe draws nothing for a large `firstIndex`).
    pub fn draw_indexed(&mut self, indices: &Buffer, first_index: u32, index_count: u32) {
        self.hold(indices.held());
        // SAFETY: as above; the index buffer was created with index usage.
        unsafe {
            self.device().cmd_bind_index_buffer(
                self.raw,
                indices.raw,
                first_index as u64 * 4,
                vk::IndexType::UINT32,
            );
            self.device()
                .cmd_draw_indexed(self.raw, index_count, 1, 0, 0, 0);
        }
    }

    /// Dispatches with workgroup counts (3 x u32) that an earlier pass wrote into `args`
    /// at byte `offset` (a multiple of 4).
    pub fn dispatch_indirect(&mut self, args: &Buffer, offset: u64) {
        if self.refused.is_some() {
            return;
        }
        self.hold(args.held());
        // SAFETY: a compute pipeline is bound; `args` has indirect usage (device buffers).
        unsafe {
            self.device()
                .cmd_dispatch_indirect(self.raw, args.raw, offset)
        };
    }

    /// Dispatches `x` x `y` x `z` workgroups; a count above the device's
    /// `maxComputeWorkGroupCount` is not recorded and fails [`Recorder::finish`].
    pub fn dispatch(&mut self, x: u32, y: u32, z: u32) {
        if self.refused.is_some() {
            return;
        }
        let max = self.ctx.info().max_compute_workgroup_count;
        if x > max[0] || y > max[1] || z > max[2] {
            self.refused.get_or_insert(Error::Limit(format!(
                "a dispatch of {x} x {y} x {z} workgroups exceeds the device's \
                 maxComputeWorkGroupCount of {} x {} x {}",
                max[0], max[1], max[2]
            )));
            return;
        }
        // SAFETY: a compute pipeline is bound; the counts are within the device's limits.
        unsafe { self.device().cmd_dispatch(self.raw, x, y, z) };
    }

    /// One compute pass: binds `pipeline`, pushes its bindings (in binding order) and its
    /// push constants (`&()` for none), and dispatches `groups`.
    pub fn run_compute<T: bytemuck::Pod>(
        &mut self,
        pipeline: &ComputePipeline,
        bindings: &[Binding],
        constants: &T,
        groups: Groups,
    ) {
        self.bind_compute(pipeline);
        self.push_compute_bindings(pipeline, bindings);
        self.compute_constants(pipeline, constants);
        match groups {
            Groups::Count(x, y, z) => self.dispatch(x, y, z),
            Groups::Indirect(args, offset) => self.dispatch_indirect(args, offset),
        }
    }

    /// Copies `size` bytes from `src` at byte `src_offset` into `dst` at byte `dst_offset`;
    /// the caller keeps both ranges inside their buffers.
    pub fn copy_buffer(
        &mut self,
        src: &Buffer,
        src_offset: u64,
        dst: &Buffer,
        dst_offset: u64,
        size: u64,
    ) {
        self.hold(src.held());
        self.hold(dst.held());
        let region = [vk::BufferCopy::default()
            .src_offset(src_offset)
            .dst_offset(dst_offset)
            .size(size)];
        // SAFETY: recording state; ranges checked by callers.
        unsafe {
            self.device()
                .cmd_copy_buffer(self.raw, src.raw, dst.raw, &region)
        };
    }

    /// Fills `size` bytes of a buffer from `offset` (both multiples of 4) with a repeated
    /// 32-bit word.
    pub fn fill_buffer_range(&mut self, buffer: &Buffer, offset: u64, size: u64, word: u32) {
        debug_assert!(
            offset.is_multiple_of(4) && size.is_multiple_of(4) && offset + size <= buffer.size()
        );
        self.hold(buffer.held());
        // SAFETY: recording state; the range lies inside the buffer (checked above in debug
        // builds, by the callers' fixed layouts otherwise).
        unsafe {
            self.device()
                .cmd_fill_buffer(self.raw, buffer.raw, offset, size, word)
        };
    }

    /// Fills a whole buffer with a repeated 32-bit word.
    pub fn fill_buffer(&mut self, buffer: &Buffer, word: u32) {
        self.hold(buffer.held());
        // SAFETY: recording state; size is a multiple of 4 (see `Buffer::new`).
        unsafe {
            self.device()
                .cmd_fill_buffer(self.raw, buffer.raw, 0, vk::WHOLE_SIZE, word)
        };
    }

    /// Copies all layers of `image` (in [`ImageState::TransferSrc`]) into `buffer`,
    /// packed tightly as (layer, row, column).
    pub fn copy_image_to_buffer(&mut self, image: &Image, buffer: &Buffer) -> Result<()> {
        if buffer.size() < image.byte_size() {
            return Err(Error::InvalidInput(format!(
                "buffer '{}' of {} bytes cannot hold an image of {} bytes",
                buffer.name(),
                buffer.size(),
                image.byte_size()
            )));
        }
        self.hold(image.held());
        self.hold(buffer.held());
        let region = [vk::BufferImageCopy::default()
            .image_subresource(
                vk::ImageSubresourceLayers::default()
                    .aspect_mask(image.format().aspect())
                    .layer_count(image.layers()),
            )
            .image_extent(vk::Extent3D {
                width: image.width(),
                height: image.height(),
                depth: 1,
            })];
        // SAFETY: recording state; sizes checked above.
        unsafe {
            self.device().cmd_copy_image_to_buffer(
                self.raw,
                image.raw,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                buffer.raw,
                &region,
            )
        };
        Ok(())
    }

    /// Resets all slots of `timestamps` (before writing them in this recording).
    pub fn reset_timestamps(&mut self, timestamps: &Timestamps) {
        self.hold(timestamps.held());
        // SAFETY: recording state, outside a render pass.
        unsafe {
            self.device()
                .cmd_reset_query_pool(self.raw, timestamps.pool, 0, timestamps.count())
        };
    }

    /// Writes slot `index` once all earlier commands have finished.
    pub fn timestamp(&mut self, timestamps: &Timestamps, index: u32) {
        self.hold(timestamps.held());
        // SAFETY: recording state; index < count is checked by the validation layer.
        unsafe {
            self.device().cmd_write_timestamp2(
                self.raw,
                vk::PipelineStageFlags2::ALL_COMMANDS,
                timestamps.pool,
                index,
            )
        };
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        // A recorder dropped without `finish` was never submitted.
        if self.raw != vk::CommandBuffer::null() {
            self.ctx.free_command_buffer(self.raw);
        }
    }
}
