//! The `vkdr` command line: the parser and the dispatch to the commands, one module each.

mod args;
mod bench;
mod bench_register;
mod check_cmd;
mod choices;
mod cpd_cmd;
mod dataset_cmd;
mod demo_cmd;
mod eval_cmd;
mod eval_report;
mod frames_cmd;
mod frames_report;
mod grad;
mod info_cmd;
mod out;
mod pictures;
mod register_cmd;
mod registration;
mod render_cmd;
mod shape_cmd;
mod shard;
mod spaces;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "vkdr",
    version,
    about = "Differentiable rasterization and deformable registration on Vulkan"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Write into an --out folder that already holds files (files of the same names are
    /// replaced, the rest stay), or over an existing --out file.
    #[arg(long, global = true)]
    force: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Print the chosen Vulkan device, its driver, features and limits.
    Info,
    /// Render a mesh's G-buffer (triangle ids, barycentrics, depth) and pictures of it.
    Render(render_cmd::Args),
    /// Loss and exact gradients (vertices and pose) of a render against an observed mask.
    Grad(grad::Args),
    /// Time forward and backward passes against a plain colour render (1e3..1e6 vertices).
    Bench(bench::Args),
    /// Time one registration at benchmark size (640x480, ~1e4 vertices, pose noise):
    /// wall time, device time per pass, batched throughput, speed against error.
    BenchRegister(bench_register::Args),
    /// Non-rigid Coherent Point Drift of SOURCE onto TARGET (OBJ vertices or N x 3 .npy).
    Cpd(cpd_cmd::Args),
    /// Generate the category dataset (bottle, mug, spray_bottle, drill, bowl) in the design's layout.
    GenDataset(dataset_cmd::Args),
    /// Check a category dataset (DIR with category folders, or one category folder) before
    /// a long run: sizes, units, up axis, open or unwelded meshes, frame; contact sheets.
    CheckDataset(check_cmd::Args),
    /// Build a category's latent shape space (CPD from the canonical mesh, then PCA).
    ShapeSpace(shape_cmd::Args),
    /// Register a shape space to an observed mask (render-and-compare on the device).
    Register(register_cmd::Args),
    /// The paper's Table 1 on a dataset: oracle, known pose and pose noise per test instance.
    Eval(eval_cmd::Args),
    /// The evaluation on observed frames in the BOP format (visible masks, sensor depth,
    /// ground-truth poses): known pose and pose noise per frame and object.
    EvalFrames(frames_cmd::Args),
    /// Render BOP-format frames of a dataset's test instances (table, occluder, depth noise
    /// and holes) with their models and the map for eval-frames.
    GenFrames(frames_cmd::GenArgs),
    /// The quick start: generate a dataset, build a shape space, register a held-out
    /// instance from a rendered mask with pose noise, print its Table-1 row, write pictures.
    Demo(demo_cmd::Args),
}

fn main() {
    let cli = Cli::parse();
    let created = match claim_out(&cli.command, cli.force) {
        Ok(created) => created,
        Err(e) => {
            eprintln!("error: {}", report(&e));
            std::process::exit(1);
        }
    };
    let result = match &cli.command {
        Command::Info => info_cmd::run(),
        Command::Render(args) => render_cmd::run(args),
        Command::Grad(args) => grad::run(args),
        Command::Bench(args) => bench::run(args),
        Command::BenchRegister(args) => bench_register::run(args),
        Command::Cpd(args) => cpd_cmd::run(args),
        Command::GenDataset(args) => dataset_cmd::run(args, cli.force),
        Command::CheckDataset(args) => check_cmd::run(args),
        Command::ShapeSpace(args) => shape_cmd::run(args),
        Command::Register(args) => register_cmd::run(args),
        Command::Eval(args) => eval_cmd::run(args),
        Command::EvalFrames(args) => frames_cmd::run(args),
        Command::GenFrames(args) => frames_cmd::generate(args),
        Command::Demo(args) => demo_cmd::run(args),
    };
    if let Err(e) = result {
        if let Some(dir) = created {
            out::release(&dir);
        }
        eprintln!("error: {}", report(&e));
        std::process::exit(1);
    }
}

/// Claims the command's --out before any work (see `out`); returns the output folder
/// when the claim created it.
fn claim_out(command: &Command, force: bool) -> Result<Option<PathBuf>> {
    let dir = match command {
        Command::Info => return Ok(None),
        Command::ShapeSpace(args) => {
            out::claim_file(&args.out, force)?;
            return Ok(None);
        }
        Command::Demo(args) => {
            let created = out::claim_dir(&args.out, force, Some(out::DEMO_MARK))?;
            return Ok(created.then(|| args.out.clone()));
        }
        Command::CheckDataset(args) => &args.out,
        Command::Bench(args) => &args.out,
        Command::GenDataset(args) => &args.out,
        Command::Cpd(args) => &args.out,
        Command::Render(args) => &args.out,
        Command::Grad(args) => &args.out,
        Command::Eval(args) => args.shards.out(),
        Command::EvalFrames(args) => args.shards.out(),
        Command::GenFrames(args) => &args.out,
        Command::BenchRegister(args) => &args.out,
        Command::Register(args) => args.out(),
    };
    let created = out::claim_dir(dir, force, None)?;
    Ok(created.then(|| dir.to_path_buf()))
}

/// The error and its causes in one line, each cause once (a cause whose text the message
/// already holds, as an I/O error that names its file, is not repeated).
fn report(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let said = cause.to_string();
        if !text.contains(&said) {
            if !text.is_empty() {
                text.push_str(": ");
            }
            text.push_str(&said);
        }
    }
    text
}
