//! `vkdr shape-space`: build and save a category's latent shape space.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use glam::DVec3;

use vkdr::cpd::CpdParams;
use vkdr::gpu::Context;
use vkdr::shape::ShapeSpace;
use vkdr::Mesh;
use vkdr_app::eval::mean_nearest;

use crate::args::CpdArgs;
use crate::check_cmd;

#[derive(clap::Args)]
pub struct Args {
    /// DIR/<category> with canonical.obj and train/*.obj.
    category_dir: PathBuf,
    /// Use train/NAME.obj as the canonical instead of canonical.obj (or `auto`: the
    /// training instance with the lowest mean nearest-neighbour distance to the others).
    #[arg(long)]
    canonical: Option<String>,
    #[arg(long, default_value_t = 5)]
    dims: usize,
    #[command(flatten)]
    cpd: CpdArgs,
    /// Run even where `check-dataset` finds the category unusable.
    #[arg(long)]
    skip_checks: bool,
    /// Output .npz (a .npz.json description is written beside it).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let params = args.cpd.params()?;
    if args.dims == 0 {
        bail!("--dims must be at least 1 (a shape space of no dimensions is the canonical alone)");
    }
    check_cmd::check_first(
        &args.category_dir,
        args.skip_checks,
        args.canonical.is_some(),
    )?;
    build(
        &args.category_dir,
        args.canonical.as_deref(),
        args.dims,
        &params,
        &args.out,
    )
}

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
