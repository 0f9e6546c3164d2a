//! 2D array images (one layer per view) used as render attachments, storage images and
//! copy sources.

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use std::sync::Arc;

use super::{vk_err, Context, Held};
use crate::error::{Error, Result};

/// The pixel formats the engine uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// One 32-bit unsigned integer channel (triangle ids).
    R32Uint,
    /// One 32-bit float channel.
    R32Float,
    /// Two 32-bit float channels (barycentrics).
    Rg32Float,
    /// Four 8-bit normalized channels (colour images).
    Rgba8Unorm,
    /// 32-bit float depth (depth-test attachments).
    D32Float,
}

impl Format {
    pub(crate) fn raw(self) -> vk::Format {
        match self {
            Format::R32Uint => vk::Format::R32_UINT,
            Format::R32Float => vk::Format::R32_SFLOAT,
            Format::Rg32Float => vk::Format::R32G32_SFLOAT,
            Format::Rgba8Unorm => vk::Format::R8G8B8A8_UNORM,
            Format::D32Float => vk::Format::D32_SFLOAT,
        }
    }

    /// Bytes per pixel.
    pub fn texel_bytes(self) -> u64 {
        match self {
            Format::Rg32Float => 8,
            _ => 4,
        }
    }

    /// Whether this is a depth format (used as a depth attachment, not a colour one).
    pub fn is_depth(self) -> bool {
        self == Format::D32Float
    }

    pub(crate) fn aspect(self) -> vk::ImageAspectFlags {
        if self.is_depth() {
            vk::ImageAspectFlags::DEPTH
        } else {
            vk::ImageAspectFlags::COLOR
        }
    }
}

/// What an image is being used for; [`super::Recorder::transition`] moves between states.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageState {
    /// Contents undefined (before first use).
    Undefined,
    /// Render target (colour or depth attachment).
    Attachment,
    /// Source of a copy to a buffer.
    TransferSrc,
    /// Read or written by compute shaders as a storage image.
    Storage,
}

impl ImageState {
    pub(crate) fn layout(self, format: Format) -> vk::ImageLayout {
        match self {
            ImageState::Undefined => vk::ImageLayout::UNDEFINED,
            ImageState::Attachment if format.is_depth() => {
                vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL
            }
            ImageState::Attachment => vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
            ImageState::TransferSrc => vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            ImageState::Storage => vk::ImageLayout::GENERAL,
        }
    }

    pub(crate) fn stage_access(
        self,
        format: Format,
    ) -> (vk::PipelineStageFlags2, vk::AccessFlags2) {
        match self {
            ImageState::Undefined => (vk::PipelineStageFlags2::TOP_OF_PIPE, vk::AccessFlags2::NONE),
            ImageState::Attachment if format.is_depth() => (
                vk::PipelineStageFlags2::EARLY_FRAGMENT_TESTS
                    | vk::PipelineStageFlags2::LATE_FRAGMENT_TESTS,
                vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_READ
                    | vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE,
            ),
            ImageState::Attachment => (
                vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
                vk::AccessFlags2::COLOR_ATTACHMENT_READ | vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            ),
            ImageState::TransferSrc => (
                vk::PipelineStageFlags2::ALL_TRANSFER,
                vk::AccessFlags2::TRANSFER_READ,
            ),
            ImageState::Storage => (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_STORAGE_READ | vk::AccessFlags2::SHADER_STORAGE_WRITE,
            ),
        }
    }
}

/// A 2D array image with one view per layer (for rendering) and one over all layers
/// (for compute). Freed in `Drop`.
pub struct Image {
    memory: Arc<ImageMemory>,
    pub(crate) raw: vk::Image,
    pub(crate) layer_views: Vec<vk::ImageView>,
    pub(crate) array_view: vk::ImageView,
    width: u32,
    height: u32,
    layers: u32,
    format: Format,
}

/// What an [`Image`] owns on the device (the image, its views, its memory); shared with
/// the recordings that use it, freed when the last of them and the image are gone.
struct ImageMemory {
    ctx: Context,
    raw: vk::Image,
    views: Vec<vk::ImageView>,
    allocation: Option<Allocation>,
}

