//! Compute and graphics pipelines from SPIR-V, with push-descriptor set layouts and a
//! push-constant range.

use std::sync::Arc;

use ash::vk;

use super::{vk_err, Buffer, Context, DeviceInfo, Format, Held, Image};
use crate::error::{Error, Result};

/// A shader as `build.rs` compiled and reflected it (`crate::shaders` has one per file in
/// `glsl/`): what a pipeline layout needs comes from the module itself.
#[derive(Clone, Copy, Debug)]
pub struct Shader {
    /// The file in `glsl/`.
    pub name: &'static str,
    /// SPIR-V bytes (entry point `main`).
    pub spirv: &'static [u8],
    /// The set-0 bindings the module declares: binding number and kind, ascending.
    pub bindings: &'static [(u32, BindingKind)],
    /// Size of the module's push-constant block, bytes (0: none).
    pub push_constant_bytes: u32,
}

impl Shader {
    /// Whether `T` is exactly the size of the module's push-constant block: assert it at
    /// compile time beside each push-constant struct,
    /// `const _: () = assert!(shaders::CLASSIFY_COMP.takes::<PassConstants>());`.
    pub const fn takes<T>(&self) -> bool {
        std::mem::size_of::<T>() == self.push_constant_bytes as usize
    }
}

/// The kind of resource a pipeline binding (set 0) takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BindingKind {
    /// A storage buffer, pushed as [`Binding::Buffer`].
    StorageBuffer,
    /// A storage image, pushed as [`Binding::Image`].
    StorageImage,
}

/// A resource pushed to a binding at record time.
pub enum Binding<'a> {
    /// A byte range of a buffer (offset aligned to the device's
    /// `minStorageBufferOffsetAlignment`).
    Buffer {
        /// The buffer.
        buffer: &'a Buffer,
        /// Start of the range, bytes.
        offset: u64,
        /// Length of the range, bytes (at most the device's `maxStorageBufferRange`, else
        /// [`super::Recorder::finish`] fails with [`Error::Limit`]).
        range: u64,
    },
    /// All layers of an image, in the storage state.
    Image(&'a Image),
}

impl<'a> Binding<'a> {
    /// The whole buffer.
    pub fn buffer(buffer: &'a Buffer) -> Self {
        Binding::Buffer {
            buffer,
            offset: 0,
            range: buffer.size(),
        }
    }
}

/// Layout objects shared by both pipeline kinds.
pub(crate) struct PipelineCommon {
    ctx: Context,
    pub(crate) pipeline: vk::Pipeline,
    pub(crate) layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    /// Binding numbers and kinds of set 0, ascending.
    pub(crate) bindings: Vec<(u32, BindingKind)>,
    pub(crate) push_constant_bytes: u32,
    pub(crate) stages: vk::ShaderStageFlags,
}

impl PipelineCommon {
    fn layouts(
        ctx: &Context,
        bindings: &[(u32, BindingKind)],
        push_constant_bytes: u32,
        stages: vk::ShaderStageFlags,
    ) -> Result<(vk::DescriptorSetLayout, vk::PipelineLayout)> {
        check_layout_fits(ctx.info(), bindings, push_constant_bytes)?;
        let device = ctx.device();
        let raw_bindings: Vec<_> = bindings
            .iter()
            .map(|&(binding, kind)| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(binding)
                    .descriptor_type(match kind {
                        BindingKind::StorageBuffer => vk::DescriptorType::STORAGE_BUFFER,
                        BindingKind::StorageImage => vk::DescriptorType::STORAGE_IMAGE,
                    })
                    .descriptor_count(1)
                    .stage_flags(stages)
            })
            .collect();
        let set_info = vk::DescriptorSetLayoutCreateInfo::default()
            .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
            .bindings(&raw_bindings);
        // SAFETY: valid device and create info.
        let set_layout = unsafe { device.create_descriptor_set_layout(&set_info, None) }
            .map_err(vk_err("vkCreateDescriptorSetLayout"))?;
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(stages)
            .offset(0)
            .size(push_constant_bytes)];
        let set_layouts = [set_layout];
        let mut info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if push_constant_bytes > 0 {
            info = info.push_constant_ranges(&ranges);
        }
        // SAFETY: as above.
        let layout = unsafe { device.create_pipeline_layout(&info, None) }
            .map_err(vk_err("vkCreatePipelineLayout"))?;
        Ok((set_layout, layout))
    }
}

