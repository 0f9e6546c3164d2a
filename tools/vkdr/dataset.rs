//! A generated category dataset, so that everything can be tested and shown without
//! downloads: bottles, open mugs (a wall, an inside bottom, a handle), spray bottles,
//! drills (composite parts) and open bowls, each instance a watertight, welded mesh in one common frame
//! per category (centred, metres, y up), reproducible from a seed. Layout: `DIR/<category>/canonical.obj`, `train/*.obj`,
//! `test/*.obj`, `info.json`.

use std::path::Path;

use glam::{DMat3, DVec3};

use vkdr::error::{Error, Result};
use vkdr::mesh::Mesh;

pub const CATEGORIES: [&str; 5] = ["bottle", "mug", "spray_bottle", "drill", "bowl"];

pub use vkdr::rng::Rng;

/// Applies a rotation then a translation to every vertex.
fn transformed(mesh: &Mesh, rotation: DMat3, translation: DVec3) -> Mesh {
    let positions = mesh
        .positions()
        .iter()
        .map(|p| {
            let q = rotation * DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) + translation;
            [q.x as f32, q.y as f32, q.z as f32]
        })
        .collect();
    Mesh::new(positions, mesh.triangles().to_vec()).expect("a transformed valid mesh is valid")
}

/// Several closed parts as one mesh (each part stays watertight).
fn merged(parts: &[Mesh]) -> Mesh {
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    for part in parts {
        let offset = positions.len() as u32;
        positions.extend_from_slice(part.positions());
        triangles.extend(part.triangles().iter().map(|t| t.map(|v| v + offset)));
    }
    Mesh::new(positions, triangles).expect("merged valid meshes are valid")
}

/// A closed axis-aligned box centred at the origin with the given half sizes.
fn cuboid(half: DVec3) -> Mesh {
    let corners: Vec<[f32; 3]> = (0..8)
        .map(|i| {
            let s = |bit: i32| if i & bit != 0 { 1.0 } else { -1.0 };
            [
                (s(1) * half.x) as f32,
                (s(2) * half.y) as f32,
                (s(4) * half.z) as f32,
            ]
        })
        .collect();
    // Faces as quads (outward, counter-clockwise), split into two triangles each.
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let triangles = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    Mesh::new(corners, triangles).expect("a cuboid is valid")
}

/// A closed cylinder along y of radius r from y0 to y1 (with a few rings for CPD).
fn cylinder(r: f64, y0: f64, y1: f64, segments: u32) -> Mesh {
    let profile: Vec<(f32, f32)> = (0..=4)
        .map(|k| (r as f32, (y0 + (y1 - y0) * k as f64 / 4.0) as f32))
        .collect();
    Mesh::lathe(&profile, segments).expect("a cylinder is valid")
}

/// A closed torus in the x-y plane (ring radius big, tube radius small).
fn bottle(rng: &mut Rng) -> Mesh {
    let h = rng.range(0.20, 0.30);
    let r = rng.range(0.028, 0.045);
    let shoulder = rng.range(0.55, 0.72);
    let neck = rng.range(0.28, 0.42) * r;
    let profile = [
        (0.85 * r, 0.0),
        (r, 0.03 * h),
        (r, shoulder * h),
        (0.75 * r, (shoulder + 0.08) * h),
        (neck * 1.1, 0.86 * h),
        (neck, 0.96 * h),
        (neck * 1.15, h),
    ];
    lathe_centred(&profile, 32)
}

fn spray_bottle(rng: &mut Rng) -> Mesh {
    let h = rng.range(0.17, 0.24);
    let r = rng.range(0.03, 0.045);
    let body = lathe_centred(
        &[
            (0.9 * r, 0.0),
            (r, 0.05 * h),
            (r, 0.7 * h),
            (0.5 * r, 0.78 * h),
            (0.45 * r, 0.82 * h),
        ],
        24,
    );
    let head_h = rng.range(0.03, 0.045);
    let head = cuboid(DVec3::new(rng.range(0.025, 0.035), head_h / 2.0, 0.015));
    let (lo, hi) = body.bounds();
    let top = hi[1] as f64;
    let head = transformed(
        &head,
        DMat3::IDENTITY,
        DVec3::new(0.01, top + head_h / 2.0 - 0.003, 0.0),
    );
    let nozzle = transformed(
        &cylinder(0.006, 0.0, rng.range(0.015, 0.025), 12),
        DMat3::from_rotation_z(-std::f64::consts::FRAC_PI_2),
        DVec3::new(0.035, top + head_h * 0.6, 0.0),
    );
    let _ = lo;
    centred(&merged(&[body, head, nozzle]))
}

