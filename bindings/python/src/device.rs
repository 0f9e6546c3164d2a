//! `vkdr.Device`: one Vulkan device and the engine's pipelines on it (built on first use),
//! with the rasterizer, the exact loss gradients and the registration.

use std::sync::Arc;

use glam::{DMat3, DVec3};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use vkdr::diff::{ObservedDepth, Scene, SceneDesc};
use vkdr::loss::Loss;
use vkdr::raster::{GbufferData, Outputs, View};
use vkdr::register::{Job, Plan, ViewImages};

use crate::arrays::{self, array, bad};
use crate::engine::{Device, Engine};
use crate::options::{further_views, DepthOptions, Looks, Options};
use crate::space::{Registration, ShapeSpace};
use crate::{OrPy, Progress};

#[pymethods]
impl Device {
    #[new]
    #[pyo3(signature = (name=None, validation=false))]
    fn new(py: Python<'_>, name: Option<String>, validation: bool) -> PyResult<Self> {
        let engine = py.detach(|| Engine::new(name, validation)).py()?;
        Ok(Self {
            engine: Arc::new(engine),
        })
    }

    /// The device's name, as its driver reports it.
    #[getter]
    fn name(&self) -> String {
        self.engine.ctx.info().name.clone()
    }

    /// discrete GPU, integrated GPU, virtual GPU, CPU or other.
    #[getter]
    fn kind(&self) -> String {
        self.engine.ctx.info().kind.clone()
    }

    /// The Vulkan version the device supports.
    #[getter]
    fn api_version(&self) -> String {
        self.engine.ctx.info().api_version.clone()
    }

    /// The driver's name and its version details.
    #[getter]
    fn driver(&self) -> String {
        let info = self.engine.ctx.info();
        format!("{} {}", info.driver_name, info.driver_info)
            .trim()
            .to_string()
    }

