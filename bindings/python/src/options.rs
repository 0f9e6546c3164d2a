//! What `Device.register` and `register_batch` are given, read into the engine's types:
//! the further views, the depth cost and the shading model, the observation ([`Looks`])
//! and the keyword options with their plan.

use glam::DVec3;
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use vkdr::diff::{DepthLoss, Shading};
use vkdr::loss::Loss;
use vkdr::register::{
    self, Gravity, Observation, Optimizer, OtherView, Plan, PoseMode, RegisterParams, ViewImages,
};

use crate::arrays::{self, bad};
use crate::OrPy;

/// A further camera of `views`, with its images.
pub(crate) struct FurtherView {
    pub(crate) other: OtherView,
    pub(crate) mask: Vec<f32>,
    pub(crate) depth: Option<Vec<f32>>,
    pub(crate) shading: Option<Vec<f32>>,
}

/// The further views from a list of dicts (`K`, `size`, `from_first`, `mask`, and
/// optionally `depth` and `shading`).
pub(crate) fn further_views(list: &Bound<'_, PyList>) -> PyResult<Vec<FurtherView>> {
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
pub(crate) struct DepthOptions {
    pub(crate) sigma: Option<f64>,
    pub(crate) weight: Option<f64>,
    pub(crate) occlusion: Option<f64>,
}

impl DepthOptions {
    pub(crate) fn loss(&self) -> PyResult<DepthLoss> {
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
pub(crate) fn shading_model(
    (light, ambient): (Option<[f64; 3]>, Option<f64>),
) -> PyResult<Shading> {
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

/// What is observed ([`Observation`]: the mask with unknown pixels marked, the depth and
/// shading where given) and how the depth and shading are compared.
pub(crate) struct Looks {
    pub(crate) observation: Observation,
    pub(crate) depth_loss: DepthLoss,
    pub(crate) shading: Option<Shading>,
}

impl Looks {
    /// The first view's images from their arguments, and `further`'s (the ignore mask
    /// applies to the first).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn read_views(
        mask: &Bound<'_, PyAny>,
        depth: Option<&Bound<'_, PyAny>>,
        shading: Option<&Bound<'_, PyAny>>,
        ignore: Option<&Bound<'_, PyAny>>,
        camera: vkdr::Camera,
        further: Vec<FurtherView>,
        depth_options: DepthOptions,
        shading_options: (Option<[f64; 3]>, Option<f64>),
    ) -> PyResult<Self> {
        let wh = (camera.width, camera.height);
        let image = |obj: Option<&Bound<'_, PyAny>>, name: &str| {
            obj.map(|o| arrays::image(o, name, wh, Some(1))).transpose()
        };
        let first = ViewImages {
            mask: arrays::mask(mask, "mask", wh, Some(1))?,
            depth: image(depth, "depth")?,
            shading: image(shading, "shading")?,
            ignore: image(ignore, "ignore")?,
        };
        let mut looks = Self::new(camera, first, depth_options, shading_options)?;
        for (k, view) in further.into_iter().enumerate() {
            let images = ViewImages {
                mask: view.mask,
                depth: view.depth,
                shading: view.shading,
                ignore: None,
            };
            looks.observation = looks
                .observation
                .with_view(view.other, images)
                .map_err(|e| bad(&format!("views[{k}]"), e))?;
        }
        Ok(looks)
    }

    /// The observation of one view's images through `camera`, with the options' depth
    /// cost and shading model.
    pub(crate) fn new(
        camera: vkdr::Camera,
        images: ViewImages,
        depth_options: DepthOptions,
        shading_options: (Option<[f64; 3]>, Option<f64>),
    ) -> PyResult<Self> {
        let shading = images
            .shading
            .is_some()
            .then(|| shading_model(shading_options))
            .transpose()?;
        Ok(Self {
            observation: Observation::new(camera, images).py()?,
            depth_loss: depth_options.loss()?,
            shading,
        })
    }

    /// The image compared: the shading where given, else the mask.
    pub(crate) fn compared(&self) -> &[f32] {
        let observation = &self.observation;
        observation.shaded.as_deref().unwrap_or(&observation.mask)
    }
}

/// The registration options of `register` and `register_batch`.
pub(crate) struct Options {
    pub(crate) optimize_pose: bool,
    pub(crate) optimize_scale: bool,
    pub(crate) iterations: Option<usize>,
    pub(crate) loss: Loss,
    pub(crate) optimizer: Option<Optimizer>,
    pub(crate) code_prior: Option<f64>,
    pub(crate) hold_unseen: Option<bool>,
    pub(crate) mask_first: Option<usize>,
    pub(crate) starts: Option<usize>,
    /// The object's up axis: as given, else the shape space's ([`Options::for_space`]).
    pub(crate) up: DVec3,
    pub(crate) up_given: bool,
    pub(crate) gravity: Option<GravityOption>,
    /// Radians.
    pub(crate) tilt_tolerance: f64,
    pub(crate) depth: DepthOptions,
    pub(crate) shading: (Option<[f64; 3]>, Option<f64>),
}

/// Which way is up in the camera frame.
pub(crate) enum GravityOption {
    Direction(DVec3),
    FromDepth,
}

impl Options {
    /// The options from `register`'s keyword arguments; a `TypeError` names one it does
    /// not know.
    pub(crate) fn read(kwargs: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
        let mut options = Self {
            optimize_pose: false,
            optimize_scale: false,
            iterations: None,
            loss: Loss::Mse,
            optimizer: None,
            code_prior: None,
            hold_unseen: None,
            mask_first: None,
            starts: None,
            up: DVec3::Y,
            up_given: false,
            gravity: None,
            tilt_tolerance: vkdr::register::TILT_TOLERANCE,
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
                "hold_unseen" => options.hold_unseen = Some(get!("True or False")),
                "mask_first" => options.mask_first = Some(get!("a count of iterations")),
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
                "tilt_tolerance" => {
                    let degrees: f64 = get!("degrees");
                    options.tilt_tolerance = degrees.to_radians();
                }
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
        if let Some(count) = options.starts {
            register::check_starts(count).map_err(crate::py_error)?;
            if count > 1 && !options.optimize_pose {
                return Err(bad(
                    "starts",
                    "turns the starting pose: give optimize_pose=True too",
                ));
            }
        }
        Ok(options)
    }

    /// The options for registrations of `space`: its category's up axis where `up` was not
    /// given (y for a space that carries none).
    pub(crate) fn for_space(self, space: &vkdr::shape::ShapeSpace) -> Self {
        match self.up_given {
            true => self,
            false => Self {
                up: space.up_or_y().0,
                ..self
            },
        }
    }

    /// The parameters for these observations: the engine's schedule for them
    /// ([`RegisterParams::for_observation`]) with the options given.
    pub(crate) fn params(&self, looks: &Looks) -> vkdr::Result<RegisterParams> {
        let observation = &looks.observation;
        let mode = if self.optimize_pose {
            PoseMode::Free
        } else {
            PoseMode::Known
        };
        let base = RegisterParams::for_observation(mode, observation);
        let code_prior = match self.code_prior {
            None => base.code_prior,
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
            depth: base.depth.map(|_| looks.depth_loss),
            code_prior,
            hold_unseen: self.hold_unseen.unwrap_or(base.hold_unseen),
            mask_first: self.mask_first.unwrap_or(base.mask_first),
            optimize_scale: self.optimize_scale,
            ..base
        };
        params.validate()?;
        Ok(params)
    }

    /// The plan of a registration of `looks` from `pose`: the starts asked for (else the
    /// engine's for the schedule, [`Plan::new`]) and gravity.
    pub(crate) fn plan(&self, looks: &Looks, pose: vkdr::Pose) -> vkdr::Result<Plan> {
        let plan = Plan::new(pose, self.up, self.params(looks)?);
        Ok(Plan {
            starts: self.starts.unwrap_or(plan.starts),
            gravity: self.gravity(looks)?,
            ..plan
        })
    }

    /// Which way is up, where asked: given, or from the observed depth.
    pub(crate) fn gravity(&self, looks: &Looks) -> vkdr::Result<Option<Gravity>> {
        let tolerance = self.tilt_tolerance;
        let gravity = match &self.gravity {
            None => return Ok(None),
            Some(GravityOption::Direction(direction)) => Gravity {
                up: self.up,
                direction: *direction,
                tolerance,
            },
            Some(GravityOption::FromDepth) => {
                if looks.observation.depth.is_none() {
                    return Err(vkdr::Error::InvalidInput(
                        "gravity=\"from-depth\" needs the observed depth".into(),
                    ));
                }
                Gravity::from_depth(&looks.observation, self.up, tolerance)?.0
            }
        };
        gravity.validate()?;
        Ok(Some(gravity))
    }
}
