//! `vkdr eval --shard K/N` and `vkdr eval --merge OUT SHARDS...`: the evaluation split
//! across processes or machines, merged into the tables one process would write.
//!
//! The unit of work is one test instance of one category: its trials share one random
//! stream and the space optimum starts from the best of their codes, so they stay
//! together. Units go to shards longest first, each to the shard with the least expected
//! cost so far (the canonical's vertices per unit: a registration's cost follows them);
//! every shard computes the same assignment from the same dataset. A shard writes its rows
//! to `shard.json` exactly (every number read back to the same f64), with the run's flags,
//! the settings they resolved to (every parameter, defaults included), the version and its
//! place K of N; the merge refuses missing, repeated or foreign shards, and shards whose
//! settings the merging build would not resolve the same flags to (a default changed
//! between them), and writes the tables from the rows in the unsharded order, so they are
//! the same bytes as one process's (the wall times aside).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use serde::{Deserialize, Serialize};

use vkdr_app::check::{Category, Role};
use vkdr_app::eval::Row;

/// The shard file's name in a shard's --out.
pub const FILE: &str = "shard.json";
/// The shard file's format, bumped with its fields and the trials' (3: the known pose's z
/// error; 4: the resolved settings); a shard of another format is refused.
const FORMAT: u32 = 4;

/// The version of this build: the package's and the git commit it was built from.
pub fn build_version() -> String {
    format!("{}+{}", env!("CARGO_PKG_VERSION"), env!("VKDR_COMMIT"))
}

/// Shard `index` of `count` (0-based, as Slurm's array task ids).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    /// `K/N` with 0 <= K < N.
    pub fn parse(text: &str) -> Result<Self> {
        let parsed = text
            .split_once('/')
            .and_then(|(k, n)| Some((k.trim().parse().ok()?, n.trim().parse().ok()?)));
        match parsed {
            Some((index, count)) if index < count => Ok(Self { index, count }),
            _ => bail!(
                "--shard must be K/N with K from 0 to N-1 (e.g. 0/4, or $SLURM_ARRAY_TASK_ID/4), not {text}"
            ),
        }
    }
}

/// The shard of each unit, given each unit's expected cost: the costliest first (ties in
/// order), each to the shard with the least cost so far (ties to the lowest index).
pub fn assign(costs: &[f64], count: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..costs.len()).collect();
    order.sort_by(|&a, &b| costs[b].total_cmp(&costs[a]).then(a.cmp(&b)));
    let mut load = vec![0.0f64; count.max(1)];
    let mut shard = vec![0; costs.len()];
    for unit in order {
        let least = (0..load.len())
            .min_by(|&a, &b| load[a].total_cmp(&load[b]).then(a.cmp(&b)))
            .expect("at least one shard");
        shard[unit] = least;
        load[least] += costs[unit];
    }
    shard
}

/// The expected cost of a unit of `category`: its canonical's vertices (a registration's
/// cost follows them), from what `check-dataset` read.
pub fn unit_cost(category: &Category) -> Result<f64> {
    category
        .meshes
        .iter()
        .find(|(stats, _)| stats.role == Role::Canonical)
        .map(|(_, mesh)| mesh.vertex_count() as f64)
        .with_context(|| format!("{}: no canonical.obj", category.name))
}

/// An error, before any work, for a --spaces that is there but is not a folder.
pub fn check_spaces(spaces: Option<&Path>) -> Result<()> {
    match spaces {
        Some(dir) if dir.exists() && !dir.is_dir() => bail!(
            "--spaces {} is not a folder: give a new one, or one that holds CATEGORY.npz files",
            dir.display()
        ),
        _ => Ok(()),
    }
}

/// Keeps the units of `shard` (all without one), given each unit's expected cost.
pub fn keep_own(units: &mut Vec<Unit>, costs: &[f64], shard: Option<Shard>) {
    if let Some(shard) = shard {
        let assigned = assign(costs, shard.count);
        let mut mine = assigned.iter().map(|&s| s == shard.index);
        units.retain(|_| mine.next().expect("one shard per unit"));
    }
}

