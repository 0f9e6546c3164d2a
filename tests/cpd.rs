//! CPD on the device against the float64 reference (same algorithm, float64 E-step), on
//! a known smooth deformation, and on hard cases.

mod common;

use glam::DVec3;
use vkdr::cpd::{self, reference, CpdParams, CpdPipelines, CpdResult};

/// Deterministic points in [-0.5, 0.5]^3 scaled by `scale` (a 64-bit LCG).
fn points(count: usize, seed: u64, scale: f64) -> Vec<DVec3> {
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    (0..count)
        .map(|_| DVec3::new(next(), next(), next()) * scale)
        .collect()
}

fn smooth(p: DVec3, amount: f64) -> DVec3 {
    p + amount
        * DVec3::new(
            (2.0 * p.y).sin(),
            (1.5 * p.z).cos() - 1.0,
            0.5 * (p.x * p.y),
        )
}

fn extent(points: &[DVec3]) -> f64 {
    let (lo, hi) = points.iter().fold(
        (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN)),
        |(l, h), p| (l.min(*p), h.max(*p)),
    );
    (hi - lo).max_element()
}

fn gpu(source: &[DVec3], target: &[DVec3], params: &CpdParams) -> CpdResult {
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let result =
        cpd::register(&ctx, &pipelines, source, target, params, &mut |_, _| {}).expect("cpd");
    common::assert_no_validation_errors(&ctx);
    assert!(
        result
            .deformed
            .iter()
            .chain(&result.w)
            .all(|p| p.is_finite()),
        "non-finite result"
    );
    assert!(
        result.sigma2.iter().all(|s| s.is_finite() && *s > 0.0),
        "sigma^2 {:?}",
        result.sigma2
    );
    result
}

