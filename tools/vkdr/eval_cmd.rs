//! `vkdr eval`: the paper's Table 1 on a dataset; and the registration with pictures that
//! `vkdr register` and `vkdr demo` share, and the reports they write.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use glam::DVec3;
use image::{Rgb, RgbImage};

use vkdr::gpu::Context;
use vkdr::io::{write_atomically, write_json, write_npy, write_png};
use vkdr::raster::View;
use vkdr::register::{Job, RegisterParams, Registrar, Registration};
use vkdr::shape::ShapeSpace;
use vkdr::{Mesh, Pose};
use vkdr_app::eval::{self, EvalSettings, Row, Trial};
use vkdr_app::plot::{Plot, PALETTE};

use crate::args::{DepthLossArgs, RenamedArgs, ShadingArgs};
use crate::choices::{LossChoice, OptimizerChoice};
use crate::shape_cmd::obj_files;
use crate::shard;

#[derive(clap::Args)]
pub struct Args {
    /// A dataset in the layout of `vkdr gen-dataset`.
    #[arg(long, required_unless_present = "merge")]
    dataset: Option<PathBuf>,
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
    #[command(flatten)]
    renamed: RenamedArgs,
    /// Cameras per trial, 1 to 6: the others at seeded azimuths at least 60 degrees from
    /// every other, their relative poses known, one code and object pose for all.
    #[arg(long, default_value_t = 1)]
    views: usize,
    /// With --views: draw each further view its own elevation (10 to 60 degrees, as the
    /// first's) instead of sharing the first's.
    #[arg(long)]
    own_elevations: bool,
    /// Keep the distance (z) at its true value with pose noise even with --depth or --views
    /// (as with one mask).
    #[arg(long)]
    fix_z: bool,
    /// With pose noise: starts per trial, the noisy start and it turned about the up axis
    /// by +-15, +-30, ... degrees (the rotation noise); the noisy start is registered and
    /// the others' turns are tried on its fit, the joint fit running again from a turn
    /// that scores 5% lower (1 to 8; the time columns count it all).
    #[arg(long, default_value_t = vkdr::register::DEFAULT_STARTS)]
    starts: usize,
    /// Weight of the Gaussian prior on the code in training standard deviations
    /// (RegisterParams::code_prior), in both conditions: auto (the weight the image's
    /// pixel count implies, register::observation_prior) or a number (0: none).
    #[arg(long, allow_hyphen_values = true, default_value = "auto")]
    code_prior: String,
    /// A box in front of the left half of each object in the first view (with --depth its
    /// depth is measured and occlusion is found from the data; without, its pixels are
    /// unknown, as BOP's mask less mask_visib).
    #[arg(long)]
    occluder: bool,
    /// The table the object stands on, in the depth (needed by --gravity from-depth).
    #[arg(long, requires = "depth")]
    table: bool,
    /// This fraction of the depth missing, in clusters (0 to 0.9).
    #[arg(
        long,
        requires = "depth",
        allow_negative_numbers = true,
        default_value_t = 0.0
    )]
    depth_holes: f64,
    /// Scale every test instance by this about its origin (e.g. 1.25: larger than every
    /// training instance).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    test_scale: f64,
    /// Fit one uniform scale of the shape too, in both conditions (0.25 to 1.75).
    #[arg(long)]
    optimize_scale: bool,
    /// With pose noise, keep the object's up axis within --tilt-tolerance of up: `known`
    /// (the true up: a known table or IMU) or `from-depth` (the table fitted in the depth;
    /// needs --table).
    #[arg(long, value_parser = ["known", "from-depth"])]
    gravity: Option<String>,
    /// Degrees of tilt from --gravity that cost nothing.
    #[arg(
        long,
        requires = "gravity",
        allow_negative_numbers = true,
        default_value_t = 1.0
    )]
    tilt_tolerance: f64,
    /// Run even where `check-dataset` finds the set unusable (millimetres, no meshes, ...).
    #[arg(long)]
    skip_checks: bool,
    /// Evaluate shard K of N only (K from 0 to N-1, as $SLURM_ARRAY_TASK_ID), one test
    /// instance a unit, balanced by expected cost; writes OUT/shard.json for --merge.
    #[arg(long)]
    shard: Option<String>,
    /// A folder of shape spaces (CATEGORY.npz): each category's is read from it where it
    /// is there and built and saved there where not, so the shards of a run build each once.
    #[arg(long)]
    spaces: Option<PathBuf>,
    /// Merge the shards of a run: OUT, then the shards' --out folders. Writes the tables
    /// one process would write into OUT; the run's flags come from the shards.
    #[arg(long, num_args = 2.., value_names = ["OUT", "SHARD_DIR"], conflicts_with_all = ["dataset", "out", "shard", "spaces"])]
    merge: Option<Vec<PathBuf>>,
    #[arg(long, required_unless_present = "merge")]
    out: Option<PathBuf>,
}

impl Args {
    /// The output folder (--out, or the first folder of --merge).
    pub fn out(&self) -> &Path {
        shard::out_folder(&self.merge, &self.out)
    }
}

/// `eval`'s flags alone, to read a merged run's flags back.
#[derive(clap::Parser)]
#[command(name = "eval")]
struct Flags {
    #[command(flatten)]
    args: Args,
}

/// `vkdr eval`: the default settings with the flags' changes; a shard of them, or the
/// merge of shards.
pub fn run(args: &Args) -> Result<()> {
    if let Some(merge) = &args.merge {
        return shard::write_merged(
            "eval",
            &merge[0],
            &merge[1..],
            |line| {
                let settings = settings(&<Flags as clap::Parser>::try_parse_from(line)?.args)?;
                let resolved = shard::resolved(&settings);
                Ok((settings, resolved))
            },
            |out, rows, _, settings, device| match rows.is_empty() {
                true => Ok(()),
                false => write_reports(out, rows, settings, device),
            },
        );
    }
    let settings = settings(args)?;
    let shard = args.shard.as_deref().map(shard::Shard::parse).transpose()?;
    shard::check_spaces(args.spaces.as_deref())?;
    let plan = Plan {
        shard,
        spaces: args.spaces.as_deref(),
    };
    evaluate(
        args.dataset.as_deref().expect("clap requires --dataset"),
        settings,
        args.categories.as_deref(),
        args.skip_checks,
        &plan,
        args.out(),
    )
}

