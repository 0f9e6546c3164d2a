//! Shared test set-up: a validated context, and a check that fails on validation errors.
//! A missing device is a failure, never a skip.

#![allow(dead_code)]

use vkdr::gpu::{Context, ContextOptions};

/// A context with validation layers on. Panics (fails the test) when no device is usable.
pub fn context() -> Context {
    let options = ContextOptions {
        validation: true,
        ..ContextOptions::default()
    };
    Context::with_options(options).unwrap_or_else(|e| {
        panic!("tests need a Vulkan device with validation layers (run tools/setup.sh): {e}")
    })
}

/// Fails the test if the validation layer reported any error.
pub fn assert_no_validation_errors(ctx: &Context) {
    if let Err(e) = ctx.check_validation() {
        panic!("{e}");
    }
}

/// A lathe (`Mesh::lathe`, `Mesh::bottle`) without its top cap, the triangles around its
/// last vertex: open at the top, as a single-sheet scan of a cup.
pub fn open_top(mesh: &vkdr::Mesh) -> vkdr::Mesh {
    let top = mesh.vertex_count() as u32 - 1;
    let triangles = mesh
        .triangles()
        .iter()
        .filter(|t| !t.contains(&top))
        .copied()
        .collect();
    vkdr::Mesh::new(mesh.positions().to_vec(), triangles).unwrap()
}
