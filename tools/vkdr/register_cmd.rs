//! `vkdr register`: one registration to observed images (a mask, optionally depth and
//! shading, in one or several views) or to a test mesh rendered as the observation.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};

use glam::DVec3;
use vkdr::camera::parse_numbers;
use vkdr::gpu::Context;
use vkdr::loss;
use vkdr::raster::View;
use vkdr::register::{
    self, Gravity, Observation, OtherView, Plan, PoseMode, RegisterParams, Registrar, ViewImages,
};
use vkdr::shape::ShapeSpace;
use vkdr::{Camera, Mesh, Pose};
use vkdr_app::eval;

use crate::args::{parse_view, DepthLossArgs, ShadingArgs, ViewArgs};
use crate::choices::{LossChoice, OptimizerChoice};

#[derive(clap::Args)]
pub struct Args {
    /// Shape space (.npz from `vkdr shape-space`).
    #[arg(long)]
    space: PathBuf,
    /// Observed mask PNG (nonzero = object), of exactly --size.
    #[arg(long, required_unless_present = "observed_mesh")]
    observed: Option<PathBuf>,
    /// A test mesh to render as the observation (same camera, at the true pose --true-pose
    /// or, without it, at --pose).
    #[arg(long, conflicts_with = "observed")]
    observed_mesh: Option<PathBuf>,
    #[arg(long, allow_hyphen_values = true, requires = "observed_mesh")]
    true_pose: Option<String>,
    /// With --shading and --observed: the observed shading, a grey PNG of exactly --size
    /// (colour is taken as its luminance; pixels off the mask count as background).
    #[arg(long, requires = "shading")]
    observed_shading: Option<PathBuf>,
    #[command(flatten)]
    shading: ShadingArgs,
    /// With --observed: the observed depth, a .npy of float32 metres (H x W) or a 16-bit grey
    /// PNG in units of --depth-scale millimetres; 0 = no measurement. Compared inside the
    /// silhouette.
    #[arg(long, requires = "observed")]
    observed_depth: Option<PathBuf>,
    /// Millimetres per unit of a depth PNG, as BOP's `depth_scale` (a PNG value times it is
    /// millimetres; 0.1 for sensors that store tenths of a millimetre). The depth cost's scale
    /// is --depth-sigma.
    #[arg(long, requires = "observed_depth")]
    depth_scale: Option<f64>,
    /// With --observed: a PNG of the pixels whose content is unknown (nonzero: hidden by
    /// something in front of the object; BOP's whole-object `mask` as it is, the pixels
    /// --observed shows as object stay known); they count for nothing, neither mask nor
    /// depth.
    #[arg(long, requires = "observed")]
    ignore: Option<PathBuf>,
    /// With --observed-mesh: observe its rendered depth too.
    #[arg(long, requires = "observed_mesh")]
    depth: bool,
    #[command(flatten)]
    depth_loss: DepthLossArgs,
    /// Further views of the object: a JSON file (docs/formats.md, the views file) with, for each camera after
    /// the first, its intrinsics, its pose relative to the first camera and its images.
    #[arg(long)]
    views: Option<PathBuf>,
    /// The camera and the initial pose.
    #[command(flatten)]
    view: ViewArgs,
    /// Optimise the pose too (the schedule of `vkdr eval`: the pose aligned alone for 15
    /// iterations with the distance loss, with depth then 10 with the mask and the depth
    /// at a wide scale, then pose and shape; z too where depth or a further view observes
    /// it).
    #[arg(long)]
    optimize_pose: bool,
    /// Iterations (after the alignment; default: that of `vkdr eval`'s condition, 30 with
    /// the pose fixed, 60 with --optimize-pose).
    #[arg(long)]
    iterations: Option<usize>,
    /// The loss.
    #[arg(long, value_enum, default_value_t = LossChoice::Mse)]
    loss: LossChoice,
    /// The optimiser (default: that of `vkdr eval`'s condition).
    #[arg(long, value_enum)]
    optimizer: Option<OptimizerChoice>,
    /// Weight of the Gaussian prior on the code in training standard deviations: auto (the
    /// weight the image's pixel count implies, register::observation_prior) or a number
    /// (0: none). It settles what the images leave open, such as a shape shifted in its
    /// own frame against a shifted pose.
    #[arg(long, allow_hyphen_values = true, default_value = "auto")]
    code_prior: String,
    /// Do not hold the directions of the code the images hardly constrain with a strong
    /// prior after the fit (RegisterParams::hold_unseen; the schedules do).
    #[arg(long)]
    no_hold: bool,
    /// With the pose known and depth observed: iterations comparing the mask alone before
    /// the fit (RegisterParams::mask_first; default the schedule's, 15; 0: none).
    #[arg(long)]
    mask_first: Option<usize>,
    /// With --optimize-pose: starts, the initial pose and it turned about the object's
    /// --up axis by +-15, +-30, ... degrees; the initial pose is registered and the
    /// others' turns are tried on its fit, the joint fit running again from a turn that
    /// scores 5% lower (1 to 8; against a rotation that stops in a local minimum, as a
    /// mug's handle; the cost: docs/evaluation.md).
    #[arg(long, default_value_t = vkdr::register::DEFAULT_STARTS)]
    starts: usize,
    /// The object's up axis for --starts and --gravity, in its own frame: x,y,z. Default:
    /// the shape space's (its category's info.json up_axis), or y for a space that does
    /// not carry one.
    #[arg(long, allow_hyphen_values = true)]
    up: Option<String>,
    /// With --optimize-pose: which way is up in the camera frame (the support plane's
    /// normal, away from it: x,y,z, with y down in the image), or `from-depth` to fit the
    /// plane the object stands on in the observed depth. The object's --up axis is kept
    /// within --tilt-tolerance of it; the rotation about it stays free.
    #[arg(long, requires = "optimize_pose", allow_hyphen_values = true)]
    gravity: Option<String>,
    #[command(flatten)]
    tilt: crate::args::TiltArgs,
    /// Fit one uniform scale of the shape too (0.25 to 1.75), for an instance larger or
    /// smaller than the training set's; observable with depth or a further view.
    #[arg(long)]
    optimize_scale: bool,
    #[arg(long)]
    out: PathBuf,
}

