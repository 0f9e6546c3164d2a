//! `vkdr eval --shard K/N` and `--merge`: the merged tables of 1, 3 and 7 shards are the
//! bytes of the unsharded run's (the wall times aside), and the merge refuses a missing
//! shard, a shard given twice and a shard of another run.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{fails, ok, s, table_without_times};

#[test]
fn merged_shards_are_the_unsharded_tables() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("shards");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let data = dir.join("data");
    vkdr_app::dataset::generate(&data, 0, 4, 2, |_, _, _| {}).unwrap();
    let spaces = dir.join("spaces");
    let run = [
        "eval",
        "--dataset",
        s(&data),
        "--categories",
        "bottle,mug",
        "--trials",
        "2",
        "--known-iterations",
        "4",
        "--noise-iterations",
        "4",
        "--align",
        "2",
        "--starts",
        "2",
        "--spaces",
        s(&spaces),
    ];
    let full = dir.join("full");
    ok(&[&run[..], &["--out", s(&full)]].concat());
    let rows = table_without_times(&full);
    assert_eq!(rows.as_array().unwrap().len(), 4);
    let trials = std::fs::read(full.join("trials.csv")).unwrap();

    // The shards of a run at once, as a cluster runs them.
    let shard_dirs = |n: usize| -> Vec<PathBuf> {
        let outs: Vec<PathBuf> = (0..n).map(|k| dir.join(format!("n{n}_{k}"))).collect();
        let children: Vec<_> = outs
            .iter()
            .enumerate()
            .map(|(k, out)| {
                let shard = format!("{k}/{n}");
                Command::new(env!("CARGO_BIN_EXE_vkdr"))
                    .args([&run[..], &["--shard", &shard, "--out", s(out)]].concat())
                    .stdout(std::process::Stdio::null())
                    .stderr(std::process::Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for (k, child) in children.into_iter().enumerate() {
            let done = child.wait_with_output().unwrap();
            assert!(
                done.status.success(),
                "shard {k}/{n}: {}",
                String::from_utf8_lossy(&done.stderr)
            );
        }
        outs
    };
    for n in [1, 3, 7] {
        let shards = shard_dirs(n);
        let merged = dir.join(format!("merged{n}"));
        let mut args = vec!["eval", "--merge", s(&merged)];
        // Given in any order.
        args.extend(shards.iter().rev().map(|d| s(d)));
        ok(&args);
        assert_eq!(table_without_times(&merged), rows, "{n} shards' table.json");
        assert!(
            std::fs::read(merged.join("trials.csv")).unwrap() == trials,
            "{n} shards' trials.csv"
        );

        if n == 3 {
            let said = fails(&[
                "eval",
                "--merge",
                s(&dir.join("m_missing")),
                s(&shards[0]),
                s(&shards[2]),
            ]);
            assert!(said.contains("shard 1/3 of the run missing"), "{said}");
            let said = fails(&[
                "eval",
                "--merge",
                s(&dir.join("m_twice")),
                s(&shards[0]),
                s(&shards[1]),
                s(&shards[1]),
            ]);
            assert!(said.contains("shard 1/3 is given twice"), "{said}");
            let other = dir.join("other");
            let mut flags = run.to_vec();
            flags[6] = "3"; // --trials 3
            ok(&[&flags[..], &["--shard", "2/3", "--out", s(&other)]].concat());
            let said = fails(&[
                "eval",
                "--merge",
                s(&dir.join("m_other")),
                s(&shards[0]),
                s(&shards[1]),
                s(&other),
            ]);
            assert!(
                said.contains("is a shard of another run") && said.contains("--trials 3"),
                "{said}"
            );
            // Shards whose settings this build would not resolve their flags to (as after
            // a default changed between the shards and the merge) are refused, not
            // described with this build's settings.
            let edited: Vec<PathBuf> = (0..3).map(|k| dir.join(format!("edited_{k}"))).collect();
            for (from, to) in shards.iter().zip(&edited) {
                std::fs::create_dir_all(to).unwrap();
                let text = std::fs::read_to_string(from.join("shard.json")).unwrap();
                assert_eq!(text.matches("plateau: 0.0001,").count(), 2, "{text}");
                let text = text.replace("plateau: 0.0001,", "plateau: 0.001,");
                std::fs::write(to.join("shard.json"), text).unwrap();
            }
            let merged_edited = dir.join("m_edited");
            let mut args = vec!["eval", "--merge", s(&merged_edited)];
            args.extend(edited.iter().map(|p| s(p)));
            let said = fails(&args);
            assert!(
                said.contains("the shards ran other settings")
                    && said.contains("`plateau: 0.001,`, here `plateau: 0.0001,`"),
                "{said}"
            );
            assert!(!merged_edited.join("table.md").exists());
            // A shard of an older format is refused with the reason.
            let old = dir.join("old_format");
            std::fs::create_dir_all(&old).unwrap();
            let text = std::fs::read_to_string(shards[0].join("shard.json")).unwrap();
            let text = text.replacen("\"format\":4", "\"format\":3", 1);
            std::fs::write(old.join("shard.json"), text).unwrap();
            let said = fails(&[
                "eval",
                "--merge",
                s(&dir.join("m_old")),
                s(&old),
                s(&shards[1]),
                s(&shards[2]),
            ]);
            assert!(
                said.contains("shard format 3") && said.contains("run the shards again"),
                "{said}"
            );
            let said = fails(&["eval", "--merge", s(&dir.join("m_none")), s(&data)]);
            assert!(said.contains("not a shard's output"), "{said}");
        }
    }
    let said = fails(&[&run[..], &["--shard", "3/3", "--out", s(&dir.join("bad"))]].concat());
    assert!(said.contains("--shard must be K/N"), "{said}");
    let mut not_a_folder = run.to_vec();
    let spaces_file = dir.join("full").join("table.json");
    *not_a_folder.last_mut().unwrap() = s(&spaces_file);
    let said = fails(&[&not_a_folder[..], &["--out", s(&dir.join("bad"))]].concat());
    assert!(said.contains("is not a folder"), "{said}");
}
