//! Several starting poses: the starts turned about the up axis, the turns tried on the
//! first start's fit, and the pivot a symmetric body turns about.

use std::time::Instant;

use glam::{DMat3, DVec3};

use crate::error::{Error, Result};
use crate::gpu::Context;
use crate::raster::View;
use crate::Pose;

use super::task::{lower_loss, Stage, Staged};
use super::{nearest, Job, RegisterParams, Registrar, Registration, STAGE_TURNED};

/// The turn between the starts of a registration with the pose free (`vkdr register`
/// turns its starts about the up axis by multiples of it, [`turned_starts`]; `vkdr eval`
/// by its rotation noise, the same 15 degrees by default).
pub const START_TURN: f64 = 15f64.to_radians();

/// Starts of a registration with the pose free unless told otherwise: the start and it
/// turned by +-1 and +-2 [`START_TURN`]s (against a rotation that stops in a local
/// minimum, as a mug's handle; docs/evaluation.md has the cost). `vkdr register`, `vkdr
/// eval`, `eval-frames`, `bench-register` and the Python module take it from here.
pub const DEFAULT_STARTS: usize = 5;
/// The most starts one registration takes (each start's turn is scored on the first
/// start's fit; past +-4 turns of 15 degrees a start is no longer near the first).
pub const MAX_STARTS: usize = 8;

/// How a registration uses several starting poses ([`super::Registrar::register_starts`]).
#[derive(Clone, Copy, Debug)]
pub enum Starts<'a> {
    /// Every pose registered in full (one batch), the least final loss kept.
    Poses(&'a [Pose]),
    /// The first pose registered, then the turns that take it to the others tried on its
    /// fit ([`super::Registrar::register_with_turns`]; [`turned_starts`] makes such poses).
    Turns(&'a [Pose]),
}

impl<'a> Starts<'a> {
    /// The schedules' rule: turns where `params` align the pose first (the pose free),
    /// every pose in full otherwise.
    pub fn for_params(poses: &'a [Pose], params: &RegisterParams) -> Self {
        if params.pose_every > 0 && params.align > 0 {
            Starts::Turns(poses)
        } else {
            Starts::Poses(poses)
        }
    }
}

/// One job per starting pose: `job` from each of `poses`.
pub(super) fn jobs_from<'a>(job: Job<'a>, poses: &[Pose]) -> Vec<Job<'a>> {
    poses
        .iter()
        .map(|&pose| Job {
            view: View { pose, ..job.view },
            ..job
        })
        .collect()
}

/// An error unless `count` is 1 to [`MAX_STARTS`].
pub fn check_starts(count: usize) -> Result<()> {
    if (1..=MAX_STARTS).contains(&count) {
        return Ok(());
    }
    Err(Error::InvalidInput(format!(
        "starts must be 1 to {MAX_STARTS}, not {count}"
    )))
}

/// The turns (radians) of [`turned_starts`]: 0, +`step`, -`step`, +2 `step`, -2 `step`,
/// ..., `count` of them.
pub fn start_turns(count: usize, step: f64) -> Vec<f64> {
    (0..count)
        .map(|j| {
            let turns = j.div_ceil(2) as f64 * step;
            if j % 2 == 1 {
                turns
            } else {
                -turns
            }
        })
        .collect()
}

/// `count` starting poses for [`super::Registrar::register_starts`]: `pose`, then `pose`
/// with the object first turned about its own `up` axis (through its origin) by each
/// further [`start_turns`], so that a start lies on either side of a minimum next to
/// `pose`'s.
pub fn turned_starts(pose: Pose, up: DVec3, count: usize, step: f64) -> Vec<Pose> {
    start_turns(count, step)
        .into_iter()
        .map(|angle| {
            let turn = DMat3::from_axis_angle(up.normalize(), angle);
            Pose {
                translation: pose.translation,
                rotation: glam::DQuat::from_mat3(&(pose.rotation_matrix() * turn)).to_scaled_axis(),
            }
        })
        .collect()
}