impl Args {
    /// The output folder.
    pub fn out(&self) -> &Path {
        &self.out
    }
}

/// A camera after the first, as the views file gives it.
struct FurtherView {
    other: OtherView,
    mask: Option<PathBuf>,
    depth: Option<PathBuf>,
    shading: Option<PathBuf>,
}

/// Reads the views file: `{"views": [{"intrinsics": [fx, fy, cx, cy], "size": [w, h],
/// "from_first": {"translation": [x, y, z], "rotation": [rx, ry, rz]}, "mask": PATH,
/// "depth": PATH, "shading": PATH}, ...]}`, one entry per camera after the first.
/// `from_first` maps the first camera's frame to this one's (metres, axis-angle radians);
/// paths are relative to the file's folder. Every view has the first's size.
fn read_views(path: &Path, first: &Camera) -> Result<Vec<FurtherView>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let folder = path.parent().unwrap_or(Path::new("."));
    let entries = json
        .get("views")
        .and_then(|v| v.as_array())
        .with_context(|| format!("{}: no \"views\" list", path.display()))?;
    if entries.is_empty() || entries.len() > 7 {
        bail!(
            "{}: {} further views; 1 to 7 are supported",
            path.display(),
            entries.len()
        );
    }
    let numbers = |v: &serde_json::Value, key: &str, n: usize, at: usize| -> Result<Vec<f64>> {
        let list = v.get(key).and_then(|x| x.as_array());
        let values: Option<Vec<f64>> = list.and_then(|l| l.iter().map(|x| x.as_f64()).collect());
        match values {
            Some(values) if values.len() == n && values.iter().all(|x| x.is_finite()) => Ok(values),
            _ => bail!(
                "{}: view {} needs \"{key}\" as {n} finite numbers",
                path.display(),
                at + 1
            ),
        }
    };
    let file = |v: &serde_json::Value, key: &str, at: usize| -> Result<Option<PathBuf>> {
        match v.get(key) {
            None | Some(serde_json::Value::Null) => Ok(None),
            Some(serde_json::Value::String(s)) => Ok(Some(folder.join(s))),
            Some(_) => bail!(
                "{}: view {}'s \"{key}\" must be a path",
                path.display(),
                at + 1
            ),
        }
    };
    entries
        .iter()
        .enumerate()
        .map(|(at, v)| {
            let [fx, fy, cx, cy] = numbers(v, "intrinsics", 4, at)?[..] else {
                unreachable!()
            };
            let size = numbers(v, "size", 2, at)?;
            if size != [first.width as f64, first.height as f64] {
                bail!(
                    "{}: view {} is {}x{}, but every view must have the first's size ({}x{})",
                    path.display(),
                    at + 1,
                    size[0],
                    size[1],
                    first.width,
                    first.height
                );
            }
            let mut camera = Camera::new(fx, fy, cx, cy, first.width, first.height)?;
            camera.near = first.near;
            let camera = camera
                .validated()
                .with_context(|| format!("{}: view {}", path.display(), at + 1))?;
            let from_first = v.get("from_first").with_context(|| {
                format!("{}: view {} needs \"from_first\"", path.display(), at + 1)
            })?;
            let t = numbers(from_first, "translation", 3, at)?;
            let r = numbers(from_first, "rotation", 3, at)?;
            Ok(FurtherView {
                other: OtherView {
                    camera,
                    from_first: Pose::new([t[0], t[1], t[2]], [r[0], r[1], r[2]])?,
                },
                mask: file(v, "mask", at)?,
                depth: file(v, "depth", at)?,
                shading: file(v, "shading", at)?,
            })
        })
        .collect()
}