/// A command's flags read back from the command line a shard saved.
pub fn parse_flags<A: clap::Args + clap::FromArgMatches>(
    command: &'static str,
    line: Vec<String>,
) -> Result<A> {
    let matches = A::augment_args(clap::Command::new(command)).try_get_matches_from(line)?;
    Ok(A::from_arg_matches(&matches)?)
}

/// The settings a run resolved its flags to, every parameter with its value (defaults
/// included), as a shard stores them and the merge compares them: Rust's `Debug` form,
/// whose numbers read back to the same f64.
pub fn resolved(settings: &impl std::fmt::Debug) -> String {
    format!("{settings:#?}")
}

/// Merges the shards of a `command` run in `dirs` and writes its tables into `out` with
/// `write` (the rows, the failures, what `settings_of` read back from the run's command
/// line: the command, its flags and `--out`, with their [`resolved`] form; and the device).
/// The settings are those the shards ran: where this build resolves their flags to other
/// settings (a default changed since), an error says which and nothing is written. An
/// error when a unit failed in a shard, after the tables are written.
pub fn write_merged<S>(
    command: &str,
    out: &Path,
    dirs: &[PathBuf],
    settings_of: impl FnOnce(Vec<String>) -> Result<(S, String)>,
    write: impl FnOnce(&Path, &[Row], &[String], &S, &str) -> Result<()>,
) -> Result<()> {
    let merged = merge(command, dirs)?;
    let line: Vec<String> = std::iter::once(command.to_string())
        .chain(merged.run.iter().cloned())
        .chain(["--out".to_string(), out.display().to_string()])
        .collect();
    let (settings, here) = settings_of(line).context("the shards' flags")?;
    if here != merged.settings {
        bail!(
            "the shards ran other settings than this vkdr ({}) resolves their flags to: {}; \
             merge with the vkdr that ran them ({})",
            build_version(),
            first_difference(&merged.settings, &here),
            merged.version
        );
    }
    write(
        out,
        &merged.rows,
        &merged.failures,
        &settings,
        &merged.device,
    )?;
    if out.join("table.md").is_file() {
        print!("{}", std::fs::read_to_string(out.join("table.md"))?);
        println!(
            "merged {} shards: wrote {}/table.md, table.json, trials.csv, speed_vs_error.png",
            dirs.len(),
            out.display()
        );
    }
    if !merged.failures.is_empty() {
        bail!(
            "{} units failed in the shards:\n  {}",
            merged.failures.len(),
            merged.failures.join("\n  ")
        );
    }
    Ok(())
}

/// A unit of work: test instance `instance` of category `category` (indices in the
/// unsharded run's order) and their names.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Unit {
    pub category: usize,
    pub instance: usize,
    pub category_name: String,
    pub instance_name: String,
}

/// A row with its unit.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Placed {
    pub unit: Unit,
    pub row: Row,
}

/// What a shard writes.
#[derive(Serialize, Deserialize)]
pub struct ShardFile {
    pub format: u32,
    /// The command that ran it: `eval` or `eval-frames`.
    pub command: String,
    /// The vkdr version that ran it, with its build's commit ([`build_version`]).
    pub version: String,
    /// The run's flags after `eval`, without --shard, --out and --spaces: every shard of a
    /// run has the same.
    pub run: Vec<String>,
    /// The settings they resolved to ([`resolved`]): the merge refuses a build that
    /// resolves the flags otherwise.
    pub settings: String,
    pub shard: usize,
    pub shards: usize,
    /// The device, as the tables name it.
    pub device: String,
    /// The units assigned to this shard, and the rows of those that finished.
    pub units: Vec<Unit>,
    pub rows: Vec<Placed>,
    /// Categories that failed, with why.
    pub failures: Vec<String>,
}

