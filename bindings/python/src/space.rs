//! `vkdr.ShapeSpace`, `vkdr.Registration`, `vkdr.cpd` and `vkdr.load_mesh`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::DVec3;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyList};

use vkdr::cpd::CpdParams;
use vkdr::Mesh;

use crate::arrays::{self, array, bad};
use crate::engine::{engine_of, Device};
use crate::{OrPy, Progress};

/// Points from an (N, 3) float array.
fn points(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<DVec3>> {
    let values = arrays::floats(obj, name)?.expect(name, &[None, Some(3)], "(N, 3)")?;
    if values.shape[0] == 0 {
        return Err(bad(name, "no points"));
    }
    Ok(values
        .data
        .chunks_exact(3)
        .map(|p| DVec3::new(p[0], p[1], p[2]))
        .collect())
}

/// Points as an (N, 3) float64 array.
fn point_array<'py>(py: Python<'py>, points: &[DVec3]) -> PyResult<Bound<'py, PyAny>> {
    let data = points.iter().flat_map(|p| p.to_array()).collect();
    Ok(array(py, data, &[points.len(), 3])?.into_any())
}

/// A mesh's faces as an (F, 3) uint32 array.
fn face_array<'py>(py: Python<'py>, mesh: &Mesh) -> PyResult<Bound<'py, PyAny>> {
    let data = mesh.triangles().iter().flatten().copied().collect();
    Ok(array::<u32>(py, data, &[mesh.triangle_count(), 3])?.into_any())
}

/// CPD's parameters: the engine's defaults where a value is None.
fn cpd_params(
    beta: Option<f64>,
    lam: Option<f64>,
    w: Option<f64>,
    max_iterations: Option<usize>,
    tolerance: Option<f64>,
) -> PyResult<CpdParams> {
    let default = CpdParams::default();
    let params = CpdParams {
        beta: beta.unwrap_or(default.beta),
        lambda: lam.unwrap_or(default.lambda),
        w: w.unwrap_or(default.w),
        max_iterations: max_iterations.unwrap_or(default.max_iterations),
        tolerance: tolerance.unwrap_or(default.tolerance),
        ..default
    };
    params
        .validate()
        .map_err(|e| bad("beta, lam, w, max_iterations or tolerance", e))?;
    Ok(params)
}

/// Non-rigid Coherent Point Drift of `source` (M x 3) onto `target` (N x 3), the E-step
/// and kernel products on the device. `beta` is the kernel width in units of the source's
/// RMS radius, `lam` the smoothness weight, `w` the outlier weight (defaults: the
/// engine's, as `vkdr cpd`). `progress(iteration, max_iterations)` is called each
/// iteration where given. Returns `(deformed, W, log)`: the moved source points
/// (M x 3, float64), the coefficients W (deformed = source + G W) and a dict (iterations,
/// converged, stop, seconds, sigma2, ...).
#[pyfunction]
#[pyo3(signature = (source, target, beta=None, lam=None, w=None, max_iterations=None, tolerance=None, device=None, progress=None))]
#[allow(clippy::too_many_arguments)]
pub fn cpd<'py>(
    py: Python<'py>,
    source: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    beta: Option<f64>,
    lam: Option<f64>,
    w: Option<f64>,
    max_iterations: Option<usize>,
    tolerance: Option<f64>,
    device: Option<&Bound<'py, Device>>,
    progress: Option<Py<PyAny>>,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyDict>)> {
    let params = cpd_params(beta, lam, w, max_iterations, tolerance)?;
    let y = points(source, "source")?;
    let x = points(target, "target")?;
    let engine = engine_of(py, device)?;
    let progress = Progress::new(progress);
    let result = py.detach(|| {
        engine.run(|ctx, parts| {
            let total = params.max_iterations;
            vkdr::cpd::register(ctx, parts.cpd(ctx)?, &y, &x, &params, &mut |i, _| {
                // CPD runs to its end (its iterations are one submission each).
                let _ = progress.call(i, total);
            })
        })
    });
    let result = progress.finish(result)?;
    let log = PyDict::new(py);
    log.set_item("iterations", result.iterations)?;
    log.set_item("converged", result.stop.converged())?;
    log.set_item("stop", format!("{:?}", result.stop))?;
    log.set_item("seconds", result.seconds)?;
    log.set_item("kernel_products", result.products)?;
    log.set_item("jumps", result.jumps)?;
    log.set_item("sigma2", result.sigma2.clone())?;
    Ok((
        point_array(py, &result.deformed)?,
        point_array(py, &result.w)?,
        log,
    ))
}

