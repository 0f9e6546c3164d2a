//! Shape space: build from a generated category, round trip through its file, the oracle,
//! and refusal of corrupt files.

mod common;

use glam::DVec3;
use vkdr::cpd::{self, CpdParams, CpdPipelines};
use vkdr::shape::ShapeSpace;
use vkdr_app::dataset::{instance, Rng};
use vkdr_app::eval;

fn small_space(
    ctx: &vkdr::gpu::Context,
    training: usize,
    dims: usize,
) -> (ShapeSpace, Vec<(String, Vec<DVec3>)>) {
    let mut rng = Rng::new(3);
    let canonical = instance("bottle", &mut rng).unwrap();
    let train: Vec<(String, Vec<DVec3>)> = (0..training)
        .map(|i| {
            (
                format!("bottle_{i}"),
                instance("bottle", &mut rng).unwrap().points(),
            )
        })
        .collect();
    let params = CpdParams {
        max_iterations: 60,
        ..CpdParams::default()
    };
    let space = ShapeSpace::build(
        ctx,
        "bottle",
        &canonical,
        &train,
        dims,
        &params,
        |_, _, _| {},
    )
    .unwrap();
    (space, train)
}

#[test]
fn oracle_of_a_training_instance_reproduces_its_cpd_result() {
    let ctx = common::context();
    let (space, train) = small_space(&ctx, 4, 5);
    assert_eq!(
        space.dims(),
        3,
        "4 training instances support 3 dimensions, not 5"
    );
    let total: f64 = space.explained_variance.iter().sum();
    assert!(
        (total - 1.0).abs() < 1e-9,
        "all variance explained: {total}"
    );
    let params = CpdParams {
        max_iterations: 60,
        ..CpdParams::default()
    };
    let canonical = space.canonical.points();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    for (i, (_, target)) in train.iter().enumerate() {
        let code = space.oracle_code(&ctx, target, &params).unwrap();
        for (a, b) in code.iter().zip(&space.training_codes[i]) {
            assert!(
                (a - b).abs() <= 1e-6 * (1.0 + b.abs()),
                "code {code:?} vs {:?}",
                space.training_codes[i]
            );
        }
        let cpd_result = cpd::register(
            &ctx,
            &pipelines,
            &canonical,
            target,
            &params,
            &mut |_, _| {},
        )
        .unwrap();
        let from_space = space.vertices(&code).unwrap();
        let worst = from_space
            .iter()
            .zip(&cpd_result.deformed)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-6,
            "instance {i}: shape space and CPD differ by {worst} m"
        );
    }
    common::assert_no_validation_errors(&ctx);
}

