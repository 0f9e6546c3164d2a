//! `vkdr cpd`: non-rigid CPD between two point sets (OBJ vertices or N x 3 .npy).

use std::path::{Path, PathBuf};

use anyhow::{Context as _, Result};
use glam::DVec3;
use ndarray::Array2;

use vkdr::cpd::{self, CpdParams, CpdPipelines, CpdResult};
use vkdr::gpu::Context;
use vkdr::io::write_npy;

use crate::args::CpdArgs;

#[derive(clap::Args)]
pub struct Args {
    source: PathBuf,
    target: PathBuf,
    #[command(flatten)]
    cpd: CpdArgs,
    /// Output directory for deformed.npy, W.npy and log.json.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: &Args) -> Result<()> {
    let params = args.cpd.params()?;
    let r = register(&args.source, &args.target, &params, &args.out)?;
    println!(
        "{} iterations ({}) in {:.3} s; final sigma^2 {:.3e}; wrote {4}/deformed.npy, {4}/W.npy, {4}/log.json",
        r.iterations,
        r.stop.describe(),
        r.seconds,
        r.sigma2.last().copied().unwrap_or(f64::NAN),
        args.out.display()
    );
    Ok(())
}

/// From this many source points, a lambda below DENSE_LAMBDA gets a note: on the peers'
/// noise-free sets 2e4 points wanted hundreds, 1e5 thousands (docs/method.md's table; with
/// missing points and outliers 2 was right at 2e4 and 5000 oversmoothed).
const DENSE_POINTS: usize = 10_000;
const DENSE_LAMBDA: f64 = 100.0;

/// Registers `source` onto `target` and writes deformed.npy, W.npy and log.json into `out`.
fn register(source: &Path, target: &Path, params: &CpdParams, out: &Path) -> Result<CpdResult> {
    let y = vkdr::io::load_points(source)?;
    let x = vkdr::io::load_points(target)?;
    let ctx = Context::new()?;
    let pipelines = CpdPipelines::new(&ctx)?;
    eprintln!(
        "CPD: {} source points onto {} target points on {}",
        y.len(),
        x.len(),
        ctx.info().name
    );
    if y.len() >= DENSE_POINTS && params.lambda < DENSE_LAMBDA {
        eprintln!(
            "note: lambda {} smooths {} points little (the data term grows with the points, \
             the smoothness term does not); if regions end beside their correspondences, \
             try hundreds to thousands (noise-free dense sets; docs/method.md, CPD)",
            params.lambda,
            y.len()
        );
    }
    let result = cpd::register(&ctx, &pipelines, &y, &x, params, &mut |i, s2| {
        eprint!("\r  iteration {i:>4}  sigma^2 {s2:.3e}   ");
    })?;
    eprintln!();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let matrix = |points: &[DVec3]| {
        Array2::from_shape_vec(
            (points.len(), 3),
            points.iter().flat_map(|p| p.to_array()).collect(),
        )
    };
    write_npy(&out.join("deformed.npy"), &matrix(&result.deformed)?)?;
    write_npy(&out.join("W.npy"), &matrix(&result.w)?)?;
    let log = serde_json::json!({
        "iterations": result.iterations,
        "converged": result.stop.converged(),
        "stop": format!("{:?}", result.stop),
        "seconds": result.seconds,
        "kernel_products": result.products,
        "limited_m_steps": result.limited,
        "jumps": result.jumps,
        "coarse_points": result.coarse_points,
        "coarse_iterations": result.coarse_iterations,
        "beta": params.beta,
        "lambda": params.lambda,
        "w": params.w,
        "sigma2": result.sigma2,
    });
    vkdr::io::write_json(&out.join("log.json"), &log)?;
    Ok(result)
}
