//! After a joint fit with depth: whether the fitted surface lies where the measured depth
//! puts it, and the fit again from there where it does not.
//!
//! The depth cost is bounded (a residual past a few of its scales pulls almost nothing),
//! so a joint fit can settle centimetres along the line of sight with its silhouette
//! matched by a nearer, smaller shape and the depth given up: on the real can one trial of
//! 30 ended 33 mm near at 0.89 of its size, at 4 times the loss of the others. The median depth
//! residual over the pixels the fitted surface and the mask share tells it where the
//! loss cannot (what loss a frame allows is not known). Where it is over
//! [`SETTLE_TOLERANCE`] depth scales, the fit runs again from the pose moved along the line
//! of sight by it (the shape scaled with it where the scale is free, so that its
//! silhouette stays) and the lower loss is kept.

use std::time::Instant;

use glam::DVec3;

use crate::error::Result;
use crate::gpu::Context;
use crate::mesh::Mesh;
use crate::raster::reference::rasterize;
use crate::raster::View;
use crate::{Camera, Pose};

use super::params::SCALE_BOUND;
use super::region::mask_box;
use super::task::{lower_loss, Stage, Staged};
use super::{Job, RegisterParams, Registrar, SCALE_UNIT, STAGE_SETTLED};

/// The median depth residual, in depth scales ([`crate::diff::DepthLoss::scale`]), past
/// which a fit is run again from the pose it implies.
pub const SETTLE_TOLERANCE: f64 = 0.5;
/// Pixels (shared by the fitted surface, the mask and the measured depth) under which the
/// median is not trusted and the fit is kept.
const MIN_PIXELS: usize = 32;
/// About how many pixels across the mask's bounding box the fitted surface is rendered
/// with (a coarser step over a larger box): a median needs no more.
const SAMPLES_ACROSS: usize = 32;

/// Where a fitted surface lies against the measured depth: the median of measured minus
/// rendered depth over the pixels where `vertices` (the job's space's mesh, object frame)
/// are rendered at `pose` in the job's first view, the mask is object and the depth
/// measured, and the median rendered depth there (metres). None without depth or with
/// fewer than [`MIN_PIXELS`] such pixels.
pub(super) fn depth_offset(job: &Job, vertices: &[DVec3], pose: &Pose) -> Option<(f64, f64)> {
    let depth = job.depth?;
    let positions = vertices.iter().map(|v| v.as_vec3().to_array()).collect();
    let triangles = job.space.canonical.triangles().to_vec();
    let mesh = Mesh::new(positions, triangles).ok()?;
    // Rendered over the mask's bounding box only, at a step that keeps about
    // SAMPLES_ACROSS pixels across it: the camera's principal point moved to the box's
    // corner and the focal lengths divided by the step, each coarse pixel compared with
    // the frame's pixel under its centre.
    let camera = job.view.camera;
    let width = camera.width as usize;
    let object = |i: usize| job.observed[i] > 0.0;
    let (x0, y0, x1, y1) = mask_box(&job.observed[..width * camera.height as usize], width)?;
    let (across, down) = (x1 - x0 + 1, y1 - y0 + 1);
    let step = (across.max(down) / SAMPLES_ACROSS).max(1);
    let coarse = step as f64;
    let boxed = Camera {
        fx: camera.fx / coarse,
        fy: camera.fy / coarse,
        cx: (camera.cx - x0 as f64) / coarse,
        cy: (camera.cy - y0 as f64) / coarse,
        width: across.div_ceil(step) as u32,
        height: down.div_ceil(step) as u32,
        ..camera
    };
    let rendered = rasterize(&mesh, &boxed, pose);
    let under = |k: usize| {
        let fine = |c: usize| ((c as f64 + 0.5) * coarse) as usize;
        let (x, y) = (fine(k % rendered.width), fine(k / rendered.width));
        (x < across && y < down).then(|| (y0 + y) * width + x0 + x)
    };
    let (mut residuals, mut depths): (Vec<f64>, Vec<f64>) = (0..rendered.ids.len())
        .filter_map(|k| under(k).map(|i| (k, i)))
        .filter(|&(k, i)| rendered.ids[k] != 0 && object(i) && depth[i] > 0.0)
        .map(|(k, i)| (depth[i] as f64 - rendered.depth[k], rendered.depth[k]))
        .unzip();
    if residuals.len() < MIN_PIXELS {
        return None;
    }
    Some((median(&mut residuals), median(&mut depths)))
}

fn median(values: &mut [f64]) -> f64 {
    let middle = values.len() / 2;
    *values.select_nth_unstable_by(middle, f64::total_cmp).1
}