/// The evaluation's settings: the defaults with the flags' changes, each checked.
fn settings(args: &Args) -> Result<EvalSettings> {
    args.renamed.check()?;
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
    if args.own_elevations && args.views == 1 {
        bail!("--own-elevations draws the elevations of further views: give --views 2 or more");
    }
    settings.own_elevations = args.own_elevations;
    settings.fix_z = args.fix_z;
    vkdr::register::check_starts(args.starts).context("--starts")?;
    settings.starts = args.starts;
    let pixels = (settings.camera.width * settings.camera.height) as usize;
    let prior = crate::args::code_prior(&args.code_prior, pixels)?;
    settings.known_pose.code_prior = prior;
    settings.pose_noise.code_prior = prior;
    settings.occluder = args.occluder;
    settings.table = args.table;
    if !(args.depth_holes.is_finite() && (0.0..=0.9).contains(&args.depth_holes)) {
        bail!(
            "--depth-holes must be a fraction, 0 to 0.9, not {}",
            args.depth_holes
        );
    }
    settings.depth_holes = args.depth_holes;
    if !(args.test_scale.is_finite() && (0.1..=10.0).contains(&args.test_scale)) {
        bail!("--test-scale must be 0.1 to 10, not {}", args.test_scale);
    }
    settings.test_scale = args.test_scale;
    settings.known_pose.optimize_scale = args.optimize_scale;
    settings.pose_noise.optimize_scale = args.optimize_scale;
    settings.gravity = match args.gravity.as_deref() {
        None => None,
        Some("known") => Some(vkdr_app::eval::GravitySource::Known),
        Some(_) if !args.table => bail!(
            "--gravity from-depth fits the table the object stands on: give --table (and --depth)"
        ),
        Some(_) => Some(vkdr_app::eval::GravitySource::FromDepth),
    };
    settings.tilt_tolerance = crate::args::tilt_tolerance(args.tilt_tolerance)?;
    let loss: Option<vkdr::loss::Loss> = args.loss.map(Into::into);
    let optimizer: Option<vkdr::register::Optimizer> = args.optimizer.map(Into::into);
    for params in [&mut settings.known_pose, &mut settings.pose_noise] {
        params.latent_step = args.latent_step;
        params.optimizer = optimizer.unwrap_or(params.optimizer);
        params.loss = loss.unwrap_or(params.loss);
        params.validate()?;
    }
    Ok(settings)
}

/// What of the dataset one process evaluates, and where the shape spaces are kept.
struct Plan<'a> {
    /// Only this shard's test instances (all without).
    shard: Option<shard::Shard>,
    /// Shape spaces read from here where present, saved here where built.
    spaces: Option<&'a Path>,
}

/// Evaluates the dataset with `settings`: prints the table and writes the reports into
/// `out`, or with a shard writes its rows (`shard.json`) for the merge; an error when any
/// category failed.
fn evaluate(
    dataset: &Path,
    settings: EvalSettings,
    categories: Option<&str>,
    skip_checks: bool,
    plan: &Plan,
    out: &Path,
) -> Result<()> {
    let ctx = Context::new()?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    let only: Option<Vec<String>> =
        categories.map(|c| c.split(',').map(|s| s.trim().to_string()).collect());
    let mut file = None;
    let (rows, failures) = eval(
        &ctx,
        dataset,
        &settings,
        only.as_deref(),
        skip_checks,
        plan,
        |units, placed, failures| match plan.shard {
            // No tables before a row: a run whose every category fails leaves --out as
            // it found it.
            None if placed.is_empty() => Ok(()),
            None => {
                let rows: Vec<Row> = placed.iter().map(|p| p.row.clone()).collect();
                write_reports(out, &rows, &settings, &device)
            }
            Some(shard) => {
                let file = file.get_or_insert_with(|| {
                    shard::ShardFile::new(
                        "eval",
                        shard::run_flags("eval"),
                        shard::resolved(&settings),
                        shard,
                        device.clone(),
                        units.to_vec(),
                    )
                });
                file.rows = placed.to_vec();
                file.failures = failures.to_vec();
                file.write(out)
            }
        },
    )?;
    match plan.shard {
        Some(shard) => println!(
            "shard {}/{}: {} test instances; wrote {}/{}",
            shard.index,
            shard.count,
            rows.len(),
            out.display(),
            shard::FILE
        ),
        None if !rows.is_empty() => {
            print!("{}", std::fs::read_to_string(out.join("table.md"))?);
            println!(
                "wrote {0}/table.md, table.csv, table.json, trials.csv, speed_vs_error.png",
                out.display()
            );
        }
        None => {}
    }
    if !failures.is_empty() {
        bail!(
            "{} of the categories failed{}:\n  {}",
            failures.len(),
            if rows.is_empty() {
                String::new()
            } else {
                format!(" (the others' rows are in {})", out.display())
            },
            failures.join("\n  ")
        );
    }
    Ok(())
}

/// Observed mask in blue, rendered silhouette in red (overlap magenta); pixels whose
/// content is unknown (`loss::UNKNOWN`: hidden, ignored) green.
pub fn overlay(observed: &[f32], rendered: &[f32], width: u32, height: u32) -> RgbImage {
    RgbImage::from_fn(width, height, |x, y| {
        let k = (y * width + x) as usize;
        let unknown = observed[k] < 0.0;
        Rgb([
            (30.0 + 225.0 * rendered[k]) as u8,
            if unknown { 110 } else { 30 },
            (30.0 + 225.0 * observed[k].max(0.0)) as u8,
        ])
    })
}

