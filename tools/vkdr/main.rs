//! The `vkdr` command line: device information, G-buffer renders and the demo.

mod bench;
mod bench_register;
mod check_cmd;
mod choices;
mod cpd_cmd;
mod eval_cmd;
mod grad;
mod out;
mod pictures;
mod register_cmd;
mod shape_cmd;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context as _, Result};
use clap::{Parser, Subcommand};
use ndarray::s;

use vkdr::camera::{parse_numbers, parse_size};
use vkdr::cpd::CpdParams;
use vkdr::gpu::Context;
use vkdr::io::{write_npy, write_png};
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::{Camera, Mesh, Pose};

use choices::{LossChoice, OptimizerChoice};

#[derive(Parser)]
#[command(
    name = "vkdr",
    version,
    about = "Differentiable rasterization and deformable registration on Vulkan"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Write into an --out folder that already holds files (files of the same names are
    /// replaced, the rest stay), or over an existing --out file.
    #[arg(long, global = true)]
    force: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Print the chosen Vulkan device, its driver, features and limits.
    Info,
    /// Render a mesh's G-buffer (triangle ids, barycentrics, depth) and pictures of it.
    Render(RenderArgs),
    /// Loss and exact gradients (vertices and pose) of a render against an observed mask.
    Grad(GradArgs),
    /// Time forward and backward passes against a plain colour render (1e3..1e6 vertices).
    Bench {
        /// Image size WxH, or one number for a square image.
        #[arg(long, default_value = "1024")]
        size: String,
        /// Timed repeats per mesh (after one warm-up); medians are reported.
        #[arg(long, default_value_t = 10)]
        repeats: usize,
        /// Skip meshes with more vertices than this.
        #[arg(long, default_value_t = 1_000_000)]
        max_vertices: usize,
        /// Loss of the timed iteration.
        #[arg(long, value_enum, default_value_t = LossChoice::Mse)]
        loss: LossChoice,
        /// Output directory for bench.csv, bench.json and bench.png.
        #[arg(long)]
        out: PathBuf,
    },
    /// Time one registration at benchmark size (640x480, ~1e4 vertices, pose noise):
    /// wall time, device time per pass, batched throughput, speed against error.
    BenchRegister(bench_register::Args),
    /// Non-rigid Coherent Point Drift of SOURCE onto TARGET (OBJ vertices or N x 3 .npy).
    Cpd {
        source: PathBuf,
        target: PathBuf,
        #[command(flatten)]
        cpd: CpdArgs,
        /// Output directory for deformed.npy, W.npy and log.json.
        #[arg(long)]
        out: PathBuf,
    },
    /// Generate the category dataset (bottle, mug, spray_bottle, drill) in the design's layout.
    GenDataset {
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Training instances per category.
        #[arg(long, default_value_t = 10)]
        train: usize,
        /// Test instances per category.
        #[arg(long, default_value_t = 2)]
        test: usize,
    },
    /// Check a category dataset (DIR with category folders, or one category folder) before
    /// a long run: sizes, units, up axis, open or unwelded meshes, frame; contact sheets.
    CheckDataset {
        dataset: PathBuf,
        /// Where report.txt and contact_<category>.png go.
        #[arg(long)]
        out: PathBuf,
    },
    /// Build a category's latent shape space (CPD from the canonical mesh, then PCA).
    ShapeSpace {
        /// DIR/<category> with canonical.obj and train/*.obj.
        category_dir: PathBuf,
        /// Use train/NAME.obj as the canonical instead of canonical.obj (or `auto`: the
        /// training instance with the lowest mean nearest-neighbour distance to the others).
        #[arg(long)]
        canonical: Option<String>,
        #[arg(long, default_value_t = 5)]
        dims: usize,
        #[command(flatten)]
        cpd: CpdArgs,
        /// Run even where `check-dataset` finds the category unusable.
        #[arg(long)]
        skip_checks: bool,
        /// Output .npz (a .npz.json description is written beside it).
        #[arg(long)]
        out: PathBuf,
    },
    /// Register a shape space to an observed mask (render-and-compare on the device).
    Register(register_cmd::Args),
    /// The paper's Table 1 on a dataset: oracle, known pose and pose noise per test instance.
    Eval(EvalArgs),
    /// The quick start: generate a dataset, build a shape space, register a held-out
    /// instance from a rendered mask with pose noise, print its Table-1 row, write pictures.
    Demo {
        /// Where to write the results.
        #[arg(long, default_value = "vkdr-demo")]
        out: PathBuf,
    },
}

