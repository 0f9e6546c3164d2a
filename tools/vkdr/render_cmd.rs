//! `vkdr render`: a mesh's G-buffer (triangle ids, barycentrics, depth) and pictures of it.

use std::path::PathBuf;

use anyhow::{Context as _, Result};

use vkdr::gpu::Context;
use vkdr::raster::{Rasterizer, View};
use vkdr::Mesh;

use crate::args::ViewArgs;
use crate::pictures::write_views;

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
