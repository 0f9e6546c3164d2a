//! Triangle meshes on the host: validated construction, OBJ in and out, PLY in (BOP's
//! object models), generators.
//!
//! Vertices keep the order of the OBJ file's `v` lines and triangles the order of its
//! `f` lines, so triangle ids and per-vertex outputs line up with the file. Polygons with
//! more than three corners are split into a fan (corner 0, k, k + 1).

use std::fmt::Write as _;
use std::path::Path;

use glam::DVec3;

use crate::error::{Error, Result};

mod ply;

/// The mean of `points` (zero for none).
pub fn centroid(points: &[DVec3]) -> DVec3 {
    points.iter().sum::<DVec3>() / points.len().max(1) as f64
}

/// `n` points on the surface of `triangles` over `points`, uniform by area, drawn with a
/// generator seeded `seed` (deterministic); none for a surface without area. A triangle
/// without area (zero, or not finite) is never drawn.
pub fn surface_sample(points: &[DVec3], triangles: &[[u32; 3]], n: usize, seed: u64) -> Vec<DVec3> {
    let corners = |t: &[u32; 3]| t.map(|i| points[i as usize]);
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut total = 0.0;
    for t in triangles {
        let [a, b, c] = corners(t);
        let area = 0.5 * (b - a).cross(c - a).length();
        total += if area.is_finite() { area } else { 0.0 };
        cumulative.push(total);
    }
    if total <= 0.0 {
        return Vec::new();
    }
    let mut rng = crate::rng::Rng::new(seed);
    (0..n)
        .map(|_| {
            let r = rng.range(0.0, total);
            let k = cumulative
                .partition_point(|&c| c <= r)
                .min(triangles.len() - 1);
            let [a, b, c] = corners(&triangles[k]);
            let (mut u, mut v) = (rng.uniform(), rng.uniform());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            a + u * (b - a) + v * (c - a)
        })
        .collect()
}

