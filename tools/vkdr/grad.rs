//! `vkdr grad`: loss and exact gradients of one render against an observed mask, and a
//! picture of them.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, Result};
use glam::DVec3;
use image::{Rgb, RgbImage};

use vkdr::diff::{DiffRenderer, Evaluation, Scene, SceneDesc};
use vkdr::gpu::Context;
use vkdr::io::{write_npy, write_png};
use vkdr::loss::{load_mask, Loss};
use vkdr::raster::View;
use vkdr::Mesh;

use crate::args::ViewArgs;
use crate::choices::LossChoice;

#[derive(clap::Args)]
pub struct Args {
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
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let mesh = Mesh::load_obj(&args.mesh)?;
    let view = args.view.view()?;
    let loss: vkdr::loss::Loss = args.loss.into();
    let ctx = Context::new()?;
    let result = evaluate(&ctx, &mesh, view, &args.observed, loss, &args.out)?;
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

/// One view of `mesh` compared with `mask` (coverage, no attributes or shading).
pub fn mask_scene(
    ctx: &Context,
    mesh: &Mesh,
    view: View,
    mask: &[f32],
    loss: Loss,
) -> vkdr::Result<Scene> {
    Scene::new(
        ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh,
            views: &[view],
            loss,
            observed: mask,
            attributes: None,
            shading: None,
            depth: None,
        },
    )
}

/// The loss and gradients of `mesh` against the mask in `observed`, written into `out`:
/// loss.json, vertex_grad.npy, pose_grad.npy and gradient.png.
fn evaluate(
    ctx: &Context,
    mesh: &Mesh,
    view: View,
    observed: &Path,
    loss: Loss,
    out: &Path,
) -> Result<Evaluation> {
    let (w, h) = (view.camera.width, view.camera.height);
    let mask = load_mask(observed, w, h)?;
    let renderer = DiffRenderer::new(ctx)?;
    let mut scene = mask_scene(ctx, mesh, view, &mask, loss)?;
    let result = scene.evaluate(ctx, &renderer)?;

    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let loss_value = result.loss[0];
    vkdr::io::write_json(
        &out.join("loss.json"),
        &serde_json::json!({ "loss": loss_value }),
    )?;
    let vertex = ndarray::Array2::from_shape_vec(
        (mesh.vertex_count(), 3),
        result.vertex_gradient.iter().flatten().copied().collect(),
    )?;
    write_npy(&out.join("vertex_grad.npy"), &vertex)?;
    write_npy(
        &out.join("pose_grad.npy"),
        &ndarray::arr1(&result.pose_gradient[0]),
    )?;
    write_png(
        &out.join("gradient.png"),
        &image::DynamicImage::ImageRgb8(picture(mesh, &view, &mask, &result)),
    )?;
    Ok(result)
}

/// Observed mask in blue, antialiased render in red (overlap magenta), and for each vertex
/// on the silhouette the image-space direction of steepest descent (-gradient) in green,
/// the longest 20 pixels.
fn picture(mesh: &Mesh, view: &View, mask: &[f32], result: &Evaluation) -> RgbImage {
    let (w, h) = (view.camera.width, view.camera.height);
    let mut img = RgbImage::from_fn(w, h, |x, y| {
        let k = (y * w + x) as usize;
        let a = result.antialiased[k].clamp(0.0, 1.0);
        Rgb([(40.0 + 215.0 * a) as u8, 40, (40.0 + 180.0 * mask[k]) as u8])
    });
    let rotation = view.pose.rotation_matrix();
    let longest = result
        .vertex_gradient
        .iter()
        .map(|g| DVec3::new(g[0] as f64, g[1] as f64, g[2] as f64).length())
        .fold(0.0, f64::max);
    if longest == 0.0 {
        return img;
    }
    let (lo, hi) = mesh.bounds();
    let size = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    for (p, g) in mesh.positions().iter().zip(&result.vertex_gradient) {
        let g = DVec3::new(g[0] as f64, g[1] as f64, g[2] as f64);
        if g.length() == 0.0 {
            continue;
        }
        let x = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let from = view.pose.apply(x);
        let to = from - rotation * g * (1e-3 * size / longest);
        if from.z <= view.camera.near || to.z <= view.camera.near {
            continue;
        }
        let (u0, v0) = view.camera.project(from);
        let (u1, v1) = view.camera.project(to);
        let (du, dv) = (u1 - u0, v1 - v0);
        let length = du.hypot(dv);
        if length == 0.0 {
            continue;
        }
        let scale = 20.0 * g.length() / longest / length;
        let steps = (20.0 * g.length() / longest).ceil() as usize + 1;
        for s in 0..=steps {
            let t = s as f64 / steps as f64;
            let (u, v) = (u0 + du * scale * t, v0 + dv * scale * t);
            if u >= 0.0 && v >= 0.0 && (u as u32) < w && (v as u32) < h {
                img.put_pixel(u as u32, v as u32, Rgb([60, 255, 60]));
            }
        }
    }
    img
}
