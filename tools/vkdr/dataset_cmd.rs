//! `vkdr gen-dataset`: generate the category dataset (bottle, mug, spray_bottle, drill, bowl) in
//! the design's layout.

use std::path::PathBuf;

use anyhow::{Context as _, Result};

#[derive(clap::Args)]
pub struct Args {
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Training instances per category.
    #[arg(long, default_value_t = 10)]
    train: usize,
    /// Test instances per category.
    #[arg(long, default_value_t = 2)]
    test: usize,
}

/// Generates the dataset into `--out`; with `force`, each generated category's folder
/// there is replaced whole.
pub fn run(args: &Args, force: bool) -> Result<()> {
    let (out, seed, train, test) = (&args.out, args.seed, args.train, args.test);
    if force {
        // A dataset written over with fewer meshes must not keep the old ones beside the
        // new info.json: each generated category's folder is replaced whole.
        for category in vkdr_app::dataset::CATEGORIES {
            let dir = out.join(category);
            if dir.is_dir() {
                std::fs::remove_dir_all(&dir)
                    .with_context(|| format!("replacing {}", dir.display()))?;
            }
        }
    }
    let dirs = vkdr_app::dataset::generate(out, seed, train, test, |category, done, total| {
        eprint!("\r  {category:<14} {done:>3}/{total}");
        if done == total {
            eprintln!();
        }
    })?;
    for dir in dirs {
        println!("wrote {}", dir.display());
    }
    Ok(())
}