/// Observed shading on the left, the registered mesh's on the right (grey).
fn shading_pair(observed: &[f32], rendered: &[f32], width: u32, height: u32) -> RgbImage {
    RgbImage::from_fn(2 * width, height, |x, y| {
        let (image, x) = if x < width {
            (observed, x)
        } else {
            (rendered, x - width)
        };
        let v = (255.0 * image[(y * width + x) as usize].clamp(0.0, 1.0)) as u8;
        Rgb([v, v, v])
    })
}

/// Runs one registration (comparing shading and depth too where `params` asks) from each
/// of `starts` at once, keeps the least final loss, and writes its outputs: the
/// pictures of the first view as `overlay_start.png` / `overlay_end.png`
/// (`shading_end.png`), those of any further view `v` with a `_view{v}` suffix.
pub fn register(
    ctx: &Context,
    job: Job,
    starts: &[Pose],
    params: &RegisterParams,
    out: &Path,
) -> Result<Registration> {
    let registrar = Registrar::new(ctx)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let space = job.space;
    let views = job.views();
    let (w, h) = (job.view.camera.width, job.view.camera.height);
    let pixels = (w * h) as usize;
    let name = |stem: &str, v: usize| {
        out.join(if v == 0 {
            format!("{stem}.png")
        } else {
            format!("{stem}_view{v}.png")
        })
    };
    let mean = space
        .canonical
        .with_points(&space.vertices(&vec![0.0; space.dims()])?)?;
    for (v, &view) in views.iter().enumerate() {
        let start = eval::render_mask(ctx, &registrar, &mean, view)?;
        let observed = &job.observed[v * pixels..(v + 1) * pixels];
        write_png(
            &name("overlay_start", v),
            &image::DynamicImage::ImageRgb8(overlay(observed, &start, w, h)),
        )?;
    }
    let total = params.total_iterations();
    let progress = |done: usize, loss: f64| {
        let filled = (done * 30 / total.max(1)).min(30);
        eprint!(
            "\r  register [{}{}] {done}/{total} loss {loss:.5}",
            "#".repeat(filled),
            ".".repeat(30 - filled)
        );
    };
    let result = registrar.register_from_starts(ctx, job, starts, params, progress)?;
    eprintln!();
    let mesh = space.canonical.with_points(&result.vertices)?;
    mesh.save_obj(out.join("deformed.obj"))?;
    let ended = Job {
        view: View {
            camera: job.view.camera,
            pose: result.pose,
        },
        ..job
    };
    for (v, &view) in ended.views().iter().enumerate() {
        let end = eval::render_mask(ctx, &registrar, &mesh, view)?;
        let observed = &job.observed[v * pixels..(v + 1) * pixels];
        write_png(
            &name("overlay_end", v),
            &image::DynamicImage::ImageRgb8(overlay(observed, &end, w, h)),
        )?;
        if let (Some(shading), Some(shaded)) = (params.shading, job.shaded) {
            let end = eval::render_shading(ctx, &registrar, &mesh, &[view], shading)?;
            write_png(
                &name("shading_end", v),
                &image::DynamicImage::ImageRgb8(shading_pair(
                    &shaded[v * pixels..(v + 1) * pixels],
                    &end,
                    w,
                    h,
                )),
            )?;
        }
    }
    write_npy(
        &out.join("code.npy"),
        &ndarray::Array1::from_vec(result.code.clone()),
    )?;
    let p = result.pose;
    write_json(
        &out.join("pose.json"),
        &serde_json::json!({
            "translation": p.translation.to_array(),
            "rotation": p.rotation.to_array(),
            "scale": result.scale,
            "code_sd": space.code_in_deviations(&result.code),
            "loss": result.loss,
        }),
    )?;
    // The kept run's iterations (with several starts `iterations` counts them all, and
    // the milliseconds are the batch's).
    let per = result.milliseconds / result.losses.len().max(1) as f64;
    let log: Vec<serde_json::Value> = result
        .losses
        .iter()
        .enumerate()
        .map(|(i, l)| serde_json::json!({ "iteration": i, "loss": l, "ms": per * (i + 1) as f64 }))
        .collect();
    write_json(&out.join("log.json"), &serde_json::Value::Array(log))?;
    Ok(result)
}

fn category_dirs(dataset: &Path) -> Result<Vec<PathBuf>> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dataset)
        .with_context(|| format!("reading {}", dataset.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.join("train").is_dir() && p.join("test").is_dir() && p.join("canonical.obj").is_file()
        })
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        bail!(
            "{} has no category folders (canonical.obj, train/, test/)",
            dataset.display()
        );
    }
    Ok(dirs)
}