/// An open mug: a wall a few millimetres thick, an inside bottom, and a handle welded to
/// the wall (one closed surface, with a hole through it): a square tube along a half
/// ellipse whose two ends are quads of the outer wall, taken out of it.
fn mug(rng: &mut Rng) -> Mesh {
    const SEGMENTS: u32 = 32;
    /// Quads up the outer wall; the handle's ends are two of them.
    const WALL_QUADS: usize = 12;
    /// Cross-sections along the handle between its ends.
    const HANDLE_STEPS: usize = 20;
    let h = rng.range(0.08, 0.115);
    let r = rng.range(0.035, 0.05);
    let top = r * rng.range(1.0, 1.12);
    let wall = rng.range(0.005, 0.007);
    let base = rng.range(0.006, 0.01);
    // Half the handle's height, and how far it stands out from the wall.
    let big = rng.range(0.25, 0.38) * h;
    let reach = rng.range(0.8, 1.2) * big;

    let (y0, y1) = (0.04 * h, h);
    let mut profile = vec![(0.92 * r, 0.0)];
    profile.extend((0..=WALL_QUADS).map(|k| {
        let t = k as f64 / WALL_QUADS as f64;
        (r + (top - r) * t, y0 + (y1 - y0) * t)
    }));
    profile.extend([(top - wall, h), (r - wall, base)]);
    let profile: Vec<(f32, f32)> = profile.iter().map(|&(r, y)| (r as f32, y as f32)).collect();
    let body = Mesh::lathe(&profile, SEGMENTS).expect("the profile is valid");
    // Mesh::lathe's vertex of profile point `i` (wall ring k is point 1 + k), segment `s`.
    let at = |i: usize, s: u32| 1 + i as u32 * SEGMENTS + s % SEGMENTS;
    let spacing = (y1 - y0) / WALL_QUADS as f64;
    let half = ((big / spacing).round() as usize).clamp(1, WALL_QUADS / 2 - 1);
    let middle =
        (((0.55 * (y0 + y1) - y0) / spacing).round() as usize).clamp(half + 1, WALL_QUADS - half);
    let (low, high) = (middle - half, middle + half - 1);
    // The handle's end rings, corners in the order (-e, -n), (+e, -n), (+e, +n), (-e, +n),
    // e the direction of the segments and n the handle's normal in its plane (up at the
    // lower end, down at the upper, where the tube comes back).
    let lower = [
        at(1 + low, 0),
        at(1 + low, 1),
        at(2 + low, 1),
        at(2 + low, 0),
    ];
    let upper = [
        at(2 + high, 0),
        at(2 + high, 1),
        at(1 + high, 1),
        at(1 + high, 0),
    ];

    let point = |v: u32| {
        let p = body.positions()[v as usize];
        DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
    };
    let centre = |ring: &[u32; 4]| ring.iter().map(|&v| point(v)).sum::<DVec3>() / 4.0;
    let angle = std::f64::consts::PI / SEGMENTS as f64;
    let (d, e) = (
        DVec3::new(angle.cos(), 0.0, angle.sin()),
        DVec3::new(-angle.sin(), 0.0, angle.cos()),
    );
    let (from, to) = (centre(&lower), centre(&upper));
    let (rho0, rho1) = (from.dot(d), to.dot(d));
    // The half ellipse from the lower quad out and up to the upper quad, and its tangent.
    let path = |u: f64| {
        let rho = rho0 + (rho1 - rho0) * 0.5 * (1.0 - u.cos()) + reach * u.sin();
        rho * d + (0.5 * (from.y + to.y) - 0.5 * (to.y - from.y) * u.cos()) * DVec3::Y
    };
    let tangent = |u: f64| {
        let rho = (rho1 - rho0) * 0.5 * u.sin() + reach * u.cos();
        (rho * d + 0.5 * (to.y - from.y) * u.sin() * DVec3::Y).normalize()
    };
    let half_width = |ring: &[u32; 4]| 0.5 * (point(ring[1]) - point(ring[0])).length();
    let half_height = |ring: &[u32; 4]| 0.5 * (point(ring[3]) - point(ring[0])).length();
    let mut positions = body.positions().to_vec();
    let mut rings = vec![lower];
    for i in 1..HANDLE_STEPS {
        let u = std::f64::consts::PI * i as f64 / HANDLE_STEPS as f64;
        let t = i as f64 / HANDLE_STEPS as f64;
        let w = half_width(&lower) + (half_width(&upper) - half_width(&lower)) * t;
        let v = half_height(&lower) + (half_height(&upper) - half_height(&lower)) * t;
        let tan = tangent(u);
        let n = DVec3::Y * tan.dot(d) - d * tan.dot(DVec3::Y);
        let first = positions.len() as u32;
        for (se, sn) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            positions.push((path(u) + se * w * e + sn * v * n).as_vec3().to_array());
        }
        rings.push([first, first + 1, first + 2, first + 3]);
    }
    rings.push(upper);

    // The wall without the two end quads, and the tube's sides, each facing away from
    // the handle's path.
    let ends: Vec<&[u32; 4]> = vec![&lower, &upper];
    let mut triangles: Vec<[u32; 3]> = body
        .triangles()
        .iter()
        .filter(|t| !ends.iter().any(|q| t.iter().all(|v| q.contains(v))))
        .copied()
        .collect();
    let position = |v: u32| {
        let p = positions[v as usize];
        DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
    };
    for (i, pair) in rings.windows(2).enumerate() {
        let axis = 0.5
            * (path(std::f64::consts::PI * i as f64 / HANDLE_STEPS as f64)
                + path(std::f64::consts::PI * (i + 1) as f64 / HANDLE_STEPS as f64));
        for k in 0..4 {
            let quad = [
                pair[0][k],
                pair[0][(k + 1) % 4],
                pair[1][(k + 1) % 4],
                pair[1][k],
            ];
            let out = quad.iter().map(|&v| position(v)).sum::<DVec3>() / 4.0 - axis;
            for mut tri in [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]] {
                let (a, b, c) = (position(tri[0]), position(tri[1]), position(tri[2]));
                if (b - a).cross(c - a).dot(out) < 0.0 {
                    tri.swap(1, 2);
                }
                triangles.push(tri);
            }
        }
    }
    let mug = Mesh::new(positions, triangles).expect("the welded mug is valid");
    // The handle towards +x, as before.
    centred(&transformed(
        &mug,
        DMat3::from_rotation_y(angle),
        DVec3::ZERO,
    ))
}

