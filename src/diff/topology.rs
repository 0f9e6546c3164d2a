//! Mesh topology the antialiasing walks: each triangle's neighbours across its edges, and
//! the triangles around each vertex.

use std::collections::HashMap;

use crate::mesh::Mesh;

/// Marks an edge without exactly one neighbouring triangle.
pub const NO_NEIGHBOUR: u32 = u32::MAX;

/// For each triangle t and corner k, the triangle across the edge opposite corner k
/// (`neighbours[3 t + k]`), or [`NO_NEIGHBOUR`] for a boundary edge or one shared by more
/// than two triangles. Edges are matched by vertex index (welded meshes). A triangle that
/// names a vertex twice has no area and no neighbours, and is no triangle's neighbour.
pub fn neighbours(mesh: &Mesh) -> Vec<u32> {
    let triangles = mesh.triangles();
    let mut edges: HashMap<(u32, u32), Vec<(u32, usize)>> =
        HashMap::with_capacity(triangles.len() * 3 / 2);
    for (t, tri) in triangles.iter().enumerate() {
        if tri[0] == tri[1] || tri[1] == tri[2] || tri[2] == tri[0] {
            continue;
        }
        for k in 0..3 {
            let (a, b) = (tri[(k + 1) % 3], tri[(k + 2) % 3]);
            edges
                .entry((a.min(b), a.max(b)))
                .or_default()
                .push((t as u32, k));
        }
    }
    let mut out = vec![NO_NEIGHBOUR; triangles.len() * 3];
    for sharing in edges.values() {
        if let [(t0, k0), (t1, k1)] = sharing[..] {
            out[3 * t0 as usize + k0] = t1;
            out[3 * t1 as usize + k1] = t0;
        }
    }
    out
}

/// For each vertex, its triangles as `3 triangle + corner`: `(start, list)` with vertex v's
/// entries at `list[start[v]..start[v + 1]]` (ascending triangle order).
pub fn incident_triangles(mesh: &Mesh) -> (Vec<u32>, Vec<u32>) {
    let mut count = vec![0u32; mesh.vertex_count() + 1];
    for tri in mesh.triangles() {
        for &v in tri {
            count[v as usize + 1] += 1;
        }
    }
    for v in 0..mesh.vertex_count() {
        count[v + 1] += count[v];
    }
    let start = count.clone();
    let mut list = vec![0u32; start[mesh.vertex_count()] as usize];
    for (t, tri) in mesh.triangles().iter().enumerate() {
        for (corner, &v) in tri.iter().enumerate() {
            list[count[v as usize] as usize] = 3 * t as u32 + corner as u32;
            count[v as usize] += 1;
        }
    }
    (start, list)
}
