//! Reproducible numerics: the same inputs on the same device give bit-identical outputs.
//! Every sum that threads add to in parallel is fixed point or in a fixed order
//! (`glsl/include/fixed_point.glsl`), so nothing depends on the order threads arrive in.
//! Each case runs twice in one process and compares every output bit for bit.

mod common;

use glam::DVec3;
use vkdr::cpd::CpdParams;
use vkdr::diff::{DiffRenderer, Evaluation, Scene, SceneDesc, Shading};
use vkdr::loss::Loss;
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::register::{Job, Optimizer, RegisterParams, Registrar, Registration};
use vkdr::shape::ShapeSpace;
use vkdr::{Camera, Mesh, Pose};
use vkdr_app::dataset::{instance, Rng};

fn bits(values: impl IntoIterator<Item = f32>) -> Vec<u32> {
    values.into_iter().map(f32::to_bits).collect()
}

fn evaluate(ctx: &vkdr::gpu::Context, desc: &SceneDesc) -> Evaluation {
    let renderer = DiffRenderer::new(ctx).unwrap();
    let mut scene = Scene::new(ctx, desc).unwrap();
    scene.evaluate(ctx, &renderer).unwrap()
}

#[test]
fn gradients_are_bit_identical_run_to_run() {
    let ctx = common::context();
    // A dense sphere (many silhouette pairs adding to the same vertices) in two views,
    // for every loss, and with shading (every covered pixel adds to its vertices).
    let mesh = Mesh::uv_sphere(0.1, 40, 48);
    let camera = Camera::new(170.0, 170.0, 61.0, 66.0, 128, 128).unwrap();
    let views = [
        View {
            camera,
            pose: Pose::new([0.01, -0.005, 0.45], [0.4, -0.3, 0.2]).unwrap(),
        },
        View {
            camera,
            pose: Pose::new([-0.02, 0.01, 0.5], [1.2, 0.3, -0.4]).unwrap(),
        },
    ];
    let disc: Vec<f32> = (0..2 * 128 * 128)
        .map(|i| {
            let (x, y) = ((i % 128) as f64 + 0.5, ((i / 128) % 128) as f64 + 0.5);
            if (x - 70.0).hypot(y - 60.0) < 35.0 {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    for (loss, shading) in [
        (Loss::Mse, None),
        (Loss::Iou, None),
        (Loss::Distance, None),
        (Loss::Mse, Some(Shading::default())),
    ] {
        let desc = SceneDesc {
            loss_pixels: None,
            mesh: &mesh,
            views: &views,
            loss,
            observed: &disc,
            attributes: None,
            shading,
            depth: None,
        };
        let (a, b) = (evaluate(&ctx, &desc), evaluate(&ctx, &desc));
        let name = format!("{} loss, shading {}", loss.name(), shading.is_some());
        assert!(
            a.vertex_gradient.iter().flatten().any(|&g| g != 0.0),
            "{name}: vacuous"
        );
        assert_eq!(bits(a.loss.clone()), bits(b.loss.clone()), "{name}: loss");
        assert_eq!(
            bits(a.vertex_gradient.iter().flatten().copied()),
            bits(b.vertex_gradient.iter().flatten().copied()),
            "{name}: vertex gradient"
        );
        assert_eq!(
            bits(a.pose_gradient.iter().flatten().copied()),
            bits(b.pose_gradient.iter().flatten().copied()),
            "{name}: pose gradient"
        );
        assert_eq!(
            bits(a.attribute_gradient.clone()),
            bits(b.attribute_gradient.clone()),
            "{name}: attribute gradient"
        );
        assert_eq!(
            bits(a.antialiased.clone()),
            bits(b.antialiased.clone()),
            "{name}: image"
        );
    }
    common::assert_no_validation_errors(&ctx);
}

fn space(ctx: &vkdr::gpu::Context) -> ShapeSpace {
    let mut rng = Rng::new(11);
    let canonical = instance("bottle", &mut rng).unwrap();
    let train: Vec<(String, Vec<DVec3>)> = (0..5)
        .map(|i| {
            (
                format!("b{i}"),
                instance("bottle", &mut rng).unwrap().points(),
            )
        })
        .collect();
    let params = CpdParams {
        max_iterations: 40,
        ..Default::default()
    };
    ShapeSpace::build(ctx, "bottle", &canonical, &train, 3, &params, |_, _, _| {}).unwrap()
}

fn same_registration(a: &Registration, b: &Registration, name: &str) {
    let f64_bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(f64_bits(&a.code), f64_bits(&b.code), "{name}: code");
    assert_eq!(f64_bits(&a.losses), f64_bits(&b.losses), "{name}: losses");
    let pose = |r: &Registration| {
        f64_bits(&[r.pose.translation.to_array(), r.pose.rotation.to_array()].concat())
    };
    assert_eq!(pose(a), pose(b), "{name}: pose");
    assert_eq!(a.evaluations, b.evaluations, "{name}: iterations");
    for (ca, cb) in a.codes.iter().zip(&b.codes) {
        assert_eq!(f64_bits(ca), f64_bits(cb), "{name}: codes per iteration");
    }
}

#[test]
fn registrations_are_bit_identical_run_to_run() {
    let ctx = common::context();
    let space = space(&ctx);
    let truth = space.training_codes[1].clone();
    let camera = Camera::new(260.0, 260.0, 64.0, 64.0, 128, 128).unwrap();
    let pose = Pose::new([0.0, 0.0, 0.6], [2.9, 0.3, 0.1]).unwrap();
    let mesh = space
        .canonical
        .with_points(&space.vertices(&truth).unwrap())
        .unwrap();
    let ids = Rasterizer::new(&ctx)
        .unwrap()
        .render(&ctx, &mesh, &[View { camera, pose }], Outputs::Ids)
        .unwrap()
        .ids;
    let observed: Vec<f32> = ids.iter().map(|&id| (id > 0) as u32 as f32).collect();
    let start = View {
        camera,
        pose: Pose::new([0.012, -0.01, 0.6], [2.95, 0.25, 0.12]).unwrap(),
    };
    let registrar = Registrar::new(&ctx).unwrap();
    for optimizer in [Optimizer::Bfgs, Optimizer::Sgd, Optimizer::Adam] {
        let params = RegisterParams {
            iterations: 24,
            pose_every: 3,
            align: 6,
            check_every: 6,
            optimizer,
            ..Default::default()
        };
        let run = || {
            registrar
                .register(&ctx, Job::new(&space, &observed, start), &params, |_, _| {})
                .unwrap()
        };
        let (a, b) = (run(), run());
        let name = format!("{optimizer:?}");
        assert!(a.losses.len() > 2, "{name}: vacuous");
        same_registration(&a, &b, &name);
    }
    common::assert_no_validation_errors(&ctx);
}
