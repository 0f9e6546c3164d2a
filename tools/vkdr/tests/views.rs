//! What depth and a second view add to registration: a shape space whose first mode
//! stretches the object along the first camera's optical axis, which one silhouette barely
//! shows. From one mask the registration cannot find it; from two views sharing one code
//! and one object pose (known relative camera poses), or from one view with depth, it
//! converges to the known shape and pose.

#[path = "../../../tests/common/mod.rs"]
mod common;

use glam::DVec3;
use vkdr::diff::DepthLoss;
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::register::{Job, Optimizer, OtherView, RegisterParams, Registrar, Registration};
use vkdr::shape::{ShapeSpace, TrainingFit};
use vkdr::{Camera, Mesh, Pose};
use vkdr_app::dataset::Rng;

/// How far the object is from the first camera (the focal length follows, so that it
/// always spans the same pixels): far enough that perspective barely shows its depth.
const DISTANCE: f64 = 3.0;

/// Training shapes: a rounded box of 12 x 18 x 9 cm (no rotational symmetry) stretched along the object's z (up to +-50%) and, less, along x (+-20%).
fn stretch_space() -> ShapeSpace {
    let sphere = Mesh::uv_sphere(1.0, 12, 18);
    let axes = [0.06, 0.09, 0.045];
    let positions = sphere
        .positions()
        .iter()
        .map(|p| std::array::from_fn(|k| p[k].signum() * p[k].abs().sqrt() * axes[k]))
        .collect();
    let canonical = Mesh::new(positions, sphere.triangles().to_vec()).unwrap();
    let points = canonical.points();
    let mut rng = Rng::new(3);
    let fits: Vec<TrainingFit> = (0..8)
        .map(|_| {
            let (along_z, along_x) = (rng.range(-0.5, 0.5), rng.range(-0.2, 0.2));
            let d: Vec<f64> = points
                .iter()
                .flat_map(|p| [along_x * p.x, 0.0, along_z * p.z])
                .collect();
            TrainingFit {
                w: d.clone(),
                displacement: d,
            }
        })
        .collect();
    let names = (0..8).map(|i| format!("s{i}")).collect();
    ShapeSpace::from_fits("stretch", &canonical, 0.1, &fits, 2, names).unwrap()
}

/// The object in front of the first camera, its z axis along the optical axis.
fn truth_pose() -> Pose {
    Pose::at([0.0, 0.0, DISTANCE])
}

fn camera() -> Camera {
    let f = 350.0 * DISTANCE;
    Camera::new(f, f, 48.0, 48.0, 96, 96).unwrap()
}

/// A second camera that sees the object from above: turned 90 degrees about the object's
/// x axis. (From the side, turned about the vertical axis, two silhouettes of a shape
/// whose horizontal slices are all alike would leave a turn about that axis traded
/// against the widths: found in this test's first version.)
fn top_camera() -> OtherView {
    let turn = Pose::new([0.0; 3], [std::f64::consts::FRAC_PI_2, 0.0, 0.0]).unwrap();
    let centre = truth_pose().translation;
    OtherView {
        camera: camera(),
        from_first: Pose {
            translation: centre - turn.apply(centre),
            rotation: turn.rotation,
        },
    }
}

/// Masks and depth of `vertices` in every view, each [view][row][column].
fn observe(
    ctx: &vkdr::gpu::Context,
    space: &ShapeSpace,
    vertices: &[DVec3],
    views: &[View],
) -> (Vec<f32>, Vec<f32>) {
    let mesh = space.canonical.with_points(vertices).unwrap();
    let g = Rasterizer::new(ctx)
        .unwrap()
        .render(ctx, &mesh, views, Outputs::IdsBaryDepth)
        .unwrap();
    let mask = g.ids.iter().map(|&id| (id > 0) as u32 as f32).collect();
    (mask, g.depth.unwrap().iter().copied().collect())
}

fn rms(a: &[DVec3], b: &[DVec3]) -> f64 {
    (a.iter()
        .zip(b)
        .map(|(p, q)| (*p - *q).length_squared())
        .sum::<f64>()
        / a.len() as f64)
        .sqrt()
}

/// RMS of the vertices' z (the first camera's optical axis) against the truth's.
fn rms_z(a: &[DVec3], b: &[DVec3]) -> f64 {
    (a.iter()
        .zip(b)
        .map(|(p, q)| (p.z - q.z).powi(2))
        .sum::<f64>()
        / a.len() as f64)
        .sqrt()
}

struct Case {
    space: ShapeSpace,
    truth: Vec<DVec3>,
    mean: Vec<DVec3>,
}

