//! Render a sphere, compare it with a disc mask, and read the loss and its gradients.
//!
//!     cargo run --release --example render
//!
//! Writes `render_mask.png` (the antialiased silhouette) to the working directory.

use vkdr::diff::{DiffRenderer, Scene, SceneDesc};
use vkdr::gpu::Context;
use vkdr::loss::Loss;
use vkdr::raster::View;
use vkdr::{Camera, Mesh, Pose};

fn main() -> vkdr::Result<()> {
    let ctx = Context::new()?;
    println!("device: {}", ctx.info().name);
    let (width, height) = (160u32, 120u32);
    let view = View {
        camera: Camera::new(200.0, 200.0, 80.0, 60.0, width, height)?,
        // The object 0.5 m in front of the camera, unrotated.
        pose: Pose::new([0.0, 0.0, 0.5], [0.0, 0.0, 0.0])?,
    };
    let sphere = Mesh::uv_sphere(0.1, 24, 48);
    // The observation: a disc a little larger than the sphere's silhouette.
    let observed: Vec<f32> = (0..width * height)
        .map(|i| {
            let (x, y) = ((i % width) as f32 - 80.0, (i / width) as f32 - 60.0);
            if x.hypot(y) < 45.0 {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let renderer = DiffRenderer::new(&ctx)?;
    let mut scene = Scene::new(
        &ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh: &sphere,
            views: &[view],
            loss: Loss::Mse,
            observed: &observed,
            attributes: None,
            shading: None,
            depth: None,
        },
    )?;
    let result = scene.evaluate(&ctx, &renderer)?;
    let [tx, ty, tz, ..] = result.pose_gradient[0];
    println!(
        "loss {:.5}; dL/dt = ({tx:.4}, {ty:.4}, {tz:.4})",
        result.loss[0]
    );
    println!("(moving the sphere closer, -z, makes it larger and lowers the loss: dL/dtz > 0)");
    let pixels = result
        .antialiased
        .iter()
        .map(|&a| (a.clamp(0.0, 1.0) * 255.0) as u8);
    image::GrayImage::from_raw(width, height, pixels.collect())
        .expect("one value per pixel")
        .save("render_mask.png")
        .map_err(|e| vkdr::Error::InvalidInput(format!("render_mask.png: {e}")))?;
    println!("wrote render_mask.png");
    Ok(())
}
