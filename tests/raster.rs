//! The forward rasterizer against the CPU float64 reference (`raster::reference`).
//!
//! Tolerances: ids are compared exactly on every pixel whose centre lies farther than
//! 2^-subPixelPrecisionBits pixels from every projected edge (closer pixels depend on the
//! device's vertex snapping). Barycentrics (interpolated perspective-correctly by the
//! device) are compared within 1e-4 absolute and depth within 1e-5 relative, on pixels
//! of triangles no smaller than a few pixels: at that size the snapping of vertices to
//! 2^-8 px moves a weight by less than 1e-4.

mod common;

use vkdr::raster::reference::{self, ReferenceGbuffer};
use vkdr::raster::{GbufferData, Outputs, Rasterizer, View};
use vkdr::{Camera, Mesh, Pose};

const BARY_TOLERANCE: f64 = 1e-4;
const DEPTH_RELATIVE_TOLERANCE: f64 = 1e-5;

/// What a comparison looked at, so tests can insist it was not vacuous.
#[derive(Debug, Default)]
struct Compared {
    pixels: usize,
    covered: usize,
    skipped_near_edges: usize,
}

/// Compares view `layer` of `gpu` against the reference; panics with the first mismatch.
fn compare(gpu: &GbufferData, layer: usize, expected: &ReferenceGbuffer, margin: f64) -> Compared {
    let mut seen = Compared::default();
    let depth = gpu.depth.as_ref().expect("rendered with depth");
    for i in 0..expected.height {
        for j in 0..expected.width {
            let k = i * expected.width + j;
            if expected.edge_distance[k] <= margin {
                seen.skipped_near_edges += 1;
                continue;
            }
            seen.pixels += 1;
            let id = gpu.ids[[layer, i, j]];
            assert_eq!(
                id, expected.ids[k],
                "view {layer} pixel ({i}, {j}): triangle id + 1"
            );
            if id == 0 {
                assert_eq!(depth[[layer, i, j]], 0.0, "background depth at ({i}, {j})");
                continue;
            }
            seen.covered += 1;
            let b = expected.bary[k];
            let bary = gpu.bary.as_ref().expect("rendered with barycentrics");
            for c in 0..2 {
                let got = bary[[layer, i, j, c]] as f64;
                assert!(
                    (got - b[c]).abs() <= BARY_TOLERANCE,
                    "view {layer} pixel ({i}, {j}): barycentric {c} is {got}, reference {}",
                    b[c]
                );
            }
            let got = depth[[layer, i, j]] as f64;
            let want = expected.depth[k];
            assert!(
                (got - want).abs() <= DEPTH_RELATIVE_TOLERANCE * want.abs(),
                "view {layer} pixel ({i}, {j}): depth {got}, reference {want}"
            );
        }
    }
    seen
}

fn margin(ctx: &vkdr::gpu::Context) -> f64 {
    (-(ctx.info().sub_pixel_precision_bits as f64)).exp2()
}

fn check_views(mesh: &Mesh, views: &[View]) -> Vec<Compared> {
    let ctx = common::context();
    let rasterizer = Rasterizer::new(&ctx).expect("rasterizer");
    let gpu = rasterizer
        .render(&ctx, mesh, views, Outputs::IdsBaryDepth)
        .expect("render");
    // The ids-only pass (one indexed draw, ids from the provoking vertex) covers exactly the
    // same pixels with the same triangles as the non-indexed one.
    let ids_only = rasterizer
        .render(&ctx, mesh, views, Outputs::Ids)
        .expect("render ids");
    assert!(
        ids_only.ids == gpu.ids,
        "ids-only and full G-buffer ids differ"
    );
    let seen = views
        .iter()
        .enumerate()
        .map(|(layer, view)| {
            let expected = reference::rasterize(mesh, &view.camera, &view.pose);
            compare(&gpu, layer, &expected, margin(&ctx))
        })
        .collect();
    common::assert_no_validation_errors(&ctx);
    seen
}

fn camera(width: u32, height: u32) -> Camera {
    Camera::new(
        1.1 * width as f64,
        1.1 * width as f64,
        width as f64 / 2.0 - 0.3,
        height as f64 / 2.0 + 0.2,
        width,
        height,
    )
    .unwrap()
}

