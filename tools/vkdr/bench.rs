//! `vkdr bench`: forward and backward passes of the differentiable renderer against a
//! plain colour render of the same mesh, at one image size, for spheres of about 1e3 to
//! 1e6 vertices. GPU times come from timestamps (median over repeats); wall time is a
//! whole submission with its wait.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context as _, Result};

use vkdr::camera::parse_size;
use vkdr::diff::DiffRenderer;
use vkdr::gpu::{Context, Recorder, Timestamps};
use vkdr::loss::Loss;
use vkdr::raster::{MeshBuffers, ShadedTarget, View};
use vkdr::{Camera, Mesh, Pose};
use vkdr_app::plot::{Plot, PALETTE};

use crate::choices::LossChoice;
use crate::grad::mask_scene;

#[derive(clap::Args)]
pub struct Args {
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
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let size = match args.size.parse::<u32>() {
        Ok(s) => (s, s),
        Err(_) => parse_size(&args.size)?,
    };
    let ctx = Context::new()?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    println!("device: {device}");
    let settings = Settings {
        size,
        repeats: args.repeats.max(1),
        max_vertices: args.max_vertices,
        loss: args.loss.into(),
    };
    let rows = measure(&ctx, &settings)?;
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    write(out, &rows, size, &device)?;
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

/// What one run measures.
struct Settings {
    /// Width and height.
    pub size: (u32, u32),
    pub repeats: usize,
    pub max_vertices: usize,
    pub loss: Loss,
}

#[derive(Clone, Debug)]
pub struct Row {
    pub vertices: usize,
    pub faces: usize,
    pub forward_ms: f64,
    pub backward_ms: f64,
    pub plain_ms: f64,
    pub wall_ms: f64,
    pub plain_wall_ms: f64,
    /// Median over repeats of (forward + backward) / plain, each repeat's pair timed one
    /// after the other (steadier than a ratio of medians on a shared machine).
    pub ratio: f64,
    /// |dL/dtz - central difference| / |central difference|, tz +- 2 mm, re-rendered.
    pub dtz_error: f64,
    /// The same for the vertex gradients along a stretch of the mesh along its x axis
    /// (x (1 +- 0.003)): sum over vertices of dL/dx_v * x_v against re-rendered losses.
    pub stretch_error: f64,
    /// Median GPU time of each pass of the forward and backward (a separate profiled run).
    pub passes: Vec<(&'static str, f64)>,
}

/// The mesh stretched along its own x axis by 1 + `e`.
fn stretched(mesh: &Mesh, e: f32) -> Result<Mesh> {
    let positions = mesh
        .positions()
        .iter()
        .map(|&[x, y, z]| [x * (1.0 + e), y, z])
        .collect();
    Ok(Mesh::new(positions, mesh.triangles().to_vec())?)
}

/// The loss of `mesh` seen in `view` against `mask` (a fresh scene: visibility and
/// silhouettes re-rendered).
fn loss_of(
    ctx: &Context,
    renderer: &DiffRenderer,
    mesh: &Mesh,
    view: View,
    mask: &[f32],
    loss: Loss,
) -> Result<f64> {
    let mut scene = mask_scene(ctx, mesh, view, mask, loss)?;
    Ok(scene.evaluate(ctx, renderer)?.loss[0] as f64)
}

fn relative_error(got: f64, want: f64) -> f64 {
    (got - want).abs() / want.abs().max(f64::MIN_POSITIVE)
}

/// A sphere with about `vertices` vertices.
pub fn sphere(vertices: usize) -> Mesh {
    let rings = ((vertices as f64 / 1.6).sqrt()).round().max(2.0) as u32;
    let segments = (vertices as u32 / rings).max(3);
    Mesh::uv_sphere(0.1, rings, segments)
}

use vkdr_app::metrics::median;

fn measure(ctx: &Context, settings: &Settings) -> Result<Vec<Row>> {
    let (width, height) = settings.size;
    let counts: Vec<usize> = [1_000, 10_000, 100_000, 1_000_000]
        .into_iter()
        .filter(|&v| v <= settings.max_vertices)
        .collect();
    // Before the observed mask is allocated at that size.
    let largest = counts.last().copied().unwrap_or(0) as u64;
    vkdr::diff::check_scene_fits(ctx, (width, height, 1), 1, largest, 0)?;
    let renderer = DiffRenderer::new(ctx)?;
    let camera = Camera::centered(2.0 * width.max(height) as f64, width, height)?;
    let view = View {
        camera,
        pose: Pose::new([0.005, -0.004, 0.6], [0.3, 0.2, 0.0])?,
    };
    // The observed mask: a disc a little off the sphere's silhouette.
    let (w, h, s) = (width as f64, height as f64, width.max(height) as f64);
    let mask: Vec<f32> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x as f64 + 0.5, y as f64 + 0.5)))
        .map(|(x, y)| {
            if (x - 0.53 * w).hypot(y - 0.48 * h) < 0.38 * s {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let mut rows = Vec::new();
    for (k, &target) in counts.iter().enumerate() {
        let mesh = sphere(target);
        eprintln!(
            "[{}/{}] {} vertices, {} faces at {width}x{height}, {} repeats",
            k + 1,
            counts.len(),
            mesh.vertex_count(),
            mesh.triangle_count(),
            settings.repeats
        );
        let mut scene = mask_scene(ctx, &mesh, view, &mask, settings.loss)?;
        let stamps = Timestamps::new(ctx, 3)?;
        let mut rec = Recorder::new(ctx)?;
        scene.record_prepare(&renderer, &mut rec)?;
        ctx.submit_and_wait(rec)?;
        let mut rec = Recorder::new(ctx)?;
        scene.record(&renderer, &mut rec, Some(&stamps))?;
        let iteration = rec.finish()?;

        let buffers = MeshBuffers::new(ctx, &mesh)?;
        let shaded = ShadedTarget::new(ctx, width, height, 1)?;
        let plain_stamps = Timestamps::new(ctx, 2)?;
        let mut rec = Recorder::new(ctx)?;
        rec.reset_timestamps(&plain_stamps);
        rec.timestamp(&plain_stamps, 0);
        renderer
            .rasterizer()
            .draw_shaded(&mut rec, &buffers, &[view], &shaded)?;
        rec.timestamp(&plain_stamps, 1);
        let plain = rec.finish()?;

        let (mut forward, mut backward, mut plain_ms, mut wall, mut plain_wall, mut ratio) =
            (vec![], vec![], vec![], vec![], vec![], vec![]);
        for repeat in 0..=settings.repeats {
            let started = Instant::now();
            ctx.replay(&iteration)?;
            let elapsed = started.elapsed().as_secs_f64() * 1e3;
            let t = stamps.read_ms()?;
            let started = Instant::now();
            ctx.replay(&plain)?;
            let plain_elapsed = started.elapsed().as_secs_f64() * 1e3;
            let p = plain_stamps.read_ms()?;
            if repeat == 0 {
                continue; // warm-up
            }
            forward.push(t[1] - t[0]);
            backward.push(t[2] - t[1]);
            wall.push(elapsed);
            plain_ms.push(p[1] - p[0]);
            plain_wall.push(plain_elapsed);
            ratio.push((t[2] - t[0]) / (p[1] - p[0]));
        }
        // A profile: each pass of the same evaluation submitted alone.
        let passes: Vec<(&'static str, f64)> = scene
            .profile(ctx, &renderer, settings.repeats)?
            .into_iter()
            .map(|(name, times)| (name, median(times)))
            .collect();
        eprintln!(
            "      passes: {}",
            passes
                .iter()
                .map(|(name, ms)| format!("{name} {ms:.3}"))
                .collect::<Vec<_>>()
                .join(", ")
        );

        let result = scene.read()?;
        let missed = scene.missed_starts()?;
        let slack = scene.bound_slack()?.map_or("no camera term".into(), |s| {
            format!("fixed-point bound {s:.1}x the largest camera term")
        });
        let loss = result.loss[0];
        // The gradients against central differences of re-rendered losses.
        let h = 0.002;
        let moved = |dz: f64| {
            let mut v = view;
            v.pose.translation.z += dz;
            loss_of(ctx, &renderer, &mesh, v, &mask, settings.loss)
        };
        let fd_tz = (moved(h)? - moved(-h)?) / (2.0 * h);
        let dtz_error = relative_error(result.pose_gradient[0][2] as f64, fd_tz);
        let e = 0.003;
        let stretch = |e: f32| {
            loss_of(
                ctx,
                &renderer,
                &stretched(&mesh, e)?,
                view,
                &mask,
                settings.loss,
            )
        };
        let fd_stretch = (stretch(e)? - stretch(-e)?) / (2.0 * e as f64);
        let got_stretch: f64 = result
            .vertex_gradient
            .iter()
            .zip(mesh.positions())
            .map(|(g, p)| g[0] as f64 * p[0] as f64)
            .sum();
        let stretch_error = relative_error(got_stretch, fd_stretch);
        let row = Row {
            vertices: mesh.vertex_count(),
            faces: mesh.triangle_count(),
            forward_ms: median(forward),
            backward_ms: median(backward),
            plain_ms: median(plain_ms),
            wall_ms: median(wall),
            plain_wall_ms: median(plain_wall),
            ratio: median(ratio),
            dtz_error,
            stretch_error,
            passes,
        };
        eprintln!(
            "      forward {:.3} ms, backward {:.3} ms, plain {:.3} ms, (forward + backward) / plain = {:.2}; wall {:.3} ms vs {:.3} ms; loss {loss:.5}; dL/dtz {:.4} vs {fd_tz:.4} (error {:.2}%), stretch {got_stretch:.4} vs {fd_stretch:.4} (error {:.2}%); {missed} pixel pairs whose line misses the front triangle; {slack}",
            row.forward_ms,
            row.backward_ms,
            row.plain_ms,
            row.ratio,
            row.wall_ms,
            row.plain_wall_ms,
            result.pose_gradient[0][2],
            100.0 * dtz_error,
            100.0 * stretch_error,
        );
        rows.push(row);
    }
    Ok(rows)
}

/// Writes `bench.csv` (the columns the peers' script writes too), `bench.json` (with wall
/// times) and `bench.png` (time against vertex count, log axes).
pub fn write(out: &Path, rows: &[Row], (width, height): (u32, u32), device: &str) -> Result<()> {
    let mut csv =
        String::from("vertices,faces,width,height,forward_ms,backward_ms,plain_ms,device,dtz_error,stretch_error,ratio\n");
    let mut json = Vec::new();
    let device_field = device.replace(',', ";");
    for r in rows {
        csv.push_str(&format!(
            "{},{},{width},{height},{:.4},{:.4},{:.4},{device_field},{:.5},{:.5},{:.3}\n",
            r.vertices,
            r.faces,
            r.forward_ms,
            r.backward_ms,
            r.plain_ms,
            r.dtz_error,
            r.stretch_error,
            r.ratio
        ));
        let passes: serde_json::Map<String, serde_json::Value> = r
            .passes
            .iter()
            .map(|(name, ms)| (name.to_string(), serde_json::json!(ms)))
            .collect();
        json.push(serde_json::json!({
            "vertices": r.vertices,
            "faces": r.faces,
            "width": width,
            "height": height,
            "forward_ms": r.forward_ms,
            "backward_ms": r.backward_ms,
            "plain_ms": r.plain_ms,
            "wall_ms": r.wall_ms,
            "plain_wall_ms": r.plain_wall_ms,
            "dtz_error": r.dtz_error,
            "stretch_error": r.stretch_error,
            "ratio": r.ratio,
            "device": device,
            "pass_ms": passes,
        }));
    }
    vkdr::io::write_atomically(&out.join("bench.csv"), csv.as_bytes()).context("bench.csv")?;
    vkdr::io::write_json(&out.join("bench.json"), &serde_json::Value::Array(json))
        .context("bench.json")?;

    let series = |f: &dyn Fn(&Row) -> f64| rows.iter().map(|r| (r.vertices as f64, f(r))).collect();
    let name = device.split(" (").next().unwrap_or(device);
    let plot = Plot::new(
        &format!("vkdr bench {width}x{height}, {name}"),
        "vertices",
        "GPU time per pass (ms)",
    )
    .log_x()
    .log_y()
    .series("forward", PALETTE[0], series(&|r| r.forward_ms))
    .series("backward", PALETTE[1], series(&|r| r.backward_ms))
    .series(
        "forward + backward",
        PALETTE[2],
        series(&|r| r.forward_ms + r.backward_ms),
    )
    .series("plain colour render", PALETTE[3], series(&|r| r.plain_ms));
    vkdr::io::write_png(
        &out.join("bench.png"),
        &image::DynamicImage::ImageRgb8(plot.render()),
    )?;
    Ok(())
}