/// The largest entry difference of two matrices, and the largest entry of `want`.
fn worst_and_scale(
    got: &vkdr::cpd::linalg::Matrix,
    want: &vkdr::cpd::linalg::Matrix,
) -> (f64, f64) {
    let scale = want.data.iter().map(|v| v.abs()).fold(0.0, f64::max);
    let worst = got
        .data
        .iter()
        .zip(&want.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    (worst, scale)
}

fn max_difference(a: &[DVec3], b: &[DVec3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (*p - *q).length())
        .fold(0.0, f64::max)
}

/// Final points within 1e-4 of the set's extent of the float64 reference.
#[test]
fn device_matches_the_float64_reference() {
    let source = points(60, 1, 1.0);
    let target: Vec<DVec3> = points(75, 2, 1.0)
        .into_iter()
        .map(|p| smooth(p, 0.1))
        .collect();
    let params = CpdParams {
        beta: 0.5,
        max_iterations: 40,
        ..CpdParams::default()
    };
    let device = gpu(&source, &target, &params);
    let expected = reference::register(&source, &target, &params).unwrap();
    let bound = 1e-4 * extent(&target);
    let diff = max_difference(&device.deformed, &expected.deformed);
    assert!(
        diff <= bound,
        "device and reference differ by {diff} (bound {bound})"
    );
    assert_eq!(device.iterations, expected.iterations);
}

#[test]
fn recovers_a_known_smooth_deformation() {
    let source = points(300, 3, 1.0);
    let target: Vec<DVec3> = source.iter().map(|&p| smooth(p, 0.15)).collect();
    let params = CpdParams {
        beta: 0.5,
        lambda: 1.0,
        max_iterations: 150,
        ..CpdParams::default()
    };
    let result = gpu(&source, &target, &params);
    let before: f64 = source
        .iter()
        .zip(&target)
        .map(|(a, b)| (*a - *b).length())
        .sum::<f64>()
        / 300.0;
    let after: f64 = result
        .deformed
        .iter()
        .zip(&target)
        .map(|(a, b)| (*a - *b).length())
        .sum::<f64>()
        / 300.0;
    eprintln!(
        "mean correspondence error {before:.4} -> {after:.5} in {} iterations",
        result.iterations
    );
    assert!(after < 0.1 * before, "CPD left {after} of {before}");
}

/// The coarse stage (`CpdParams::coarse`): subsets registered first, the full sets
/// started from their field. Where the subsets are dense next to the deformation (here a
/// surface of 2000 points, subsets of 800) it recovers the deformation to 1e-3 of its
/// size (one stage does better here: 2e-6 against 1e-4), and the result says it ran.
#[test]
fn a_coarse_stage_recovers_the_deformation_too() {
    let source: Vec<DVec3> = points(2000, 3, 1.0)
        .into_iter()
        .map(|p| 0.5 * p.normalize())
        .collect();
    let truth: Vec<DVec3> = source.iter().map(|&p| smooth(p, 0.15)).collect();
    let target: Vec<DVec3> = truth.iter().rev().copied().collect();
    let error = |moved: &[DVec3]| {
        moved
            .iter()
            .zip(&truth)
            .map(|(a, b)| (*a - *b).length())
            .sum::<f64>()
            / moved.len() as f64
    };
    let one_stage = CpdParams::default();
    let coarse = CpdParams {
        coarse: Some(800),
        ..one_stage
    };
    let single = gpu(&source, &target, &one_stage);
    let staged = gpu(&source, &target, &coarse);
    let initial = error(&source);
    eprintln!(
        "mean error {initial:.4}: one stage {:.2e} ({} iterations), coarse stage {:.2e} \
         ({} + {} iterations)",
        error(&single.deformed),
        single.iterations,
        error(&staged.deformed),
        staged.coarse_iterations,
        staged.iterations - staged.coarse_iterations,
    );
    assert_eq!((single.coarse_points, single.coarse_iterations), (0, 0));
    assert_eq!(staged.coarse_points, 800);
    assert!(staged.coarse_iterations > 0 && staged.iterations > staged.coarse_iterations);
    let e = error(&staged.deformed);
    assert!(
        e < 1e-3 * initial,
        "coarse stage left {e} (one stage {}, start {initial})",
        error(&single.deformed)
    );
    // Below twice its size the coarse stage does not run.
    let small = gpu(&source[..1500], &truth[..1500], &coarse);
    assert_eq!(small.coarse_points, 0);
}

#[test]
fn low_rank_m_step_agrees_with_the_exact_one() {
    let source = points(400, 4, 1.0);
    let target: Vec<DVec3> = points(380, 5, 1.0)
        .into_iter()
        .map(|p| smooth(p, 0.1))
        .collect();
    let dense = CpdParams {
        beta: 1.0,
        max_iterations: 30,
        ..CpdParams::default()
    };
    let low = CpdParams {
        rank: Some(120),
        ..dense
    };
    let a = gpu(&source, &target, &dense);
    let b = gpu(&source, &target, &low);
    let diff = max_difference(&a.deformed, &b.deformed);
    assert!(
        diff <= 1e-3 * extent(&target),
        "exact and rank-120 differ by {diff}"
    );
}

#[test]
fn a_target_point_far_from_every_source_point() {
    let source = points(30, 6, 1.0);
    let mut target = points(30, 7, 1.0);
    target.push(DVec3::new(1e4, -1e4, 1e4));
    let result = gpu(
        &source,
        &target,
        &CpdParams {
            max_iterations: 30,
            ..CpdParams::default()
        },
    );
    // The outlier must not drag the set: every moved point stays near the data.
    assert!(
        result.deformed.iter().all(|p| p.length() < 5.0),
        "{:?}",
        result.deformed
    );
}

#[test]
fn identical_sets_collapse_sigma_without_nan() {
    let source = points(40, 8, 1.0);
    let result = gpu(
        &source,
        &source,
        &CpdParams {
            beta: 0.5,
            max_iterations: 60,
            tolerance: 0.0,
            ..CpdParams::default()
        },
    );
    assert!(
        result.sigma2.last().unwrap() < &1e-4,
        "sigma^2 {:?}",
        result.sigma2.last()
    );
    assert!(max_difference(&result.deformed, &source) < 1e-3);
}

/// A noise-free deformation drives sigma^2 towards zero and the M-step's system towards
/// singular. The device's float32 kernel products must not throw the points off there
/// (they did: 5000 such points at sigma^2 = 2e-8 jumped to sigma^2 = 2e-3, later 12, and
/// ended with 70 times the error they had reached). With no tolerance the run must stop
/// by itself at a fixed point, with the deformation recovered and sigma^2 never rising
/// tenfold from one iteration to the next; with SQUAREM's jumps (which this case takes)
/// and with plain EM.
#[test]
fn noise_free_sets_run_to_precision_without_blowing_up() {
    let source = points(1500, 11, 1.0);
    let truth: Vec<DVec3> = source.iter().map(|&p| smooth(p, 0.15)).collect();
    let mut target = truth.clone();
    target.reverse();
    for accelerate in [true, false] {
        let params = CpdParams {
            tolerance: 0.0,
            max_iterations: 400,
            accelerate,
            ..CpdParams::default()
        };
        let result = gpu(&source, &target, &params);
        let error = result
            .deformed
            .iter()
            .zip(&truth)
            .map(|(a, b)| (*a - *b).length())
            .sum::<f64>()
            / truth.len() as f64;
        let rises = result
            .sigma2
            .windows(2)
            .filter(|s| s[1] > 10.0 * s[0])
            .count();
        eprintln!(
            "{} iterations, stop {:?}, {} SQUAREM jumps, {} limited M-steps, final sigma^2 {:e}, \
             error {error:e}",
            result.iterations,
            result.stop,
            result.jumps,
            result.limited,
            result.sigma2.last().unwrap()
        );
        assert!(result.stop.converged(), "{:?}", result.stop);
        assert_eq!(rises, 0, "sigma^2 {:?}", result.sigma2);
        assert!(error < 1e-4 * extent(&truth), "mean error {error}");
        assert_eq!(result.jumps > 0, accelerate);
    }
}

#[test]
fn different_sizes_and_tiny_sets() {
    for (m, n) in [(1, 1), (1, 3), (3, 1), (2, 3), (3, 2), (20, 70), (70, 20)] {
        let source = points(m, 9 + m as u64, 1.0);
        let target = points(n, 19 + n as u64, 1.0);
        let result = gpu(
            &source,
            &target,
            &CpdParams {
                max_iterations: 20,
                ..CpdParams::default()
            },
        );
        assert_eq!(result.deformed.len(), m);
    }
}

/// The same problem in millimetres gives the same result x 1000 (beta is relative to the
/// source's RMS radius).
#[test]
fn millimetres_as_well_as_metres() {
    let source = points(50, 10, 0.2);
    let target: Vec<DVec3> = points(50, 11, 0.2)
        .into_iter()
        .map(|p| smooth(p, 0.02))
        .collect();
    let params = CpdParams {
        beta: 1.0,
        max_iterations: 30,
        ..CpdParams::default()
    };
    let metres = gpu(&source, &target, &params);
    let mm = |v: &[DVec3]| v.iter().map(|p| *p * 1000.0).collect::<Vec<_>>();
    let millimetres = gpu(&mm(&source), &mm(&target), &params);
    let diff = max_difference(&mm(&metres.deformed), &millimetres.deformed);
    assert!(
        diff <= 1e-3 * extent(&mm(&target)),
        "mm and m differ by {diff} mm"
    );
}

/// A target of 1e5 points (the E-step's work is M x N; M is kept small for CI). The run
/// checks sum P1 = sum Pt1 every iteration, which a device that dropped terms fails.
#[test]
fn a_target_of_1e5_points() {
    let source = points(64, 12, 1.0);
    let target = points(100_000, 13, 1.0);
    let result = gpu(
        &source,
        &target,
        &CpdParams {
            max_iterations: 3,
            ..CpdParams::default()
        },
    );
    assert_eq!(result.iterations, 3);
}

/// The device E-step where the other set spans many dispatches (`cpd::SPAN`): 7e4 source
/// points onto 96 targets (the denominators loop over the sources) and 96 onto 7e4 (the
/// sums loop over the targets), against float64. A single loop over 7e4 points is what
/// lavapipe cuts short (65535 iterations per invocation): its sums missed two thirds of
/// the terms at 4e4.
#[test]
fn e_step_over_many_spans_matches_float64() {
    use vkdr::cpd::{reference::ReferenceBackend, Backend, GpuBackend};
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let (many, few) = (70_000, 96);
    // sigma^2 0.05 visits every pair; at 1e-3 both sets are sorted into cells and each
    // workgroup visits only the cells near its points, in several pieces
    // (cpd::neighbours): the terms left out must not show.
    for (m, n, sigma2) in [
        (many, few, 0.05),
        (few, many, 0.05),
        (many, few, 1e-3),
        (few, many, 1e-3),
    ] {
        let source = points(m, 41, 1.0);
        let target: Vec<DVec3> = points(n, 42, 1.0)
            .into_iter()
            .map(|p| smooth(p, 0.1))
            .collect();
        let log_c = -3.0;
        let width = vkdr::cpd::neighbours::cutoff(sigma2, log_c, m.max(n));
        let grid = vkdr::cpd::neighbours::Grid::new(source.iter().chain(&target), width);
        assert_eq!(
            grid.is_some(),
            sigma2 < 0.01,
            "sigma^2 {sigma2}: cells of {width}"
        );
        let mut device = GpuBackend::new(&ctx, &pipelines, &source, &target, 1.0).unwrap();
        let got = device.expectation(&source, sigma2, log_c).unwrap();
        let want = ReferenceBackend::new(&source, &target, 1.0)
            .expectation(&source, sigma2, log_c)
            .unwrap();
        let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-4 * scale + 1e-6;
        let p1_scale = want.p1.iter().copied().fold(0.0, f64::max);
        for i in 0..m {
            assert!(
                close(got.p1[i], want.p1[i], p1_scale)
                    && (got.pull[i] - want.pull[i]).length() <= 1e-4 * p1_scale + 1e-6
                    && close(got.spread[i], want.spread[i], p1_scale),
                "{m} onto {n}: source {i}: P1 {} pull {} spread {} against {} {} {}",
                got.p1[i],
                got.pull[i],
                got.spread[i],
                want.p1[i],
                want.pull[i],
                want.spread[i]
            );
        }
        let (a, b) = (got.log_denominators, want.log_denominators);
        assert!(
            (a - b).abs() <= 1e-5 * b.abs().max(n as f64),
            "{m} onto {n}: sum of log denominators {a} against {b}"
        );
        for j in 0..n {
            assert!(
                close(got.pt1[j], want.pt1[j], 1.0),
                "{m} onto {n}: target {j}: Pt1 {} against {}",
                got.pt1[j],
                want.pt1[j]
            );
        }
    }
    common::assert_no_validation_errors(&ctx);
}

#[test]
fn bad_input_is_an_error() {
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let ok = points(5, 1, 1.0);
    let mut nan = ok.clone();
    nan[2].y = f64::NAN;
    for (source, target, params, expected) in [
        (&ok, &vec![], CpdParams::default(), "empty"),
        (&nan, &ok, CpdParams::default(), "not finite"),
        (
            &ok,
            &ok,
            CpdParams {
                w: 0.0,
                ..CpdParams::default()
            },
            "w 0 must be in (0, 1)",
        ),
        (
            &ok,
            &ok,
            CpdParams {
                beta: -1.0,
                ..CpdParams::default()
            },
            "beta -1 must be in [1e-6, 1e6]",
        ),
    ] {
        let err = cpd::register(&ctx, &pipelines, source, target, &params, &mut |_, _| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains(expected), "{err}");
    }
}

/// The device's Gaussian kernel product against the dense float64 one (relative 1e-4).
#[test]
fn kernel_product_matches_float64() {
    use vkdr::cpd::{linalg::Matrix, Backend, GpuBackend};
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let y = points(150, 21, 2.0);
    let mut backend = GpuBackend::new(&ctx, &pipelines, &y, &y, 0.7).unwrap();
    let cols = 21; // several blocks of 4 columns, and a partial one
    let v = Matrix {
        rows: 150,
        cols,
        data: (0..150 * cols)
            .map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0)
            .collect(),
    };
    let got = backend.kernel_product(&v).unwrap();
    let want = cpd::kernel_matrix(&y, 0.7).mul(&v);
    let (worst, scale) = worst_and_scale(&got, &want);
    assert!(
        worst <= 1e-4 * scale,
        "kernel product off by {worst} (scale {scale})"
    );
    common::assert_no_validation_errors(&ctx);
}