impl Drop for ImageMemory {
    fn drop(&mut self) {
        let device = self.ctx.device();
        // SAFETY: the image and every recording that used it are gone, and submissions
        // block until the device is done; the views go before the image.
        unsafe {
            for &v in &self.views {
                device.destroy_image_view(v, None);
            }
            device.destroy_image(self.raw, None);
        }
        if let Some(allocation) = self.allocation.take() {
            let _ = self.ctx.with_allocator(|a| a.free(allocation));
        }
    }
}

impl Image {
    /// A `width` x `height` image with `layers` layers. `storage` adds storage-image use.
    pub fn new(
        ctx: &Context,
        name: &str,
        format: Format,
        width: u32,
        height: u32,
        layers: u32,
        storage: bool,
    ) -> Result<Self> {
        let max = ctx.info().max_image_dimension_2d;
        if width == 0 || height == 0 || layers == 0 {
            return Err(Error::InvalidInput(format!(
                "image '{name}' of {width} x {height} x {layers} is empty"
            )));
        }
        if width > max || height > max {
            return Err(Error::Limit(format!(
                "image '{name}' of {width} x {height} exceeds the device's maximum of {max}"
            )));
        }
        let mut usage = vk::ImageUsageFlags::TRANSFER_SRC | vk::ImageUsageFlags::TRANSFER_DST;
        usage |= if format.is_depth() {
            vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT
        } else {
            vk::ImageUsageFlags::COLOR_ATTACHMENT
        };
        if storage {
            usage |= vk::ImageUsageFlags::STORAGE;
        }
        let device = ctx.device();
        let info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(format.raw())
            .extent(vk::Extent3D {
                width,
                height,
                depth: 1,
            })
            .mip_levels(1)
            .array_layers(layers)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE)
            .initial_layout(vk::ImageLayout::UNDEFINED);
        // SAFETY: valid device and create info.
        let raw = unsafe { device.create_image(&info, None) }.map_err(vk_err("vkCreateImage"))?;
        // SAFETY: `raw` belongs to this device.
        let requirements = unsafe { device.get_image_memory_requirements(raw) };
        let allocation = ctx
            .with_allocator(|a| {
                a.allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location: MemoryLocation::GpuOnly,
                    linear: false,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                })
            })
            .map_err(|e| {
                // SAFETY: unused image without memory.
                unsafe { device.destroy_image(raw, None) };
                Error::Allocation {
                    name: name.into(),
                    reason: e.to_string(),
                }
            })?;
        // SAFETY: allocation fits the image's requirements.
        unsafe { device.bind_image_memory(raw, allocation.memory(), allocation.offset()) }
            .map_err(vk_err("vkBindImageMemory"))?;
        ctx.name_object(raw, name);

        let view = |view_type: vk::ImageViewType, first: u32, count: u32| {
            let info = vk::ImageViewCreateInfo::default()
                .image(raw)
                .view_type(view_type)
                .format(format.raw())
                .subresource_range(
                    vk::ImageSubresourceRange::default()
                        .aspect_mask(format.aspect())
                        .level_count(1)
                        .base_array_layer(first)
                        .layer_count(count),
                );
            // SAFETY: the image outlives its views (destroyed first in Drop).
            unsafe { device.create_image_view(&info, None) }.map_err(vk_err("vkCreateImageView"))
        };
        // Owned from here on: a failed view frees what exists so far.
        let mut memory = ImageMemory {
            ctx: ctx.clone(),
            raw,
            views: Vec::new(),
            allocation: Some(allocation),
        };
        for layer in 0..layers {
            memory
                .views
                .push(view(vk::ImageViewType::TYPE_2D, layer, 1)?);
        }
        let array_view = view(vk::ImageViewType::TYPE_2D_ARRAY, 0, layers)?;
        memory.views.push(array_view);
        Ok(Self {
            raw,
            layer_views: memory.views[..layers as usize].to_vec(),
            array_view,
            memory: Arc::new(memory),
            width,
            height,
            layers,
            format,
        })
    }

    /// A share in the image's Vulkan objects and memory, for a recording that uses it.
    pub(crate) fn held(&self) -> Held {
        self.memory.clone()
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Number of array layers (one per view).
    pub fn layers(&self) -> u32 {
        self.layers
    }

    /// Pixel format.
    pub fn format(&self) -> Format {
        self.format
    }

    /// Bytes of all layers packed tightly (layer, row, column).
    pub fn byte_size(&self) -> u64 {
        self.width as u64 * self.height as u64 * self.layers as u64 * self.format.texel_bytes()
    }
}
