//! One trial's scene: the test instance rendered (or a real frame read) with what a real
//! frame has around it: a table, an occluder in front, depth noise and holes.

use glam::DVec3;

use crate::dataset::Rng;
use vkdr::camera::{Camera, Pose};
use vkdr::diff::{Scene, SceneDesc, Shading};
use vkdr::error::Result;
use vkdr::gpu::Context;
use vkdr::loss::Loss;
use vkdr::mesh::Mesh;
use vkdr::raster::{Outputs, View};
use vkdr::register::{OtherView, Registrar};

use super::settings::{gaussian, trial_cameras};
use super::{view_pose_up, EvalSettings, Reference};

/// Angle (radians, 0 to pi/2) between the line of sight from the camera to the object's
/// origin through `pose` and the object-frame `axis` (either way along it).
pub fn line_of_sight_angle(pose: Pose, axis: DVec3) -> f64 {
    let sight = pose.rotation_matrix().transpose() * pose.translation.normalize();
    sight.dot(axis.normalize()).abs().min(1.0).acos()
}

/// The object-frame unit axes of `mesh`'s bounding box, longest extent first.
pub fn extent_axes(mesh: &Mesh) -> [DVec3; 3] {
    let (lo, hi) = mesh.bounds();
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| (hi[b] - lo[b]).total_cmp(&(hi[a] - lo[a])));
    order.map(|k| DVec3::from_array(std::array::from_fn(|j| if j == k { 1.0 } else { 0.0 })))
}

/// The mask of `mesh` rendered through `view`.
pub fn render_mask(
    ctx: &Context,
    registrar: &Registrar,
    mesh: &Mesh,
    view: View,
) -> Result<Vec<f32>> {
    let g = registrar
        .renderer()
        .rasterizer()
        .render(ctx, mesh, &[view], Outputs::Ids)?;
    Ok(g.ids
        .iter()
        .map(|&id| if id > 0 { 1.0 } else { 0.0 })
        .collect())
}

/// A square plane 0.6 m across (both sides), normal to `up`, half a millimetre below the
/// lowest point of `test` along it: the table it stands on.
pub fn table_under(test: &Mesh, up: DVec3) -> Result<Mesh> {
    let up = up.normalize();
    let lowest = test
        .points()
        .iter()
        .map(|p| p.dot(up))
        .fold(f64::INFINITY, f64::min);
    let a = up.any_orthonormal_vector();
    let b = up.cross(a);
    let centre = up * (lowest - 5e-4);
    let corners: Vec<[f32; 3]> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .iter()
        .map(|&(u, v)| (centre + 0.3 * (u * a + v * b)).as_vec3().to_array())
        .collect();
    Mesh::new(corners, vec![[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]])
}

/// A rectangle facing the camera (both sides, camera coordinates) in front of the left
/// half of the mask's box (`[row][column]` of `camera`'s size), 5 cm nearer than `near`
/// (the nearest depth of the object) and a little taller than the box: an occluder that
/// hides about half the object. None for an empty mask.
pub fn occluder_before(camera: &Camera, mask: &[f32], near: f64) -> Result<Option<Mesh>> {
    let w = camera.width as usize;
    let covered: Vec<usize> = (0..mask.len()).filter(|&i| mask[i] > 0.0).collect();
    if covered.is_empty() {
        return Ok(None);
    }
    let xs = covered.iter().map(|&i| (i % w) as f64);
    let ys = covered.iter().map(|&i| (i / w) as f64);
    let (x0, x1) = (
        xs.clone().fold(f64::INFINITY, f64::min),
        xs.fold(0.0, f64::max) + 1.0,
    );
    let (y0, y1) = (
        ys.clone().fold(f64::INFINITY, f64::min),
        ys.fold(0.0, f64::max) + 1.0,
    );
    let z = (near - 0.05).max(2.0 * camera.near);
    let margin = 0.1 * (y1 - y0);
    let corner = |u: f64, v: f64| {
        [
            ((u - camera.cx) * z / camera.fx) as f32,
            ((v - camera.cy) * z / camera.fy) as f32,
            z as f32,
        ]
    };
    let middle = 0.5 * (x0 + x1);
    let (left, top, bottom) = (x0 - 4.0 * margin, y0 - margin, y1 + margin);
    let corners = vec![
        corner(left, top),
        corner(middle, top),
        corner(middle, bottom),
        corner(left, bottom),
    ];
    Ok(Some(Mesh::new(
        corners,
        vec![[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]],
    )?))
}

