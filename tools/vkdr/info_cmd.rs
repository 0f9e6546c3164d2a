//! `vkdr info`: the chosen Vulkan device, its driver, features and limits.

use anyhow::Result;

use vkdr::gpu::Context;

pub fn run() -> Result<()> {
    let devices = Context::list_devices()?;
    println!("Vulkan devices:");
    for (i, name) in devices.iter().enumerate() {
        println!("  {i}: {name}");
    }
    let ctx = Context::new()?;
    let d = ctx.info();
    println!("chosen: {} ({}), index {}", d.name, d.kind, d.index);
    println!(
        "  Vulkan {} / driver {} {}",
        d.api_version, d.driver_name, d.driver_info
    );
    println!("  features:");
    let width = d.features.iter().map(|(n, _)| n.len()).max().unwrap_or(0);
    for (name, has) in &d.features {
        println!(
            "    {name:<width$}  {}",
            if *has { "yes" } else { "MISSING" }
        );
    }
    println!("  limits:");
    println!(
        "    subPixelPrecisionBits           {}",
        d.sub_pixel_precision_bits
    );
    println!(
        "    maxImageDimension2D             {}",
        d.max_image_dimension_2d
    );
    println!(
        "    maxStorageBufferRange           {} MiB",
        d.max_storage_buffer_range >> 20
    );
    println!(
        "    minStorageBufferOffsetAlignment {}",
        d.min_storage_buffer_offset_alignment
    );
    println!(
        "    maxComputeWorkGroupInvocations  {}",
        d.max_compute_workgroup_invocations
    );
    println!(
        "    maxPushConstantsSize            {}",
        d.max_push_constants_size
    );
    println!(
        "    timestampPeriod                 {} ns",
        d.timestamp_period_ns
    );
    println!(
        "  grid-stride passes use at most {} workgroups of 64 ({} device; subgroups of {})",
        d.grid_groups, d.kind, d.subgroup_size
    );
    Ok(())
}
