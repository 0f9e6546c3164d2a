//! Where commands write, checked before any work: a run never ends by finding that it
//! cannot write its results, and never writes over what is there unless `--force` says so.

use std::path::Path;

use anyhow::{bail, Context as _, Result};

/// The file `vkdr demo` leaves in its folder: a folder holding it may be written over by
/// the next demo without `--force` (it holds nothing the demo did not make).
pub const DEMO_MARK: &str = "vkdr-demo.txt";

/// Claims `dir` as an output folder: creates it if missing; an existing file there, or a
/// folder that already holds anything, is an error unless `force` (then the files the
/// command writes replace those of the same name and the rest stay). A folder holding
/// `mark` (when given) counts as the command's own. The folder must be writable: a probe
/// file is created and removed. Returns whether the folder was created (see [`release`]).
pub fn claim_dir(dir: &Path, force: bool, mark: Option<&str>) -> Result<bool> {
    if dir.exists() && !dir.is_dir() {
        bail!(
            "--out {} exists and is not a folder: give a folder to write into",
            dir.display()
        );
    }
    if dir.is_dir() && !force {
        let mut held: Vec<String> = std::fs::read_dir(dir)
            .with_context(|| format!("reading {}", dir.display()))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        let own = mark.is_some_and(|m| held.iter().any(|h| h == m));
        if !held.is_empty() && !own {
            held.sort();
            let shown = held.iter().take(4).cloned().collect::<Vec<_>>().join(", ");
            let more = if held.len() > 4 { ", ..." } else { "" };
            bail!(
                "--out {} already holds {} ({shown}{more}): give an empty or new folder, or \
                 --force to write over files of the same names",
                dir.display(),
                plural(held.len(), "entry", "entries")
            );
        }
    }
    let created = !dir.exists();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    probe(dir)?;
    Ok(created)
}

/// After a failed command: removes the folder `claim_dir` created if nothing was written
/// into it (a failure leaves no empty folder behind).
pub fn release(dir: &Path) {
    if std::fs::read_dir(dir).is_ok_and(|mut entries| entries.next().is_none()) {
        let _ = std::fs::remove_dir(dir);
    }
}

/// Claims `file` as an output file: an existing one is an error unless `force`; its
/// folder is created if missing and must be writable.
pub fn claim_file(file: &Path, force: bool) -> Result<()> {
    if file.is_dir() {
        bail!(
            "--out {} is a folder: give a file name to write",
            file.display()
        );
    }
    if file.exists() && !force {
        bail!(
            "--out {} exists: give a new name, or --force to replace it",
            file.display()
        );
    }
    let folder = match file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(folder).with_context(|| format!("creating {}", folder.display()))?;
    probe(folder)
}

/// An error unless a file can be created (and is removed again) in `dir`.
fn probe(dir: &Path) -> Result<()> {
    let probe = dir.join(format!(".vkdr-probe-{}", std::process::id()));
    std::fs::write(&probe, b"").with_context(|| format!("{} is not writable", dir.display()))?;
    std::fs::remove_file(&probe).with_context(|| format!("removing {}", probe.display()))
}

fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}
