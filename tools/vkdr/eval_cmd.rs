//! `vkdr eval`: the paper's Table 1 on a dataset (its tables: `eval_report`).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};

use vkdr::gpu::Context;
use vkdr::register::Registrar;
use vkdr::shape::ShapeSpace;
use vkdr::Mesh;
use vkdr_app::eval::{self, EvalSettings, Row};

use crate::args::{DepthLossArgs, RenamedArgs, ShadingArgs, ShardArgs};
use crate::choices::{LossChoice, OptimizerChoice};
use crate::eval_report::write_reports;
use crate::shard;
use crate::spaces::{category_dirs, dir_name, obj_files, shared_space, stem};

#[derive(clap::Args)]
pub struct Args {
    /// A dataset in the layout of `vkdr gen-dataset`.
    #[arg(long, required_unless_present = "merge", conflicts_with = "merge")]
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
    /// Do not hold the directions of the code the images hardly constrain with a strong
    /// prior after the fit (RegisterParams::hold_unseen; the schedules do).
    #[arg(long)]
    no_hold: bool,
    /// With the pose known and --depth: iterations comparing the mask alone before the fit
    /// (RegisterParams::mask_first; 0: none).
    #[arg(long, default_value_t = vkdr::register::MASK_FIRST)]
    mask_first: usize,
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
    #[command(flatten)]
    tilt: crate::args::TiltArgs,
    /// Run even where `check-dataset` finds the set unusable (millimetres, no meshes, ...).
    #[arg(long)]
    skip_checks: bool,
    #[command(flatten)]
    pub shards: ShardArgs,
}

/// `vkdr eval`: the default settings with the flags' changes; a shard of them, or the
/// merge of shards.
pub fn run(args: &Args) -> Result<()> {
    if let Some(merge) = &args.shards.merge {
        return shard::write_merged(
            "eval",
            &merge[0],
            &merge[1..],
            |line| {
                let settings = settings(&shard::parse_flags::<Args>("eval", line)?)?;
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
    let shard = args.shards.shard()?;
    let plan = Plan {
        shard,
        spaces: args.shards.spaces.as_deref(),
    };
    evaluate(
        args.dataset.as_deref().expect("clap requires --dataset"),
        settings,
        args.categories.as_deref(),
        args.skip_checks,
        &plan,
        args.shards.out(),
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
    settings.known_pose.hold_unseen &= !args.no_hold;
    settings.pose_noise.hold_unseen &= !args.no_hold;
    settings.known_pose.mask_first = args.mask_first;
    settings.known_pose.depth_detail = args.depth_loss.depth_detail;
    settings.pose_noise.depth_detail = args.depth_loss.depth_detail;
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
    settings.tilt_tolerance = args.tilt.radians(args.gravity.is_some())?;
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
        let category = crate::spaces::check_first(dir, skip_checks, false)?;
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
        |_, _| Ok(()),
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
