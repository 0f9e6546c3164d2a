//! Every shader of the engine as compiled and reflected by `build.rs`: its SPIR-V, its
//! descriptor-set-0 bindings and the size of its push-constant block, taken from the
//! module itself. Pipelines are made from these ([`crate::gpu::ComputePipeline::new`]), so
//! no binding list or push-constant size is written by hand, and each push-constant struct
//! is checked against its shader's block at compile time (`const` assertions beside the
//! structs): a struct of the wrong size does not build.
//!
//! ```compile_fail
//! // loss_finalize.comp's block is (loss, stats_shift): 8 bytes, not 12.
//! const _: () = assert!(vkdr::shaders::LOSS_FINALIZE_COMP.takes::<[u32; 3]>());
//! ```
//!
//! ```
//! const _: () = assert!(vkdr::shaders::LOSS_FINALIZE_COMP.takes::<[u32; 2]>());
//! ```

use crate::gpu::{BindingKind, Shader};

include!(concat!(env!("OUT_DIR"), "/shaders.rs"));

#[cfg(test)]
mod tests {
    use super::*;

    /// What build.rs reads from the SPIR-V is what the GLSL declares.
    #[test]
    fn reflection_reads_the_declared_bindings_and_push_constants() {
        use BindingKind::StorageBuffer as B;
        // loss_finalize.comp: stats (0), stats_fixed (1); push (loss, stats_shift).
        assert_eq!(LOSS_FINALIZE_COMP.bindings, &[(0, B), (1, B)]);
        assert_eq!(LOSS_FINALIZE_COMP.push_constant_bytes, 8);
        // work_args.comp: work_count (0); push max_groups.
        assert_eq!(WORK_ARGS_COMP.bindings, &[(0, B)]);
        assert_eq!(WORK_ARGS_COMP.push_constant_bytes, 4);
        // shaded.vert: positions (0); push the view's camera data, 24 floats.
        assert_eq!(SHADED_VERT.bindings, &[(0, B)]);
        assert_eq!(SHADED_VERT.push_constant_bytes, 96);
        // classify.comp uses 8 of the 23 per-pixel bindings; the pipeline takes those.
        let numbers: Vec<u32> = CLASSIFY_COMP.bindings.iter().map(|b| b.0).collect();
        assert!(
            numbers.contains(&5) && numbers.contains(&14),
            "ids and stats_fixed: {numbers:?}"
        );
        assert!(
            !numbers.contains(&19),
            "no pair records in classify: {numbers:?}"
        );
        assert!(GBUFFER_FRAG.bindings.is_empty());
    }
}
