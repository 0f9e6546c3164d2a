//! OpenCV pinhole cameras and object-to-camera poses, on the host.
//!
//! The camera looks along +z with x right and y down; pixel (i, j) has its centre at
//! (j + 0.5, i + 0.5). A pose maps object coordinates to camera coordinates: x_c = R x + t,
//! metres, with R given as an axis-angle vector in radians.

use glam::{DMat3, DVec3};

use crate::error::{show, Error, Result};

/// Intrinsics and image size of an OpenCV pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Near clipping distance in metres: surface closer than this is not drawn.
    pub near: f64,
}

impl Camera {
    /// Default near plane: 1 mm.
    pub const DEFAULT_NEAR: f64 = 1e-3;
    /// The largest focal length or principal point coordinate, pixels.
    pub const MAX_PIXELS: f64 = 1e7;

    /// A camera with the default near plane; an error unless [`Camera::validated`] accepts it.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Result<Self> {
        Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            near: Self::DEFAULT_NEAR,
        }
        .validated()
    }

    /// Checks that every value is finite, positive where it must be, and small enough that
    /// the device's float32 projection cannot overflow: |fx|, |fy|, |cx|, |cy| at most
    /// [`Camera::MAX_PIXELS`], the near plane in (0, [`Pose::MAX_TRANSLATION`]].
    pub fn validated(self) -> Result<Self> {
        let intrinsics = [self.fx, self.fy, self.cx, self.cy];
        let in_range = intrinsics
            .iter()
            .all(|v| v.is_finite() && v.abs() <= Self::MAX_PIXELS);
        if !in_range || self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(Error::InvalidInput(format!(
                "intrinsics fx={}, fy={}, cx={}, cy={} must be finite, at most {:e} px, with fx, fy > 0",
                show(self.fx), show(self.fy), show(self.cx), show(self.cy), Self::MAX_PIXELS
            )));
        }
        if self.width == 0 || self.height == 0 {
            return Err(Error::InvalidInput(format!(
                "image size {}x{} is empty",
                self.width, self.height
            )));
        }
        if !(self.near > 0.0 && self.near <= Pose::MAX_TRANSLATION) {
            return Err(Error::InvalidInput(format!(
                "near plane {} m must be > 0 and at most {:e} m",
                show(self.near),
                Pose::MAX_TRANSLATION
            )));
        }
        Ok(self)
    }

    /// A camera whose principal point is the image centre.
    pub fn centered(focal: f64, width: u32, height: u32) -> Result<Self> {
        Self::new(
            focal,
            focal,
            width as f64 / 2.0,
            height as f64 / 2.0,
            width,
            height,
        )
    }

    /// Pixel coordinates (u, v) of a camera-space point with z > 0.
    pub fn project(&self, p: DVec3) -> (f64, f64) {
        (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy)
    }
}

/// Object-to-camera rigid transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Translation in metres.
    pub translation: DVec3,
    /// Axis-angle rotation in radians.
    pub rotation: DVec3,
}

impl Pose {
    /// The largest translation coordinate, metres (1000 km: past it float32 on the device
    /// has no millimetres left).
    pub const MAX_TRANSLATION: f64 = 1e6;
    /// The longest axis-angle vector, radians (past it the angle has lost its precision).
    pub const MAX_ROTATION: f64 = 1e3;

    /// A pose; an error unless every value is finite, each translation coordinate at most
    /// [`Pose::MAX_TRANSLATION`] and the rotation at most [`Pose::MAX_ROTATION`] long.
    pub fn new(translation: [f64; 3], rotation: [f64; 3]) -> Result<Self> {
        if translation.iter().chain(&rotation).any(|v| !v.is_finite()) {
            return Err(Error::InvalidInput(format!(
                "pose {translation:?} {rotation:?} has a non-finite value"
            )));
        }
        if translation.iter().any(|t| t.abs() > Self::MAX_TRANSLATION) {
            return Err(Error::InvalidInput(format!(
                "pose translation {translation:?} is past {:e} m",
                Self::MAX_TRANSLATION
            )));
        }
        if DVec3::from(rotation).length() > Self::MAX_ROTATION {
            return Err(Error::InvalidInput(format!(
                "pose rotation {rotation:?} is longer than {:e} rad (give the angle modulo 2 pi)",
                Self::MAX_ROTATION
            )));
        }
        Ok(Self {
            translation: translation.into(),
            rotation: rotation.into(),
        })
    }

    /// The identity rotation at `translation`.
    pub fn at(translation: [f64; 3]) -> Self {
        Self {
            translation: translation.into(),
            rotation: DVec3::ZERO,
        }
    }

    /// The rotation matrix (Rodrigues).
    pub fn rotation_matrix(&self) -> DMat3 {
        let angle = self.rotation.length();
        if angle < 1e-12 {
            // First-order expansion keeps tiny rotations exact to rounding.
            let w = self.rotation;
            return DMat3::from_cols(
                DVec3::new(1.0, w.z, -w.y),
                DVec3::new(-w.z, 1.0, w.x),
                DVec3::new(w.y, -w.x, 1.0),
            );
        }
        DMat3::from_axis_angle(self.rotation / angle, angle)
    }

    /// Maps an object-space point to camera space.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.rotation_matrix() * p + self.translation
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Pose {
        let r = self.rotation_matrix().transpose();
        Pose {
            translation: -(r * self.translation),
            rotation: -self.rotation,
        }
    }

    /// This transform followed by `next`: x -> next(self(x)).
    pub fn followed_by(&self, next: &Pose) -> Pose {
        let r = next.rotation_matrix() * self.rotation_matrix();
        Pose {
            translation: next.apply(self.translation),
            rotation: glam::DQuat::from_mat3(&r).to_scaled_axis(),
        }
    }

    /// The transform as a column-major 4x4 matrix in f32 (for shaders).
    pub fn matrix_f32(&self) -> [[f32; 4]; 4] {
        let r = self.rotation_matrix();
        let t = self.translation;
        let c = |v: DVec3| [v.x as f32, v.y as f32, v.z as f32, 0.0];
        [
            c(r.x_axis),
            c(r.y_axis),
            c(r.z_axis),
            [t.x as f32, t.y as f32, t.z as f32, 1.0],
        ]
    }
}

/// Parses `a,b,c,...` into exactly `N` finite numbers (command-line flags).
pub fn parse_numbers<const N: usize>(text: &str, what: &str) -> Result<[f64; N]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| Error::InvalidInput(format!("{what} '{text}': {e}")))?;
    let values: [f64; N] = values.try_into().map_err(|v: Vec<f64>| {
        Error::InvalidInput(format!(
            "{what} '{text}' has {} values, expected {N}",
            v.len()
        ))
    })?;
    if values.iter().any(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(format!(
            "{what} '{text}' has a non-finite value"
        )));
    }
    Ok(values)
}

/// Parses `WxH`.
pub fn parse_size(text: &str) -> Result<(u32, u32)> {
    let bad = || Error::InvalidInput(format!("size '{text}' is not WxH, e.g. 640x480"));
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok((w, h))
}