/// Builds each category's shape space from train/ (or reads it from the plan's spaces)
/// and evaluates every test instance (or the plan's shard's), after checking every chosen
/// category (`check-dataset`): what would make the figures meaningless stops the run
/// before any work unless `skip_checks`. `on_row` sees the units to evaluate, the rows so
/// far (in the unsharded order) and the failures after each instance and each failed
/// category (to write them: a later failure keeps them). A category that fails on the way
/// (a mesh that does not load, a registration error) does not stop the others: the
/// failures are returned next to the rows.
fn eval(
    ctx: &Context,
    dataset: &Path,
    settings: &EvalSettings,
    only: Option<&[String]>,
    skip_checks: bool,
    plan: &Plan,
    mut on_row: impl FnMut(&[shard::Unit], &[shard::Placed], &[String]) -> Result<()>,
) -> Result<(Vec<shard::Placed>, Vec<String>)> {
    let mut chosen = category_dirs(dataset)?;
    if let Some(only) = only {
        let names: Vec<String> = chosen.iter().map(|d| dir_name(d)).collect();
        if let Some(missing) = only.iter().find(|c| !names.contains(c)) {
            bail!(
                "--categories: {} has no category \"{missing}\" (it has {})",
                dataset.display(),
                names.join(", ")
            );
        }
        chosen.retain(|d| only.contains(&dir_name(d)));
    }
    // Every unit of work (a test instance) and its expected cost, the canonical's vertices.
    let mut checked = Vec::new();
    let (mut units, mut costs) = (Vec::new(), Vec::new());
    for (c, dir) in chosen.iter().enumerate() {
        let category = crate::check_cmd::check_first(dir, skip_checks, false)?;
        let tests = obj_files(&dir.join("test"))?;
        if tests.is_empty() {
            bail!("{}: test/ has no meshes to evaluate", dir.display());
        }
        let name = dir_name(dir);
        let cost = shard::unit_cost(&category)?;
        for (i, test) in tests.iter().enumerate() {
            units.push(shard::Unit {
                category: c,
                instance: i,
                category_name: name.clone(),
                instance_name: stem(test),
            });
            costs.push(cost);
        }
        checked.push((dir.clone(), name, category.info.up, tests));
    }
    shard::keep_own(&mut units, &costs, plan.shard);
    let registrar = Registrar::new(ctx)?;
    let mut rows = Vec::new();
    let mut failures = Vec::new();
    on_row(&units, &rows, &failures)?;
    for (c, (dir, category, up, tests)) in checked.into_iter().enumerate() {
        let mine: Vec<&shard::Unit> = units.iter().filter(|u| u.category == c).collect();
        if mine.is_empty() {
            continue;
        }
        let settings = EvalSettings {
            up,
            ..settings.clone()
        };
        let result = (|| -> Result<()> {
            let space = shared_space(ctx, &dir, &category, &settings, plan.spaces)?;
            for unit in mine {
                let row = evaluate_instance(
                    ctx,
                    &registrar,
                    &space,
                    &category,
                    &tests[unit.instance],
                    &settings,
                )?;
                rows.push(shard::Placed {
                    unit: unit.clone(),
                    row,
                });
                on_row(&units, &rows, &failures)?;
            }
            Ok(())
        })();
        if let Err(e) = result {
            eprintln!("\n{category}: failed, going on with the others: {e:#}");
            failures.push(format!("{category}: {e:#}"));
            on_row(&units, &rows, &failures)?;
        }
    }
    Ok((rows, failures))
}

/// A folder's (a category's) name.
pub fn dir_name(dir: &Path) -> String {
    dir.file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned()
}

/// A file's name without its extension.
fn stem(path: &Path) -> String {
    path.file_stem()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned()
}

/// The category's shape space: read from `spaces` (CATEGORY.npz) where it is there and
/// built from the dataset where not (and saved there, where given). A space read is
/// checked against the dataset and the settings: the same category, canonical, training
/// files, dimensions and kernel width.
pub fn shared_space(
    ctx: &Context,
    dir: &Path,
    category: &str,
    settings: &EvalSettings,
    spaces: Option<&Path>,
) -> Result<ShapeSpace> {
    let Some(spaces) = spaces else {
        return category_space(ctx, dir, category, settings);
    };
    let path = spaces.join(format!("{category}.npz"));
    if !path.exists() {
        let space = category_space(ctx, dir, category, settings)?;
        std::fs::create_dir_all(spaces)
            .with_context(|| format!("creating {}", spaces.display()))?;
        // Another shard may save the same space at once: the same bytes, each renamed
        // into place whole.
        space.save(&path)?;
        return Ok(space);
    }
    let space = ShapeSpace::load(&path)?;
    let canonical = Mesh::load_obj(dir.join("canonical.obj"))?;
    let training: Vec<String> = obj_files(&dir.join("train"))?
        .iter()
        .map(|f| f.display().to_string())
        .collect();
    let beta = settings.cpd.beta * vkdr::cpd::Normalization::of(&canonical.points()).scale;
    let dims = settings.dims.min(training.len().saturating_sub(1));
    let problem = if space.category != category {
        Some(format!("is the space of {}", space.category))
    } else if space.canonical.positions() != canonical.positions()
        || space.canonical.triangles() != canonical.triangles()
    {
        Some("has another canonical mesh".to_string())
    } else if space.training_names != training {
        Some("was built from other training files".to_string())
    } else if space.beta != beta || space.dims() > dims {
        Some(format!(
            "was built with other settings ({} dimensions, kernel width {}; this run: at most {dims}, {beta})",
            space.dims(),
            space.beta
        ))
    } else {
        None
    };
    if let Some(problem) = problem {
        bail!(
            "--spaces: {} {problem} than {} asks for; give another --spaces folder",
            path.display(),
            dir.display()
        );
    }
    Ok(space)
}

/// The shape space of the category folder `dir` from its canonical.obj and train/, with
/// the settings' dimensions and CPD.
pub fn category_space(
    ctx: &Context,
    dir: &Path,
    category: &str,
    settings: &EvalSettings,
) -> Result<ShapeSpace> {
    let canonical = Mesh::load_obj(dir.join("canonical.obj"))?;
    let training: Vec<(String, Vec<DVec3>)> = obj_files(&dir.join("train"))?
        .iter()
        .map(|f| Ok((f.display().to_string(), Mesh::load_obj(f)?.points())))
        .collect::<Result<_>>()?;
    eprintln!(
        "{category}: shape space from {} training instances",
        training.len()
    );
    let up = vkdr_app::check::Info::read(dir)?.up;
    Ok(ShapeSpace::build(
        ctx,
        category,
        &canonical,
        &training,
        settings.dims,
        &settings.cpd,
        |_, _, _| {},
    )?
    .with_up(up)?)
}

