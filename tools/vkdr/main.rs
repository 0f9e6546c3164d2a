//! The `vkdr` command line: device information, G-buffer renders and the demo.

mod pictures;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context as _, Result};
use clap::{Parser, Subcommand};
use ndarray::s;

use vkdr::camera::{parse_numbers, parse_size};
use vkdr::gpu::Context;
use vkdr::io::{write_npy, write_png};
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::{Camera, Mesh, Pose};

#[derive(Parser)]
#[command(
    name = "vkdr",
    version,
    about = "Differentiable rasterization and deformable registration on Vulkan"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the chosen Vulkan device, its driver, features and limits.
    Info,
    /// Render a mesh's G-buffer (triangle ids, barycentrics, depth) and pictures of it.
    Render(RenderArgs),
    /// The quick start: generate a mesh, render it from a few views, write the pictures.
    Demo {
        /// Where to write the results.
        #[arg(long, default_value = "vkdr-demo")]
        out: PathBuf,
    },
}

#[derive(clap::Args)]
struct RenderArgs {
    /// OBJ file (triangle ids follow its face order).
    mesh: PathBuf,
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
    #[arg(long, default_value_t = Camera::DEFAULT_NEAR)]
    near: f64,
    /// Also write the raw G-buffer: ids.npy, bary.npy, depth.npy.
    #[arg(long)]
    raw: bool,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Info => info(),
        Command::Render(args) => render(&args),
        Command::Demo { out } => demo(&out),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
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
    for (name, has) in &d.features {
        println!("    {:<48} {}", name, if *has { "yes" } else { "MISSING" });
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
    Ok(())
}

fn render(args: &RenderArgs) -> Result<()> {
    let mesh = Mesh::load_obj(&args.mesh)?;
    let [fx, fy, cx, cy] = parse_numbers::<4>(&args.intrinsics, "--intrinsics")?;
    let (width, height) = parse_size(&args.size)?;
    let mut camera = Camera::new(fx, fy, cx, cy, width, height)?;
    camera.near = args.near;
    let camera = camera.validated()?;
    let [tx, ty, tz, rx, ry, rz] = parse_numbers::<6>(&args.pose, "--pose")?;
    let pose = Pose::new([tx, ty, tz], [rx, ry, rz])?;

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

fn demo(out: &Path) -> Result<()> {
    let started = Instant::now();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let ctx = Context::new()?;
    println!("device: {} ({})", ctx.info().name, ctx.info().driver_info);

    let mesh = Mesh::bottle(48);
    let mesh_path = out.join("bottle.obj");
    mesh.save_obj(&mesh_path)?;
    println!(
        "generated a bottle: {} vertices, {} triangles -> {}",
        mesh.vertex_count(),
        mesh.triangle_count(),
        mesh_path.display()
    );

    let camera = Camera::new(600.0, 600.0, 320.0, 240.0, 640, 480)?;
    // Object +y (the bottle's up) is rotated to image-up (camera -y).
    let views: Vec<View> = [[3.14159, 0.0, 0.0], [2.7, 0.0, 0.6], [2.2, 0.9, -0.4]]
        .iter()
        .map(|&rotation| View {
            camera,
            pose: Pose {
                translation: [0.0, 0.0, 0.6].into(),
                rotation: rotation.into(),
            },
        })
        .collect();
    let rasterizer = Rasterizer::new(&ctx)?;
    let written = write_views(&ctx, &rasterizer, &mesh, &views, out, true)?;
    println!(
        "rendered {} views of 640x480 in one submission; wrote:",
        views.len()
    );
    for path in &written {
        println!("  {path}");
    }
    println!("done in {:.1} s", started.elapsed().as_secs_f64());
    Ok(())
}