/// The observation from files: the first view's from the flags, the others' from the
/// views file. A view without a depth image has no measurement anywhere.
fn from_files(args: &Args, view: View, further: &[FurtherView]) -> Result<Observation> {
    let shading = args.shading.shading()?.is_some();
    let with_depth = args.observed_depth.is_some();
    let camera = view.camera;
    let (w, h) = (camera.width, camera.height);
    let first = args.observed.as_deref().expect("clap requires --observed");
    let images = |v: usize,
                  mask: &Option<PathBuf>,
                  depth: &Option<PathBuf>,
                  shaded: &Option<PathBuf>|
     -> Result<ViewImages> {
        let Some(mask) = mask else {
            bail!("view {v} of the views file has no \"mask\" (needed with --observed)");
        };
        let mask = loss::load_mask(mask, w, h)?;
        let depth = match depth {
            Some(path) if with_depth => Some(load_depth(args, path, w, h)?),
            _ => None,
        };
        let shading = match (shading, shaded) {
            (false, _) => None,
            (true, Some(path)) => Some(loss::load_shading(path, &mask, w, h)?),
            (true, None) => bail!(if v == 0 {
                "--shading with --observed needs the observed image too (--observed-shading)"
                    .to_string()
            } else {
                format!("--shading: view {v} of the views file has no \"shading\" image")
            }),
        };
        Ok(ViewImages {
            mask,
            depth,
            shading,
            ignore: None,
        })
    };
    let first = ViewImages {
        ignore: args
            .ignore
            .as_ref()
            .map(|path| loss::load_mask(path, w, h))
            .transpose()?,
        ..images(
            0,
            &Some(first.to_path_buf()),
            &args.observed_depth,
            &args.observed_shading,
        )?
    };
    let mut observation = Observation::new(camera, first)?;
    for (v, f) in further.iter().enumerate() {
        let images = images(v + 1, &f.mask, &f.depth, &f.shading)?;
        observation = observation.with_view(f.other, images)?;
    }
    Ok(observation)
}

/// The up direction of --gravity: given, or the normal of the support plane fitted in the
/// observed depth (printed).
fn gravity(text: &str, up: DVec3, tolerance: f64, observed: &Observation) -> Result<Gravity> {
    let gravity = if text == "from-depth" {
        if observed.depth.is_none() {
            bail!("--gravity from-depth needs the observed depth (--observed-depth, or --depth)");
        }
        let (gravity, plane) =
            Gravity::from_depth(observed, up, tolerance).context("--gravity from-depth")?;
        println!(
            "support plane: normal {:.4},{:.4},{:.4} at {:.4} m, {} of {} pixels around the mask on it (rms {:.1} mm)",
            plane.normal.x,
            plane.normal.y,
            plane.normal.z,
            plane.offset,
            plane.inliers,
            plane.candidates,
            plane.rms * 1e3
        );
        gravity
    } else {
        Gravity {
            up,
            direction: DVec3::from_array(parse_numbers::<3>(text, "--gravity")?),
            tolerance,
        }
    };
    gravity
        .validate()
        .context("--gravity and --tilt-tolerance")?;
    Ok(gravity)
}