impl ShardFile {
    /// Writes the file into `dir`, checked first to read back as the same rows.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let text = serde_json::to_string(self).context("shard file")?;
        let again: ShardFile = serde_json::from_str(&text).with_context(|| {
            "a figure of the shard cannot be written exactly (not finite?)".to_string()
        })?;
        if serde_json::to_string(&again)? != text {
            bail!("the shard's rows do not read back as written");
        }
        vkdr::io::write_atomically(&dir.join(FILE), (text + "\n").as_bytes())?;
        Ok(())
    }

    fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(FILE);
        let text = std::fs::read_to_string(&path).with_context(|| {
            format!(
                "{}: not a shard's output (run `vkdr eval --shard K/N --out {}` first)",
                path.display(),
                dir.display()
            )
        })?;
        // The format first: a shard of an older vkdr lacks fields this one reads.
        #[derive(Deserialize)]
        struct Head {
            format: u32,
            version: Option<String>,
        }
        let head: Head = serde_json::from_str(&text)
            .with_context(|| format!("{}: not a shard file of vkdr", path.display()))?;
        if head.format != FORMAT {
            bail!(
                "{}: shard format {} (written by vkdr {}), this vkdr ({}) reads format {FORMAT}: \
                 run the shards again with this vkdr",
                path.display(),
                head.format,
                head.version.as_deref().unwrap_or("of unknown version"),
                build_version()
            );
        }
        serde_json::from_str(&text)
            .with_context(|| format!("{}: not a shard file of this vkdr", path.display()))
    }

    /// A new, empty file for `shard` of the `command` run with flags `run`, resolved to
    /// `settings` ([`resolved`]).
    pub fn new(
        command: &str,
        run: Vec<String>,
        settings: String,
        shard: Shard,
        device: String,
        units: Vec<Unit>,
    ) -> Self {
        Self {
            format: FORMAT,
            command: command.to_string(),
            version: build_version(),
            run,
            settings,
            shard: shard.index,
            shards: shard.count,
            device,
            units,
            rows: Vec::new(),
            failures: Vec::new(),
        }
    }
}

/// The flags of this process's `command` run (`eval`, `eval-frames`) without those that
/// do not change its results (--shard, --out, --spaces, and the global --force), as given.
pub fn run_flags(command: &str) -> Vec<String> {
    let args: Vec<String> = std::env::args().collect();
    let start = args
        .iter()
        .position(|a| a == command)
        .map_or(args.len(), |i| i + 1);
    let mut flags = Vec::new();
    let mut rest = args[start..].iter();
    while let Some(arg) = rest.next() {
        let name = arg.split('=').next().unwrap_or(arg);
        if name == "--force" {
            continue;
        }
        if ["--shard", "--out", "--spaces"].contains(&name) {
            if !arg.contains('=') {
                rest.next();
            }
            continue;
        }
        flags.push(arg.clone());
    }
    flags
}

/// The merged run: its flags, the device(s), the rows in the unsharded order and the
/// failures. An error names a shard that is missing, given twice, of another run or
/// version, or a unit that two shards hold.
pub struct Merged {
    pub run: Vec<String>,
    /// The settings the shards resolved the flags to, and the version that ran them.
    pub settings: String,
    pub version: String,
    pub device: String,
    pub rows: Vec<Row>,
    pub failures: Vec<String>,
}