/// One test instance of a category.
fn evaluate_instance(
    ctx: &Context,
    registrar: &Registrar,
    space: &ShapeSpace,
    category: &str,
    test: &Path,
    settings: &EvalSettings,
) -> Result<Row> {
    let name = stem(test);
    let mesh = Mesh::load_obj(test)?;
    let row = eval::evaluate_instance(
        ctx,
        registrar,
        space,
        category,
        &name,
        &mesh,
        settings,
        eval::TrialSource::Rendered,
        |done, total| {
            eprint!("\r  {name:<22} trial {done}/{total}  ");
        },
    )?;
    eprintln!(
        "\r  {name:<22} oracle {:.2} mm (space optimum {:.2}), known pose {:.2} mm ({:.2}x), pose noise {:.2} mm ({:.2}x), {:.0} ms",
        1e3 * row.oracle,
        1e3 * row.space_optimum,
        1e3 * row.known_pose.mean,
        row.known_pose.mean / row.oracle,
        1e3 * row.pose_noise.mean,
        row.pose_noise.mean / row.oracle,
        row.ms
    );
    if let Some(f) = row.from_truth {
        eprintln!(
            "  {:<22} from the true pose {:.2} mm ({:.2}x)",
            "",
            1e3 * f.mean,
            f.mean / row.oracle
        );
    }
    Ok(row)
}

/// Each category's means over its test instances, and the ratios of those means.
/// The rows' categories in order (rows come grouped by category).
fn categories(rows: &[Row]) -> Vec<&str> {
    let mut categories: Vec<&str> = rows.iter().map(|r| r.category.as_str()).collect();
    categories.dedup();
    categories
}

fn category_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "\nPer category (means over its test instances; ratio = mean error / mean oracle error; \
         / optimum = mean error / mean space optimum):\n\n\
         | category | oracle | space optimum | known pose | ratio | / optimum | pose noise | ratio | / optimum | worst noise trial | noise, placed (ratio) | noise, as seen (ratio) | as seen, both ways (ratio) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for category in categories(rows) {
        let of: Vec<&Row> = rows.iter().filter(|r| r.category == category).collect();
        let mean = |f: &dyn Fn(&Row) -> f64| of.iter().map(|r| f(r)).sum::<f64>() / of.len() as f64;
        let oracle = mean(&|r| r.oracle);
        let optimum = mean(&|r| r.space_optimum);
        let (known, noise) = (mean(&|r| r.known_pose.mean), mean(&|r| r.pose_noise.mean));
        let worst = of.iter().map(|r| r.pose_noise_worst).fold(0.0, f64::max);
        let placed = mean(&|r| r.pose_noise_placed.mean);
        let seen = mean(&|r| r.pose_noise_seen.mean);
        let both_ways = mean(&|r| r.pose_noise_seen_both_ways.mean);
        let oracle_both_ways = mean(&|r| r.oracle_both_ways);
        md.push_str(&format!(
            "| {category} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} ({:.2}) |\n",
            1e3 * oracle,
            1e3 * optimum,
            1e3 * known,
            known / oracle,
            known / optimum,
            1e3 * noise,
            noise / oracle,
            noise / optimum,
            1e3 * worst,
            1e3 * placed,
            placed / oracle,
            1e3 * seen,
            seen / oracle,
            1e3 * both_ways,
            both_ways / oracle_both_ways
        ));
    }
    md.push_str(&view_table(rows));
    md.push_str(&preference_table(rows));
    md
}

/// The pose with pose noise, per instance: what a robot acting on it meets. Ratios of the
/// error as seen to the space optimum, and both ways to the larger of the oracle's error
/// both ways and a quarter pixel's footprint at the object's distance (a sub-pixel
/// residual against a 0.04 mm oracle is no "30x").
fn pose_table(rows: &[Row], settings: &EvalSettings) -> String {
    let footprint = 0.25 * settings.distance / settings.camera.fx.min(settings.camera.fy);
    let mut md = format!(
        "\nPose with pose noise (rotation up to the symmetry about the up axis where the instance has it; tilt: the angle \
         between the registered and the true up axis; z: the error in the camera's z of the surface's area-weighted centroid, registered at its pose against the test surface at the true pose, with that of the object frame's origin (a diagnostic: the shape modes move the surface about it) in trials.csv; size: the registered surface's root-mean-square distance from its centroid over the test surface's, 1 where the registration found the object's size, by the scale or by the shape; as seen / opt.: the error as seen over \
         the larger of the space optimum and a quarter pixel's footprint at the object's distance; both ways / floor: the error as seen both ways over the larger of the oracle's both ways and a \
         quarter pixel's footprint at the object's distance, {:.3} mm; means, largest in brackets):\n\n\
         | category | instance | rotation (deg) | tilt (deg) | z (mm) | scale | size | as seen / opt. | both ways / floor |\n|---|---|---|---|---|---|---|---|---|\n",
        1e3 * footprint
    );
    for r in rows {
        let n = r.trials.len().max(1) as f64;
        let mean = |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).sum::<f64>() / n;
        let most = |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).fold(0.0, f64::max);
        let least =
            |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).fold(f64::INFINITY, f64::min);
        let floor = r.oracle_both_ways.max(footprint);
        md.push_str(&format!(
            "| {} | {} | {:.1} ({:.1}) | {:.1} ({:.1}) | {:.1} ({:.1}) | {:.3} ({:.3}-{:.3}) | {:.3} ({:.3}-{:.3}) | {:.2} ({:.2}) | {:.2} ({:.2}) |\n",
            r.category,
            r.instance,
            mean(&|t| t.rotation_error_symmetric.to_degrees()),
            most(&|t| t.rotation_error_symmetric.to_degrees()),
            mean(&|t| t.tilt.to_degrees()),
            most(&|t| t.tilt.to_degrees()),
            mean(&|t| 1e3 * t.z_error.abs()),
            most(&|t| 1e3 * t.z_error.abs()),
            mean(&|t| t.scale),
            least(&|t| t.scale),
            most(&|t| t.scale),
            mean(&|t| t.size),
            least(&|t| t.size),
            most(&|t| t.size),
            mean(&|t| t.pose_noise_seen) / r.space_optimum.max(footprint),
            most(&|t| t.pose_noise_seen) / r.space_optimum.max(footprint),
            mean(&|t| t.pose_noise_seen_both_ways) / floor,
            most(&|t| t.pose_noise_seen_both_ways) / floor,
        ));
    }
    md
}

