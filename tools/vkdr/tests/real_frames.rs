//! Real YCB-Video frames (`../shared/real/ycbv-dev`, beside the repository: a fresh clone
//! has it there): a mug, the master chef can and the mustard bottle, registered from pose
//! noise with `eval-frames`' defaults (gravity from the depth, the scale free), the errors
//! asserted with a margin over what they measured; and the failure paths: a frame whose
//! support plane cannot be found is registered without gravity and says so, or, with
//! `--gravity-fallback error`, is a failed unit while the others' rows are written and the
//! run exits non-zero after trying them all; a mug cut in half by the image's border
//! registers, and an object out of view is a failed unit that says so.

mod common;

use std::path::{Path, PathBuf};

use common::{ok, s, vkdr};

/// The shared real set; a failure (not a skip) where it is missing.
fn real_set() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/real/ycbv-dev/bop");
    assert!(
        dir.join("map.json").is_file(),
        "the shared real frames are not at {} (a checkout has ../shared beside it)",
        dir.display()
    );
    dir
}

fn folder(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("real_{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// table.json of an eval-frames run.
fn table(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("table.json")).unwrap()).unwrap()
}

/// The mean of trial field `key` over a row's trials.
fn mean(row: &serde_json::Value, key: &str) -> f64 {
    let trials = row["trials"].as_array().unwrap();
    trials.iter().map(|t| t[key].as_f64().unwrap()).sum::<f64>() / trials.len() as f64
}

/// The one failed unit of a run's table.json (asserting that exactly one failed).
fn only_failure(table: &serde_json::Value) -> &str {
    let failures = table["failures"].as_array().unwrap();
    assert_eq!(failures.len(), 1, "{failures:?}");
    failures[0].as_str().unwrap()
}

fn row<'a>(table: &'a serde_json::Value, category: &str) -> &'a serde_json::Value {
    table["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["category"] == category)
        .unwrap_or_else(|| panic!("no {category} row in {table}"))
}

