//! Gradients of the differentiable renderer against central differences of the float64
//! reference model (`diff::reference`), with the triangle ids of every pixel held at the
//! device's (visibility is piecewise constant; within a piece the loss is smooth).
//!
//! Each case checks: the device's loss and antialiased image against the model (loss
//! within 1e-4 relative, pixels within 1e-3), no NaN or Inf anywhere, and the vertex
//! gradient (all vertices, 3 coordinates) and the pose gradient (translation and rotation
//! separately) against central differences with step 1e-6 x the object's size (1e-6 rad
//! for rotations): relative error |g - g_fd| / |g_fd| (Euclidean norms over the whole
//! vector) at most 1e-2.

mod common;

use glam::{DMat3, DVec3};

use vkdr::diff::reference::{self, Problem, RigidPose};
use vkdr::diff::{
    neighbours, DepthLoss, DiffRenderer, Evaluation, ObservedDepth, Scene, SceneDesc, Shading,
};
use vkdr::loss::Loss;
use vkdr::raster::View;
use vkdr::{Camera, Mesh, Pose};

const TOLERANCE: f64 = 1e-2;
/// Central-difference step, relative to the object's size.
const STEP: f64 = 1e-6;

#[derive(Clone)]
struct Case {
    mesh: Mesh,
    views: Vec<View>,
    loss: Loss,
    /// [view][row][column][channel]
    observed: Vec<f32>,
    attributes: Option<(Vec<f32>, u32)>,
    shading: Option<Shading>,
    /// Observed depth [view][row][column] and how it is compared.
    depth: Option<(Vec<f32>, DepthLoss)>,
}

/// What a check measured.
#[derive(Debug)]
struct Report {
    loss: f64,
    vertex_error: f64,
    vertex_norm: f64,
    translation_error: f64,
    translation_norm: f64,
    rotation_error: f64,
    rotation_norm: f64,
}

fn relative_error(got: &[f64], want: &[f64]) -> (f64, f64) {
    let diff: f64 = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    let norm: f64 = want.iter().map(|b| b * b).sum::<f64>().sqrt();
    (if norm > 0.0 { diff / norm } else { diff }, norm)
}

fn rigid(pose: &Pose) -> RigidPose {
    RigidPose {
        rotation: pose.rotation_matrix(),
        translation: pose.translation,
    }
}

/// Evaluates on the device and against the model; returns the report (asserting the
/// forward agreement and the absence of NaN here, the gradient bounds in the caller).
fn check(case: &Case) -> (Report, Evaluation) {
    check_vertices(case, Vertices::All, STEP)
}

/// As [`check`], with the vertex gradient compared on a subset of the vertices (those
/// with a nonzero device gradient, and every 17th of the others, which must be zero), for
/// meshes too dense to difference every vertex. The pose gradients, which sum every
/// vertex's contribution, are still compared in full.
fn check_subset(case: &Case) -> (Report, Evaluation) {
    check_vertices(case, Vertices::Subset, STEP)
}

/// Which vertices' gradients [`check_vertices`] compares with central differences.
#[derive(Clone, Copy, PartialEq)]
enum Vertices {
    All,
    /// Those with a nonzero device gradient, and every 17th of the others.
    Subset,
    /// Every this many-th vertex (for images too large to difference many).
    Every(usize),
}

/// The case's scene on the device.
fn device_scene(ctx: &vkdr::gpu::Context, case: &Case) -> Scene {
    let attributes = case.attributes.as_ref().map(|(a, c)| (a.as_slice(), *c));
    Scene::new(
        ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh: &case.mesh,
            views: &case.views,
            loss: case.loss,
            observed: &case.observed,
            attributes,
            shading: case.shading,
            depth: case
                .depth
                .as_ref()
                .map(|(depth, loss)| ObservedDepth { depth, loss: *loss }),
        },
    )
    .expect("scene")
}

