//! What a scene compares besides the mask: Lambert shading and measured depth, with their
//! models' parameters.

use crate::error::{Error, Result};

/// Grey Lambert shading, compared instead of the coverage: one directional light fixed in
/// the camera frame, the smooth (area-weighted) vertex normals, and an ambient term, so
/// that an object pixel has `ambient + (1 - ambient) max(0, n . light)` interpolated from
/// its triangle's vertices and the background 0. Two-sided: where a vertex faces away from
/// the camera, n is flipped, so the inside of an open scan is lit as a camera sees it
/// (`glsl/lambert.comp`). Unlike a silhouette it shows how the
/// surface turns, which one mask leaves open (the tilt of a bottle towards the camera).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shading {
    /// Direction towards the light in the camera frame (x right, y down, z forward;
    /// normalised on use).
    pub light: [f64; 3],
    /// Ambient term in `[0, 1)`: the shade of a surface the light does not reach.
    pub ambient: f64,
}

impl Default for Shading {
    /// A light at the camera (a flash or a ring light): of the directions tried on a
    /// validation set (also above-left of the camera, and from the side) it registered
    /// with pose noise best.
    fn default() -> Self {
        Self {
            light: [0.0, 0.0, -1.0],
            ambient: 0.2,
        }
    }
}

impl Shading {
    /// The unit light direction, or an error for a zero or non-finite one or an ambient
    /// term outside [0, 1).
    pub fn unit_light(&self) -> Result<[f64; 3]> {
        let [x, y, z] = self.light;
        let norm = (x * x + y * y + z * z).sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(Error::InvalidInput(format!(
                "the light direction {:?} has no length",
                self.light
            )));
        }
        if !(0.0..1.0).contains(&self.ambient) {
            return Err(Error::InvalidInput(format!(
                "the ambient term {} is outside [0, 1)",
                self.ambient
            )));
        }
        Ok([x / norm, y / norm, z / norm])
    }
}

/// How a depth observation is compared (see [`ObservedDepth`]): per pixel where the
/// rendering covers the pixel centre and the observation measured depth (> 0), a bounded
/// (Geman-McClure) cost of the residual r = rendered - observed in units of `scale`,
/// u^2 / (1 + u^2) with u = r / s: about u^2 for small residuals and never more than 1,
/// so that a depth edge inside the silhouette (an open container's rim before its
/// inside), a mixed pixel or a sensor's outlier costs at most a wrong mask pixel; times
/// `weight`, averaged over the image's pixels as the mask term is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthLoss {
    /// Metres: the cost's scale (a residual of it costs half its most).
    pub scale: f64,
    /// Weight against the mask (or shading) term: at 1, a pixel whose depth is off by
    /// `scale` costs as much as a pixel of mask that is wrong.
    pub weight: f64,
    /// Metres (0: off): a rendered pixel that the observation shows as background, with a
    /// measured depth nearer than the rendered surface by more than this, is hidden by
    /// something in front (an occluder outside the instance mask) and counts for nothing,
    /// neither mask nor depth. Pixels the observation shows as object always count.
    pub occlusion: f64,
}

impl Default for DepthLoss {
    /// 1 cm, weight 1: a consumer RGB-D sensor's noise at half a metre is a few mm;
    /// occluders 2 cm in front of the rendered surface.
    fn default() -> Self {
        Self {
            scale: 0.01,
            weight: 1.0,
            occlusion: 0.02,
        }
    }
}

impl DepthLoss {
    /// An error for a scale or weight that is not positive and finite, or an occlusion
    /// tolerance that is negative or not finite.
    pub fn validate(&self) -> Result<()> {
        for (what, value) in [("scale", self.scale), ("weight", self.weight)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(Error::InvalidInput(format!(
                    "the depth loss {what} must be positive and finite, not {value}"
                )));
            }
        }
        if !(self.occlusion.is_finite() && self.occlusion >= 0.0) {
            return Err(Error::InvalidInput(format!(
                "the occlusion tolerance must be >= 0 m (0: off) and finite, not {}",
                self.occlusion
            )));
        }
        Ok(())
    }
}

/// An observed depth image of every view, compared with the rendered camera-space depth
/// besides the mask (or shading): `[view][row][column]` in metres, 0 where nothing was
/// measured. Depth is compared inside the rendered silhouette only and is not
/// antialiased; the silhouette's own gradient comes from the mask term.
#[derive(Clone, Copy, Debug)]
pub struct ObservedDepth<'a> {
    /// Observed depth, `[view][row][column]` in metres, 0 = not measured.
    pub depth: &'a [f32],
    /// How the depth is compared.
    pub loss: DepthLoss,
}
