//! The engine behind `vkdr.Device`: one Vulkan device, the pipelines built on it so far,
//! one call at a time, and the default device of calls given none.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

use vkdr::cpd::CpdPipelines;
use vkdr::gpu::{Context, ContextOptions};
use vkdr::register::Registrar;

use crate::OrPy;

/// A device and the pipelines built on it so far. Its work runs one call at a time (a
/// queue takes one submission at a time; two Python threads calling at once wait in turn,
/// with the GIL released).
pub struct Engine {
    pub(crate) ctx: Context,
    pub(crate) parts: Mutex<Parts>,
    pub(crate) engine_ms: Mutex<f64>,
    /// The process that made it: a Vulkan device does not survive a fork.
    pub(crate) pid: u32,
}

/// The pipelines, each built when a call first needs it.
#[derive(Default)]
pub struct Parts {
    pub(crate) registrar: Option<Registrar>,
    pub(crate) cpd: Option<CpdPipelines>,
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
    pub(crate) fn new(name: Option<String>, validation: bool) -> vkdr::Result<Self> {
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
    pub(crate) fn is_ours(&self) -> bool {
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
