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

/// A tube of radius `small` along the arc of radius `big` about (`centre_x`, 0, 0) in the
/// xy plane, from angle `from` to `to` (radians from +x towards +y), closed at both ends.
fn arc_tube(
    centre_x: f64,
    big: f64,
    small: f64,
    from: f64,
    to: f64,
    rings: u32,
    sides: u32,
) -> Mesh {
    let mut positions = Vec::new();
    let axis = |u: f64| DVec3::new(centre_x + big * u.cos(), big * u.sin(), 0.0);
    for i in 0..rings {
        let u = from + (to - from) * i as f64 / (rings - 1) as f64;
        let radial = DVec3::new(u.cos(), u.sin(), 0.0);
        for j in 0..sides {
            let v = std::f64::consts::TAU * j as f64 / sides as f64;
            let p = axis(u) + small * (v.cos() * radial + v.sin() * DVec3::Z);
            positions.push(p.as_vec3().to_array());
        }
    }
    let (first, last) = (rings * sides, rings * sides + 1);
    positions.push(axis(from).as_vec3().to_array());
    positions.push(axis(to).as_vec3().to_array());
    let at = |i: u32, j: u32| i * sides + j % sides;
    let mut triangles = Vec::new();
    for i in 0..rings - 1 {
        for j in 0..sides {
            triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
            triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
        }
    }
    for j in 0..sides {
        triangles.push([first, at(0, j), at(0, j + 1)]);
        triangles.push([last, at(rings - 1, j + 1), at(rings - 1, j)]);
    }
    Mesh::new(positions, triangles).expect("an arc tube is valid")
}

/// An open mug: a wall a few millimetres thick, an inside bottom, and a handle whose ends
/// sit in the wall (its outer quarter), not in the cavity.
fn mug(rng: &mut Rng) -> Mesh {
    let h = rng.range(0.08, 0.115);
    let r = rng.range(0.035, 0.05);
    let top = r * rng.range(1.0, 1.12);
    let wall = rng.range(0.005, 0.007);
    let base = rng.range(0.006, 0.01);
    let body = lathe_centred(
        &[
            (0.92 * r, 0.0),
            (r, 0.04 * h),
            (top, h),
            (top - wall, h),
            (r - wall, base),
        ],
        32,
    );
    // The outer radius at height y of the centred body (its box is centred in y).
    let outer = |y: f64| {
        let t = ((y + 0.5 * h - 0.04 * h) / (0.96 * h)).clamp(0.0, 1.0);
        r + (top - r) * t
    };
    let big = rng.range(0.25, 0.38) * h;
    let small = rng.range(0.004, 0.006);
    let centre_x = r + 0.5 * big;
    // Each end where the arc's axis reaches the wall's outer quarter (bisection on the
    // angle; the axis moves inwards from u = pi/2 to pi).
    let end = |sign: f64| {
        let inside = |u: f64| {
            let (x, y) = (centre_x + big * u.cos(), sign * big * u.sin());
            x < outer(y) - 0.25 * wall
        };
        let (mut lo, mut hi) = (std::f64::consts::FRAC_PI_2, std::f64::consts::PI);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if inside(mid) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        sign * hi
    };
    let handle = arc_tube(centre_x, big, small, end(-1.0), end(1.0), 24, 10);
    centred(&merged(&[body, handle]))
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
}
