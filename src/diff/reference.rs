//! Float64 reference of the differentiable renderer's forward model, with the triangle
//! ids of every pixel held fixed (visibility is piecewise constant: within one piece the
//! image is a smooth function of the vertices and poses, which is what central
//! differences of this model measure and the device's gradients must match).
//!
//! It mirrors `glsl/include/diff.glsl`, `shade.glsl`, `antialias.comp` and `lambert.comp`
//! step by step.

use glam::{DMat3, DVec2, DVec3};

use super::{DepthLoss, Shading, MAX_DEPTH_RESIDUAL, NO_NEIGHBOUR};
use crate::camera::Camera;
use crate::loss::{reference as loss_reference, Loss};

/// As `MAX_WALK` in `glsl/include/diff.glsl`: a guard against broken meshes, not a limit
/// real crossings reach.
const MAX_WALK: usize = 65536;

/// Everything the model holds fixed.
pub struct Problem<'a> {
    /// Vertex indices of each triangle.
    pub triangles: &'a [[u32; 3]],
    /// As [`super::neighbours`].
    pub neighbours: &'a [u32],
    /// Camera of each view.
    pub cameras: &'a [Camera],
    /// Triangle id + 1 per pixel, `[view][row][column]` (from the device).
    pub ids: &'a [u32],
    /// Observed images, `[view][row][column][channel]`.
    pub observed: &'a [f64],
    /// Signed distance fields, `[view][row][column]` (only read by [`Loss::Distance`]).
    pub distance: &'a [f64],
    /// Per-vertex attributes and their channel count, or `None` for coverage.
    pub attributes: Option<(&'a [f64], usize)>,
    /// Lambert shading instead of attributes (one channel).
    pub shading: Option<Shading>,
    /// How the images are compared.
    pub loss: Loss,
    /// Observed depth, `[view][row][column]` (0: not measured), and how it is compared.
    pub depth: Option<(&'a [f64], DepthLoss)>,
}

/// The depth term of one pixel with residual r (as `depth_term` in
/// `glsl/include/diff_pass.glsl`), over `pixels` pixels.
pub fn depth_term(loss: &DepthLoss, r: f64, pixels: f64) -> f64 {
    let u = r.clamp(-MAX_DEPTH_RESIDUAL, MAX_DEPTH_RESIDUAL) / loss.scale;
    loss.weight * u * u / (1.0 + u * u) / pixels
}

/// A pose as the model takes it: camera = rotation * object + translation.
#[derive(Clone, Copy, Debug)]
pub struct RigidPose {
    /// Object-to-camera rotation.
    pub rotation: DMat3,
    /// The object origin in the camera frame, metres.
    pub translation: DVec3,
}

/// The model's output.
pub struct Output {
    /// Sum over views of each view's loss.
    pub loss: f64,
    /// Loss of each view.
    pub view_losses: Vec<f64>,
    /// Antialiased images, `[view][row][column][channel]` (with depth, a last channel: the
    /// depth at covered pixel centres, 0 elsewhere).
    pub antialiased: Vec<f64>,
}

struct Tri {
    v: [usize; 3],
    cam: [DVec3; 3],
    clip: [DVec3; 3],
}

struct ViewModel<'a> {
    problem: &'a Problem<'a>,
    camera: Camera,
    ids: &'a [u32],
    cam: Vec<DVec3>,
    /// This view's shading of every vertex (with `Problem::shading`).
    shade: Vec<f64>,
    scale: DVec2,
    shift: DVec2,
}

fn cross2(a: DVec2, b: DVec2) -> f64 {
    a.x * b.y - a.y * b.x
}

fn edge_function(ci: DVec3, cj: DVec3, p: DVec2) -> f64 {
    cross2(
        DVec2::new(ci.x, ci.y) - p * ci.z,
        DVec2::new(cj.x, cj.y) - p * cj.z,
    )
}

fn edge_functions(c: &[DVec3; 3], p: DVec2) -> [f64; 3] {
    [
        edge_function(c[1], c[2], p),
        edge_function(c[2], c[0], p),
        edge_function(c[0], c[1], p),
    ]
}

struct Crossing {
    triangle: usize,
    edge: usize,
    alpha: f64,
}

struct Pair {
    f: (usize, usize),
    g: (usize, usize),
    affects_g: bool,
    weight: f64,
}

