//! The paper's Table 1 on a category dataset: per held-out test instance, the oracle error
//! (the shape space's best fit to the true 3D instance) next to registration from a
//! rendered mask with the pose known and with pose noise, over seeded trials, plus
//! timings and the error after every iteration (speed against error).
//!
//! Error: for every vertex of the test instance, the distance to the nearest vertex of
//! the deformed canonical mesh, averaged (metres). The symmetric chamfer distance (the
//! mean of both directions' mean nearest distances) is reported too.

use glam::{DMat3, DVec3};

use crate::camera::{Camera, Pose};
use crate::cpd::CpdParams;
use crate::dataset::Rng;
use crate::error::Result;
use crate::gpu::Context;
use crate::loss::Loss;
use crate::mesh::Mesh;
use crate::raster::{Outputs, View};
use crate::register::{RegisterParams, Registrar};
use crate::shape::ShapeSpace;

/// Mean over `a` of the distance to the nearest point of `b`.
pub fn mean_nearest(a: &[DVec3], b: &[DVec3]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::NAN;
    }
    a.iter()
        .map(|p| {
            b.iter()
                .map(|q| (*p - *q).length_squared())
                .fold(f64::MAX, f64::min)
                .sqrt()
        })
        .sum::<f64>()
        / a.len() as f64
}

/// Symmetric chamfer distance: the mean of both directions' mean nearest distances.
pub fn chamfer(a: &[DVec3], b: &[DVec3]) -> f64 {
    0.5 * (mean_nearest(a, b) + mean_nearest(b, a))
}

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
            rotation_noise: 15f64.to_radians(),
            known_pose: RegisterParams {
                iterations: 30,
                ..RegisterParams::default()
            },
            pose_noise: RegisterParams {
                iterations: 30,
                pose_every: 3,
                loss: Loss::Distance,
                ..RegisterParams::default()
            },
            dims: 5,
            cpd: CpdParams::default(),
        }
    }
}