/// The CPD flags shared by cpd and shape-space.
#[derive(clap::Args)]
struct CpdArgs {
    /// Kernel width, in units of the source's RMS radius.
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().beta)]
    beta: f64,
    /// Smoothness weight.
    #[arg(long = "lambda", allow_negative_numbers = true, default_value_t = CpdParams::default().lambda)]
    lambda: f64,
    /// Outlier weight, in (0, 1).
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().w)]
    w: f64,
    #[arg(long, default_value_t = CpdParams::default().max_iterations)]
    max_iterations: usize,
    /// Stop when an iteration lowers the objective (negative log-likelihood plus the
    /// smoothness term) by less than this fraction of it and moves the points by less
    /// than this many source RMS radii on average.
    #[arg(long, allow_negative_numbers = true, default_value_t = CpdParams::default().tolerance)]
    tolerance: f64,
    /// Replace the kernel by its Nystrom approximation from this many landmarks (faster,
    /// approximate); by default the M-step uses the exact kernel.
    #[arg(long)]
    rank: Option<usize>,
    /// Plain EM iterations, as pycpd's (no SQUAREM extrapolation).
    #[arg(long)]
    no_accelerate: bool,
    /// Above twice this many source points, register subsets of this many source points
    /// first and start the full sets from their field: 2-3x faster from 2e4 points on,
    /// accuracy varies (e.g. 5000; 0: one stage)
    #[arg(long, default_value_t = 0)]
    coarse: usize,
}