fn check_vertices(case: &Case, vertices: Vertices, step: f64) -> (Report, Evaluation) {
    let ctx = common::context();
    let renderer = DiffRenderer::new(&ctx).expect("diff renderer");
    let mut scene = device_scene(&ctx, case);
    let gpu = scene.evaluate(&ctx, &renderer).expect("evaluate");
    let distance: Vec<f64> = if case.loss == Loss::Distance {
        scene
            .read_distance_field()
            .unwrap()
            .iter()
            .map(|&d| d as f64)
            .collect()
    } else {
        Vec::new()
    };
    common::assert_no_validation_errors(&ctx);

    let finite = gpu
        .loss
        .iter()
        .chain(gpu.vertex_gradient.iter().flatten())
        .chain(gpu.pose_gradient.iter().flatten());
    for value in finite
        .chain(&gpu.antialiased)
        .chain(&gpu.attribute_gradient)
    {
        assert!(value.is_finite(), "non-finite output {value}");
    }

    let cameras: Vec<Camera> = case.views.iter().map(|v| v.camera).collect();
    let triangles = case.mesh.triangles();
    let adjacency = neighbours(&case.mesh);
    let observed: Vec<f64> = case.observed.iter().map(|&v| v as f64).collect();
    let depth64: Option<Vec<f64>> = case
        .depth
        .as_ref()
        .map(|(d, _)| d.iter().map(|&v| v as f64).collect());
    let attributes64: Option<Vec<f64>> = case
        .attributes
        .as_ref()
        .map(|(a, _)| a.iter().map(|&v| v as f64).collect());
    let problem = Problem {
        triangles,
        neighbours: &adjacency,
        cameras: &cameras,
        ids: &gpu.ids,
        observed: &observed,
        distance: &distance,
        attributes: attributes64
            .as_deref()
            .zip(case.attributes.as_ref().map(|(_, c)| *c as usize)),
        shading: case.shading,
        loss: case.loss,
        depth: depth64
            .as_deref()
            .zip(case.depth.as_ref().map(|(_, loss)| *loss)),
    };
    let positions: Vec<DVec3> = case.mesh.points();
    let poses: Vec<RigidPose> = case.views.iter().map(|v| rigid(&v.pose)).collect();
    let base = reference::evaluate(&problem, &positions, &poses);

    let gpu_loss: f64 = gpu.loss.iter().map(|&l| l as f64).sum();
    assert!(
        (gpu_loss - base.loss).abs() <= 1e-4 * base.loss.abs().max(1e-3),
        "loss: device {gpu_loss}, reference {}",
        base.loss
    );
    for (k, (&a, &b)) in gpu.antialiased.iter().zip(&base.antialiased).enumerate() {
        assert!(
            (a as f64 - b).abs() <= 1e-3,
            "antialiased value {k}: device {a}, reference {b}"
        );
    }

    let (lo, hi) = case.mesh.bounds();
    let size = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    let h = step * size;
    let loss_at = |positions: &[DVec3], poses: &[RigidPose]| {
        reference::evaluate(&problem, positions, poses).loss
    };

    let checked: Vec<usize> = (0..positions.len())
        .filter(|&v| match vertices {
            Vertices::All => true,
            Vertices::Subset => v % 17 == 0 || gpu.vertex_gradient[v] != [0.0; 3],
            Vertices::Every(k) => v % k == 0,
        })
        .collect();
    let mut fd_vertex = Vec::with_capacity(checked.len() * 3);
    let mut moved = positions.clone();
    for &v in &checked {
        for axis in 0..3 {
            let mut step = DVec3::ZERO;
            step[axis] = h;
            moved[v] = positions[v] + step;
            let plus = loss_at(&moved, &poses);
            moved[v] = positions[v] - step;
            let minus = loss_at(&moved, &poses);
            moved[v] = positions[v];
            fd_vertex.push((plus - minus) / (2.0 * h));
        }
    }
    let got_vertex: Vec<f64> = checked
        .iter()
        .flat_map(|&v| gpu.vertex_gradient[v])
        .map(|g| g as f64)
        .collect();
    let (vertex_error, vertex_norm) = relative_error(&got_vertex, &fd_vertex);

    let (mut fd_t, mut fd_r, mut got_t, mut got_r) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let angle = 1e-6;
    for (view, pose) in poses.iter().enumerate() {
        for axis in 0..3 {
            let mut moved = poses.clone();
            let mut e = DVec3::ZERO;
            e[axis] = 1.0;
            moved[view].translation = pose.translation + e * h;
            let plus = loss_at(&positions, &moved);
            moved[view].translation = pose.translation - e * h;
            let minus = loss_at(&positions, &moved);
            fd_t.push((plus - minus) / (2.0 * h));
            moved[view].translation = pose.translation;
            moved[view].rotation = DMat3::from_axis_angle(e, angle) * pose.rotation;
            let plus = loss_at(&positions, &moved);
            moved[view].rotation = DMat3::from_axis_angle(e, -angle) * pose.rotation;
            let minus = loss_at(&positions, &moved);
            fd_r.push((plus - minus) / (2.0 * angle));
            got_t.push(gpu.pose_gradient[view][axis] as f64);
            got_r.push(gpu.pose_gradient[view][3 + axis] as f64);
        }
    }
    let (translation_error, translation_norm) = relative_error(&got_t, &fd_t);
    let (rotation_error, rotation_norm) = relative_error(&got_r, &fd_r);
    let report = Report {
        loss: base.loss,
        vertex_error,
        vertex_norm,
        translation_error,
        translation_norm,
        rotation_error,
        rotation_norm,
    };
    eprintln!("{report:?}");
    (report, gpu)
}

/// Asserts gradients that are not all zero and within the tolerance.
fn assert_gradients_match(case: &Case) -> Report {
    let (report, _) = check(case);
    assert_report_within_tolerance(&report);
    report
}