/// Whether the pose-noise fit of `trial` ended with a lower loss than the fit at the true
/// pose: the images prefer what it found to the truth's best code.
fn images_prefer_noise_fit(trial: &Trial) -> bool {
    trial.pose_noise_loss < trial.known_pose_loss
}

/// Pose-noise errors split by what the images prefer: trials whose fit explains the images
/// better than the best code at the true pose (its error is what the observation leaves
/// open: no optimiser would bring it nearer the truth) against trials that ended above it
/// (a local minimum: more starts or iterations can help).
fn preference_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "\nPose noise by what the images prefer (lower loss: the pose-noise fit's final loss is below that of the fit at the true pose, \
         so the images prefer it to the best code at the truth and an error there is what the observation leaves open; \
         higher: it stopped in a local minimum; ratio = mean over the trials of error / the instance's oracle error, \
         as seen in brackets):\n\n\
         | category | lower-loss trials | ratio (as seen) | higher-loss trials | ratio (as seen) |\n|---|---|---|---|---|\n",
    );
    for category in categories(rows) {
        let trials = category_trials(rows, category);
        let summary = |lower: bool| {
            let of: Vec<_> = trials
                .iter()
                .filter(|(_, t)| images_prefer_noise_fit(t) == lower)
                .collect();
            if of.is_empty() {
                return "0 | -".to_string();
            }
            let n = of.len() as f64;
            let ratio = of.iter().map(|(r, t)| t.pose_noise / r.oracle).sum::<f64>() / n;
            let seen = of
                .iter()
                .map(|(r, t)| t.pose_noise_seen / r.oracle)
                .sum::<f64>()
                / n;
            format!("{} | {ratio:.2} ({seen:.2})", of.len())
        };
        md.push_str(&format!(
            "| {category} | {} | {} |\n",
            summary(true),
            summary(false)
        ));
    }
    md
}

/// Every trial of `category`'s rows, with its row.
fn category_trials<'a>(rows: &'a [Row], category: &str) -> Vec<(&'a Row, &'a Trial)> {
    rows.iter()
        .filter(|r| r.category == category)
        .flat_map(|r| r.trials.iter().map(move |t| (r, t)))
        .collect()
}

/// Views whose line of sight lies within this angle of the plane of a test instance's two
/// longest axes count as edge-on.
const EDGE_ON: f64 = 30.0;

/// Pose-noise errors split by view: edge-on views (rotations about the object's shortest
/// axis move it mostly along the line of sight) against the rest.
fn view_table(rows: &[Row]) -> String {
    let mut md = format!(
        "\nPose noise by view (edge-on: the line of sight within {EDGE_ON:.0} deg of the plane of the test instance's two longest \
         bounding-box axes, where rotations about its shortest axis are seen only foreshortened; \
         ratio = mean over the trials of error / the instance's oracle error; rotation: mean final rotation error, \
         up to turns about the up axis for rotationally symmetric instances, raw in brackets):\n\n\
         | category | edge-on trials | ratio | rotation (deg) | other trials | ratio | rotation (deg) |\n|---|---|---|---|---|---|---|\n"
    );
    for category in categories(rows) {
        let trials = category_trials(rows, category);
        let summary = |edge_on: bool| {
            let of: Vec<_> = trials
                .iter()
                .filter(|(_, t)| (t.short_axis_angle.to_degrees() > 90.0 - EDGE_ON) == edge_on)
                .collect();
            if of.is_empty() {
                return "0 | - | -".to_string();
            }
            let n = of.len() as f64;
            let ratio = of.iter().map(|(r, t)| t.pose_noise / r.oracle).sum::<f64>() / n;
            let mean = |f: &dyn Fn(&Trial) -> f64| of.iter().map(|(_, t)| f(t)).sum::<f64>() / n;
            let symmetric = mean(&|t| t.rotation_error_symmetric.to_degrees());
            let raw = mean(&|t| t.rotation_error.to_degrees());
            format!("{} | {ratio:.2} | {symmetric:.1} ({raw:.1})", of.len())
        };
        md.push_str(&format!(
            "| {category} | {} | {} |\n",
            summary(true),
            summary(false)
        ));
    }
    md
}

/// One line per trial: the view, the errors, and the pose error with pose noise.
pub fn trials_csv(rows: &[Row]) -> String {
    let mut csv = String::from(
        "category,instance,trial,azimuth_deg,elevation_deg,long_axis_angle_deg,short_axis_angle_deg,known_pose,pose_noise,pose_noise_placed,pose_noise_seen,rotation_error_deg,rotation_error_symmetric_deg,translation_error,known_pose_on_bound,pose_noise_on_bound,known_pose_loss,pose_noise_loss,pose_noise_seen_both_ways,tilt_deg,z_error,scale,gravity_error_deg,z_error_origin,size,gravity_fallback,add_s,centroid_error,rotation_error_nocs_deg,iou,z_error_known\n",
    );
    for r in rows {
        for (i, t) in r.trials.iter().enumerate() {
            csv.push_str(&format!(
                "{},{},{i},{:.2},{:.2},{:.2},{:.2},{:e},{:e},{:e},{:e},{:.3},{:.3},{:e},{},{},{:e},{:e},{:e},{:.3},{:e},{:.5},{:.3},{:e},{:.5},{},{:e},{:e},{:.3},{:.4},{:e}\n",
                r.category,
                r.instance,
                t.azimuth.to_degrees(),
                t.elevation.to_degrees(),
                t.long_axis_angle.to_degrees(),
                t.short_axis_angle.to_degrees(),
                t.known_pose,
                t.pose_noise,
                t.pose_noise_placed,
                t.pose_noise_seen,
                t.rotation_error.to_degrees(),
                t.rotation_error_symmetric.to_degrees(),
                t.translation_error,
                t.known_pose_on_bound,
                t.pose_noise_on_bound,
                t.known_pose_loss,
                t.pose_noise_loss,
                t.pose_noise_seen_both_ways,
                t.tilt.to_degrees(),
                t.z_error,
                t.scale,
                t.gravity_error.to_degrees(),
                t.z_error_origin,
                t.size,
                t.gravity_fallback,
                t.add_s,
                t.centroid_error,
                t.rotation_error_nocs.to_degrees(),
                t.iou,
                t.z_error_known,
            ));
        }
    }
    csv
}

