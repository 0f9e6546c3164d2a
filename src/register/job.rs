//! One registration to run: a shape space, what is observed, and the views it was seen
//! through.

use crate::raster::View;
use crate::shape::ShapeSpace;
use crate::{Camera, Pose};

use super::Gravity;

/// A further camera of a multi-view registration: it sees the same object, from a pose
/// known relative to the first camera (a point x in the first camera's frame is
/// `from_first.apply(x)` in this one's). Its image has the first view's size.
#[derive(Clone, Copy, Debug)]
pub struct OtherView {
    /// Intrinsics and image size of this camera.
    pub camera: Camera,
    /// Transform from the first camera's frame to this camera's frame.
    pub from_first: Pose,
}

/// One registration to run: a shape space, an observed mask (`[row][column]`, nonzero =
/// object), optionally the observed shading (grey, `[row][column]`, background 0; compared
/// when `RegisterParams::shading` is set) and depth (metres, 0 = not measured; compared
/// when `RegisterParams::depth` is set), and the view it was seen through (its pose is
/// the initial pose). With `others`, the object is seen by several cameras at once: one
/// code and one object pose explain every view, and each image holds every view's,
/// `[view][row][column]`, the first view first.
#[derive(Clone, Copy)]
pub struct Job<'a> {
    /// The shape space whose latent code is fitted.
    pub space: &'a ShapeSpace,
    /// Observed mask, `[row][column]` (`[view][row][column]` with `others`),
    /// nonzero = object.
    pub observed: &'a [f32],
    /// Observed grey shading in the mask's layout, background 0.
    pub shaded: Option<&'a [f32]>,
    /// Observed depth in the mask's layout, metres, 0 = not measured.
    pub depth: Option<&'a [f32]>,
    /// The (first) camera and the initial object pose.
    pub view: View,
    /// Further cameras of a multi-view registration (empty: one view).
    pub others: &'a [OtherView],
    /// Which way is up, where known (used when the pose is optimised).
    pub gravity: Option<Gravity>,
    /// The pixel count each view's loss is averaged over (None: the view's own): a job
    /// cut to a region of interest of a larger image keeps the larger image's
    /// ([`crate::diff::SceneDesc::loss_pixels`]).
    pub loss_pixels: Option<u64>,
    /// The observed depth holds measurements at every `depth_every`-th pixel along each
    /// axis only (0 elsewhere), each standing for `depth_every` squared pixels: the depth
    /// loss's weight is multiplied by that (a job cut to a [`super::Region`] with a
    /// `depth_step`). 1: every pixel.
    pub depth_every: u32,
}

impl<'a> Job<'a> {
    /// A registration of `space` to an observed mask seen through `view`.
    pub fn new(space: &'a ShapeSpace, observed: &'a [f32], view: View) -> Self {
        Self {
            space,
            observed,
            shaded: None,
            depth: None,
            view,
            others: &[],
            gravity: None,
            loss_pixels: None,
            depth_every: 1,
        }
    }

    /// The same with the observed shading too.
    pub fn with_shading(self, shaded: &'a [f32]) -> Self {
        Self {
            shaded: Some(shaded),
            ..self
        }
    }

    /// The same with the observed depth too.
    pub fn with_depth(self, depth: &'a [f32]) -> Self {
        Self {
            depth: Some(depth),
            ..self
        }
    }

    /// The same seen by further cameras (the images then hold every view's).
    pub fn with_others(self, others: &'a [OtherView]) -> Self {
        Self { others, ..self }
    }

    /// Every view: the first, then the others at their poses relative to it.
    pub fn views(&self) -> Vec<View> {
        all_views(self.view, self.others)
    }
}

/// The views of a rig: `first`, then each of `others` at its pose relative to it.
pub fn all_views(first: View, others: &[OtherView]) -> Vec<View> {
    std::iter::once(first)
        .chain(others.iter().map(|o| View {
            camera: o.camera,
            pose: first.pose.followed_by(&o.from_first),
        }))
        .collect()
}