fn assert_report_within_tolerance(report: &Report) {
    assert!(
        report.vertex_norm > 0.0 && report.translation_norm > 0.0 && report.rotation_norm > 0.0,
        "vacuous: {report:?}"
    );
    assert!(
        report.vertex_error <= TOLERANCE,
        "vertex gradient: {report:?}"
    );
    assert!(
        report.translation_error <= TOLERANCE,
        "translation gradient: {report:?}"
    );
    assert!(
        report.rotation_error <= TOLERANCE,
        "rotation gradient: {report:?}"
    );
}

/// A disc mask (1 inside) centred at (cx, cy) with radius r, in pixels.
fn disc(width: u32, height: u32, cx: f64, cy: f64, r: f64) -> Vec<f32> {
    let mut mask = Vec::with_capacity((width * height) as usize);
    for y in 0..height {
        for x in 0..width {
            let d = ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2)).sqrt();
            mask.push(if d <= r { 1.0 } else { 0.0 });
        }
    }
    mask
}

fn camera(size: u32) -> Camera {
    Camera::new(
        1.3 * size as f64,
        1.25 * size as f64,
        0.52 * size as f64,
        0.47 * size as f64,
        size,
        size,
    )
    .unwrap()
}

/// A sphere of `radius` seen at `distance`, compared with an off-centre disc.
fn sphere_case(loss: Loss, radius: f32, distance: f64, size: u32) -> Case {
    let camera = camera(size);
    let pose = Pose::new(
        [0.1 * distance * 0.1, -0.05 * distance * 0.1, distance],
        [0.4, -0.3, 0.2],
    )
    .unwrap();
    let s = size as f64;
    Case {
        mesh: Mesh::uv_sphere(radius, 6, 9),
        views: vec![View { camera, pose }],
        loss,
        observed: disc(size, size, 0.58 * s, 0.43 * s, 0.3 * s),
        attributes: None,
        shading: None,
        depth: None,
    }
}

#[test]
fn mse_of_coverage() {
    assert_gradients_match(&sphere_case(Loss::Mse, 0.1, 0.45, 64));
}

#[test]
fn soft_iou() {
    assert_gradients_match(&sphere_case(Loss::Iou, 0.1, 0.45, 64));
}

#[test]
fn distance_loss() {
    assert_gradients_match(&sphere_case(Loss::Distance, 0.1, 0.45, 64));
}

#[test]
fn mse_of_interpolated_colour() {
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    let colours: Vec<f32> = case
        .mesh
        .positions()
        .iter()
        .flat_map(|p| [0.5 + 4.0 * p[0], 0.5 + 4.0 * p[1], 0.5 + 4.0 * p[2]])
        .collect();
    let mask = case.observed.clone();
    case.observed = mask
        .iter()
        .flat_map(|&m| [0.2 * m, 0.6 * m, 0.9 * m])
        .collect();
    case.attributes = Some((colours, 3));
    let report = assert_gradients_match(&case);
    assert!(report.loss > 0.0);
}

/// Adds a view from another side, of the same size, observing the first view's image
/// turned upside down.
fn add_second_view(case: &mut Case) {
    case.views.push(View {
        camera: camera(case.views[0].camera.width),
        pose: Pose::new([-0.02, 0.01, 0.5], [1.2, 0.3, -0.4]).unwrap(),
    });
    let image = case.observed.clone();
    case.observed.extend(image.iter().rev());
}

/// A grey disc (the sphere's mean shade, about) to compare the sphere's shading with.
fn grey_disc_case(views: usize) -> Case {
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 48);
    case.shading = Some(Shading::default());
    if views == 2 {
        add_second_view(&mut case);
    }
    case.observed.iter_mut().for_each(|v| *v *= 0.6);
    case
}

#[test]
fn mse_of_lambert_shading() {
    let case = grey_disc_case(1);
    let (_, gpu) = check(&case);
    // Shading, not coverage: the object's pixels take more than two values.
    let mut shades: Vec<f32> = gpu.antialiased.clone();
    shades.sort_by(f32::total_cmp);
    shades.dedup_by(|a, b| (*a - *b).abs() < 1e-3);
    assert!(shades.len() > 20, "{} distinct shades", shades.len());
    let report = assert_gradients_match(&case);
    assert!(report.loss > 0.0);
}

#[test]
fn lambert_shading_in_two_views() {
    // Each view shades the vertices under its own rotation.
    assert_gradients_match(&grey_disc_case(2));
}

/// Adds an observed depth to every view: a tilted plane through the sphere, so that the
/// residuals cover both sides of the depth cost's bend (its inflection at 1 cm / sqrt(3)), with every 7th pixel
/// unmeasured (0) and a few measured outside the rendered silhouette.
fn with_depth(mut case: Case) -> Case {
    let (w, h) = (case.views[0].camera.width, case.views[0].camera.height);
    let mut depth = Vec::new();
    for view in &case.views {
        let centre = view.pose.translation.z;
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let tilt = 0.002 * (x as f64 - w as f64 / 2.0) + 0.001 * y as f64;
                let plane = centre - 0.08 + tilt * 64.0 / w as f64;
                depth.push(if i % 7 == 3 { 0.0 } else { plane as f32 });
            }
        }
    }
    // The plain depth term: occlusion has its own test.
    let loss = DepthLoss {
        occlusion: 0.0,
        ..DepthLoss::default()
    };
    case.depth = Some((depth, loss));
    case
}