/// Reads a mesh (OBJ, or PLY as BOP ships its models). Returns `(vertices, faces)`:
/// (V, 3) float32 in the file's order and (F, 3) uint32.
#[pyfunction]
pub fn load_mesh(py: Python<'_>, path: PathBuf) -> PyResult<(Bound<'_, PyAny>, Bound<'_, PyAny>)> {
    let mesh = py.detach(|| Mesh::load(&path)).py()?;
    let data = mesh.positions().iter().flatten().copied().collect();
    let vertices = array::<f32>(py, data, &[mesh.vertex_count(), 3])?;
    Ok((vertices.into_any(), face_array(py, &mesh)?))
}

/// A category's latent shape space: a canonical mesh, its training instances registered
/// to it by CPD, and the PCA of the deformation fields. `vertices(code)` is the canonical
/// deformed by a code.
#[pyclass(module = "vkdr", frozen)]
pub struct ShapeSpace {
    pub inner: Arc<vkdr::shape::ShapeSpace>,
}

#[pymethods]
impl ShapeSpace {
    /// Builds a space from the canonical mesh (`vertices` V x 3, `faces` F x 3) and the
    /// training `instances` (a list of N_i x 3 point arrays, e.g. their vertices), with at
    /// most `dims` dimensions (never more than instances - 1). The CPD parameters are
    /// `vkdr.cpd`'s; `progress(instances done, instances)` is called as each is registered.
    /// `up` (3,) is the category's up axis, which `register` then uses by default (as
    /// `vkdr shape-space` takes it from the category's info.json).
    #[staticmethod]
    #[pyo3(signature = (vertices, faces, instances, dims=5, category="object", names=None, beta=None, lam=None, w=None, device=None, progress=None, up=None))]
    #[allow(clippy::too_many_arguments)]
    fn build(
        py: Python<'_>,
        vertices: &Bound<'_, PyAny>,
        faces: &Bound<'_, PyAny>,
        instances: &Bound<'_, PyList>,
        dims: usize,
        category: &str,
        names: Option<Vec<String>>,
        beta: Option<f64>,
        lam: Option<f64>,
        w: Option<f64>,
        device: Option<&Bound<'_, Device>>,
        progress: Option<Py<PyAny>>,
        up: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        if dims == 0 {
            return Err(bad("dims", "must be at least 1"));
        }
        let up = up
            .map(|u| -> PyResult<DVec3> {
                let values = arrays::floats(u, "up")?.expect("up", &[Some(3)], "(3,)")?;
                let up = DVec3::from_slice(&values.data);
                // Before the build (minutes for a large category), not after it.
                vkdr::shape::check_up(up).map_err(|e| bad("up", e))?;
                Ok(up)
            })
            .transpose()?;
        let params = cpd_params(beta, lam, w, None, None)?;
        let canonical = crate::mesh(vertices, faces)?;
        let names = names.unwrap_or_else(|| {
            (0..instances.len())
                .map(|k| format!("instance{k}"))
                .collect()
        });
        if names.len() != instances.len() {
            return Err(bad(
                "names",
                format!("{} names for {} instances", names.len(), instances.len()),
            ));
        }
        let training = instances
            .iter()
            .enumerate()
            .zip(names)
            .map(|((k, obj), name)| Ok((name, points(&obj, &format!("instances[{k}]"))?)))
            .collect::<PyResult<Vec<_>>>()?;
        let engine = engine_of(py, device)?;
        let progress = Progress::new(progress);
        let space = py.detach(|| {
            engine.run(|ctx, _| {
                vkdr::shape::ShapeSpace::build(
                    ctx,
                    category,
                    &canonical,
                    &training,
                    dims,
                    &params,
                    |done, total, _| {
                        let _ = progress.call(done, total);
                    },
                )
            })
        });
        let mut space = progress.finish(space)?;
        if let Some(up) = up {
            space = space.with_up(up).map_err(|e| bad("up", e))?;
        }
        Ok(Self {
            inner: Arc::new(space),
        })
    }

