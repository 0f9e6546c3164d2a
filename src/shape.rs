//! The latent shape space of a category: CPD from the canonical mesh's vertices C to each
//! training instance gives W_i (T_i = C + G W_i); PCA of the flattened W_i gives
//! W(s) = mean + U s; the deformed vertices are `C + d0 + B s` with `d0 = G mean` and
//! `B = G U` precomputed. The inverse (the evaluation oracle) is the latent code that best
//! explains a given 3D instance: CPD to it, then projection on U.
//!
//! Files: an `.npz` (arrays below) and a JSON description beside it (`<file>.json`) with
//! a format version; loading checks both and refuses corrupt or mismatched files.

use std::path::{Path, PathBuf};

use glam::DVec3;
use ndarray::{Array1, Array2};

use crate::cpd::{self, linalg, CpdParams, CpdPipelines, Normalization};
use crate::error::{Error, Result};
use crate::gpu::Context;
use crate::io::write_atomically;
use crate::mesh::Mesh;

/// Format version written to a shape space's JSON description, and the
/// one loading requires.
pub const FORMAT_VERSION: u32 = 1;

/// A category's latent shape space.
#[derive(Clone, Debug, PartialEq)]
pub struct ShapeSpace {
    /// The canonical mesh, whose vertices C the space deforms.
    pub canonical: Mesh,
    /// Kernel width in the data's units (the CPD beta times the canonical's RMS radius).
    pub beta: f64,
    /// Mean of the training W, M x 3 (flattened row-major as in `basis`).
    pub mean: Vec<f64>,
    /// Principal directions of W, k x 3M.
    pub basis: Vec<Vec<f64>>,
    /// Singular value of each principal direction (of the centred training W).
    pub singular_values: Vec<f64>,
    /// Latent codes of the training instances, T x k.
    pub training_codes: Vec<Vec<f64>>,
    /// Fraction of the training variance each dimension explains.
    pub explained_variance: Vec<f64>,
    /// d0 = G mean, M x 3 flattened.
    pub offset: Vec<f64>,
    /// B = G U: k x 3M (dimension j's displacement of every vertex).
    pub deformation_basis: Vec<Vec<f64>>,
    /// Name of the category.
    pub category: String,
    /// Name of each training instance, in the order of `training_codes`.
    pub training_names: Vec<String>,
    /// The category's up axis in the canonical frame (its dataset's `info.json`
    /// `up_axis`), where known: registrations keep it along gravity and turn their starts
    /// about it. None in spaces built without it and in files written before it was kept.
    pub up: Option<DVec3>,
}

/// What CPD found for one training instance, both flattened M x 3: the coefficients W and
/// the displacement G W they make (with the G of the fit: exact, or the Nystrom one of the
/// low-rank option).
#[derive(Clone, Debug)]
pub struct TrainingFit {
    /// The coefficients W, flattened M x 3.
    pub w: Vec<f64>,
    /// The displacement G W, flattened M x 3.
    pub displacement: Vec<f64>,
}

impl ShapeSpace {
    /// Builds the space from the canonical mesh and training instances (points), with at
    /// most `dims` dimensions (never more than the training set supports: T - 1).
    pub fn build(
        ctx: &Context,
        category: &str,
        canonical: &Mesh,
        training: &[(String, Vec<DVec3>)],
        dims: usize,
        params: &CpdParams,
        mut progress: impl FnMut(usize, usize, &str),
    ) -> Result<Self> {
        if training.len() < 2 {
            return Err(Error::InvalidInput(format!(
                "a shape space needs at least 2 training instances, got {}",
                training.len()
            )));
        }
        let c = canonical.points();
        let pipelines = CpdPipelines::new(ctx)?;
        let mut fits = Vec::new();
        for (i, (name, points)) in training.iter().enumerate() {
            progress(i, training.len(), name);
            let result = cpd::register(ctx, &pipelines, &c, points, params, &mut |_, _| {})?;
            fits.push(TrainingFit {
                w: result.w.iter().flat_map(|w| w.to_array()).collect(),
                displacement: displacement(&result, &c),
            });
        }
        progress(training.len(), training.len(), "");
        let beta = params.beta * Normalization::of(&c).scale;
        Self::from_fits(
            category,
            canonical,
            beta,
            &fits,
            dims,
            training.iter().map(|t| t.0.clone()).collect(),
        )
    }

