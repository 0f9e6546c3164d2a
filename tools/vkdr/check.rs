//! Checks of a user's category dataset before any long run (`vkdr check-dataset`, and the
//! first thing `eval` and `shape-space` do): what each mesh is (sizes, open boundaries,
//! components, duplicate vertices, degenerate faces), whether the category is one set in
//! metres, in one frame, with the up axis its `info.json` names, and a contact sheet that
//! shows all of it at a glance.
//!
//! Findings are [`Severity::Fatal`] where they would make a registration's figures
//! meaningless (no test instances, a millimetre-sized set against a camera in metres, an
//! up axis that cannot be read), and [`Severity::Warning`] where the data is usable but a
//! person should know (CPD only needs points, so open or unwelded scans register; shading
//! sees the inside of an open scan).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use image::{Rgb, RgbImage};

use crate::plot::draw_text;
use vkdr::error::{Error, Result};
use vkdr::mesh::Mesh;

/// What a category's `info.json` says (all of it optional).
#[derive(Clone, Debug, PartialEq)]
pub struct Info {
    /// The object-frame up axis, a signed unit axis (`"up_axis": "y"`, `"-z"`, ...; y when
    /// absent).
    pub up: DVec3,
    /// As written (`"y"` when absent).
    pub up_name: String,
    /// `"units"` as written, if given.
    pub units: Option<String>,
    /// Whether `info.json` exists.
    pub found: bool,
}

impl Info {
    /// Reads `dir/info.json`; a missing file means y up.
    pub fn read(dir: &Path) -> Result<Info> {
        let path = dir.join("info.json");
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Info {
                    up: DVec3::Y,
                    up_name: "y".into(),
                    units: None,
                    found: false,
                })
            }
            Err(source) => return Err(Error::Io { path, source }),
        };
        let bad = |message: String| Error::Format {
            path: path.clone(),
            message,
        };
        let json: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
        let field = |key: &str| -> Result<Option<String>> {
            match json.get(key) {
                None | Some(serde_json::Value::Null) => Ok(None),
                Some(serde_json::Value::String(s)) => Ok(Some(s.clone())),
                Some(other) => Err(bad(format!("\"{key}\" must be a string, not {other}"))),
            }
        };
        let up_name = field("up_axis")?.unwrap_or_else(|| "y".into());
        let up = parse_axis(&up_name).ok_or_else(|| {
            bad(format!(
                "\"up_axis\": \"{up_name}\" is not an axis (x, y, z, with an optional sign)"
            ))
        })?;
        Ok(Info {
            up,
            up_name,
            units: field("units")?,
            found: true,
        })
    }

    /// The rotation that takes this dataset's up axis to +y (the frame views are drawn in).
    pub fn to_y_up(&self) -> DQuat {
        DQuat::from_rotation_arc(self.up, DVec3::Y)
    }
}

/// `x`, `+Y`, `-z`, ... as a signed unit axis.
pub fn parse_axis(name: &str) -> Option<DVec3> {
    let name = name.trim().to_ascii_lowercase();
    let (sign, axis) = match name.strip_prefix('-') {
        Some(rest) => (-1.0, rest),
        None => (1.0, name.strip_prefix('+').unwrap_or(&name)),
    };
    let unit = match axis {
        "x" => DVec3::X,
        "y" => DVec3::Y,
        "z" => DVec3::Z,
        _ => return None,
    };
    Some(sign * unit)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    Canonical,
    Train,
    Test,
}

impl Role {
    fn colour(self) -> [u8; 3] {
        match self {
            Role::Canonical => [40, 90, 200],
            Role::Train => [120, 120, 120],
            Role::Test => [220, 120, 20],
        }
    }
}

/// What one mesh is.
#[derive(Clone, Debug)]
pub struct MeshStats {
    pub name: String,
    pub role: Role,
    pub vertices: usize,
    pub faces: usize,
    /// Bounding-box side lengths (the data's units).
    pub extent: DVec3,
    /// Mean of the vertices.
    pub centroid: DVec3,
    /// Centre of the bounding box (what "centred" means for a dataset: a dense part, as a
    /// can's lid, moves the vertex mean but not this).
    pub centre: DVec3,
    /// Edges of one face only (open boundaries).
    pub boundary_edges: usize,
    /// Edges of more than two faces.
    pub nonmanifold_edges: usize,
    /// Connected parts (vertices at one position count as one).
    pub components: usize,
    /// Vertices at the position of an earlier one.
    pub duplicate_vertices: usize,
    /// Faces of (near) zero area.
    pub degenerate_faces: usize,
}