#[test]
fn sphere_matches_reference() {
    let mesh = Mesh::uv_sphere(0.1, 12, 18);
    let pose = Pose::new([0.01, -0.02, 0.5], [0.3, -0.5, 0.2]).unwrap();
    let seen = check_views(
        &mesh,
        &[View {
            camera: camera(128, 96),
            pose,
        }],
    );
    assert!(seen[0].covered > 1000, "{seen:?}");
    assert!(seen[0].pixels > seen[0].skipped_near_edges, "{seen:?}");
}

/// Views beyond one submission's chunk (`RENDER_CHUNK`, and a partial last chunk): each
/// matches the CPU reference, and the batch is each view rendered alone, byte for byte.
#[test]
fn several_views_in_one_submission() {
    let mesh = Mesh::uv_sphere(0.1, 10, 14);
    let count = vkdr::raster::RENDER_CHUNK + 3;
    let views: Vec<View> = (0..count)
        .map(|k| View {
            camera: camera(96, 96),
            pose: Pose::new(
                [0.01 * k as f64 - 0.05, 0.01, 0.4 + 0.02 * k as f64],
                [0.4 * k as f64, 0.2, -0.1],
            )
            .unwrap(),
        })
        .collect();
    let seen = check_views(&mesh, &views);
    for s in &seen {
        assert!(s.covered > 300, "{seen:?}");
    }
    let ctx = common::context();
    let rasterizer = Rasterizer::new(&ctx).unwrap();
    let all = rasterizer
        .render(&ctx, &mesh, &views, Outputs::IdsBaryDepth)
        .unwrap();
    for (k, view) in views.iter().enumerate() {
        let alone = rasterizer
            .render(&ctx, &mesh, &[*view], Outputs::IdsBaryDepth)
            .unwrap();
        let one = ndarray::s![k..k + 1, .., ..];
        assert!(all.ids.slice(one) == alone.ids, "view {k}: ids");
        assert!(
            all.depth.as_ref().unwrap().slice(one) == alone.depth.unwrap(),
            "view {k}: depth"
        );
        let bary = ndarray::s![k..k + 1, .., .., ..];
        assert!(
            all.bary.as_ref().unwrap().slice(bary) == alone.bary.unwrap(),
            "view {k}: bary"
        );
    }
}

/// One triangle from 0.2 m in front of the camera to 0.3 m behind it.
#[test]
fn triangle_crossing_near_plane() {
    let mesh = Mesh::new(
        vec![[-0.05, 0.02, 0.2], [0.06, 0.03, 0.2], [0.0, 0.01, -0.3]],
        vec![[0, 1, 2]],
    )
    .unwrap();
    let mut cam = camera(128, 128);
    cam.near = 0.01;
    let seen = check_views(
        &mesh,
        &[View {
            camera: cam,
            pose: Pose::at([0.0, 0.0, 0.0]),
        }],
    );
    assert!(seen[0].covered > 500, "{seen:?}");
}

#[test]
fn triangle_entirely_behind_camera() {
    let mesh = Mesh::new(
        vec![[-0.1, -0.1, -0.5], [0.1, -0.1, -0.5], [0.0, 0.1, -0.5]],
        vec![[0, 1, 2]],
    )
    .unwrap();
    let seen = check_views(
        &mesh,
        &[View {
            camera: camera(64, 64),
            pose: Pose::at([0.0, 0.0, 0.0]),
        }],
    );
    assert_eq!(seen[0].covered, 0);
    assert_eq!(
        seen[0].pixels,
        64 * 64,
        "nothing is near an edge: every pixel is compared"
    );
}

#[test]
fn empty_view() {
    // The sphere is beside the camera's field of view.
    let mesh = Mesh::uv_sphere(0.1, 8, 12);
    let seen = check_views(
        &mesh,
        &[View {
            camera: camera(64, 64),
            pose: Pose::at([2.0, 0.0, 0.5]),
        }],
    );
    assert_eq!(seen[0].covered, 0);
    assert_eq!(seen[0].pixels, 64 * 64);
}