    /// The same space with the category's up axis `up` (a nonzero direction, normalised
    /// here).
    pub fn with_up(self, up: DVec3) -> Result<Self> {
        check_up(up)?;
        Ok(Self {
            up: Some(up.normalize()),
            ..self
        })
    }

    /// The up axis registrations use: the space's own, or y (with `known` false) for a
    /// space that does not carry one.
    pub fn up_or_y(&self) -> (DVec3, bool) {
        match self.up {
            Some(up) => (up, true),
            None => (DVec3::Y, false),
        }
    }

    /// PCA of the flattened coefficients (T x 3M) through the T x T Gram matrix. G is
    /// linear, so `d0 = G mean` and `B = G U` are the same combinations of the fits'
    /// displacements: no kernel product is needed here, at any size.
    pub fn from_fits(
        category: &str,
        canonical: &Mesh,
        beta: f64,
        fits: &[TrainingFit],
        dims: usize,
        names: Vec<String>,
    ) -> Result<Self> {
        let t = fits.len();
        let d = 3 * canonical.vertex_count();
        if t < 2
            || fits
                .iter()
                .any(|f| f.w.len() != d || f.displacement.len() != d)
        {
            return Err(Error::InvalidInput(format!(
                "a shape space needs at least 2 fits of {d} values each"
            )));
        }
        let mean_of = |field: fn(&TrainingFit) -> &[f64]| -> Vec<f64> {
            (0..d)
                .map(|j| fits.iter().map(|f| field(f)[j]).sum::<f64>() / t as f64)
                .collect()
        };
        let mean = mean_of(|f| &f.w);
        let offset = mean_of(|f| &f.displacement);
        let centre = |values: &[f64], mean: &[f64]| -> Vec<f64> {
            values.iter().zip(mean).map(|(a, b)| a - b).collect()
        };
        let centred: Vec<Vec<f64>> = fits.iter().map(|f| centre(&f.w, &mean)).collect();
        let centred_displacements: Vec<Vec<f64>> = fits
            .iter()
            .map(|f| centre(&f.displacement, &offset))
            .collect();
        let mut gram = linalg::Matrix::zeros(t, t);
        for i in 0..t {
            for j in 0..t {
                gram.set(
                    i,
                    j,
                    centred[i].iter().zip(&centred[j]).map(|(a, b)| a * b).sum(),
                );
            }
        }
        let (values, vectors) = linalg::symmetric_eigen(&gram);
        let total: f64 = values.iter().map(|v| v.max(0.0)).sum();
        let k = dims.min(t - 1).min(
            values
                .iter()
                .filter(|&&v| v > 1e-12 * total.max(f64::MIN_POSITIVE))
                .count(),
        );
        if k == 0 {
            return Err(Error::InvalidInput(
                "the training instances do not vary: the shape space would be empty".into(),
            ));
        }
        let mut basis = Vec::new();
        let mut deformation_basis = Vec::new();
        let mut singular_values = Vec::new();
        for j in 0..k {
            let sigma = values[j].max(0.0).sqrt();
            // u_j = X^T v_j / sigma_j, and G u_j the same combination of displacements.
            let combine = |rows: &[Vec<f64>]| -> Vec<f64> {
                (0..d)
                    .map(|c| (0..t).map(|i| rows[i][c] * vectors.at(i, j)).sum::<f64>() / sigma)
                    .collect()
            };
            basis.push(combine(&centred));
            deformation_basis.push(combine(&centred_displacements));
            singular_values.push(sigma);
        }
        let training_codes = centred
            .iter()
            .map(|w| basis.iter().map(|u| dot(u, w)).collect())
            .collect();
        let explained_variance = values[..k].iter().map(|v| v / total).collect();
        Ok(Self {
            canonical: canonical.clone(),
            beta,
            mean,
            basis,
            singular_values,
            training_codes,
            explained_variance,
            offset,
            deformation_basis,
            category: category.into(),
            training_names: names,
            up: None,
        })
    }