fn case() -> Case {
    let space = stretch_space();
    // 40% longer along z, 10% wider along x.
    let truth: Vec<DVec3> = space
        .canonical
        .points()
        .iter()
        .map(|p| DVec3::new(1.1 * p.x, p.y, 1.4 * p.z))
        .collect();
    let mean = space.vertices(&[0.0, 0.0]).unwrap();
    Case { space, truth, mean }
}

/// A start 7 mm and about 3 degrees off the truth.
fn start_pose() -> Pose {
    Pose::new([0.006, -0.004, DISTANCE], [0.03, -0.04, 0.02]).unwrap()
}

fn params(optimize_pose: bool) -> RegisterParams {
    RegisterParams {
        iterations: 60,
        check_every: 60,
        optimizer: Optimizer::Bfgs,
        pose_every: optimize_pose as usize,
        optimize_z: optimize_pose,
        translation_step: 0.005,
        rotation_step: 0.03,
        ..Default::default()
    }
}

fn pose_errors(found: Pose) -> (f64, f64) {
    let truth = truth_pose();
    let rotation =
        glam::DQuat::from_mat3(&(found.rotation_matrix() * truth.rotation_matrix().transpose()))
            .to_scaled_axis()
            .length();
    ((found.translation - truth.translation).length(), rotation)
}

fn report(what: &str, case: &Case, result: &Registration) {
    let (t, r) = pose_errors(result.pose);
    let error = glam::DQuat::from_mat3(
        &(result.pose.rotation_matrix() * truth_pose().rotation_matrix().transpose()),
    )
    .to_scaled_axis();
    eprintln!(
        "{what}: rotation error {error:?}, translation {:?}",
        result.pose.translation
    );
    eprintln!(
        "{what}: vertex RMS {:.5} -> {:.5} m, along z {:.5} -> {:.5} m; pose {t:.5} m {r:.5} rad; {} iterations",
        rms(&case.mean, &case.truth),
        rms(&result.vertices, &case.truth),
        rms_z(&case.mean, &case.truth),
        rms_z(&result.vertices, &case.truth),
        result.evaluations
    );
}

#[test]
fn one_mask_along_the_stretch_cannot_see_it() {
    let ctx = common::context();
    let case = case();
    let view = View {
        camera: camera(),
        pose: truth_pose(),
    };
    let (mask, _) = observe(&ctx, &case.space, &case.truth, &[view]);
    let registrar = Registrar::new(&ctx).unwrap();
    let result = registrar
        .register(
            &ctx,
            Job::new(&case.space, &mask, view),
            &params(false),
            |_, _| {},
        )
        .unwrap();
    common::assert_no_validation_errors(&ctx);
    report("one view, known pose", &case, &result);
    // The width is found, the length along the optical axis is not.
    let (before, after) = (
        rms_z(&case.mean, &case.truth),
        rms_z(&result.vertices, &case.truth),
    );
    assert!(after > 0.5 * before, "along z {before} -> {after}");
}

#[test]
fn two_views_share_one_code_and_find_shape_and_pose() {
    let ctx = common::context();
    let case = case();
    let others = [top_camera()];
    let truth_job = Job::new(
        &case.space,
        &[],
        View {
            camera: camera(),
            pose: truth_pose(),
        },
    )
    .with_others(&others);
    let (masks, _) = observe(&ctx, &case.space, &case.truth, &truth_job.views());
    let start = View {
        camera: camera(),
        pose: start_pose(),
    };
    let job = Job::new(&case.space, &masks, start).with_others(&others);
    let registrar = Registrar::new(&ctx).unwrap();
    let result = registrar
        .register(&ctx, job, &params(true), |_, _| {})
        .unwrap();
    common::assert_no_validation_errors(&ctx);
    report("two views, pose from a start off", &case, &result);
    let before = rms(&case.mean, &case.truth);
    let after = rms(&result.vertices, &case.truth);
    assert!(after < 0.15 * before, "vertex RMS {before} -> {after}");
    let (t, r) = pose_errors(result.pose);
    let (t0, r0) = pose_errors(start_pose());
    assert!(t < 0.2 * t0 && r < 0.3 * r0, "pose {t0} {r0} -> {t} {r}");
}

