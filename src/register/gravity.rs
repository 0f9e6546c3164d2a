//! Which way is up, and the tilt the registration allows from it.

use glam::{DMat3, DVec3};

use crate::error::{Error, Result};
use crate::Pose;

/// Per squared radian of tilt past [`Gravity::tolerance`], as the optimisers add it to the
/// loss (`glsl/include/objective.glsl`, GRAVITY_WEIGHT).
pub const GRAVITY_WEIGHT: f64 = 100.0;

/// [`Gravity::tolerance`] where a caller does not choose one: 1 degree, in radians (the
/// command line's `--tilt-tolerance`, the Python module's `tilt_tolerance` and the
/// evaluations' default).
pub const TILT_TOLERANCE: f64 = 1f64.to_radians();

/// Which way is up: a robot knows it from its table plane or its IMU. The registration
/// keeps the object's up axis within `tolerance` of `direction` (a loss of
/// [`GRAVITY_WEIGHT`] per squared radian beyond it), and starts levelled; the rotation
/// about the up axis stays free.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gravity {
    /// The object's up axis in its own frame (the category's, `info.json`'s `up_axis`).
    pub up: DVec3,
    /// Up in the (first) camera's frame: the support plane's normal, away from it.
    pub direction: DVec3,
    /// Radians of tilt that cost nothing.
    pub tolerance: f64,
}

impl Gravity {
    /// An error for a zero or non-finite axis or direction, or a tolerance outside
    /// [0, pi/2).
    pub fn validate(&self) -> Result<()> {
        for (what, v) in [("up axis", self.up), ("gravity direction", self.direction)] {
            if !(v.is_finite() && v.length() > 0.0) {
                return Err(Error::InvalidInput(format!(
                    "the {what} must be a nonzero direction, not {v}"
                )));
            }
        }
        if !(self.tolerance.is_finite()
            && (0.0..std::f64::consts::FRAC_PI_2).contains(&self.tolerance))
        {
            return Err(Error::InvalidInput(format!(
                "the tilt tolerance must be in [0, 90) degrees, not {} rad",
                crate::error::show(self.tolerance)
            )));
        }
        Ok(())
    }

    /// The angle (radians) between the object's up axis at `pose` and up.
    pub fn tilt(&self, pose: &Pose) -> f64 {
        let v = pose.rotation_matrix() * self.up.normalize();
        v.dot(self.direction.normalize()).clamp(-1.0, 1.0).acos()
    }

    /// `pose` turned by the least rotation (about the object's origin) that makes its up
    /// axis point up; a pose within the tolerance stays as it is.
    pub fn level(&self, pose: Pose) -> Pose {
        if self.tilt(&pose) <= self.tolerance {
            return pose;
        }
        let r = pose.rotation_matrix();
        let turn = glam::DQuat::from_rotation_arc(
            (r * self.up.normalize()).normalize(),
            self.direction.normalize(),
        );
        Pose {
            translation: pose.translation,
            rotation: glam::DQuat::from_mat3(&(DMat3::from_quat(turn) * r)).to_scaled_axis(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shaders' gravity weight (glsl/include/objective.glsl) is [`GRAVITY_WEIGHT`].
    #[test]
    fn the_gravity_weight_matches_the_shaders() {
        let glsl = include_str!("../../glsl/include/objective.glsl");
        let line = format!("const float GRAVITY_WEIGHT = {GRAVITY_WEIGHT:.1};");
        assert!(glsl.contains(&line), "objective.glsl lacks `{line}`");
    }
}
