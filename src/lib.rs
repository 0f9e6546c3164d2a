//! vkdr: differentiable rasterization and category-level deformable registration on
//! Vulkan. See `DESIGN` notes in the README: `gpu` is the only layer that calls `ash`;
//! `raster` is the forward rasterizer; `mesh` and `camera` are host geometry.

#![warn(unsafe_op_in_unsafe_fn)]

pub mod camera;
pub mod check;
pub mod cpd;
pub mod dataset;
pub mod diff;
pub mod error;
pub mod eval;
pub mod gpu;
pub mod io;
pub mod loss;
pub mod mesh;
pub mod plot;
pub mod raster;
pub mod register;
pub mod shape;

pub use camera::{Camera, Pose};
pub use error::{Error, Result};
pub use mesh::Mesh;