/// Two overlapping triangles, listed far-then-near and near-then-far: the nearer one wins
/// regardless of drawing order.
#[test]
fn overlapping_triangles_nearer_wins() {
    let far = [[-0.1f32, -0.1, 0.6], [0.1, -0.1, 0.6], [0.0, 0.1, 0.6]];
    let near = [[-0.1f32, 0.1, 0.5], [0.1, 0.1, 0.5], [0.0, -0.1, 0.45]];
    for (first, second, near_id) in [(far, near, 2u32), (near, far, 1u32)] {
        let positions = first.iter().chain(second.iter()).copied().collect();
        let mesh = Mesh::new(positions, vec![[0, 1, 2], [3, 4, 5]]).unwrap();
        let view = View {
            camera: camera(96, 96),
            pose: Pose::at([0.0, 0.0, 0.0]),
        };
        let seen = check_views(&mesh, &[view]);
        assert!(seen[0].covered > 1000, "{seen:?}");
        // The centre is covered by both; the nearer must be there.
        let ctx = common::context();
        let gpu = Rasterizer::new(&ctx)
            .unwrap()
            .render(&ctx, &mesh, &[view], Outputs::Ids)
            .unwrap();
        assert_eq!(gpu.ids[[0, 48, 48]], near_id);
        common::assert_no_validation_errors(&ctx);
    }
}

/// A grid of 2 x 4096 x 2060 > 2^24 triangles, seen from close up at its last rows, so that
/// visible ids are above 2^24 (where float32 cannot hold every integer), drawn in several
/// chunks on devices whose storage buffer range is smaller than the index buffer.
#[test]
fn more_than_2_pow_24_triangles_have_exact_ids() {
    let (nx, ny) = (4096u32, 2060u32);
    let spacing = 0.01f32;
    let grid = Mesh::grid(nx, ny, spacing);
    assert!(grid.triangle_count() > 1 << 24);
    // Put the grid's last corner at the origin so float32 coordinates stay small there.
    let (_, hi) = grid.bounds();
    let positions = grid
        .positions()
        .iter()
        .map(|p| [p[0] - hi[0], p[1] - hi[1], p[2]])
        .collect();
    let mesh = Mesh::new(positions, grid.triangles().to_vec()).unwrap();
    let camera = Camera::new(80.0, 80.0, 40.0, 40.0, 64, 64).unwrap();
    let pose = Pose::new([0.12, 0.12, 0.5], [0.1, -0.05, 0.02]).unwrap();
    let seen = check_views(&mesh, &[View { camera, pose }]);
    assert!(seen[0].covered > 500, "{seen:?}");

    let ctx = common::context();
    let gpu = Rasterizer::new(&ctx)
        .unwrap()
        .render(&ctx, &mesh, &[View { camera, pose }], Outputs::Ids)
        .unwrap();
    let above = gpu
        .ids
        .iter()
        .filter(|&&id| id > (1 << 24) && id % 2 == 1)
        .count();
    assert!(above > 100, "only {above} pixels show odd ids above 2^24");
    common::assert_no_validation_errors(&ctx);
}

#[test]
fn image_of_4096_by_4096() {
    let mesh = Mesh::new(
        vec![
            [-0.1, -0.1, 0.0],
            [0.1, -0.1, 0.0],
            [0.1, 0.1, 0.0],
            [-0.1, 0.1, 0.0],
        ],
        vec![[0, 1, 2], [0, 2, 3]],
    )
    .unwrap();
    let pose = Pose::new([0.0, 0.0, 0.5], [0.2, 0.3, 0.1]).unwrap();
    let seen = check_views(
        &mesh,
        &[View {
            camera: camera(4096, 4096),
            pose,
        }],
    );
    assert!(seen[0].covered > 1_000_000, "{seen:?}");
}

#[test]
fn mismatched_camera_size_is_an_error() {
    let ctx = common::context();
    let rasterizer = Rasterizer::new(&ctx).unwrap();
    let mesh = Mesh::uv_sphere(0.1, 6, 8);
    let views = [
        View {
            camera: camera(64, 64),
            pose: Pose::at([0.0, 0.0, 0.5]),
        },
        View {
            camera: camera(32, 64),
            pose: Pose::at([0.0, 0.0, 0.5]),
        },
    ];
    let err = rasterizer
        .render(&ctx, &mesh, &views, Outputs::Ids)
        .unwrap_err();
    assert!(err.to_string().contains("does not match"), "{err}");
    common::assert_no_validation_errors(&ctx);
}