    /// Number of latent dimensions k.
    pub fn dims(&self) -> usize {
        self.basis.len()
    }

    /// The standard deviation of each latent dimension over the training codes (which
    /// are centred: PCA of the centred W), never below 1e-12.
    pub fn code_deviations(&self) -> Vec<f64> {
        let t = (self.training_codes.len() as f64 - 1.0).max(1.0);
        (0..self.dims())
            .map(|j| {
                let var = self.training_codes.iter().map(|c| c[j] * c[j]).sum::<f64>() / t;
                var.sqrt().max(1e-12)
            })
            .collect()
    }

    /// A latent code in training standard deviations (each dimension over
    /// [`ShapeSpace::code_deviations`]): where a code lies against the training spread.
    pub fn code_in_deviations(&self, s: &[f64]) -> Vec<f64> {
        s.iter()
            .zip(self.code_deviations())
            .map(|(v, d)| v / d)
            .collect()
    }

    /// Vertices of the deformed canonical mesh for latent code `s`: C + d0 + B s.
    pub fn vertices(&self, s: &[f64]) -> Result<Vec<DVec3>> {
        if s.len() != self.dims() {
            return Err(Error::InvalidInput(format!(
                "latent code of {} values for a {}-dimensional space",
                s.len(),
                self.dims()
            )));
        }
        let mut field = self.offset.clone();
        for (b, &sj) in self.deformation_basis.iter().zip(s) {
            for (f, v) in field.iter_mut().zip(b) {
                *f += sj * v;
            }
        }
        Ok(self
            .canonical
            .points()
            .iter()
            .enumerate()
            .map(|(i, c)| *c + DVec3::new(field[3 * i], field[3 * i + 1], field[3 * i + 2]))
            .collect())
    }

    /// The latent code whose deformation `d0 + B s` is closest in least squares to the
    /// displacement field `d` (flattened M x 3, in the data's units).
    pub fn code_of_displacement(&self, d: &[f64]) -> Result<Vec<f64>> {
        let k = self.dims();
        let residual: Vec<f64> = d.iter().zip(&self.offset).map(|(a, b)| a - b).collect();
        let mut normal = linalg::Matrix::zeros(k, k);
        let mut rhs = linalg::Matrix::zeros(k, 1);
        for (i, bi) in self.deformation_basis.iter().enumerate() {
            for (j, bj) in self.deformation_basis.iter().enumerate() {
                normal.set(i, j, dot(bi, bj));
            }
            rhs.set(i, 0, dot(bi, &residual));
        }
        // A tiny ridge keeps a dimension that barely moves any vertex solvable.
        let trace: f64 = (0..k).map(|i| normal.at(i, i)).sum();
        for i in 0..k {
            let v = normal.at(i, i) + 1e-12 * trace.max(f64::MIN_POSITIVE);
            normal.set(i, i, v);
        }
        Ok(linalg::solve(normal, rhs)?.data)
    }

    /// The oracle: the best the space can do when the 3D instance `points` is known.
    /// CPD deforms the canonical onto it, and the code is the least-squares fit of the
    /// space's deformation to CPD's over all vertices (measured where the error is, in
    /// vertex positions, rather than as a projection of the coefficients W).
    pub fn oracle_code(
        &self,
        ctx: &Context,
        points: &[DVec3],
        params: &CpdParams,
    ) -> Result<Vec<f64>> {
        let pipelines = CpdPipelines::new(ctx)?;
        let c = self.canonical.points();
        let result = cpd::register(ctx, &pipelines, &c, points, params, &mut |_, _| {})?;
        self.code_of_displacement(&displacement(&result, &c))
    }

    /// Writes `path` (.npz, which alone is enough to load) and `path.json` (its
    /// description, for people).
    pub fn save(&self, path: &Path) -> Result<()> {
        let bytes = self.to_bytes()?;
        write_atomically(path, &bytes)?;
        let mut description = self.description();
        description["arrays"] = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
            .into();
        write_atomically(&description_path(path), pretty(&description)?.as_bytes())
    }

