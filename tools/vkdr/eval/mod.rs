//! The paper's Table 1 on a category dataset: per held-out test instance, the oracle error
//! (the shape space's best fit to the true 3D instance) next to registration from a
//! rendered mask with the pose known and with pose noise, over seeded trials, plus
//! timings and the error after every iteration (speed against error).
//!
//! Error: for every point of a uniform sample of the test instance's surface, the distance
//! to the deformed canonical mesh's surface (nearest point on its triangles), averaged
//! (metres). Not the design's "nearest vertex of the deformed canonical": generated
//! instances share the canonical's topology, so from the test's own vertices that rewards
//! landing every vertex on its twin (which CPD, the oracle, does and no silhouette can
//! show), and from a surface sample it measures the canonical's vertex spacing (about
//! 20 mm for a 226-vertex bottle) more than its shape. The symmetric chamfer distance of
//! the vertex sets (the mean of both directions' mean nearest distances) is reported too.

use glam::DVec3;

use crate::dataset::Rng;
use vkdr::camera::Pose;
use vkdr::error::Result;
use vkdr::gpu::Context;
use vkdr::mesh::{centroid, Mesh};
use vkdr::register::Registrar;
use vkdr::shape::ShapeSpace;

pub use crate::metrics::{
    angle_between, pose_error, surface_error, surface_extent, symmetric_about,
    symmetric_rotation_error,
};
pub use crate::reference::{space_optimum, surface_sample, Optimum, Reference, SAMPLE_POINTS};

mod scene;
mod settings;
mod trial;

pub use scene::*;
pub use settings::*;
pub use trial::Registered;
use trial::{register_trial, Measure};

/// Mean over `a` of the distance to the nearest point of `b`.
pub fn mean_nearest(a: &[DVec3], b: &[DVec3]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::NAN;
    }
    a.iter()
        .map(|&p| crate::metrics::nearest(p, b))
        .sum::<f64>()
        / a.len() as f64
}

/// Symmetric chamfer distance: the mean of both directions' mean nearest distances.
pub fn chamfer(a: &[DVec3], b: &[DVec3]) -> f64 {
    0.5 * (mean_nearest(a, b) + mean_nearest(b, a))
}

/// Mean and (sample) standard deviation.
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Stat {
    pub mean: f64,
    pub std: f64,
}

impl Stat {
    pub fn of(values: &[f64]) -> Self {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        Self {
            mean,
            std: var.sqrt(),
        }
    }
}

/// One row of the table.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Row {
    pub category: String,
    pub instance: String,
    pub oracle: f64,
    /// The least error the shape space reaches on this instance ([`space_optimum`]).
    pub space_optimum: f64,
    /// The oracle's largest code coordinate in training standard deviations: where the
    /// truth's own code lies against the training set.
    #[serde(default)]
    pub oracle_code_sd: f64,
    pub oracle_chamfer: f64,
    pub known_pose: Stat,
    pub known_pose_chamfer: Stat,
    pub pose_noise: Stat,
    pub pose_noise_chamfer: Stat,
    /// Largest pose-noise error over the trials (divergence check).
    pub pose_noise_worst: f64,
    /// The pose-noise error after moving each registered shape so that its vertex centroid
    /// is the oracle fit's (see `placed_like`).
    pub pose_noise_placed: Stat,
    /// The pose-noise error of each registered shape where the registration put it: moved
    /// by its registered pose and back by the true one (see `as_seen`).
    pub pose_noise_seen: Stat,
    /// The oracle's error both ways and the pose-noise error as seen both ways (the mean
    /// of test to shape and shape to test, [`reverse_error`]).
    pub oracle_both_ways: f64,
    pub pose_noise_seen_both_ways: Stat,
    /// With `EvalSettings::from_truth`: pose and shape optimised from the true pose.
    pub from_truth: Option<Stat>,
    /// Mean iterations and milliseconds of a registration with the pose known...
    pub iterations: f64,
    pub ms: f64,
    /// ...and with pose noise (the alignment's included).
    pub noise_iterations: f64,
    pub noise_ms: f64,
    /// Mean error after each iteration (known pose, pose noise) and mean ms per iteration.
    pub curve_known: Vec<f64>,
    pub curve_noise: Vec<f64>,
    pub ms_per_iteration: f64,
    /// Each trial's view and errors.
    pub trials: Vec<Trial>,
}