/// An error naming the device limit a pipeline's bindings or push constants pass.
fn check_layout_fits(
    info: &DeviceInfo,
    bindings: &[(u32, BindingKind)],
    push_bytes: u32,
) -> Result<()> {
    let buffers = bindings
        .iter()
        .filter(|b| matches!(b.1, BindingKind::StorageBuffer))
        .count() as u32;
    let checks = [
        (
            bindings.len() as u32,
            info.max_push_descriptors,
            "bindings",
            "maxPushDescriptors",
        ),
        (
            buffers,
            info.max_per_stage_storage_buffers,
            "storage buffers",
            "maxPerStageDescriptorStorageBuffers",
        ),
        (
            push_bytes,
            info.max_push_constants_size,
            "bytes of push constants",
            "maxPushConstantsSize",
        ),
    ];
    for (need, limit, what, name) in checks {
        if need > limit {
            return Err(Error::Limit(format!(
                "a pipeline needs {need} {what}, more than the device's {name} of {limit}"
            )));
        }
    }
    Ok(())
}

impl PipelineCommon {
    /// A share in the pipeline's Vulkan objects, for a recording that uses it.
    pub(crate) fn held(self: &Arc<Self>) -> Held {
        self.clone()
    }
}

impl Drop for PipelineCommon {
    fn drop(&mut self) {
        let device = self.ctx.device();
        // SAFETY: per the lifetime model no submitted work uses the pipeline any more.
        unsafe {
            device.destroy_pipeline(self.pipeline, None);
            device.destroy_pipeline_layout(self.layout, None);
            device.destroy_descriptor_set_layout(self.set_layout, None);
        }
    }
}

fn shader_module(ctx: &Context, spirv: &[u32]) -> Result<vk::ShaderModule> {
    let info = vk::ShaderModuleCreateInfo::default().code(spirv);
    // SAFETY: SPIR-V produced by build.rs through shaderc.
    unsafe { ctx.device().create_shader_module(&info, None) }
        .map_err(vk_err("vkCreateShaderModule"))
}

/// A compute pipeline.
pub struct ComputePipeline {
    pub(crate) common: Arc<PipelineCommon>,
}

impl ComputePipeline {
    /// A compute pipeline from a reflected shader: its set-0 bindings and push-constant
    /// size are the module's own. Fails with [`Error::Limit`] when the layout exceeds the
    /// device's limits.
    pub fn new(ctx: &Context, shader: &Shader) -> Result<Self> {
        Self::specialized(ctx, shader, &[])
    }