    /// The limits the engine checks its work against (as `vkdr info` prints them).
    #[getter]
    fn limits<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let info = self.engine.ctx.info();
        let limits = PyDict::new(py);
        limits.set_item("max_image_dimension_2d", info.max_image_dimension_2d)?;
        limits.set_item("max_storage_buffer_range", info.max_storage_buffer_range)?;
        limits.set_item(
            "max_compute_workgroup_invocations",
            info.max_compute_workgroup_invocations,
        )?;
        limits.set_item(
            "max_compute_workgroup_count",
            info.max_compute_workgroup_count.to_vec(),
        )?;
        limits.set_item("max_push_constants_size", info.max_push_constants_size)?;
        limits.set_item("subgroup_size", info.subgroup_size)?;
        limits.set_item("sub_pixel_precision_bits", info.sub_pixel_precision_bits)?;
        Ok(limits)
    }

    /// Milliseconds the last call spent in the engine (GIL released), the rest of its
    /// time being the binding's: reading the arrays in, making the arrays out.
    #[getter]
    fn engine_ms(&self) -> f64 {
        self.engine
            .engine_ms
            .lock()
            .map(|ms| *ms)
            .unwrap_or(f64::NAN)
    }

    fn __repr__(&self) -> String {
        let info = self.engine.ctx.info();
        format!(
            "vkdr.Device('{}', {}, Vulkan {}, driver {})",
            info.name,
            info.kind,
            info.api_version,
            self.driver()
        )
    }

    /// Rasterizes a mesh (`vertices` V x 3, `faces` F x 3) seen through the camera `K`
    /// at `size` = (width, height) from one pose (6,) or several (N, 6). Returns `(ids,
    /// bary, depth)`: the triangle id + 1 at each pixel centre (uint32, 0 on background),
    /// the barycentric weights of corners 0 and 1 (float32, ..., 2), and the camera-space
    /// depth in metres (float32, 0 on background); each `(H, W, ...)`, or `(N, H, W, ...)`
    /// for several poses.
    #[pyo3(signature = (vertices, faces, K, size, poses))]
    #[allow(non_snake_case)]
    fn rasterize<'py>(
        &self,
        py: Python<'py>,
        vertices: &Bound<'py, PyAny>,
        faces: &Bound<'py, PyAny>,
        K: &Bound<'py, PyAny>,
        size: &Bound<'_, PyAny>,
        poses: &Bound<'py, PyAny>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let (g, mut shape) = render_poses(
            self,
            py,
            (vertices, faces),
            (K, size),
            poses,
            Outputs::IdsBaryDepth,
        )?;
        let ids = array(py, into_vec(g.ids), &shape)?;
        let depth = g.depth.map(into_vec).unwrap_or_default();
        let depth = array::<f32>(py, depth, &shape)?;
        shape.push(2);
        let bary = g.bary.map(into_vec).unwrap_or_default();
        let bary = array::<f32>(py, bary, &shape)?;
        Ok((ids.into_any(), bary.into_any(), depth.into_any()))
    }

    /// Which face each pixel centre sees, as `rasterize`'s `ids` (uint32, face + 1, 0 on
    /// background; (H, W) for one pose, (N, H, W) for several) without the barycentrics
    /// and depth: a quarter of the memory read back (what `vkdr.torch.rasterize` needs).
    #[pyo3(signature = (vertices, faces, K, size, poses))]
    #[allow(non_snake_case)]
    fn visibility<'py>(
        &self,
        py: Python<'py>,
        vertices: &Bound<'py, PyAny>,
        faces: &Bound<'py, PyAny>,
        K: &Bound<'py, PyAny>,
        size: &Bound<'_, PyAny>,
        poses: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (g, shape) = render_poses(self, py, (vertices, faces), (K, size), poses, Outputs::Ids)?;
        Ok(array(py, into_vec(g.ids), &shape)?.into_any())
    }

    /// The loss of the mesh's rendering at `pose` (6,) against the observed `mask` (H, W;
    /// nonzero = object, `vkdr.UNKNOWN` = unknown), and its exact gradients. Returns
    /// `(loss, grad_vertices, grad_pose)`: dL/dvertices (V x 3, float32, object frame) and
    /// dL/dpose (6, float64) for the pose's own numbers (translation, axis-angle).
    ///
    /// `loss`: "mse" (antialiased coverage), "iou" or "distance". `depth` (H, W, metres, 0 =
    /// not measured) adds a bounded depth term (`depth_sigma` m, `depth_weight`; pixels
    /// measured more than `occlusion` m in front of the surface count for nothing).
    /// `shading` (H, W, grey) compares Lambert shading (`light` towards the light, camera
    /// frame; `ambient`) instead of the mask. `ignore` (H, W, nonzero) marks pixels unknown
    /// where the mask does not show the object (BOP's whole-object mask works as it is).
    #[pyo3(signature = (vertices, faces, K, size, pose, mask, loss="mse", depth=None, shading=None, ignore=None, depth_sigma=None, depth_weight=None, occlusion=None, light=None, ambient=None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn loss_and_grad<'py>(
        &self,
        py: Python<'py>,
        vertices: &Bound<'py, PyAny>,
        faces: &Bound<'py, PyAny>,
        K: &Bound<'py, PyAny>,
        size: &Bound<'_, PyAny>,
        pose: &Bound<'py, PyAny>,
        mask: &Bound<'py, PyAny>,
        loss: &str,
        depth: Option<&Bound<'py, PyAny>>,
        shading: Option<&Bound<'py, PyAny>>,
        ignore: Option<&Bound<'py, PyAny>>,
        depth_sigma: Option<f64>,
        depth_weight: Option<f64>,
        occlusion: Option<f64>,
        light: Option<[f64; 3]>,
        ambient: Option<f64>,
    ) -> PyResult<(f64, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let mesh = crate::mesh(vertices, faces)?;
        let camera = crate::camera(K, crate::size(size, "size")?)?;
        let pose = crate::pose(pose, "pose")?;
        let loss: Loss = loss.parse().map_err(|e| bad("loss", e))?;
        let looks = Looks::read_views(
            mask,
            depth,
            shading,
            ignore,
            camera,
            Vec::new(),
            DepthOptions {
                sigma: depth_sigma,
                weight: depth_weight,
                occlusion,
            },
            (light, ambient),
        )?;
        let view = View { camera, pose };
        let result = py.detach(|| {
            self.engine.run(|ctx, parts| {
                let desc = SceneDesc {
                    loss_pixels: None,
                    mesh: &mesh,
                    views: &[view],
                    loss,
                    observed: looks.compared(),
                    attributes: None,
                    shading: looks.shading,
                    depth: looks
                        .observation
                        .depth
                        .as_deref()
                        .map(|depth| ObservedDepth {
                            depth,
                            loss: looks.depth_loss,
                        }),
                };
                let renderer = parts.registrar(ctx)?.renderer();
                Scene::new(ctx, &desc)?.evaluate(ctx, renderer)
            })
        })?;
        let vertex: Vec<f32> = result.vertex_gradient.iter().flatten().copied().collect();
        let grad_vertices = array(py, vertex, &[mesh.vertex_count(), 3])?;
        let grad_pose = array(py, pose_gradient(&pose, &result.pose_gradient[0]), &[6])?;
        Ok((
            result.loss[0] as f64,
            grad_vertices.into_any(),
            grad_pose.into_any(),
        ))
    }

    /// Registers `space` (a `vkdr.ShapeSpace`) to an observed `mask` (H, W) seen through
    /// `K` at `size` from the initial `pose` (6,): fits its latent code, and with
    /// `optimize_pose=True` the pose too. Returns a `vkdr.Registration`.
    ///
    /// Observations: `depth` (H, W, metres, 0 = not measured), `shading` (H, W, grey),
    /// `ignore` (H, W: pixels hidden by something in front), and `views`, a list of
    /// further cameras, each a dict with `K`, `size`, `from_first` (6,: the first camera's
    /// frame to this one's), `mask` and optionally `depth` and `shading`.
    ///
    /// Options (the command line's `vkdr register` flags, the same defaults):
    /// `optimize_pose` (False), `optimize_scale` (False: one uniform scale, 0.25-1.75),
    /// `iterations` (30, or 60 after a 15-iteration pose alignment with the pose free,
    /// and with depth 10 more at a wide depth scale),
    /// `loss` ("mse"), `optimizer` ("bfgs"; "sgd", "adam"), `code_prior` ("auto" or a
    /// weight), `starts` (5 with the pose free, else 1: the pose turned about `up` by
    /// +-15, +-30 degrees, tried on the first start's fit), `up` ((0, 1, 0), the object's up
    /// axis), `gravity` (None, (x, y, z) up in the camera frame, or "from-depth"),
    /// `tilt_tolerance` (1 degree), `depth_sigma` (0.01 m), `depth_weight` (1),
    /// `occlusion` (0.02 m), `light` ((0, 0, -1)), `ambient` (0.2). `progress(iterations
    /// done, iterations)` is called after each chunk of iterations where given.
    #[pyo3(signature = (space, mask, K, size, pose, *, depth=None, shading=None, ignore=None, views=None, progress=None, **options))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn register<'py>(
        &self,
        py: Python<'py>,
        space: &Bound<'py, ShapeSpace>,
        mask: &Bound<'py, PyAny>,
        K: &Bound<'py, PyAny>,
        size: &Bound<'_, PyAny>,
        pose: &Bound<'py, PyAny>,
        depth: Option<&Bound<'py, PyAny>>,
        shading: Option<&Bound<'py, PyAny>>,
        ignore: Option<&Bound<'py, PyAny>>,
        views: Option<&Bound<'py, PyList>>,
        progress: Option<Py<PyAny>>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Registration> {
        let options = Options::read(options)?;
        let camera = crate::camera(K, crate::size(size, "size")?)?;
        let view = View {
            camera,
            pose: crate::pose(pose, "pose")?,
        };
        let further = views.map(further_views).transpose()?.unwrap_or_default();
        let space = space.get().inner.clone();
        let options = options.for_space(&space);
        let looks = Looks::read_views(
            mask,
            depth,
            shading,
            ignore,
            camera,
            further,
            options.depth,
            options.shading,
        )?;
        let progress = Progress::new(progress);
        let result = py.detach(|| {
            self.engine.run(|ctx, parts| {
                let plan = options.plan(&looks, view.pose)?;
                let total = plan.params.total_iterations();
                parts.registrar(ctx)?.register_observation(
                    ctx,
                    &space,
                    &looks.observation,
                    &plan,
                    |done, _| progress.call(done, total),
                )
            })
        });
        let result = progress.finish(result)?;
        Ok(Registration::new(&space, result))
    }

    /// Registers `space` to many observations in one call: `masks` (N, H, W) from `poses`
    /// (N, 6), with `depths` (N, H, W) where given, through one camera `K` at `size`; the
    /// options are `register`'s. With one start per observation they run together (one
    /// submission per chunk of iterations); with several, one after the other. Returns a
    /// list of `vkdr.Registration`.
    #[pyo3(signature = (space, masks, K, size, poses, *, depths=None, progress=None, **options))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn register_batch<'py>(
        &self,
        py: Python<'py>,
        space: &Bound<'py, ShapeSpace>,
        masks: &Bound<'py, PyAny>,
        K: &Bound<'py, PyAny>,
        size: &Bound<'_, PyAny>,
        poses: &Bound<'py, PyAny>,
        depths: Option<&Bound<'py, PyAny>>,
        progress: Option<Py<PyAny>>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Vec<Registration>> {
        let options = Options::read(options)?;
        let camera = crate::camera(K, crate::size(size, "size")?)?;
        let (poses, _) = crate::poses(poses, "poses")?;
        let n = poses.len();
        let wh = (camera.width, camera.height);
        let pixels = (camera.width * camera.height) as usize;
        let masks = arrays::mask(masks, "masks", wh, Some(n))?;
        let depths = depths
            .map(|d| arrays::image(d, "depths", wh, Some(n)))
            .transpose()?;
        let space = space.get().inner.clone();
        let options = options.for_space(&space);
        let looks: Vec<Looks> = (0..n)
            .map(|k| {
                let part = |all: &[f32]| all[k * pixels..(k + 1) * pixels].to_vec();
                let images = ViewImages {
                    mask: part(&masks),
                    depth: depths.as_deref().map(part),
                    ..Default::default()
                };
                Looks::new(camera, images, options.depth, options.shading)
            })
            .collect::<PyResult<_>>()?;
        let progress = Progress::new(progress);
        let results = py.detach(|| {
            self.engine.run(|ctx, parts| {
                let registrar = parts.registrar(ctx)?;
                let plans = looks
                    .iter()
                    .zip(&poses)
                    .map(|(look, &pose)| options.plan(look, pose))
                    .collect::<vkdr::Result<Vec<Plan>>>()?;
                let total = plans[0].params.total_iterations();
                if plans[0].starts == 1 {
                    let jobs: Vec<Job> = looks
                        .iter()
                        .zip(&plans)
                        .map(|(look, plan)| Job {
                            gravity: plan.gravity,
                            ..look.observation.job(&space, plan.start)
                        })
                        .collect();
                    return registrar.register_batch(ctx, &jobs, &plans[0].params, |done, _| {
                        progress.call(done, total)
                    });
                }
                // One observation after the other: the iterations of all of them.
                let all = total * looks.len();
                looks
                    .iter()
                    .zip(&plans)
                    .enumerate()
                    .map(|(k, (look, plan))| {
                        registrar.register_observation(
                            ctx,
                            &space,
                            &look.observation,
                            plan,
                            |done, _| progress.call(k * total + done, all),
                        )
                    })
                    .collect()
            })
        });
        let results = progress.finish(results)?;
        Ok(results
            .into_iter()
            .map(|r| Registration::new(&space, r))
            .collect())
    }
}

