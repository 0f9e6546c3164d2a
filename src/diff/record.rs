//! A scene's passes recorded: the marked pixels' forward and backward passes, Lambert
//! shading and the depth channel.

use crate::error::Result;
use crate::gpu::{Binding, Buffer, Groups, ImageState, Recorder};

use super::{
    DepthConstants, DiffRenderer, FinalizeConstants, LambertConstants, Marks, PoseConstants,
    ResolveConstants, Scene, ATTRIBUTE_MAX, ATTRIBUTE_SEEN, CAMERA_MAX, CAMERA_SEEN, LOST_WALKS,
    PAIR_DISPATCH, TERMS_PER_LISTED, UNFINISHED, VERTEX_BLOCK, WORK_COUNT_WORDS,
};

impl Scene {
    pub(super) fn record_marked(
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
        // writes every element before the shading passes add to them.
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
        // shading passes add to every covered vertex) all of them. (The depth's gradient
        // the backward adds itself, to the vertices it touches.)
        let shaded = self.lambert.is_some();
        rec.fill_buffer(&self.touched, if shaded { u32::MAX } else { 0 });
        marks.pass(rec, "clear")?;
        self.record_lambert(renderer, rec, 0);
        self.record_depth(renderer, rec);
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
        // The camera gradients go to floats here only when the shading passes add to them;
        // otherwise the pose pass reads the fixed-point sums itself. (With depth the
        // attribute gradients of the coverage and depth channels resolve to 0: the backward
        // adds the depth's to the camera-space z.)
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
    pub(super) fn record_lambert(&self, renderer: &DiffRenderer, rec: &mut Recorder, stage: u32) {
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

    /// With depth, `glsl/depth.comp`: the vertices' camera-space depth as their last
    /// attribute (and a barrier after it).
    pub(super) fn record_depth(&self, renderer: &DiffRenderer, rec: &mut Recorder) {
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
            ],
            &DepthConstants {
                vertex_count: vertices,
                channels: self.channels,
                coverage: self.coverage as u32,
            },
            Groups::Count(vertices.div_ceil(64), 1, self.views.count()),
        );
        rec.memory_barrier();
    }
}