fn drill(rng: &mut Rng) -> Mesh {
    let length = rng.range(0.15, 0.21);
    let radius = rng.range(0.026, 0.036);
    let body = transformed(
        &cylinder(radius, -length / 2.0, length / 2.0, 20),
        DMat3::from_rotation_z(-std::f64::consts::FRAC_PI_2),
        DVec3::new(0.0, 0.08, 0.0),
    );
    let chuck_r = rng.range(0.01, 0.016);
    let chuck = transformed(
        &cylinder(chuck_r, 0.0, rng.range(0.03, 0.05), 16),
        DMat3::from_rotation_z(-std::f64::consts::FRAC_PI_2),
        DVec3::new(length / 2.0, 0.08, 0.0),
    );
    let handle_h = rng.range(0.09, 0.13);
    let handle = transformed(
        &cuboid(DVec3::new(0.018, handle_h / 2.0, 0.016)),
        DMat3::from_rotation_z(rng.range(-0.3, -0.1)),
        DVec3::new(-0.01, 0.08 - radius - handle_h / 2.0 + 0.01, 0.0),
    );
    let battery = transformed(
        &cuboid(DVec3::new(rng.range(0.035, 0.05), 0.02, 0.03)),
        DMat3::IDENTITY,
        DVec3::new(-0.005, 0.08 - radius - handle_h - 0.005, 0.0),
    );
    centred(&merged(&[body, chuck, handle, battery]))
}

/// An open bowl on a foot: its outside curves from the foot up to the rim, its inside
/// follows a wall 4-6 mm thick down to a flat inside bottom.
fn bowl(rng: &mut Rng) -> Mesh {
    let h = rng.range(0.05, 0.08);
    let rim = rng.range(0.06, 0.09);
    let foot = rng.range(0.4, 0.5) * rim;
    let foot_h = rng.range(0.006, 0.01);
    let wall = rng.range(0.004, 0.006);
    let bulge = rng.range(0.6, 0.9);
    let outside = |t: f64| {
        let r = foot + (rim - foot) * (t * std::f64::consts::FRAC_PI_2).sin().powf(bulge);
        (r, foot_h + (h - foot_h) * t)
    };
    let steps = 8;
    let mut profile = vec![(foot, 0.0)];
    profile.extend((0..=steps).map(|k| outside(k as f64 / steps as f64)));
    profile.extend((0..=steps).rev().map(|k| {
        let (r, y) = outside(k as f64 / steps as f64);
        (r - wall, y.max(foot_h + wall))
    }));
    lathe_centred(&profile, 32)
}

fn lathe_centred(profile: &[(f64, f64)], segments: u32) -> Mesh {
    let p: Vec<(f32, f32)> = profile.iter().map(|&(r, y)| (r as f32, y as f32)).collect();
    centred(&Mesh::lathe(&p, segments).expect("profiles are valid"))
}

/// Moved so that its bounding box is centred at the origin.
fn centred(mesh: &Mesh) -> Mesh {
    let (lo, hi) = mesh.bounds();
    let c = DVec3::new(
        (lo[0] + hi[0]) as f64,
        (lo[1] + hi[1]) as f64,
        (lo[2] + hi[2]) as f64,
    ) / 2.0;
    transformed(mesh, DMat3::IDENTITY, -c)
}