/// The object-to-camera pose looking at the object (y up) from azimuth `azimuth` and
/// elevation `elevation` at `distance`.
pub fn view_pose(azimuth: f64, elevation: f64, distance: f64) -> Pose {
    // Object y up to image up (camera -y), then the azimuth about the object's up axis,
    // then tilt so the camera looks down from `elevation`.
    let r = DMat3::from_rotation_x(-elevation)
        * DMat3::from_rotation_x(std::f64::consts::PI)
        * DMat3::from_rotation_y(azimuth);
    Pose {
        translation: DVec3::new(0.0, 0.0, distance),
        rotation: glam::DQuat::from_mat3(&r).to_scaled_axis(),
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

/// Mean and (sample) standard deviation.
#[derive(Clone, Copy, Debug, Default)]
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
#[derive(Clone, Debug)]
pub struct Row {
    pub category: String,
    pub instance: String,
    pub oracle: f64,
    pub oracle_chamfer: f64,
    pub known_pose: Stat,
    pub known_pose_chamfer: Stat,
    pub pose_noise: Stat,
    pub pose_noise_chamfer: Stat,
    /// Largest pose-noise error over the trials (divergence check).
    pub pose_noise_worst: f64,
    pub iterations: f64,
    pub ms: f64,
    /// Mean error after each iteration (known pose, pose noise) and mean ms per iteration.
    pub curve_known: Vec<f64>,
    pub curve_noise: Vec<f64>,
    pub ms_per_iteration: f64,
}

/// The mask of `mesh` rendered through `view`.
pub fn render_mask(
    ctx: &Context,
    registrar: &Registrar,
    mesh: &Mesh,
    view: View,
) -> Result<Vec<f32>> {
    let g = registrar
        .renderer()
        .rasterizer()
        .render(ctx, mesh, &[view], Outputs::Ids)?;
    Ok(g.ids
        .iter()
        .map(|&id| if id > 0 { 1.0 } else { 0.0 })
        .collect())
}

/// Evaluates one test instance against a built shape space.
pub fn evaluate_instance(
    ctx: &Context,
    registrar: &Registrar,
    space: &ShapeSpace,
    category: &str,
    name: &str,
    test: &Mesh,
    settings: &EvalSettings,
    mut progress: impl FnMut(usize, usize),
) -> Result<Row> {
    let truth = test.points();
    let oracle_code = space.oracle_code(ctx, &truth, &settings.cpd)?;
    let oracle_vertices = space.vertices(&oracle_code)?;
    let mut rng = Rng::new(settings.seed ^ hash(name));
    let (mut known, mut known_ch, mut noisy, mut noisy_ch, mut iterations, mut ms) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut curve_known = vec![0.0; settings.known_pose.iterations];
    let mut curve_noise = vec![0.0; settings.pose_noise.iterations];
    let mut ms_per_iteration = Vec::new();
    for trial in 0..settings.trials {
        progress(trial, settings.trials);
        let azimuth = rng.range(0.0, std::f64::consts::TAU);
        let elevation = rng.range(settings.elevation.0, settings.elevation.1);
        let pose = view_pose(azimuth, elevation, settings.distance);
        let view = View {
            camera: settings.camera,
            pose,
        };
        let mask = render_mask(ctx, registrar, test, view)?;

        let result =
            registrar.register(ctx, space, &mask, view, &settings.known_pose, |_, _| {})?;
        known.push(mean_nearest(&truth, &result.vertices));
        known_ch.push(chamfer(&truth, &result.vertices));
        iterations.push(result.iterations as f64);
        ms.push(result.milliseconds);
        ms_per_iteration.push(result.milliseconds / result.iterations as f64);
        accumulate_curve(
            &mut curve_known,
            space,
            &truth,
            &result.codes,
            settings.trials,
        )?;

        let start = noisy_pose(
            pose,
            &mut rng,
            settings.translation_noise,
            settings.rotation_noise,
        );
        let result = registrar.register(
            ctx,
            space,
            &mask,
            View {
                camera: settings.camera,
                pose: start,
            },
            &settings.pose_noise,
            |_, _| {},
        )?;
        noisy.push(mean_nearest(&truth, &result.vertices));
        noisy_ch.push(chamfer(&truth, &result.vertices));
        accumulate_curve(
            &mut curve_noise,
            space,
            &truth,
            &result.codes,
            settings.trials,
        )?;
    }
    progress(settings.trials, settings.trials);
    Ok(Row {
        category: category.into(),
        instance: name.into(),
        oracle: mean_nearest(&truth, &oracle_vertices),
        oracle_chamfer: chamfer(&truth, &oracle_vertices),
        known_pose: Stat::of(&known),
        known_pose_chamfer: Stat::of(&known_ch),
        pose_noise_worst: noisy.iter().copied().fold(0.0, f64::max),
        pose_noise: Stat::of(&noisy),
        pose_noise_chamfer: Stat::of(&noisy_ch),
        iterations: Stat::of(&iterations).mean,
        ms: Stat::of(&ms).mean,
        curve_known,
        curve_noise,
        ms_per_iteration: Stat::of(&ms_per_iteration).mean,
    })
}

/// Adds error-after-each-iteration / trials (a stopped run holds its last value).
fn accumulate_curve(
    curve: &mut [f64],
    space: &ShapeSpace,
    truth: &[DVec3],
    codes: &[Vec<f64>],
    trials: usize,
) -> Result<()> {
    let mut last = f64::NAN;
    for (t, slot) in curve.iter_mut().enumerate() {
        if let Some(code) = codes.get(t) {
            last = mean_nearest(truth, &space.vertices(code)?);
        }
        *slot += last / trials as f64;
    }
    Ok(())
}

fn hash(s: &str) -> u64 {
    s.bytes().fold(0xcbf29ce484222325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100000001b3)
    })
}