/// The rotations (object frame) that took the first job's pose to each job's: identity
/// first.
pub(super) fn relative_turns(jobs: &[Job]) -> Vec<DMat3> {
    let first = jobs[0].view.pose.rotation_matrix();
    jobs.iter()
        .map(|job| first.transpose() * job.view.pose.rotation_matrix())
        .collect()
}

/// A point on the axis about which `vertices` are most nearly symmetric, among the axes
/// along `axis`: the shape turned by +-30 degrees about it lies closest to itself, the
/// points that land farther than 1.5 times the median distance from it (a handle) left out.
/// Iterated closest points on at most 1000 vertices (found in a grid: a scan of all made
/// this 200 ms of a 0.9 s registration on lavapipe); the two turns' opposite biases along
/// the turn (the nearest vertex lies behind or ahead of a turned one) cancel. The origin
/// for no finite vertices.
pub fn symmetry_pivot(vertices: &[DVec3], axis: DVec3) -> DVec3 {
    let step = vertices.len().div_ceil(1000).max(1);
    // A non-finite vertex is no one's nearest (the grid needs finite points).
    let points: Vec<DVec3> = vertices
        .iter()
        .step_by(step)
        .copied()
        .filter(|p| p.is_finite())
        .collect();
    let axis = axis.normalize();
    let across = |v: DVec3| v - axis * axis.dot(v);
    let half_turn = 15f64.to_radians();
    if points.is_empty() {
        return DVec3::ZERO;
    }
    let nearest = nearest::Nearest::new(&points);
    let mut pivot = across(crate::mesh::centroid(&points));
    // Each estimate is a function of the pivot alone (through the nearest points it
    // pairs): once an estimate returns the pivot unchanged, every later one would too.
    for _ in 0..20 {
        let estimates = [1.0, -1.0].map(|side: f64| {
            let turn = DMat3::from_axis_angle(axis, side * 2.0 * half_turn);
            // Turned about the pivot c, x goes to turn x + (I - turn) c; its nearest point
            // q asks (I - turn) c = q - turn x, across the axis. There I - turn is a turn
            // by side (15 - 90) degrees scaled by 2 sin(15 degrees).
            let mut pairs: Vec<(f64, DVec3)> = points
                .iter()
                .map(|&x| {
                    let moved = turn * x + (pivot - turn * pivot);
                    let q = nearest.nearest(moved);
                    ((q - moved).length_squared(), across(q - turn * x))
                })
                .collect();
            let mut distances: Vec<f64> = pairs.iter().map(|p| p.0).collect();
            distances.sort_by(f64::total_cmp);
            // Squared: 2.25 times the median's square is 1.5 times its distance.
            let far = 2.25 * distances[distances.len() / 2];
            pairs.retain(|p| p.0 <= far);
            let target = pairs.iter().map(|p| p.1).sum::<DVec3>() / pairs.len() as f64;
            let inverse = DMat3::from_axis_angle(axis, side * (90f64.to_radians() - half_turn));
            inverse * target / (2.0 * half_turn.sin())
        });
        let next = 0.5 * (estimates[0] + estimates[1]);
        if next == pivot {
            break;
        }
        pivot = next;
    }
    pivot
}

/// Points sampled on a surface for [`turns_can_tell`]: enough that a handle's few per
/// cent of the area hold dozens.
const SURFACE_SAMPLES: usize = 2000;
/// [`turns_can_tell`]'s bound: a shape whose turned sample lies this close to a second
/// sample of itself, against the unturned sample's own distance, looks the same turned.
/// Measured (the ratio below): the generated bottles and bowls and the real master chef
/// can 1.00-1.16; the generated mugs 2.8-5.3, spray bottles 4.2-6.0 and drills 12-14, the
/// real mug about 4 and the flat-sided shapes the real mustard bottle is fitted with
/// 2.6-3.9.
const SAME_TURNED: f64 = 1.7;

