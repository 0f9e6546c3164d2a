//! A minimal registration: a shape space of bottles, the mask of an unseen one, and the
//! latent code that deforms the canonical bottle to match it, found on the device.
//! `cargo run --release --example register`

use glam::DVec3;
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::register::{Job, Optimizer, RegisterParams, Registrar};
use vkdr::{cpd::CpdParams, gpu::Context, shape::ShapeSpace, Camera, Mesh, Pose};

fn main() -> vkdr::Result<()> {
    let ctx = Context::new()?;
    // The category: a canonical bottle, and training bottles wider, slimmer or taller.
    let canonical = Mesh::bottle(32);
    let stretched = |sx: f64, sy: f64| -> Vec<DVec3> {
        let scale = DVec3::new(sx, sy, sx);
        canonical.points().iter().map(|p| *p * scale).collect()
    };
    let training: Vec<(String, Vec<DVec3>)> = [(1.2, 1.0), (0.85, 1.0), (1.0, 1.25), (1.0, 0.8)]
        .map(|(sx, sy)| (format!("{sx} x {sy}"), stretched(sx, sy)))
        .into();
    let cpd = CpdParams::default();
    let space = ShapeSpace::build(&ctx, "bottle", &canonical, &training, 2, &cpd, |_, _, _| {})?;

    // The observation: the mask of a bottle the space has not seen, side on at 0.6 m.
    let camera = Camera::new(300.0, 300.0, 80.0, 80.0, 160, 160)?;
    let pose = Pose::new([0.0, 0.0, 0.6], [1.3, 0.0, 0.0])?;
    let view = View { camera, pose };
    let unseen = stretched(1.1, 1.12);
    let mesh = canonical.with_points(&unseen)?;
    let g = Rasterizer::new(&ctx)?.render(&ctx, &mesh, &[view], Outputs::Ids)?;
    let mask: Vec<f32> = g.ids.iter().map(|&id| (id > 0) as u8 as f32).collect();

    // The code starts at the mean shape; the pose is known here (see RegisterParams).
    let mut params = RegisterParams::default();
    (params.iterations, params.optimizer) = (100, Optimizer::Bfgs);
    let job = Job::new(&space, &mask, view);
    let found = Registrar::new(&ctx)?.register(&ctx, job, &params, |_, _| {})?;

    let mean_shape = space.vertices(&vec![0.0; space.dims()])?;
    println!(
        "loss {:.1e} -> {:.1e} in {} iterations; code {:.1?}; mean vertex error {:.2} mm \
         (the mean shape's {:.2} mm)",
        found.losses[0],
        found.losses[found.losses.len() - 1],
        found.iterations(),
        found.code,
        mean_mm(&found.vertices, &unseen),
        mean_mm(&mean_shape, &unseen)
    );
    Ok(())
}

/// The mean distance between corresponding points, in millimetres.
fn mean_mm(a: &[DVec3], b: &[DVec3]) -> f64 {
    1e3 * a.iter().zip(b).map(|(p, q)| p.distance(*q)).sum::<f64>() / a.len() as f64
}