    /// Reads a space that `save` or `vkdr shape-space` wrote (.npz).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let space = py.detach(|| vkdr::shape::ShapeSpace::load(&path)).py()?;
        Ok(Self {
            inner: Arc::new(space),
        })
    }

    /// Writes the space (.npz, which alone is enough to load; and .npz.json, its
    /// description for people), as `vkdr shape-space` does.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach(|| self.inner.save(&path)).py()
    }

    /// The bytes of the space's .npz file, as `save` writes it.
    fn to_bytes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyBytes>> {
        let bytes = py.detach(|| self.inner.to_bytes()).py()?;
        Ok(PyBytes::new(py, &bytes))
    }

    /// A space from the bytes of its .npz file (`to_bytes`, or the file `save` wrote).
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &[u8]) -> PyResult<Self> {
        let bytes = data.to_vec();
        let space = py
            .detach(|| vkdr::shape::ShapeSpace::from_bytes(bytes, Path::new("<bytes>")))
            .py()?;
        Ok(Self {
            inner: Arc::new(space),
        })
    }

    /// Pickles as its .npz file's bytes.
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, (Bound<'py, PyBytes>,))> {
        let from_bytes = slf.get_type().getattr("from_bytes")?;
        Ok((from_bytes, (slf.get().to_bytes(slf.py())?,)))
    }

    /// The canonical mesh deformed by `code` (dims,): its vertices (V x 3, float64).
    fn vertices<'py>(
        &self,
        py: Python<'py>,
        code: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let code = arrays::floats(code, "code")?.expect(
            "code",
            &[Some(self.inner.dims())],
            &format!("({},)", self.inner.dims()),
        )?;
        point_array(py, &self.inner.vertices(&code.data).py()?)
    }

    /// `code` in training standard deviations (each dimension over its spread in the
    /// training set).
    fn code_in_deviations<'py>(
        &self,
        py: Python<'py>,
        code: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let dims = self.inner.dims();
        let code =
            arrays::floats(code, "code")?.expect("code", &[Some(dims)], &format!("({dims},)"))?;
        Ok(array(py, self.inner.code_in_deviations(&code.data), &[dims])?.into_any())
    }

    /// Latent dimensions.
    #[getter]
    fn dims(&self) -> usize {
        self.inner.dims()
    }

    /// The category's name.
    #[getter]
    fn category(&self) -> String {
        self.inner.category.clone()
    }

    /// The canonical mesh's vertices (V x 3, float32).
    #[getter]
    fn canonical<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let mesh = &self.inner.canonical;
        let data = mesh.positions().iter().flatten().copied().collect();
        Ok(array::<f32>(py, data, &[mesh.vertex_count(), 3])?.into_any())
    }

    /// The canonical mesh's faces (F x 3, uint32).
    #[getter]
    fn faces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        face_array(py, &self.inner.canonical)
    }

    /// The training instances' codes (T x dims).
    #[getter]
    fn training_codes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let codes = &self.inner.training_codes;
        let data = codes.iter().flatten().copied().collect();
        Ok(array::<f64>(py, data, &[codes.len(), self.inner.dims()])?.into_any())
    }

    /// The training instances' names.
    #[getter]
    fn training_names(&self) -> Vec<String> {
        self.inner.training_names.clone()
    }

    fn __repr__(&self) -> String {
        format!(
            "vkdr.ShapeSpace('{}', {} dims, {} vertices, {} training instances)",
            self.inner.category,
            self.inner.dims(),
            self.inner.canonical.vertex_count(),
            self.inner.training_codes.len()
        )
    }
}

/// The engine's stage names for pickled (name, count) pairs.
fn stages(pairs: Vec<(String, usize)>) -> PyResult<Vec<(&'static str, usize)>> {
    pairs
        .into_iter()
        .map(|(name, count)| {
            vkdr::register::STAGES
                .into_iter()
                .find(|s| *s == name)
                .map(|s| (s, count))
                .ok_or_else(|| bad("state", format!("unknown stage {name:?}")))
        })
        .collect()
}

/// What a registration found: `code` (dims,) and `code_sd` (in training standard
/// deviations), `pose` (6,), `vertices` (V x 3, the deformed canonical times `scale`, object
/// frame) and `faces`, `losses` before each iteration, `loss` (the objective at the
/// result), `iterations`, `milliseconds`, `scale`.
#[pyclass(module = "vkdr", frozen)]
pub struct Registration {
    result: vkdr::register::Registration,
    code_sd: Vec<f64>,
    space: Arc<vkdr::shape::ShapeSpace>,
}

impl Registration {
    pub fn new(space: &Arc<vkdr::shape::ShapeSpace>, result: vkdr::register::Registration) -> Self {
        Self {
            code_sd: space.code_in_deviations(&result.code),
            result,
            space: space.clone(),
        }
    }
}

