//! Categories' folders and their shape spaces: the files a category holds, a space built
//! from them or read back from a folder of spaces and checked against them.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use glam::DVec3;

use vkdr::cpd::CpdParams;
use vkdr::gpu::Context;
use vkdr::shape::ShapeSpace;
use vkdr::Mesh;
use vkdr_app::check::{self, Category};
use vkdr_app::eval::{mean_nearest, EvalSettings};

/// The `.obj` files of a directory, sorted by name.
pub fn obj_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj")))
        .collect();
    files.sort();
    Ok(files)
}

/// The dataset's category folders (canonical.obj, train/, test/), sorted.
pub fn category_dirs(dataset: &Path) -> Result<Vec<PathBuf>> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dataset)
        .with_context(|| format!("reading {}", dataset.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.join("train").is_dir() && p.join("test").is_dir() && p.join("canonical.obj").is_file()
        })
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        bail!(
            "{} has no category folders (canonical.obj, train/, test/)",
            dataset.display()
        );
    }
    Ok(dirs)
}

/// A folder's (a category's) name.
pub fn dir_name(dir: &Path) -> String {
    dir.file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned()
}

/// A file's name without its extension.
pub fn stem(path: &Path) -> String {
    path.file_stem()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned()
}

/// The category's shape space: read from `spaces` (CATEGORY.npz) where it is there and
/// built from the dataset where not (and saved there, where given). A space read is
/// checked against the dataset and the settings: the same category, canonical, training
/// files, dimensions and kernel width.
pub fn shared_space(
    ctx: &Context,
    dir: &Path,
    category: &str,
    settings: &EvalSettings,
    spaces: Option<&Path>,
) -> Result<ShapeSpace> {
    let Some(spaces) = spaces else {
        return category_space(ctx, dir, category, settings);
    };
    let path = spaces.join(format!("{category}.npz"));
    if !path.exists() {
        let space = category_space(ctx, dir, category, settings)?;
        std::fs::create_dir_all(spaces)
            .with_context(|| format!("creating {}", spaces.display()))?;
        // Another shard may save the same space at once: the same bytes, each renamed
        // into place whole.
        space.save(&path)?;
        return Ok(space);
    }
    let space = ShapeSpace::load(&path)?;
    let canonical = Mesh::load_obj(dir.join("canonical.obj"))?;
    let training: Vec<String> = obj_files(&dir.join("train"))?
        .iter()
        .map(|f| f.display().to_string())
        .collect();
    let beta = settings.cpd.beta * vkdr::cpd::Normalization::of(&canonical.points()).scale;
    let dims = settings.dims.min(training.len().saturating_sub(1));
    let problem = if space.category != category {
        Some(format!("is the space of {}", space.category))
    } else if space.canonical.positions() != canonical.positions()
        || space.canonical.triangles() != canonical.triangles()
    {
        Some("has another canonical mesh".to_string())
    } else if space.training_names != training {
        Some("was built from other training files".to_string())
    } else if space.beta != beta || space.dims() > dims {
        Some(format!(
            "was built with other settings ({} dimensions, kernel width {}; this run: at most {dims}, {beta})",
            space.dims(),
            space.beta
        ))
    } else {
        None
    };
    if let Some(problem) = problem {
        bail!(
            "--spaces: {} {problem} than {} asks for; give another --spaces folder",
            path.display(),
            dir.display()
        );
    }
    Ok(space)
}

/// The shape space of the category folder `dir` from its canonical.obj and train/, with
/// the settings' dimensions and CPD.
pub fn category_space(
    ctx: &Context,
    dir: &Path,
    category: &str,
    settings: &EvalSettings,
) -> Result<ShapeSpace> {
    let canonical = Mesh::load_obj(dir.join("canonical.obj"))?;
    let training: Vec<(String, Vec<DVec3>)> = obj_files(&dir.join("train"))?
        .iter()
        .map(|f| Ok((f.display().to_string(), Mesh::load_obj(f)?.points())))
        .collect::<Result<_>>()?;
    eprintln!(
        "{category}: shape space from {} training instances",
        training.len()
    );
    let up = vkdr_app::check::Info::read(dir)?.up;
    Ok(ShapeSpace::build(
        ctx,
        category,
        &canonical,
        &training,
        settings.dims,
        &settings.cpd,
        |_, _, _| {},
    )?
    .with_up(up)?)
}