/// One trial of a test instance: the view, the errors and the pose error with pose noise.
#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize)]
pub struct Trial {
    /// The view, radians.
    pub azimuth: f64,
    pub elevation: f64,
    /// Angles (radians, 0 to pi/2) between the line of sight and the test instance's
    /// longest and shortest bounding-box axes. Near 0 for the longest the view is end-on;
    /// near pi/2 for the shortest it is edge-on: the line of sight lies in the plane of the
    /// two longest axes, and rotations about the shortest move the object mostly along the
    /// line of sight, where one view sees them least.
    pub long_axis_angle: f64,
    pub short_axis_angle: f64,
    pub known_pose: f64,
    pub pose_noise: f64,
    pub pose_noise_placed: f64,
    pub pose_noise_seen: f64,
    /// The same as seen, the mean of the error both ways (test to shape and shape to test,
    /// [`reverse_error`]).
    pub pose_noise_seen_both_ways: f64,
    /// The final loss of the registration with the pose known and of the one with pose
    /// noise (the same images and loss; with `--code-prior` the latter's includes the
    /// prior's term). Below the known pose's, the pose-noise fit explains the images
    /// better than the best code at the true pose does: the images prefer it, and no
    /// optimiser would bring it nearer the truth.
    pub known_pose_loss: f64,
    pub pose_noise_loss: f64,
    /// The registered pose against the true one with pose noise: rotation (radians) and
    /// translation (metres).
    pub rotation_error: f64,
    /// The rotation error up to the instance's symmetry: the least over turns about its up
    /// axis where it is rotationally symmetric ([`symmetric_about`]), else the same.
    pub rotation_error_symmetric: f64,
    pub translation_error: f64,
    /// Code coordinates the optimiser ended with on its bound, with the pose known and
    /// with pose noise ([`Registration::on_bound`](vkdr::register::Registration)).
    pub known_pose_on_bound: usize,
    pub pose_noise_on_bound: usize,
    /// With pose noise: the angle (radians) between the registered and the true up axis,
    /// the error in the camera's z of the surface's centroid (metres, registered less
    /// true; [`surface_extent`]), and the scale found (1 unless it is optimised).
    pub tilt: f64,
    pub z_error: f64,
    /// With pose noise: the registered surface's size over the test surface's (their
    /// root-mean-square distances from their centroids, [`surface_extent`]): 1 where the
    /// registration found the object's size, whether by the scale or by the shape.
    pub size: f64,
    /// The error in the camera's z of the object frame's origin (metres). A diagnostic:
    /// the shape modes move the surface about the origin, so a registered origin off in
    /// depth with the surface in place is a shape shifted in its own frame, not an
    /// object misplaced.
    pub z_error_origin: f64,
    /// The same z error for the registration with the pose known (its surface at the true
    /// pose): the part of `z_error` that is the shape's, not the pose's.
    pub z_error_known: f64,
    pub scale: f64,
    /// The angle (radians) between the up direction the registration was given and the
    /// true one (0 without gravity or with it known; the support plane's error from depth).
    pub gravity_error: f64,
    /// Gravity from the depth was asked for and no support plane was found: the trial ran
    /// without gravity ([`EvalSettings::gravity_fallback`]).
    pub gravity_fallback: bool,
    /// The field's metrics ([`crate::metrics`]): ADD-S with the registered surface
    /// (metres), ...
    pub add_s: f64,
    /// ... the distance between the registered and the true surface's centroids in the
    /// camera frame (metres), ...
    pub centroid_error: f64,
    /// ... the rotation error as NOCS counts it (radians; up to the turns about the up
    /// axis where the instance is symmetric or its asymmetric part is out of view), ...
    pub rotation_error_nocs: f64,
    /// ... and the 3D IoU of the registered and the true oriented bounding boxes.
    pub iou: f64,
    /// The largest code coordinate in training standard deviations
    /// ([`ShapeSpace::code_in_deviations`]) with the pose known and with
    /// pose noise: how far into the tails of the training set the images took the shape.
    #[serde(default)]
    pub known_pose_code_sd: f64,
    #[serde(default)]
    pub pose_noise_code_sd: f64,
}

