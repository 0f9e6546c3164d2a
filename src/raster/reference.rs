//! CPU float64 reference rasterizer with the engine's conventions: pixel centres at
//! (j + 0.5, i + 0.5), surface nearer than the camera's near plane clipped away, the
//! nearest surface wins (ties go to the lower triangle id, as drawing order does on the
//! device). It is an independent formulation (ray-plane intersection in camera space) of
//! what the GPU computes with homogeneous edge functions, used by tests.

use glam::{DVec2, DVec3};

use crate::camera::{Camera, Pose};
use crate::mesh::Mesh;

/// The reference G-buffer of one view, row-major.
#[derive(Clone, Debug)]
pub struct ReferenceGbuffer {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Triangle id + 1, 0 = background.
    pub ids: Vec<u32>,
    /// Perspective-correct barycentric weights of the triangle's three corners.
    pub bary: Vec<[f64; 3]>,
    /// Camera-space z, 0 = background.
    pub depth: Vec<f64>,
    /// Distance in pixels from the pixel centre to the nearest projected (and near-clipped)
    /// triangle edge; infinity where no edge passes within a pixel.
    pub edge_distance: Vec<f64>,
}

/// Rasterizes `mesh` seen by `camera` from `pose`.
pub fn rasterize(mesh: &Mesh, camera: &Camera, pose: &Pose) -> ReferenceGbuffer {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = ReferenceGbuffer {
        width: w,
        height: h,
        ids: vec![0; w * h],
        bary: vec![[0.0; 3]; w * h],
        depth: vec![0.0; w * h],
        edge_distance: vec![f64::INFINITY; w * h],
    };
    let rotation = pose.rotation_matrix();
    let to_camera = |p: &[f32; 3]| {
        rotation * DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) + pose.translation
    };
    let camera_points: Vec<DVec3> = mesh.positions().iter().map(to_camera).collect();

    for (t, tri) in mesh.triangles().iter().enumerate() {
        let c = tri.map(|v| camera_points[v as usize]);
        let polygon = clip_near(&c, camera.near);
        if polygon.len() < 3 {
            continue;
        }
        let projected: Vec<DVec2> = polygon
            .iter()
            .map(|&p| {
                let (u, v) = camera.project(p);
                DVec2::new(u, v)
            })
            .collect();
        let (mut lo, mut hi) = (projected[0], projected[0]);
        for p in &projected {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        // Pixels whose centre lies within one pixel of the polygon (for edge distances).
        let column = |x: f64| (x - 1.5).floor().clamp(0.0, w as f64) as usize;
        let row = |y: f64| (y - 1.5).floor().clamp(0.0, h as f64) as usize;
        let (j0, j1) = (column(lo.x), ((hi.x + 0.5).ceil().max(0.0) as usize).min(w));
        let (i0, i1) = (row(lo.y), ((hi.y + 0.5).ceil().max(0.0) as usize).min(h));
        let area = signed_area(&projected);
        if area == 0.0 {
            continue;
        }
        let normal = (c[1] - c[0]).cross(c[2] - c[0]);
        for i in i0..i1 {
            for j in j0..j1 {
                let pixel = DVec2::new(j as f64 + 0.5, i as f64 + 0.5);
                let k = i * w + j;
                let distance = edge_distance(&projected, pixel);
                if distance < out.edge_distance[k] {
                    out.edge_distance[k] = distance;
                }
                if !inside(&projected, area, pixel) {
                    continue;
                }
                // Ray through the pixel centre meets the triangle's plane at s * ray.
                let ray = DVec3::new(
                    (pixel.x - camera.cx) / camera.fx,
                    (pixel.y - camera.cy) / camera.fy,
                    1.0,
                );
                let s = normal.dot(c[0]) / normal.dot(ray);
                let x = ray * s;
                let nn = normal.length_squared();
                let bary = [
                    (c[1] - x).cross(c[2] - x).dot(normal) / nn,
                    (c[2] - x).cross(c[0] - x).dot(normal) / nn,
                    (c[0] - x).cross(c[1] - x).dot(normal) / nn,
                ];
                let z = x.z;
                if out.ids[k] == 0 || z < out.depth[k] {
                    out.ids[k] = t as u32 + 1;
                    out.bary[k] = bary;
                    out.depth[k] = z;
                }
            }
        }
    }
    out
}

/// Clips a camera-space triangle to z >= near (Sutherland-Hodgman).
fn clip_near(triangle: &[DVec3; 3], near: f64) -> Vec<DVec3> {
    let mut out = Vec::with_capacity(4);
    for k in 0..3 {
        let (a, b) = (triangle[k], triangle[(k + 1) % 3]);
        let (a_in, b_in) = (a.z >= near, b.z >= near);
        if a_in {
            out.push(a);
        }
        if a_in != b_in {
            let s = (near - a.z) / (b.z - a.z);
            let mut p = a + (b - a) * s;
            p.z = near;
            out.push(p);
        }
    }
    out
}

fn signed_area(polygon: &[DVec2]) -> f64 {
    let n = polygon.len();
    (0..n)
        .map(|k| polygon[k].perp_dot(polygon[(k + 1) % n]))
        .sum::<f64>()
        / 2.0
}

/// Strictly inside a convex polygon of the given orientation.
fn inside(polygon: &[DVec2], area: f64, p: DVec2) -> bool {
    let n = polygon.len();
    (0..n).all(|k| {
        let (a, b) = (polygon[k], polygon[(k + 1) % n]);
        (b - a).perp_dot(p - a) * area.signum() > 0.0
    })
}

/// Distance from `p` to the nearest edge of the polygon.
fn edge_distance(polygon: &[DVec2], p: DVec2) -> f64 {
    let n = polygon.len();
    (0..n)
        .map(|k| {
            let (a, b) = (polygon[k], polygon[(k + 1) % n]);
            let ab = b - a;
            let s = if ab.length_squared() > 0.0 {
                ((p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0)
            } else {
                0.0
            };
            (a + ab * s - p).length()
        })
        .fold(f64::INFINITY, f64::min)
}