/// A depth image in metres: a `.npy` as it is, a PNG times --depth-scale millimetres.
fn load_depth(args: &Args, path: &Path, w: u32, h: u32) -> Result<Vec<f32>> {
    let is_png = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    let scale = match (args.depth_scale, is_png) {
        (Some(_), false) => bail!(
            "--depth-scale (millimetres per unit of a depth PNG) does not apply to {}, which \
             holds metres; the depth cost's scale is --depth-sigma",
            path.display()
        ),
        (scale, _) => scale.unwrap_or(1.0),
    };
    Ok(loss::load_depth(path, w, h, scale)?)
}

/// Warns when the observed depth and the mask's size disagree with the shape space by
/// about an order of magnitude (a depth in other units than declared): the mask's size
/// in metres at the measured depth against the canonical's two longest extents.
fn check_depth_units(space: &ShapeSpace, camera: &Camera, mask: &[f32], depth: &[f32]) {
    let mut measured: Vec<f32> = mask
        .iter()
        .zip(depth)
        .filter(|&(&m, &z)| m > 0.0 && z > 0.0)
        .map(|(_, &z)| z)
        .collect();
    if measured.is_empty() {
        return;
    }
    measured.sort_by(f32::total_cmp);
    let z = measured[measured.len() / 2] as f64;
    let pixels = mask.iter().filter(|&&m| m > 0.0).count() as f64;
    let seen = pixels.sqrt() * z / (camera.fx * camera.fy).sqrt();
    let (lo, hi) = space.canonical.bounds();
    let mut extents: Vec<f64> = (0..3).map(|k| (hi[k] - lo[k]) as f64).collect();
    extents.sort_by(f64::total_cmp);
    let expected = (extents[1] * extents[2]).sqrt();
    let ratio = seen / expected;
    if !(0.25..=4.0).contains(&ratio) {
        eprintln!(
            "warning: at the measured depth (median {z:.3} m) the mask is about {seen:.3} m \
             across, {ratio:.2}x the shape space's canonical ({expected:.3} m): is the depth in \
             the units declared (a depth PNG times --depth-scale is millimetres)?"
        );
    }
}

/// The observation rendered from a test mesh at the true pose, in every view.
fn rendered(
    ctx: &Context,
    args: &Args,
    mesh: &Path,
    truth: View,
    others: &[OtherView],
) -> Result<Observation> {
    let registrar = Registrar::new(ctx)?;
    let mesh = Mesh::load_obj(mesh)?;
    let views = register::all_views(truth, others);
    let seen = eval::observe(
        ctx,
        &registrar,
        &mesh,
        &views,
        args.depth,
        args.shading.shading()?,
    )?;
    Ok(Observation {
        camera: truth.camera,
        others: others.to_vec(),
        mask: seen.mask,
        depth: seen.depth,
        shaded: seen.shaded,
    })
}

