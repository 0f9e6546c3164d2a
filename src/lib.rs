//! vkdr: differentiable rasterization and category-level deformable registration on
//! Vulkan (after StillebenDR, "Iterative 3D Deformable Registration from Single-View RGB
//! Images Using Differentiable Rendering").
//!
//! # Entry points
//!
//! | what | type | |
//! |---|---|---|
//! | the device | [`gpu::Context`] | one Vulkan device, its queue and allocator; every other type takes it |
//! | rasterizer | [`raster::Rasterizer`] | triangle ids, barycentrics and depth of meshes in several views, one submission |
//! | differentiable scene | [`diff::Scene`] with [`diff::DiffRenderer`] | loss of a rendering against an observation, and its exact gradients for vertices, attributes and pose |
//! | shape space | [`shape::ShapeSpace`] | a canonical mesh, training instances registered to it by CPD, PCA of the fields |
//! | registrar | [`register::Registrar`] | the render-and-compare loop: a latent code (and pose) fitted to masks, depth or several views, on the device |
//! | CPD | [`cpd::register`] | non-rigid Coherent Point Drift, E-step and kernel products on the device |
//!
//! These types are re-exported here (`vkdr::Context`, `vkdr::Rasterizer`,
//! `vkdr::Registrar`, ...). The float64 reference models the tests check the device
//! against (`raster::reference`, ...), CPD's internals and the compiled shaders are public
//! for the tests and benchmarks, and hidden from these pages.
//!
//! Host geometry is [`Mesh`], [`Camera`] and [`Pose`]; every fallible call returns
//! [`Result`] with an [`Error`] that names what went wrong (a device limit, bad input, a
//! Vulkan call). `gpu` is the only module that calls `ash`. The examples
//! (`cargo run --release --example render`, `--example register`) show a whole use.
//!
//! # Rasterize
//!
//! ```
//! use vkdr::raster::{Outputs, Rasterizer, View};
//! use vkdr::{gpu::Context, Camera, Mesh, Pose};
//!
//! let ctx = Context::new()?;
//! let view = View {
//!     camera: Camera::new(100.0, 100.0, 32.0, 32.0, 64, 64)?,
//!     pose: Pose::new([0.0, 0.0, 0.5], [0.0, 0.0, 0.0])?,
//! };
//! let sphere = Mesh::uv_sphere(0.1, 16, 32);
//! let g = Rasterizer::new(&ctx)?.render(&ctx, &sphere, &[view], Outputs::Ids)?;
//! // A sphere of radius 0.1 m at 0.5 m covers a disc of about 20 px radius.
//! let covered = g.ids.iter().filter(|&&id| id > 0).count() as f64;
//! assert!((covered - std::f64::consts::PI * 400.0).abs() < 0.05 * covered);
//! # Ok::<(), vkdr::Error>(())
//! ```
//!
//! # Differentiate a loss
//!
//! ```
//! use vkdr::diff::{DiffRenderer, Scene, SceneDesc};
//! use vkdr::raster::View;
//! use vkdr::{gpu::Context, loss::Loss, Camera, Mesh, Pose};
//!
//! let ctx = Context::new()?;
//! let view = View {
//!     camera: Camera::new(100.0, 100.0, 32.0, 32.0, 64, 64)?,
//!     pose: Pose::new([0.0, 0.0, 0.5], [0.0, 0.0, 0.0])?,
//! };
//! // The observed mask: every pixel object, so a larger silhouette lowers the loss.
//! let observed = vec![1.0f32; 64 * 64];
//! let sphere = Mesh::uv_sphere(0.1, 16, 32);
//! let desc = SceneDesc {
//!     mesh: &sphere,
//!     views: &[view],
//!     loss: Loss::Mse,
//!     observed: &observed,
//!     attributes: None,
//!     shading: None,
//!     loss_pixels: None,
//!     depth: None,
//! };
//! let renderer = DiffRenderer::new(&ctx)?;
//! let result = Scene::new(&ctx, &desc)?.evaluate(&ctx, &renderer)?;
//! // Moving the sphere away (+z) shrinks it: the loss rises.
//! assert!(result.pose_gradient[0][2] > 0.0);
//! # Ok::<(), vkdr::Error>(())
//! ```
//!
//! # Register point sets
//!
//! ```
//! use glam::DVec3;
//! use vkdr::cpd::{self, CpdParams, CpdPipelines};
//!
//! let ctx = vkdr::gpu::Context::new()?;
//! // Points on a ring, and the same points stretched along x.
//! let source: Vec<DVec3> = (0..200)
//!     .map(|i| {
//!         let a = i as f64 * 0.0314;
//!         DVec3::new(a.cos(), a.sin(), 0.1 * (3.0 * a).sin())
//!     })
//!     .collect();
//! let target: Vec<DVec3> = source.iter().map(|p| *p * DVec3::new(1.2, 1.0, 1.0)).collect();
//! let pipelines = CpdPipelines::new(&ctx)?;
//! let fit = cpd::register(&ctx, &pipelines, &source, &target, &CpdParams::default(), &mut |_, _| {})?;
//! let error = fit.deformed.iter().zip(&target).map(|(a, b)| (*a - *b).length()).fold(0.0, f64::max);
//! assert!(error < 1e-3, "largest error {error}");
//! # Ok::<(), vkdr::Error>(())
//! ```

#![warn(unsafe_op_in_unsafe_fn)]
#![warn(missing_docs)]

pub mod camera;
pub mod cpd;
pub mod diff;
pub mod error;
pub mod gpu;
pub mod io;
pub mod loss;
pub mod mesh;
pub mod raster;
pub mod register;
pub mod rng;
#[doc(hidden)] // the compiled SPIR-V and its reflected contracts, for the engine's tests
pub mod shaders;
pub mod shape;
pub mod support;

pub use camera::{Camera, Pose};
pub use cpd::CpdParams;
pub use diff::{DiffRenderer, Scene};
pub use error::{Error, Result};
pub use gpu::Context;
pub use mesh::Mesh;
pub use raster::{Outputs, Rasterizer, View};
pub use register::{
    Gravity, Job, Observation, Plan, PoseMode, RegisterParams, Registrar, Registration, ViewImages,
};
pub use shape::ShapeSpace;