    /// The description of the space: format version, category, shapes, training names,
    /// beta, explained variance, up axis.
    fn description(&self) -> serde_json::Value {
        serde_json::json!({
            "format_version": FORMAT_VERSION,
            "category": self.category,
            "vertices": self.canonical.vertex_count(),
            "faces": self.canonical.triangle_count(),
            "dims": self.dims(),
            "training_instances": self.training_codes.len(),
            "training_names": self.training_names,
            "beta": self.beta,
            "explained_variance": self.explained_variance,
            "up_axis": self.up.map(|u| u.to_array()),
        })
    }

    /// The space as its `.npz` file's bytes, the description inside (the array
    /// `description`, its UTF-8 JSON): the same bytes for the same space wherever saved.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let m = self.canonical.vertex_count();
        let k = self.dims();
        let err = |e: ndarray::ShapeError| Error::InvalidInput(e.to_string());
        let flat = |rows: &[Vec<f64>], cols: usize| {
            Array2::from_shape_vec((rows.len(), cols), rows.concat()).map_err(err)
        };
        let description = pretty(&self.description())?;
        let mut bytes = Vec::new();
        {
            let mut npz = ndarray_npy::NpzWriter::new(std::io::Cursor::new(&mut bytes));
            let npz_err = |e: ndarray_npy::WriteNpzError| Error::InvalidInput(e.to_string());
            npz.add_array(
                "description",
                &Array1::from_vec(description.as_bytes().to_vec()),
            )
            .map_err(npz_err)?;
            let canonical: Vec<f64> = self
                .canonical
                .points()
                .iter()
                .flat_map(|p| p.to_array())
                .collect();
            npz.add_array(
                "canonical_vertices",
                &Array2::from_shape_vec((m, 3), canonical).map_err(err)?,
            )
            .map_err(npz_err)?;
            let faces: Vec<u32> = self
                .canonical
                .triangles()
                .iter()
                .flatten()
                .copied()
                .collect();
            npz.add_array(
                "canonical_faces",
                &Array2::from_shape_vec((self.canonical.triangle_count(), 3), faces)
                    .map_err(err)?,
            )
            .map_err(npz_err)?;
            npz.add_array("beta", &Array1::from_vec(vec![self.beta]))
                .map_err(npz_err)?;
            npz.add_array(
                "mean",
                &Array2::from_shape_vec((m, 3), self.mean.clone()).map_err(err)?,
            )
            .map_err(npz_err)?;
            npz.add_array("basis", &flat(&self.basis, 3 * m)?)
                .map_err(npz_err)?;
            npz.add_array(
                "singular_values",
                &Array1::from_vec(self.singular_values.clone()),
            )
            .map_err(npz_err)?;
            npz.add_array("training_codes", &flat(&self.training_codes, k)?)
                .map_err(npz_err)?;
            npz.add_array(
                "explained_variance",
                &Array1::from_vec(self.explained_variance.clone()),
            )
            .map_err(npz_err)?;
            npz.add_array(
                "offset",
                &Array2::from_shape_vec((m, 3), self.offset.clone()).map_err(err)?,
            )
            .map_err(npz_err)?;
            npz.add_array("deformation_basis", &flat(&self.deformation_basis, 3 * m)?)
                .map_err(npz_err)?;
            npz.finish().map_err(npz_err)?;
        }
        Ok(bytes)
    }

    /// Loads and checks a saved space.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::from_bytes(bytes, path)
    }

    /// A space from its `.npz` file's bytes ([`ShapeSpace::to_bytes`]); one written before
    /// the description was kept inside reads it from the `.npz.json` beside `path`, which
    /// errors name.
    pub fn from_bytes(bytes: Vec<u8>, path: &Path) -> Result<Self> {
        crate::io::check_npz_sizes(&path.display().to_string(), &bytes)?;
        let mut npz = ndarray_npy::NpzReader::new(std::io::Cursor::new(bytes))
            .map_err(|e| Error::format(path, format!("not a readable .npz: {e}")))?;
        let inside: Option<Vec<u8>> = npz
            .by_name::<ndarray::OwnedRepr<u8>, ndarray::Ix1>("description")
            .ok()
            .map(|a| a.to_vec());
        let (description, text) = match inside {
            Some(text) => (
                path.to_path_buf(),
                String::from_utf8(text)
                    .map_err(|_| Error::format(path, "description: not UTF-8"))?,
            ),
            None => {
                let description = description_path(path);
                let text = std::fs::read_to_string(&description)
                    .map_err(|e| Error::io(&description, e))?;
                (description, text)
            }
        };
        let json: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::format(&description, format!("not JSON: {e}")))?;
        let version = json["format_version"]
            .as_f64()
            .ok_or_else(|| Error::format(&description, "no format_version"))?;
        if version != FORMAT_VERSION as f64 {
            return Err(Error::format(
                &description,
                format!("format version {version}, this vkdr reads {FORMAT_VERSION}"),
            ));
        }
        let bad = |what: &str| Error::format(path, what.to_string());
        let mut get2 = |name: &str| -> Result<Array2<f64>> {
            npz.by_name::<ndarray::OwnedRepr<f64>, ndarray::Ix2>(name)
                .map_err(|e| Error::format(path, format!("{name}: {e}")))
        };
        let vertices = get2("canonical_vertices")?;
        let mean = get2("mean")?;
        let basis = get2("basis")?;
        let codes = get2("training_codes")?;
        let offset = get2("offset")?;
        let deformation = get2("deformation_basis")?;
        let faces: Array2<u32> = npz
            .by_name("canonical_faces")
            .map_err(|e| Error::format(path, format!("canonical_faces: {e}")))?;
        let mut get1 = |name: &str| -> Result<Vec<f64>> {
            npz.by_name::<ndarray::OwnedRepr<f64>, ndarray::Ix1>(name)
                .map(|a| a.to_vec())
                .map_err(|e| Error::format(path, format!("{name}: {e}")))
        };
        let beta = get1("beta")?;
        let singular_values = get1("singular_values")?;
        let explained_variance = get1("explained_variance")?;
        let m = vertices.nrows();
        let k = basis.nrows();
        let shapes_ok = vertices.ncols() == 3
            && mean.dim() == (m, 3)
            && offset.dim() == (m, 3)
            && basis.ncols() == 3 * m
            && deformation.dim() == (k, 3 * m)
            && codes.ncols() == k
            && singular_values.len() == k
            && explained_variance.len() == k
            && beta.len() == 1
            && faces.ncols() == 3;
        if !shapes_ok {
            return Err(bad("array shapes do not fit together"));
        }
        for (key, expected) in [("vertices", m), ("dims", k), ("faces", faces.nrows())] {
            if json[key].as_u64() != Some(expected as u64) {
                return Err(Error::format(
                    &description,
                    format!("\"{key}\" does not match {}", path.display()),
                ));
            }
        }
        let all = [&vertices, &mean, &basis, &codes, &offset, &deformation];
        if all.iter().any(|a| a.iter().any(|v| !v.is_finite()))
            || !beta[0].is_finite()
            || beta[0] <= 0.0
        {
            return Err(bad("non-finite values"));
        }
        // The names, one per training code (absent in files written before they were
        // kept: then none).
        let training_names: Vec<String> = match json.get("training_names") {
            None => Vec::new(),
            Some(names) => names
                .as_array()
                .and_then(|a| a.iter().map(|n| n.as_str().map(String::from)).collect())
                .filter(|n: &Vec<String>| n.len() == codes.nrows())
                .ok_or_else(|| {
                    Error::format(
                        &description,
                        format!("\"training_names\" is not {} strings", codes.nrows()),
                    )
                })?,
        };
        // The category's up axis (absent in files written before it was kept: None).
        let up = match json.get("up_axis") {
            None | Some(serde_json::Value::Null) => None,
            Some(axis) => {
                let values: Option<Vec<f64>> = axis
                    .as_array()
                    .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect());
                match values.as_deref() {
                    Some(&[x, y, z]) if DVec3::new(x, y, z).length() > 1e-6 => {
                        Some(DVec3::new(x, y, z).normalize())
                    }
                    _ => {
                        return Err(Error::format(
                            &description,
                            format!("\"up_axis\" must be 3 numbers, not zero, not {axis}"),
                        ))
                    }
                }
            }
        };
        let positions = vertices
            .rows()
            .into_iter()
            .map(|r| [r[0] as f32, r[1] as f32, r[2] as f32])
            .collect();
        let triangles = faces
            .rows()
            .into_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect();
        let canonical =
            Mesh::new(positions, triangles).map_err(|e| Error::format(path, e.to_string()))?;
        let rows = |a: &Array2<f64>| a.rows().into_iter().map(|r| r.to_vec()).collect::<Vec<_>>();
        Ok(Self {
            canonical,
            beta: beta[0],
            mean: mean.iter().copied().collect(),
            basis: rows(&basis),
            singular_values,
            training_codes: rows(&codes),
            explained_variance,
            offset: offset.iter().copied().collect(),
            deformation_basis: rows(&deformation),
            category: json["category"].as_str().unwrap_or_default().to_string(),
            training_names,
            up,
        })
    }
}