pub fn run(args: &Args) -> Result<()> {
    vkdr::register::check_starts(args.starts).context("--starts")?;
    if args.starts > 1 && args.starts != vkdr::register::DEFAULT_STARTS && !args.optimize_pose {
        bail!("--starts turns the starting pose: give --optimize-pose too");
    }
    let tolerance = args.tilt.radians(args.gravity.is_some())?;
    let space = ShapeSpace::load(&args.space)?;
    let up = match &args.up {
        Some(text) => {
            let up = DVec3::from_array(parse_numbers::<3>(text, "--up")?);
            if !(up.is_finite() && up.length() > 0.0) {
                bail!("--up must be a nonzero direction x,y,z, not {text}");
            }
            up
        }
        None => {
            let (up, known) = space.up_or_y();
            if !known && (args.gravity.is_some() || args.optimize_pose) {
                eprintln!(
                    "note: {} carries no up axis (built before spaces kept their category's); \
                     using y: give --up or rebuild it with shape-space",
                    args.space.display()
                );
            }
            up
        }
    };
    let view = args.view.view()?;
    let depth_loss = args.depth_loss.loss()?;
    let further = match &args.views {
        Some(path) => read_views(path, &view.camera)?,
        None => Vec::new(),
    };
    let others: Vec<OtherView> = further.iter().map(|f| f.other).collect();
    let ctx = Context::new()?;
    let observed = match &args.observed_mesh {
        None => from_files(args, view, &further)?,
        Some(mesh) => {
            let truth = match &args.true_pose {
                Some(p) => parse_view(&args.view.intrinsics, &args.view.size, p, args.view.near)?,
                None => view,
            };
            rendered(&ctx, args, mesh, truth, &others)?
        }
    };
    if let Some(depth) = observed.first_depth() {
        check_depth_units(&space, &view.camera, observed.first_mask(), depth);
    }
    // The schedules of `vkdr eval` (with the pose: the pose alone first, then both).
    let mode = if args.optimize_pose {
        PoseMode::Free
    } else {
        PoseMode::Known
    };
    let base = RegisterParams::for_observation(mode, &observed);
    let optimizer: Option<vkdr::register::Optimizer> = args.optimizer.map(Into::into);
    let params = RegisterParams {
        iterations: args.iterations.unwrap_or(base.iterations),
        loss: args.loss.into(),
        optimizer: optimizer.unwrap_or(base.optimizer),
        shading: args.shading.shading()?,
        depth: base.depth.map(|_| depth_loss),
        code_prior: crate::args::code_prior(&args.code_prior, observed.pixels())?,
        optimize_scale: args.optimize_scale,
        hold_unseen: base.hold_unseen && !args.no_hold,
        mask_first: args.mask_first.unwrap_or(base.mask_first),
        depth_detail: args.depth_loss.depth_detail,
        ..base
    };
    let gravity = match &args.gravity {
        None => None,
        Some(g) => Some(gravity(g, up, tolerance, &observed)?),
    };
    let plan = Plan {
        starts: if args.optimize_pose { args.starts } else { 1 },
        gravity,
        ..Plan::new(view.pose, up, params)
    };
    let result = crate::registration::register(&ctx, &space, &observed, &plan, &args.out)?;
    let kept = result.iterations().max(1);
    let first = result.losses.first().copied().unwrap_or(f64::NAN);
    println!(
        "{kept} iterations{} in {:.1} ms ({:.2} ms per iteration); loss {first:.5} -> {:.5}{}",
        if plan.starts > 1 {
            format!(
                " ({} starts: the first fitted, the others' turns tried on its fit; {} evaluations in all)",
                plan.starts,
                result.evaluations
            )
        } else {
            String::new()
        },
        result.milliseconds,
        result.milliseconds / kept as f64,
        result.loss,
        if params.optimize_scale {
            format!("; scale {:.4}", result.scale)
        } else {
            String::new()
        },
    );
    let sd = space.code_in_deviations(&result.code);
    println!(
        "code in training standard deviations {:?}{}",
        sd.iter()
            .map(|c| (c * 100.0).round() / 100.0)
            .collect::<Vec<_>>(),
        match sd.iter().map(|c| c.abs()).fold(0.0, f64::max) {
            m if m > 3.0 => format!(" (beyond 3 SD: {m:.1})"),
            _ => String::new(),
        }
    );
    if let Some(g) = &gravity {
        println!(
            "tilt from up {:.2} degrees (tolerance {:.2})",
            g.tilt(&result.pose).to_degrees(),
            g.tolerance.to_degrees()
        );
    }
    // The stage after the pose alignment starts from its own loss (another loss function).
    let joint_start = result.losses.get(params.align.min(kept - 1)).copied();
    if args.optimize_pose && params.align > 0 {
        if let Some(start) = joint_start.filter(|&s| result.loss > s) {
            eprintln!(
                "warning: the registration ended above its start ({start:.5} -> {:.5})",
                result.loss
            );
        }
    } else if result.loss > first {
        eprintln!(
            "warning: the registration ended above its start ({first:.5} -> {:.5})",
            result.loss
        );
    }
    println!(
        "wrote {0}/deformed.obj, pose.json, code.npy, log.json, overlay_start.png, overlay_end.png{1}{2}",
        args.out.display(),
        if params.shading.is_some() {
            ", shading_end.png"
        } else {
            ""
        },
        if others.is_empty() {
            String::new()
        } else {
            format!(
                " (the further views' pictures with the suffix _view1 to _view{})",
                others.len()
            )
        }
    );
    Ok(())
}
