//! Buffers in device memory through gpu-allocator, with upload and readback.

use std::sync::{Arc, Mutex};

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use super::{vk_err, Context, Held, Recorder};
use crate::error::{Error, Result};

/// Where a buffer lives and what it is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BufferKind {
    /// Device memory: storage, index, transfer source and destination.
    Device,
    /// Host-visible memory the device reads (staging uploads).
    Upload,
    /// Host-visible memory the device writes and the host reads back.
    Readback,
}

/// A Vulkan buffer with its memory, freed when the buffer and every [`super::Recording`]
/// that uses it are gone (see the lifetime model in `gpu`).
pub struct Buffer {
    memory: Arc<BufferMemory>,
    pub(crate) raw: vk::Buffer,
    size: u64,
    name: String,
}

/// What a [`Buffer`] owns on the device; shared with the recordings that use it.
struct BufferMemory {
    ctx: Context,
    raw: vk::Buffer,
    allocation: Mutex<Option<Allocation>>,
}

impl Drop for BufferMemory {
    fn drop(&mut self) {
        // SAFETY: the buffer and every recording that used it are gone, and submissions
        // block until the device is done, so no work uses the buffer any more.
        unsafe { self.ctx.device().destroy_buffer(self.raw, None) };
        let allocation = self.allocation.get_mut().map(Option::take);
        if let Ok(Some(allocation)) = allocation {
            let _ = self.ctx.with_allocator(|a| a.free(allocation));
        }
    }
}

impl Buffer {
    /// A buffer of `size` bytes (at least 4: Vulkan has no empty buffers).
    pub fn new(ctx: &Context, name: &str, size: u64, kind: BufferKind) -> Result<Self> {
        let size = size.max(4).next_multiple_of(4);
        let usage = vk::BufferUsageFlags::STORAGE_BUFFER
            | vk::BufferUsageFlags::TRANSFER_SRC
            | vk::BufferUsageFlags::TRANSFER_DST
            | match kind {
                BufferKind::Device => {
                    vk::BufferUsageFlags::INDEX_BUFFER | vk::BufferUsageFlags::INDIRECT_BUFFER
                }
                _ => vk::BufferUsageFlags::empty(),
            };
        let device = ctx.device();
        let info = vk::BufferCreateInfo::default()
            .size(size)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid device and create info.
        let raw = unsafe { device.create_buffer(&info, None) }.map_err(vk_err("vkCreateBuffer"))?;
        // SAFETY: `raw` was just created on this device.
        let requirements = unsafe { device.get_buffer_memory_requirements(raw) };
        let location = match kind {
            BufferKind::Device => MemoryLocation::GpuOnly,
            BufferKind::Upload => MemoryLocation::CpuToGpu,
            BufferKind::Readback => MemoryLocation::GpuToCpu,
        };
        let allocation = ctx.with_allocator(|a| {
            a.allocate(&AllocationCreateDesc {
                name,
                requirements,
                location,
                linear: true,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
        });
        let allocation = match allocation {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: the buffer has no memory bound and was never used.
                unsafe { device.destroy_buffer(raw, None) };
                return Err(Error::Allocation {
                    name: name.into(),
                    reason: format!("{size} bytes: {e}"),
                });
            }
        };
        // SAFETY: memory and offset come from an allocation that fits `requirements`.
        unsafe { device.bind_buffer_memory(raw, allocation.memory(), allocation.offset()) }
            .map_err(vk_err("vkBindBufferMemory"))?;
        ctx.name_object(raw, name);
        Ok(Self {
            memory: Arc::new(BufferMemory {
                ctx: ctx.clone(),
                raw,
                allocation: Mutex::new(Some(allocation)),
            }),
            raw,
            size,
            name: name.into(),
        })
    }

    /// A share in the buffer's memory, for a recording that uses it.
    pub(crate) fn held(&self) -> Held {
        self.memory.clone()
    }

    fn ctx(&self) -> &Context {
        &self.memory.ctx
    }

    /// A device buffer holding `data`.
    pub fn from_slice<T: bytemuck::Pod>(ctx: &Context, name: &str, data: &[T]) -> Result<Self> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let mut buffer = Self::new(ctx, name, bytes.len() as u64, BufferKind::Device)?;
        buffer.write(0, data)?;
        Ok(buffer)
    }

