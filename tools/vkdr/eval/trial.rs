//! One trial of a test instance, in two steps: [`register_trial`] registers its observation
//! (with the pose known, from the truth where asked, from pose noise) and
//! [`Measure::trial`] measures what the registrations found against the test instance.

use glam::DVec3;

use crate::dataset::Rng;
use vkdr::camera::Pose;
use vkdr::error::Result;
use vkdr::gpu::Context;
use vkdr::mesh::Mesh;
use vkdr::raster::View;
use vkdr::register::{Gravity, Job, Plan, Registrar, Registration};
use vkdr::shape::ShapeSpace;

use super::{
    angle_between, as_seen, largest_sd, line_of_sight_angle, noisy_pose, placed_like, pose_error,
    reverse_error, surface_error, surface_extent, symmetric_rotation_error, EvalSettings,
    GravitySource, Trial, TrialScene, TrialSource,
};

/// What one trial's registrations were given and found.
pub struct Registered {
    /// The first camera's azimuth and elevation about the object (radians), the true
    /// pose and the first view.
    pub azimuth: f64,
    pub elevation: f64,
    pub pose: Pose,
    pub view: View,
    pub observation: vkdr::Observation,
    /// The up direction the registrations were given, and whether gravity from the depth
    /// found no support plane and the trial ran without it.
    pub gravity: Option<Gravity>,
    pub gravity_fallback: bool,
    /// With the pose known (a frame's is registered once and reused).
    pub known: Registration,
    /// Pose and shape from the true pose, with `EvalSettings::from_truth`.
    pub from_truth: Option<Registration>,
    /// From the noisy start (and its turns).
    pub noisy: Registration,
}

/// The up direction a trial's registrations are given: none, the truth's, or the support
/// plane's in the depth; `true` where that plane was not found and the settings fall back
/// to none.
fn trial_gravity(
    settings: &EvalSettings,
    observation: &vkdr::Observation,
    pose: Pose,
) -> Result<(Option<Gravity>, bool)> {
    match settings.gravity {
        None => Ok((None, false)),
        Some(GravitySource::Known) => Ok((
            Some(Gravity {
                up: settings.up,
                direction: pose.rotation_matrix() * settings.up,
                tolerance: settings.tilt_tolerance,
            }),
            false,
        )),
        Some(GravitySource::FromDepth) => {
            if observation.depth.is_none() {
                return Err(vkdr::Error::InvalidInput(
                    "gravity from the depth needs depth".into(),
                ));
            }
            match Gravity::from_depth(observation, settings.up, settings.tilt_tolerance) {
                Ok((gravity, _)) => Ok((Some(gravity), false)),
                Err(_) if settings.gravity_fallback => Ok((None, true)),
                Err(e) => Err(e),
            }
        }
    }
}

/// Registers one trial's `scene` as the settings say: with the pose known (a frame's once:
/// `known_once` keeps it for the next trials), from the truth where asked, and from a
/// start drawn from `rng` with the settings' pose noise.
#[allow(clippy::too_many_arguments)] // the trial, its instance's context and the frame's cache
pub fn register_trial(
    ctx: &Context,
    registrar: &Registrar,
    space: &ShapeSpace,
    settings: &EvalSettings,
    source: TrialSource,
    scene: TrialScene,
    known_once: &mut Option<Registration>,
    rng: &mut Rng,
) -> Result<Registered> {
    let TrialScene {
        azimuth,
        elevation,
        pose,
        view,
        others,
        observed,
    } = scene;
    let observation = vkdr::Observation {
        camera: view.camera,
        others,
        mask: observed.mask,
        depth: observed.depth,
        shaded: observed.shaded,
    };
    observation.check_visible()?;
    let (gravity, gravity_fallback) = trial_gravity(settings, &observation, pose)?;
    let job = |view: View| Job {
        gravity,
        ..observation.job(space, view.pose)
    };
    let (known_pose, pose_noise) = (settings.known_pose_params(), settings.pose_noise_params());
    // A frame is the same in every trial: its registration with the pose known once.
    let known = match (&*known_once, source) {
        (Some(known), TrialSource::Frame { .. }) => known.clone(),
        _ => registrar.register(ctx, job(view), &known_pose, |_, _| {})?,
    };
    if matches!(source, TrialSource::Frame { .. }) {
        *known_once = Some(known.clone());
    }
    let from_truth = if settings.from_truth {
        let params = vkdr::register::RegisterParams {
            align: 0,
            ..pose_noise
        };
        Some(registrar.register(ctx, job(view), &params, |_, _| {})?)
    } else {
        None
    };
    let start = noisy_pose(
        pose,
        rng,
        settings.translation_noise,
        settings.rotation_noise,
    );
    // The noisy start and it turned about the up axis by the rotation noise.
    let plan = Plan {
        starts: settings.starts,
        turn: settings.rotation_noise,
        gravity,
        ..Plan::new(start, settings.up, pose_noise)
    };
    let noisy = registrar.register_observation(ctx, space, &observation, &plan, |_, _| {})?;
    Ok(Registered {
        azimuth,
        elevation,
        pose,
        view,
        observation,
        gravity,
        gravity_fallback,
        known,
        from_truth,
        noisy,
    })
}