/// The largest |coordinate| of `code` in training standard deviations.
fn largest_sd(space: &ShapeSpace, code: &[f64]) -> f64 {
    space
        .code_in_deviations(code)
        .into_iter()
        .fold(0.0, |m, v| m.max(v.abs()))
}

/// The mean distance from `SAMPLE_POINTS` points sampled uniformly on the surface of
/// `vertices` (over `triangles`) to the surface of `test`: the direction the reported error
/// does not look in, which sees parts the registered shape has and the test instance has
/// not (a registered shape shorter than the truth is seen from the test's side, one longer
/// from this side).
pub fn reverse_error(
    vertices: &[DVec3],
    triangles: &[[u32; 3]],
    test: &Mesh,
    seed: u64,
) -> Result<f64> {
    let positions = vertices.iter().map(|v| v.as_vec3().to_array()).collect();
    let shape = Mesh::new(positions, triangles.to_vec())?;
    let points = surface_sample(&shape, SAMPLE_POINTS, seed);
    Ok(surface_error(&points, &test.points(), test.triangles()))
}

/// `vertices` moved so that their centroid is that of `reference` (the same mesh's
/// vertices). With the x and y translation unknown, one view cannot tell a shape shifted
/// in its own frame from a shifted pose, and the error counts such a shift in full; the
/// error of the shape placed like the oracle fit shows how much of it is placement.
pub fn placed_like(vertices: &[DVec3], reference: &[DVec3]) -> Vec<DVec3> {
    let shift = centroid(reference) - centroid(vertices);
    vertices.iter().map(|&v| v + shift).collect()
}

/// The registered `vertices` (object frame) where the registration put them, in the true
/// object frame: camera to object by the true `pose` after object to camera by the
/// `registered` one. Their error against the test surface is the camera-frame distance
/// between the registered surface at the registered pose and the test surface at the true
/// pose, what a robot acting on the registration meets; a shape shifted in its own frame
/// together with a pose shifted back (which one view cannot tell apart) costs nothing
/// here.
pub fn as_seen(vertices: &[DVec3], registered: Pose, pose: Pose) -> Vec<DVec3> {
    let back = pose.inverse();
    vertices
        .iter()
        .map(|&v| back.apply(registered.apply(v)))
        .collect()
}

