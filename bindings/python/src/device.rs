//! `vkdr.Device`: one Vulkan device and the engine's pipelines on it (built on first use),
//! with the rasterizer, the exact loss gradients and the registration.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use glam::{DMat3, DVec3};
use pyo3::exceptions::{PyRuntimeError, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use vkdr::cpd::CpdPipelines;
use vkdr::diff::{DepthLoss, ObservedDepth, Scene, SceneDesc, Shading};
use vkdr::gpu::{Context, ContextOptions};
use vkdr::loss::{self, Loss};
use vkdr::raster::{Outputs, View};
use vkdr::register::{self, Gravity, Job, Optimizer, OtherView, RegisterParams, Registrar};

use crate::arrays::{self, array, bad};
use crate::space::{Registration, ShapeSpace};
use crate::{OrPy, Progress};

/// A device and the pipelines built on it so far. Its work runs one call at a time (a
/// queue takes one submission at a time; two Python threads calling at once wait in turn,
/// with the GIL released).
pub struct Engine {
    ctx: Context,
    parts: Mutex<Parts>,
    engine_ms: Mutex<f64>,
    /// The process that made it: a Vulkan device does not survive a fork.
    pid: u32,
}

/// The pipelines, each built when a call first needs it.
#[derive(Default)]
pub struct Parts {
    registrar: Option<Registrar>,
    cpd: Option<CpdPipelines>,
}

impl Parts {
    /// The registration pipelines (they hold the differentiable renderer and the
    /// rasterizer).
    pub fn registrar(&mut self, ctx: &Context) -> vkdr::Result<&Registrar> {
        if self.registrar.is_none() {
            self.registrar = Some(Registrar::new(ctx)?);
        }
        Ok(self.registrar.as_ref().expect("built above"))
    }

    /// CPD's pipelines.
    pub fn cpd(&mut self, ctx: &Context) -> vkdr::Result<&CpdPipelines> {
        if self.cpd.is_none() {
            self.cpd = Some(CpdPipelines::new(ctx)?);
        }
        Ok(self.cpd.as_ref().expect("built above"))
    }
}

impl Engine {
    fn new(name: Option<String>, validation: bool) -> vkdr::Result<Self> {
        let mut options = ContextOptions::default();
        options.validation |= validation;
        if name.is_some() {
            options.device = name;
        }
        Ok(Self {
            ctx: Context::with_options(options)?,
            parts: Mutex::new(Parts::default()),
            engine_ms: Mutex::new(0.0),
            pid: std::process::id(),
        })
    }

    /// Whether this process made the engine (not a child forked after it was made).
    fn is_ours(&self) -> bool {
        self.pid == std::process::id()
    }

    /// Runs `work` on the device, after any other call's, and keeps its wall time.
    pub fn run<T>(
        &self,
        work: impl FnOnce(&Context, &mut Parts) -> vkdr::Result<T>,
    ) -> PyResult<T> {
        if !self.is_ours() {
            return Err(PyRuntimeError::new_err(format!(
                "this Device was made in process {} and cannot be used in a forked child \
                 (process {}): make a vkdr.Device() in the child (a DataLoader's \
                 worker_init_fn), or start workers with the 'spawn' method",
                self.pid,
                std::process::id()
            )));
        }
        let mut parts = self
            .parts
            .lock()
            .map_err(|_| PyRuntimeError::new_err("an earlier call on this device panicked"))?;
        let start = Instant::now();
        let result = work(&self.ctx, &mut parts);
        if let Ok(mut ms) = self.engine_ms.lock() {
            *ms = start.elapsed().as_secs_f64() * 1e3;
        }
        result.py()
    }
}

/// The engine of calls given no device: the best device, made on first use.
static DEFAULT: Mutex<Option<Arc<Engine>>> = Mutex::new(None);

/// `device`'s engine, or the default one.
pub fn engine_of(py: Python<'_>, device: Option<&Bound<'_, Device>>) -> PyResult<Arc<Engine>> {
    if let Some(device) = device {
        return Ok(device.get().engine.clone());
    }
    py.detach(|| {
        let mut default = DEFAULT
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the default device failed to start"))?;
        // A forked child makes its own (the parent's is left alone: its Vulkan objects
        // are the parent's, not the child's to destroy).
        if let Some(inherited) = default.take_if(|engine| !engine.is_ours()) {
            std::mem::forget(inherited);
        }
        if default.is_none() {
            *default = Some(Arc::new(Engine::new(None, false).py()?));
        }
        Ok(default.as_ref().expect("made above").clone())
    })
}

/// The device of calls given none (`vkdr.cpd`, `vkdr.ShapeSpace.build`,
/// `vkdr.torch.silhouette_loss`): the best device, made on first use and shared.
#[pyfunction]
pub fn default_device(py: Python<'_>) -> PyResult<Device> {
    Ok(Device {
        engine: engine_of(py, None)?,
    })
}

/// A Vulkan device: `Device()` picks the best (a discrete GPU first; `VKDR_DEVICE` or
/// `name`, an index or part of a name, chooses another). `validation=True` turns on the
/// Khronos validation layer.
#[pyclass(module = "vkdr", frozen)]
pub struct Device {
    pub engine: Arc<Engine>,
}

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
        let mesh = crate::mesh(vertices, faces)?;
        let camera = crate::camera(K, crate::size(size, "size")?)?;
        let (poses, batched) = crate::poses(poses, "poses")?;
        let views: Vec<View> = poses.iter().map(|&pose| View { camera, pose }).collect();
        let g = py.detach(|| {
            self.engine.run(|ctx, parts| {
                parts.registrar(ctx)?.renderer().rasterizer().render(
                    ctx,
                    &mesh,
                    &views,
                    Outputs::IdsBaryDepth,
                )
            })
        })?;
        let (h, w) = (camera.height as usize, camera.width as usize);
        let mut shape = vec![views.len(), h, w];
        if !batched {
            shape.remove(0);
        }
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
        let mesh = crate::mesh(vertices, faces)?;
        let camera = crate::camera(K, crate::size(size, "size")?)?;
        let (poses, batched) = crate::poses(poses, "poses")?;
        let views: Vec<View> = poses.iter().map(|&pose| View { camera, pose }).collect();
        let g = py.detach(|| {
            self.engine.run(|ctx, parts| {
                parts.registrar(ctx)?.renderer().rasterizer().render(
                    ctx,
                    &mesh,
                    &views,
                    Outputs::Ids,
                )
            })
        })?;
        let (h, w) = (camera.height as usize, camera.width as usize);
        let shape = if batched {
            vec![views.len(), h, w]
        } else {
            vec![h, w]
        };
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
        let wh = (camera.width, camera.height);
        let loss: Loss = loss.parse().map_err(|e| bad("loss", e))?;
        let looks = Looks::read(
            mask,
            depth,
            shading,
            ignore,
            wh,
            1,
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
                    depth: looks.depth.as_deref().map(|depth| ObservedDepth {
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
        let others: Vec<OtherView> = further.iter().map(|f| f.other).collect();
        let looks = Looks::read_views(mask, depth, shading, ignore, camera, &further, &options)?;
        let space = space.get().inner.clone();
        let options = options.for_space(&space);
        let progress = Progress::new(progress);
        let result = py.detach(|| {
            self.engine.run(|ctx, parts| {
                let job = options.job(&space, &looks, view, &others)?;
                let params = options.params(&looks, camera, !others.is_empty())?;
                let starts = options.starts(view)?;
                let total = params.total_iterations();
                parts.registrar(ctx)?.register_starts(
                    ctx,
                    job,
                    register::Starts::for_params(&starts, &params),
                    &params,
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
        let looks: Vec<Looks> = (0..n)
            .map(|k| {
                let part = |all: &[f32]| all[k * pixels..(k + 1) * pixels].to_vec();
                let depth = depths.as_deref().map(part);
                Looks::assemble(
                    part(&masks),
                    depth,
                    None,
                    None,
                    options.depth,
                    options.shading,
                )
            })
            .collect::<PyResult<_>>()?;
        let space = space.get().inner.clone();
        let options = options.for_space(&space);
        let progress = Progress::new(progress);
        let results = py.detach(|| {
            self.engine.run(|ctx, parts| {
                let registrar = parts.registrar(ctx)?;
                let params = options.params(&looks[0], camera, false)?;
                let jobs = looks
                    .iter()
                    .zip(&poses)
                    .map(|(look, &pose)| options.job(&space, look, View { camera, pose }, &[]))
                    .collect::<vkdr::Result<Vec<Job>>>()?;
                let total = params.total_iterations();
                if options.start_count()? == 1 {
                    return registrar
                        .register_batch(ctx, &jobs, &params, |done, _| progress.call(done, total));
                }
                // One observation after the other: the iterations of all of them.
                let all = total * jobs.len();
                jobs.iter()
                    .enumerate()
                    .map(|(k, job)| {
                        let starts = options.starts(job.view)?;
                        registrar.register_starts(
                            ctx,
                            *job,
                            register::Starts::for_params(&starts, &params),
                            &params,
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

/// dL/d(pose numbers) from the engine's pose gradient: dL/dt, and dL/dd for a rotation
/// increment d on the left (`x_camera = exp([d]x) R x + t`). With R = exp([r]x), a change
/// dr of the axis-angle moves it by d = J(r) dr, J the left Jacobian of SO(3):
/// I + (1 - cos a)/a^2 [r]x + (a - sin a)/a^3 [r]x^2, a = |r|; so dL/dr = J^T dL/dd.
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

/// A further camera of `views`, with its images.
struct FurtherView {
    other: OtherView,
    mask: Vec<f32>,
    depth: Option<Vec<f32>>,
    shading: Option<Vec<f32>>,
}

/// The further views from a list of dicts (`K`, `size`, `from_first`, `mask`, and
/// optionally `depth` and `shading`).
fn further_views(list: &Bound<'_, PyList>) -> PyResult<Vec<FurtherView>> {
    list.iter()
        .enumerate()
        .map(|(k, item)| {
            let name = format!("views[{k}]");
            let dict = item
                .cast::<PyDict>()
                .map_err(|_| bad(&name, "expected a dict with K, size, from_first, mask"))?;
            let get = |key: &str| -> PyResult<Bound<'_, PyAny>> {
                dict.get_item(key)?
                    .ok_or_else(|| bad(&name, format!("has no \"{key}\"")))
            };
            let size = crate::size(&get("size")?, &format!("{name}[\"size\"]"))?;
            let camera = crate::camera(&get("K")?, size)?;
            let from_first = crate::pose(&get("from_first")?, &format!("{name}[\"from_first\"]"))?;
            let wh = (camera.width, camera.height);
            let image = |key: &str| -> PyResult<Option<Vec<f32>>> {
                match dict.get_item(key)? {
                    None => Ok(None),
                    Some(v) if v.is_none() => Ok(None),
                    Some(v) => arrays::image(&v, &format!("{name}[\"{key}\"]"), wh, None).map(Some),
                }
            };
            Ok(FurtherView {
                other: OtherView { camera, from_first },
                mask: image("mask")?
                    .map(|m| {
                        m.into_iter()
                            .map(|v| if v > 0.0 { 1.0 } else { 0.0 })
                            .collect()
                    })
                    .ok_or_else(|| bad(&name, "has no \"mask\""))?,
                depth: image("depth")?,
                shading: image("shading")?,
            })
        })
        .collect()
}

/// How the depth is compared, where given (None: the engine's default).
#[derive(Clone, Copy)]
struct DepthOptions {
    sigma: Option<f64>,
    weight: Option<f64>,
    occlusion: Option<f64>,
}

impl DepthOptions {
    fn loss(&self) -> PyResult<DepthLoss> {
        let default = DepthLoss::default();
        let loss = DepthLoss {
            scale: self.sigma.unwrap_or(default.scale),
            weight: self.weight.unwrap_or(default.weight),
            occlusion: self.occlusion.unwrap_or(default.occlusion),
        };
        loss.validate()
            .map_err(|e| bad("depth_sigma, depth_weight or occlusion", e))?;
        Ok(loss)
    }
}

/// The shading model from `light` and `ambient` (None: the engine's default).
fn shading_model((light, ambient): (Option<[f64; 3]>, Option<f64>)) -> PyResult<Shading> {
    let default = Shading::default();
    let shading = Shading {
        light: light.unwrap_or(default.light),
        ambient: ambient.unwrap_or(default.ambient),
    };
    shading
        .unit_light()
        .map_err(|e| bad("light or ambient", e))?;
    Ok(shading)
}

/// What is observed, in the engine's layout (`[view][row][column]`): the mask with unknown
/// pixels marked, and the depth and shading where given.
struct Looks {
    mask: Vec<f32>,
    depth: Option<Vec<f32>>,
    depth_loss: DepthLoss,
    shaded: Option<Vec<f32>>,
    shading: Option<Shading>,
}

impl Looks {
    /// One view's images from their arguments.
    #[allow(clippy::too_many_arguments)]
    fn read(
        mask: &Bound<'_, PyAny>,
        depth: Option<&Bound<'_, PyAny>>,
        shading: Option<&Bound<'_, PyAny>>,
        ignore: Option<&Bound<'_, PyAny>>,
        wh: (u32, u32),
        views: usize,
        depth_options: DepthOptions,
        shading_options: (Option<[f64; 3]>, Option<f64>),
    ) -> PyResult<Self> {
        let image = |obj: Option<&Bound<'_, PyAny>>, name: &str| {
            obj.map(|o| arrays::image(o, name, wh, Some(views)))
                .transpose()
        };
        let mask = arrays::mask(mask, "mask", wh, Some(views))?;
        let depth = image(depth, "depth")?;
        let shaded = image(shading, "shading")?;
        let ignore = image(ignore, "ignore")?;
        Self::assemble(mask, depth, shaded, ignore, depth_options, shading_options)
    }

    /// The images of the first view and `further`'s (the ignore mask applies to the first).
    fn read_views(
        mask: &Bound<'_, PyAny>,
        depth: Option<&Bound<'_, PyAny>>,
        shading: Option<&Bound<'_, PyAny>>,
        ignore: Option<&Bound<'_, PyAny>>,
        camera: vkdr::Camera,
        further: &[FurtherView],
        options: &Options,
    ) -> PyResult<Self> {
        let mut first = Self::read(
            mask,
            depth,
            shading,
            ignore,
            (camera.width, camera.height),
            1,
            options.depth,
            options.shading,
        )?;
        if further.is_empty() {
            return Ok(first);
        }
        let pixels = first.mask.len();
        for (k, view) in further.iter().enumerate() {
            if view.mask.len() != pixels {
                return Err(bad(
                    &format!("views[{k}]"),
                    "every view needs the first view's image size",
                ));
            }
            first.mask.extend(&view.mask);
            if let Some(all) = first.depth.as_mut() {
                all.extend(view.depth.clone().unwrap_or_else(|| vec![0.0; pixels]));
            }
            if let Some(all) = first.shaded.as_mut() {
                let shaded = view.shading.as_ref().ok_or_else(|| {
                    bad(
                        &format!("views[{k}]"),
                        "has no \"shading\" (the first view has)",
                    )
                })?;
                all.extend(off_mask_black(shaded, &view.mask));
            }
        }
        Ok(first)
    }

    /// The observation of images in the engine's layout: the ignore mask marks pixels
    /// unknown, the shading is background off the mask.
    fn assemble(
        mut mask: Vec<f32>,
        depth: Option<Vec<f32>>,
        shaded: Option<Vec<f32>>,
        ignore: Option<Vec<f32>>,
        depth_options: DepthOptions,
        shading_options: (Option<[f64; 3]>, Option<f64>),
    ) -> PyResult<Self> {
        // Pixels the mask shows as background are background in the shading too.
        let mut shaded = shaded.map(|s| off_mask_black(&s, &mask));
        if let Some(ignore) = ignore {
            // Only pixels the mask does not show as object become unknown: BOP's whole
            // `mask` works as it is, as with `vkdr register --ignore`.
            let hidden = loss::hidden_pixels(&mask, &ignore).py()?;
            loss::mark_unknown(&mut mask, 1, &hidden).py()?;
            if let Some(shaded) = shaded.as_mut() {
                loss::mark_unknown(shaded, 1, &hidden).py()?;
            }
        }
        let shading = shaded
            .is_some()
            .then(|| shading_model(shading_options))
            .transpose()?;
        Ok(Self {
            mask,
            depth,
            depth_loss: depth_options.loss()?,
            shaded,
            shading,
        })
    }

    /// The image compared: the shading where given, else the mask.
    fn compared(&self) -> &[f32] {
        self.shaded.as_deref().unwrap_or(&self.mask)
    }
}

/// `shaded` with the pixels `mask` shows as background set to 0 (as `vkdr register` reads
/// its shading image); unknown pixels stay unknown.
fn off_mask_black(shaded: &[f32], mask: &[f32]) -> Vec<f32> {
    shaded
        .iter()
        .zip(mask)
        .map(|(&s, &m)| if m == 0.0 { 0.0 } else { s })
        .collect()
}

/// The registration options of `register` and `register_batch`.
struct Options {
    optimize_pose: bool,
    optimize_scale: bool,
    iterations: Option<usize>,
    loss: Loss,
    optimizer: Option<Optimizer>,
    code_prior: Option<f64>,
    starts: Option<usize>,
    /// The object's up axis: as given, else the shape space's ([`Options::for_space`]).
    up: DVec3,
    up_given: bool,
    gravity: Option<GravityOption>,
    tilt_tolerance: f64,
    depth: DepthOptions,
    shading: (Option<[f64; 3]>, Option<f64>),
}

/// Which way is up in the camera frame.
enum GravityOption {
    Direction(DVec3),
    FromDepth,
}

impl Options {
    /// The options from `register`'s keyword arguments; a `TypeError` names one it does
    /// not know.
    fn read(kwargs: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        let mut options = Self {
            optimize_pose: false,
            optimize_scale: false,
            iterations: None,
            loss: Loss::Mse,
            optimizer: None,
            code_prior: None,
            starts: None,
            up: DVec3::Y,
            up_given: false,
            gravity: None,
            tilt_tolerance: 1.0,
            depth: DepthOptions {
                sigma: None,
                weight: None,
                occlusion: None,
            },
            shading: (None, None),
        };
        let Some(kwargs) = kwargs else {
            return Ok(options);
        };
        for (key, value) in kwargs.iter() {
            let key: String = key.extract()?;
            let name = key.as_str();
            let wrong = |what: &str| bad(name, format!("expected {what}, got {value}"));
            macro_rules! get {
                ($what:expr) => {
                    value.extract().map_err(|_| wrong($what))?
                };
            }
            match name {
                "optimize_pose" => options.optimize_pose = get!("True or False"),
                "optimize_scale" => options.optimize_scale = get!("True or False"),
                "iterations" => options.iterations = get!("a count of iterations"),
                "loss" => {
                    let text: String = get!("\"mse\", \"iou\" or \"distance\"");
                    options.loss = text.parse().map_err(|e| bad(name, e))?;
                }
                "optimizer" => {
                    let text: Option<String> = get!("\"bfgs\", \"sgd\" or \"adam\"");
                    options.optimizer = text
                        .map(|t| t.parse())
                        .transpose()
                        .map_err(|e| bad(name, e))?;
                }
                "code_prior" => {
                    options.code_prior = if value.extract::<String>().is_ok_and(|s| s == "auto") {
                        None
                    } else {
                        let w: f64 = get!("\"auto\" or a weight in [0, 1]");
                        Some(w)
                    }
                }
                "starts" => options.starts = get!("a count of starts, 1 to 8"),
                "up" => {
                    options.up = DVec3::from_array(get!("(x, y, z)"));
                    options.up_given = true;
                }
                "gravity" => {
                    options.gravity = if value.is_none() {
                        None
                    } else if value.extract::<String>().is_ok_and(|s| s == "from-depth") {
                        Some(GravityOption::FromDepth)
                    } else {
                        let d: [f64; 3] = get!("None, (x, y, z) or \"from-depth\"");
                        Some(GravityOption::Direction(DVec3::from_array(d)))
                    }
                }
                "tilt_tolerance" => options.tilt_tolerance = get!("degrees"),
                "depth_sigma" => options.depth.sigma = get!("metres"),
                "depth_weight" => options.depth.weight = get!("a weight"),
                "occlusion" => options.depth.occlusion = get!("metres"),
                "light" => options.shading.0 = get!("(x, y, z)"),
                "ambient" => options.shading.1 = get!("a number in [0, 1)"),
                other => {
                    return Err(PyTypeError::new_err(format!(
                        "register got an unexpected keyword argument '{other}'"
                    )))
                }
            }
        }
        if !(options.up.is_finite() && options.up.length() > 0.0) {
            return Err(bad("up", "must be a nonzero direction (x, y, z)"));
        }
        let starts = options.start_count().map_err(crate::py_error)?;
        if starts > 1 && !options.optimize_pose {
            return Err(bad(
                "starts",
                "turns the starting pose: give optimize_pose=True too",
            ));
        }
        Ok(options)
    }

    /// The options for registrations of `space`: its category's up axis where `up` was not
    /// given (y for a space that carries none).
    fn for_space(self, space: &vkdr::shape::ShapeSpace) -> Self {
        match self.up_given {
            true => self,
            false => Self {
                up: space.up_or_y().0,
                ..self
            },
        }
    }

    /// Starts: as given, else [`register::DEFAULT_STARTS`] with the pose free and 1 with
    /// it known.
    fn start_count(&self) -> vkdr::Result<usize> {
        let count = self.starts.unwrap_or(if self.optimize_pose {
            register::DEFAULT_STARTS
        } else {
            1
        });
        register::check_starts(count)?;
        Ok(count)
    }

    /// The starting poses: `view`'s pose turned about the up axis.
    fn starts(&self, view: View) -> vkdr::Result<Vec<vkdr::Pose>> {
        Ok(register::turned_starts(
            view.pose,
            self.up,
            self.start_count()?,
            register::START_TURN,
        ))
    }

    /// The parameters `vkdr register` would use for these observations.
    fn params(
        &self,
        looks: &Looks,
        camera: vkdr::Camera,
        several_views: bool,
    ) -> vkdr::Result<RegisterParams> {
        let pixels = (camera.width * camera.height) as usize;
        let base = if self.optimize_pose {
            RegisterParams::free_pose(pixels)
        } else {
            RegisterParams::known_pose(pixels)
        };
        let observes_z = looks.depth.is_some() || several_views;
        let code_prior = match self.code_prior {
            None => register::observation_prior(pixels),
            Some(w) if w.is_finite() && (0.0..=1.0).contains(&w) => w,
            Some(w) => {
                return Err(vkdr::Error::InvalidInput(format!(
                    "code_prior: must be \"auto\" or a weight in [0, 1], not {w}"
                )))
            }
        };
        let params = RegisterParams {
            iterations: self.iterations.unwrap_or(base.iterations),
            loss: self.loss,
            optimizer: self.optimizer.unwrap_or(base.optimizer),
            shading: looks.shading,
            depth: looks.depth.is_some().then_some(looks.depth_loss),
            optimize_z: base.optimize_z || (self.optimize_pose && observes_z),
            code_prior,
            optimize_scale: self.optimize_scale,
            ..base
        };
        params.validate()?;
        Ok(params)
    }

    /// The job of `looks` seen through `view` (and `others`), with gravity where asked.
    fn job<'a>(
        &self,
        space: &'a vkdr::shape::ShapeSpace,
        looks: &'a Looks,
        view: View,
        others: &'a [OtherView],
    ) -> vkdr::Result<Job<'a>> {
        let direction = match &self.gravity {
            None => None,
            Some(GravityOption::Direction(d)) => Some(*d),
            Some(GravityOption::FromDepth) => {
                let Some(depth) = &looks.depth else {
                    return Err(vkdr::Error::InvalidInput(
                        "gravity=\"from-depth\" needs the observed depth".into(),
                    ));
                };
                let n = (view.camera.width * view.camera.height) as usize;
                let mask: Vec<f32> = looks.mask[..n].iter().map(|&m| m.max(0.0)).collect();
                let plane =
                    vkdr::support::fit_support_plane(&view.camera, &depth[..n], &mask, 0.5)?;
                Some(plane.normal)
            }
        };
        let gravity = direction
            .map(|direction| {
                let gravity = Gravity {
                    up: self.up,
                    direction,
                    tolerance: self.tilt_tolerance.to_radians(),
                };
                gravity.validate().map(|_| gravity)
            })
            .transpose()?;
        Ok(Job {
            shaded: looks.shaded.as_deref(),
            depth: looks.depth.as_deref(),
            others,
            gravity,
            ..Job::new(space, &looks.mask, view)
        })
    }
}
