//! The evaluation's settings: the camera, the trials' views and noise, the schedules, and
//! the poses the trials are seen from.

use glam::{DMat3, DVec3};

use crate::dataset::Rng;
use vkdr::camera::{Camera, Pose};
use vkdr::cpd::CpdParams;
use vkdr::diff::{DepthLoss, Shading};
use vkdr::register::RegisterParams;

/// The evaluation's camera and trial settings.
#[derive(Clone, Debug)]
pub struct EvalSettings {
    pub camera: Camera,
    /// Camera-to-object distance, metres.
    pub distance: f64,
    pub trials: usize,
    pub seed: u64,
    /// Elevation of the views above the horizon, radians (drawn uniformly).
    pub elevation: (f64, f64),
    /// Pose noise: uniform +-translation (x, y) and +-rotation about each axis.
    pub translation_noise: f64,
    pub rotation_noise: f64,
    pub known_pose: RegisterParams,
    pub pose_noise: RegisterParams,
    pub dims: usize,
    pub cpd: CpdParams,
    /// Also register each trial with the pose optimised as with pose noise but starting
    /// at the true pose (no alignment): how far the silhouette's own optimum lies from the
    /// truth, apart from the start.
    pub from_truth: bool,
    /// Observe and compare Lambert shading (besides the mask, which the pose alignment
    /// compares); overrides the registration parameters' own.
    pub shading: Option<Shading>,
    /// The dataset's up axis (its `info.json`, [`crate::check::Info`]): views are drawn
    /// from the hemisphere it points into.
    pub up: DVec3,
    /// Observe depth too (the test instance's rendered depth), compared with this loss;
    /// the pose's z translation is then optimised with pose noise.
    pub depth: Option<DepthLoss>,
    /// Standard deviation (metres) of Gaussian noise added to every measured depth.
    pub depth_noise: f64,
    /// Cameras per trial: the first as with one view, the others at the same distance and
    /// elevation (or their own, [`EvalSettings::own_elevations`]), at seeded azimuths at
    /// least [`MIN_VIEW_SEPARATION`] from every other view's, their poses relative to the
    /// first known. With more than one the z translation is optimised with pose noise.
    pub views: usize,
    /// Draw each view after the first its own elevation from [`EvalSettings::elevation`]
    /// (a head and a wrist camera) instead of sharing the first's.
    pub own_elevations: bool,
    /// Keep z at its true value even where depth or a second view observe it (as with one
    /// mask, where the distance is given): separates what the observation tells from what
    /// the free distance costs.
    pub fix_z: bool,
    /// Starts per trial with pose noise: the noisy start and the starts turned about the
    /// object's up axis by multiples of the rotation noise
    /// ([`vkdr::register::turned_starts`]); the noisy start is registered and the others'
    /// turns are tried on its fit, by the loss (what the images tell, not the error)
    /// (`Registrar::register_with_turns`); the milliseconds are the wall time and the
    /// iterations count every evaluation.
    pub starts: usize,
    /// A real frame's ways, rendered into each trial's first view: a box in front of the
    /// object's left half (the mask shows the visible part; with depth the box's depth is
    /// measured, without it the box's pixels are unknown), ...
    pub occluder: bool,
    /// ... the table the object stands on (in the depth only: a plane under the test
    /// instance's lowest point, normal to the up axis), ...
    pub table: bool,
    /// ... holes in the depth (this fraction of the pixels, in clusters of a few pixels'
    /// radius), ...
    pub depth_holes: f64,
    /// ... and a test instance of another size than the training set's (each test mesh
    /// scaled by this about its origin).
    pub test_scale: f64,
    /// Which way is up with pose noise: the true pose's up axis (a known table or IMU), or
    /// the support plane fitted in the observed depth (needs `table`); None: not used.
    pub gravity: Option<GravitySource>,
    /// Radians of tilt from up that cost nothing ([`vkdr::register::Gravity::tolerance`]).
    pub tilt_tolerance: f64,
    /// Where gravity from the depth finds no support plane: register without gravity
    /// (true; the trial says so) or fail the unit (false).
    pub gravity_fallback: bool,
}

/// Where [`EvalSettings::gravity`] comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GravitySource {
    /// The true up direction (a robot's table plane or IMU).
    Known,
    /// The support plane fitted in the observed depth ([`vkdr::support`]).
    FromDepth,
}