/// Marks a band of columns (40% to 60% of the width) unknown in every view: it crosses
/// the sphere's silhouette and the disc's edge.
fn with_unknown_band(mut case: Case) -> Case {
    let w = case.views[0].camera.width as usize;
    let channels = case.observed.len() / (case.views.len() * w * w);
    let ignore: Vec<f32> = (0..case.observed.len() / channels)
        .map(|i| ((i % w) * 5 / w == 2) as u32 as f32)
        .collect();
    vkdr::loss::mark_unknown(&mut case.observed, channels, &ignore).unwrap();
    case
}

/// The device's total loss of a case.
fn device_loss(case: &Case) -> f64 {
    let ctx = common::context();
    let renderer = DiffRenderer::new(&ctx).unwrap();
    let gpu = device_scene(&ctx, case).evaluate(&ctx, &renderer).unwrap();
    gpu.loss.iter().map(|&l| l as f64).sum()
}

#[test]
fn unknown_pixels_count_for_nothing() {
    // The loss and its gradients over the known pixels only, exact at the band's borders
    // (an antialiased pixel beside it still counts), for every loss and with depth.
    for case in [
        sphere_case(Loss::Mse, 0.1, 0.45, 48),
        sphere_case(Loss::Iou, 0.1, 0.45, 48),
        sphere_case(Loss::Distance, 0.1, 0.45, 48),
        with_depth(sphere_case(Loss::Mse, 0.1, 0.45, 48)),
    ] {
        let hidden = with_unknown_band(case.clone());
        let (all, part) = (device_loss(&case), device_loss(&hidden));
        assert!(
            (all - part).abs() > 1e-3 * all.abs(),
            "{:?}: the band changed nothing ({all} and {part})",
            case.loss
        );
        assert_gradients_match(&hidden);
    }
}

#[test]
fn occluded_pixels_count_for_nothing() {
    // The observed depth is a plane in front of much of the sphere; where the disc mask
    // is 0 and the plane is more than 1 cm nearer than the rendered surface, the plane
    // hides the sphere: those pixels count for nothing, and the gradients stay exact.
    let plain = with_depth(sphere_case(Loss::Mse, 0.1, 0.45, 48));
    let mut occluded = plain.clone();
    if let Some((_, loss)) = occluded.depth.as_mut() {
        loss.occlusion = 0.01;
    }
    let (all, part) = (device_loss(&plain), device_loss(&occluded));
    assert!(
        part < all - 1e-3 * all,
        "occlusion dropped no pixel ({all} and {part})"
    );
    assert_gradients_match(&occluded);
}

#[test]
fn mask_with_depth() {
    let case = with_depth(sphere_case(Loss::Mse, 0.1, 0.45, 64));
    let (_, gpu) = check(&case);
    // The compared image holds coverage and the depth of the sphere's front.
    let depths: Vec<f32> = gpu.antialiased.chunks(2).map(|c| c[1]).collect();
    let covered = depths.iter().filter(|&&z| z > 0.0).count();
    assert!(covered > 500, "{covered} pixels with depth");
    assert!(depths.iter().all(|&z| z == 0.0 || (0.3..0.5).contains(&z)));
    let report = assert_gradients_match(&case);
    assert!(report.loss > 0.0);
}

#[test]
fn depth_term_alone_has_the_same_gradients() {
    // A mask equal to the rendering's coverage leaves (almost) only the depth term.
    let case = with_depth(sphere_case(Loss::Mse, 0.1, 0.45, 48));
    let ctx = common::context();
    let renderer = DiffRenderer::new(&ctx).unwrap();
    let ids = device_scene(&ctx, &case)
        .evaluate(&ctx, &renderer)
        .unwrap()
        .ids;
    let mut matched = case.clone();
    matched.observed = ids.iter().map(|&id| (id > 0) as u32 as f32).collect();
    assert_gradients_match(&matched);
}

#[test]
fn shading_with_depth_in_two_views() {
    let mut case = grey_disc_case(2);
    case = with_depth(case);
    assert_gradients_match(&case);
}

#[test]
fn depth_needs_the_mse_loss_and_valid_depths() {
    let ctx = common::context();
    let case = with_depth(sphere_case(Loss::Iou, 0.1, 0.45, 32));
    let Err(e) = Scene::new(
        &ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh: &case.mesh,
            views: &case.views,
            loss: case.loss,
            observed: &case.observed,
            attributes: None,
            shading: None,
            depth: case
                .depth
                .as_ref()
                .map(|(depth, loss)| ObservedDepth { depth, loss: *loss }),
        },
    ) else {
        panic!("iou with depth was accepted");
    };
    assert!(e.to_string().contains("mse with depth"), "{e}");
    let mut bad = with_depth(sphere_case(Loss::Mse, 0.1, 0.45, 32));
    bad.depth.as_mut().unwrap().0[5] = -1.0;
    let Err(e) = Scene::new(
        &ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh: &bad.mesh,
            views: &bad.views,
            loss: bad.loss,
            observed: &bad.observed,
            attributes: None,
            shading: None,
            depth: bad
                .depth
                .as_ref()
                .map(|(depth, loss)| ObservedDepth { depth, loss: *loss }),
        },
    ) else {
        panic!("a negative depth was accepted");
    };
    assert!(e.to_string().contains("observed depth holds -1"), "{e}");
}

