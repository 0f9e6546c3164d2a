//! What a test model is measured against: a uniform sample of its surface, the paper's
//! oracle (a latent fit to CPD's deformation), and the space optimum (the least error the
//! shape space reaches); computed once per model, and kept in a folder across runs and
//! shards.

use std::path::Path;

use glam::DVec3;

use crate::metrics::{surface_error, surface_extent, symmetric_about};
use crate::surface::Surface;
use vkdr::cpd::linalg::{self, Matrix};
use vkdr::cpd::CpdParams;
use vkdr::error::Result;
use vkdr::gpu::Context;
use vkdr::mesh::Mesh;
use vkdr::shape::ShapeSpace;

/// Barycentric weights of `q` (a point of the triangle's plane) in triangle a, b, c.
fn barycentric(q: DVec3, a: DVec3, b: DVec3, c: DVec3) -> [f64; 3] {
    let (e1, e2, d) = (b - a, c - a, q - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (d1, d2) = (d.dot(e1), d.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if det.abs() <= f64::EPSILON * d11 * d22 {
        return [1.0, 0.0, 0.0];
    }
    let v = (d22 * d1 - d12 * d2) / det;
    let w = (d11 * d2 - d12 * d1) / det;
    [1.0 - v - w, v, w]
}

/// The least error a shape space reaches for a surface ([`space_optimum`]).
#[derive(Clone, Debug)]
pub struct Optimum {
    pub code: Vec<f64>,
    /// The uniform scale of the deformed canonical (1 unless the scale was free).
    pub scale: f64,
    pub error: f64,
}

/// The code (and with `free_scale` the uniform scale, within
/// [`vkdr::register::SCALE_RANGE`]) whose deformed canonical is nearest to the surface
/// sample `truth` by the reported error itself ([`surface_error`]; the object frame, so
/// the pose is known): the best the shape space can do, with which to judge registration
/// where the paper-style oracle (a fit to CPD's deformation) is not the best fit.
///
/// Levenberg-Marquardt on the distances: each point's distance to the surface is
/// linearised through its nearest point (moving with its triangle's corners, its
/// direction the gradient of the distance), weighted by 1 / distance (iteratively
/// reweighted least squares: the sum of distances, not of their squares, is what is
/// minimised), and a step is kept only where the error falls; otherwise the damping grows.
/// Started at `start` (and scale 1), at most `iterations` evaluations of the error, so the
/// result is never worse than the start.
pub fn space_optimum(
    space: &ShapeSpace,
    truth: &[DVec3],
    start: &[f64],
    iterations: usize,
    free_scale: bool,
) -> Result<Optimum> {
    let triangles = space.canonical.triangles();
    let k = space.dims();
    // The parameters: the code, then the scale where it is free.
    let n = k + free_scale as usize;
    let (lowest, highest) = vkdr::register::SCALE_RANGE;
    let scale_of = |x: &[f64]| if free_scale { x[k] } else { 1.0 };
    let shape = |x: &[f64]| -> Result<Vec<DVec3>> {
        let scale = scale_of(x);
        Ok(space
            .vertices(&x[..k])?
            .into_iter()
            .map(|v| v * scale)
            .collect())
    };
    let error_of = |x: &[f64]| -> Result<f64> { Ok(surface_error(truth, &shape(x)?, triangles)) };
    let mut first = start.to_vec();
    if free_scale {
        first.push(1.0);
    }
    let mut best = (first.clone(), error_of(&first)?);
    let mut damping = 1e-3;
    let mut evaluations = 0;
    while evaluations < iterations && best.1 > 0.0 {
        // The weighted normal equations at the best parameters.
        let vertices = shape(&best.0)?;
        let scale = scale_of(&best.0);
        let mut normal = Matrix::zeros(n, n);
        let mut gradient = vec![0.0; n];
        let floor = 1e-2 * best.1;
        let surface = Surface::new(&vertices, triangles);
        for &p in truth {
            let (t, q) = surface.closest(p).ok_or_else(|| {
                vkdr::error::Error::InvalidInput(
                    "the shape space's canonical has no triangles".into(),
                )
            })?;
            let tri = triangles[t];
            let [a, b, c] = tri.map(|i| vertices[i as usize]);
            let r = q - p;
            let distance = r.length();
            // d distance / d q: along r, or the face's normal for a point on the surface.
            let direction = if distance > 1e-12 * best.1 {
                r / distance
            } else {
                (b - a).cross(c - a).normalize_or_zero()
            };
            let weights = barycentric(q, a, b, c);
            // d distance / d s_j: the triangle's corners moved by basis j (times the
            // scale), mixed by the weights, seen along the direction; d distance / d scale:
            // the point moved by q / scale.
            let mut row: Vec<f64> = (0..k)
                .map(|j| {
                    let basis = &space.deformation_basis[j];
                    (0..3)
                        .map(|corner| {
                            let v = 3 * tri[corner] as usize;
                            weights[corner]
                                * scale
                                * direction.dot(DVec3::new(basis[v], basis[v + 1], basis[v + 2]))
                        })
                        .sum()
                })
                .collect();
            if free_scale {
                row.push(direction.dot(q / scale));
            }
            let w = 1.0 / distance.max(floor);
            for i in 0..n {
                for j in 0..n {
                    normal.set(i, j, normal.at(i, j) + w * row[i] * row[j]);
                }
                gradient[i] += w * distance * row[i];
            }
        }
        // Damped steps until one lowers the error (or the evaluations run out).
        let mut improved = false;
        while evaluations < iterations && !improved {
            let mut damped = normal.clone();
            let trace = (0..n).map(|i| normal.at(i, i)).sum::<f64>() / n as f64;
            for i in 0..n {
                damped.set(i, i, normal.at(i, i) * (1.0 + damping) + 1e-12 * trace);
            }
            let mut rhs = Matrix::zeros(n, 1);
            for i in 0..n {
                rhs.set(i, 0, -gradient[i]);
            }
            let step = linalg::solve(damped, rhs)?;
            let mut x: Vec<f64> = (0..n).map(|i| best.0[i] + step.at(i, 0)).collect();
            if free_scale {
                x[k] = x[k].clamp(lowest, highest);
            }
            let error = error_of(&x)?;
            evaluations += 1;
            if error < best.1 {
                improved = true;
                damping = (damping / 3.0).max(1e-9);
                let gain = best.1 - error;
                best = (x, error);
                if gain <= 1e-5 * best.1 {
                    return Ok(optimum(best, k, free_scale));
                }
            } else {
                damping *= 4.0;
                if damping > 1e12 {
                    return Ok(optimum(best, k, free_scale));
                }
            }
        }
    }
    Ok(optimum(best, k, free_scale))
}

/// [`space_optimum`]'s parameters and error as an [`Optimum`].
fn optimum((mut x, error): (Vec<f64>, f64), k: usize, free_scale: bool) -> Optimum {
    let scale = if free_scale { x[k] } else { 1.0 };
    x.truncate(k);
    Optimum {
        code: x,
        scale,
        error,
    }
}

/// `n` points drawn uniformly (by area) on the surface of `mesh`, seeded
/// ([`vkdr::mesh::surface_sample`]).
pub fn surface_sample(mesh: &Mesh, n: usize, seed: u64) -> Vec<DVec3> {
    vkdr::mesh::surface_sample(&mesh.points(), mesh.triangles(), n, seed)
}

/// Points of the test surface the error is measured on.
pub const SAMPLE_POINTS: usize = 2000;

/// What one test model is measured against, the same in every frame that shows it: its
/// surface sample, the oracle's code and vertices, and the space optimum from the
/// oracle's code and the mean shape.
#[derive(Clone, Debug)]
pub struct Reference {
    pub truth: Vec<DVec3>,
    pub oracle_code: Vec<f64>,
    pub oracle_vertices: Vec<DVec3>,
    /// The least error found from the oracle's code and from the mean shape.
    pub optimum: f64,
    /// Whether the optimum's scale was free.
    pub free_scale: bool,
    /// Whether `truth` is symmetric about the up axis ([`symmetric_about`]).
    pub symmetric: bool,
    /// Where it is not, the points of `truth` that break the symmetry (a mug's handle,
    /// [`crate::metrics::asymmetric_points`]).
    pub asymmetric: Vec<DVec3>,
}

/// What a [`Reference`] is computed from, and all it depends on.
#[derive(Clone, Copy)]
pub struct Model<'a> {
    pub space: &'a ShapeSpace,
    /// The test model, in the category's frame.
    pub test: &'a Mesh,
    /// Seeds the surface sample.
    pub seed: u64,
    /// CPD's settings for the oracle.
    pub cpd: &'a CpdParams,
    /// Other than 1: the instance at its own size is `test` over it, and the references
    /// are that instance's, scaled (where the scale is optimised the space with a scale
    /// reaches exactly that).
    pub scale: f64,
    /// Whether the space optimum's scale is free too (a registration that fits the scale
    /// is judged against that).
    pub free_scale: bool,
    /// The category's up axis, about which symmetry is judged.
    pub up: DVec3,
}

impl Reference {
    /// The reference of `model.test` in `model.space`: a surface sample of
    /// [`SAMPLE_POINTS`], CPD's oracle, the space optimum, and what breaks its symmetry
    /// about the up axis ([`Model`]).
    pub fn of(ctx: &Context, model: &Model) -> Result<Self> {
        let Model {
            space,
            test,
            seed,
            cpd,
            scale,
            free_scale,
            up,
        } = *model;
        let truth = surface_sample(test, SAMPLE_POINTS, seed);
        let symmetric = symmetric_about(&truth, up);
        let asymmetric = match symmetric {
            true => Vec::new(),
            false => {
                let size = surface_extent(&test.points(), test.triangles()).1;
                crate::metrics::asymmetric_points(&truth, up, 0.01 * size)
            }
        };
        let unscaled: Vec<DVec3> = test.points().iter().map(|p| *p / scale).collect();
        let oracle_code = space.oracle_code(ctx, &unscaled, cpd)?;
        let oracle_vertices: Vec<DVec3> = space
            .vertices(&oracle_code)?
            .iter()
            .map(|p| *p * scale)
            .collect();
        let unscaled_truth: Vec<DVec3> = truth.iter().map(|p| *p / scale).collect();
        let mut optimum = f64::INFINITY;
        for start in [oracle_code.clone(), vec![0.0; space.dims()]] {
            optimum =
                optimum.min(space_optimum(space, &unscaled_truth, &start, 30, free_scale)?.error);
        }
        Ok(Self {
            truth,
            oracle_code,
            oracle_vertices,
            optimum: optimum * scale,
            free_scale,
            symmetric,
            asymmetric,
        })
    }
}

/// The version of the files [`Reference::cached`] keeps, part of their key: bump it when
/// what a reference holds or how it is computed changes.
const CACHE_FORMAT: u32 = 2;

/// A [`Reference`] as [`Reference::cached`] keeps it (JSON; numbers read back exactly).
#[derive(serde::Serialize, serde::Deserialize)]
struct Stored {
    key: String,
    truth: Vec<[f64; 3]>,
    oracle_code: Vec<f64>,
    oracle_vertices: Vec<[f64; 3]>,
    optimum: f64,
    free_scale: bool,
    symmetric: bool,
    asymmetric: Vec<[f64; 3]>,
}

impl Reference {
    /// [`Reference::of`], kept in `dir` (the `--spaces` folder, under `references/`) where
    /// one is given: read where a file of the same inputs is there (the space's arrays, the
    /// model's mesh, the seed, CPD's parameters, the scale, whether it is free, the up
    /// axis), computed and saved where not. So shards of one run, and runs after it, fit
    /// each model's oracle and space optimum once. A file that cannot be read is computed
    /// anew and replaced, with a warning. `computing` is called before a computation.
    pub fn cached(
        dir: Option<&Path>,
        computing: impl FnOnce(),
        ctx: &Context,
        model: &Model,
    ) -> Result<Self> {
        let compute = || {
            computing();
            Self::of(ctx, model)
        };
        let Some(dir) = dir else {
            return compute();
        };
        let key = cache_key(model);
        let path = dir.join("references").join(format!("{key}.json"));
        if path.exists() {
            match read_stored(&path, &key) {
                Ok(reference) => return Ok(reference),
                Err(e) => eprintln!("warning: {e}; computing the reference anew"),
            }
        }
        let reference = compute()?;
        store(&path, key, &reference)?;
        Ok(reference)
    }
}

/// Writes `reference` to `path` under `key`, atomically (shards may save the same
/// reference at once: the same bytes, each renamed into place whole).
fn store(path: &Path, key: String, reference: &Reference) -> Result<()> {
    let triples = |points: &[DVec3]| points.iter().map(|p| p.to_array()).collect();
    let stored = Stored {
        key,
        truth: triples(&reference.truth),
        oracle_code: reference.oracle_code.clone(),
        oracle_vertices: triples(&reference.oracle_vertices),
        optimum: reference.optimum,
        free_scale: reference.free_scale,
        symmetric: reference.symmetric,
        asymmetric: triples(&reference.asymmetric),
    };
    if let Some(folder) = path.parent() {
        std::fs::create_dir_all(folder).map_err(|e| vkdr::Error::io(folder, e))?;
    }
    let text =
        serde_json::to_string(&stored).map_err(|e| vkdr::Error::format(path, e.to_string()))?;
    vkdr::io::write_atomically(path, text.as_bytes())
}

/// A stored reference, checked against its key.
fn read_stored(path: &Path, key: &str) -> Result<Reference> {
    let text = std::fs::read_to_string(path).map_err(|e| vkdr::Error::io(path, e))?;
    let stored: Stored =
        serde_json::from_str(&text).map_err(|e| vkdr::Error::format(path, e.to_string()))?;
    if stored.key != key {
        return Err(vkdr::Error::format(path, "holds another model's reference"));
    }
    let points = |triples: Vec<[f64; 3]>| triples.into_iter().map(DVec3::from_array).collect();
    Ok(Reference {
        truth: points(stored.truth),
        oracle_code: stored.oracle_code,
        oracle_vertices: points(stored.oracle_vertices),
        optimum: stored.optimum,
        free_scale: stored.free_scale,
        symmetric: stored.symmetric,
        asymmetric: points(stored.asymmetric),
    })
}

/// A digest (FNV-1a, 64 bits, as hex) of everything [`Reference::of`] depends on.
fn cache_key(model: &Model) -> String {
    let Model {
        space,
        test,
        seed,
        cpd,
        scale,
        free_scale,
        up,
    } = *model;
    let mut digest = Fnv::default();
    digest.add(&CACHE_FORMAT.to_le_bytes());
    digest.add(space.category.as_bytes());
    for v in space.canonical.positions().iter().flatten() {
        digest.add(&v.to_le_bytes());
    }
    for t in space.canonical.triangles().iter().flatten() {
        digest.add(&t.to_le_bytes());
    }
    let arrays = [&space.mean, &space.offset]
        .into_iter()
        .chain(&space.deformation_basis)
        .chain(&space.basis)
        .chain(std::iter::once(&space.singular_values));
    for array in arrays {
        digest.add(&(array.len() as u64).to_le_bytes());
        for x in array {
            digest.add(&x.to_le_bytes());
        }
    }
    digest.add(&space.beta.to_le_bytes());
    for v in test.positions().iter().flatten() {
        digest.add(&v.to_le_bytes());
    }
    for t in test.triangles().iter().flatten() {
        digest.add(&t.to_le_bytes());
    }
    digest.add(&seed.to_le_bytes());
    digest.add(format!("{cpd:?}").as_bytes());
    digest.add(&scale.to_le_bytes());
    digest.add(&[free_scale as u8]);
    for x in up.to_array() {
        digest.add(&x.to_le_bytes());
    }
    format!("{}-{:016x}", space.category, digest.0)
}

/// FNV-1a over bytes: a stable digest (the same in every build), enough to tell inputs
/// apart where no adversary chooses them (the evaluation's seeds per name too).
pub(crate) struct Fnv(pub(crate) u64);

impl Default for Fnv {
    fn default() -> Self {
        Self(0xcbf29ce484222325)
    }
}

impl Fnv {
    pub(crate) fn add(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(0x100000001b3);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stored reference reads back bit for bit (awkward floats included), and a file
    /// under another key is refused rather than used.
    #[test]
    fn a_stored_reference_reads_back_exactly_and_only_under_its_key() {
        let awkward = [
            0.1 + 0.2,
            1e-300,
            f64::MIN_POSITIVE / 3.0,
            -2.5e17,
            1.0 / 3.0,
        ];
        let reference = Reference {
            truth: vec![DVec3::new(awkward[0], awkward[1], awkward[2])],
            oracle_code: awkward.to_vec(),
            oracle_vertices: vec![DVec3::new(awkward[3], awkward[4], 0.0); 2],
            optimum: awkward[4],
            free_scale: true,
            symmetric: false,
            asymmetric: vec![DVec3::new(awkward[2], awkward[1], awkward[0])],
        };
        let dir = std::env::temp_dir().join(format!("vkdr-reference-{}", std::process::id()));
        let path = dir.join("references").join("cup-1.json");
        store(&path, "cup-1".into(), &reference).unwrap();
        let read = read_stored(&path, "cup-1").unwrap();
        let bits = |r: &Reference| {
            let points = r
                .truth
                .iter()
                .chain(&r.oracle_vertices)
                .chain(&r.asymmetric);
            let numbers: Vec<u64> = points
                .flat_map(|p| p.to_array())
                .chain(r.oracle_code.iter().copied())
                .chain([r.optimum])
                .map(f64::to_bits)
                .collect();
            (numbers, r.free_scale, r.symmetric)
        };
        assert_eq!(bits(&read), bits(&reference));
        let err = read_stored(&path, "cup-2").unwrap_err().to_string();
        assert!(err.contains("another model's reference"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
