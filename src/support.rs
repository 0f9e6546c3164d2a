//! The support plane an object stands on, found in an observed depth image: a robust plane
//! fit (RANSAC, then least squares over its inliers) to the measured pixels around the
//! object's mask, oriented towards the object. Its normal is the scene's up direction
//! ([`crate::register::Gravity`]) where a robot has no IMU to tell it.

use glam::DVec3;

use crate::error::{Error, Result};
use crate::rng::Rng;
use crate::Camera;

/// A plane n . x = d in the camera frame (n unit, pointing up: towards the object).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupportPlane {
    /// Unit normal, camera frame, on the object's side of the plane.
    pub normal: DVec3,
    /// n . x for points x on the plane, metres.
    pub offset: f64,
    /// Measured pixels within [`INLIER_DISTANCE`] of the plane, and those looked at.
    pub inliers: usize,
    /// Pixels around the mask with a measurement, the candidates.
    pub candidates: usize,
    /// RMS distance of the inliers from the plane, metres.
    pub rms: f64,
}

/// Metres from the plane within which a measured point counts as on it (a few times a
/// consumer sensor's noise at a metre).
pub const INLIER_DISTANCE: f64 = 0.006;
/// Metres: the object's lowest measured points (its lowest fiftieth) lie within this of a
/// plane that supports it; nearer than [`INLIER_DISTANCE`] below it they may not lie.
pub const TOUCHING: f64 = 0.03;
/// RANSAC hypotheses.
const HYPOTHESES: usize = 300;
/// The fewest measured pixels around the mask that a fit takes.
const MIN_CANDIDATES: usize = 50;