/// Whether turning the surface of `triangles` over `vertices` about the axis along `axis`
/// through `pivot` can tell one turn from another: whether, turned by 30, 90 or 150
/// degrees, part of it leaves the unturned surface (a mug's handle, a spray bottle's
/// trigger), or whether it is a body of revolution (a can, a bottle, a bowl), whose
/// turns all look the same. A sample of the surface turned is compared with a second,
/// independent sample: the 99th percentile of its points' distances to their nearest in
/// the second, against the same for the unturned sample (what sampling alone gives).
pub(super) fn turns_can_tell(
    vertices: &[DVec3],
    triangles: &[[u32; 3]],
    axis: DVec3,
    pivot: DVec3,
) -> bool {
    let sample = crate::mesh::surface_sample(vertices, triangles, SURFACE_SAMPLES, 1);
    let other = crate::mesh::surface_sample(vertices, triangles, SURFACE_SAMPLES, 2);
    if sample.is_empty() || sample.iter().chain(&other).any(|p| !p.is_finite()) {
        return true;
    }
    let nearest = nearest::Nearest::new(&other);
    let percentile = |turn: DMat3| {
        let mut distances: Vec<f64> = sample
            .iter()
            .map(|&p| {
                let moved = pivot + turn * (p - pivot);
                (nearest.nearest(moved) - moved).length()
            })
            .collect();
        distances.sort_by(f64::total_cmp);
        distances[distances.len() * 99 / 100]
    };
    let unturned = percentile(DMat3::IDENTITY);
    let axis = axis.normalize();
    // One turn that tells is enough (a mug's handle leaves at the first).
    [30f64, 90.0, 150.0].into_iter().any(|degrees| {
        percentile(DMat3::from_axis_angle(axis, degrees.to_radians())) > SAME_TURNED * unturned
    })
}

/// A turned pose's loss must be this fraction below the fit's for the joint fit to run
/// again from it (the registration from starts).
pub const TURN_GAIN: f64 = 0.05;
/// Pose-only iterations that score a turned pose (the registration from starts).
pub const TURN_ITERATIONS: usize = 1;

/// `jobs` at the poses that `results` reached.
pub(super) fn at_poses<'a>(jobs: &[Job<'a>], results: &[Registration]) -> Vec<Job<'a>> {
    jobs.iter()
        .zip(results)
        .map(|(job, r)| Job {
            view: View {
                pose: r.pose,
                ..job.view
            },
            ..*job
        })
        .collect()
}

