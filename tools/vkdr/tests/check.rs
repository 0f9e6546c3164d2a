//! `check-dataset` on a small user-like category made here: z up (as many scan sets are),
//! one open scan, one of two components, one in millimetres, one still y up. Each problem
//! is reported, the millimetre mesh stops `check-dataset`, `shape-space` and `eval` before
//! any work, and the contact sheet shows every mesh.

#[path = "../../../tests/common/mod.rs"]
mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use glam::{DQuat, DVec3};
use vkdr::Mesh;
use vkdr_app::check::{self, Role, Severity};

/// `mesh` turned by `rotation`, scaled by `scale` and moved by `offset`.
fn placed(mesh: &Mesh, rotation: DQuat, scale: f64, offset: DVec3) -> Mesh {
    let points: Vec<DVec3> = mesh
        .points()
        .into_iter()
        .map(|p| rotation * p * scale + offset)
        .collect();
    mesh.with_points(&points).unwrap()
}

fn merged(a: &Mesh, b: &Mesh) -> Mesh {
    let mut positions = a.positions().to_vec();
    let offset = positions.len() as u32;
    positions.extend_from_slice(b.positions());
    let mut triangles = a.triangles().to_vec();
    triangles.extend(b.triangles().iter().map(|t| t.map(|v| v + offset)));
    Mesh::new(positions, triangles).unwrap()
}

/// A fresh category folder `cups` in a dataset folder `set` under the target directory.
fn category(set: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(set)
        .join("cups");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("train")).unwrap();
    std::fs::create_dir_all(dir.join("test")).unwrap();
    std::fs::write(dir.join("info.json"), r#"{"up_axis": "z", "units": "m"}"#).unwrap();
    let z_up = DQuat::from_rotation_arc(DVec3::Y, DVec3::Z);
    let bottle = placed(&Mesh::bottle(16), z_up, 1.0, DVec3::ZERO);
    let save = |name: &str, mesh: &Mesh| mesh.save_obj(dir.join(name)).unwrap();
    save("canonical.obj", &bottle);
    save("train/a_open.obj", &common::open_top(&bottle));
    let small = placed(&bottle, DQuat::IDENTITY, 0.3, DVec3::new(0.06, 0.0, 0.0));
    save("train/b_two_parts.obj", &merged(&bottle, &small));
    save(
        "train/c_millimetres.obj",
        &placed(&bottle, DQuat::IDENTITY, 1000.0, DVec3::ZERO),
    );
    save("train/d_y_up.obj", &Mesh::bottle(16));
    save(
        "test/e.obj",
        &placed(&bottle, DQuat::IDENTITY, 1.05, DVec3::ZERO),
    );
    dir
}

fn findings_of<'a>(category: &'a check::Category, subject: &str) -> Vec<&'a check::Finding> {
    category
        .findings
        .iter()
        .filter(|f| f.subject == subject)
        .collect()
}

#[test]
fn each_problem_of_a_user_category_is_reported() {
    let dir = category("check_report");
    let category = check::check_category(&dir).unwrap();
    print!("{}", check::report(&category));
    assert_eq!(category.info.up, DVec3::Z);
    assert_eq!(category.meshes.len(), 6);
    assert_eq!(category.meshes[0].0.role, Role::Canonical);
    assert!(findings_of(&category, "canonical.obj").is_empty());
    assert!(findings_of(&category, "test/e.obj").is_empty());

    let has = |subject: &str, severity: Severity, words: &str| {
        assert!(
            findings_of(&category, subject)
                .iter()
                .any(|f| f.severity == severity && f.message.contains(words)),
            "{subject}: no {severity:?} with \"{words}\" in {:?}",
            findings_of(&category, subject)
        );
    };
    has(
        "train/a_open.obj",
        Severity::Warning,
        "open: 16 boundary edges",
    );
    has(
        "train/b_two_parts.obj",
        Severity::Warning,
        "2 separate components",
    );
    has("train/c_millimetres.obj", Severity::Fatal, "millimetres");
    has("train/d_y_up.obj", Severity::Warning, "longest along y");
    assert_eq!(category.fatal().count(), 1);

    // Every mesh shows in its tiles, and in the overlay.
    let sheet = check::contact_sheet(&category);
    let dark = sheet.pixels().filter(|p| p.0[0] < 128).count();
    assert!(dark > 6 * 2 * 200, "{dark} dark pixels");
}

fn vkdr(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_vkdr"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout),
    )
}

#[test]
fn an_unusable_category_stops_every_command_before_any_work() {
    let dir = category("check_cli");
    let out = dir.parent().unwrap().join("out");
    let _ = std::fs::remove_dir_all(&out);
    let (ok, said) = vkdr(&[
        "check-dataset",
        dir.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && said.contains("millimetres"), "{said}");
    assert!(out.join("contact_cups.png").is_file() && out.join("report.txt").is_file());

    let space = out.join("space.npz");
    let (ok, said) = vkdr(&[
        "shape-space",
        dir.to_str().unwrap(),
        "--out",
        space.to_str().unwrap(),
    ]);
    assert!(
        !ok && said.contains("millimetres") && said.contains("--skip-checks"),
        "{said}"
    );
    assert!(!space.exists());

    let dataset = dir.parent().unwrap();
    let table = out.join("eval");
    let (ok, said) = vkdr(&[
        "eval",
        "--dataset",
        dataset.to_str().unwrap(),
        "--out",
        table.to_str().unwrap(),
    ]);
    assert!(!ok && said.contains("millimetres"), "{said}");
    let (ok, said) = vkdr(&[
        "eval",
        "--dataset",
        dataset.to_str().unwrap(),
        "--categories",
        "cupz",
        "--out",
        table.to_str().unwrap(),
    ]);
    assert!(!ok && said.contains("no category \"cupz\""), "{said}");
}

/// Cans, y up, each centred on its bounding box: a tall canonical, a flat can wider than
/// it is tall, and one whose lid is finely ringed (its vertex mean high above its centre).
/// None of it is a problem, and none is reported.
#[test]
fn flat_and_lidded_cans_are_not_reported() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("check_cans");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("train")).unwrap();
    std::fs::create_dir_all(dir.join("test")).unwrap();
    let can = |r: f32, h: f32, lid_rings: usize| {
        let mut profile = vec![(r, -h / 2.0), (r, h / 2.0 - 0.004)];
        for k in 0..lid_rings {
            profile.push((r * (1.0 - 0.9 * k as f32 / lid_rings as f32), h / 2.0));
        }
        Mesh::lathe(&profile, 24).unwrap()
    };
    let save = |name: &str, mesh: &Mesh| mesh.save_obj(dir.join(name)).unwrap();
    save("canonical.obj", &can(0.033, 0.115, 1));
    save("train/flat.obj", &can(0.05, 0.07, 1));
    save("train/lidded.obj", &can(0.033, 0.12, 40));
    save("train/tall.obj", &can(0.03, 0.13, 1));
    save("test/t.obj", &can(0.034, 0.11, 1));
    let category = check::check_category(&dir).unwrap();
    for subject in ["train/flat.obj", "train/lidded.obj"] {
        assert!(
            findings_of(&category, subject).is_empty(),
            "{subject}: {:?}",
            findings_of(&category, subject)
        );
    }
    // The lid moves the vertex mean by more than a quarter of the size.
    let lidded = category
        .meshes
        .iter()
        .find(|(s, _)| s.name == "train/lidded.obj")
        .unwrap();
    assert!(lidded.0.centroid.y > 0.03, "{:?}", lidded.0.centroid);
}
