//! `vkdr shape-space`: build and save a category's latent shape space.

use std::path::PathBuf;

use anyhow::{bail, Result};

use crate::args::CpdArgs;

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
    crate::spaces::check_first(
        &args.category_dir,
        args.skip_checks,
        args.canonical.is_some(),
    )?;
    crate::spaces::build(
        &args.category_dir,
        args.canonical.as_deref(),
        args.dims,
        &params,
        &args.out,
    )
}