/// The kernel product over 6e4 points (eight spans; one loop over them all is what
/// lavapipe cuts short), against float64 on every 97th row.
#[test]
fn kernel_product_over_many_spans_matches_float64() {
    use vkdr::cpd::{linalg::Matrix, Backend, GpuBackend};
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let m = 60_000;
    let y = points(m, 51, 2.0);
    let beta = 0.3;
    let mut backend = GpuBackend::new(&ctx, &pipelines, &y, &y, beta).unwrap();
    let v = Matrix {
        rows: m,
        cols: 3,
        data: (0..3 * m)
            .map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0)
            .collect(),
    };
    let got = backend.kernel_product(&v).unwrap();
    let inv = 1.0 / (2.0 * beta * beta);
    for i in (0..m).step_by(97) {
        let mut want = [0.0; 3];
        let mut magnitude = 0.0;
        for (j, q) in y.iter().enumerate() {
            let k = (-(y[i] - *q).length_squared() * inv).exp();
            magnitude += k;
            for (c, w) in want.iter_mut().enumerate() {
                *w += k * v.at(j, c);
            }
        }
        for (c, w) in want.iter().enumerate() {
            assert!(
                (got.at(i, c) - w).abs() <= 1e-4 * magnitude,
                "row {i} column {c}: {} against {w} (sum of the kernel {magnitude})",
                got.at(i, c)
            );
        }
    }
    common::assert_no_validation_errors(&ctx);
}