/// `pose` moved along the line of sight so that a surface point at depth `at` moves by
/// `offset` (the object's origin keeps its pixel), and the factor its distance grew by.
pub(super) fn moved_along_sight(pose: Pose, offset: f64, at: f64) -> (Pose, f64) {
    let factor = (at + offset) / at;
    let moved = Pose {
        translation: pose.translation * factor,
        ..pose
    };
    (moved, factor)
}

/// The device's code coordinates (the scale's last where `scaled`) of a shape `factor`
/// times as large: the code keeps its deformation over the scale ([`super::task::Task::code`]),
/// so every coordinate grows with the scale, within the scale's bound.
pub(super) fn scaled_coordinates(coordinates: &[f32], factor: f64, scaled: bool) -> Vec<f32> {
    if !scaled {
        return coordinates.to_vec();
    }
    let (code, scale) = coordinates.split_at(coordinates.len() - 1);
    let old = 1.0 + scale[0] as f64 * SCALE_UNIT;
    let unit = ((old * factor - 1.0) / SCALE_UNIT).clamp(-SCALE_BOUND, SCALE_BOUND);
    let new = 1.0 + unit * SCALE_UNIT;
    let grown = new / old;
    code.iter()
        .map(|&c| (c as f64 * grown) as f32)
        .chain([unit as f32])
        .collect()
}