#[test]
fn triangles_much_smaller_than_a_pixel() {
    // 1200 triangles on a sphere about 14 pixels across.
    let mut case = sphere_case(Loss::Mse, 0.1, 1.5, 24);
    case.mesh = Mesh::uv_sphere(0.1, 24, 26);
    assert_gradients_match(&case);
}

#[test]
fn sliver_triangle() {
    // A quad split into a regular triangle and a sliver 1e-3 of its width.
    let mesh = Mesh::new(
        vec![
            [-0.1, -0.1, 0.0],
            [0.1, -0.1, 0.0],
            [0.1, 0.1, 0.0],
            [-0.1, 0.1, 0.0],
            [-0.0998, 0.1, 0.0],
        ],
        vec![[0, 1, 2], [0, 2, 4], [0, 4, 3]],
    )
    .unwrap();
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.mesh = mesh;
    assert_gradients_match(&case);
}

#[test]
fn triangle_crossing_near_plane() {
    // A floor-like quad from 0.1 m to 3 m in front of the camera and 0.5 m behind it.
    let mesh = Mesh::new(
        vec![
            [-0.3, 0.15, -0.5],
            [0.3, 0.15, -0.5],
            [0.25, 0.1, 3.0],
            [-0.35, 0.1, 3.0],
        ],
        vec![[0, 1, 2], [0, 2, 3]],
    )
    .unwrap();
    let mut cam = camera(64);
    cam.near = 0.05;
    let case = Case {
        mesh,
        views: vec![View {
            camera: cam,
            pose: Pose::new([0.02, 0.0, 0.0], [0.05, 0.1, 0.0]).unwrap(),
        }],
        loss: Loss::Mse,
        observed: disc(64, 64, 30.0, 40.0, 15.0),
        attributes: None,
        shading: None,
        depth: None,
    };
    assert_gradients_match(&case);
}

#[test]
fn object_partly_outside_the_image() {
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.views[0].pose.translation.x = 0.12;
    assert_gradients_match(&case);
}

#[test]
fn object_entirely_outside_the_image_has_zero_gradient() {
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.views[0].pose.translation.x = 2.0;
    let (report, gpu) = check(&case);
    assert!(gpu.vertex_gradient.iter().flatten().all(|&g| g == 0.0));
    assert!(gpu.pose_gradient.iter().flatten().all(|&g| g == 0.0));
    assert_eq!(report.vertex_norm, 0.0);
    assert!(
        report.loss > 0.0,
        "the observed disc is still there: {report:?}"
    );
}

/// A sphere of radius 0.06 in front of one of 0.1 (both `rings` x `segments`, each
/// triangle cut into 4^`times`), seen as in [`sphere_case`].
fn occluder_case(rings: u32, segments: u32, times: usize) -> Case {
    let front = subdivided(&Mesh::uv_sphere(0.06, rings, segments), times);
    let back = subdivided(&Mesh::uv_sphere(0.1, rings, segments), times);
    let offset = front.vertex_count() as u32;
    let positions = front
        .positions()
        .iter()
        .map(|p| [p[0] + 0.05, p[1] + 0.02, p[2] - 0.12])
        .chain(back.positions().iter().copied())
        .collect();
    let triangles = front
        .triangles()
        .iter()
        .copied()
        .chain(back.triangles().iter().map(|t| t.map(|v| v + offset)))
        .collect();
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.mesh = Mesh::new(positions, triangles).unwrap();
    case
}

#[test]
fn one_surface_occluding_another() {
    assert_gradients_match(&occluder_case(6, 9, 0));
}

#[test]
fn duplicated_vertices() {
    // Every triangle with its own three vertices: no shared edges, every edge a boundary.
    let welded = Mesh::uv_sphere(0.1, 6, 9);
    let positions = welded
        .triangles()
        .iter()
        .flat_map(|t| t.map(|v| welded.positions()[v as usize]))
        .collect();
    let triangles = (0..welded.triangle_count() as u32)
        .map(|t| [3 * t, 3 * t + 1, 3 * t + 2])
        .collect();
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.mesh = Mesh::new(positions, triangles).unwrap();
    assert_gradients_match(&case);
}

#[test]
fn object_of_one_millimetre() {
    assert_gradients_match(&sphere_case(Loss::Mse, 0.0005, 0.00225, 64));
}

#[test]
fn object_of_one_kilometre() {
    assert_gradients_match(&sphere_case(Loss::Mse, 500.0, 2250.0, 64));
}