/// One instance of `category` drawn with `rng`.
pub fn instance(category: &str, rng: &mut Rng) -> Result<Mesh> {
    Ok(match category {
        "bottle" => bottle(rng),
        "mug" => mug(rng),
        "spray_bottle" => spray_bottle(rng),
        "drill" => drill(rng),
        "bowl" => bowl(rng),
        other => {
            return Err(Error::InvalidInput(format!(
                "unknown category '{other}' ({})",
                CATEGORIES.join(", ")
            )))
        }
    })
}

/// Writes the dataset: per category `train` training and `test` test instances plus a
/// canonical one (the instance of mid-range parameters: a separate draw with seed-derived
/// state), and `info.json`. Returns the category directories.
pub fn generate(
    out: &Path,
    seed: u64,
    train: usize,
    test: usize,
    mut progress: impl FnMut(&str, usize, usize),
) -> Result<Vec<std::path::PathBuf>> {
    let mut dirs = Vec::new();
    for (c, category) in CATEGORIES.iter().enumerate() {
        let dir = out.join(category);
        for sub in ["train", "test"] {
            std::fs::create_dir_all(dir.join(sub)).map_err(|e| Error::io(dir.join(sub), e))?;
        }
        let mut rng = Rng::new(seed.wrapping_mul(31).wrapping_add(c as u64));
        let total = 1 + train + test;
        instance(category, &mut rng)?.save_obj(dir.join("canonical.obj"))?;
        progress(category, 1, total);
        for i in 0..train {
            instance(category, &mut rng)?
                .save_obj(dir.join("train").join(format!("{category}_{i:02}.obj")))?;
            progress(category, 2 + i, total);
        }
        for i in 0..test {
            instance(category, &mut rng)?
                .save_obj(dir.join("test").join(format!("{category}_test_{i:02}.obj")))?;
            progress(category, 2 + train + i, total);
        }
        let info = serde_json::json!({
            "category": category,
            "up_axis": "y",
            "units": "m",
            "seed": seed,
            "train": train,
            "test": test,
            "generator": "vkdr gen-dataset",
        });
        vkdr::io::write_json(&dir.join("info.json"), &info)?;
        dirs.push(dir);
    }
    Ok(dirs)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every edge of a closed surface is shared by exactly two triangles, once each way.
    fn is_watertight(mesh: &Mesh) -> bool {
        let mut edges = std::collections::HashMap::new();
        for t in mesh.triangles() {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        edges
            .iter()
            .all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    #[test]
    fn instances_are_watertight_reproducible_and_of_realistic_size() {
        for category in CATEGORIES {
            let a = instance(category, &mut Rng::new(7)).unwrap();
            let b = instance(category, &mut Rng::new(7)).unwrap();
            assert_eq!(a, b, "{category} is reproducible");
            let c = instance(category, &mut Rng::new(8)).unwrap();
            assert_ne!(a, c, "{category} varies with the seed");
            assert!(is_watertight(&a), "{category} is watertight");
            // Outward faces: the enclosed volume is positive.
            let p = a.points();
            let volume: f64 = a
                .triangles()
                .iter()
                .map(|t| {
                    let [x, y, z] = t.map(|v| p[v as usize]);
                    x.dot(y.cross(z)) / 6.0
                })
                .sum();
            assert!(volume > 0.0, "{category}: volume {volume}");
            let (lo, hi) = a.bounds();
            let size = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max);
            assert!((0.05..0.4).contains(&size), "{category}: {size} m");
            let centre = (0..3).map(|k| (hi[k] + lo[k]).abs()).fold(0.0f32, f32::max);
            assert!(centre < 1e-4, "{category} is centred");
        }
    }

    /// The triangles' connected pieces (through shared vertices).
    fn components(mesh: &Mesh) -> usize {
        let mut parent: Vec<usize> = (0..mesh.vertex_count()).collect();
        fn root(parent: &mut [usize], mut v: usize) -> usize {
            while parent[v] != v {
                parent[v] = parent[parent[v]];
                v = parent[v];
            }
            v
        }
        for t in mesh.triangles() {
            for k in 1..3 {
                let (a, b) = (
                    root(&mut parent, t[0] as usize),
                    root(&mut parent, t[k] as usize),
                );
                parent[a] = b;
            }
        }
        let mut roots: Vec<usize> = mesh
            .triangles()
            .iter()
            .map(|t| root(&mut parent, t[0] as usize))
            .collect();
        roots.sort();
        roots.dedup();
        roots.len()
    }

    /// The mug's handle is welded to its wall: one closed surface, for every draw.
    #[test]
    fn mugs_are_one_piece() {
        for seed in 0..20 {
            let mug = instance("mug", &mut Rng::new(seed)).unwrap();
            assert_eq!(components(&mug), 1, "seed {seed}");
            assert!(is_watertight(&mug), "seed {seed}");
        }
    }
}