    /// The same with the shader's specialization constants `constant_id = i` set to
    /// `constants[i]` (32-bit each, as `uint`): the driver compiles the pipeline for those
    /// values, so a branch on one costs nothing at run time (a CPU driver otherwise runs
    /// both sides of every branch, masked).
    pub fn specialized(ctx: &Context, shader: &Shader, constants: &[u32]) -> Result<Self> {
        let stages = vk::ShaderStageFlags::COMPUTE;
        let (bindings, push_constant_bytes) = (shader.bindings, shader.push_constant_bytes);
        let (set_layout, layout) =
            PipelineCommon::layouts(ctx, bindings, push_constant_bytes, stages)?;
        let spirv = super::spirv(shader.spirv)?;
        let module = shader_module(ctx, &spirv)?;
        let entries: Vec<vk::SpecializationMapEntry> = (0..constants.len() as u32)
            .map(|i| vk::SpecializationMapEntry {
                constant_id: i,
                offset: 4 * i,
                size: 4,
            })
            .collect();
        let specialization = vk::SpecializationInfo::default()
            .map_entries(&entries)
            .data(bytemuck::cast_slice(constants));
        let mut stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(stages)
            .module(module)
            .name(c"main");
        if !constants.is_empty() {
            stage = stage.specialization_info(&specialization);
        }
        let info = vk::ComputePipelineCreateInfo::default()
            .stage(stage)
            .layout(layout);
        // SAFETY: module and layout are valid; the module is destroyed after creation.
        let created = unsafe {
            let created =
                ctx.device()
                    .create_compute_pipelines(vk::PipelineCache::null(), &[info], None);
            ctx.device().destroy_shader_module(module, None);
            created
        };
        let pipeline = created.map_err(|(_, e)| vk_err("vkCreateComputePipelines")(e))?[0];
        ctx.name_object(pipeline, shader.name);
        Ok(Self {
            common: Arc::new(PipelineCommon {
                ctx: ctx.clone(),
                pipeline,
                layout,
                set_layout,
                bindings: bindings.to_vec(),
                push_constant_bytes,
                stages,
            }),
        })
    }
}

/// What a graphics pipeline draws: triangle lists with no vertex input (vertices are
/// pulled from storage buffers), no culling, dynamic viewport and scissor, and, with a
/// depth attachment, a reverse-Z depth test (greater wins, cleared to 0).
pub struct GraphicsPipelineDesc<'a> {
    /// Name for validation messages and debug tools.
    pub name: &'a str,
    /// The vertex shader; the pipeline's bindings and push constants are the union of
    /// both stages' (both stages see them).
    pub vertex: &'a Shader,
    /// The fragment shader.
    pub fragment: &'a Shader,
    /// Formats of the colour attachments, in attachment order.
    pub color_formats: &'a [Format],
    /// Format of the depth attachment; `None` turns the depth test off.
    pub depth_format: Option<Format>,
}

/// A graphics pipeline for dynamic rendering.
pub struct GraphicsPipeline {
    pub(crate) common: Arc<PipelineCommon>,
}

