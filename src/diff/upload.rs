//! A scene uploaded: its buffers sized, checked against the device's limits, and filled.

use crate::error::{Error, Result};
use crate::gpu::{Buffer, BufferKind, Context};
use crate::loss::{DistanceField, Loss};
use crate::raster::{Gbuffer, MeshBuffers, Outputs, ViewBuffers};

use super::{
    box_words, check_scene_fits, incident_triangles, neighbours, stats_shift, LambertBuffers,
    Scene, SceneDesc, MAX_TRIANGLES, POSE_GROUPS, VERTEX_BLOCK, WORK_COUNT_WORDS,
};

impl Scene {
    /// Uploads the scene `desc` describes; an error for inconsistent inputs or
    /// buffers past the device's limits.
    pub fn new(ctx: &Context, desc: &SceneDesc) -> Result<Self> {
        let mesh = MeshBuffers::new(ctx, desc.mesh)?;
        let views = ViewBuffers::new(ctx, desc.views)?;
        let (w, h, n) = (views.width(), views.height(), views.count());
        let pixels = w as u64 * h as u64 * n as u64;
        let loss_pixels = desc.loss_pixels.unwrap_or(w as u64 * h as u64);
        if loss_pixels < w as u64 * h as u64 {
            // The fixed-point sums' bound (stats_shift) holds for terms averaged over at
            // least the image's pixels.
            return Err(Error::InvalidInput(format!(
                "the loss averaged over {loss_pixels} pixels: at least the view's {w}x{h}"
            )));
        }
        let vertices = desc.mesh.vertex_count() as u64;
        if desc.mesh.triangle_count() >= MAX_TRIANGLES {
            return Err(Error::Limit(format!(
                "{} triangles: the pixel-pair records hold triangle numbers below {MAX_TRIANGLES}",
                desc.mesh.triangle_count()
            )));
        }
        if desc.shading.is_some() && desc.attributes.is_some() {
            return Err(Error::InvalidInput(
                "a scene compares either attributes or shading, not both".into(),
            ));
        }
        let lambert = match desc.shading {
            None => None,
            Some(shading) => {
                let light = shading.unit_light()?.map(|v| v as f32);
                let (start, incident) = incident_triangles(desc.mesh);
                // lambert.comp loops over a vertex's triangles in one invocation.
                let valence = start.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);
                if valence > crate::gpu::LOOP_LIMIT / 2 {
                    return Err(Error::Limit(format!(
                        "a vertex of the mesh is shared by {valence} triangles; shading \
                         handles at most {} per vertex",
                        crate::gpu::LOOP_LIMIT / 2
                    )));
                }
                Some(LambertBuffers {
                    start: Buffer::from_slice(ctx, "incident triangle starts", &start)?,
                    incident: Buffer::from_slice(ctx, "incident triangles", &incident)?,
                    grad_normal: Buffer::new(
                        ctx,
                        "normal gradients",
                        n as u64 * vertices * 12,
                        BufferKind::Device,
                    )?,
                    light,
                    ambient: shading.ambient as f32,
                })
            }
        };
        if let Some(depth) = &desc.depth {
            depth.loss.validate()?;
        }
        // With depth, every vertex gains a last channel (written on the device), and a mask
        // becomes a constant channel 0 (coverage) so that depth can be interpolated.
        let with_depth = desc.depth.is_some() as u32;
        let coverage = desc.depth.is_some() && desc.attributes.is_none() && lambert.is_none();
        // Every view has its own attributes: given ones repeated, shading's and depth's
        // written on the device.
        let (attributes, channels) = match (desc.attributes, &lambert) {
            (None, None) if !coverage => (Buffer::from_slice(ctx, "attributes", &[0.0f32])?, 0),
            (None, _) => {
                let channels = 1 + with_depth;
                let bytes = n as u64 * vertices * channels as u64 * 4;
                (
                    Buffer::new(ctx, "attributes", bytes, BufferKind::Device)?,
                    channels,
                )
            }
            (Some((values, channels)), _) => {
                if !(1..=4 - with_depth).contains(&channels)
                    || values.len() != desc.mesh.vertex_count() * channels as usize
                {
                    return Err(Error::InvalidInput(format!(
                        "{} attribute values for {} vertices x {channels} channels (1 to {}{})",
                        values.len(),
                        desc.mesh.vertex_count(),
                        4 - with_depth,
                        if with_depth > 0 { " with depth" } else { "" }
                    )));
                }
                let stride = (channels + with_depth) as usize;
                let mut per_view = vec![0f32; desc.mesh.vertex_count() * stride];
                for (row, given) in per_view
                    .chunks_mut(stride)
                    .zip(values.chunks(channels as usize))
                {
                    row[..channels as usize].copy_from_slice(given);
                }
                let repeated = per_view.repeat(n as usize);
                (
                    Buffer::from_slice(ctx, "attributes", &repeated)?,
                    channels + with_depth,
                )
            }
        };
        if channels > 0 && desc.loss != Loss::Mse {
            let compared = if desc.depth.is_some() {
                "depth"
            } else if lambert.is_some() {
                "shading"
            } else {
                "attributes"
            };
            return Err(Error::InvalidInput(format!(
                "the {} loss compares masks; use mse with {compared}",
                desc.loss.name()
            )));
        }
        let image_channels = channels.max(1) as u64;
        let given_channels = image_channels - with_depth as u64;
        if desc.observed.len() as u64 != pixels * given_channels {
            return Err(Error::InvalidInput(format!(
                "observed images hold {} values, expected {n} views x {w} x {h} x {given_channels}",
                desc.observed.len()
            )));
        }
        if desc.observed.iter().any(|v| !v.is_finite()) {
            return Err(Error::InvalidInput(
                "observed images contain NaN or Inf".into(),
            ));
        }
        if let Some(depth) = &desc.depth {
            if depth.depth.len() as u64 != pixels {
                return Err(Error::InvalidInput(format!(
                    "observed depth holds {} values, expected {n} views x {w} x {h}",
                    depth.depth.len()
                )));
            }
            if let Some(bad) = depth.depth.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                return Err(Error::InvalidInput(format!(
                    "observed depth holds {bad}: depths are metres, >= 0 (0: not measured)"
                )));
            }
        }
        check_scene_fits(ctx, (w, h, n), image_channels, vertices, channels)?;
        // The compared image's channels side by side: the given ones, then depth.
        let observed: Vec<f32> = match &desc.depth {
            None => desc.observed.to_vec(),
            Some(depth) => desc
                .observed
                .chunks(given_channels as usize)
                .zip(depth.depth)
                .flat_map(|(given, &d)| given.iter().copied().chain([d]))
                .collect(),
        };
        let device = |name, bytes| Buffer::new(ctx, name, bytes, BufferKind::Device);
        let with_distance = desc.loss == Loss::Distance;
        let subgroups = 64u32.div_ceil(ctx.info().subgroup_size.max(1));
        let stats_shift = stats_shift(desc, w, h);
        let grid_groups = ctx.info().grid_groups.max(1);
        let pose_groups = (vertices as u32)
            .div_ceil(64)
            .clamp(1, POSE_GROUPS.min(grid_groups));
        Ok(Self {
            gbuffer: Gbuffer::new(ctx, w, h, n, Outputs::Ids)?,
            neighbours: Buffer::from_slice(ctx, "neighbours", &neighbours(desc.mesh))?,
            attributes,
            lambert,
            observed: Buffer::from_slice(ctx, "observed", &observed)?,
            distance: device("distance field", if with_distance { pixels * 4 } else { 4 })?,
            distance_scratch: if with_distance {
                let bytes = DistanceField::scratch_bytes(w, h, n);
                Some([
                    device("jump flooding a", bytes)?,
                    device("jump flooding b", bytes)?,
                ])
            } else {
                None
            },
            antialiased: device("antialiased", pixels * image_channels * 4)?,
            stats: device("loss stats", n as u64 * 16)?,
            stats_fixed: device("fixed-point loss stats", n as u64 * 24)?,
            background: device("background loss stats", n as u64 * 24)?,
            boxes: device("pixel boxes", box_words(n) * 4)?,
            stats_shift,
            loss_pixels,
            work: device("work list", pixels * 4)?,
            pair_work_x: device("pairs along x", pixels * 4)?,
            pair_work_y: device("pairs along y", pixels * 4)?,
            work_count: device("work count", WORK_COUNT_WORDS * 4)?,
            grad_camera: device("camera gradients", n as u64 * vertices * 12)?,
            grad_attributes: device(
                "attribute gradients",
                (n as u64 * vertices * channels as u64 * 4).max(4),
            )?,
            grad_camera_fixed: device("fixed-point camera gradients", n as u64 * vertices * 24)?,
            grad_attributes_fixed: device(
                "fixed-point attribute gradients",
                (n as u64 * vertices * channels as u64 * 8).max(8),
            )?,
            grad_object: device("vertex gradients", vertices * 12)?,
            grad_pose: device("pose gradients", n as u64 * 24)?,
            pose_partials: device(
                "pose partial sums",
                n as u64 * pose_groups as u64 * subgroups as u64 * 24,
            )?,
            touched: device(
                "touched vertex blocks",
                (vertices.div_ceil(VERTEX_BLOCK as u64).div_ceil(32) * 4).max(4),
            )?,
            pose_groups,
            grid_groups,
            subgroups,
            ids: device("triangle ids", pixels * 4)?,
            pairs_x: device("pixel pairs along x", pixels * 4)?,
            pairs_y: device("pixel pairs along y", pixels * 4)?,
            alphas_x: device("pixel-pair crossings along x", pixels * 4)?,
            alphas_y: device("pixel-pair crossings along y", pixels * 4)?,
            mesh,
            views,
            loss: desc.loss,
            channels,
            depth: desc.depth.map(|d| d.loss),
            coverage,
        })
    }
}