#[test]
fn several_views_in_one_submission() {
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 48);
    add_second_view(&mut case);
    assert_gradients_match(&case);
}

/// The device's loss, pose gradient and the derivative along a stretch of the mesh
/// (x_v (1 + e) along the object's x axis: sum over vertices of dL/dx_v x_v), which are
/// properties of the surface, not of its tessellation.
fn surface_quantities(case: &Case) -> (f64, Vec<f64>, f64) {
    let ctx = common::context();
    let renderer = DiffRenderer::new(&ctx).expect("diff renderer");
    let mut scene = device_scene(&ctx, case);
    let gpu = scene.evaluate(&ctx, &renderer).expect("evaluate");
    common::assert_no_validation_errors(&ctx);
    let loss = gpu.loss.iter().map(|&l| l as f64).sum();
    let pose = gpu.pose_gradient[0].iter().map(|&g| g as f64).collect();
    let stretch = gpu
        .vertex_gradient
        .iter()
        .zip(case.mesh.positions())
        .map(|(g, p)| g[0] as f64 * p[0] as f64)
        .sum();
    (loss, pose, stretch)
}

/// Asserts that `fine`, the surface of `coarse` cut into many more (sub-pixel) triangles,
/// has the same loss, pose gradient and stretch derivative: silhouette gradients that do
/// not depend on tessellation. (The old walk of at most 8 triangles lost most crossings
/// here.)
fn assert_same_surface_gradients(coarse: &Case, fine: &Case) {
    let (loss_c, pose_c, stretch_c) = surface_quantities(coarse);
    let (loss_f, pose_f, stretch_f) = surface_quantities(fine);
    eprintln!(
        "{} -> {} triangles: loss {loss_c} / {loss_f}, pose {pose_c:?} / {pose_f:?}, stretch {stretch_c} / {stretch_f}",
        coarse.mesh.triangle_count(),
        fine.mesh.triangle_count()
    );
    assert!(
        (loss_c - loss_f).abs() <= 1e-4 * loss_c,
        "loss {loss_c} / {loss_f}"
    );
    let (pose_error, pose_norm) = relative_error(&pose_f, &pose_c);
    assert!(pose_norm > 0.0, "vacuous: zero pose gradient");
    assert!(pose_error <= 2e-3, "pose gradient {pose_c:?} / {pose_f:?}");
    assert!(stretch_c != 0.0, "vacuous: zero stretch derivative");
    assert!(
        (stretch_c - stretch_f).abs() <= 2e-3 * stretch_c.abs(),
        "stretch derivative {stretch_c} / {stretch_f}"
    );
}

/// The mesh with every triangle cut into 4^`times` (the surface unchanged).
fn subdivided(mesh: &Mesh, times: usize) -> Mesh {
    (0..times).fold(mesh.clone(), |m, _| m.subdivided())
}

#[test]
fn dense_sphere_with_sub_pixel_rim_triangles() {
    // 28 800 triangles on a sphere 40 pixels across: near the rim, seen edge-on, a dozen
    // or more triangles lie between two pixel centres (the old 8-step walk lost them).
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    case.mesh = Mesh::uv_sphere(0.1, 120, 121);
    let (report, _) = check_subset(&case);
    assert!(report.vertex_error <= TOLERANCE, "{report:?}");
    assert!(report.translation_error <= TOLERANCE, "{report:?}");
    // A sphere's rotation gradient is nearly zero (0.001 against 3.7 for translation):
    // compare its error with what the translation gradient moves over the radius.
    assert!(
        report.rotation_error * report.rotation_norm <= TOLERANCE * 0.1 * report.translation_norm,
        "{report:?}"
    );
}

#[test]
fn a_subdivided_sphere_has_the_same_gradients() {
    // 96 flat faces, then each cut into 1024 (98 304 triangles, most far below a pixel):
    // the same surface, so the same silhouette.
    let coarse = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    let mut fine = sphere_case(Loss::Mse, 0.1, 0.45, 64);
    fine.mesh = subdivided(&coarse.mesh, 5);
    assert_same_surface_gradients(&coarse, &fine);
}

#[test]
fn one_silhouette_edge_behind_many_sub_pixel_triangles() {
    // A flat square facing the camera whose right edge is one long boundary edge; left of
    // it, `strips` strips 1e-5 m wide (about 1/400 of a pixel each), so that every walk
    // from a covered pixel to the right edge crosses hundreds of triangles.
    let square = |strips: u32| {
        let width = 1e-5f32;
        let mut positions = vec![[-0.1, -0.1, 0.0], [-0.1, 0.1, 0.0]];
        for k in 0..=strips {
            let x = 0.1 - (strips - k) as f32 * width;
            positions.push([x, -0.1, 0.0]);
            positions.push([x, 0.1, 0.0]);
        }
        // Counter-clockwise seen from -z (the camera looks along +z).
        let mut triangles = vec![[0, 1, 2], [1, 3, 2]];
        for k in 0..strips {
            let (b, t, nb, nt) = (2 + 2 * k, 3 + 2 * k, 4 + 2 * k, 5 + 2 * k);
            triangles.push([b, t, nb]);
            triangles.push([t, nt, nb]);
        }
        let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 64);
        case.mesh = Mesh::new(positions, triangles).unwrap();
        case.views[0].pose = Pose::new([0.01, -0.005, 0.45], [0.1, 0.2, 0.05]).unwrap();
        case
    };
    let fine = square(200);
    assert_gradients_match(&fine);
    assert_same_surface_gradients(&square(0), &fine);
}