impl Registrar {
    /// The joint fits `fitted` of `jobs` (with depth), each checked against its depth
    /// ([`depth_offset`]); those off by more than [`SETTLE_TOLERANCE`] fitted again in one
    /// batch from the pose moved along the line of sight, the lower final loss kept (its
    /// stage then [`STAGE_SETTLED`]).
    pub(super) fn settle_on_depth(
        &self,
        ctx: &Context,
        jobs: &[Job],
        fitted: Vec<Staged>,
        params: &RegisterParams,
        started: Instant,
    ) -> Result<Vec<Staged>> {
        // Only where the depth is compared and z is free to follow it.
        let Some(depth) = params.depth.filter(|d| d.weight > 0.0 && params.optimize_z) else {
            return Ok(fitted);
        };
        let mut moved = Vec::new();
        for (i, (job, staged)) in jobs.iter().zip(&fitted).enumerate() {
            let Some((offset, at)) =
                depth_offset(job, &staged.result.vertices, &staged.result.pose)
            else {
                continue;
            };
            if offset.abs() <= SETTLE_TOLERANCE * depth.scale {
                continue;
            }
            let (pose, factor) = moved_along_sight(staged.result.pose, offset, at);
            let coordinates =
                scaled_coordinates(&staged.coordinates, factor, params.optimize_scale);
            let job = Job {
                view: View { pose, ..job.view },
                ..*job
            };
            moved.push((i, job, coordinates));
        }
        if moved.is_empty() {
            return Ok(fitted);
        }
        let moved_jobs: Vec<Job> = moved.iter().map(|(_, job, _)| *job).collect();
        let codes: Vec<Vec<f32>> = moved.iter().map(|(_, _, c)| c.clone()).collect();
        let again = self.run(
            ctx,
            &moved_jobs,
            Stage::fit(params, Some(&codes), started),
            &mut |_, _| {},
        )?;
        let mut refits: Vec<Option<Staged>> = fitted.iter().map(|_| None).collect();
        for ((i, _, _), again) in moved.into_iter().zip(again) {
            refits[i] = Some(again);
        }
        Ok(fitted
            .into_iter()
            .zip(refits)
            .map(|(staged, again)| match again {
                Some(again) => lower_loss(staged, again, STAGE_SETTLED, started),
                None => staged,
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::shape::random_space;

    /// The offset of a surface rendered where the depth was measured is 0; of the same
    /// surface 3 cm farther, about -3 cm; and the pose moved along the line of sight by
    /// it is back within a millimetre or two of the truth.
    #[test]
    fn depth_offset_finds_a_surface_off_along_the_line_of_sight() {
        let space = random_space(&mut Rng::new(3), 4, 2);
        let vertices = space.vertices(&[0.0, 0.0]).unwrap();
        let camera = Camera::new(240.0, 240.0, 80.0, 60.0, 160, 120).unwrap();
        let truth = Pose::new([0.02, -0.01, 0.5], [0.3, 0.2, 0.1]).unwrap();
        let positions = vertices.iter().map(|v| v.as_vec3().to_array()).collect();
        let mesh = Mesh::new(positions, space.canonical.triangles().to_vec()).unwrap();
        let seen = rasterize(&mesh, &camera, &truth);
        let mask: Vec<f32> = seen.ids.iter().map(|&id| (id != 0) as u32 as f32).collect();
        let depth: Vec<f32> = seen.depth.iter().map(|&z| z as f32).collect();
        assert!(
            mask.iter().sum::<f32>() > 500.0,
            "the object fills too few pixels"
        );
        let job = Job {
            depth: Some(&depth),
            ..Job::new(
                &space,
                &mask,
                View {
                    camera,
                    pose: truth,
                },
            )
        };
        let (offset, at) = depth_offset(&job, &vertices, &truth).unwrap();
        assert!(offset.abs() < 1e-6, "{offset}");
        assert!((0.4..0.6).contains(&at), "{at}");
        let far = Pose {
            translation: truth.translation + DVec3::new(0.0, 0.0, 0.03),
            ..truth
        };
        let (offset, at) = depth_offset(&job, &vertices, &far).unwrap();
        assert!((offset + 0.03).abs() < 0.004, "{offset}");
        let (back, _) = moved_along_sight(far, offset, at);
        let miss = (back.translation - truth.translation).length();
        assert!(miss < 0.003, "{miss}");
        // Seen from nearer (about 300 pixels across), it is rendered at a coarser step:
        // the offsets are the same to a fraction of a millimetre.
        let near = Pose {
            translation: DVec3::new(0.0, 0.0, 0.18),
            ..truth
        };
        let seen = rasterize(&mesh, &camera, &near);
        let close: Vec<f32> = seen.ids.iter().map(|&id| (id != 0) as u32 as f32).collect();
        let close_depth: Vec<f32> = seen.depth.iter().map(|&z| z as f32).collect();
        let close_job = Job {
            depth: Some(&close_depth),
            ..Job::new(&space, &close, View { camera, pose: near })
        };
        let (offset, _) = depth_offset(&close_job, &vertices, &near).unwrap();
        assert!(offset.abs() < 2e-4, "{offset}");
        let nearer = Pose {
            translation: near.translation - DVec3::new(0.0, 0.0, 0.01),
            ..near
        };
        let (offset, _) = depth_offset(&close_job, &vertices, &nearer).unwrap();
        assert!((offset - 0.01).abs() < 0.002, "{offset}");
        // Without depth, or nothing in common with the mask, there is no offset.
        assert!(depth_offset(
            &Job::new(
                &space,
                &mask,
                View {
                    camera,
                    pose: truth
                }
            ),
            &vertices,
            &truth
        )
        .is_none());
        let away = Pose {
            translation: DVec3::new(5.0, 0.0, 0.5),
            ..truth
        };
        assert!(depth_offset(&job, &vertices, &away).is_none());
    }

    /// Moving along the line of sight keeps the origin's pixel and moves a point at the
    /// given depth by the offset.
    #[test]
    fn moved_along_sight_keeps_the_pixel() {
        let pose = Pose {
            translation: DVec3::new(0.1, -0.05, 0.8),
            rotation: DVec3::new(0.2, 0.1, -0.3),
        };
        let (moved, factor) = moved_along_sight(pose, 0.03, 0.75);
        assert!((factor - 0.78 / 0.75).abs() < 1e-12);
        let t = moved.translation;
        assert!((t.x / t.z - 0.1 / 0.8).abs() < 1e-12 && (t.y / t.z + 0.05 / 0.8).abs() < 1e-12);
        assert!((t.z - 0.8 * factor).abs() < 1e-12);
        assert_eq!(moved.rotation, pose.rotation);
    }

    /// A shape scaled by a factor: the scale coordinate grows the scale by it and the code
    /// coordinates with it (so the code, their ratio, stays); at the bound the growth is
    /// what the bound allows, and without a scale nothing moves.
    #[test]
    fn scaled_coordinates_keep_the_code() {
        let scale = |u: f32| 1.0 + u as f64 * SCALE_UNIT;
        let z = [0.4f32, -1.2, 0.8];
        let grown = scaled_coordinates(&z, 1.1, true);
        assert!((scale(grown[2]) - 1.1 * scale(z[2])).abs() < 1e-6);
        for j in 0..2 {
            let (before, after) = (z[j] as f64 / scale(z[2]), grown[j] as f64 / scale(grown[2]));
            assert!((before - after).abs() < 1e-6, "{before} {after}");
        }
        let capped = scaled_coordinates(&[1.0, 2.9], 1.5, true);
        assert_eq!(capped[1] as f64, SCALE_BOUND);
        let growth = scale(capped[1]) / scale(2.9);
        assert!((capped[0] as f64 - growth).abs() < 1e-6);
        assert_eq!(scaled_coordinates(&z, 1.1, false), z.to_vec());
    }
}
