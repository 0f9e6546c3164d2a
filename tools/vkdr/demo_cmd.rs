//! `vkdr demo`: the quick start: generate a dataset, build a shape space, register a
//! held-out instance from a rendered mask with pose noise, print its Table-1 row, write
//! pictures.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, Result};

use vkdr::cpd::CpdParams;
use vkdr::gpu::Context;
use vkdr::raster::{Rasterizer, View};
use vkdr::{Mesh, Pose};

use crate::pictures::write_views;
use crate::{out, registration, spaces};

#[derive(clap::Args)]
pub struct Args {
    /// Where to write the results.
    #[arg(long, default_value = "vkdr-demo")]
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let out = &args.out;
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
        "1. generated {} (bottle, mug, spray_bottle, drill, bowl: 10 training and 2 test meshes each)",
        dataset.display()
    );

    // 2. The bottle's shape space from its training instances.
    let category = dataset.join("bottle");
    let space_path = out.join("bottle_space.npz");
    spaces::build(&category, None, 5, &CpdParams::default(), &space_path)?;
    let space = vkdr::shape::ShapeSpace::load(&space_path)?;
    println!(
        "2. built the bottle shape space ({} dimensions) -> {}",
        space.dims(),
        space_path.display()
    );

    // 3. Register a held-out bottle from rendered masks, with the pose known and with
    //    pose noise, over a few seeded trials: its Table-1 row.
    let test_path = spaces::obj_files(&category.join("test"))?
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
            vkdr_app::eval::TrialSource::Rendered,
            |_, _| {},
            |_, _| Ok(()),
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
    // What any front end does: the images read into an observation, one start planned.
    let observation = vkdr::Observation::new(
        settings.camera,
        vkdr::ViewImages {
            mask,
            ..Default::default()
        },
    )?;
    let plan = vkdr::Plan {
        starts: 1,
        ..vkdr::Plan::new(start, settings.up, settings.pose_noise)
    };
    let result = registration::register(&ctx, &space, &observation, &plan, &register_out)?;
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