/// Evaluates one test instance against a built shape space; `on_trial` sees each trial's
/// registrations (its number from 0) before they are measured.
#[allow(clippy::too_many_arguments)] // the instance, its category's context, and progress
pub fn evaluate_instance(
    ctx: &Context,
    registrar: &Registrar,
    space: &ShapeSpace,
    category: &str,
    name: &str,
    test: &Mesh,
    settings: &EvalSettings,
    source: TrialSource,
    mut progress: impl FnMut(usize, usize),
    mut on_trial: impl FnMut(usize, &Registered) -> Result<()>,
) -> Result<Row> {
    // A test instance of another size: where the scale is optimised, the oracle and the
    // space optimum are those of the instance at its own size, scaled (the space with a
    // scale reaches exactly that); otherwise the space's own at the scaled size.
    let scaled;
    let (test, floor_scale) = if settings.test_scale == 1.0 {
        (test, 1.0)
    } else {
        let k = settings.test_scale;
        scaled = test.with_points(&test.points().iter().map(|p| *p * k).collect::<Vec<_>>())?;
        let scaled_floor = settings.known_pose.optimize_scale && settings.pose_noise.optimize_scale;
        (&scaled, if scaled_floor { k } else { 1.0 })
    };
    let table = if settings.table {
        Some(table_under(test, settings.up)?)
    } else {
        None
    };
    let computed;
    let reference = match source {
        TrialSource::Frame { reference, .. } => reference,
        TrialSource::Rendered => {
            computed = Reference::of(
                ctx,
                &crate::reference::Model {
                    space,
                    test,
                    seed: hash(name),
                    cpd: &settings.cpd,
                    scale: floor_scale,
                    free_scale: false,
                    up: settings.up,
                },
            )?;
            &computed
        }
    };
    let Reference {
        truth,
        oracle_vertices,
        symmetric,
        asymmetric,
        ..
    } = reference;
    let measure = Measure::new(space, name, test, truth, settings, *symmetric, asymmetric);
    let test_vertices = &measure.test_vertices;
    let mut rng = Rng::new(settings.seed ^ hash(name));
    let (mut known_ch, mut noisy_ch) = (vec![], vec![]);
    let mut trials: Vec<Trial> = Vec::new();
    let mut known_once: Option<vkdr::register::Registration> = None;
    let mut from_truth = Vec::new();
    let (mut iterations, mut ms, mut noise_iterations, mut noise_ms) =
        (vec![], vec![], vec![], vec![]);
    let mut ms_per_iteration = Vec::new();
    // The space optimum's starts besides the oracle's code: the mean shape and the best
    // known-pose registration's code (the oracle can be poor, and the least error the
    // space reaches must not be above what a registration found).
    let mut best_known: Option<(f64, Vec<f64>)> = None;
    let (known_pose, pose_noise) = (settings.known_pose_params(), settings.pose_noise_params());
    let mut curve_known = vec![0.0; known_pose.total_iterations()];
    let mut curve_noise = vec![0.0; pose_noise.total_iterations()];
    for trial in 0..settings.trials {
        progress(trial, settings.trials);
        let scene = match source {
            TrialSource::Rendered => {
                render_trial(ctx, registrar, test, table.as_ref(), settings, &mut rng)?
            }
            TrialSource::Frame { scene, .. } => scene.clone(),
        };
        let registered = register_trial(
            ctx,
            registrar,
            space,
            settings,
            source,
            scene,
            &mut known_once,
            &mut rng,
        )?;
        on_trial(trial, &registered)?;
        let measured = measure.trial(&registered, oracle_vertices)?;
        let Registered {
            known,
            from_truth: truth_started,
            noisy,
            ..
        } = registered;
        if best_known
            .as_ref()
            .is_none_or(|(e, _)| measured.known_pose < *e)
        {
            best_known = Some((measured.known_pose, known.code.clone()));
        }
        known_ch.push(chamfer(test_vertices, &known.vertices));
        iterations.push(known.evaluations as f64);
        ms.push(known.milliseconds);
        ms_per_iteration.push(known.milliseconds / known.evaluations as f64);
        accumulate_curve(&mut curve_known, space, truth, &known, settings.trials)?;
        if let Some(result) = truth_started {
            from_truth.push(measure.error(&result.vertices));
        }
        noisy_ch.push(chamfer(test_vertices, &noisy.vertices));
        noise_iterations.push(noisy.evaluations as f64);
        noise_ms.push(noisy.milliseconds);
        accumulate_curve(&mut curve_noise, space, truth, &noisy, settings.trials)?;
        trials.push(measured);
    }
    progress(settings.trials, settings.trials);
    // The space optimum from the reference's starts, and from the best known-pose
    // registration's code (the least error the space reaches must not be above what a
    // registration found).
    let unscaled_truth: Vec<DVec3> = truth.iter().map(|p| *p / floor_scale).collect();
    let mut optimum = reference.optimum;
    if let Some((_, code)) = best_known {
        optimum = optimum.min(
            space_optimum(space, &unscaled_truth, &code, 30, reference.free_scale)?.error
                * floor_scale,
        );
    }
    let stat = |of: fn(&Trial) -> f64| Stat::of(&trials.iter().map(of).collect::<Vec<_>>());
    let oracle = measure.error(oracle_vertices);
    Ok(Row {
        category: category.into(),
        instance: name.into(),
        oracle,
        space_optimum: optimum,
        oracle_code_sd: largest_sd(space, &reference.oracle_code),
        oracle_chamfer: chamfer(test_vertices, oracle_vertices),
        known_pose: stat(|t| t.known_pose),
        known_pose_chamfer: Stat::of(&known_ch),
        pose_noise_worst: trials.iter().map(|t| t.pose_noise).fold(0.0, f64::max),
        pose_noise_placed: stat(|t| t.pose_noise_placed),
        pose_noise_seen: stat(|t| t.pose_noise_seen),
        oracle_both_ways: measure.both_ways(oracle_vertices, oracle)?,
        pose_noise_seen_both_ways: stat(|t| t.pose_noise_seen_both_ways),
        pose_noise: stat(|t| t.pose_noise),
        pose_noise_chamfer: Stat::of(&noisy_ch),
        from_truth: settings.from_truth.then(|| Stat::of(&from_truth)),
        iterations: Stat::of(&iterations).mean,
        ms: Stat::of(&ms).mean,
        noise_iterations: Stat::of(&noise_iterations).mean,
        noise_ms: Stat::of(&noise_ms).mean,
        curve_known,
        curve_noise,
        ms_per_iteration: Stat::of(&ms_per_iteration).mean,
        trials,
    })
}