/// Azimuth and elevation (radians) of each camera of one trial: the first at a random
/// azimuth and elevation, the others at [`view_offsets`] from it, at its elevation or
/// (with [`EvalSettings::own_elevations`]) each at its own, drawn after the offsets so that
/// shared-elevation trials keep their random stream.
pub(super) fn trial_cameras(rng: &mut Rng, settings: &EvalSettings) -> Vec<(f64, f64)> {
    let azimuth = rng.range(0.0, std::f64::consts::TAU);
    let elevation = rng.range(settings.elevation.0, settings.elevation.1);
    let offsets = view_offsets(rng, settings.views);
    let mut cameras = vec![(azimuth, elevation)];
    for offset in offsets {
        let own = match settings.own_elevations {
            true => rng.range(settings.elevation.0, settings.elevation.1),
            false => elevation,
        };
        cameras.push((azimuth + offset, own));
    }
    cameras
}

/// The least azimuth between two views of one trial, radians (60 degrees).
pub const MIN_VIEW_SEPARATION: f64 = std::f64::consts::PI / 3.0;

impl EvalSettings {
    /// The registrations' parameters with the pose known, with what the trials observe.
    pub fn known_pose_params(&self) -> RegisterParams {
        RegisterParams {
            shading: self.shading,
            depth: self.depth,
            ..self.known_pose
        }
    }

    /// The registrations' parameters with pose noise, with what the trials observe: depth
    /// or a second view observe the distance, so z is optimised too (unless `fix_z`).
    pub fn pose_noise_params(&self) -> RegisterParams {
        let observes_z = (self.depth.is_some() || self.views > 1) && !self.fix_z;
        RegisterParams {
            shading: self.shading,
            depth: self.depth,
            optimize_z: self.pose_noise.optimize_z || observes_z,
            ..self.pose_noise
        }
    }

    /// What each trial observes, in words (the table states it).
    pub fn observation(&self) -> String {
        let mut parts = vec![if self.shading.is_some() {
            "mask and shading"
        } else {
            "mask"
        }
        .to_string()];
        if self.depth.is_some() {
            parts.push(if self.depth_noise > 0.0 {
                format!("depth (noise {:.1} mm)", 1e3 * self.depth_noise)
            } else {
                "depth (noise-free)".into()
            });
        }
        let views = if self.views > 1 {
            format!(
                "{} views (azimuths at least 60 degrees apart, {}, relative poses known)",
                self.views,
                if self.own_elevations {
                    "elevations drawn per view"
                } else {
                    "a shared elevation"
                }
            )
        } else {
            "one view".into()
        };
        let z = if self.fix_z && (self.depth.is_some() || self.views > 1) {
            "; the distance (z) known"
        } else {
            ""
        };
        if self.depth.is_some() && self.depth_holes > 0.0 {
            parts.push(format!(
                "{:.0}% of the depth missing in clusters",
                100.0 * self.depth_holes
            ));
        }
        if self.table {
            parts.push("the table under the object in the depth".into());
        }
        if self.occluder {
            parts.push(if self.depth.is_some() {
                "a box in front of the object's left half (occlusion found from the depth)".into()
            } else {
                "a box in front of the object's left half (its pixels unknown)".into()
            });
        }
        if self.test_scale != 1.0 {
            parts.push(format!("test instances scaled by {}", self.test_scale));
        }
        let gravity = match self.gravity {
            None => String::new(),
            Some(source) => format!(
                "; up known{} within {:.1} deg with pose noise",
                match source {
                    GravitySource::Known => "",
                    GravitySource::FromDepth => " from the table fitted in the depth",
                },
                self.tilt_tolerance.to_degrees()
            ),
        };
        format!("{}; {views}{z}{gravity}", parts.join(", "))
    }
}