/// `json` as pretty-printed text with a final newline.
fn pretty(json: &serde_json::Value) -> Result<String> {
    Ok(serde_json::to_string_pretty(json).map_err(|e| Error::InvalidInput(e.to_string()))? + "\n")
}

/// What a CPD fit moved each source point by, flattened M x 3.
fn displacement(fit: &cpd::CpdResult, source: &[DVec3]) -> Vec<f64> {
    fit.deformed
        .iter()
        .zip(source)
        .flat_map(|(t, y)| (*t - *y).to_array())
        .collect()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn description_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".json");
    PathBuf::from(name)
}

/// A shape space of `dims` dimensions over an 8-segment bottle from `instances` random
/// training fits (coefficients in +-1, displacements in +-1 cm), for tests: no CPD runs.
pub fn random_space(rng: &mut crate::rng::Rng, instances: usize, dims: usize) -> ShapeSpace {
    let canonical = Mesh::bottle(8);
    let d = 3 * canonical.vertex_count();
    let fits: Vec<TrainingFit> = (0..instances)
        .map(|_| TrainingFit {
            w: (0..d).map(|_| rng.range(-1.0, 1.0)).collect(),
            displacement: (0..d).map(|_| rng.range(-0.01, 0.01)).collect(),
        })
        .collect();
    let names = (0..instances).map(|i| i.to_string()).collect();
    ShapeSpace::from_fits("test", &canonical, 0.1, &fits, dims, names).unwrap()
}