/// The error (against the surface sample `truth`) of the deformed canonical of each code
/// times its scale (`scales`, one per code: a registration's `codes` and `scales`),
/// measured once for a run of equal codes and scales (the pose alignment keeps the mean
/// shape, and a rejected BFGS step keeps the last code).
pub fn error_curve(
    space: &ShapeSpace,
    truth: &[DVec3],
    codes: &[Vec<f64>],
    scales: &[f64],
) -> Result<Vec<f64>> {
    let mut curve: Vec<f64> = Vec::with_capacity(codes.len());
    for (t, (code, &scale)) in codes.iter().zip(scales).enumerate() {
        let error = match curve.last() {
            Some(&last) if codes[t - 1] == *code && scales[t - 1] == scale => last,
            _ => {
                let vertices: Vec<DVec3> = space
                    .vertices(code)?
                    .into_iter()
                    .map(|v| v * scale)
                    .collect();
                surface_error(truth, &vertices, space.canonical.triangles())
            }
        };
        curve.push(error);
    }
    Ok(curve)
}

/// Adds error-after-each-iteration / trials (a stopped run holds its last value).
fn accumulate_curve(
    curve: &mut [f64],
    space: &ShapeSpace,
    truth: &[DVec3],
    result: &vkdr::register::Registration,
    trials: usize,
) -> Result<()> {
    let errors = error_curve(space, truth, &result.codes, &result.scales)?;
    let mut last = f64::NAN;
    for (t, slot) in curve.iter_mut().enumerate() {
        last = errors.get(t).copied().unwrap_or(last);
        *slot += last / trials as f64;
    }
    Ok(())
}

fn hash(s: &str) -> u64 {
    let mut digest = crate::reference::Fnv::default();
    digest.add(s.as_bytes());
    digest.0
}

#[cfg(test)]
mod tests {
    use super::settings::trial_cameras;
    use super::*;
    use glam::DMat3;

    /// Further views share the first's elevation unless told to draw their own, which stay
    /// in the elevation range, differ from it, and leave the first camera and the azimuths
    /// as they were.
    #[test]
    fn trial_cameras_share_or_draw_elevations() {
        let settings = EvalSettings {
            views: 3,
            ..EvalSettings::default()
        };
        let own = EvalSettings {
            own_elevations: true,
            ..settings.clone()
        };
        let (lo, hi) = settings.elevation;
        for seed in 0..50 {
            let shared = trial_cameras(&mut Rng::new(seed), &settings);
            let drawn = trial_cameras(&mut Rng::new(seed), &own);
            assert_eq!(shared.len(), 3);
            assert!(shared.iter().all(|c| c.1 == shared[0].1), "{shared:?}");
            assert_eq!(drawn[0], shared[0]);
            for (d, s) in drawn.iter().zip(&shared).skip(1) {
                assert_eq!(d.0, s.0);
                assert!((lo..hi).contains(&d.1) && d.1 != shared[0].1, "{drawn:?}");
            }
        }
    }