#[pymethods]
impl Registration {
    #[getter]
    fn code<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(array(py, self.result.code.clone(), &[self.result.code.len()])?.into_any())
    }

    #[getter]
    fn code_sd<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(array(py, self.code_sd.clone(), &[self.code_sd.len()])?.into_any())
    }

    #[getter]
    fn pose<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(array(py, crate::pose_numbers(&self.result.pose), &[6])?.into_any())
    }

    #[getter]
    fn vertices<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        point_array(py, &self.result.vertices)
    }

    #[getter]
    fn faces<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        face_array(py, &self.space.canonical)
    }

    #[getter]
    fn losses<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        Ok(array(py, self.result.losses.clone(), &[self.result.losses.len()])?.into_any())
    }

    /// The stages `losses` holds, in order: (name, count), the counts adding up to
    /// `len(losses)` ("mask first", "pose alignment", "depth reach", "fit", "fit from a
    /// turn", "fit moved to the depth", "fit with the unseen held"); each stage's losses
    /// are its own objective's.
    #[getter]
    fn stages(&self) -> Vec<(&'static str, usize)> {
        self.result.stages.clone()
    }

    #[getter]
    fn loss(&self) -> f64 {
        self.result.loss
    }

    /// The iterations whose losses are kept: the stages' counts, `len(losses)`.
    #[getter]
    fn iterations(&self) -> usize {
        self.result.iterations()
    }

    /// Every evaluation the registration made, the turns' checks and a joint fit that a
    /// turned one replaced included (what `milliseconds` paid for).
    #[getter]
    fn evaluations(&self) -> usize {
        self.result.evaluations
    }

    #[getter]
    fn milliseconds(&self) -> f64 {
        self.result.milliseconds
    }

    #[getter]
    fn scale(&self) -> f64 {
        self.result.scale
    }

    /// Pickles as its space and its numbers (`_restore` makes it again, exactly).
    #[allow(clippy::type_complexity)]
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, (ShapeSpace, Bound<'py, PyDict>))> {
        let py = slf.py();
        let r = &slf.get().result;
        let state = PyDict::new(py);
        state.set_item("code", r.code.clone())?;
        state.set_item("pose", crate::pose_numbers(&r.pose))?;
        state.set_item(
            "vertices",
            r.vertices.iter().map(|v| v.to_array()).collect::<Vec<_>>(),
        )?;
        state.set_item("losses", r.losses.clone())?;
        state.set_item("stages", r.stages.clone())?;
        state.set_item("codes", r.codes.clone())?;
        state.set_item("scales", r.scales.clone())?;
        state.set_item("evaluations", r.evaluations)?;
        state.set_item("milliseconds", r.milliseconds)?;
        state.set_item("on_bound", r.on_bound)?;
        state.set_item("scale", r.scale)?;
        state.set_item("loss", r.loss)?;
        let space = ShapeSpace {
            inner: slf.get().space.clone(),
        };
        Ok((slf.get_type().getattr("_restore")?, (space, state)))
    }

    /// A registration from `__reduce__`'s state.
    #[staticmethod]
    fn _restore(space: &Bound<'_, ShapeSpace>, state: &Bound<'_, PyDict>) -> PyResult<Self> {
        let get = |key: &str| -> PyResult<Bound<'_, PyAny>> {
            state
                .get_item(key)?
                .ok_or_else(|| bad("state", format!("has no {key:?}")))
        };
        let pose: [f64; 6] = get("pose")?.extract()?;
        let vertices: Vec<[f64; 3]> = get("vertices")?.extract()?;
        let result = vkdr::register::Registration {
            code: get("code")?.extract()?,
            pose: vkdr::Pose {
                translation: DVec3::new(pose[0], pose[1], pose[2]),
                rotation: DVec3::new(pose[3], pose[4], pose[5]),
            },
            vertices: vertices.into_iter().map(DVec3::from_array).collect(),
            losses: get("losses")?.extract()?,
            stages: stages(get("stages")?.extract()?)?,
            codes: get("codes")?.extract()?,
            scales: get("scales")?.extract()?,
            evaluations: get("evaluations")?.extract()?,
            milliseconds: get("milliseconds")?.extract()?,
            on_bound: get("on_bound")?.extract()?,
            scale: get("scale")?.extract()?,
            loss: get("loss")?.extract()?,
        };
        Ok(Self::new(&space.get().inner, result))
    }

    fn __repr__(&self) -> String {
        format!(
            "vkdr.Registration(loss {:.5}, {} iterations, {:.1} ms, code in SD {:?}, scale {:.4})",
            self.result.loss,
            self.result.iterations(),
            self.result.milliseconds,
            self.code_sd
                .iter()
                .map(|c| (c * 100.0).round() / 100.0)
                .collect::<Vec<_>>(),
            self.result.scale
        )
    }
}