/// An error unless `up` is a nonzero, finite direction (a shape space's up axis,
/// [`ShapeSpace::with_up`]): callers check it before a build that takes minutes.
pub fn check_up(up: DVec3) -> Result<()> {
    if !(up.is_finite() && up.length() > 0.0) {
        return Err(Error::InvalidInput(format!(
            "a shape space's up axis must be a nonzero direction, not {up}"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn displacement_codes_are_least_squares_fits() {
        let mut rng = Rng::new(1);
        let space = random_space(&mut rng, 5, 3);
        let m = space.canonical.vertex_count();
        let residual = |code: &[f64], d: &[f64]| -> f64 {
            let v = space.vertices(code).unwrap();
            let c = space.canonical.points();
            (0..m)
                .map(|i| {
                    let r = v[i] - c[i] - DVec3::new(d[3 * i], d[3 * i + 1], d[3 * i + 2]);
                    r.length_squared()
                })
                .sum()
        };
        // A field inside the space gives its own code back.
        let code = vec![0.3, -1.2, 0.7];
        let inside: Vec<f64> = space
            .vertices(&code)
            .unwrap()
            .iter()
            .zip(space.canonical.points())
            .flat_map(|(v, c)| (*v - c).to_array())
            .collect();
        let fitted = space.code_of_displacement(&inside).unwrap();
        for (a, b) in fitted.iter().zip(&code) {
            assert!((a - b).abs() < 1e-9, "{fitted:?} vs {code:?}");
        }
        // Any other field: every nearby code fits worse.
        let outside: Vec<f64> = (0..3 * m).map(|_| rng.range(-0.02, 0.02)).collect();
        let best = space.code_of_displacement(&outside).unwrap();
        let at_best = residual(&best, &outside);
        for j in 0..3 {
            for step in [-1e-3, 1e-3] {
                let mut other = best.clone();
                other[j] += step;
                assert!(residual(&other, &outside) > at_best, "dimension {j} {step}");
            }
        }
    }
}