/// A welded triangle mesh: shared vertices, one index per corner, counter-clockwise
/// outward faces.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    positions: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// The largest vertex coordinate, metres (as [`crate::Pose::MAX_TRANSLATION`]: past it
    /// the device's float32 has no millimetres left).
    pub const MAX_COORDINATE: f64 = 1e6;

    /// Checks and builds a mesh: at least one triangle, finite coordinates, indices in
    /// range.
    pub fn new(positions: Vec<[f32; 3]>, triangles: Vec<[u32; 3]>) -> Result<Self> {
        if triangles.is_empty() {
            return Err(Error::InvalidInput("mesh has no triangles".into()));
        }
        if let Some(i) = positions.iter().position(|p| {
            p.iter()
                .any(|c| !(c.is_finite() && c.abs() as f64 <= Mesh::MAX_COORDINATE))
        }) {
            return Err(Error::InvalidInput(format!(
                "vertex {i} has a coordinate that is not finite or past {:e} m: {:?}",
                Mesh::MAX_COORDINATE,
                positions[i]
            )));
        }
        let n = positions.len();
        if let Some((t, tri)) = triangles
            .iter()
            .enumerate()
            .find(|(_, tri)| tri.iter().any(|&v| v as usize >= n))
        {
            return Err(Error::InvalidInput(format!(
                "triangle {t} {tri:?} refers to a vertex out of range (mesh has {n} vertices)"
            )));
        }
        Ok(Self {
            positions,
            triangles,
        })
    }

    /// Vertex positions (x, y, z), metres.
    pub fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }

    /// Vertex indices of each triangle, counter-clockwise seen from outside.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    /// The positions in float64 (for host-side geometry).
    pub fn points(&self) -> Vec<DVec3> {
        self.positions
            .iter()
            .map(|p| DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .collect()
    }

    /// The same triangles over new vertex positions (one per vertex, checked).
    pub fn with_points(&self, points: &[DVec3]) -> Result<Self> {
        if points.len() != self.positions.len() {
            return Err(Error::InvalidInput(format!(
                "{} points for a mesh of {} vertices",
                points.len(),
                self.positions.len()
            )));
        }
        let positions = points
            .iter()
            .map(|p| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        Self::new(positions, self.triangles.clone())
    }

    /// Midpoint subdivision: every triangle becomes four, edge midpoints are shared, so
    /// the surface is unchanged and a welded mesh stays welded (about 4x the vertices).
    pub fn subdivided(&self) -> Self {
        let mut positions = self.positions.clone();
        let mut midpoints = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32| -> u32 {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let (p, q) = (positions[a as usize], positions[b as usize]);
                positions.push(std::array::from_fn(|k| 0.5 * (p[k] + q[k])));
                positions.len() as u32 - 1
            })
        };
        let mut triangles = Vec::with_capacity(4 * self.triangles.len());
        for &[a, b, c] in &self.triangles {
            let (ab, bc, ca) = (midpoint(a, b), midpoint(b, c), midpoint(c, a));
            triangles.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        Self {
            positions,
            triangles,
        }
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Axis-aligned bounds (min, max).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// Reads a PLY file (ASCII or binary little-endian; positions and faces, other
    /// properties are ignored), as BOP ships its object models.
    pub fn load_ply(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let at = |e: Error| match e {
            Error::InvalidInput(message) => Error::format(path, message),
            other => other,
        };
        ply::parse(&bytes).map_err(at)
    }

    /// Reads a mesh by its extension: `.ply` as PLY, anything else as OBJ.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        match path.extension() {
            Some(e) if e.eq_ignore_ascii_case("ply") => Self::load_ply(path),
            _ => Self::load_obj(path),
        }
    }

    /// Reads a Wavefront OBJ file (positions and faces; other statements are ignored).
    pub fn load_obj(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::parse_obj(&text).map_err(|e| match e {
            Error::InvalidInput(message) => Error::format(path, message),
            other => other,
        })
    }

    /// Parses OBJ text. Errors name the line.
    pub fn parse_obj(text: &str) -> Result<Self> {
        let mut positions = Vec::new();
        let mut triangles = Vec::new();
        for (number, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("");
            let mut words = line.split_whitespace();
            let at =
                |message: String| Error::InvalidInput(format!("line {}: {message}", number + 1));
            match words.next() {
                Some("v") => {
                    let mut p = [0f32; 3];
                    for c in &mut p {
                        let word = words
                            .next()
                            .ok_or_else(|| at("vertex has fewer than 3 coordinates".into()))?;
                        *c = word
                            .parse()
                            .map_err(|_| at(format!("'{word}' is not a number")))?;
                        if !c.is_finite() {
                            return Err(at(format!("non-finite coordinate '{word}'")));
                        }
                    }
                    positions.push(p);
                }
                Some("f") => {
                    let corners = words
                        .map(|word| {
                            let index = word.split('/').next().unwrap_or("");
                            let i: i64 = index
                                .parse()
                                .map_err(|_| at(format!("'{word}' is not a vertex reference")))?;
                            // OBJ indices are 1-based; negative ones count back from the end.
                            let resolved = if i > 0 {
                                i - 1
                            } else {
                                positions.len() as i64 + i
                            };
                            if i == 0 || resolved < 0 || resolved >= positions.len() as i64 {
                                return Err(at(format!(
                                    "vertex reference {i} is out of range ({} vertices so far)",
                                    positions.len()
                                )));
                            }
                            Ok(resolved as u32)
                        })
                        .collect::<Result<Vec<u32>>>()?;
                    if corners.len() < 3 {
                        return Err(at(format!(
                            "face has {} corners, needs at least 3",
                            corners.len()
                        )));
                    }
                    for k in 1..corners.len() - 1 {
                        triangles.push([corners[0], corners[k], corners[k + 1]]);
                    }
                }
                _ => {}
            }
        }
        Self::new(positions, triangles)
    }

    /// OBJ text for this mesh (vertices and faces in order).
    pub fn to_obj(&self) -> String {
        let mut out = String::with_capacity(self.positions.len() * 40 + self.triangles.len() * 24);
        out.push_str("# written by vkdr\n");
        for p in &self.positions {
            let _ = writeln!(out, "v {} {} {}", p[0], p[1], p[2]);
        }
        for t in &self.triangles {
            let _ = writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        out
    }

    /// Writes the mesh as OBJ, through a temporary file so a failure never leaves a
    /// truncated file behind.
    pub fn save_obj(&self, path: impl AsRef<Path>) -> Result<()> {
        crate::io::write_atomically(path.as_ref(), self.to_obj().as_bytes())
    }

    /// A UV sphere of `radius` centred at the origin: `rings` latitude bands and
    /// `segments` longitude segments, welded, outward counter-clockwise faces.
    pub fn uv_sphere(radius: f32, rings: u32, segments: u32) -> Self {
        let rings = rings.max(2);
        let segments = segments.max(3);
        let mut positions = vec![[0.0, -radius, 0.0]];
        for r in 1..rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            let (y, ring_radius) = (-radius * theta.cos(), radius * theta.sin());
            for s in 0..segments {
                let phi = std::f32::consts::TAU * s as f32 / segments as f32;
                positions.push([ring_radius * phi.cos(), y, ring_radius * phi.sin()]);
            }
        }
        positions.push([0.0, radius, 0.0]);
        Self {
            positions,
            triangles: capped_rings(rings - 1, segments),
        }
    }

    /// A closed surface of revolution about the y axis: `profile` lists (radius, y) from
    /// bottom to top (radii > 0); both ends are closed with a cap vertex on the axis.
    /// `segments` around the axis. Outward counter-clockwise faces.
    pub fn lathe(profile: &[(f32, f32)], segments: u32) -> Result<Self> {
        if profile.len() < 2 || segments < 3 {
            return Err(Error::InvalidInput(format!(
                "a lathe needs at least 2 profile points and 3 segments, got {} and {segments}",
                profile.len()
            )));
        }
        if profile
            .iter()
            .any(|&(r, y)| !r.is_finite() || r <= 0.0 || !y.is_finite())
        {
            return Err(Error::InvalidInput(
                "lathe radii must be finite and > 0".into(),
            ));
        }
        let rings = profile.len() as u32;
        let mut positions = vec![[0.0, profile[0].1, 0.0]];
        for &(r, y) in profile {
            for s in 0..segments {
                let phi = std::f32::consts::TAU * s as f32 / segments as f32;
                positions.push([r * phi.cos(), y, r * phi.sin()]);
            }
        }
        positions.push([0.0, profile[profile.len() - 1].1, 0.0]);
        Self::new(positions, capped_rings(rings, segments))
    }

    /// A bottle of about 0.25 m height (for demos and tests), centred at the origin.
    pub fn bottle(segments: u32) -> Self {
        let profile = [
            (0.030, -0.125),
            (0.036, -0.120),
            (0.037, -0.100),
            (0.037, 0.020),
            (0.034, 0.045),
            (0.022, 0.070),
            (0.014, 0.090),
            (0.013, 0.115),
            (0.015, 0.118),
            (0.015, 0.125),
        ];
        Self::lathe(&profile, segments).expect("the bottle profile is valid")
    }

    /// A flat grid of `nx` x `ny` quads (two triangles each) in the z = 0 plane,
    /// spanning [0, nx * spacing] x [0, ny * spacing]; triangles are ordered row by row.
    pub fn grid(nx: u32, ny: u32, spacing: f32) -> Self {
        let mut positions = Vec::with_capacity(((nx + 1) * (ny + 1)) as usize);
        for j in 0..=ny {
            for i in 0..=nx {
                positions.push([i as f32 * spacing, j as f32 * spacing, 0.0]);
            }
        }
        let mut triangles = Vec::with_capacity((2 * nx * ny) as usize);
        let v = |i: u32, j: u32| j * (nx + 1) + i;
        for j in 0..ny {
            for i in 0..nx {
                triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        Self {
            positions,
            triangles,
        }
    }
}

/// Triangles of a closed surface of `rings` rings of `segments` vertices each, stacked
/// bottom to top between two poles: vertex 0 is the bottom pole, then the rings, then the
/// top pole. Outward counter-clockwise faces when the rings run counter-clockwise seen
/// from below (as `uv_sphere` and `lathe` lay them out).
fn capped_rings(rings: u32, segments: u32) -> Vec<[u32; 3]> {
    let top = 1 + rings * segments;
    let ring = |r: u32, s: u32| 1 + r * segments + s % segments;
    let mut triangles = Vec::new();
    for s in 0..segments {
        triangles.push([0, ring(0, s), ring(0, s + 1)]);
        triangles.push([top, ring(rings - 1, s + 1), ring(rings - 1, s)]);
    }
    for r in 0..rings - 1 {
        for s in 0..segments {
            let (a, b) = (ring(r, s), ring(r, s + 1));
            let (c, d) = (ring(r + 1, s), ring(r + 1, s + 1));
            triangles.push([a, c, d]);
            triangles.push([a, d, b]);
        }
    }
    triangles
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_round_trip_keeps_order_and_triangulates_polygons() {
        let text =
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\nf -1 -2 -3\n";
        let mesh = Mesh::parse_obj(text).unwrap();
        assert_eq!(mesh.triangles(), &[[0, 1, 2], [0, 2, 3], [3, 2, 1]]);
        let again = Mesh::parse_obj(&mesh.to_obj()).unwrap();
        assert_eq!(again, mesh);
    }

    #[test]
    fn bad_obj_input_is_a_clear_error() {
        let cases = [
            ("v 0 0 0\nf 1 2 3\n", "out of range"),
            ("v 0 nan 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "non-finite"),
            ("v 0 inf 0\n", "non-finite"),
            ("v 0 0 0\nv 1 0 0\nf 1 2\n", "at least 3"),
            ("# nothing\n", "no triangles"),
            ("v 0 0\n", "fewer than 3"),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n",
                "not a vertex reference",
            ),
        ];
        for (text, expected) in cases {
            let message = Mesh::parse_obj(text).unwrap_err().to_string();
            assert!(message.contains(expected), "{text:?}: {message}");
        }
    }

    #[test]
    fn surface_samples_follow_area_and_skip_what_has_none() {
        let points = [
            DVec3::ZERO,
            DVec3::X,
            DVec3::Y,
            DVec3::new(5.0, 0.0, 0.0),
            DVec3::new(8.0, 0.0, 0.0),
            DVec3::new(5.0, 2.0, 0.0),
            DVec3::new(f64::NAN, 0.0, 0.0),
        ];
        // Areas 0.5, 3, 0 (collinear) and not finite.
        let triangles = [[0, 1, 2], [3, 4, 5], [0, 1, 3], [6, 1, 2]];
        let sample = surface_sample(&points, &triangles, 4000, 7);
        assert_eq!(sample, surface_sample(&points, &triangles, 4000, 7));
        let in_second = sample.iter().filter(|p| p.x >= 5.0).count() as f64 / 4000.0;
        assert!((in_second - 3.0 / 3.5).abs() < 0.02, "{in_second}");
        for p in &sample {
            let first = p.x >= 0.0 && p.y >= 0.0 && p.x + p.y <= 1.0 + 1e-12;
            let second = p.x >= 5.0 && p.y >= 0.0 && (p.x - 5.0) / 3.0 + p.y / 2.0 <= 1.0 + 1e-12;
            assert!(p.z == 0.0 && (first || second), "{p}");
        }
        assert!(surface_sample(&points, &triangles[2..3], 10, 7).is_empty());
    }

    #[test]
    fn generators_are_welded_and_in_range() {
        for mesh in [
            Mesh::uv_sphere(1.0, 8, 12),
            Mesh::grid(3, 2, 0.5),
            Mesh::bottle(16),
        ] {
            let checked = Mesh::new(mesh.positions.clone(), mesh.triangles.clone()).unwrap();
            assert_eq!(checked, mesh);
        }
        let sphere = Mesh::uv_sphere(1.0, 8, 12);
        assert_eq!(sphere.vertex_count(), 2 + 7 * 12);
        // Closed surfaces: V - E + F = 2 with E = 3F / 2.
        for closed in [sphere, Mesh::bottle(16)] {
            let (v, f) = (closed.vertex_count() as i64, closed.triangle_count() as i64);
            assert_eq!(v - 3 * f / 2 + f, 2);
        }
    }

    #[test]
    fn subdivision_keeps_the_surface_closed_and_in_place() {
        let mesh = Mesh::bottle(16);
        let fine = mesh.subdivided();
        let edges = 3 * mesh.triangle_count() / 2;
        assert_eq!(fine.vertex_count(), mesh.vertex_count() + edges);
        assert_eq!(fine.triangle_count(), 4 * mesh.triangle_count());
        assert_eq!(fine.bounds(), mesh.bounds());
        assert_eq!(&fine.positions()[..mesh.vertex_count()], mesh.positions());
        let (v, f) = (fine.vertex_count() as i64, fine.triangle_count() as i64);
        assert_eq!(v - 3 * f / 2 + f, 2, "still a closed genus-0 surface");
        Mesh::new(fine.positions.clone(), fine.triangles.clone()).unwrap();
    }
}