impl MeshStats {
    pub fn of(name: &str, role: Role, mesh: &Mesh) -> Self {
        let points = mesh.points();
        let (lo, hi) = mesh.bounds();
        let extent = DVec3::from_array(hi.map(f64::from)) - DVec3::from_array(lo.map(f64::from));
        let centroid = vkdr::mesh::centroid(&points);
        // One id per distinct position, so unwelded seams do not split components.
        let mut first_at: HashMap<[u32; 3], u32> = HashMap::new();
        let welded: Vec<u32> = mesh
            .positions()
            .iter()
            .enumerate()
            .map(|(i, p)| *first_at.entry(p.map(f32::to_bits)).or_insert(i as u32))
            .collect();
        let duplicate_vertices = points.len() - first_at.len();
        let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
        let mut parts = UnionFind::new(points.len());
        let mut degenerate_faces = 0;
        let tiny = 1e-12 * extent.length_squared().max(f64::MIN_POSITIVE);
        for t in mesh.triangles() {
            let [a, b, c] = t.map(|v| points[v as usize]);
            if (b - a).cross(c - a).length() <= tiny {
                degenerate_faces += 1;
            }
            for (u, v) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                let (u, v) = (welded[u as usize], welded[v as usize]);
                parts.join(u, v);
                *edges.entry((u.min(v), u.max(v))).or_default() += 1;
            }
        }
        let used: std::collections::HashSet<u32> = mesh
            .triangles()
            .iter()
            .flatten()
            .map(|&v| parts.root(welded[v as usize]))
            .collect();
        MeshStats {
            name: name.to_string(),
            role,
            vertices: points.len(),
            faces: mesh.triangle_count(),
            extent,
            centroid,
            centre: 0.5
                * (DVec3::from_array(hi.map(f64::from)) + DVec3::from_array(lo.map(f64::from))),
            boundary_edges: edges.values().filter(|&&n| n == 1).count(),
            nonmanifold_edges: edges.values().filter(|&&n| n > 2).count(),
            components: used.len(),
            duplicate_vertices,
            degenerate_faces,
        }
    }

    /// Index of the longest bounding-box side.
    pub fn longest_axis(&self) -> usize {
        let e = self.extent.to_array();
        (0..3).max_by(|&a, &b| e[a].total_cmp(&e[b])).unwrap_or(0)
    }

    /// Whether the longest side is clearly the longest (1.2 times the next): where two
    /// sides are about equal (a can as tall as it is wide) which is longest says nothing
    /// about the frame.
    pub fn clearly_longest(&self) -> bool {
        let mut e = self.extent.to_array();
        e.sort_by(f64::total_cmp);
        e[2] >= 1.2 * e[1]
    }
}

struct UnionFind(Vec<u32>);