/// Builds the shape space of the category in `dir` (from `canonical`, see `--canonical`)
/// and saves it to `out`.
pub fn build(
    dir: &Path,
    canonical: Option<&str>,
    dims: usize,
    params: &CpdParams,
    out: &Path,
) -> Result<()> {
    let category = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let files = obj_files(&dir.join("train"))?;
    if files.len() < 2 {
        bail!(
            "{} holds {} training meshes; a shape space needs at least 2",
            dir.join("train").display(),
            files.len()
        );
    }
    let meshes: Vec<(String, Mesh)> = files
        .iter()
        .map(|f| {
            Ok((
                f.file_stem()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned(),
                Mesh::load_obj(f)?,
            ))
        })
        .collect::<Result<_>>()?;
    let canonical_mesh = match canonical {
        None => Mesh::load_obj(dir.join("canonical.obj"))?,
        Some("auto") => {
            let clouds: Vec<Vec<DVec3>> = meshes.iter().map(|(_, m)| m.points()).collect();
            let score = |i: usize| {
                (0..clouds.len())
                    .filter(|&j| j != i)
                    .map(|j| mean_nearest(&clouds[i], &clouds[j]))
                    .sum::<f64>()
            };
            let best = (0..clouds.len())
                .min_by(|&a, &b| score(a).total_cmp(&score(b)))
                .unwrap_or(0);
            eprintln!(
                "canonical: {} (lowest mean nearest-neighbour distance to the others)",
                meshes[best].0
            );
            meshes[best].1.clone()
        }
        Some(name) => match meshes.iter().find(|(n, _)| n == name) {
            Some((_, m)) => m.clone(),
            None => bail!("no train/{name}.obj in {}", dir.display()),
        },
    };
    let training: Vec<(String, Vec<DVec3>)> = meshes
        .iter()
        .map(|(n, m)| (n.clone(), m.points()))
        .collect();
    let ctx = Context::new()?;
    let total = training.len();
    let mut last = std::time::Instant::now();
    let space = ShapeSpace::build(
        &ctx,
        &category,
        &canonical_mesh,
        &training,
        dims,
        params,
        |done, _, name| {
            let width = 30;
            let filled = done * width / total.max(1);
            let took = match done {
                0 => String::new(),
                _ => format!("(last {:.1} s) ", last.elapsed().as_secs_f64()),
            };
            eprint!(
                "\r  CPD [{}{}] {done}/{total} {took}{name:<24}",
                "#".repeat(filled),
                ".".repeat(width - filled),
            );
            last = std::time::Instant::now();
            if done == total {
                eprintln!();
            }
        },
    )?;
    // The category's up axis travels with its space (register and eval-frames use it).
    let space = space.with_up(vkdr_app::check::Info::read(dir)?.up)?;
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    space.save(out)?;
    let explained: Vec<String> = space
        .explained_variance
        .iter()
        .map(|v| format!("{:.1}%", 100.0 * v))
        .collect();
    println!(
        "{category}: {} dimensions from {total} instances, explained variance {}; wrote {} and {}.json",
        space.dims(),
        explained.join(" "),
        out.display(),
        out.display()
    );
    Ok(())
}

/// `check-dataset`'s checks of one category before a long run (`shape-space`, `eval`):
/// stops on what would make the results meaningless unless `skip`, and says how many
/// warnings there are. `own_canonical`: another canonical is named, so a missing
/// canonical.obj is fine.
pub fn check_first(dir: &Path, skip: bool, own_canonical: bool) -> Result<Category> {
    let category = check::check_category(dir)?;
    let fatal: Vec<String> = category
        .fatal()
        .filter(|f| !(own_canonical && f.message == "no canonical.obj"))
        .map(|f| format!("  {}: {}", f.subject, f.message))
        .collect();
    if !fatal.is_empty() && !skip {
        bail!(
            "{} is not usable as it is (vkdr check-dataset shows all; --skip-checks runs anyway):\n{}",
            dir.display(),
            fatal.join("\n")
        );
    }
    let warnings = category
        .findings
        .iter()
        .filter(|f| f.severity == check::Severity::Warning)
        .count();
    if warnings > 0 {
        eprintln!(
            "{}: {warnings} warnings (vkdr check-dataset {} lists them)",
            category.name,
            dir.display()
        );
    }
    Ok(category)
}
