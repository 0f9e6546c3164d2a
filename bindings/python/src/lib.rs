//! The Python module `vkdr` (this crate is its compiled part, `vkdr._vkdr`): the engine's
//! rasterizer, exact loss gradients, CPD, shape spaces and registration, with NumPy arrays
//! in and out. `python/vkdr/__init__.py` re-exports it; `python/vkdr/torch.py` wraps
//! `Device.loss_and_grad` as a PyTorch autograd function.
//!
//! Conventions, as the command line's: a pose is 6 numbers, the translation in metres and
//! an axis-angle rotation in radians, object to camera (x right, y down, z forward); `K` is
//! a pinhole intrinsics matrix (3 x 3, or fx, fy, cx, cy) in pixels; `size` is (width,
//! height); images are `(height, width)` arrays. The device's work runs with the GIL
//! released, one call at a time per `Device`.

use std::ops::ControlFlow;

use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};
use pyo3::prelude::*;

use vkdr::{Camera, Mesh, Pose};

mod arrays;
mod device;
mod engine;
mod options;
mod space;

use arrays::bad;

/// The engine's error as a Python exception: bad input (arguments, file contents) is a
/// `ValueError`, a file that cannot be read or written an `OSError`, and the device's
/// errors and limits a `RuntimeError`; each carries the engine's message.
fn py_error(error: vkdr::Error) -> PyErr {
    let message = error.to_string();
    match error {
        vkdr::Error::InvalidInput(_) | vkdr::Error::Format { .. } => PyValueError::new_err(message),
        vkdr::Error::Io { .. } => PyOSError::new_err(message),
        _ => PyRuntimeError::new_err(message),
    }
}

/// The engine's result as Python's.
trait OrPy<T> {
    fn py(self) -> PyResult<T>;
}

impl<T> OrPy<T> for vkdr::Result<T> {
    fn py(self) -> PyResult<T> {
        self.map_err(py_error)
    }
}

/// A Python progress callback, `progress(done, total)`, called from the device's work with
/// the GIL taken for the call. The first exception it raises, or that a signal handler
/// raises meanwhile (Ctrl-C's KeyboardInterrupt, with or without a callback), stops a
/// registration between submissions ([`vkdr::register::OnChunk`]) and is raised when the
/// work ends.
struct Progress {
    callback: Option<Py<PyAny>>,
    error: std::sync::Mutex<Option<PyErr>>,
}

impl Progress {
    fn new(callback: Option<Py<PyAny>>) -> Self {
        Self {
            callback,
            error: std::sync::Mutex::new(None),
        }
    }

    /// Calls the callback and runs the signal handlers; `Break` once either raised.
    fn call(&self, done: usize, total: usize) -> ControlFlow<()> {
        let Ok(mut error) = self.error.lock() else {
            return ControlFlow::Break(());
        };
        if error.is_some() {
            return ControlFlow::Break(());
        }
        Python::attach(|py| {
            let called = match &self.callback {
                Some(callback) => callback.call1(py, (done, total)).map(drop),
                None => Ok(()),
            };
            match called.and_then(|()| py.check_signals()) {
                Ok(()) => ControlFlow::Continue(()),
                Err(e) => {
                    *error = Some(e);
                    ControlFlow::Break(())
                }
            }
        })
    }

    /// The callback's (or a signal handler's) exception where one was raised, the work
    /// stopped by it; else the work's result.
    fn finish<T>(self, result: PyResult<T>) -> PyResult<T> {
        match self.error.into_inner().ok().flatten() {
            Some(error) => Err(error),
            None => result,
        }
    }
}

/// A mesh from `vertices` (V x 3, float) and `faces` (F x 3, integer indices into the
/// vertices).
fn mesh(vertices: &Bound<'_, PyAny>, faces: &Bound<'_, PyAny>) -> PyResult<Mesh> {
    let v =
        arrays::floats32(vertices, "vertices")?.expect("vertices", &[None, Some(3)], "(V, 3)")?;
    let count = v.shape[0];
    let positions: Vec<[f32; 3]> = v.data.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    let triangles = triangles(faces, count)?;
    Mesh::new(positions, triangles).py()
}