    /// Size in bytes: the requested size rounded up to a multiple of 4, at least 4.
    pub fn size(&self) -> u64 {
        self.size
    }

    /// The name given at creation (for messages and validation output).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// `f` of the mapped bytes when the memory is host-visible and coherent (lavapipe:
    /// always), else None.
    fn with_mapped<R>(&self, f: impl FnOnce(&mut [u8]) -> R) -> Option<R> {
        let mut allocation = self.memory.allocation.lock().ok()?;
        let allocation = allocation.as_mut()?;
        let coherent = allocation
            .memory_properties()
            .contains(vk::MemoryPropertyFlags::HOST_COHERENT);
        allocation.mapped_slice_mut().filter(|_| coherent).map(f)
    }

    /// Writes `data` at byte `offset`, directly when mapped, else through a staging copy.
    /// Blocks until the data is in place; the device must not be using the buffer.
    pub fn write<T: bytemuck::Pod>(&mut self, offset: u64, data: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let end = offset + bytes.len() as u64;
        if end > self.size {
            return Err(Error::InvalidInput(format!(
                "write of {} bytes at {offset} overruns buffer '{}' of {} bytes",
                bytes.len(),
                self.name,
                self.size
            )));
        }
        if bytes.is_empty() {
            return Ok(());
        }
        let range = offset as usize..end as usize;
        if let Some(()) = self.with_mapped(|mapped| mapped[range].copy_from_slice(bytes)) {
            return Ok(());
        }
        let mut staging = Buffer::new(
            self.ctx(),
            "staging upload",
            bytes.len() as u64,
            BufferKind::Upload,
        )?;
        staging.write(0, bytes)?;
        let mut rec = Recorder::new(self.ctx())?;
        rec.copy_buffer(&staging, 0, self, offset, bytes.len() as u64);
        self.ctx().submit_and_wait(rec)
    }

    /// Reads the whole buffer back as `T`s (the device must be done writing it).
    pub fn read<T: bytemuck::Pod>(&self) -> Result<Vec<T>> {
        let count = self.size as usize / std::mem::size_of::<T>();
        self.read_range(0, count)
    }

    /// Reads `count` values of `T` from byte `offset`.
    pub fn read_range<T: bytemuck::Pod>(&self, offset: u64, count: usize) -> Result<Vec<T>> {
        let mut out = vec![T::zeroed(); count];
        self.read_range_into(offset, &mut out)?;
        Ok(out)
    }

    /// Reads `out.len()` values of `T` from byte `offset` into `out`.
    pub fn read_range_into<T: bytemuck::Pod>(&self, offset: u64, out: &mut [T]) -> Result<()> {
        let len = std::mem::size_of_val(out) as u64;
        if offset + len > self.size {
            return Err(Error::InvalidInput(format!(
                "read of {len} bytes at {offset} overruns buffer '{}' of {} bytes",
                self.name, self.size
            )));
        }
        if len == 0 {
            return Ok(());
        }
        let range = offset as usize..(offset + len) as usize;
        let out_bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        if let Some(()) = self.with_mapped(|mapped| out_bytes.copy_from_slice(&mapped[range])) {
            return Ok(());
        }
        let staging = Buffer::new(self.ctx(), "staging readback", len, BufferKind::Readback)?;
        let mut rec = Recorder::new(self.ctx())?;
        rec.copy_buffer(self, offset, &staging, 0, len);
        self.ctx().submit_and_wait(rec)?;
        staging
            .with_mapped(|mapped| out_bytes.copy_from_slice(&mapped[..len as usize]))
            .ok_or_else(|| Error::Allocation {
                name: "staging readback".into(),
                reason: "readback memory is not host-visible and coherent".into(),
            })
    }
}