#[test]
fn one_view_with_depth_finds_shape_and_pose() {
    let ctx = common::context();
    let case = case();
    let view = View {
        camera: camera(),
        pose: truth_pose(),
    };
    let (mask, depth) = observe(&ctx, &case.space, &case.truth, &[view]);
    let start = View {
        camera: camera(),
        pose: start_pose(),
    };
    let job = Job::new(&case.space, &mask, start).with_depth(&depth);
    let params = RegisterParams {
        depth: Some(DepthLoss::default()),
        ..params(true)
    };
    let registrar = Registrar::new(&ctx).unwrap();
    let result = registrar.register(&ctx, job, &params, |_, _| {}).unwrap();
    common::assert_no_validation_errors(&ctx);
    report("one view with depth, pose from a start off", &case, &result);
    let before = rms(&case.mean, &case.truth);
    let after = rms(&result.vertices, &case.truth);
    assert!(after < 0.15 * before, "vertex RMS {before} -> {after}");
    let (t, r) = pose_errors(result.pose);
    let (t0, r0) = pose_errors(start_pose());
    assert!(t < 0.2 * t0 && r < 0.3 * r0, "pose {t0} {r0} -> {t} {r}");
}

fn vkdr(args: &[&str]) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_vkdr"))
        .args(args)
        .output()
        .unwrap();
    let said =
        String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "vkdr {args:?} failed: {said}");
    said
}

fn vkdr_fails(args: &[&str]) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_vkdr"))
        .args(args)
        .output()
        .unwrap();
    assert!(!out.status.success(), "vkdr {args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// `vkdr register` with a depth image and a views file, as a user with an RGB-D camera and
/// a second camera would call it: the object pose comes back from a start 1 cm and 3
/// degrees off, and a views file that does not fit is refused by name.
#[test]
fn the_register_command_takes_depth_and_a_views_file() {
    let dir = std::env::temp_dir().join(format!("vkdr-views-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let p = |rel: &str| dir.join(rel).to_str().unwrap().to_string();
    vkdr(&["gen-dataset", "--out", &p("data")]);
    vkdr(&["shape-space", &p("data/bottle"), "--out", &p("space.npz")]);
    let test = p("data/bottle/test/bottle_test_00.obj");
    let camera = ["--intrinsics", "250,250,100,75", "--size", "200x150"];
    // The second camera sees the object from 90 degrees further about the first's x axis.
    for (view, pose) in [("v0", "0,0,0.6,0.5,0,0"), ("v1", "0,0,0.6,2.0707963,0,0")] {
        let mut args = vec!["render", test.as_str(), "--pose", pose, "--raw", "--out"];
        let out = p(view);
        args.push(&out);
        args.extend(camera);
        vkdr(&args);
    }
    let views = |size: &str| {
        format!(
            r#"{{"views": [{{"intrinsics": [250, 250, 100, 75], "size": {size},
            "from_first": {{"translation": [0, 0.6, 0.6], "rotation": [1.5707963, 0, 0]}},
            "mask": "v1/mask.png", "depth": "v1/depth.npy"}}]}}"#
        )
    };
    std::fs::write(dir.join("views.json"), views("[200, 150]")).unwrap();
    let space = p("space.npz");
    let (mask, depth, views_file, out) = (
        p("v0/mask.png"),
        p("v0/depth.npy"),
        p("views.json"),
        p("out"),
    );
    let mut args = vec![
        "register",
        "--space",
        &space,
        "--observed",
        &mask,
        "--observed-depth",
        &depth,
        "--views",
        &views_file,
        "--pose",
        "0.01,-0.005,0.6,0.55,0.02,0.0",
        "--optimize-pose",
        "--out",
        &out,
    ];
    args.extend(camera);
    vkdr(&args);
    let pose: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/pose.json")).unwrap()).unwrap();
    let t: Vec<f64> = (0..3)
        .map(|i| pose["translation"][i].as_f64().unwrap())
        .collect();
    let r: Vec<f64> = (0..3)
        .map(|i| pose["rotation"][i].as_f64().unwrap())
        .collect();
    let off = DVec3::new(t[0], t[1], t[2] - 0.6).length();
    assert!(off < 2e-3, "translation {t:?} is {off} m from the truth");
    // The bottle turns freely about its own axis; about the camera's x axis it may not.
    assert!((r[0] - 0.5).abs() < 0.02, "rotation {r:?}");
    for picture in ["overlay_end.png", "overlay_end_view1.png"] {
        assert!(dir.join("out").join(picture).is_file(), "{picture}");
    }
    // A further view of another size is refused, naming the file and the sizes.
    std::fs::write(dir.join("views.json"), views("[100, 150]")).unwrap();
    let out = p("out2");
    let at = args.iter().position(|a| *a == "--out").unwrap();
    args[at + 1] = &out;
    let said = vkdr_fails(&args);
    assert!(
        said.contains("views.json") && said.contains("200x150"),
        "{said}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
