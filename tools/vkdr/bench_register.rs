//! `vkdr bench-register`: one registration at benchmark size (by default 640 x 480, a
//! canonical of about 1e4 vertices, pose noise: 15 iterations aligning the pose, then 30
//! of pose and shape): the wall time of the whole
//! registration (median over repeats), the device time of each pass of an iteration, the
//! throughput of registrations batched in one submission against one at a time, and the
//! error after each iteration against cumulative time.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context as _, Result};
use glam::DVec3;

use vkdr::camera::parse_size;
use vkdr::diff::{DepthLoss, Shading};
use vkdr::gpu::Context;
use vkdr::io::{write_atomically, write_png};
use vkdr::raster::View;
use vkdr::register::{Job, OtherView, PassTimes, Registrar};
use vkdr::shape::ShapeSpace;
use vkdr::Camera;
use vkdr_app::dataset::{instance, Rng};
use vkdr_app::eval::{self, surface_error, EvalSettings};
use vkdr_app::plot::{Plot, PALETTE};

use vkdr_app::metrics::median;

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value = "bottle")]
    pub category: String,
    /// Midpoint subdivisions of the canonical (each about 4x the vertices; the bottle
    /// has 226, so 3 gives 14 338).
    #[arg(long, default_value_t = 3)]
    pub subdivide: u32,
    /// Image size WxH.
    #[arg(long, default_value = "640x480")]
    pub size: String,
    /// Iterations of pose and shape, after the pose alignment's.
    #[arg(long, default_value_t = 30)]
    pub iterations: usize,
    /// Timed registrations (after one warm-up); medians are reported.
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Registrations in the throughput comparison.
    #[arg(long, default_value_t = 4)]
    pub batch: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Observe and compare grey Lambert shading too (the default light, at the camera).
    #[arg(long)]
    pub shading: bool,
    /// Observe the test instance's depth too (noise-free; the default depth cost).
    #[arg(long)]
    pub depth: bool,
    /// Cameras, 1 to 6: the others at the same elevation, evenly spaced in azimuth, their
    /// poses relative to the first known.
    #[arg(long, default_value_t = 1)]
    pub views: usize,
    /// Starts of the registration from starts (the first registered, the others' turns
    /// tried on its fit: the default of `vkdr eval` and `vkdr register` with pose noise),
    /// timed against one start.
    #[arg(long, default_value_t = vkdr::register::DEFAULT_STARTS)]
    pub starts: usize,
    /// Render an object over twice this many pixels across at a coarser step (as `vkdr
    /// eval` and `register` do, at 64); 0, the default: the image's own pixels (the device
    /// passes are always timed there).
    #[arg(long, default_value_t = 0)]
    pub detail: u32,
    /// Reuse the space.npz of an earlier run with the same category, subdivision and seed.
    #[arg(long)]
    pub space: Option<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let ctx = &Context::new()?;
    let started = Instant::now();
    let (width, height) = parse_size(&args.size)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    println!("device: {device}");
    if args.repeats == 0 || args.batch == 0 || args.iterations == 0 {
        bail!("--repeats, --batch and --iterations must be at least 1");
    }
    if !(1..=6).contains(&args.views) {
        bail!("--views must be 1 to 6, not {}", args.views);
    }

    // The category: a subdivided canonical, 10 training instances, one test instance.
    let mut rng = Rng::new(args.seed);
    let mut canonical = instance(&args.category, &mut rng)?;
    // Each subdivision has 4 times the triangles and about 4 times the vertices: refuse
    // what the device could not hold before building it.
    let vertices = 4u64
        .checked_pow(args.subdivide)
        .and_then(|f| f.checked_mul(canonical.vertex_count() as u64))
        .unwrap_or(u64::MAX);
    vkdr::diff::check_scene_fits(ctx, (width, height, args.views as u32), 1, vertices, 0)
        .with_context(|| format!("--subdivide {}", args.subdivide))?;
    for _ in 0..args.subdivide {
        canonical = canonical.subdivided();
    }
    let training: Vec<(String, Vec<DVec3>)> = (0..10)
        .map(|i| {
            Ok((
                format!("train_{i:02}"),
                instance(&args.category, &mut rng)?.points(),
            ))
        })
        .collect::<Result<_>>()?;
    let test = instance(&args.category, &mut rng)?;
    let settings = EvalSettings::default();
    let space = match &args.space {
        Some(path) => {
            let space = ShapeSpace::load(path)?;
            if space.canonical != canonical {
                bail!(
                    "{} was not built for --category {} --subdivide {} --seed {}",
                    path.display(),
                    args.category,
                    args.subdivide,
                    args.seed
                );
            }
            space
        }
        None => {
            let t = Instant::now();
            let space = ShapeSpace::build(
                ctx,
                &args.category,
                &canonical,
                &training,
                settings.dims,
                &settings.cpd,
                |done, total, _| eprint!("\r  shape space: CPD {done}/{total}"),
            )?;
            let path = args.out.join("space.npz");
            space.save(&path)?;
            eprintln!(
                "\r  shape space of {} vertices built in {:.1} s -> {} (reuse it with --space)",
                canonical.vertex_count(),
                t.elapsed().as_secs_f64(),
                path.display()
            );
            space
        }
    };
    let truth = eval::surface_sample(&test, eval::SAMPLE_POINTS, args.seed);
    let triangles = space.canonical.triangles();
    let oracle = surface_error(
        &truth,
        &space.vertices(&space.oracle_code(ctx, &test.points(), &settings.cpd)?)?,
        triangles,
    );

    // The camera of the evaluation at twice the resolution, and one noisy start per batch
    // slot.
    let scale = width as f64 / settings.camera.width as f64;
    let camera = Camera::new(
        settings.camera.fx * scale,
        settings.camera.fy * scale,
        0.5 * width as f64,
        0.5 * height as f64,
        width,
        height,
    )?;
    let azimuth = rng.range(0.0, std::f64::consts::TAU);
    let elevation = rng.range(settings.elevation.0, settings.elevation.1);
    let pose = eval::view_pose(azimuth, elevation, settings.distance);
    let others: Vec<OtherView> = (1..args.views)
        .map(|k| {
            let turned = azimuth + std::f64::consts::TAU * k as f64 / args.views as f64;
            OtherView {
                camera,
                from_first: pose.inverse().followed_by(&eval::view_pose(
                    turned,
                    elevation,
                    settings.distance,
                )),
            }
        })
        .collect();
    let views = vkdr::register::all_views(View { camera, pose }, &others);
    let registrar = Registrar::new(ctx)?;
    let shading = args.shading.then(Shading::default);
    let eval::Images {
        mask: observed,
        depth,
        shaded,
    } = eval::observe(ctx, &registrar, &test, &views, args.depth, shading)?;
    let jobs: Vec<Job> = (0..args.batch)
        .map(|_| {
            let start = eval::noisy_pose(
                pose,
                &mut rng,
                settings.translation_noise,
                settings.rotation_noise,
            );
            Job {
                shaded: shaded.as_deref(),
                depth: depth.as_deref(),
                others: &others,
                ..Job::new(
                    &space,
                    &observed,
                    View {
                        camera,
                        pose: start,
                    },
                )
            }
        })
        .collect();
    let mut params = settings.pose_noise;
    params.iterations = args.iterations;
    params.shading = shading;
    params.depth = args.depth.then(DepthLoss::default);
    params.optimize_z = args.depth || args.views > 1;
    params.check_every = args.iterations; // no plateau stop: every run does all iterations
    params.detail = args.detail;
    params.code_prior = vkdr::register::observation_prior((width * height) as usize);
    vkdr::register::check_starts(args.starts).context("--starts")?;

    // One registration, end to end (scene set-up included), after a warm-up.
    registrar.register_batch(ctx, &jobs[..1], &params, |_, _| {})?;
    let mut walls = Vec::new();
    let mut runs = Vec::new();
    for r in 0..args.repeats {
        eprint!("\r  registration {}/{}", r + 1, args.repeats);
        let t = Instant::now();
        let result = registrar.register_batch(ctx, &jobs[..1], &params, |_, _| {})?;
        walls.push(t.elapsed().as_secs_f64() * 1e3);
        runs.extend(result);
    }
    eprintln!();
    let wall = median(walls.clone());
    // The same registration from starts turned about the up axis (the first registered,
    // the others' turns tried on its fit), timed in turn with one start so that both see
    // the same machine.
    let starts = vkdr::register::turned_starts(
        jobs[0].view.pose,
        settings.up,
        args.starts,
        settings.rotation_noise,
    );
    let (mut one, mut many) = (Vec::new(), Vec::new());
    let mut from_starts = None;
    for r in 0..args.repeats {
        eprint!(
            "\r  one start against {} starts {}/{}",
            args.starts,
            r + 1,
            args.repeats
        );
        let t = Instant::now();
        registrar.register_batch(ctx, &jobs[..1], &params, |_, _| {})?;
        one.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        from_starts = Some(registrar.register_starts(
            ctx,
            jobs[0],
            vkdr::register::Starts::for_params(&starts, &params),
            &params,
            |_, _| {},
        )?);
        many.push(t.elapsed().as_secs_f64() * 1e3);
    }
    eprintln!();
    let ratios: Vec<f64> = many.iter().zip(&one).map(|(m, o)| m / o).collect();
    let starts_ratio = median(ratios);
    let from_starts = from_starts.expect("at least one repeat");
    let passes = registrar.profile(ctx, &jobs[0], &params, args.iterations)?;
    let each_pass: Vec<(&str, f64)> = registrar
        .pass_profile(ctx, &jobs[0], &params, args.iterations)?
        .into_iter()
        .map(|(name, times)| (name, median(times)))
        .collect();
    let median_of = |f: fn(&PassTimes) -> f64| median(passes.iter().map(f).collect());
    let pass = PassTimes {
        deform: median_of(|p| p.deform),
        forward: median_of(|p| p.forward),
        backward: median_of(|p| p.backward),
        update: median_of(|p| p.update),
        total: median_of(|p| p.total),
    };

    // Throughput: the batch one at a time against in one submission per chunk.
    let t = Instant::now();
    for job in &jobs {
        registrar.register_batch(ctx, std::slice::from_ref(job), &params, |_, _| {})?;
    }
    let sequential = t.elapsed().as_secs_f64() * 1e3;
    let t = Instant::now();
    let batched_results = registrar.register_batch(ctx, &jobs, &params, |_, _| {})?;
    let batched = t.elapsed().as_secs_f64() * 1e3;

    // Error after each iteration of the first run against cumulative time.
    let run = &runs[0];
    let per_iteration = wall / run.evaluations as f64;
    let mut curve = vec![(
        0.0,
        surface_error(
            &truth,
            &space.vertices(&vec![0.0; space.dims()])?,
            triangles,
        ),
    )];
    for (t, error) in eval::error_curve(&space, &truth, &run.codes, &run.scales)?
        .into_iter()
        .enumerate()
    {
        curve.push(((t + 1) as f64 * per_iteration, error));
    }
    let seen = surface_error(
        &truth,
        &eval::as_seen(&run.vertices, run.pose, pose),
        triangles,
    );
    let seen_starts = surface_error(
        &truth,
        &eval::as_seen(&from_starts.vertices, from_starts.pose, pose),
        triangles,
    );
    let batch_errors: Vec<f64> = batched_results
        .iter()
        .map(|r| surface_error(&truth, &r.vertices, triangles) / oracle)
        .collect();

    let m = space.canonical.vertex_count();
    let mut summary = format!(
        "# vkdr bench-register\n\nDevice: {device}.\n\
         One registration of a {category} ({m} vertices, {faces} triangles, {dims}-dimensional space) from a {w}x{h} mask{observed} with pose noise \
         (+-{tn} cm, +-{rn:.0} deg), the schedule of `vkdr eval`: {align} iterations aligning the pose alone, then {it} of pose and shape \
         ({optimizer}), seed {seed}; {detail}.\n\n\
         | measure | value |\n|---|---|\n\
         | registration, wall (median of {reps}, set-up included) | {wall:.1} ms |\n\
         | per iteration, wall | {per_iteration:.2} ms |\n\
         | per iteration, device: deform | {deform:.3} ms |\n\
         | per iteration, device: forward (raster, classify, antialias, loss) | {forward:.3} ms |\n\
         | per iteration, device: backward (vertices, pose) | {backward:.3} ms |\n\
         | per iteration, device: dL/ds and optimiser step | {update:.3} ms |\n\
         | per iteration, device: total | {total:.3} ms |\n\
         | {batch} registrations one at a time | {sequential:.1} ms ({seq_rate:.2} per s) |\n\
         | {batch} registrations batched | {batched:.1} ms ({batch_rate:.2} per s, {speedup:.2}x) |\n\
         | oracle error | {oracle:.2} mm |\n\
         | error at the start (mean shape) / end | {start:.2} / {end:.2} mm ({ratio:.2}x oracle) |\n\
         | error at the end as seen (at its registered pose, against the test surface at the true one) | {seen:.2} mm ({seen_ratio:.2}x oracle) |\n\
         | batched runs' error / oracle | {batch_errors} |\n\
         | {starts} starts (the first fitted, the turns tried on its fit) / one start, wall (median of {reps} pairs, the code prior in both) | {starts_ratio:.2} |\n\
         | error at the end as seen from {starts} starts | {seen_starts:.2} mm ({seen_starts_ratio:.2}x oracle) |\n",
        category = args.category,
        observed = match shading {
            Some(s) => format!(
                " and its grey Lambert shading (light towards {:?}, ambient {}; compared after the alignment)",
                s.light, s.ambient
            ),
            None => String::new(),
        } + if args.depth { " and its depth" } else { "" }
            + &if args.views > 1 {
                format!(" in {} views (evenly spaced in azimuth)", args.views)
            } else {
                String::new()
            },
        faces = space.canonical.triangle_count(),
        dims = space.dims(),
        w = width,
        h = height,
        tn = 100.0 * settings.translation_noise,
        rn = settings.rotation_noise.to_degrees(),
        it = args.iterations,
        align = params.align,
        optimizer = params.optimizer.name(),
        detail = match args.detail {
            0 => "rendered at the image's pixels".to_string(),
            d => format!("an object over {} pixels across rendered at a coarser step (detail {d})", 2 * d),
        },
        seed = args.seed,
        reps = args.repeats,
        deform = pass.deform,
        forward = pass.forward,
        backward = pass.backward,
        update = pass.update,
        total = pass.total,
        batch = args.batch,
        seq_rate = 1e3 * args.batch as f64 / sequential,
        batch_rate = 1e3 * args.batch as f64 / batched,
        speedup = sequential / batched,
        oracle = 1e3 * oracle,
        start = 1e3 * curve[0].1,
        end = 1e3 * curve.last().map_or(f64::NAN, |c| c.1),
        ratio = curve.last().map_or(f64::NAN, |c| c.1) / oracle,
        seen = 1e3 * seen,
        seen_ratio = seen / oracle,
        starts = args.starts,
        seen_starts = 1e3 * seen_starts,
        seen_starts_ratio = seen_starts / oracle,
        batch_errors = batch_errors
            .iter()
            .map(|e| format!("{e:.2}"))
            .collect::<Vec<_>>()
            .join(", "),
    );
    summary += &format!(
        "\nEach pass of an iteration's evaluation submitted alone (host clock, median of {}; \
         each time includes one submission's overhead):\n\n| pass | ms |\n|---|---|\n",
        args.iterations
    );
    for (name, ms) in &each_pass {
        summary += &format!("| {name} | {ms:.3} |\n");
    }
    print!("{summary}");
    write_atomically(&args.out.join("bench_register.md"), summary.as_bytes())?;
    let json = serde_json::json!({
        "device": device,
        "category": args.category,
        "shading": shading.is_some(),
        "depth": args.depth,
        "views": args.views,
        "vertices": m,
        "width": width,
        "height": height,
        "iterations": args.iterations,
        "detail": args.detail,
        "wall_ms": walls,
        "wall_ms_median": wall,
        "passes_ms": {
            "deform": pass.deform,
            "forward": pass.forward,
            "backward": pass.backward,
            "update": pass.update,
            "total": pass.total,
        },
        "each_pass_ms": each_pass
            .iter()
            .map(|(name, ms)| serde_json::json!({ "pass": name, "ms": ms }))
            .collect::<Vec<_>>(),
        "batch": args.batch,
        "sequential_ms": sequential,
        "batched_ms": batched,
        "oracle_m": oracle,
        "seen_m": seen,
        "starts": args.starts,
        "one_start_ms": one,
        "starts_ms": many,
        "starts_over_one_median": starts_ratio,
        "seen_from_starts_m": seen_starts,
        "curve": curve
            .iter()
            .map(|(t, e)| serde_json::json!({ "ms": t, "error_m": e }))
            .collect::<Vec<_>>(),
    });
    vkdr::io::write_json(&args.out.join("bench_register.json"), &json)?;
    let name = device.split(" (").next().unwrap_or(&device);
    let plot = Plot::new(
        &format!("registration {}x{}, {m} vertices, {name}", width, height),
        "cumulative time (ms)",
        "error / oracle error",
    )
    .series(
        "pose noise",
        PALETTE[1],
        curve.iter().map(|&(t, e)| (t, e / oracle)).collect(),
    );
    write_png(
        &args.out.join("speed_vs_error.png"),
        &image::DynamicImage::ImageRgb8(plot.render()),
    )?;
    println!(
        "wrote {0}/bench_register.md, bench_register.json, speed_vs_error.png in {1:.1} s",
        args.out.display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}
