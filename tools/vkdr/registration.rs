//! The registration with pictures that `vkdr register`, `vkdr demo` and `vkdr eval`
//! share: the overlays before and after, the deformed mesh, its code, pose and loss log.

use std::path::Path;

use anyhow::{Context as _, Result};
use image::{Rgb, RgbImage};

use vkdr::gpu::Context;
use vkdr::io::{write_json, write_npy, write_png};
use vkdr::raster::View;
use vkdr::register::{Job, Observation, Plan, Registrar, Registration};
use vkdr::shape::ShapeSpace;
use vkdr_app::eval;

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

/// Registers `space` to `observation` as `plan` says ([`Registrar::register_observation`],
/// with a progress bar) and writes its outputs: the pictures of the first view as
/// `overlay_start.png` / `overlay_end.png` (`shading_end.png`), those of any further view
/// `v` with a `_view{v}` suffix, the deformed mesh, its code, pose and loss log.
pub fn register(
    ctx: &Context,
    space: &ShapeSpace,
    observation: &Observation,
    plan: &Plan,
    out: &Path,
) -> Result<Registration> {
    let registrar = Registrar::new(ctx)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let job = observation.job(space, plan.start);
    let params = &plan.params;
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
    let result = registrar.register_observation(ctx, space, observation, plan, progress)?;
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