/// Puts `other` (an observation of one view with depth: mask and depth of another
/// surface) into the first view of `observed` (with depth), nearest surface first: where
/// it lies in front of the object the object is hidden (mask 0, or unknown where
/// `unknown`), and its depth is measured wherever it is the nearest surface.
pub fn put_in_front(observed: &mut Images, other: &Images, unknown: bool) {
    let (Some(depth), Some(other_depth)) = (observed.depth.as_mut(), other.depth.as_ref()) else {
        return;
    };
    for i in 0..other.mask.len() {
        let z = other_depth[i];
        if other.mask[i] <= 0.0 || !(depth[i] == 0.0 || z < depth[i]) {
            continue;
        }
        depth[i] = z;
        let hidden = if unknown { vkdr::loss::UNKNOWN } else { 0.0 };
        if unknown || observed.mask[i] > 0.0 {
            observed.mask[i] = hidden;
            if let Some(shaded) = observed.shaded.as_mut() {
                shaded[i] = hidden;
            }
        }
    }
}

/// Removes about `fraction` of the measured depth of one view (`width` wide) in clusters:
/// discs of 2 to 6 pixels' radius at random centres, as a sensor loses dark, shiny or
/// grazing surfaces.
pub fn cluster_holes(depth: &mut [f32], width: usize, fraction: f64, rng: &mut Rng) {
    let height = depth.len() / width.max(1);
    let target = (fraction * depth.len() as f64) as usize;
    let mut removed = 0;
    let mut attempts = 0;
    while removed < target && attempts < 100 * depth.len() {
        attempts += 1;
        let (cx, cy) = (rng.range(0.0, width as f64), rng.range(0.0, height as f64));
        let r = rng.range(2.0, 6.0);
        let (x0, x1) = (
            (cx - r).max(0.0) as usize,
            ((cx + r) as usize).min(width - 1),
        );
        let (y0, y1) = (
            (cy - r).max(0.0) as usize,
            ((cy + r) as usize).min(height - 1),
        );
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                let i = y * width + x;
                if dx * dx + dy * dy <= r * r && depth[i] > 0.0 {
                    depth[i] = 0.0;
                    removed += 1;
                }
            }
        }
    }
}

/// What cameras see, each image `[view][row][column]` (rendered by [`observe`], or a real
/// frame's): the engine's [`vkdr::Observation`] without its cameras.
#[derive(Clone)]
pub struct Images {
    /// The mask: nonzero where the object is seen (1 where a rendered mesh covers the pixel
    /// centre), [`vkdr::loss::UNKNOWN`] where unknown.
    pub mask: Vec<f32>,
    /// Camera-space depth where covered, 0 elsewhere (no measurement), if asked for.
    pub depth: Option<Vec<f32>>,
    /// The Lambert shading ([`render_shading`]), if asked for.
    pub shaded: Option<Vec<f32>>,
}

/// Renders what cameras at `views` observe of `mesh`: its mask, and its depth and shading
/// where asked for (the test instance's observation in `eval`, `register --observed-mesh`
/// and `bench-register`).
pub fn observe(
    ctx: &Context,
    registrar: &Registrar,
    mesh: &Mesh,
    views: &[View],
    depth: bool,
    shading: Option<Shading>,
) -> Result<Images> {
    let outputs = if depth {
        Outputs::IdsBaryDepth
    } else {
        Outputs::Ids
    };
    let g = registrar
        .renderer()
        .rasterizer()
        .render(ctx, mesh, views, outputs)?;
    Ok(Images {
        mask: g.ids.iter().map(|&id| (id > 0) as u32 as f32).collect(),
        depth: g.depth.map(|d| d.iter().copied().collect()),
        shaded: shading
            .map(|s| render_shading(ctx, registrar, mesh, views, s))
            .transpose()?,
    })
}

/// The Lambert shading of `mesh` rendered through `views` (`[view][row][column]`, background
/// 0, antialiased as the registration renders its own).
pub fn render_shading(
    ctx: &Context,
    registrar: &Registrar,
    mesh: &Mesh,
    views: &[View],
    shading: Shading,
) -> Result<Vec<f32>> {
    let pixels: usize = views
        .iter()
        .map(|v| v.camera.width as usize * v.camera.height as usize)
        .sum();
    let mut scene = Scene::new(
        ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh,
            views,
            loss: Loss::Mse,
            observed: &vec![0.0; pixels],
            attributes: None,
            shading: Some(shading),
            depth: None,
        },
    )?;
    Ok(scene.evaluate(ctx, registrar.renderer())?.antialiased)
}