impl CpdArgs {
    /// The parameters, checked before any file is read.
    fn params(&self) -> Result<CpdParams> {
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
struct ViewArgs {
    /// Pinhole intrinsics in pixels: fx,fy,cx,cy.
    #[arg(long)]
    intrinsics: String,
    /// Image size WxH.
    #[arg(long)]
    size: String,
    /// Object-to-camera pose tx,ty,tz,rx,ry,rz (metres; axis-angle in radians).
    #[arg(long, allow_hyphen_values = true)]
    pose: String,
    /// Near clipping distance in metres.
    #[arg(long, allow_negative_numbers = true, default_value_t = Camera::DEFAULT_NEAR)]
    near: f64,
}

impl ViewArgs {
    fn view(&self) -> Result<View> {
        parse_view(&self.intrinsics, &self.size, &self.pose, self.near)
    }
}

#[derive(clap::Args)]
struct RenderArgs {
    /// OBJ file (triangle ids follow its face order).
    mesh: PathBuf,
    #[command(flatten)]
    view: ViewArgs,
    /// Also write the raw G-buffer: ids.npy, bary.npy, depth.npy.
    #[arg(long)]
    raw: bool,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args)]
struct EvalArgs {
    /// A dataset in the layout of `vkdr gen-dataset`.
    #[arg(long)]
    dataset: PathBuf,
    #[arg(long, default_value_t = 10)]
    trials: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Only these categories (comma-separated).
    #[arg(long)]
    categories: Option<String>,
    /// Dimensions of each category's shape space (at most its training instances less one).
    #[arg(long, default_value_t = vkdr_app::eval::EvalSettings::default().dims)]
    dims: usize,
    /// Iterations with pose noise, after the alignment's.
    #[arg(long, default_value_t = vkdr_app::eval::EvalSettings::default().pose_noise.iterations)]
    noise_iterations: usize,
    /// Iterations with the pose known.
    #[arg(long, default_value_t = vkdr_app::eval::EvalSettings::default().known_pose.iterations)]
    known_iterations: usize,
    /// Loss of both conditions (default: each condition's own).
    #[arg(long, value_enum)]
    loss: Option<LossChoice>,
    /// Length of the first latent step, in training standard deviations.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.5)]
    latent_step: f64,
    /// Optimiser of both conditions (default: each condition's own).
    #[arg(long, value_enum)]
    optimizer: Option<OptimizerChoice>,
    /// First pose steps with pose noise: translation (m) and rotation (rad).
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr_app::eval::EvalSettings::default().pose_noise.translation_step)]
    translation_step: f64,
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr_app::eval::EvalSettings::default().pose_noise.rotation_step)]
    rotation_step: f64,
    /// With pose noise: update the pose once every this many iterations...
    #[arg(long, default_value_t = vkdr_app::eval::EvalSettings::default().pose_noise.pose_every)]
    pose_every: usize,
    /// With pose noise: iterations that first align the pose alone (distance loss).
    #[arg(long, default_value_t = vkdr_app::eval::EvalSettings::default().pose_noise.align)]
    align: usize,
    /// Also optimise pose and shape from the true pose (a column of its own): where the
    /// silhouette's optimum lies, apart from the start.
    #[arg(long)]
    from_truth: bool,
    #[command(flatten)]
    shading: ShadingArgs,
    /// Observe the test instance's rendered depth too (then z is optimised with pose noise).
    #[arg(long)]
    depth: bool,
    /// Standard deviation of Gaussian noise added to every measured depth, metres.
    #[arg(
        long,
        allow_negative_numbers = true,
        requires = "depth",
        default_value_t = 0.0
    )]
    depth_noise: f64,
    #[command(flatten)]
    depth_loss: DepthLossArgs,
    /// Cameras per trial, 1 to 6: the others at seeded azimuths at least 60 degrees from
    /// every other, their relative poses known, one code and object pose for all.
    #[arg(long, default_value_t = 1)]
    views: usize,
    /// Keep the distance (z) at its true value with pose noise even with --depth or --views
    /// (as with one mask).
    #[arg(long)]
    fix_z: bool,
    /// With pose noise: weight of a Gaussian prior on the code (RegisterParams::code_prior;
    /// with the pose known the images leave no shift of the shape open). 0: none.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0)]
    code_prior: f64,
    /// Run even where `check-dataset` finds the set unusable (millimetres, no meshes, ...).
    #[arg(long)]
    skip_checks: bool,
    #[arg(long)]
    out: PathBuf,
}

#[derive(clap::Args)]
struct DepthLossArgs {
    /// Depth residuals up to this (metres) cost quadratically, beyond linearly (Huber).
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr::diff::DepthLoss::default().scale)]
    depth_scale: f64,
    /// Weight of the depth term against the mask (or shading) term.
    #[arg(long, allow_negative_numbers = true, default_value_t = vkdr::diff::DepthLoss::default().weight)]
    depth_weight: f64,
}

impl DepthLossArgs {
    fn loss(&self) -> Result<vkdr::diff::DepthLoss> {
        let loss = vkdr::diff::DepthLoss {
            scale: self.depth_scale,
            weight: self.depth_weight,
        };
        loss.validate()?;
        Ok(loss)
    }
}

#[derive(clap::Args)]
struct ShadingArgs {
    /// Observe and compare grey Lambert shading as well as the mask (the pose alignment
    /// still compares masks).
    #[arg(long)]
    shading: bool,
    /// Direction towards the light in the camera frame (x right, y down, z forward).
    #[arg(long, requires = "shading", default_value_t = default_light())]
    light: String,
    /// Ambient term of the shading, in [0, 1).
    #[arg(long, allow_negative_numbers = true, requires = "shading", default_value_t = vkdr::diff::Shading::default().ambient)]
    ambient: f64,
}

/// `Shading::default()`'s light as the flag writes it.
fn default_light() -> String {
    vkdr::diff::Shading::default()
        .light
        .map(|v| v.to_string())
        .join(",")
}