pub fn write_reports(
    out: &Path,
    rows: &[Row],
    settings: &EvalSettings,
    device: &str,
) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let c = &settings.camera;
    let (known, noisy) = (&settings.known_pose, &settings.pose_noise);
    let mut md = format!(
        "# Registration error (Table 1)\n\nObserved: {}.\n\nDevice: {device}. Camera: fx {} fy {} cx {} cy {}, {}x{} px; object at {} m; views from the hemisphere of each category's up axis (info.json) \
         (elevation {:.0}-{:.0} deg) at random azimuth; {} trials per instance (seed {}); shape spaces of up to {} dimensions (fewer where the training instances span fewer). Pose noise: uniform +-{} cm in x and y, +-{:.0} deg about each axis. \
         Error: mean distance (mm) from {} points sampled uniformly on the test surface to the deformed canonical's surface; \
         oracle: least-squares latent fit to CPD of the canonical onto the true instance (the paper's); \
         space optimum: the code with the least error itself for the true instance (a direct 3D fit: the best the shape space can do); \
         ratio = error / oracle error; / opt. = error / space optimum; chamfer = symmetric chamfer distance of the vertex sets (mm); \
         placed: the pose-noise error after moving each registered shape so that its vertex centroid is the oracle fit's \
         (one view cannot tell a shape shifted in its frame from a shifted pose); \
         as seen: the pose-noise error of each registered shape at its registered pose against the test surface at the true pose \
         (the distance in the camera frame, what a robot acting on the registration meets; the oracle's is the same in either frame); \
         as seen, both ways: the mean of that error and the one from points sampled on the registered surface to the test surface \
         (which also sees parts the registration has and the test instance has not), its ratio to the oracle's error both ways. \
         Registration: known pose, {} for {} iterations ({} loss); pose noise, the pose aligned alone for {} iterations ({} loss), \
         {}then pose and shape by {} for {} ({}).{}{}\n\n\
         | category | instance | oracle | space optimum | known pose | ratio | / opt. | pose noise | ratio | / opt. | worst noise trial | noise, placed | noise, as seen | chamfer oracle / known / noise | iterations known / noise | ms known / noise |{}\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|{}\n",
        settings.observation(),
        c.fx, c.fy, c.cx, c.cy, c.width, c.height, settings.distance,
        settings.elevation.0.to_degrees(), settings.elevation.1.to_degrees(), settings.trials, settings.seed, settings.dims,
        100.0 * settings.translation_noise, settings.rotation_noise.to_degrees(), eval::SAMPLE_POINTS,
        known.optimizer.name(), known.iterations, known.loss.name(), noisy.align, noisy.align_loss.name(),
        settings.pose_noise_params().reach().map_or(String::new(), |reach| {
            format!(
                "then {} for {} with the mask and the depth at {} times the depth scale, ",
                if noisy.optimize_scale { "with the shape" } else { "alone" },
                reach.iterations,
                vkdr::register::REACH
            )
        }),
        noisy.optimizer.name(), noisy.iterations,
        if noisy.code_prior > 0.0 {
            format!("{} loss, plus a code prior of weight {:.3e} in training SD, both conditions", noisy.loss.name(), noisy.code_prior)
        } else {
            format!("{} loss", noisy.loss.name())
        },
        settings.shading.map_or(String::new(), |s| format!(
            " Observed: the mask and grey Lambert shading (light towards {:?} in the camera frame, ambient {}); \
             the registrations compare the shading (mse) after the alignment.",
            s.light, s.ambient
        )),
        if settings.starts > 1 {
            format!(" Pose noise: {} starts per trial (the noisy start, and it turned about the up axis by {}): the noisy start registered, the others' turns tried on its fit, the joint fit again from a turn that scores 5% lower; its iterations and ms count it all.",
                settings.starts,
                vkdr::register::start_turns(settings.starts, settings.rotation_noise)[1..].iter().map(|t| format!("{:+.0} deg", t.to_degrees())).collect::<Vec<_>>().join(", "))
        } else {
            String::new()
        } + if settings.from_truth { " From true pose: pose and shape as with pose noise, but starting at the true pose (no alignment)." } else { "" },
        if settings.from_truth { " from true pose | ratio |" } else { "" },
        if settings.from_truth { "---|---|" } else { "" },
    );
    let mut csv = String::from("category,instance,oracle,known_pose_mean,known_pose_std,pose_noise_mean,pose_noise_std,iterations,ms,oracle_chamfer,known_pose_chamfer,pose_noise_chamfer,noise_iterations,noise_ms,from_truth_mean,from_truth_std,pose_noise_placed_mean,pose_noise_placed_std,space_optimum,pose_noise_seen_mean,pose_noise_seen_std,oracle_both_ways,pose_noise_seen_both_ways_mean,pose_noise_seen_both_ways_std\n");
    let shading_json = settings
        .shading
        .map(|s| serde_json::json!({ "light": s.light, "ambient": s.ambient }));
    let depth_json = settings.depth.map(|d| {
        serde_json::json!({ "scale": d.scale, "weight": d.weight, "noise": settings.depth_noise })
    });
    let stat = |s: &eval::Stat| serde_json::json!({ "mean": s.mean, "std": s.std });
    let mut json = Vec::new();
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.2} +- {:.2} | {:.2} | {:.2} | {:.2} +- {:.2} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} / {:.2} / {:.2} | {:.1} / {:.1} | {:.0} / {:.0} |{}\n",
            r.category, r.instance, 1e3 * r.oracle, 1e3 * r.space_optimum, 1e3 * r.known_pose.mean, 1e3 * r.known_pose.std, r.known_pose.mean / r.oracle,
            r.known_pose.mean / r.space_optimum,
            1e3 * r.pose_noise.mean, 1e3 * r.pose_noise.std, r.pose_noise.mean / r.oracle, r.pose_noise.mean / r.space_optimum, 1e3 * r.pose_noise_worst,
            1e3 * r.pose_noise_placed.mean, r.pose_noise_placed.mean / r.oracle,
            1e3 * r.pose_noise_seen.mean, r.pose_noise_seen.mean / r.oracle,
            1e3 * r.oracle_chamfer, 1e3 * r.known_pose_chamfer.mean, 1e3 * r.pose_noise_chamfer.mean, r.iterations, r.noise_iterations, r.ms, r.noise_ms,
            r.from_truth.map_or(String::new(), |f| format!(" {:.2} +- {:.2} | {:.2} |", 1e3 * f.mean, 1e3 * f.std, f.mean / r.oracle))
        ));
        csv.push_str(&format!(
            "{},{},{:e},{:e},{:e},{:e},{:e},{},{:.3},{:e},{:e},{:e},{},{:.3},{},{},{:e},{:e},{:e},{:e},{:e},{:e},{:e},{:e}\n",
            r.category,
            r.instance,
            r.oracle,
            r.known_pose.mean,
            r.known_pose.std,
            r.pose_noise.mean,
            r.pose_noise.std,
            r.iterations,
            r.ms,
            r.oracle_chamfer,
            r.known_pose_chamfer.mean,
            r.pose_noise_chamfer.mean,
            r.noise_iterations,
            r.noise_ms,
            r.from_truth
                .map_or(String::new(), |f| format!("{:e}", f.mean)),
            r.from_truth
                .map_or(String::new(), |f| format!("{:e}", f.std)),
            r.pose_noise_placed.mean,
            r.pose_noise_placed.std,
            r.space_optimum,
            r.pose_noise_seen.mean,
            r.pose_noise_seen.std,
            r.oracle_both_ways,
            r.pose_noise_seen_both_ways.mean,
            r.pose_noise_seen_both_ways.std,
        ));
        json.push(serde_json::json!({
            "category": r.category,
            "instance": r.instance,
            "observation": settings.observation(),
            "views": settings.views,
            "oracle": r.oracle,
            "space_optimum": r.space_optimum,
            "known_pose": stat(&r.known_pose),
            "pose_noise": stat(&r.pose_noise),
            "iterations": r.iterations,
            "ms": r.ms,
            "chamfer": {
                "oracle": r.oracle_chamfer,
                "known_pose": r.known_pose_chamfer.mean,
                "pose_noise": r.pose_noise_chamfer.mean,
            },
            "noise_iterations": r.noise_iterations,
            "noise_ms": r.noise_ms,
            "from_truth": r.from_truth.as_ref().map(stat),
            "pose_noise_placed": stat(&r.pose_noise_placed),
            "pose_noise_seen": stat(&r.pose_noise_seen),
            "oracle_both_ways": r.oracle_both_ways,
            "pose_noise_seen_both_ways": stat(&r.pose_noise_seen_both_ways),
            // Trials whose pose-noise fit ended with a lower loss than the known-pose fit.
            "pose_noise_lower_loss": r.trials.iter().filter(|t| images_prefer_noise_fit(t)).count(),
            "shading": shading_json,
            "depth": depth_json,
            "code_prior": noisy.code_prior,
            "pose_noise_pose": {
                "rotation_symmetric_deg": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.rotation_error_symmetric.to_degrees()).collect::<Vec<_>>())),
                "tilt_deg": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.tilt.to_degrees()).collect::<Vec<_>>())),
                "z_error_abs": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.z_error.abs()).collect::<Vec<_>>())),
                "scale": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.scale).collect::<Vec<_>>())),
                "size": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.size).collect::<Vec<_>>())),
            },
        }));
    }
    md.push_str(&category_table(rows));
    md.push_str(&pose_table(rows, settings));
    write_atomically(&out.join("table.md"), md.as_bytes())?;
    write_atomically(&out.join("table.csv"), csv.as_bytes())?;
    write_atomically(&out.join("trials.csv"), trials_csv(rows).as_bytes())?;
    write_json(&out.join("table.json"), &serde_json::Value::Array(json))?;

    // Speed against error: mean error relative to the oracle after each iteration, at each
    // condition's own mean time per iteration (the pose-noise runs include the alignment).
    let curve = |pick: &dyn Fn(&Row) -> &Vec<f64>, ms: &dyn Fn(&Row) -> f64| -> Vec<(f64, f64)> {
        let n = rows.iter().map(|r| pick(r).len()).min().unwrap_or(0);
        let ms = rows.iter().map(ms).sum::<f64>() / rows.len().max(1) as f64;
        (0..n)
            .map(|t| {
                (
                    (t + 1) as f64 * ms,
                    rows.iter().map(|r| pick(r)[t] / r.oracle).sum::<f64>() / rows.len() as f64,
                )
            })
            .collect()
    };
    let plot = Plot::new(
        "speed against error (all test instances)",
        "cumulative time (ms)",
        "error / oracle error",
    )
    .series(
        "known pose",
        PALETTE[0],
        curve(&|r| &r.curve_known, &|r| r.ms / r.iterations.max(1.0)),
    )
    .series(
        "pose noise",
        PALETTE[1],
        curve(&|r| &r.curve_noise, &|r| {
            r.noise_ms / r.noise_iterations.max(1.0)
        }),
    );
    write_png(
        &out.join("speed_vs_error.png"),
        &image::DynamicImage::ImageRgb8(plot.render()),
    )?;
    Ok(())
}
