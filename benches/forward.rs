//! Forward pass at 1024 x 1024 for spheres of about 1e3 .. 1e6 vertices: the G-buffer
//! pass (ids + barycentrics + depth test) next to a plain colour-only render of the same
//! mesh. Each is measured twice: GPU time from timestamps around the pass (`gpu/...`) and
//! wall time of a whole submission including the wait (`wall/...`). The ratio
//! gbuffer / plain is the cost of the extra attachments.
//!
//! `cargo bench --bench forward`; set VKDR_BENCH_MAX_VERTICES to skip the big meshes.

use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};

use vkdr::gpu::{Context, Recorder, Recording, Timestamps};
use vkdr::raster::{Gbuffer, MeshBuffers, Outputs, Rasterizer, ShadedTarget, View, ViewBuffers};
use vkdr::{Camera, Mesh, Pose};

const SIZE: u32 = 1024;

/// A sphere with about `vertices` vertices filling most of the image.
fn sphere(vertices: usize) -> Mesh {
    let rings = ((vertices as f64 / 1.6).sqrt()).round() as u32;
    let segments = (vertices as u32 / rings).max(3);
    Mesh::uv_sphere(0.1, rings, segments)
}

/// One recording: reset timestamps, stamp, the pass, stamp.
fn record(ctx: &Context, stamps: &Timestamps, pass: impl FnOnce(&mut Recorder)) -> Recording {
    let mut rec = Recorder::new(ctx).expect("recorder");
    rec.reset_timestamps(stamps);
    rec.timestamp(stamps, 0);
    pass(&mut rec);
    rec.timestamp(stamps, 1);
    rec.finish().expect("finish")
}

fn gpu_time(
    ctx: &Context,
    recording: &Recording,
    stamps: &Timestamps,
    iterations: u64,
) -> Duration {
    let mut total = 0.0;
    for _ in 0..iterations {
        ctx.replay(recording).expect("replay");
        let t = stamps.read_ms().expect("timestamps");
        total += t[1] - t[0];
    }
    Duration::from_secs_f64(total * 1e-3)
}

fn forward(c: &mut Criterion) {
    let ctx = Context::new().expect("a Vulkan device (run tools/setup.sh)");
    let rasterizer = Rasterizer::new(&ctx).expect("rasterizer");
    let camera = Camera::centered(2.0 * SIZE as f64, SIZE, SIZE).unwrap();
    let views = [View {
        camera,
        pose: Pose::new([0.0, 0.0, 0.6], [0.3, 0.2, 0.0]).unwrap(),
    }];
    let max_vertices: usize = std::env::var("VKDR_BENCH_MAX_VERTICES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(usize::MAX);
    eprintln!("device: {} ({})", ctx.info().name, ctx.info().driver_info);

    let mut group = c.benchmark_group(format!("forward_{SIZE}"));
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500));
    for vertices in [1_000, 10_000, 100_000, 1_000_000]
        .into_iter()
        .filter(|&v| v <= max_vertices)
    {
        let mesh = sphere(vertices);
        let buffers = MeshBuffers::new(&ctx, &mesh).unwrap();
        let gbuffer = Gbuffer::new(&ctx, SIZE, SIZE, 1, Outputs::IdsBary).unwrap();
        let shaded = ShadedTarget::new(&ctx, SIZE, SIZE, 1).unwrap();
        let stamps = Timestamps::new(&ctx, 2).unwrap();
        let view_buffers = ViewBuffers::new(&ctx, &views).unwrap();
        let gbuffer_pass = record(&ctx, &stamps, |rec| {
            rasterizer
                .draw(rec, &buffers, &view_buffers, &gbuffer)
                .unwrap()
        });
        let plain_pass = record(&ctx, &stamps, |rec| {
            rasterizer
                .draw_shaded(rec, &buffers, &views, &shaded)
                .unwrap()
        });
        let v = mesh.vertex_count();
        for (name, pass) in [("gbuffer", &gbuffer_pass), ("plain", &plain_pass)] {
            group.bench_function(BenchmarkId::new(format!("gpu/{name}"), v), |b| {
                b.iter_custom(|n| gpu_time(&ctx, pass, &stamps, n))
            });
            group.bench_function(BenchmarkId::new(format!("wall/{name}"), v), |b| {
                b.iter_custom(|n| {
                    let start = Instant::now();
                    for _ in 0..n {
                        ctx.replay(pass).unwrap();
                    }
                    start.elapsed()
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, forward);
criterion_main!(benches);
