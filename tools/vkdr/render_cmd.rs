//! `vkdr render`: a mesh's G-buffer (triangle ids, barycentrics, depth) and pictures of it.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, Result};
use ndarray::s;

use vkdr::gpu::Context;
use vkdr::io::{write_npy, write_png};
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::Mesh;

use crate::args::ViewArgs;
use crate::pictures;

#[derive(clap::Args)]
pub struct Args {
    /// OBJ file (triangle ids follow its face order).
    mesh: PathBuf,
    #[command(flatten)]
    view: ViewArgs,
    /// Also write the raw G-buffer: ids.npy, bary.npy, depth.npy.
    #[arg(long)]
    raw: bool,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
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
pub fn write_views(
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