impl Registrar {
    /// After the joint fit from the first start: the fitted shape and pose turned as each
    /// start was turned from the first (`turns`, object frame, the first the identity),
    /// about the fitted shape's own axis, each scored by its loss at one evaluation. A
    /// mask alone cannot choose among the starts before the fit (a mug's handle is a few
    /// pixels against the body's hundreds: aligned starts' losses differ by about 0.1%);
    /// the fitted shape can. Where a turned pose's loss is [`TURN_GAIN`] below the fit's,
    /// the joint fit runs again from it with the fitted code, and the lower final loss is
    /// kept. Costs one evaluation per turn, and a second joint fit only where a turn is
    /// better; nothing where the fitted shape is a body of revolution about the turns'
    /// axis ([`turns_can_tell`]), whose turns all look the same.
    pub(super) fn check_turns(
        &self,
        ctx: &Context,
        job: &Job,
        params: &RegisterParams,
        fitted: Staged,
        turns: &[DMat3],
        started: Instant,
    ) -> Result<Staged> {
        let pose = fitted.result.pose;
        let r = pose.rotation_matrix();
        let Some(axis) = turns
            .iter()
            .map(|turn| glam::DQuat::from_mat3(turn).to_axis_angle())
            .find(|(_, angle)| angle.abs() > 1e-6)
            .map(|(axis, _)| axis)
        else {
            return Ok(fitted);
        };
        // Turned about the fitted shape's own axis, not the frame's origin: a bounding
        // box centred mug has its body's axis a centimetre or two from the origin.
        let vertices = &fitted.result.vertices;
        let pivot = symmetry_pivot(vertices, axis);
        // A body of revolution looks the same at every turn: a turned pose could only
        // score lower where the fit has not settled, and a second fit from it chose by
        // noise (on the real can it ended at a lower loss and a larger error).
        if !turns_can_tell(vertices, job.space.canonical.triangles(), axis, pivot) {
            let mut fitted = fitted;
            fitted.result.milliseconds = started.elapsed().as_secs_f64() * 1e3;
            return Ok(fitted);
        }
        let turned: Vec<Job> = turns
            .iter()
            .map(|turn| Job {
                view: View {
                    pose: Pose {
                        translation: pose.translation + r * (pivot - *turn * pivot),
                        rotation: glam::DQuat::from_mat3(&(r * *turn)).to_scaled_axis(),
                    },
                    ..job.view
                },
                ..*job
            })
            .collect();
        let score = RegisterParams {
            iterations: TURN_ITERATIONS,
            ..*params
        };
        let codes = vec![fitted.coordinates.clone(); turned.len()];
        let scored = self.run(
            ctx,
            &turned,
            Stage::fit(&score, Some(&codes), started).pose_only(),
            &mut |_, _| {},
        )?;
        let loss = |s: &Staged| s.result.losses.first().copied().unwrap_or(f64::INFINITY);
        let (best, best_loss) = scored
            .iter()
            .enumerate()
            .map(|(i, s)| (i, loss(s)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("at least one turn");
        let mut fitted = fitted;
        fitted.result.evaluations += scored.iter().map(|s| s.result.evaluations).sum::<usize>();
        if best == 0 || best_loss > (1.0 - TURN_GAIN) * loss(&scored[0]) {
            fitted.result.milliseconds = started.elapsed().as_secs_f64() * 1e3;
            return Ok(fitted);
        }
        let again = self
            .run(
                ctx,
                &turned[best..best + 1],
                Stage::fit(params, Some(&codes[..1]), started),
                &mut |_, _| {},
            )?
            .remove(0);
        Ok(lower_loss(fitted, again, STAGE_TURNED, started))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mug-like shape (a ring of points about an axis off the origin, and a handle on
    /// one side) turns about its body's axis: the pivot lands on it, where the centroid
    /// is pulled toward the handle.
    #[test]
    fn the_symmetry_pivot_is_the_body_s_axis() {
        let axis_at = DVec3::new(0.015, 0.0, -0.01);
        let mut points = Vec::new();
        for ring in 0..12 {
            for k in 0..40 {
                let a = k as f64 * std::f64::consts::TAU / 40.0;
                let y = ring as f64 * 0.008;
                points.push(axis_at + DVec3::new(0.04 * a.cos(), y, 0.04 * a.sin()));
            }
        }
        for k in 0..60 {
            let a = k as f64 * std::f64::consts::TAU / 60.0;
            let handle = DVec3::new(0.06 + 0.015 * a.cos(), 0.045 + 0.025 * a.sin(), 0.0);
            points.push(axis_at + handle);
        }
        let centroid = crate::mesh::centroid(&points);
        let across = |v: DVec3| DVec3::new(v.x, 0.0, v.z);
        assert!(across(centroid - axis_at).length() > 4e-3, "{centroid}");
        let pivot = symmetry_pivot(&points, DVec3::new(0.0, 2.0, 0.0));
        assert!(
            across(pivot - axis_at).length() < 5e-4,
            "{pivot} against {axis_at}"
        );
    }

    /// A non-finite vertex (a diverged fit) is left out rather than poisoning the pivot;
    /// with none finite the pivot is the origin.
    #[test]
    fn the_symmetry_pivot_leaves_non_finite_vertices_out() {
        let axis = DVec3::Y;
        let ring: Vec<DVec3> = (0..40)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 40.0;
                DVec3::new(0.02 + 0.04 * a.cos(), 0.0, 0.04 * a.sin())
            })
            .collect();
        let mut with_nan = ring.clone();
        with_nan.insert(7, DVec3::new(f64::NAN, 0.0, 0.0));
        with_nan.push(DVec3::splat(f64::INFINITY));
        assert_eq!(symmetry_pivot(&with_nan, axis), symmetry_pivot(&ring, axis));
        assert_eq!(symmetry_pivot(&[DVec3::NAN], axis), DVec3::ZERO);
    }

    /// The starts alternate sides at growing turns, and a turn about the object's up axis
    /// keeps the position and the axis and moves a point off the axis by the turn.
    #[test]
    fn starts_turn_about_the_up_axis_on_either_side() {
        let r = 0.25;
        assert!(start_turns(0, r).is_empty());
        assert_eq!(start_turns(5, r), vec![0.0, r, -r, 2.0 * r, -2.0 * r]);
        let pose = Pose::new([0.02, -0.01, 0.6], [0.3, -0.2, 0.1]).unwrap();
        let up = DVec3::new(0.0, 2.0, 0.0);
        let starts = turned_starts(pose, up, 3, r);
        assert_eq!(starts.len(), 3);
        assert!((starts[0].rotation - pose.rotation).length() < 1e-12);
        let x = DVec3::X;
        for (turned, angle) in starts.iter().zip([0.0, r, r]) {
            assert!((turned.translation - pose.translation).length() < 1e-12);
            assert!((turned.apply(up) - pose.apply(up)).length() < 1e-12);
            let moved = (turned.apply(x) - pose.apply(x)).length();
            assert!((moved - 2.0 * (angle / 2.0).sin()).abs() < 1e-12, "{moved}");
        }
        // The second and third turn to either side.
        let side = |p: &Pose| pose.inverse().followed_by(p).apply(x).z;
        assert!(side(&starts[1]) * side(&starts[2]) < 0.0);
    }

    /// [`crate::mesh::Mesh::lathe`]'s closed surface of `profile` ((radius, height)) moved
    /// to stand on `at`: its vertices and triangles.
    fn lathe(at: DVec3, profile: &[(f32, f32)], segments: u32) -> (Vec<DVec3>, Vec<[u32; 3]>) {
        let mesh = crate::mesh::Mesh::lathe(profile, segments).unwrap();
        let vertices = mesh.points().into_iter().map(|p| at + p).collect();
        (vertices, mesh.triangles().to_vec())
    }

    /// A cup-like body of revolution (off the origin) looks the same at every turn about
    /// its own axis, but not about another; a handle on its side tells the turns apart.
    #[test]
    fn turns_tell_a_handle_and_not_a_body_of_revolution() {
        let at = DVec3::new(0.02, 0.0, -0.015);
        let profile = [(0.03, 0.0), (0.035, 0.02), (0.038, 0.05), (0.04, 0.08)];
        // 50 segments: no multiple of 30 degrees turns the facets onto themselves.
        let (body, body_triangles) = lathe(at, &profile, 50);
        assert!(!turns_can_tell(&body, &body_triangles, DVec3::Y, at));
        assert!(turns_can_tell(
            &body,
            &body_triangles,
            DVec3::Y,
            DVec3::ZERO
        ));

        // A handle: a small lathe (a ring of rings) standing on the body's side.
        let (handle, handle_triangles) = lathe(
            at + DVec3::new(0.05, 0.02, 0.0),
            &[(0.006, 0.0), (0.008, 0.02), (0.006, 0.04)],
            16,
        );
        let offset = body.len() as u32;
        let vertices: Vec<DVec3> = body.iter().chain(&handle).copied().collect();
        let triangles: Vec<[u32; 3]> = body_triangles
            .iter()
            .copied()
            .chain(handle_triangles.iter().map(|t| t.map(|i| i + offset)))
            .collect();
        assert!(turns_can_tell(&vertices, &triangles, DVec3::Y, at));
        // A surface without area (none, or only non-finite) is not taken as round.
        let flat = vec![DVec3::ZERO; 3];
        assert!(turns_can_tell(&flat, &[[0, 1, 2]], DVec3::Y, DVec3::ZERO));
        let lost = vec![DVec3::NAN; body.len()];
        assert!(turns_can_tell(&lost, &body_triangles, DVec3::Y, at));
    }
}