#[test]
fn dense_occluder_in_front_of_a_dense_sphere() {
    let scene = |times| occluder_case(8, 12, times);
    let fine = scene(3);
    let (report, _) = check_subset(&fine);
    assert_report_within_tolerance(&report);
    assert_same_surface_gradients(&scene(0), &fine);
}

/// A 1280 x 1280 view of four attribute channels, the sphere larger than the image: over
/// 1e6 listed pixels, every one of them reached by the passes over the list (a device that
/// ends a loop early is caught: `Scene::check_walks`), and the loss and gradients match
/// the float64 model as at 64 px.
#[test]
fn every_listed_pixel_of_a_large_image_is_reached() {
    let size = 1280;
    let mut case = sphere_case(Loss::Mse, 0.1, 0.24, size);
    let channels = 4;
    let attributes: Vec<f32> = case
        .mesh
        .positions()
        .iter()
        .flat_map(|p| (0..channels).map(move |c| 0.5 + (c as f32 + 1.0) * p[c % 3]))
        .collect();
    let mask = case.observed.clone();
    case.observed = mask
        .iter()
        .flat_map(|&m| (0..channels).map(move |c| m * (0.1 + 0.1 * c as f32)))
        .collect();
    case.attributes = Some((attributes, channels as u32));
    // Steps of 1e-8: the finer the pixel grid, the more often a silhouette vertex lies
    // within a step of 1e-6 (1e-3 px here) of a line between pixel centres, where the
    // loss has a kink that a central difference straddles.
    let (report, gpu) = check_vertices(&case, Vertices::Every(5), 1e-8);
    let listed = gpu.ids.iter().filter(|&&id| id != 0).count();
    assert!(listed > 1_000_000, "only {listed} pixels covered");
    assert_report_within_tolerance(&report);
}

#[test]
fn images_past_the_storage_buffer_range_are_refused() {
    let ctx = common::context();
    let range = ctx.info().max_storage_buffer_range as u64;
    // The smallest square whose one-float-per-pixel image exceeds the range.
    let side = ((range / 4) as f64).sqrt() as u32 + 1;
    let mut case = sphere_case(Loss::Mse, 0.1, 0.45, 16);
    case.views[0].camera = camera(side);
    let observed = vec![0.0f32; side as usize * side as usize];
    let result = Scene::new(
        &ctx,
        &SceneDesc {
            loss_pixels: None,
            mesh: &case.mesh,
            views: &case.views,
            loss: Loss::Mse,
            observed: &observed,
            attributes: None,
            shading: None,
            depth: None,
        },
    );
    match result {
        Err(vkdr::Error::Limit(message)) => {
            eprintln!("{message}");
            assert!(message.contains(&format!("{side} x {side}")), "{message}");
        }
        Err(e) => panic!("expected a device-limit error, got {e}"),
        Ok(_) => panic!("a {side} x {side} scene past the storage buffer range was accepted"),
    }
    common::assert_no_validation_errors(&ctx);
}

/// dL/dtz and the stretch derivative of `case` on the device against central differences
/// of re-rendered device losses (tz +- `h` metres; x (1 +- `e`)): visibility re-rasterized
/// too, as a user's finite differences would see it. Returns the two relative errors.
fn errors_against_re_rendered(case: &Case, h: f64, e: f32) -> (f64, f64) {
    let (_, pose, stretch) = surface_quantities(case);
    let moved = |dz: f64| {
        let mut c = case.clone();
        c.views[0].pose.translation.z += dz;
        surface_quantities(&c).0
    };
    let fd_tz = (moved(h) - moved(-h)) / (2.0 * h);
    let stretched = |e: f32| {
        let mut c = case.clone();
        let positions = case
            .mesh
            .positions()
            .iter()
            .map(|&[x, y, z]| [x * (1.0 + e), y, z])
            .collect();
        c.mesh = Mesh::new(positions, case.mesh.triangles().to_vec()).unwrap();
        surface_quantities(&c).0
    };
    let fd_stretch = (stretched(e) - stretched(-e)) / (2.0 * e as f64);
    let error = |got: f64, want: f64| {
        assert!(want != 0.0, "vacuous: zero central difference");
        (got - want).abs() / want.abs()
    };
    eprintln!(
        "{} triangles at {} px: dL/dtz {} vs {fd_tz}, stretch {stretch} vs {fd_stretch}",
        case.mesh.triangle_count(),
        case.views[0].camera.width,
        pose[2]
    );
    (error(pose[2], fd_tz), error(stretch, fd_stretch))
}