/// One trial's scene: the view (the true pose), further cameras and what they observe.
#[derive(Clone)]
pub struct TrialScene {
    /// The first camera's azimuth and elevation about the object, radians.
    pub azimuth: f64,
    pub elevation: f64,
    /// The true object-to-camera pose (the first view's).
    pub pose: Pose,
    pub view: View,
    pub others: Vec<OtherView>,
    pub observed: Images,
}

/// Where [`super::evaluate_instance`]'s trials come from.
#[derive(Clone, Copy)]
pub enum TrialSource<'a> {
    /// Rendered from the test instance at random views, with the settings' real frames'
    /// ways (occluder, table, depth noise and holes).
    Rendered,
    /// One observed frame (its true pose given), the same in every trial: the trials differ
    /// in their pose noise; the registration with the pose known runs once. The model's
    /// [`Reference`] is computed once for every frame that shows it.
    Frame {
        scene: &'a TrialScene,
        reference: &'a Reference,
    },
}

/// A rendered trial: random views of `test` (and `table` under it) with the settings'
/// occluder, depth noise and holes.
pub fn render_trial(
    ctx: &Context,
    registrar: &Registrar,
    test: &Mesh,
    table: Option<&Mesh>,
    settings: &EvalSettings,
    rng: &mut Rng,
) -> Result<TrialScene> {
    let cameras = trial_cameras(rng, settings);
    let (azimuth, elevation) = cameras[0];
    let pose = view_pose_up(settings.up, azimuth, elevation, settings.distance);
    let view = View {
        camera: settings.camera,
        pose,
    };
    let others: Vec<OtherView> = cameras[1..]
        .iter()
        .map(|&(azimuth, elevation)| {
            let other = view_pose_up(settings.up, azimuth, elevation, settings.distance);
            OtherView {
                camera: settings.camera,
                from_first: pose.inverse().followed_by(&other),
            }
        })
        .collect();
    let views = vkdr::register::all_views(view, &others);
    let with_surroundings = settings.occluder || settings.table;
    let mut observed = observe(
        ctx,
        registrar,
        test,
        &views,
        settings.depth.is_some() || with_surroundings,
        settings.shading,
    )?;
    let n = (settings.camera.width * settings.camera.height) as usize;
    if let Some(table) = table {
        let seen = observe(ctx, registrar, table, &[view], true, None)?;
        put_in_front(&mut observed, &seen, false);
    }
    if settings.occluder {
        let near = observed.depth.as_ref().map_or(settings.distance, |d| {
            d[..n]
                .iter()
                .zip(&observed.mask)
                .filter(|&(&z, &m)| m > 0.0 && z > 0.0)
                .map(|(&z, _)| z as f64)
                .fold(f64::INFINITY, f64::min)
        });
        if let Some(occluder) = occluder_before(&settings.camera, &observed.mask[..n], near)? {
            let camera_frame = View {
                camera: settings.camera,
                pose: Pose::at([0.0; 3]),
            };
            let seen = observe(ctx, registrar, &occluder, &[camera_frame], true, None)?;
            put_in_front(&mut observed, &seen, settings.depth.is_none());
        }
    }
    if settings.depth.is_none() {
        observed.depth = None;
    }
    let (mask, shaded) = (observed.mask, observed.shaded);
    let depth: Option<Vec<f32>> = observed.depth.map(|depth| {
        let mut depth: Vec<f32> = depth
            .iter()
            .map(|&z| {
                if z > 0.0 && settings.depth_noise > 0.0 {
                    // A measurement stays a measurement (> 0).
                    (z as f64 + settings.depth_noise * gaussian(rng)).max(1e-4) as f32
                } else {
                    z
                }
            })
            .collect();
        if settings.depth_holes > 0.0 {
            for view in depth.chunks_mut(n) {
                let width = settings.camera.width as usize;
                cluster_holes(view, width, settings.depth_holes, rng);
            }
        }
        depth
    });
    Ok(TrialScene {
        azimuth,
        elevation,
        pose,
        view,
        others,
        observed: Images {
            mask,
            depth,
            shaded,
        },
    })
}