impl ShadingArgs {
    fn shading(&self) -> Result<Option<vkdr::diff::Shading>> {
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

#[derive(clap::Args)]
struct GradArgs {
    /// OBJ file (vertex_grad.npy follows its vertex order).
    mesh: PathBuf,
    /// Observed mask PNG (nonzero = object), of exactly --size.
    #[arg(long)]
    observed: PathBuf,
    #[command(flatten)]
    view: ViewArgs,
    /// The loss.
    #[arg(long, value_enum, default_value_t = LossChoice::Mse)]
    loss: LossChoice,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

fn main() {
    let cli = Cli::parse();
    let created = match claim_out(&cli.command, cli.force) {
        Ok(created) => created,
        Err(e) => {
            eprintln!("error: {}", report(&e));
            std::process::exit(1);
        }
    };
    let result = match cli.command {
        Command::Info => info(),
        Command::CheckDataset { dataset, out } => check_cmd::run(&dataset, &out),
        Command::Render(args) => render(&args),
        Command::Grad(args) => grad(&args),
        Command::Bench {
            size,
            repeats,
            max_vertices,
            loss,
            out,
        } => bench(&size, repeats, max_vertices, loss.into(), &out),
        Command::BenchRegister(args) => Context::new()
            .map_err(anyhow::Error::from)
            .and_then(|ctx| bench_register::run(&ctx, &args)),
        Command::Demo { out } => demo(&out),
        Command::GenDataset {
            out,
            seed,
            train,
            test,
        } => gen_dataset(&out, seed, train, test, cli.force),
        Command::Register(args) => register_cmd::run(&args),
        Command::Eval(args) => eval_command(&args),
        Command::ShapeSpace {
            category_dir,
            canonical,
            dims,
            cpd,
            skip_checks,
            out,
        } => (|| {
            let params = cpd.params()?;
            if dims == 0 {
                bail!("--dims must be at least 1 (a shape space of no dimensions is the canonical alone)");
            }
            check_cmd::check_first(&category_dir, skip_checks, canonical.is_some())?;
            shape_cmd::run(&category_dir, canonical.as_deref(), dims, &params, &out)
        })(),
        Command::Cpd {
            source,
            target,
            cpd,
            out,
        } => {
            cpd.params().and_then(|params| cpd_cmd::run(&source, &target, &params, &out)).map(|r| {
                println!(
                    "{} iterations ({}) in {:.3} s; final sigma^2 {:.3e}; wrote {4}/deformed.npy, {4}/W.npy, {4}/log.json",
                    r.iterations,
                    r.stop.describe(),
                    r.seconds,
                    r.sigma2.last().copied().unwrap_or(f64::NAN),
                    out.display()
                );
            })
        }
    };
    if let Err(e) = result {
        if let Some(dir) = created {
            out::release(&dir);
        }
        eprintln!("error: {}", report(&e));
        std::process::exit(1);
    }
}

/// Claims the command's --out before any work (see `out`); returns the output folder
/// when the claim created it.
fn claim_out(command: &Command, force: bool) -> Result<Option<PathBuf>> {
    let dir = match command {
        Command::Info => return Ok(None),
        Command::ShapeSpace { out, .. } => {
            out::claim_file(out, force)?;
            return Ok(None);
        }
        Command::Demo { out } => {
            let created = out::claim_dir(out, force, Some(out::DEMO_MARK))?;
            return Ok(created.then(|| out.clone()));
        }
        Command::CheckDataset { out, .. }
        | Command::Bench { out, .. }
        | Command::GenDataset { out, .. }
        | Command::Cpd { out, .. } => out,
        Command::Render(RenderArgs { out, .. })
        | Command::Grad(GradArgs { out, .. })
        | Command::Eval(EvalArgs { out, .. }) => out,
        Command::BenchRegister(args) => &args.out,
        Command::Register(args) => args.out(),
    };
    let created = out::claim_dir(dir, force, None)?;
    Ok(created.then(|| dir.to_path_buf()))
}

/// The error and its causes in one line, each cause once (a cause whose text the message
/// already holds, as an I/O error that names its file, is not repeated).
fn report(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let said = cause.to_string();
        if !text.contains(&said) {
            if !text.is_empty() {
                text.push_str(": ");
            }
            text.push_str(&said);
        }
    }
    text
}

fn info() -> Result<()> {
    let devices = Context::list_devices()?;
    println!("Vulkan devices:");
    for (i, name) in devices.iter().enumerate() {
        println!("  {i}: {name}");
    }
    let ctx = Context::new()?;
    let d = ctx.info();
    println!("chosen: {} ({}), index {}", d.name, d.kind, d.index);
    println!(
        "  Vulkan {} / driver {} {}",
        d.api_version, d.driver_name, d.driver_info
    );
    println!("  features:");
    let width = d.features.iter().map(|(n, _)| n.len()).max().unwrap_or(0);
    for (name, has) in &d.features {
        println!(
            "    {name:<width$}  {}",
            if *has { "yes" } else { "MISSING" }
        );
    }
    println!("  limits:");
    println!(
        "    subPixelPrecisionBits           {}",
        d.sub_pixel_precision_bits
    );
    println!(
        "    maxImageDimension2D             {}",
        d.max_image_dimension_2d
    );
    println!(
        "    maxStorageBufferRange           {} MiB",
        d.max_storage_buffer_range >> 20
    );
    println!(
        "    minStorageBufferOffsetAlignment {}",
        d.min_storage_buffer_offset_alignment
    );
    println!(
        "    maxComputeWorkGroupInvocations  {}",
        d.max_compute_workgroup_invocations
    );
    println!(
        "    maxPushConstantsSize            {}",
        d.max_push_constants_size
    );
    println!(
        "    timestampPeriod                 {} ns",
        d.timestamp_period_ns
    );
    println!(
        "  grid-stride passes use at most {} workgroups of 64 ({} device; subgroups of {})",
        d.grid_groups, d.kind, d.subgroup_size
    );
    Ok(())
}

/// The camera and pose of the command-line flags.
fn parse_view(intrinsics: &str, size: &str, pose: &str, near: f64) -> Result<View> {
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

fn grad(args: &GradArgs) -> Result<()> {
    let mesh = Mesh::load_obj(&args.mesh)?;
    let view = args.view.view()?;
    let loss: vkdr::loss::Loss = args.loss.into();
    let ctx = Context::new()?;
    let result = grad::run(&ctx, &mesh, view, &args.observed, loss, &args.out)?;
    println!("loss ({}): {:e}", loss.name(), result.loss[0]);
    let p = result.pose_gradient[0];
    println!(
        "pose gradient: translation [{:e}, {:e}, {:e}], rotation [{:e}, {:e}, {:e}]",
        p[0], p[1], p[2], p[3], p[4], p[5]
    );
    println!(
        "wrote {0}/loss.json, {0}/vertex_grad.npy, {0}/pose_grad.npy, {0}/gradient.png",
        args.out.display()
    );
    Ok(())
}

fn bench(
    size: &str,
    repeats: usize,
    max_vertices: usize,
    loss: vkdr::loss::Loss,
    out: &Path,
) -> Result<()> {
    let size = match size.parse::<u32>() {
        Ok(s) => (s, s),
        Err(_) => parse_size(size)?,
    };
    let ctx = Context::new()?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    println!("device: {device}");
    let args = bench::BenchArgs {
        size,
        repeats: repeats.max(1),
        max_vertices,
        loss,
    };
    let rows = bench::run(&ctx, &args)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    bench::write(out, &rows, size, &device)?;
    println!("vertices,faces,forward_ms,backward_ms,plain_ms,ratio,dtz_error,stretch_error");
    for r in &rows {
        println!(
            "{},{},{:.3},{:.3},{:.3},{:.2},{:.4},{:.4}",
            r.vertices,
            r.faces,
            r.forward_ms,
            r.backward_ms,
            r.plain_ms,
            r.ratio,
            r.dtz_error,
            r.stretch_error
        );
    }
    println!(
        "wrote {0}/bench.csv, {0}/bench.json and {0}/bench.png",
        out.display()
    );
    Ok(())
}

fn render(args: &RenderArgs) -> Result<()> {
    let mesh = Mesh::load_obj(&args.mesh)?;
    let view = args.view.view()?;
    let (camera, pose) = (view.camera, view.pose);
    let (width, height) = (camera.width, camera.height);

    let ctx = Context::new()?;
    let rasterizer = Rasterizer::new(&ctx)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let written = write_views(
        &ctx,
        &rasterizer,
        &mesh,
        &[View { camera, pose }],
        &args.out,
        args.raw,
    )?;
    println!(
        "rendered {} triangles at {width}x{height} on {}; wrote {}",
        mesh.triangle_count(),
        ctx.info().name,
        written.join(", ")
    );
    Ok(())
}

/// Renders the views and writes pictures (and the raw G-buffer) into `out`; with several
/// views, file names get a `view<k>_` prefix. Returns the written paths.
fn write_views(
    ctx: &Context,
    rasterizer: &Rasterizer,
    mesh: &Mesh,
    views: &[View],
    out: &Path,
    raw: bool,
) -> Result<Vec<String>> {
    let gbuffer = rasterizer.render(ctx, mesh, views, Outputs::IdsBaryDepth)?;
    let colour = rasterizer.render_shaded(ctx, mesh, views)?;
    let depth = gbuffer
        .depth
        .as_ref()
        .context("G-buffer rendered without depth")?;
    let bary_all = gbuffer
        .bary
        .as_ref()
        .context("G-buffer rendered without barycentrics")?;
    let mut written = Vec::new();
    for k in 0..views.len() {
        let prefix = if views.len() > 1 {
            format!("view{k}_")
        } else {
            String::new()
        };
        let ids = gbuffer.ids.slice(s![k, .., ..]);
        let bary = bary_all.slice(s![k, .., .., ..]);
        let z = depth.slice(s![k, .., ..]);
        let mut save = |name: &str, picture: image::DynamicImage| -> Result<()> {
            let path = out.join(format!("{prefix}{name}"));
            write_png(&path, &picture)?;
            written.push(path.display().to_string());
            Ok(())
        };
        save(
            "colour.png",
            pictures::colour(colour.slice(s![k, .., .., ..])),
        )?;
        save("mask.png", pictures::mask(ids))?;
        save("ids.png", pictures::ids(ids))?;
        save("bary.png", pictures::barycentrics(ids, bary))?;
        save("depth.png", pictures::depth(z))?;
        if raw {
            for (name, result) in [
                (
                    "ids.npy",
                    write_npy(&out.join(format!("{prefix}ids.npy")), &ids),
                ),
                (
                    "bary.npy",
                    write_npy(&out.join(format!("{prefix}bary.npy")), &bary),
                ),
                (
                    "depth.npy",
                    write_npy(&out.join(format!("{prefix}depth.npy")), &z),
                ),
            ] {
                result?;
                written.push(out.join(format!("{prefix}{name}")).display().to_string());
            }
        }
    }
    Ok(written)
}

/// `vkdr eval`: the default settings with the flags' changes.
fn eval_command(args: &EvalArgs) -> Result<()> {
    if args.dims == 0 {
        bail!("--dims must be at least 1");
    }
    if !(2..=1000).contains(&args.trials) {
        bail!(
            "--trials must be 2 to 1000 (a spread needs two), not {}",
            args.trials
        );
    }
    let mut settings = vkdr_app::eval::EvalSettings {
        trials: args.trials,
        seed: args.seed,
        dims: args.dims,
        ..Default::default()
    };
    settings.pose_noise.iterations = args.noise_iterations;
    settings.known_pose.iterations = args.known_iterations;
    settings.pose_noise.translation_step = args.translation_step;
    settings.pose_noise.rotation_step = args.rotation_step;
    settings.pose_noise.pose_every = args.pose_every;
    settings.pose_noise.align = args.align;
    settings.from_truth = args.from_truth;
    settings.shading = args.shading.shading()?;
    if args.depth {
        settings.depth = Some(args.depth_loss.loss()?);
    }
    if !(args.depth_noise.is_finite() && (0.0..=1.0).contains(&args.depth_noise)) {
        bail!(
            "--depth-noise must be a standard deviation in metres, 0 to 1, not {}",
            args.depth_noise
        );
    }
    settings.depth_noise = args.depth_noise;
    if !(1..=6).contains(&args.views) {
        bail!(
            "--views must be 1 to 6 (views at least 60 degrees apart), not {}",
            args.views
        );
    }
    settings.views = args.views;
    settings.fix_z = args.fix_z;
    settings.pose_noise.code_prior = args.code_prior;
    let loss: Option<vkdr::loss::Loss> = args.loss.map(Into::into);
    let optimizer: Option<vkdr::register::Optimizer> = args.optimizer.map(Into::into);
    for params in [&mut settings.known_pose, &mut settings.pose_noise] {
        params.latent_step = args.latent_step;
        params.optimizer = optimizer.unwrap_or(params.optimizer);
        params.loss = loss.unwrap_or(params.loss);
        params.validate()?;
    }
    eval(
        &args.dataset,
        settings,
        args.categories.as_deref(),
        args.skip_checks,
        &args.out,
    )
}

fn eval(
    dataset: &Path,
    settings: vkdr_app::eval::EvalSettings,
    categories: Option<&str>,
    skip_checks: bool,
    out: &Path,
) -> Result<()> {
    let ctx = Context::new()?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    let only: Option<Vec<String>> =
        categories.map(|c| c.split(',').map(|s| s.trim().to_string()).collect());
    let (rows, failures) = eval_cmd::eval(
        &ctx,
        dataset,
        &settings,
        only.as_deref(),
        skip_checks,
        |rows| eval_cmd::write_reports(out, rows, &settings, &device),
    )?;
    if !rows.is_empty() {
        print!("{}", std::fs::read_to_string(out.join("table.md"))?);
        println!(
            "wrote {0}/table.md, table.csv, table.json, trials.csv, speed_vs_error.png",
            out.display()
        );
    }
    if !failures.is_empty() {
        bail!(
            "{} of the categories failed{}:\n  {}",
            failures.len(),
            if rows.is_empty() {
                String::new()
            } else {
                format!(" (the others' tables are in {})", out.display())
            },
            failures.join("\n  ")
        );
    }
    Ok(())
}

fn gen_dataset(out: &Path, seed: u64, train: usize, test: usize, force: bool) -> Result<()> {
    if force {
        // A dataset written over with fewer meshes must not keep the old ones beside the
        // new info.json: each generated category's folder is replaced whole.
        for category in vkdr_app::dataset::CATEGORIES {
            let dir = out.join(category);
            if dir.is_dir() {
                std::fs::remove_dir_all(&dir)
                    .with_context(|| format!("replacing {}", dir.display()))?;
            }
        }
    }
    let dirs = vkdr_app::dataset::generate(out, seed, train, test, |category, done, total| {
        eprint!("\r  {category:<14} {done:>3}/{total}");
        if done == total {
            eprintln!();
        }
    })?;
    for dir in dirs {
        println!("wrote {}", dir.display());
    }
    Ok(())
}

fn demo(out: &Path) -> Result<()> {
    let started = Instant::now();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    vkdr::io::write_atomically(
        &out.join(out::DEMO_MARK),
        b"Written by `vkdr demo`: a later demo writes over this folder without --force.\n",
    )?;
    let ctx = Context::new()?;
    println!("device: {} ({})", ctx.info().name, ctx.info().driver_info);

    // 1. A generated dataset.
    let dataset = out.join("dataset");
    vkdr_app::dataset::generate(&dataset, 0, 10, 2, |_, _, _| {})?;
    println!(
        "1. generated {} (bottle, mug, spray_bottle, drill: 10 training and 2 test meshes each)",
        dataset.display()
    );

    // 2. The bottle's shape space from its training instances.
    let category = dataset.join("bottle");
    let space_path = out.join("bottle_space.npz");
    shape_cmd::run(&category, None, 5, &CpdParams::default(), &space_path)?;
    let space = vkdr::shape::ShapeSpace::load(&space_path)?;
    println!(
        "2. built the bottle shape space ({} dimensions) -> {}",
        space.dims(),
        space_path.display()
    );

    // 3. Register a held-out bottle from rendered masks, with the pose known and with
    //    pose noise, over a few seeded trials: its Table-1 row.
    let test_path = shape_cmd::obj_files(&category.join("test"))?
        .into_iter()
        .next()
        .context("no test bottle")?;
    let test = Mesh::load_obj(&test_path)?;
    let settings = vkdr_app::eval::EvalSettings {
        trials: 3,
        up: vkdr_app::check::Info::read(&category)?.up,
        ..Default::default()
    };
    let registrar = vkdr::register::Registrar::new(&ctx)?;
    let evaluate = |settings: &vkdr_app::eval::EvalSettings| {
        vkdr_app::eval::evaluate_instance(
            &ctx,
            &registrar,
            &space,
            "bottle",
            "test_00",
            &test,
            settings,
            |_, _| {},
        )
    };
    let row = evaluate(&settings)?;
    println!(
        "3. {}: oracle {:.2} mm | known pose {:.2} +- {:.2} mm ({:.2}x oracle) | pose noise {:.2} +- {:.2} mm ({:.2}x) | {:.0} iterations, {:.0} ms ({:.1} ms per iteration)",
        test_path.display(),
        1e3 * row.oracle,
        1e3 * row.known_pose.mean,
        1e3 * row.known_pose.std,
        row.known_pose.mean / row.oracle,
        1e3 * row.pose_noise.mean,
        1e3 * row.pose_noise.std,
        row.pose_noise.mean / row.oracle,
        row.iterations,
        row.ms,
        row.ms_per_iteration
    );
    let shaded_settings = vkdr_app::eval::EvalSettings {
        shading: Some(vkdr::diff::Shading::default()),
        ..settings.clone()
    };
    let shaded = evaluate(&shaded_settings)?;
    println!(
        "   with the shading observed too (a light at the camera): known pose {:.2} mm ({:.2}x) | pose noise {:.2} +- {:.2} mm ({:.2}x) | {:.0} ms",
        1e3 * shaded.known_pose.mean,
        shaded.known_pose.mean / shaded.oracle,
        1e3 * shaded.pose_noise.mean,
        1e3 * shaded.pose_noise.std,
        shaded.pose_noise.mean / shaded.oracle,
        shaded.ms,
    );

    // 4. One registration with pose noise, with pictures.
    let truth = vkdr_app::eval::view_pose_up(settings.up, 0.8, 0.5, settings.distance);
    let view = View {
        camera: settings.camera,
        pose: truth,
    };
    let mask = vkdr_app::eval::render_mask(&ctx, &registrar, &test, view)?;
    let start = Pose {
        translation: truth.translation + glam::DVec3::new(0.03, -0.02, 0.0),
        rotation: truth.rotation + glam::DVec3::new(0.1, -0.15, 0.05),
    };
    let register_out = out.join("register");
    let job = vkdr::register::Job::new(
        &space,
        &mask,
        View {
            camera: settings.camera,
            pose: start,
        },
    );
    let result = eval_cmd::register(&ctx, job, &settings.pose_noise, &register_out)?;
    println!(
        "4. registered with pose noise in {:.0} ms: error {:.2} mm; pictures {2}/overlay_start.png, {2}/overlay_end.png (observed blue, rendered red)",
        result.milliseconds,
        1e3 * vkdr_app::eval::surface_error(
            &vkdr_app::eval::surface_sample(&test, vkdr_app::eval::SAMPLE_POINTS, 0),
            &result.vertices,
            space.canonical.triangles()
        ),
        register_out.display()
    );
    let render_out = out.join("render");
    std::fs::create_dir_all(&render_out)?;
    let deformed = Mesh::load_obj(register_out.join("deformed.obj"))?;
    let written = write_views(
        &ctx,
        &Rasterizer::new(&ctx)?,
        &deformed,
        &[View {
            camera: settings.camera,
            pose: result.pose,
        }],
        &render_out,
        true,
    )?;
    println!("5. G-buffer of the registered mesh: {}", written.join(", "));
    println!("done in {:.1} s", started.elapsed().as_secs_f64());
    Ok(())
}