impl ViewModel<'_> {
    fn tri(&self, t: usize) -> Tri {
        let v = self.problem.triangles[t].map(|i| i as usize);
        let cam = v.map(|i| self.cam[i]);
        let clip = cam.map(|c| {
            let xy = self.scale * DVec2::new(c.x, c.y) + self.shift * c.z;
            DVec3::new(xy.x, xy.y, c.z)
        });
        Tri { v, cam, clip }
    }

    fn facing(tri: &Tri) -> f64 {
        if tri.cam[0].dot(tri.cam[1].cross(tri.cam[2])) >= 0.0 {
            1.0
        } else {
            -1.0
        }
    }

    fn ndc(&self, (x, y): (usize, usize)) -> DVec2 {
        DVec2::new(
            (x as f64 + 0.5) * 2.0 / self.camera.width as f64 - 1.0,
            (y as f64 + 0.5) * 2.0 / self.camera.height as f64 - 1.0,
        )
    }

    fn id(&self, (x, y): (usize, usize)) -> u32 {
        self.ids[y * self.camera.width as usize + x]
    }

    fn barycentrics(tri: &Tri, p: DVec2) -> [f64; 3] {
        let e = edge_functions(&tri.clip, p);
        let s = e[0] + e[1] + e[2];
        e.map(|v| v / s)
    }

    fn depth(&self, t: usize, p: DVec2) -> f64 {
        let tri = self.tri(t);
        let b = Self::barycentrics(&tri, p);
        (0..3).map(|k| b[k] * tri.cam[k].z).sum()
    }

    fn colour(&self, pixel: (usize, usize), channels: usize) -> Vec<f64> {
        let id = self.id(pixel);
        let mut c = vec![0.0; channels];
        if id == 0 {
            return c;
        }
        let attributes = match (self.problem.shading, self.problem.attributes) {
            (Some(_), _) => Some((&self.shade[..], 1)),
            (None, given) => given,
        };
        match attributes {
            None => c[0] = 1.0,
            Some((attributes, n)) => {
                let tri = self.tri(id as usize - 1);
                let b = Self::barycentrics(&tri, self.ndc(pixel));
                for (ch, value) in c.iter_mut().enumerate() {
                    *value = (0..3).map(|k| b[k] * attributes[tri.v[k] * n + ch]).sum();
                }
            }
        }
        c
    }

    /// The function of the edge opposite corner k at p, from its vertices in index order
    /// (as `walk_edge_function`).
    fn walk_edge_function(tri: &Tri, k: usize, p: DVec2) -> f64 {
        let (i, j) = ((k + 1) % 3, (k + 2) % 3);
        if tri.v[i] < tri.v[j] {
            edge_function(tri.clip[i], tri.clip[j], p)
        } else {
            -edge_function(tri.clip[j], tri.clip[i], p)
        }
    }

    /// The walk of `find_crossing` in `glsl/include/diff.glsl`: the first triangle's
    /// exit by its crossing parameters, every later one by the side of the segment's line
    /// its corner opposite the entry edge lies on. Panics when the walk reaches
    /// `MAX_WALK` or the neighbour table does not match (the device reports both).
    fn find_crossing(&self, t: usize, pf: DVec2, pb: DVec2) -> Option<Crossing> {
        let d = pb - pf;
        let left_of_line = |c: DVec3| cross2(d, DVec2::new(c.x, c.y) - pf * c.z) >= 0.0;
        let mut current = t;
        let mut entry: Option<[usize; 2]> = None;
        for _ in 0..MAX_WALK {
            let tri = self.tri(current);
            let inside = Self::facing(&tri);
            let left = tri.clip.map(left_of_line);
            let edge = match entry {
                None => {
                    (0..3)
                        .filter(|&k| left[(k + 1) % 3] != left[(k + 2) % 3])
                        .map(|k| {
                            let ef = Self::walk_edge_function(&tri, k, pf);
                            let eb = Self::walk_edge_function(&tri, k, pb);
                            (k, (ef - eb) * inside)
                        })
                        .max_by(|a, b| a.1.total_cmp(&b.1))?
                        .0
                }
                Some(entry) => {
                    let on_entry = |k: usize| entry.contains(&tri.v[k]);
                    let apex = (0..3).find(|&k| !on_entry(k));
                    let apex = match apex {
                        Some(a) if (0..3).filter(|&k| on_entry(k)).count() == 2 => a,
                        _ => panic!("the neighbour table does not match triangle {current}"),
                    };
                    let (i, j) = ((apex + 1) % 3, (apex + 2) % 3);
                    if left[i] != left[apex] {
                        j
                    } else {
                        i
                    }
                }
            };
            let ef = Self::walk_edge_function(&tri, edge, pf);
            let eb = Self::walk_edge_function(&tri, edge, pb);
            if eb * inside >= 0.0 {
                return None;
            }
            let next = self.problem.neighbours[3 * current + edge];
            let silhouette =
                next == NO_NEIGHBOUR || Self::facing(&self.tri(next as usize)) != inside;
            if silhouette {
                return Some(Crossing {
                    triangle: current,
                    edge,
                    alpha: ef / (ef - eb),
                });
            }
            entry = Some([tri.v[(edge + 1) % 3], tri.v[(edge + 2) % 3]]);
            current = next as usize;
        }
        panic!("the silhouette search crossed {MAX_WALK} triangles without an end");
    }

    fn handled_along_x(&self, tri: &Tri, edge: usize) -> bool {
        let ci = tri.clip[(edge + 1) % 3];
        let cj = tri.clip[(edge + 2) % 3];
        let lx = ci.y * cj.z - ci.z * cj.y;
        let ly = ci.z * cj.x - ci.x * cj.z;
        lx.abs() / self.camera.width as f64 >= ly.abs() / self.camera.height as f64
    }

    fn make_pair(&self, p: (usize, usize), q: (usize, usize), along_x: bool) -> Option<Pair> {
        let (id_p, id_q) = (self.id(p), self.id(q));
        if id_p == id_q {
            return None;
        }
        let (np, nq) = (self.ndc(p), self.ndc(q));
        let depth = |id: u32, n: DVec2| {
            if id == 0 {
                f64::INFINITY
            } else {
                self.depth(id as usize - 1, n)
            }
        };
        let p_front = depth(id_p, np) <= depth(id_q, nq);
        let (f, g, front_id, pf, pb) = if p_front {
            (p, q, id_p, np, nq)
        } else {
            (q, p, id_q, nq, np)
        };
        let crossing = self.find_crossing(front_id as usize - 1, pf, pb)?;
        if self.handled_along_x(&self.tri(crossing.triangle), crossing.edge) != along_x {
            return None;
        }
        Some(Pair {
            f,
            g,
            affects_g: crossing.alpha > 0.5,
            // As place_alpha in glsl/include/diff.glsl: a crossing outside the pair counts
            // as at the nearer centre.
            weight: (crossing.alpha.clamp(0.0, 1.0) - 0.5).abs(),
        })
    }

    fn antialiased(&self, channels: usize) -> Vec<f64> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let mut out = vec![0.0; w * h * channels];
        for y in 0..h {
            for x in 0..w {
                let p = (x, y);
                let c = self.colour(p, channels);
                let mut a = c.clone();
                let neighbours = [(1i64, 0i64), (0, 1), (-1, 0), (0, -1)];
                for (s, (dx, dy)) in neighbours.into_iter().enumerate() {
                    let (qx, qy) = (x as i64 + dx, y as i64 + dy);
                    if qx < 0 || qy < 0 || qx >= w as i64 || qy >= h as i64 {
                        continue;
                    }
                    let q = (qx as usize, qy as usize);
                    let pair = if s < 2 {
                        self.make_pair(p, q, s == 0)
                    } else {
                        self.make_pair(q, p, s == 2)
                    };
                    let Some(pair) = pair else { continue };
                    let affected = if pair.affects_g { pair.g } else { pair.f };
                    if affected != p {
                        continue;
                    }
                    let other = if pair.affects_g { pair.f } else { pair.g };
                    let co = self.colour(other, channels);
                    for ch in 0..channels {
                        a[ch] += pair.weight * (co[ch] - c[ch]);
                    }
                }
                out[(y * w + x) * channels..][..channels].copy_from_slice(&a);
            }
        }
        out
    }
}