/// Fits the support plane to the measured pixels (`depth` in metres, 0 = none,
/// `[row][column]` of `camera`'s size) outside `mask` (nonzero = object) within `margin`
/// times the mask's box size around it: the plane with the most of them within
/// [`INLIER_DISTANCE`] that has the object's measured points on one side and touching it
/// (its lowest within [`TOUCHING`]) and the camera on that side too, so that an occluder
/// or a wall is not taken for it.
/// Seeded: the same input gives the same plane. An error where too few pixels are
/// measured there or no such plane holds a fifth of them.
pub fn fit_support_plane(
    camera: &Camera,
    depth: &[f32],
    mask: &[f32],
    margin: f64,
) -> Result<SupportPlane> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    if depth.len() != w * h || mask.len() != w * h {
        return Err(Error::InvalidInput(format!(
            "a support plane fit needs a depth and a mask of {w}x{h} pixels, not {} and {}",
            depth.len(),
            mask.len()
        )));
    }
    let back_project = |i: usize| {
        let z = depth[i] as f64;
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        DVec3::new(
            (u - camera.cx) * z / camera.fx,
            (v - camera.cy) * z / camera.fy,
            z,
        )
    };
    let object: Vec<usize> = (0..w * h).filter(|&i| mask[i] > 0.0).collect();
    if object.is_empty() {
        return Err(Error::InvalidInput(
            "a support plane fit needs the object's mask, and it is empty".into(),
        ));
    }
    let (mut lo, mut hi) = ((w, h), (0, 0));
    for &i in &object {
        let (x, y) = (i % w, i / w);
        lo = (lo.0.min(x), lo.1.min(y));
        hi = (hi.0.max(x), hi.1.max(y));
    }
    // The same margin on every side, from the box's larger side: a narrow mask (an
    // upright bottle, or half of one behind an occluder) still gets the table beside it.
    let pad = ((hi.0 - lo.0 + 1).max(hi.1 - lo.1 + 1) as f64 * margin).ceil() as usize;
    let grow = |a: usize, b: usize, n: usize| (a.saturating_sub(pad), (b + pad).min(n - 1));
    let (x0, x1) = grow(lo.0, hi.0, w);
    let (y0, y1) = grow(lo.1, hi.1, h);
    let candidates: Vec<DVec3> = (y0..=y1)
        .flat_map(|y| (x0..=x1).map(move |x| y * w + x))
        .filter(|&i| mask[i] <= 0.0 && depth[i] > 0.0)
        .map(back_project)
        .collect();
    if candidates.len() < MIN_CANDIDATES {
        return Err(Error::InvalidInput(format!(
            "only {} pixels around the mask have a depth measurement: too few to find the \
             support plane (at least {MIN_CANDIDATES})",
            candidates.len()
        )));
    }
    let mut rng = Rng::new(0x5eed);
    let mut pick = || candidates[(rng.uniform() * candidates.len() as f64) as usize];
    let count_inliers = |n: DVec3, d: f64| {
        candidates
            .iter()
            .filter(|p| (n.dot(**p) - d).abs() <= INLIER_DISTANCE)
            .count()
    };
    // The object's measured points: a support plane has them on one side, touching it
    // (an occluder in front of the object, or a wall behind it, does not).
    let on_object: Vec<DVec3> = object
        .iter()
        .filter(|&&i| depth[i] > 0.0)
        .map(|&i| back_project(i))
        .collect();
    let supports = |n: DVec3, d: f64| {
        if on_object.len() < 10 {
            return true;
        }
        let mut heights: Vec<f64> = on_object.iter().map(|p| n.dot(*p) - d).collect();
        heights.sort_by(f64::total_cmp);
        let median = heights[heights.len() / 2];
        let sign = if median < 0.0 { -1.0 } else { 1.0 };
        let mut heights: Vec<f64> = heights.iter().map(|h| h * sign).collect();
        heights.sort_by(f64::total_cmp);
        let low = heights[heights.len() / 50];
        // The camera looks at the object from the side it stands on.
        let camera_above = -d * sign > 0.0;
        low > -2.0 * INLIER_DISTANCE && low < TOUCHING && camera_above
    };
    let mut best: Option<(usize, DVec3, f64)> = None;
    for _ in 0..HYPOTHESES {
        let (a, b, c) = (pick(), pick(), pick());
        let n = (b - a).cross(c - a);
        if n.length() < 1e-9 {
            continue;
        }
        let n = n.normalize();
        let d = n.dot(a);
        let count = count_inliers(n, d);
        if best.is_none_or(|(most, _, _)| count > most) && supports(n, d) {
            best = Some((count, n, d));
        }
    }
    let Some((_, n, d)) = best.filter(|(count, _, _)| *count * 5 >= candidates.len()) else {
        return Err(Error::InvalidInput(format!(
            "no plane holds a fifth of the {} measured pixels around the mask: no support \
             plane found",
            candidates.len()
        )));
    };
    // Least squares over the inliers: the normal is the covariance's least eigenvector.
    let inliers: Vec<DVec3> = candidates
        .iter()
        .copied()
        .filter(|p| (n.dot(*p) - d).abs() <= INLIER_DISTANCE)
        .collect();
    let centre = inliers.iter().copied().sum::<DVec3>() / inliers.len() as f64;
    let mut cov = crate::cpd::linalg::Matrix::zeros(3, 3);
    for p in &inliers {
        let q = (*p - centre).to_array();
        for r in 0..3 {
            for c in 0..3 {
                cov.set(r, c, cov.at(r, c) + q[r] * q[c]);
            }
        }
    }
    let (_, vectors) = crate::cpd::linalg::symmetric_eigen(&cov);
    let least = (0..3)
        .map(|c| DVec3::new(vectors.at(0, c), vectors.at(1, c), vectors.at(2, c)))
        .min_by(|a, b| {
            let spread = |v: &DVec3| {
                inliers
                    .iter()
                    .map(|p| v.dot(*p - centre).powi(2))
                    .sum::<f64>()
            };
            spread(a).total_cmp(&spread(b))
        })
        .unwrap_or(n);
    let mut normal = least.normalize();
    // Up is the side the object is on (where nothing of it is measured, the camera's).
    let towards = if on_object.is_empty() {
        -centre
    } else {
        on_object.iter().copied().sum::<DVec3>() / on_object.len() as f64 - centre
    };
    if normal.dot(towards) < 0.0 {
        normal = -normal;
    }
    let offset = normal.dot(centre);
    let rms = (inliers
        .iter()
        .map(|p| (normal.dot(*p) - offset).powi(2))
        .sum::<f64>()
        / inliers.len() as f64)
        .sqrt();
    Ok(SupportPlane {
        normal,
        offset,
        inliers: inliers.len(),
        candidates: candidates.len(),
        rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A table seen from 35 degrees above, 2 mm of noise and 10% holes, an object in
    /// front of it: the normal within half a degree of the truth, pointing up.
    #[test]
    fn finds_a_noisy_table_under_an_object() {
        let camera = Camera::new(150.0, 150.0, 80.0, 60.0, 160, 120).unwrap();
        let e = 35f64.to_radians();
        let up = DVec3::new(0.0, -e.cos(), -e.sin());
        let d = up.dot(DVec3::new(0.0, 0.05, 0.6));
        let mut rng = Rng::new(3);
        let (mut depth, mut mask) = (Vec::new(), Vec::new());
        for y in 0..120 {
            for x in 0..160 {
                let ray = DVec3::new(
                    (x as f64 + 0.5 - 80.0) / 150.0,
                    (y as f64 + 0.5 - 60.0) / 150.0,
                    1.0,
                );
                let table = d / up.dot(ray);
                let object = (60..100).contains(&x) && (30..70).contains(&y);
                let noise = 0.002 * (rng.uniform() + rng.uniform() + rng.uniform() - 1.5) * 2.0;
                let z = if object { table - 0.05 } else { table } + noise;
                depth.push(if rng.uniform() < 0.1 { 0.0 } else { z as f32 });
                mask.push(object as u32 as f32);
            }
        }
        let plane = fit_support_plane(&camera, &depth, &mask, 0.5).unwrap();
        let angle = plane.normal.dot(up).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(
            angle < 0.5,
            "normal {:?}, {angle} degrees off",
            plane.normal
        );
        assert!((plane.offset - d).abs() < 0.002, "{plane:?}");
        assert!(plane.inliers * 10 > plane.candidates * 8, "{plane:?}");
        // Without measurements around the mask there is no plane.
        let holes: Vec<f32> = depth
            .iter()
            .zip(&mask)
            .map(|(&z, &m)| if m > 0.0 { z } else { 0.0 })
            .collect();
        let err = fit_support_plane(&camera, &holes, &mask, 0.5)
            .unwrap_err()
            .to_string();
        assert!(err.contains("too few"), "{err}");
    }
}
