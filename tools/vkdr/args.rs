//! The flag groups several commands share: camera and pose (render, grad, register), CPD
//! (cpd, shape-space), depth loss and shading (register, eval), shards (eval, eval-frames).

use std::path::{Path, PathBuf};

use anyhow::Result;

use vkdr::camera::{parse_numbers, parse_size};
use vkdr::cpd::CpdParams;
use vkdr::raster::View;
use vkdr::{Camera, Pose};

/// The CPD flags shared by cpd and shape-space.
#[derive(clap::Args)]
pub struct CpdArgs {
    /// Kernel width, in units of the source's RMS radius.
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().beta)]
    pub beta: f64,
    /// Smoothness weight. The data term grows with the points and this does not: dense
    /// noise-free sets wanted more (2 up to a few thousand points, hundreds at 2e4,
    /// thousands at 1e5), sets with missing points and outliers did not (docs/method.md, CPD).
    #[arg(long = "lambda", allow_negative_numbers = true, default_value_t = CpdParams::default().lambda)]
    pub lambda: f64,
    /// Outlier weight, in (0, 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().w)]
    pub w: f64,
    #[arg(long, default_value_t = CpdParams::default().max_iterations)]
    pub max_iterations: usize,
    /// Stop when an iteration lowers the objective (negative log-likelihood plus the
    /// smoothness term) by less than this fraction of it and moves the points by less
    /// than this many source RMS radii on average.
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().tolerance)]
    pub tolerance: f64,
    /// Replace the kernel by its Nystrom approximation from this many landmarks (faster,
    /// approximate); by default the M-step uses the exact kernel.
    #[arg(long)]
    pub rank: Option<usize>,
    /// Plain EM iterations, as pycpd's (no SQUAREM extrapolation).
    #[arg(long)]
    pub no_accelerate: bool,
    /// Above twice this many source points, register subsets of this many source points
    /// first and start the full sets from their field: 2-3x faster from 2e4 points on,
    /// accuracy varies (e.g. 5000; 0: one stage)
    #[arg(long, default_value_t = 0)]
    pub coarse: usize,
}

impl CpdArgs {
    /// The parameters, checked before any file is read.
    pub fn params(&self) -> Result<CpdParams> {
        let params = CpdParams {
            beta: self.beta,
            lambda: self.lambda,
            w: self.w,
            max_iterations: self.max_iterations,
            tolerance: self.tolerance,
            rank: self.rank,
            accelerate: !self.no_accelerate,
            coarse: (self.coarse > 0).then_some(self.coarse),
        };
        params.validate()?;
        Ok(params)
    }
}

/// The camera and pose flags shared by render, grad and register.
#[derive(clap::Args)]
pub struct ViewArgs {
    /// Pinhole intrinsics in pixels: fx,fy,cx,cy.
    #[arg(long)]
    pub intrinsics: String,
    /// Image size WxH.
    #[arg(long)]
    pub size: String,
    /// Object-to-camera pose tx,ty,tz,rx,ry,rz (metres; axis-angle in radians).
    #[arg(long, allow_hyphen_values = true)]
    pub pose: String,
    /// Near clipping distance in metres.
    #[arg(long, allow_negative_numbers = true, default_value_t = Camera::DEFAULT_NEAR)]
    pub near: f64,
}

impl ViewArgs {
    pub fn view(&self) -> Result<View> {
        parse_view(&self.intrinsics, &self.size, &self.pose, self.near)
    }
}

/// `--depth-scale` where the command has no depth unit to take (eval renders its depth,
/// eval-frames reads BOP's `depth_scale`): the flag once named the depth cost's scale, now
/// `--depth-sigma`, and clap alone would suggest `--depth-holes`.
#[derive(clap::Args)]
pub struct RenamedArgs {
    #[arg(long = "depth-scale", hide = true, allow_hyphen_values = true)]
    depth_scale: Option<String>,
}

impl RenamedArgs {
    pub fn check(&self) -> Result<()> {
        if self.depth_scale.is_some() {
            anyhow::bail!(
                "--depth-scale is the unit of a depth PNG (register's flag; eval-frames reads \
                 scene_camera.json's depth_scale): the depth cost's scale is --depth-sigma"
            );
        }
        Ok(())
    }
}

#[derive(clap::Args)]
pub struct DepthLossArgs {
    /// Metres: the depth cost's scale. A pixel's depth residual r costs (r/s)^2 / (1 +
    /// (r/s)^2): about (r/s)^2 when small, half a wrong mask pixel at s, never more than one.
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr::diff::DepthLoss::default().scale)]
    pub depth_sigma: f64,
    /// Weight of the depth term against the mask (or shading) term.
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr::diff::DepthLoss::default().weight)]
    pub depth_weight: f64,
    /// Metres: a rendered pixel outside the observed mask whose measured depth is nearer
    /// than the rendered surface by more than this is hidden by something in front and
    /// counts for nothing (0: off).
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr::diff::DepthLoss::default().occlusion)]
    pub occlusion: f64,
    /// Compare the depth at a coarser step of the rendered pixels that keeps at least this
    /// many samples across the object (32: a third faster on a real mug at the same
    /// error), each weighted by the step squared, where a region of interest is rendered
    /// (RegisterParams::depth_detail); 0: at every pixel (noisy depth averages better).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub depth_detail: u32,
}

impl DepthLossArgs {
    pub fn loss(&self) -> Result<vkdr::diff::DepthLoss> {
        let loss = vkdr::diff::DepthLoss {
            scale: self.depth_sigma,
            weight: self.depth_weight,
            occlusion: self.occlusion,
        };
        loss.validate()
            .map_err(|e| anyhow::anyhow!("--depth-sigma, --depth-weight or --occlusion: {e}"))?;
        Ok(loss)
    }
}