/// One M-step on the device (Nystrom preconditioner, conjugate gradients on the device's
/// kernel products) against the dense float64 solve of (dP1 G + s I) W = PX - dP1 Y, for
/// a wide kernel (the preconditioner alone is exact) and a narrow one (conjugate
/// gradients must do the work), with rows that no target reaches (P1 = 0).
#[test]
fn device_m_step_matches_the_dense_float64_solve() {
    use vkdr::cpd::linalg::{self, Matrix};
    use vkdr::cpd::m_step::MStep;
    use vkdr::cpd::{Expectation, GpuBackend};
    let ctx = common::context();
    let pipelines = CpdPipelines::new(&ctx).unwrap();
    let m = 400;
    let y = points(m, 31, 2.0);
    let p1: Vec<f64> = (0..m)
        .map(|i| {
            if i % 17 == 0 {
                0.0
            } else {
                0.2 + (i % 7) as f64 * 0.15
            }
        })
        .collect();
    let px: Vec<DVec3> = (0..m)
        .map(|i| p1[i] * smooth(y[(i * 7) % m], 0.2))
        .collect();
    // At the start (moving points = y): the pull is PX - P1 y.
    let e = Expectation {
        p1: p1.clone(),
        pt1: vec![],
        pull: (0..m).map(|i| px[i] - p1[i] * y[i]).collect(),
        spread: vec![0.0; m],
        log_denominators: 0.0,
    };
    // (beta, s, whether the preconditioner alone must be exact)
    for (beta, s, wide) in [(2.0, 1e-3, true), (0.15, 1e-2, false)] {
        let mut backend = GpuBackend::new(&ctx, &pipelines, &y, &y, beta).unwrap();
        let m_step = MStep::new(&y, beta, None).unwrap();
        let (mut w, mut gw) = (Matrix::zeros(m, 3), Matrix::zeros(m, 3));
        let solved = m_step
            .solve(&mut backend, &e, &y, &y, s, &mut w, &mut gw)
            .unwrap();
        let g = cpd::kernel_matrix(&y, beta);
        let mut a = g.clone();
        let mut b = Matrix::zeros(m, 3);
        for i in 0..m {
            for j in 0..m {
                a.data[i * m + j] *= p1[i];
            }
            a.data[i * m + i] += s;
            let r = px[i] - p1[i] * y[i];
            b.data[3 * i..3 * i + 3].copy_from_slice(&r.to_array());
        }
        let want = linalg::solve(a, b).unwrap();
        // Compared where the registration uses W: the displacement G W.
        let (worst, scale) = worst_and_scale(&gw, &g.mul(&want));
        eprintln!(
            "beta {beta}: {} products, rank {}, G W off by {worst:e} (scale {scale:e})",
            solved.products,
            m_step.rank()
        );
        if wide {
            assert!(solved.converged && solved.products == 0, "{solved:?}");
        } else {
            assert!(
                solved.products > 1,
                "conjugate gradients did not run: {solved:?}"
            );
        }
        assert!(
            worst <= 1e-4 * scale,
            "beta {beta}: G W off by {worst} of {scale}"
        );
        for i in (0..m).step_by(17) {
            assert!(
                DVec3::new(w.at(i, 0), w.at(i, 1), w.at(i, 2)).length() < 1e-6,
                "row {i} without targets moved"
            );
        }
    }
    common::assert_no_validation_errors(&ctx);
}