/// `faces` (F x 3 integers) as triangles of a mesh of `count` vertices.
fn triangles(faces: &Bound<'_, PyAny>, count: usize) -> PyResult<Vec<[u32; 3]>> {
    let f = arrays::integers(faces, "faces")?.expect("faces", &[None, Some(3)], "(F, 3)")?;
    if f.shape[0] == 0 {
        return Err(bad("faces", "no triangles"));
    }
    let outside = f.data.iter().position(|&i| !(0..count as i64).contains(&i));
    if let Some(k) = outside {
        return Err(bad(
            "faces",
            format!(
                "face {} has index {} outside the {count} vertices",
                k / 3,
                match f.data[k] {
                    -1 => "-1 (or one past 2^63)".to_string(),
                    i => i.to_string(),
                }
            ),
        ));
    }
    Ok(f.data
        .chunks_exact(3)
        .map(|t| [t[0] as u32, t[1] as u32, t[2] as u32])
        .collect())
}

/// The camera of intrinsics `k` (3 x 3 without skew, or fx, fy, cx, cy) and `size`
/// (width, height).
fn camera(k: &Bound<'_, PyAny>, size: (u32, u32)) -> PyResult<Camera> {
    let values = arrays::floats(k, "K")?;
    let [fx, fy, cx, cy] = match values.shape.as_slice() {
        [4] => [
            values.data[0],
            values.data[1],
            values.data[2],
            values.data[3],
        ],
        [3, 3] => {
            let m = &values.data;
            if m[1] != 0.0 || m[3] != 0.0 || m[6] != 0.0 || m[7] != 0.0 || m[8] != 1.0 {
                return Err(bad(
                    "K",
                    "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)",
                ));
            }
            [m[0], m[4], m[2], m[5]]
        }
        other => {
            return Err(bad(
                "K",
                format!("expected shape (3, 3) or (4,) (fx, fy, cx, cy), got {other:?}"),
            ))
        }
    };
    Camera::new(fx, fy, cx, cy, size.0, size.1).map_err(|e| bad("K and size", e))
}

/// Poses from `(6,)` (one, `batched` false) or `(N, 6)` (N >= 1) numbers.
fn poses(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<(Vec<Pose>, bool)> {
    let values = arrays::floats(obj, name)?;
    let batched = match values.shape.as_slice() {
        [6] => false,
        [n, 6] if *n > 0 => true,
        other => {
            return Err(bad(
                name,
                format!(
                    "expected shape (6,) (tx, ty, tz in metres, rx, ry, rz axis-angle) or (N, 6), got {other:?}"
                ),
            ))
        }
    };
    let poses = values
        .data
        .chunks_exact(6)
        .map(|p| Pose::new([p[0], p[1], p[2]], [p[3], p[4], p[5]]).map_err(|e| bad(name, e)))
        .collect::<PyResult<Vec<_>>>()?;
    Ok((poses, batched))
}

/// One pose, `(6,)`.
fn pose(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Pose> {
    match poses(obj, name)? {
        (poses, false) => Ok(poses[0]),
        _ => Err(bad(name, "expected one pose, shape (6,)")),
    }
}

/// The 6 numbers of a pose: translation, then axis-angle.
fn pose_numbers(pose: &Pose) -> Vec<f64> {
    let (t, r) = (pose.translation, pose.rotation);
    vec![t.x, t.y, t.z, r.x, r.y, r.z]
}

/// `size` = (width, height): a tuple, list or array of two positive integers.
fn size(size: &Bound<'_, PyAny>, name: &str) -> PyResult<(u32, u32)> {
    let values = arrays::integers(size, name)?;
    let &[w, h] = values.data.as_slice() else {
        return Err(bad(
            name,
            format!("expected (width, height), got shape {:?}", values.shape),
        ));
    };
    let fits = |v: i64| (1..=i64::from(u32::MAX)).contains(&v);
    if fits(w) && fits(h) {
        Ok((w as u32, h as u32))
    } else {
        Err(bad(
            name,
            format!("expected (width, height) of positive pixels, got ({w}, {h})"),
        ))
    }
}

#[pymodule]
fn _vkdr(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<engine::Device>()?;
    m.add_class::<space::ShapeSpace>()?;
    m.add_class::<space::Registration>()?;
    m.add_function(wrap_pyfunction!(space::cpd, m)?)?;
    m.add_function(wrap_pyfunction!(space::load_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(engine::default_device, m)?)?;
    m.add("UNKNOWN", vkdr::loss::UNKNOWN)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