/// A test instance as the trials' measurements need it.
pub struct Measure<'a> {
    space: &'a ShapeSpace,
    /// The instance's name (it seeds the reverse error's surface sample).
    name: &'a str,
    test: &'a Mesh,
    /// The surface sample the errors are measured from.
    truth: &'a [DVec3],
    settings: &'a EvalSettings,
    /// Whether the instance is symmetric about its up axis, and the vertices that break
    /// that symmetry (a mug's handle).
    symmetric: bool,
    asymmetric: &'a [DVec3],
    /// The test instance's vertices, its surface's centroid and size
    /// ([`surface_extent`]), and its bounding box's axes, longest first.
    pub test_vertices: Vec<DVec3>,
    test_centre: DVec3,
    test_size: f64,
    axes: [DVec3; 3],
}

impl<'a> Measure<'a> {
    /// `test` measured against `space` through the surface sample `truth`, with its
    /// symmetry (`symmetric`, `asymmetric` as in [`super::Reference`]).
    pub fn new(
        space: &'a ShapeSpace,
        name: &'a str,
        test: &'a Mesh,
        truth: &'a [DVec3],
        settings: &'a EvalSettings,
        symmetric: bool,
        asymmetric: &'a [DVec3],
    ) -> Self {
        let test_vertices = test.points();
        let (test_centre, test_size) = surface_extent(&test_vertices, test.triangles());
        Self {
            space,
            name,
            test,
            truth,
            settings,
            symmetric,
            asymmetric,
            test_vertices,
            test_centre,
            test_size,
            axes: super::extent_axes(test),
        }
    }

    /// The error of registered vertices (object frame) against the test surface.
    pub fn error(&self, vertices: &[DVec3]) -> f64 {
        surface_error(self.truth, vertices, self.space.canonical.triangles())
    }

    /// The mean of the error both ways, test to shape (`forward`, already measured) and
    /// shape to test.
    pub fn both_ways(&self, vertices: &[DVec3], forward: f64) -> Result<f64> {
        let reverse = reverse_error(
            vertices,
            self.space.canonical.triangles(),
            self.test,
            super::hash(self.name),
        )?;
        Ok(0.5 * (forward + reverse))
    }

    /// What one trial's registrations found, against the test instance at its true pose.
    pub fn trial(&self, registered: &Registered, oracle_vertices: &[DVec3]) -> Result<Trial> {
        let Registered {
            known,
            noisy: result,
            ..
        } = registered;
        let (pose, up) = (registered.pose, self.settings.up);
        let triangles = self.space.canonical.triangles();
        let (test_vertices, test_centre, test_size, axes) = (
            &self.test_vertices,
            self.test_centre,
            self.test_size,
            self.axes,
        );
        let true_up = pose.rotation_matrix() * up;

        let known_centre = surface_extent(&known.vertices, triangles).0;
        let (rotation_error, translation_error) = pose_error(result.pose, pose);
        let rotation_error_symmetric = if self.symmetric {
            symmetric_rotation_error(result.pose, pose, up)
        } else {
            rotation_error
        };
        // The first view's mask, unknown pixels (negative) as 0.
        let visible: Vec<f32> = registered
            .observation
            .first_mask()
            .iter()
            .map(|&m| m.max(0.0))
            .collect();
        let seen = as_seen(&result.vertices, result.pose, pose);
        let (seen_centre, seen_size) = surface_extent(&seen, triangles);
        let pose_noise_seen = self.error(&seen);
        let symmetric_in_view = self.symmetric
            || crate::metrics::seen_share(
                self.asymmetric,
                pose,
                &registered.view.camera,
                &visible,
                registered.observation.first_depth(),
            ) < 0.1;
        let iou = crate::metrics::iou(
            &crate::metrics::OrientedBox::of(&result.vertices, result.pose),
            &crate::metrics::OrientedBox::of(test_vertices, pose),
            up,
            symmetric_in_view,
        );
        Ok(Trial {
            azimuth: registered.azimuth,
            elevation: registered.elevation,
            long_axis_angle: line_of_sight_angle(pose, axes[0]),
            short_axis_angle: line_of_sight_angle(pose, axes[2]),
            known_pose: self.error(&known.vertices),
            pose_noise: self.error(&result.vertices),
            pose_noise_placed: self.error(&placed_like(&result.vertices, oracle_vertices)),
            pose_noise_seen,
            pose_noise_seen_both_ways: self.both_ways(&seen, pose_noise_seen)?,
            known_pose_loss: known.loss,
            pose_noise_loss: result.loss,
            rotation_error,
            rotation_error_symmetric,
            translation_error,
            known_pose_on_bound: known.on_bound,
            pose_noise_on_bound: result.on_bound,
            tilt: angle_between(result.pose.rotation_matrix() * up, true_up),
            z_error: (pose.rotation_matrix() * (seen_centre - test_centre)).z,
            size: seen_size / test_size,
            z_error_origin: result.pose.translation.z - pose.translation.z,
            z_error_known: (pose.rotation_matrix() * (known_centre - test_centre)).z,
            scale: result.scale,
            gravity_error: registered
                .gravity
                .map_or(0.0, |g| angle_between(g.direction, true_up)),
            gravity_fallback: registered.gravity_fallback,
            add_s: crate::metrics::add_s(
                test_vertices,
                pose,
                &result.vertices,
                triangles,
                result.pose,
            ),
            centroid_error: (seen_centre - test_centre).length(),
            rotation_error_nocs: crate::metrics::rotation_error(
                result.pose,
                pose,
                up,
                symmetric_in_view,
            ),
            iou,
            known_pose_code_sd: largest_sd(self.space, &known.code),
            pose_noise_code_sd: largest_sd(self.space, &result.code),
        })
    }
}