/// Azimuth offsets (radians) of the views after the first, every two views at least
/// [`MIN_VIEW_SEPARATION`] apart. Up to four views, each is drawn uniformly until it lies
/// far enough from every view before it (three views always leave a gap of 120 degrees,
/// so this ends). Five or six views may not fit after random draws (four at 90 degrees
/// leave no room): there the gaps between neighbours are the separation plus a uniform
/// share of the rest of the circle.
pub(super) fn view_offsets(rng: &mut Rng, views: usize) -> Vec<f64> {
    let tau = std::f64::consts::TAU;
    if views > 4 {
        let mut cuts: Vec<f64> = (1..views).map(|_| rng.uniform()).collect();
        cuts.sort_by(f64::total_cmp);
        let slack = tau - views as f64 * MIN_VIEW_SEPARATION;
        let mut at = 0.0;
        let mut previous = 0.0;
        return cuts
            .iter()
            .map(|&cut| {
                at += MIN_VIEW_SEPARATION + slack * (cut - previous);
                previous = cut;
                at
            })
            .collect();
    }
    let apart = |a: f64, b: f64| {
        let d = (a - b).rem_euclid(tau);
        d.min(tau - d) >= MIN_VIEW_SEPARATION - 1e-12
    };
    let mut offsets = vec![0.0];
    while offsets.len() < views {
        let candidate = rng.range(0.0, tau);
        if offsets.iter().all(|&o| apart(o, candidate)) {
            offsets.push(candidate);
        }
    }
    offsets.split_off(1)
}

/// A standard normal draw (Box-Muller).
pub(super) fn gaussian(rng: &mut Rng) -> f64 {
    let u = rng.uniform().max(f64::MIN_POSITIVE);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.uniform()).cos()
}

impl Default for EvalSettings {
    fn default() -> Self {
        Self {
            camera: Camera::new(500.0, 500.0, 160.0, 120.0, 320, 240).expect("valid camera"),
            distance: 0.7,
            trials: 10,
            seed: 0,
            elevation: (10f64.to_radians(), 60f64.to_radians()),
            translation_noise: 0.05,
            rotation_noise: vkdr::register::START_TURN,
            known_pose: RegisterParams::known_pose(320 * 240),
            pose_noise: RegisterParams::free_pose(320 * 240),
            dims: 5,
            from_truth: false,
            shading: None,
            cpd: CpdParams::default(),
            up: DVec3::Y,
            depth: None,
            depth_noise: 0.0,
            views: 1,
            own_elevations: false,
            fix_z: false,
            starts: vkdr::register::DEFAULT_STARTS,
            occluder: false,
            table: false,
            depth_holes: 0.0,
            test_scale: 1.0,
            gravity: None,
            tilt_tolerance: vkdr::register::TILT_TOLERANCE,
            gravity_fallback: true,
        }
    }
}

/// The object-to-camera pose looking at the object (y up) from azimuth `azimuth` and
/// elevation `elevation` at `distance`.
pub fn view_pose(azimuth: f64, elevation: f64, distance: f64) -> Pose {
    // Object y up to image up (camera -y), then the azimuth about the object's up axis,
    // then tilt so the camera looks down from `elevation`: the object's up axis leans
    // towards the camera (up to 2026-11 the tilt went the other way, and every view looked
    // up from below the horizon; `tests` now checks the side).
    let r = DMat3::from_rotation_x(elevation)
        * DMat3::from_rotation_x(std::f64::consts::PI)
        * DMat3::from_rotation_y(azimuth);
    Pose {
        translation: DVec3::new(0.0, 0.0, distance),
        rotation: glam::DQuat::from_mat3(&r).to_scaled_axis(),
    }
}

/// [`view_pose`] for an object whose up axis is `up` (any unit vector): the camera looks
/// down from `elevation` above the plane normal to `up`.
pub fn view_pose_up(up: DVec3, azimuth: f64, elevation: f64, distance: f64) -> Pose {
    let pose = view_pose(azimuth, elevation, distance);
    let to_y_up = glam::DQuat::from_rotation_arc(up.normalize(), DVec3::Y);
    Pose {
        translation: pose.translation,
        rotation: (glam::DQuat::from_scaled_axis(pose.rotation) * to_y_up).to_scaled_axis(),
    }
}

/// `pose` disturbed by uniform noise: +-`translation` in camera x and y, and a rotation of
/// +-`rotation` about each camera axis applied on the left.
pub fn noisy_pose(pose: Pose, rng: &mut Rng, translation: f64, rotation: f64) -> Pose {
    let mut noise = |a: f64| rng.range(-a, a);
    let dt = DVec3::new(noise(translation), noise(translation), 0.0);
    let dr = DVec3::new(noise(rotation), noise(rotation), noise(rotation));
    Pose {
        translation: pose.translation + dt,
        rotation: glam::DQuat::from_mat3(
            &(DMat3::from_euler(glam::EulerRot::XYZ, dr.x, dr.y, dr.z) * pose.rotation_matrix()),
        )
        .to_scaled_axis(),
    }
}
