//! What the command-line tests share: running the `vkdr` binary, and reading its tables.

#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs `vkdr` with `args`.
pub fn vkdr(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vkdr"))
        .args(args)
        .output()
        .unwrap()
}

/// Runs `vkdr` with `args`; fails the test with its error unless it succeeds, else
/// returns what it wrote to stderr (its progress).
pub fn ok(args: &[&str]) -> String {
    let out = vkdr(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "vkdr {args:?}: {err}");
    err
}

/// The error of a command that must fail.
pub fn fails(args: &[&str]) -> String {
    let out = vkdr(args);
    assert!(!out.status.success(), "vkdr {args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A path as an argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// An eval run's table.json without its wall times (`ms`, `noise_ms`).
pub fn table_without_times(out: &Path) -> serde_json::Value {
    fn strip(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(map) => {
                map.retain(|k, _| k != "ms" && !k.ends_with("_ms") && !k.starts_with("ms_"));
                map.values_mut().for_each(strip);
            }
            serde_json::Value::Array(items) => items.iter_mut().for_each(strip),
            _ => {}
        }
    }
    let mut table: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("table.json")).unwrap()).unwrap();
    strip(&mut table);
    table
}