/// The G-buffer of the mesh (`vertices`, `faces`) seen through `K` at `size` from each of
/// `poses` (one (6,) or several (N, 6)), and the shape of its per-pixel arrays: (H, W), or
/// (N, H, W) for several poses.
fn render_poses(
    device: &Device,
    py: Python<'_>,
    (vertices, faces): (&Bound<'_, PyAny>, &Bound<'_, PyAny>),
    (k, size): (&Bound<'_, PyAny>, &Bound<'_, PyAny>),
    poses: &Bound<'_, PyAny>,
    outputs: Outputs,
) -> PyResult<(GbufferData, Vec<usize>)> {
    let mesh = crate::mesh(vertices, faces)?;
    let camera = crate::camera(k, crate::size(size, "size")?)?;
    let (poses, batched) = crate::poses(poses, "poses")?;
    let views: Vec<View> = poses.iter().map(|&pose| View { camera, pose }).collect();
    let g = py.detach(|| {
        device.engine.run(|ctx, parts| {
            parts
                .registrar(ctx)?
                .renderer()
                .rasterizer()
                .render(ctx, &mesh, &views, outputs)
        })
    })?;
    let (h, w) = (camera.height as usize, camera.width as usize);
    let shape = if batched {
        vec![views.len(), h, w]
    } else {
        vec![h, w]
    };
    Ok((g, shape))
}