#[test]
fn a_mug_a_can_and_a_bottle_from_pose_noise() {
    let bop = real_set();
    let out = folder("three").join("out");
    ok(&[
        "eval-frames",
        s(&bop),
        "--images",
        "000000/1,000001/1",
        "--trials",
        "2",
        "--pictures",
        "--out",
        s(&out),
    ]);
    let table = table(&out);
    assert!(table["failures"].as_array().unwrap().is_empty());
    // A picture of each unit, its first panel the frame's colour image (not the depth's
    // grey: the mug is red).
    let mut pictures: Vec<String> = std::fs::read_dir(out.join("pictures"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    pictures.sort();
    assert_eq!(
        pictures,
        [
            "000000_000001_0.png",
            "000001_000001_0.png",
            "000001_000001_1.png"
        ]
    );
    let mug = image::open(out.join("pictures").join(&pictures[0]))
        .unwrap()
        .to_rgb8();
    let first = (0..mug.height())
        .flat_map(|y| (0..mug.width() / 3).map(move |x| (x, y)))
        .filter(|&(x, y)| {
            let p = mug.get_pixel(x, y);
            p[0] as i32 - p[1] as i32 > 60
        })
        .count();
    assert!(first > 1000, "{first} red pixels in the colour panel");
    // Measured (lavapipe, 3 trials, docs/evaluation.md): mug as seen 2.54 mm, 1.13x its
    // known-pose error, tilt 0.8 deg, z 1.5 mm; can size 1.026, z 4.8 mm, as seen 1.9 mm
    // (27.9 mm and size 0.65 with the scale fixed); bottle as seen 15.5 mm. Asserted with
    // margins.
    let mug = row(&table, "mug");
    let known = mug["known_pose"]["mean"].as_f64().unwrap();
    let seen = mug["pose_noise_seen"]["mean"].as_f64().unwrap();
    assert!(
        seen <= 1.5 * known,
        "mug as seen {seen} against known pose {known}"
    );
    assert!(mean(mug, "tilt").to_degrees() <= 2.0);
    assert!(mean(mug, "z_error").abs() <= 0.005);
    let can = row(&table, "can_wo_002_master_chef_can");
    assert!(
        (mean(can, "size") - 1.0).abs() <= 0.05,
        "can size {}",
        mean(can, "size")
    );
    assert!(mean(can, "z_error").abs() <= 0.009);
    assert!(can["pose_noise_seen"]["mean"].as_f64().unwrap() <= 0.004);
    // The bottle's space (two sauce bottles) is far from the mustard bottle: its surface
    // within 2.5 cm as seen.
    let bottle = row(&table, "bottle");
    assert!(bottle["pose_noise_seen"]["mean"].as_f64().unwrap() <= 0.025);
    // The field's metrics are there and agree with the errors: ADD-S within 10 cm, every
    // box overlapping.
    for r in [mug, can, bottle] {
        assert!(mean(r, "add_s") > 0.0 && mean(r, "add_s") < 0.03);
        assert!(mean(r, "iou") > 0.25);
    }
    let md = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(
        md.contains("fx 1066.8 fy 1067.5 cx 313.0 cy 241.3, 640x480 px"),
        "{md}"
    );
    assert!(
        !md.contains("320x240"),
        "eval's protocol above real frames: {md}"
    );
}

/// A test folder `name` and in it, under `frames`, a copy of images 1 and 3 of the shared
/// scene 000000 (the mug) whose image 1 keeps its depth only on the mask: no support plane
/// around it. Returns the folder and the frames.
fn without_table(name: &str) -> (PathBuf, PathBuf) {
    let bop = real_set();
    let dir = folder(name);
    let root = dir.join("frames");
    copy_without_table(&root, &bop);
    (dir, root)
}

/// [`without_table`]'s copy of the shared set `bop` at `root`, with its map.
fn copy_without_table(root: &Path, bop: &Path) {
    let scene = root.join("000000");
    for folder in ["depth", "mask_visib", "rgb"] {
        std::fs::create_dir_all(scene.join(folder)).unwrap();
    }
    let from = bop.join("000000");
    for file in ["scene_camera.json", "scene_gt.json"] {
        std::fs::copy(from.join(file), scene.join(file)).unwrap();
    }
    let mask = image::open(from.join("mask_visib/000001_000000.png"))
        .unwrap()
        .to_luma8();
    let mut depth = image::open(from.join("depth/000001.png"))
        .unwrap()
        .to_luma16();
    for (d, m) in depth.pixels_mut().zip(mask.pixels()) {
        if m.0[0] == 0 {
            d.0[0] = 0;
        }
    }
    depth.save(scene.join("depth/000001.png")).unwrap();
    std::fs::copy(
        from.join("mask_visib/000001_000000.png"),
        scene.join("mask_visib/000001_000000.png"),
    )
    .unwrap();
    std::fs::copy(
        from.join("depth/000003.png"),
        scene.join("depth/000003.png"),
    )
    .unwrap();
    std::fs::copy(
        from.join("mask_visib/000003_000000.png"),
        scene.join("mask_visib/000003_000000.png"),
    )
    .unwrap();
    // Only images 1 and 3 in the copy's JSON.
    for file in ["scene_camera.json", "scene_gt.json"] {
        let path = scene.join(file);
        let mut v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        v.as_object_mut()
            .unwrap()
            .retain(|k, _| k == "1" || k == "3");
        std::fs::write(&path, v.to_string()).unwrap();
    }
    std::fs::copy(bop.join("map.json"), root.join("map.json")).unwrap();
    let text = std::fs::read_to_string(root.join("map.json")).unwrap();
    // The map's paths are relative to its folder: point them at the shared set.
    let shared = std::fs::canonicalize(bop).unwrap();
    let text = text
        .replace(
            "\"../dataset",
            &format!("\"{}/../dataset", shared.display()),
        )
        .replace("\"models/", &format!("\"{}/models/", shared.display()));
    std::fs::write(root.join("map.json"), text).unwrap();
}

#[test]
fn a_frame_without_a_support_plane_is_a_row_not_an_exit() {
    let (dir, frames) = without_table("no_plane");
    // The default fallback: registered without gravity, and the trials say so.
    let out = dir.join("fallback");
    // Both runs keep their shape spaces and the models' references in one folder.
    let spaces = dir.join("spaces");
    let first = ok(&[
        "eval-frames",
        s(&frames),
        "--images",
        "000000/1",
        "--trials",
        "2",
        "--spaces",
        s(&spaces),
        "--out",
        s(&out),
    ]);
    let computing = "the model's oracle and space optimum";
    assert!(first.contains(computing), "{first}");
    let references: Vec<_> = std::fs::read_dir(spaces.join("references"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(references.len(), 1, "{references:?}");
    let kept = std::fs::read(&references[0]).unwrap();
    let table = table(&out);
    let mug = row(&table, "mug");
    let trials = mug["trials"].as_array().unwrap();
    assert_eq!(trials.len(), 2);
    for t in trials {
        assert_eq!(t["gravity_fallback"], true);
    }
    // --gravity-fallback error: that unit fails with its reason, the next frame is
    // registered and written, and the exit says a unit failed.
    let out = dir.join("error");
    let result = vkdr(&[
        "eval-frames",
        s(&frames),
        "--trials",
        "2",
        "--gravity-fallback",
        "error",
        "--spaces",
        s(&spaces),
        "--out",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&result.stderr);
    // The mug's reference was read, not fitted again, and is as it was.
    assert!(!err.contains(computing), "{err}");
    assert_eq!(std::fs::read(&references[0]).unwrap(), kept);
    assert!(!result.status.success());
    assert!(err.contains("1 of 2 units failed"), "{err}");
    let table = self::table(&out);
    assert!(only_failure(&table).starts_with("000000/000001/0"));
    assert_eq!(table["rows"].as_array().unwrap().len(), 1);
    assert_eq!(table["rows"][0]["instance"], "000000/000003/0");
    let md = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(md.contains("## Failed units (1)"));
}

/// A copy of scene 000000's images 1 and 3 (the mug) at `root`, with the map pointing at
/// the shared set: image 1 moved left (the principal point with it) until the mug's mask's
/// middle column is on the image's left border, which cuts the mug in half; image 3 with
/// an empty mask (the object wholly out of view).
fn cut_by_the_border(root: &Path, bop: &Path) {
    copy_without_table(root, bop); // images 1 and 3, the map; their pixels are replaced below
    let (from, scene) = (bop.join("000000"), root.join("000000"));
    let mask = image::open(from.join("mask_visib/000001_000000.png"))
        .unwrap()
        .to_luma8();
    let depth = image::open(from.join("depth/000001.png"))
        .unwrap()
        .to_luma16();
    let columns: Vec<u32> = mask
        .enumerate_pixels()
        .filter(|(_, _, m)| m.0[0] > 0)
        .map(|(x, _, _)| x)
        .collect();
    let shift = (columns.iter().min().unwrap() + columns.iter().max().unwrap()) / 2;
    let (w, h) = mask.dimensions();
    let moved_mask = image::GrayImage::from_fn(w, h, |x, y| match x + shift {
        x if x < w => *mask.get_pixel(x, y),
        _ => image::Luma([0]),
    });
    let moved_depth = image::ImageBuffer::from_fn(w, h, |x, y| match x + shift {
        x if x < w => *depth.get_pixel(x, y),
        _ => image::Luma([0u16]),
    });
    moved_mask
        .save(scene.join("mask_visib/000001_000000.png"))
        .unwrap();
    moved_depth.save(scene.join("depth/000001.png")).unwrap();
    image::GrayImage::new(w, h)
        .save(scene.join("mask_visib/000003_000000.png"))
        .unwrap();
    edit_camera(&scene.join("scene_camera.json"), "1", |k| {
        k[2] -= shift as f64
    });
}

/// Edits image `image`'s `cam_K` (row-major 3 x 3) in a scene_camera.json.
fn edit_camera(path: &Path, image: &str, edit: impl FnOnce(&mut [f64])) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let mut k: Vec<f64> = v[image]["cam_K"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    edit(&mut k);
    v[image]["cam_K"] = serde_json::json!(k);
    std::fs::write(path, v.to_string()).unwrap();
}

/// A mug cut in half by the image's border registers from pose noise (one of these trials
/// starts with 1.2% of the mean shape's vertices on the mask, most of it outside the image:
/// unless moved onto the mask first it is pulled out of the image, "the registration lost
/// the object"), and an object out of view is a failed unit that says so.
#[test]
fn an_object_cut_by_the_border_and_one_out_of_view() {
    let bop = real_set();
    let dir = folder("cut");
    let frames = dir.join("frames");
    cut_by_the_border(&frames, &bop);
    let out = dir.join("out");
    let result = vkdr(&["eval-frames", s(&frames), "--trials", "2", "--out", s(&out)]);
    let err = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success(), "{err}");
    assert!(err.contains("1 of 2 units failed"), "{err}");
    let table = table(&out);
    let failure = only_failure(&table);
    assert!(failure.starts_with("000000/000003/0"), "{failure}");
    assert!(failure.contains("shows nothing of the object"), "{failure}");
    // Measured (lavapipe, 2026-11-29): as seen 3.0 and 5.5 mm (2.6 mm uncut), tilt 0.9
    // and 1.8 deg, z 1.0 and 5.0 mm.
    let mug = row(&table, "mug");
    assert_eq!(mug["instance"], "000000/000001/0");
    let trials = mug["trials"].as_array().unwrap();
    assert_eq!(trials.len(), 2);
    for t in trials {
        assert!(t["pose_noise_seen"].as_f64().unwrap() <= 0.008, "{t}");
        assert!(t["tilt"].as_f64().unwrap().to_degrees() <= 3.0, "{t}");
        assert!(t["z_error"].as_f64().unwrap().abs() <= 0.008, "{t}");
    }
}

/// An object of which a sliver shows (the mug's top rows: a few per cent of its
/// silhouette, which the model rendered at the annotated pose gives) is under BOP's 10%
/// and a failed unit that says so, before any registration or reference.
#[test]
fn a_sliver_of_an_object_is_under_bop_s_visible_share() {
    let (dir, frames) = without_table("sliver");
    let path = frames.join("000000/mask_visib/000001_000000.png");
    let mut mask = image::open(&path).unwrap().to_luma8();
    let top = mask
        .enumerate_pixels()
        .filter(|(_, _, m)| m.0[0] > 0)
        .map(|(_, y, _)| y)
        .min()
        .unwrap();
    for (_, y, m) in mask.enumerate_pixels_mut() {
        if y >= top + 6 {
            m.0[0] = 0;
        }
    }
    mask.save(&path).unwrap();
    let out = dir.join("out");
    let run = [
        "eval-frames",
        s(&frames),
        "--images",
        "000000/1",
        "--trials",
        "2",
    ];
    let result = vkdr(&[&run[..], &["--out", s(&out)]].concat());
    let err = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success(), "{err}");
    let table = table(&out);
    let failure = only_failure(&table);
    assert!(failure.contains("under --min-visible 0.1"), "{failure}");
    let share: f64 = failure
        .split("): ")
        .nth(1)
        .unwrap()
        .split('%')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!((0.5..10.0).contains(&share), "{failure}");
    assert!(
        !err.contains("oracle"),
        "a reference computed for it: {err}"
    );
}