/// Lambert shading of every vertex at camera-space positions `cam` (as `lambert.comp`).
pub fn lambert(shading: &Shading, triangles: &[[u32; 3]], cam: &[DVec3]) -> Vec<f64> {
    let light = DVec3::from_array(shading.light).normalize();
    let mut normals = vec![DVec3::ZERO; cam.len()];
    for tri in triangles {
        let x = tri.map(|v| cam[v as usize]);
        let m = (x[1] - x[0]).cross(x[2] - x[0]);
        for &v in tri {
            normals[v as usize] += m;
        }
    }
    normals
        .iter()
        .zip(cam)
        .map(|(m, x)| {
            // Two-sided: seen from behind, the normal flips.
            let side = if m.dot(*x) > 0.0 { -1.0 } else { 1.0 };
            let lit = if m.length() > 0.0 {
                side * m.normalize().dot(light)
            } else {
                0.0
            };
            shading.ambient + (1.0 - shading.ambient) * lit.max(0.0)
        })
        .collect()
}

/// Evaluates the model at object-space `positions` and per-view `poses`.
pub fn evaluate(problem: &Problem, positions: &[DVec3], poses: &[RigidPose]) -> Output {
    let channels = match problem.shading {
        Some(_) => 1,
        None => problem.attributes.map_or(1, |(_, n)| n),
    };
    let mut offset_ids = 0;
    let mut offset_distance = 0;
    let mut view_losses = Vec::new();
    let mut antialiased = Vec::new();
    for (camera, pose) in problem.cameras.iter().zip(poses) {
        let n = camera.width as usize * camera.height as usize;
        let (w, h) = (camera.width as f64, camera.height as f64);
        let cam: Vec<DVec3> = positions
            .iter()
            .map(|&x| pose.rotation * x + pose.translation)
            .collect();
        let model = ViewModel {
            problem,
            camera: *camera,
            ids: &problem.ids[offset_ids..offset_ids + n],
            shade: problem
                .shading
                .map_or_else(Vec::new, |s| lambert(&s, problem.triangles, &cam)),
            cam,
            scale: DVec2::new(2.0 * camera.fx / w, 2.0 * camera.fy / h),
            shift: DVec2::new(2.0 * camera.cx / w - 1.0, 2.0 * camera.cy / h - 1.0),
        };
        let a = model.antialiased(channels);
        let observed = &problem.observed[offset_ids * channels..(offset_ids + n) * channels];
        let distance = if problem.loss == Loss::Distance {
            &problem.distance[offset_distance..offset_distance + n]
        } else {
            &[][..]
        };
        // Pixels that count for nothing (as `unknown` and `occluded` in
        // glsl/include/loss.glsl): an observed channel 0 below 0, or with depth a covered
        // pixel observed as background whose measured depth is nearer than the rendered
        // surface by more than the occlusion tolerance.
        let (width, height) = (camera.width as usize, camera.height as usize);
        let rendered_depth = |x: usize, y: usize| {
            let id = model.id((x, y));
            (id != 0).then(|| model.depth(id as usize - 1, model.ndc((x, y))))
        };
        let counted: Vec<bool> = (0..n)
            .map(|i| {
                let o = observed[i * channels];
                if o < 0.0 {
                    return false;
                }
                let Some((depth, loss)) = problem.depth else {
                    return true;
                };
                let measured = depth[offset_ids + i];
                let occluded = loss.occlusion > 0.0
                    && o == 0.0
                    && measured > 0.0
                    && rendered_depth(i % width, i / width)
                        .is_some_and(|z| z - measured > loss.occlusion);
                !occluded
            })
            .collect();
        let keep = |values: &[f64]| -> Vec<f64> {
            values
                .chunks(channels)
                .zip(&counted)
                .flat_map(|(v, &c)| v.iter().map(move |&x| if c { x } else { 0.0 }))
                .collect()
        };
        let mut view_loss =
            loss_reference::loss(problem.loss, &keep(&a), &keep(observed), distance, channels);
        match problem.depth {
            None => antialiased.extend(a),
            Some((depth, loss)) => {
                let depth = &depth[offset_ids..offset_ids + n];
                for y in 0..height {
                    for x in 0..width {
                        let i = y * width + x;
                        let id = model.id((x, y));
                        let z = rendered_depth(x, y).unwrap_or(0.0);
                        // Only where the observation shows the object (loss.glsl).
                        let on_object = observed[i * channels] > 0.0;
                        if id != 0 && depth[i] > 0.0 && counted[i] && on_object {
                            view_loss += depth_term(&loss, z - depth[i], n as f64);
                        }
                        antialiased.extend_from_slice(&a[i * channels..(i + 1) * channels]);
                        // Against a mask, 0 where the depth cannot count (not measured,
                        // or the pixel unknown: loss.glsl depth_measured).
                        let measured = depth[i] > 0.0 && observed[i * channels] >= 0.0;
                        let coverage = problem.shading.is_none() && problem.attributes.is_none();
                        antialiased.push(if coverage && !measured { 0.0 } else { z });
                    }
                }
            }
        }
        view_losses.push(view_loss);
        offset_ids += n;
        offset_distance += n;
    }
    Output {
        loss: view_losses.iter().sum(),
        view_losses,
        antialiased,
    }
}