impl GraphicsPipeline {
    /// Builds the pipeline `desc` describes. Fails with [`Error::Limit`] when the layout exceeds
    /// the device's limits.
    pub fn new(ctx: &Context, desc: &GraphicsPipelineDesc) -> Result<Self> {
        let stages = vk::ShaderStageFlags::VERTEX | vk::ShaderStageFlags::FRAGMENT;
        let mut bindings = desc.vertex.bindings.to_vec();
        for &(binding, kind) in desc.fragment.bindings {
            match bindings.iter().find(|b| b.0 == binding) {
                Some(&(_, other)) if other != kind => {
                    return Err(Error::InvalidInput(format!(
                        "{}: binding {binding} is a {other:?} in {} and a {kind:?} in {}",
                        desc.name, desc.vertex.name, desc.fragment.name
                    )))
                }
                Some(_) => {}
                None => bindings.push((binding, kind)),
            }
        }
        bindings.sort_by_key(|b| b.0);
        let push_constant_bytes = desc
            .vertex
            .push_constant_bytes
            .max(desc.fragment.push_constant_bytes);
        let (set_layout, layout) =
            PipelineCommon::layouts(ctx, &bindings, push_constant_bytes, stages)?;
        let vertex = shader_module(ctx, &super::spirv(desc.vertex.spirv)?)?;
        let fragment = shader_module(ctx, &super::spirv(desc.fragment.spirv)?)?;
        let shader_stages = [
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::VERTEX)
                .module(vertex)
                .name(c"main"),
            vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::FRAGMENT)
                .module(fragment)
                .name(c"main"),
        ];
        let vertex_input = vk::PipelineVertexInputStateCreateInfo::default();
        let assembly = vk::PipelineInputAssemblyStateCreateInfo::default()
            .topology(vk::PrimitiveTopology::TRIANGLE_LIST);
        let viewport = vk::PipelineViewportStateCreateInfo::default()
            .viewport_count(1)
            .scissor_count(1);
        let raster = vk::PipelineRasterizationStateCreateInfo::default()
            .polygon_mode(vk::PolygonMode::FILL)
            .cull_mode(vk::CullModeFlags::NONE)
            .front_face(vk::FrontFace::COUNTER_CLOCKWISE)
            .line_width(1.0);
        let multisample = vk::PipelineMultisampleStateCreateInfo::default()
            .rasterization_samples(vk::SampleCountFlags::TYPE_1);
        let has_depth = desc.depth_format.is_some();
        let depth = vk::PipelineDepthStencilStateCreateInfo::default()
            .depth_test_enable(has_depth)
            .depth_write_enable(has_depth)
            .depth_compare_op(vk::CompareOp::GREATER);
        let blend_attachments: Vec<_> = desc
            .color_formats
            .iter()
            .map(|_| {
                vk::PipelineColorBlendAttachmentState::default()
                    .color_write_mask(vk::ColorComponentFlags::RGBA)
            })
            .collect();
        let blend =
            vk::PipelineColorBlendStateCreateInfo::default().attachments(&blend_attachments);
        let dynamic_states = [vk::DynamicState::VIEWPORT, vk::DynamicState::SCISSOR];
        let dynamic = vk::PipelineDynamicStateCreateInfo::default().dynamic_states(&dynamic_states);
        let color_formats: Vec<vk::Format> = desc.color_formats.iter().map(|f| f.raw()).collect();
        let mut rendering = vk::PipelineRenderingCreateInfo::default()
            .color_attachment_formats(&color_formats)
            .depth_attachment_format(desc.depth_format.map_or(vk::Format::UNDEFINED, |f| f.raw()));
        let info = vk::GraphicsPipelineCreateInfo::default()
            .stages(&shader_stages)
            .vertex_input_state(&vertex_input)
            .input_assembly_state(&assembly)
            .viewport_state(&viewport)
            .rasterization_state(&raster)
            .multisample_state(&multisample)
            .depth_stencil_state(&depth)
            .color_blend_state(&blend)
            .dynamic_state(&dynamic)
            .layout(layout)
            .push_next(&mut rendering);
        // SAFETY: every pointer in `info` outlives the call; modules destroyed after.
        let created = unsafe {
            let created =
                ctx.device()
                    .create_graphics_pipelines(vk::PipelineCache::null(), &[info], None);
            ctx.device().destroy_shader_module(vertex, None);
            ctx.device().destroy_shader_module(fragment, None);
            created
        };
        let pipeline = created.map_err(|(_, e)| vk_err("vkCreateGraphicsPipelines")(e))?[0];
        ctx.name_object(pipeline, desc.name);
        Ok(Self {
            common: Arc::new(PipelineCommon {
                ctx: ctx.clone(),
                pipeline,
                layout,
                set_layout,
                bindings,
                push_constant_bytes,
                stages,
            }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_past_the_device_limits_are_refused_by_name() {
        let ctx = Context::new().expect("a Vulkan device");
        let mut info = ctx.info().clone();
        let buffers: Vec<(u32, BindingKind)> =
            (0..6).map(|b| (b, BindingKind::StorageBuffer)).collect();
        assert!(check_layout_fits(&info, &buffers, 16).is_ok());
        info.max_push_descriptors = 5;
        let message = check_layout_fits(&info, &buffers, 16)
            .unwrap_err()
            .to_string();
        assert!(message.contains("maxPushDescriptors of 5"), "{message}");
        info.max_push_descriptors = 32;
        info.max_per_stage_storage_buffers = 4;
        let message = check_layout_fits(&info, &buffers, 16)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("maxPerStageDescriptorStorageBuffers"),
            "{message}"
        );
        info.max_per_stage_storage_buffers = 32;
        let message = check_layout_fits(&info, &buffers, 4096)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("4096 bytes of push constants"),
            "{message}"
        );
    }
}