#[test]
fn round_trips_through_its_file_and_refuses_corrupt_ones() {
    let ctx = common::context();
    let (space, _) = small_space(&ctx, 3, 2);
    let dir = std::env::temp_dir().join(format!("vkdr-shape-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bottle.npz");
    space.save(&path).unwrap();
    let loaded = ShapeSpace::load(&path).unwrap();
    // Every field comes back exactly: arrays, names, category.
    assert_eq!(loaded, space);
    assert_eq!(loaded.training_names.len(), 3);
    // The description is strict JSON.
    let description: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("bottle.npz.json")).unwrap())
            .unwrap();
    assert_eq!(description["training_names"].as_array().unwrap().len(), 3);
    let code = vec![0.3; space.dims()];
    let (a, b) = (
        space.vertices(&code).unwrap(),
        loaded.vertices(&code).unwrap(),
    );
    assert!(a.iter().zip(&b).all(|(p, q)| (*p - *q).length() < 1e-12));

    // The .npz alone is the space (its description inside).
    std::fs::rename(dir.join("bottle.npz.json"), dir.join("aside.json")).unwrap();
    assert_eq!(ShapeSpace::load(&path).unwrap(), space);
    // A file written before the description went inside: read with the .npz.json beside
    // it, whose version and shapes are checked.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, without_description(&bytes)).unwrap();
    assert!(ShapeSpace::load(&path).is_err(), "no description anywhere");
    std::fs::rename(dir.join("aside.json"), dir.join("bottle.npz.json")).unwrap();
    assert_eq!(ShapeSpace::load(&path).unwrap(), space);

    // A truncated archive.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    assert!(ShapeSpace::load(&path).is_err());
    std::fs::write(&path, &bytes).unwrap();
    // A description of another version or another shape.
    let json_path = dir.join("bottle.npz.json");
    let json = std::fs::read_to_string(&json_path).unwrap();
    std::fs::write(
        &json_path,
        json.replace("\"format_version\": 1", "\"format_version\": 99"),
    )
    .unwrap();
    let err = ShapeSpace::load(&path).unwrap_err().to_string();
    assert!(err.contains("version"), "{err}");
    std::fs::write(&json_path, json.replace("\"dims\": 2", "\"dims\": 4")).unwrap();
    let err = ShapeSpace::load(&path).unwrap_err().to_string();
    assert!(err.contains("dims"), "{err}");
    std::fs::write(&json_path, &json).unwrap();
    assert!(ShapeSpace::load(&path).is_ok());
    assert!(
        space.vertices(&[1.0]).is_err(),
        "a code of the wrong length is an error"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The arrays of a space's .npz without its `description`, as files were written before it.
fn without_description(bytes: &[u8]) -> Vec<u8> {
    use ndarray::{Array1, Array2};
    let mut npz = ndarray_npy::NpzReader::new(std::io::Cursor::new(bytes.to_vec())).unwrap();
    let mut out = Vec::new();
    {
        let mut writer = ndarray_npy::NpzWriter::new(std::io::Cursor::new(&mut out));
        for name in npz.names().unwrap() {
            let name = name.trim_end_matches(".npy").to_string();
            match name.as_str() {
                "description" => {}
                "canonical_faces" => {
                    let a: Array2<u32> = npz.by_name(&name).unwrap();
                    writer.add_array(name, &a).unwrap();
                }
                "beta" | "singular_values" | "explained_variance" => {
                    let a: Array1<f64> = npz.by_name(&name).unwrap();
                    writer.add_array(name, &a).unwrap();
                }
                _ => {
                    let a: Array2<f64> = npz.by_name(&name).unwrap();
                    writer.add_array(name, &a).unwrap();
                }
            }
        }
        writer.finish().unwrap();
    }
    out
}

/// A canonical of thousands of vertices (past where a dense M-step was feasible): the
/// space must still reproduce every training fit exactly from its code.
#[test]
fn a_large_canonical_reproduces_its_fits() {
    let ctx = common::context();
    let mut rng = Rng::new(4);
    let canonical = instance("bottle", &mut rng)
        .unwrap()
        .subdivided()
        .subdivided();
    assert!(canonical.vertex_count() > 2000);
    let train: Vec<(String, Vec<DVec3>)> = (0..3)
        .map(|i| {
            (
                format!("b{i}"),
                instance("bottle", &mut rng).unwrap().points(),
            )
        })
        .collect();
    let params = CpdParams {
        max_iterations: 30,
        ..CpdParams::default()
    };
    let space =
        ShapeSpace::build(&ctx, "bottle", &canonical, &train, 5, &params, |_, _, _| {}).unwrap();
    assert_eq!(space.dims(), 2);
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let c = canonical.points();
    for (i, (_, target)) in train.iter().enumerate() {
        let fit = cpd::register(&ctx, &pipelines, &c, target, &params, &mut |_, _| {}).unwrap();
        let from_space = space.vertices(&space.training_codes[i]).unwrap();
        let worst = from_space
            .iter()
            .zip(&fit.deformed)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        assert!(worst < 1e-6, "instance {i}: {worst} m");
    }
    common::assert_no_validation_errors(&ctx);
}

#[test]
fn the_space_optimum_finds_a_shape_of_the_space_and_never_loses_to_its_start() {
    let ctx = common::context();
    let (space, train) = small_space(&ctx, 4, 3);
    // A shape inside the space: its optimum is that code, at (almost) no error.
    let codes = &space.training_codes;
    let inside: Vec<f64> = (0..space.dims())
        .map(|i| 0.6 * codes[0][i] + 0.3 * codes[1][i])
        .collect();
    let mesh = space
        .canonical
        .with_points(&space.vertices(&inside).unwrap())
        .unwrap();
    let truth = eval::surface_sample(&mesh, 500, 7);
    let zero = vec![0.0; space.dims()];
    let start = eval::surface_error(
        &truth,
        &space.vertices(&zero).unwrap(),
        space.canonical.triangles(),
    );
    let eval::Optimum { code, error, scale } =
        eval::space_optimum(&space, &truth, &zero, 30, false).unwrap();
    assert_eq!(scale, 1.0);
    assert!(
        error < 1e-4 * start,
        "error {error} m from {start} m (code {code:?}, truth {inside:?})"
    );
    for (a, b) in code.iter().zip(&inside) {
        assert!(
            (a - b).abs() < 1e-3 * (1.0 + b.abs()),
            "code {code:?}, truth {inside:?}"
        );
    }
    // The same instance 1.2 times as large: the scale found with the code where it is free.
    let larger: Vec<_> = truth.iter().map(|p| *p * 1.2).collect();
    let free = eval::space_optimum(&space, &larger, &zero, 40, true).unwrap();
    assert!(
        (free.scale - 1.2).abs() < 1e-3 && free.error < 1e-3 * start,
        "scale {}, error {} m from {start} m",
        free.scale,
        free.error
    );
    // A training instance (not in the space exactly): never worse than its oracle code.
    let oracle = &space.training_codes[0];
    let target = space.canonical.with_points(&train[0].1).unwrap();
    let truth = eval::surface_sample(&target, 500, 8);
    let at_oracle = eval::surface_error(
        &truth,
        &space.vertices(oracle).unwrap(),
        space.canonical.triangles(),
    );
    let error = eval::space_optimum(&space, &truth, oracle, 30, false)
        .unwrap()
        .error;
    assert!(
        error <= at_oracle,
        "optimum {error} m, oracle {at_oracle} m"
    );
    common::assert_no_validation_errors(&ctx);
}
