//! The GPU layer: the only code in vkdr that calls `ash`. It owns the Vulkan context
//! (instance, device, queue, allocator), buffers, images, pipelines, command recording
//! with barriers, and GPU timestamps. Everything above speaks in these types.
//!
//! # Lifetime model
//!
//! * A [`Context`] is a cheap handle to one shared device (`Arc`). Every resource
//!   ([`Buffer`], [`Image`], pipelines, [`Timestamps`]) holds such a handle and frees
//!   its Vulkan objects and memory in `Drop`; the device itself is destroyed when the
//!   last handle goes, after `vkDeviceWaitIdle`, in reverse order of creation.
//! * Commands are recorded into a [`Recorder`], which takes a share in every resource a
//!   command uses (its Vulkan objects and memory are reference counted), and the
//!   [`Recording`] it finishes into keeps those shares: a resource dropped by its owner
//!   lives on until the last recording that uses it is gone, so a recording can always be
//!   replayed safely. [`Context::submit_and_wait`] and [`Context::replay`] block (with a
//!   bounded wait) until the device is done.
//! * Nothing is destroyed while the device may still use it: the only way to run work is
//!   through those blocking calls, and `Drop` of the context waits for idle.
//!
//! Descriptors are push descriptors (`VK_KHR_push_descriptor`): a pipeline declares its
//! bindings for set 0 and a recording pushes the resources, so no pools or sets exist.

mod buffer;
mod command;
mod context;
mod image;
mod pipeline;
mod timestamps;

pub use buffer::{Buffer, BufferKind};
pub use command::{Groups, Recorder, Recording, RenderTarget};
pub use context::{Context, ContextOptions, DeviceInfo};
pub use image::{Format, Image, ImageState};
pub use pipeline::{
    Binding, BindingKind, ComputePipeline, GraphicsPipeline, GraphicsPipelineDesc, Shader,
};
pub use timestamps::Timestamps;

use ash::vk;

use crate::error::Error;

/// A share in a resource's Vulkan objects and memory, held by the recordings that use it.
pub(crate) type Held = std::sync::Arc<dyn std::any::Any + Send + Sync>;

/// Wraps a Vulkan error code with the call that returned it.
pub(crate) fn vk_err(call: &'static str) -> impl FnOnce(vk::Result) -> Error {
    move |result| Error::Vulkan {
        call,
        result: format!("{result:?}"),
    }
}

/// Reads a SPIR-V blob (as embedded with `include_bytes!`) into properly aligned words.
pub fn spirv(bytes: &[u8]) -> crate::Result<Vec<u32>> {
    ash::util::read_spv(&mut std::io::Cursor::new(bytes))
        .map_err(|e| Error::InvalidInput(format!("bad SPIR-V: {e}")))
}

/// Loop iterations one shader invocation may run, all its loops together. llvmpipe
/// (lavapipe) ends an invocation's loops silently past this (Mesa's
/// `LP_MAX_TGSI_LOOP_ITERATIONS`, one counter shared by every loop); other drivers have
/// no such limit. A shader whose loops grow with its input is dispatched once per span of
/// the input ([`spans`]), each dispatch carrying on from the last one's sums, so that no
/// invocation comes near it on any driver (and every driver adds in the same order).
pub const LOOP_LIMIT: u32 = 65535;

/// The spans [first, end) of `count` items, `span` at a time (at least one span, empty
/// when `count` is 0).
pub fn spans(count: u32, span: u32) -> impl Iterator<Item = (u32, u32)> {
    let span = span.max(1);
    (0..count.div_ceil(span).max(1)).map(move |k| (k * span, count.min(k * span + span)))
}