#[derive(clap::Args)]
pub struct ShadingArgs {
    /// Observe and compare grey Lambert shading as well as the mask (the pose alignment
    /// still compares masks).
    #[arg(long)]
    pub shading: bool,
    /// Direction towards the light in the camera frame (x right, y down, z forward).
    #[arg(long, requires = "shading", default_value_t = default_light())]
    pub light: String,
    /// Ambient term of the shading, in [0, 1).
    #[arg(long, allow_negative_numbers = true, requires = "shading", default_value_t = vkdr::diff::Shading::default().ambient)]
    pub ambient: f64,
}

/// `Shading::default()`'s light as the flag writes it.
fn default_light() -> String {
    vkdr::diff::Shading::default()
        .light
        .map(|v| v.to_string())
        .join(",")
}

impl ShadingArgs {
    pub fn shading(&self) -> Result<Option<vkdr::diff::Shading>> {
        if !self.shading {
            return Ok(None);
        }
        let shading = vkdr::diff::Shading {
            light: parse_numbers::<3>(&self.light, "--light")?,
            ambient: self.ambient,
        };
        shading.unit_light()?;
        Ok(Some(shading))
    }
}

/// The camera and pose of the command-line flags.
pub fn parse_view(intrinsics: &str, size: &str, pose: &str, near: f64) -> Result<View> {
    let [fx, fy, cx, cy] = parse_numbers::<4>(intrinsics, "--intrinsics")?;
    let (width, height) = parse_size(size)?;
    let mut camera = Camera::new(fx, fy, cx, cy, width, height)?;
    camera.near = near;
    let camera = camera.validated()?;
    let [tx, ty, tz, rx, ry, rz] = parse_numbers::<6>(pose, "--pose")?;
    Ok(View {
        camera,
        pose: Pose::new([tx, ty, tz], [rx, ry, rz])?,
    })
}

/// The `--tilt-tolerance` flag of the commands with `--gravity`.
#[derive(clap::Args)]
pub struct TiltArgs {
    /// Degrees of tilt from --gravity that cost nothing (0 to 90; default 1).
    #[arg(long = "tilt-tolerance", allow_negative_numbers = true)]
    degrees: Option<f64>,
}

impl TiltArgs {
    /// The tolerance in radians: an error outside [0, 90) degrees, or where given without
    /// a gravity to apply it to.
    pub fn radians(&self, gravity: bool) -> Result<f64> {
        let Some(degrees) = self.degrees else {
            return Ok(vkdr::register::TILT_TOLERANCE);
        };
        if !gravity {
            anyhow::bail!("--tilt-tolerance is the tolerance of --gravity: give --gravity too");
        }
        if !(degrees.is_finite() && (0.0..90.0).contains(&degrees)) {
            anyhow::bail!("--tilt-tolerance must be 0 to 90 degrees, not {degrees}");
        }
        Ok(degrees.to_radians())
    }
}

/// The `--code-prior` flag: `auto` (the weight the observation's pixel count implies,
/// [`vkdr::register::observation_prior`]), or a weight in [0, 1] (0: none).
pub fn code_prior(text: &str, pixels: usize) -> Result<f64> {
    if text == "auto" {
        return Ok(vkdr::register::observation_prior(pixels));
    }
    match text.parse::<f64>() {
        Ok(w) if w.is_finite() && (0.0..=1.0).contains(&w) => Ok(w),
        _ => anyhow::bail!("--code-prior must be auto or a weight in [0, 1], not {text}"),
    }
}

/// The flags of a run in shards (`eval`, `eval-frames`): one process a shard, the tables
/// from their merge.
#[derive(clap::Args)]
pub struct ShardArgs {
    /// Evaluate shard K of N only (K from 0 to N-1, as $SLURM_ARRAY_TASK_ID), the units
    /// (a test instance, a frame's object) balanced by expected cost; writes
    /// OUT/shard.json for --merge.
    #[arg(long)]
    pub shard: Option<String>,
    /// A folder of shape spaces (CATEGORY.npz) and of the models' references (references/:
    /// each model's oracle and space optimum): read where they are there, computed and
    /// saved there where not, so that the shards of a run compute each once.
    #[arg(long)]
    pub spaces: Option<PathBuf>,
    /// Merge the shards of a run: OUT, then the shards' --out folders. Writes the tables
    /// one process would write into OUT, from the settings the shards carry.
    #[arg(long, num_args = 2.., value_names = ["OUT", "SHARD_DIR"], conflicts_with_all = ["out", "shard", "spaces"])]
    pub merge: Option<Vec<PathBuf>>,
    #[arg(long, required_unless_present = "merge")]
    out: Option<PathBuf>,
}

impl ShardArgs {
    /// The output folder: --out, or the first folder of --merge.
    pub fn out(&self) -> &Path {
        match (&self.merge, &self.out) {
            (Some(merge), _) => &merge[0],
            (None, Some(out)) => out,
            (None, None) => unreachable!("clap requires --out or --merge"),
        }
    }

    /// The shard to evaluate (None: every unit), after checking that --spaces can be a
    /// folder of spaces.
    pub fn shard(&self) -> Result<Option<crate::shard::Shard>> {
        crate::shard::check_spaces(self.spaces.as_deref())?;
        self.shard
            .as_deref()
            .map(crate::shard::Shard::parse)
            .transpose()
    }
}