impl UnionFind {
    fn new(n: usize) -> Self {
        UnionFind((0..n as u32).collect())
    }
    fn root(&mut self, mut v: u32) -> u32 {
        while self.0[v as usize] != v {
            self.0[v as usize] = self.0[self.0[v as usize] as usize];
            v = self.0[v as usize];
        }
        v
    }
    fn join(&mut self, a: u32, b: u32) {
        let (a, b) = (self.root(a), self.root(b));
        self.0[a.max(b) as usize] = a.min(b);
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Severity {
    Warning,
    /// The results of `eval` or `shape-space` would be meaningless.
    Fatal,
}

#[derive(Clone, Debug)]
pub struct Finding {
    pub severity: Severity,
    /// The instance (its file name) or "category".
    pub subject: String,
    pub message: String,
}

/// A category's meshes and what was found in them.
pub struct Category {
    pub name: String,
    pub info: Info,
    /// Canonical first, then train/, then test/ (sorted by file name).
    pub meshes: Vec<(MeshStats, Mesh)>,
    pub findings: Vec<Finding>,
}

impl Category {
    pub fn fatal(&self) -> impl Iterator<Item = &Finding> {
        self.findings
            .iter()
            .filter(|f| f.severity == Severity::Fatal)
    }
}

/// The `.obj` files of a folder, sorted (none if it does not exist).
fn objs(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Ok(vec![]);
    }
    let entries = std::fs::read_dir(dir).map_err(|source| Error::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj")))
        .collect();
    files.sort();
    Ok(files)
}

/// Largest side (in metres) a category's objects may have before the set is taken to be
/// in millimetres, and the smallest before it is taken to be in kilometres (or broken).
pub const LARGEST_SIDE_M: f64 = 5.0;
pub const SMALLEST_SIDE_M: f64 = 0.005;

/// Loads and checks the category in `dir` (`canonical.obj`, `train/`, `test/`,
/// `info.json`). A mesh that does not load is an error naming its file.
pub fn check_category(dir: &Path) -> Result<Category> {
    let full = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    let name = full
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let info = Info::read(dir)?;
    let mut findings = Vec::new();
    let mut note = |severity, subject: &str, message: String| {
        findings.push(Finding {
            severity,
            subject: subject.to_string(),
            message,
        })
    };
    if !info.found {
        note(
            Severity::Warning,
            "category",
            "no info.json: taking y as the up axis".into(),
        );
    }
    if let Some(units) = info.units.as_deref() {
        let plain = units.trim().to_ascii_lowercase();
        if !matches!(
            plain.as_str(),
            "m" | "metre" | "meter" | "metres" | "meters"
        ) {
            note(
                Severity::Fatal,
                "category",
                format!(
                    "info.json says units \"{units}\": vkdr works in metres (scale the meshes)"
                ),
            );
        }
    }
    let mut files = Vec::new();
    let canonical = dir.join("canonical.obj");
    if canonical.is_file() {
        files.push((canonical, Role::Canonical));
    } else {
        note(Severity::Fatal, "category", "no canonical.obj".into());
    }
    for (folder, role) in [("train", Role::Train), ("test", Role::Test)] {
        let found = objs(&dir.join(folder))?;
        if found.is_empty() {
            // No training meshes: no shape space. No test meshes: nothing for eval (which
            // refuses that itself), a shape space still builds.
            let severity = match role {
                Role::Test => Severity::Warning,
                _ => Severity::Fatal,
            };
            note(
                severity,
                "category",
                format!("{folder}/ has no .obj meshes"),
            );
        }
        files.extend(found.into_iter().map(|f| (f, role)));
    }
    let mut meshes = Vec::new();
    for (path, role) in files {
        let mesh = Mesh::load_obj(&path)?;
        let file = path
            .strip_prefix(dir)
            .unwrap_or(&path)
            .display()
            .to_string();
        meshes.push((MeshStats::of(&file, role, &mesh), mesh));
    }
    let reference = meshes.first().map(|(s, _)| s.clone());
    for (s, _) in &meshes {
        let side = s.extent.max_element();
        if side > LARGEST_SIDE_M {
            let hint = if side > 1e3 * SMALLEST_SIDE_M && side / 1e3 < LARGEST_SIDE_M {
                " (millimetres? the set must be in metres)"
            } else {
                ""
            };
            note(
                Severity::Fatal,
                &s.name,
                format!("largest side {side:.4} m{hint}"),
            );
        } else if side < SMALLEST_SIDE_M {
            note(
                Severity::Fatal,
                &s.name,
                format!("largest side {side:.3e} m: too small for a camera at 0.7 m"),
            );
        }
        let of_the_mesh = [
            (
                s.boundary_edges > 0,
                format!(
                    "open: {} boundary edges (CPD registers it; shading sees its inside)",
                    s.boundary_edges
                ),
            ),
            (
                s.nonmanifold_edges > 0,
                format!("{} edges of more than two faces", s.nonmanifold_edges),
            ),
            (
                s.components > 1,
                format!("{} separate components", s.components),
            ),
            (
                s.duplicate_vertices > 0,
                format!("{} duplicate vertices (unwelded)", s.duplicate_vertices),
            ),
            (
                s.degenerate_faces > 0,
                format!("{} degenerate faces", s.degenerate_faces),
            ),
        ];
        for (found, message) in of_the_mesh {
            if found {
                note(Severity::Warning, &s.name, message);
            }
        }
        let Some(r) = reference.as_ref().filter(|r| r.name != s.name) else {
            continue;
        };
        let axes = ["x", "y", "z"];
        if s.longest_axis() != r.longest_axis() && s.clearly_longest() && r.clearly_longest() {
            note(
                Severity::Warning,
                &s.name,
                format!(
                    "longest along {} where {} is longest along {}: not in its frame (another up axis)?",
                    axes[s.longest_axis()],
                    r.name,
                    axes[r.longest_axis()]
                ),
            );
        }
        let scale = r.extent.max_element().max(f64::MIN_POSITIVE);
        let offset = (s.centre - r.centre).length();
        if offset > 0.25 * scale {
            note(
                Severity::Warning,
                &s.name,
                format!(
                    "bounding-box centre {:.3} m from {}'s ({:.0}% of its size): not centred like it?",
                    offset,
                    r.name,
                    100.0 * offset / scale
                ),
            );
        }
        let ratio = s.extent.max_element() / scale;
        if !(0.5..=2.0).contains(&ratio) {
            note(
                Severity::Warning,
                &s.name,
                format!("{ratio:.2} times the size of {}", r.name),
            );
        }
    }
    Ok(Category {
        name,
        info,
        meshes,
        findings,
    })
}

/// The report of a category as text, one line per mesh and per finding.
pub fn report(category: &Category) -> String {
    let mut out = format!(
        "{}: up axis {}{}, {} meshes\n",
        category.name,
        category.info.up_name,
        if category.info.found {
            ""
        } else {
            " (no info.json)"
        },
        category.meshes.len()
    );
    for (s, _) in &category.meshes {
        out.push_str(&format!(
            "  {:<28} {:>9} {:>7} v {:>7} f  {:.3} x {:.3} x {:.3} m  boundary {} components {} duplicates {} degenerate {}\n",
            s.name,
            format!("{:?}", s.role).to_lowercase(),
            s.vertices,
            s.faces,
            s.extent.x,
            s.extent.y,
            s.extent.z,
            s.boundary_edges,
            s.components,
            s.duplicate_vertices,
            s.degenerate_faces
        ));
    }
    for f in &category.findings {
        let tag = match f.severity {
            Severity::Fatal => "error",
            Severity::Warning => "warning",
        };
        out.push_str(&format!("  {tag}: {}: {}\n", f.subject, f.message));
    }
    out
}

/// Side of one silhouette tile of the contact sheet, pixels.
const TILE: u32 = 120;
const LABEL: u32 = 20;
const COLUMNS: u32 = 4;

/// A contact sheet of the category: per mesh, its silhouette seen from the front (along a
/// horizontal axis, up at the top) and from the top (down the up axis), all at one scale
/// about the canonical's centroid, framed in blue (canonical), grey (train) or orange
/// (test); the last cell overlays every silhouette (darker where more of them agree), so
/// a mesh out of the common frame stands out.
pub fn contact_sheet(category: &Category) -> RgbImage {
    let up = category.info.up;
    // Horizontal axes: `across` to the right in both views, `depth` down in the top view.
    let across = if up.x.abs() > 0.5 { DVec3::Z } else { DVec3::X };
    let depth = across.cross(up);
    let centre = category
        .meshes
        .first()
        .map_or(DVec3::ZERO, |(s, _)| s.centroid);
    let reach = category
        .meshes
        .iter()
        .flat_map(|(_, m)| m.points())
        .map(|p| (p - centre).length())
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let scale = 0.48 * TILE as f64 / reach;
    let views = [(across, -up), (across, depth)];
    let cells = category.meshes.len() as u32 + 1;
    let cell_w = 2 * TILE + 12;
    let cell_h = TILE + LABEL + 10;
    let rows = cells.div_ceil(COLUMNS);
    let mut sheet = RgbImage::from_pixel(
        COLUMNS * cell_w + 8,
        rows * cell_h + 8,
        Rgb([255, 255, 255]),
    );
    let mut overlay = vec![[0u32; (TILE * TILE) as usize]; 2];
    for (k, (stats, mesh)) in category.meshes.iter().enumerate() {
        let (x0, y0) = cell_origin(k as u32, cell_w, cell_h);
        for (v, &(right, down)) in views.iter().enumerate() {
            let mask = silhouette(mesh, centre, right, down, scale);
            for (count, &inside) in overlay[v].iter_mut().zip(&mask) {
                *count += u32::from(inside);
            }
            let tx = x0 + v as u32 * (TILE + 4);
            let coverage: Vec<f64> = mask.iter().map(|&i| f64::from(u8::from(i))).collect();
            draw_tile(&mut sheet, tx, y0 + LABEL, &coverage);
            frame(&mut sheet, tx, y0 + LABEL, stats.role.colour());
        }
        let label: String = stats.name.chars().take(20).collect();
        draw_text(&mut sheet, x0 as i64, y0 as i64 + 2, &label);
    }
    let (x0, y0) = cell_origin(cells - 1, cell_w, cell_h);
    let total = category.meshes.len().max(1) as f64;
    for (v, counts) in overlay.iter().enumerate() {
        let tx = x0 + v as u32 * (TILE + 4);
        let shade: Vec<f64> = counts.iter().map(|&c| c as f64 / total).collect();
        draw_tile(&mut sheet, tx, y0 + LABEL, &shade);
        frame(&mut sheet, tx, y0 + LABEL, [0, 0, 0]);
    }
    draw_text(&mut sheet, x0 as i64, y0 as i64 + 2, "all overlaid");
    sheet
}

fn cell_origin(k: u32, w: u32, h: u32) -> (u32, u32) {
    (4 + (k % COLUMNS) * w, 4 + (k / COLUMNS) * h)
}

/// Fills a tile: 0 white, 1 near black.
fn draw_tile(img: &mut RgbImage, x0: u32, y0: u32, coverage: &[f64]) {
    for y in 0..TILE {
        for x in 0..TILE {
            let c = coverage[(y * TILE + x) as usize].clamp(0.0, 1.0);
            let g = (255.0 - 215.0 * c) as u8;
            img.put_pixel(x0 + x, y0 + y, Rgb([g, g, g]));
        }
    }
}

fn frame(img: &mut RgbImage, x0: u32, y0: u32, colour: [u8; 3]) {
    for i in 0..TILE {
        for (x, y) in [
            (x0 + i, y0),
            (x0 + i, y0 + TILE - 1),
            (x0, y0 + i),
            (x0 + TILE - 1, y0 + i),
        ] {
            img.put_pixel(x, y, Rgb(colour));
        }
    }
}

/// The orthographic silhouette of `mesh` in a TILE x TILE tile: pixel (x, y) is the point
/// `centre + ((x + 0.5 - TILE/2) right + (y + 0.5 - TILE/2) down) / scale`, covered when a
/// triangle (either orientation) contains it.
fn silhouette(mesh: &Mesh, centre: DVec3, right: DVec3, down: DVec3, scale: f64) -> Vec<bool> {
    let half = TILE as f64 / 2.0;
    let project = |p: DVec3| {
        let d = p - centre;
        (d.dot(right) * scale + half, d.dot(down) * scale + half)
    };
    let points: Vec<(f64, f64)> = mesh.points().into_iter().map(project).collect();
    let mut mask = vec![false; (TILE * TILE) as usize];
    for t in mesh.triangles() {
        let [a, b, c] = t.map(|v| points[v as usize]);
        let area = (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
        if area == 0.0 || !area.is_finite() {
            continue;
        }
        let lo_x = a.0.min(b.0).min(c.0).floor().max(0.0) as u32;
        let hi_x = (a.0.max(b.0).max(c.0).ceil().min(TILE as f64)).max(0.0) as u32;
        let lo_y = a.1.min(b.1).min(c.1).floor().max(0.0) as u32;
        let hi_y = (a.1.max(b.1).max(c.1).ceil().min(TILE as f64)).max(0.0) as u32;
        let edge = |p: (f64, f64), q: (f64, f64), x: f64, y: f64| {
            ((q.0 - p.0) * (y - p.1) - (q.1 - p.1) * (x - p.0)) * area.signum()
        };
        for y in lo_y..hi_y {
            for x in lo_x..hi_x {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                if edge(a, b, px, py) >= 0.0
                    && edge(b, c, px, py) >= 0.0
                    && edge(c, a, px, py) >= 0.0
                {
                    mask[(y * TILE + x) as usize] = true;
                }
            }
        }
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axes_parse_with_signs_and_refuse_the_rest() {
        assert_eq!(parse_axis("y"), Some(DVec3::Y));
        assert_eq!(parse_axis("+Z"), Some(DVec3::Z));
        assert_eq!(parse_axis("-x"), Some(-DVec3::X));
        assert_eq!(parse_axis("up"), None);
        assert_eq!(parse_axis(""), None);
        for axis in [DVec3::X, -DVec3::Z, DVec3::Y, -DVec3::Y] {
            let info = Info {
                up: axis,
                up_name: String::new(),
                units: None,
                found: true,
            };
            assert!((info.to_y_up() * axis - DVec3::Y).length() < 1e-12);
        }
    }

    #[test]
    fn a_closed_welded_mesh_has_no_findings_of_its_own() {
        let s = MeshStats::of("bottle", Role::Canonical, &Mesh::bottle(12));
        assert_eq!(
            (
                s.boundary_edges,
                s.nonmanifold_edges,
                s.components,
                s.duplicate_vertices,
                s.degenerate_faces
            ),
            (0, 0, 1, 0, 0),
            "{s:?}"
        );
    }
}
