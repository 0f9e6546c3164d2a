//! Records the git commit the command line is built from (`VKDR_COMMIT`, "unknown" outside
//! a git checkout): shard files carry it, and a merge refuses shards of different builds.

use std::process::Command;

fn main() {
    let commit = Command::new("git")
        .args(["rev-parse", "--short=12", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".to_string());
    println!("cargo:rustc-env=VKDR_COMMIT={commit}");
    // A commit moves the branch's ref (or, packed, packed-refs); a checkout moves HEAD.
    for path in ["HEAD", "refs/heads", "packed-refs"] {
        println!("cargo:rerun-if-changed=../../.git/{path}");
    }
}