/// An array's elements in order, without a copy where they are its buffer's first ones (a
/// batch's G-buffer is 157 MB for 32 views of 640 x 480: a copy into fresh memory cost more
/// than drawing it).
fn into_vec<A: Clone, D: numpy::ndarray::Dimension>(a: numpy::ndarray::Array<A, D>) -> Vec<A> {
    let n = a.len();
    if a.is_standard_layout() {
        let (mut v, offset) = a.into_raw_vec_and_offset();
        if offset.unwrap_or(0) == 0 && v.len() >= n {
            v.truncate(n);
            return v;
        }
        return v.into_iter().skip(offset.unwrap_or(0)).take(n).collect();
    }
    a.iter().cloned().collect()
}

/// dL/d(pose numbers) from the engine's pose gradient: dL/dt, and dL/dd for a rotation
/// increment d on the left (`x_camera = exp([d]x) R x + t`). With R = exp([r]x), a change
/// dr of the axis-angle moves it by d = J(r) dr, J the left Jacobian of SO(3):
/// I + (1 - cos a)/a^2 [r]x + (a - sin a)/a^3 [r]x^2, a = |r|; so dL/dr = J^T dL/dd.
fn pose_gradient(pose: &vkdr::Pose, g: &[f32; 6]) -> Vec<f64> {
    let r = pose.rotation;
    let a2 = r.length_squared();
    let a = a2.sqrt();
    let (c1, c2) = if a < 1e-4 {
        (0.5 - a2 / 24.0, 1.0 / 6.0 - a2 / 120.0)
    } else {
        ((1.0 - a.cos()) / a2, (a - a.sin()) / (a2 * a))
    };
    let k = DMat3::from_cols(
        DVec3::new(0.0, r.z, -r.y),
        DVec3::new(-r.z, 0.0, r.x),
        DVec3::new(r.y, -r.x, 0.0),
    );
    let jacobian = DMat3::IDENTITY + k * c1 + k * k * c2;
    let d = DVec3::new(g[3] as f64, g[4] as f64, g[5] as f64);
    let dr = jacobian.transpose() * d;
    vec![g[0] as f64, g[1] as f64, g[2] as f64, dr.x, dr.y, dr.z]
}