pub fn merge(command: &str, dirs: &[PathBuf]) -> Result<Merged> {
    if dirs.is_empty() {
        bail!("--merge OUT SHARD_DIRS...: no shard folders given");
    }
    let files = dirs
        .iter()
        .map(|d| ShardFile::read(d))
        .collect::<Result<Vec<_>>>()?;
    if let Some((file, dir)) = files.iter().zip(dirs).find(|(f, _)| f.command != command) {
        bail!(
            "{} is a shard of `vkdr {}`, not of `vkdr {command}`",
            dir.display(),
            file.command
        );
    }
    let (first, first_dir) = (&files[0], &dirs[0]);
    let mut by_index: BTreeMap<usize, &Path> = BTreeMap::new();
    for (file, dir) in files.iter().zip(dirs) {
        if file.version != first.version {
            bail!(
                "{} ran vkdr {}, {} ran {}: shards of one run come from one version",
                dir.display(),
                file.version,
                first_dir.display(),
                first.version
            );
        }
        if file.run != first.run || file.settings != first.settings {
            bail!(
                "{} is a shard of another run: its flags are `{}`, {}'s `{}`",
                dir.display(),
                file.run.join(" "),
                first_dir.display(),
                first.run.join(" ")
            );
        }
        if file.shards != first.shards {
            bail!(
                "{} is shard {} of {}, {} is shard {} of {}: one run has one shard count",
                dir.display(),
                file.shard,
                file.shards,
                first_dir.display(),
                first.shard,
                first.shards
            );
        }
        if let Some(other) = by_index.insert(file.shard, dir) {
            bail!(
                "shard {}/{} is given twice: {} and {}",
                file.shard,
                file.shards,
                other.display(),
                dir.display()
            );
        }
    }
    let missing: Vec<String> = (0..first.shards)
        .filter(|k| !by_index.contains_key(k))
        .map(|k| format!("{k}/{}", first.shards))
        .collect();
    if !missing.is_empty() {
        bail!(
            "shard{} {} of the run missing (given: {})",
            if missing.len() > 1 { "s" } else { "" },
            missing.join(", "),
            dirs.iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let mut placed: Vec<(&Placed, &Path)> = Vec::new();
    for (file, dir) in files.iter().zip(dirs) {
        placed.extend(file.rows.iter().map(|p| (p, dir.as_path())));
    }
    placed.sort_by(|a, b| a.0.unit.cmp(&b.0.unit));
    for pair in placed.windows(2) {
        if pair[0].0.unit == pair[1].0.unit {
            bail!(
                "{} and {} both hold {} {}: shards of one run hold each unit once",
                pair[0].1.display(),
                pair[1].1.display(),
                pair[0].0.unit.category_name,
                pair[0].0.unit.instance_name
            );
        }
    }
    let mut devices: Vec<&str> = files.iter().map(|f| f.device.as_str()).collect();
    devices.sort();
    devices.dedup();
    Ok(Merged {
        run: first.run.clone(),
        settings: first.settings.clone(),
        version: first.version.clone(),
        device: devices.join("; "),
        rows: placed.into_iter().map(|(p, _)| p.row.clone()).collect(),
        failures: files.iter().flat_map(|f| f.failures.clone()).collect(),
    })
}

/// The first line where two resolved settings differ, as `the shards' ..., here ...`.
fn first_difference(shards: &str, here: &str) -> String {
    let mut lines = shards.lines().zip(here.lines());
    match lines.find(|(a, b)| a != b) {
        Some((a, b)) => format!("the shards' `{}`, here `{}`", a.trim(), b.trim()),
        None => "one lists more settings than the other".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_refuse() {
        assert_eq!(Shard::parse("2/4").unwrap(), Shard { index: 2, count: 4 });
        for bad in ["4/4", "1", "a/3", "-1/3", "1/0"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn assignment_balances_costs_and_covers_every_unit() {
        let costs = [5.0, 1.0, 4.0, 2.0, 3.0, 3.0];
        let shard = assign(&costs, 3);
        let mut load = [0.0; 3];
        for (u, &s) in shard.iter().enumerate() {
            load[s] += costs[u];
        }
        assert_eq!(load, [6.0, 6.0, 6.0]);
        // More shards than units: each unit alone, the rest empty.
        assert_eq!(assign(&[1.0, 1.0], 5), vec![0, 1]);
        // The same input, the same assignment.
        assert_eq!(assign(&costs, 3), shard);
    }
}
