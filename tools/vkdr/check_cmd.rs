//! `vkdr check-dataset`: what a category dataset holds and whether it is usable, before
//! any long run, with a contact sheet per category.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};

use vkdr::io::write_png;
use vkdr_app::check::{self, Category};

#[derive(clap::Args)]
pub struct Args {
    dataset: PathBuf,
    /// Where report.txt and contact_<category>.png go.
    #[arg(long)]
    pub out: PathBuf,
}

/// The category folders under `dataset` (or `dataset` itself when it is one): folders
/// with a canonical.obj, a train/ or a test/.
fn categories(dataset: &Path) -> Result<Vec<PathBuf>> {
    let is_category = |p: &Path| {
        p.join("canonical.obj").is_file() || p.join("train").is_dir() || p.join("test").is_dir()
    };
    if is_category(dataset) {
        return Ok(vec![dataset.to_path_buf()]);
    }
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dataset)
        .with_context(|| format!("reading {}", dataset.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && is_category(p))
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        bail!(
            "{} holds no category folders (canonical.obj, train/, test/)",
            dataset.display()
        );
    }
    Ok(dirs)
}

/// Checks every category, prints the report, writes `report.txt` and
/// `contact_<category>.png` into `out`; an error when any category is unusable.
pub fn run(args: &Args) -> Result<()> {
    let (dataset, out) = (args.dataset.as_path(), args.out.as_path());
    let dirs = categories(dataset)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut text = String::new();
    let mut unusable = Vec::new();
    for dir in dirs {
        let category: Category = check::check_category(&dir)?;
        let report = check::report(&category);
        print!("{report}");
        text.push_str(&report);
        let sheet = out.join(format!("contact_{}.png", category.name));
        write_png(&sheet, &check::contact_sheet(&category).into())?;
        println!("  contact sheet: {}", sheet.display());
        if category.fatal().next().is_some() {
            unusable.push(category.name.clone());
        }
    }
    vkdr::io::write_atomically(&out.join("report.txt"), text.as_bytes())?;
    if !unusable.is_empty() {
        bail!(
            "not usable as they are: {} (see the errors above)",
            unusable.join(", ")
        );
    }
    Ok(())
}