    /// Every count of views the command line accepts ends, seed after seed, with every two
    /// views at least the separation apart (with five or six, rejection alone could hang).
    #[test]
    fn view_offsets_keep_every_pair_apart_for_one_to_six_views() {
        let tau = std::f64::consts::TAU;
        for views in 1..=6 {
            for seed in 0..200 {
                let mut rng = Rng::new(seed);
                let mut all = vec![0.0];
                all.extend(view_offsets(&mut rng, views));
                assert_eq!(all.len(), views);
                for (i, a) in all.iter().enumerate() {
                    for b in &all[i + 1..] {
                        let d = (a - b).rem_euclid(tau);
                        assert!(
                            d.min(tau - d) >= MIN_VIEW_SEPARATION - 1e-9,
                            "{views} views, seed {seed}: {all:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn surface_distance_finds_faces_edges_and_corners() {
        let v = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let t = [[0u32, 1, 2]];
        let cases = [
            (DVec3::new(0.2, 0.2, 0.5), 0.5),           // above the face
            (DVec3::new(-1.0, -1.0, 0.0), 2f64.sqrt()), // beyond corner a
            (DVec3::new(0.5, -2.0, 0.0), 2.0),          // beyond edge ab
            (DVec3::new(1.0, 1.0, 0.0), 0.5f64.sqrt()), // beyond edge bc
            (DVec3::new(3.0, 0.0, 4.0), (4.0f64 + 16.0).sqrt()), // beyond corner b
        ];
        for (p, want) in cases {
            let got = surface_error(&[p], &v, &t);
            assert!((got - want).abs() < 1e-12, "{p}: {got} vs {want}");
        }
        // Points sampled on a mesh lie on it.
        let mesh = Mesh::bottle(12);
        let sample = surface_sample(&mesh, 200, 3);
        assert!(surface_error(&sample, &mesh.points(), mesh.triangles()) < 1e-7);
    }

    /// A unit square's centroid is its middle and its root-mean-square radius sqrt(1/6),
    /// split into two triangles or into four about an off-centre vertex alike; scaled and
    /// moved, the radius scales and the centroid moves.
    #[test]
    fn surface_extent_is_the_surface_s_not_its_vertices() {
        let corners = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ];
        let two: Vec<DVec3> = corners.iter().map(|&c| DVec3::from_array(c)).collect();
        let mut fan = two.clone();
        fan.push(DVec3::new(0.2, 0.7, 0.0));
        let cases = [
            (two, vec![[0, 1, 2], [0, 2, 3]]),
            (fan, vec![[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]),
        ];
        for (vertices, triangles) in cases {
            let (centre, size) = surface_extent(&vertices, &triangles);
            assert!(
                (centre - DVec3::new(0.5, 0.5, 0.0)).length() < 1e-12,
                "{centre}"
            );
            assert!((size - (1.0f64 / 6.0).sqrt()).abs() < 1e-12, "{size}");
            let moved: Vec<DVec3> = vertices.iter().map(|&v| 3.0 * v + DVec3::Z).collect();
            let (centre, size) = surface_extent(&moved, &triangles);
            assert!(
                (centre - DVec3::new(1.5, 1.5, 1.0)).length() < 1e-12,
                "{centre}"
            );
            assert!((size - 3.0 * (1.0f64 / 6.0).sqrt()).abs() < 1e-12, "{size}");
        }
    }

    /// A shape shifted in its frame is placed back exactly; a differently shaped one keeps
    /// its shape and takes the reference's centroid.
    #[test]
    fn placed_like_moves_to_the_reference_centroid() {
        let mesh = Mesh::bottle(12);
        let reference = mesh.points();
        let shift = DVec3::new(0.01, -0.02, 0.005);
        let shifted: Vec<DVec3> = reference.iter().map(|&v| v + shift).collect();
        let truth = surface_sample(&mesh, 300, 4);
        let error = |v: &[DVec3]| surface_error(&truth, v, mesh.triangles());
        assert!(error(&shifted) > 1e-3);
        assert!(error(&placed_like(&shifted, &reference)) < 1e-9);
        let stretched: Vec<DVec3> = reference
            .iter()
            .map(|&v| DVec3::new(1.1 * v.x, v.y, v.z) + shift)
            .collect();
        let placed = placed_like(&stretched, &reference);
        assert!((centroid(&placed) - centroid(&reference)).length() < 1e-12);
        assert!(((placed[0] - placed[1]) - (stretched[0] - stretched[1])).length() < 1e-12);
    }

    /// A shape shifted in its frame with the pose shifted back is seen where the true one
    /// is; the true shape at a wrong pose is seen off by that pose.
    #[test]
    fn as_seen_compares_where_the_registration_put_the_shape() {
        let mesh = Mesh::bottle(12);
        let truth = surface_sample(&mesh, 300, 5);
        let error = |v: &[DVec3]| surface_error(&truth, v, mesh.triangles());
        let pose = Pose::new([0.02, -0.01, 0.6], [0.3, -0.2, 0.1]).unwrap();
        let shift = DVec3::new(0.01, -0.02, 0.005);
        let shifted: Vec<DVec3> = mesh.points().iter().map(|&v| v + shift).collect();
        let back = Pose::at([-shift.x, -shift.y, -shift.z]).followed_by(&pose);
        assert!(error(&shifted) > 1e-3);
        assert!(error(&as_seen(&shifted, back, pose)) < 1e-9);
        let off = Pose::at([0.0, 0.0, 0.004]).followed_by(&pose);
        let seen = error(&as_seen(&mesh.points(), off, pose));
        assert!(seen > 1e-4 && seen <= 0.004 + 1e-9, "{seen}");
    }

    /// The reverse error sees what the test instance lacks: a shape stretched to twice the
    /// test's height is near the test surface from the test's side but far from it from
    /// its own; the same shape as the test is near both ways.
    #[test]
    fn reverse_error_sees_parts_the_test_lacks() {
        let test = Mesh::bottle(16);
        let truth = surface_sample(&test, 400, 7);
        let triangles = test.triangles();
        let same = test.points();
        assert!(reverse_error(&same, triangles, &test, 3).unwrap() < 1e-9);
        let low = same.iter().map(|v| v.y).fold(f64::INFINITY, f64::min);
        let taller: Vec<DVec3> = same
            .iter()
            .map(|&v| DVec3::new(v.x, low + 2.0 * (v.y - low), v.z))
            .collect();
        let height = same.iter().map(|v| v.y).fold(f64::NEG_INFINITY, f64::max) - low;
        let forward = surface_error(&truth, &taller, triangles);
        let reverse = reverse_error(&taller, triangles, &test, 3).unwrap();
        assert!(reverse > 0.1 * height, "{reverse} of {height}");
        assert!(reverse > 3.0 * forward, "{reverse} against {forward}");
    }

    /// Looking down from elevation e, the up axis lies 90 deg - e from the line of sight; at
    /// azimuth 90 deg the camera looks along the object's x axis; a pose error is the
    /// rotation and translation put in.
    #[test]
    fn views_and_pose_errors_are_measured_in_the_object_frame() {
        let deg = |a: f64| a.to_radians();
        for (azimuth, elevation) in [(0.0, 10.0), (deg(130.0), 35.0), (deg(250.0), 60.0)] {
            let pose = view_pose(azimuth, deg(elevation), 0.7);
            let angle = line_of_sight_angle(pose, DVec3::Y).to_degrees();
            assert!(
                (angle - (90.0 - elevation)).abs() < 1e-9,
                "{angle} at {elevation}"
            );
        }
        // Any up axis: the same elevation above its plane, seen from its side (looking down
        // it), the azimuth about it.
        for up in [DVec3::Y, DVec3::Z, -DVec3::Z, DVec3::X, -DVec3::Y] {
            for (azimuth, elevation) in [(0.3, 10.0), (deg(200.0), 55.0)] {
                let pose = view_pose_up(up, azimuth, deg(elevation), 0.7);
                let angle = line_of_sight_angle(pose, up).to_degrees();
                assert!((angle - (90.0 - elevation)).abs() < 1e-9, "{up} {angle}");
                let camera = -(pose.rotation_matrix().transpose() * pose.translation);
                assert!(camera.dot(up) > 0.0, "{up}: camera below the object");
            }
        }
        assert!(line_of_sight_angle(view_pose(deg(90.0), 0.0, 0.7), DVec3::X) < 1e-7);
        let side = line_of_sight_angle(view_pose(0.0, 0.0, 0.7), -DVec3::X);
        assert!((side - deg(90.0)).abs() < 1e-9);

        let drill = crate::dataset::instance("drill", &mut Rng::new(3)).unwrap();
        assert_eq!(extent_axes(&drill), [DVec3::X, DVec3::Y, DVec3::Z]);

        let truth = view_pose(deg(40.0), deg(30.0), 0.7);
        assert!(pose_error(truth, truth).0 < 1e-7 && pose_error(truth, truth).1 == 0.0);
        let turn = DMat3::from_axis_angle(DVec3::new(1.0, 2.0, -0.5).normalize(), deg(7.0));
        let moved = Pose {
            translation: truth.translation + DVec3::new(0.03, -0.04, 0.0),
            rotation: glam::DQuat::from_mat3(&(turn * truth.rotation_matrix())).to_scaled_axis(),
        };
        let (rotation, translation) = pose_error(moved, truth);
        assert!(
            (rotation - deg(7.0)).abs() < 1e-9,
            "{}",
            rotation.to_degrees()
        );
        assert!((translation - 0.05).abs() < 1e-12);
    }

    /// Bottles and bowls are symmetric about their up axis; mugs (their handle), spray
    /// bottles and drills are not; a turn about the up axis of a symmetric object is no
    /// rotation error, any other rotation still is.
    #[test]
    fn rotation_error_up_to_symmetry() {
        let deg = |a: f64| a.to_radians();
        let bottle = surface_sample(&Mesh::bottle(24), 800, 1);
        assert!(symmetric_about(&bottle, DVec3::Y));
        assert!(!symmetric_about(&bottle, DVec3::X));
        for (category, symmetric) in [
            ("bottle", true),
            ("bowl", true),
            ("mug", false),
            ("spray_bottle", false),
            ("drill", false),
        ] {
            for seed in 0..3 {
                let instance = crate::dataset::instance(category, &mut Rng::new(seed)).unwrap();
                let sample = surface_sample(&instance, 2000, 1);
                assert_eq!(
                    symmetric_about(&sample, DVec3::Y),
                    symmetric,
                    "{category} {seed}"
                );
            }
        }

        let truth = view_pose(deg(40.0), deg(30.0), 0.7);
        let turned = |axis: DVec3, angle: f64| Pose {
            translation: truth.translation,
            rotation: glam::DQuat::from_mat3(
                &(truth.rotation_matrix() * DMat3::from_axis_angle(axis, deg(angle))),
            )
            .to_scaled_axis(),
        };
        let about_up = turned(DVec3::Y, 73.0);
        assert!((pose_error(about_up, truth).0 - deg(73.0)).abs() < 1e-9);
        assert!(symmetric_rotation_error(about_up, truth, DVec3::Y) < deg(0.01));
        let tilted = turned(DVec3::X, 12.0);
        let e = symmetric_rotation_error(tilted, truth, DVec3::Y);
        assert!((e - deg(12.0)).abs() < deg(0.01), "{}", e.to_degrees());
    }

    /// The error curve measures every code, once for a run of equal codes.
    #[test]
    fn error_curve_follows_the_codes() {
        let space = vkdr::shape::random_space(&mut Rng::new(5), 4, 2);
        let canonical = &space.canonical;
        let truth = surface_sample(canonical, 300, 1);
        let (a, b) = (vec![0.0, 0.0], space.training_codes[1].clone());
        let codes = vec![a.clone(), a.clone(), b.clone(), b.clone(), a.clone()];
        let curve = error_curve(&space, &truth, &codes, &[1.0; 5]).unwrap();
        assert_eq!(curve.len(), codes.len());
        for (code, error) in codes.iter().zip(&curve) {
            let want = surface_error(
                &truth,
                &space.vertices(code).unwrap(),
                canonical.triangles(),
            );
            assert_eq!(*error, want);
        }
        assert!(
            curve[0] != curve[2],
            "different codes, different errors: {curve:?}"
        );
    }
}