#[test]
fn dense_spheres_match_re_rendered_central_differences() {
    // UV spheres of 2e3 to 2e6 triangles, 75 pixels across at 128 x 128 and 150 at 256 x
    // 256: on the dense ones the rim's triangles are far thinner than float32 resolves
    // between two pixel centres. A walk that compared rounded crossing parameters lost
    // its way there and dropped crossings (errors 3% and 6% at 5e5 triangles, 9% and 11%
    // at 2e6; about 1.5% now).
    for (rings, segments, size) in [(24, 40, 128), (400, 640, 128), (790, 1264, 256)] {
        let mut case = sphere_case(Loss::Mse, 0.1, 0.45, size);
        case.mesh = Mesh::uv_sphere(0.1, rings, segments);
        // A disc smaller than the sphere, so that both derivatives are large.
        let s = size as f64 / 128.0;
        case.observed = disc(size, size, 70.0 * s, 58.0 * s, 28.0 * s);
        let (dtz, stretch) = errors_against_re_rendered(&case, 2e-3, 3e-3);
        assert!(
            dtz <= 0.05 && stretch <= 0.05,
            "dL/dtz error {dtz}, stretch error {stretch}"
        );
    }
}

/// A scene evaluated on a region of interest cut out of its image (the camera's principal
/// point moved by the region's corner, the loss averaged over the whole image's pixels, as
/// `register` cuts it) has the whole image's loss and gradients within float rounding,
/// where the region holds the mask and the silhouette.
fn assert_region_matches_whole(case: &Case) {
    let ctx = common::context();
    let renderer = DiffRenderer::new(&ctx).unwrap();
    let whole = device_scene(&ctx, case).evaluate(&ctx, &renderer).unwrap();
    let camera = case.views[0].camera;
    let (w, h) = (camera.width, camera.height);
    // The box of the mask and of the rendered silhouette, 3 pixels wider.
    let (mut lo, mut hi) = ((w, h), (0, 0));
    for i in 0..(w * h) as usize {
        if case.observed[i] > 0.0 || whole.ids[i] > 0 {
            let (x, y) = (i as u32 % w, i as u32 / w);
            lo = (lo.0.min(x), lo.1.min(y));
            hi = (hi.0.max(x), hi.1.max(y));
        }
    }
    let region = vkdr::register::Region {
        x: lo.0.saturating_sub(3),
        y: lo.1.saturating_sub(3),
        width: (hi.0 + 4).min(w) - lo.0.saturating_sub(3),
        height: (hi.1 + 4).min(h) - lo.1.saturating_sub(3),
        step: 1,
        depth_step: 1,
    };
    assert!(region.width * region.height < w * h * 3 / 4, "{region:?}");
    let observed = region.crop(&case.observed, w);
    let depth = case.depth.as_ref().map(|(d, l)| (region.crop(d, w), *l));
    let views = [View {
        camera: region.camera(&camera),
        pose: case.views[0].pose,
    }];
    let cut = Scene::new(
        &ctx,
        &SceneDesc {
            mesh: &case.mesh,
            views: &views,
            loss: case.loss,
            observed: &observed,
            attributes: None,
            shading: None,
            depth: depth
                .as_ref()
                .map(|(depth, loss)| ObservedDepth { depth, loss: *loss }),
            loss_pixels: Some(w as u64 * h as u64),
        },
    )
    .unwrap()
    .evaluate(&ctx, &renderer)
    .unwrap();
    let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-4 * scale + 1e-12;
    assert!(
        close(
            cut.loss[0] as f64,
            whole.loss[0] as f64,
            whole.loss[0].abs() as f64
        ),
        "loss {} on the region, {} on the whole image",
        cut.loss[0],
        whole.loss[0]
    );
    let flat = |g: &[[f32; 3]]| g.iter().flatten().map(|&v| v as f64).collect::<Vec<_>>();
    let (got, want) = (flat(&cut.vertex_gradient), flat(&whole.vertex_gradient));
    let norm = want.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(norm > 0.0);
    let difference = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        difference <= 1e-4 * norm,
        "vertex gradients differ by {difference:e} of {norm:e}"
    );
    let (a, b) = (cut.pose_gradient[0], whole.pose_gradient[0]);
    let pose_norm = b.iter().map(|&v| (v as f64).powi(2)).sum::<f64>().sqrt();
    for k in 0..6 {
        assert!(
            close(a[k] as f64, b[k] as f64, pose_norm),
            "pose gradient {k}: {} on the region, {} on the whole image",
            a[k],
            b[k]
        );
    }
}

#[test]
fn a_region_of_interest_has_the_whole_image_s_loss_and_gradients() {
    for loss in [Loss::Mse, Loss::Distance, Loss::Iou] {
        assert_region_matches_whole(&sphere_case(loss, 0.06, 0.5, 128));
    }
    assert_region_matches_whole(&with_depth(sphere_case(Loss::Mse, 0.06, 0.5, 128)));
}
