//! `vkdr eval`'s reports: the tables (markdown, JSON), trials.csv and the speed against
//! error plot.

use std::path::Path;

use anyhow::{Context as _, Result};

use vkdr::io::{write_atomically, write_json, write_png};
use vkdr_app::eval::{self, EvalSettings, Row, Trial};
use vkdr_app::plot::{Plot, PALETTE};

/// Each category's means over its test instances, and the ratios of those means.
/// The rows' categories in order (rows come grouped by category).
fn categories(rows: &[Row]) -> Vec<&str> {
    let mut categories: Vec<&str> = rows.iter().map(|r| r.category.as_str()).collect();
    categories.dedup();
    categories
}

fn category_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "\nPer category (means over its test instances; ratio = mean error / mean oracle error; \
         / optimum = mean error / mean space optimum):\n\n\
         | category | oracle | space optimum | known pose | ratio | / optimum | pose noise | ratio | / optimum | worst noise trial | noise, placed (ratio) | noise, as seen (ratio) | as seen, both ways (ratio) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for category in categories(rows) {
        let of: Vec<&Row> = rows.iter().filter(|r| r.category == category).collect();
        let mean = |f: &dyn Fn(&Row) -> f64| of.iter().map(|r| f(r)).sum::<f64>() / of.len() as f64;
        let oracle = mean(&|r| r.oracle);
        let optimum = mean(&|r| r.space_optimum);
        let (known, noise) = (mean(&|r| r.known_pose.mean), mean(&|r| r.pose_noise.mean));
        let worst = of.iter().map(|r| r.pose_noise_worst).fold(0.0, f64::max);
        let placed = mean(&|r| r.pose_noise_placed.mean);
        let seen = mean(&|r| r.pose_noise_seen.mean);
        let both_ways = mean(&|r| r.pose_noise_seen_both_ways.mean);
        let oracle_both_ways = mean(&|r| r.oracle_both_ways);
        md.push_str(&format!(
            "| {category} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} ({:.2}) |\n",
            1e3 * oracle,
            1e3 * optimum,
            1e3 * known,
            known / oracle,
            known / optimum,
            1e3 * noise,
            noise / oracle,
            noise / optimum,
            1e3 * worst,
            1e3 * placed,
            placed / oracle,
            1e3 * seen,
            seen / oracle,
            1e3 * both_ways,
            both_ways / oracle_both_ways
        ));
    }
    md.push_str(&view_table(rows));
    md.push_str(&preference_table(rows));
    md.push_str(&code_table(rows));
    md
}

/// Where the registered codes lie against the training set, per instance: the largest
/// code coordinate in training standard deviations (the oracle's, and the mean and largest
/// over the trials with the pose known and with pose noise), and the trials that ended
/// with a code coordinate on the optimiser's bound.
fn code_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "\nShape codes (the largest code coordinate in training standard deviations: the oracle's, \
         then the mean over the trials, largest in brackets; on bound: trials that ended with a code \
         coordinate on the optimiser's bound, known pose / pose noise):\n\n\
         | category | instance | oracle (SD) | known pose (SD) | pose noise (SD) | on bound |\n|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let n = r.trials.len().max(1) as f64;
        let sd = |f: fn(&Trial) -> f64| {
            let mean = r.trials.iter().map(f).sum::<f64>() / n;
            let most = r.trials.iter().map(f).fold(0.0, f64::max);
            format!("{mean:.1} ({most:.1})")
        };
        let bound = |f: fn(&Trial) -> usize| r.trials.iter().filter(|t| f(t) > 0).count();
        md.push_str(&format!(
            "| {} | {} | {:.1} | {} | {} | {} / {} |\n",
            r.category,
            r.instance,
            r.oracle_code_sd,
            sd(|t| t.known_pose_code_sd),
            sd(|t| t.pose_noise_code_sd),
            bound(|t| t.known_pose_on_bound),
            bound(|t| t.pose_noise_on_bound),
        ));
    }
    md
}

/// The pose with pose noise, per instance: what a robot acting on it meets. Ratios of the
/// error as seen to the space optimum, and both ways to the larger of the oracle's error
/// both ways and a quarter pixel's footprint at the object's distance (a sub-pixel
/// residual against a 0.04 mm oracle is no "30x").
fn pose_table(rows: &[Row], settings: &EvalSettings) -> String {
    let footprint = 0.25 * settings.distance / settings.camera.fx.min(settings.camera.fy);
    let mut md = format!(
        "\nPose with pose noise (rotation up to the symmetry about the up axis where the instance has it; tilt: the angle \
         between the registered and the true up axis; z: the error in the camera's z of the surface's area-weighted centroid, registered at its pose against the test surface at the true pose, with that of the object frame's origin (a diagnostic: the shape modes move the surface about it) in trials.csv; size: the registered surface's root-mean-square distance from its centroid over the test surface's, 1 where the registration found the object's size, by the scale or by the shape; as seen / opt.: the error as seen over \
         the larger of the space optimum and a quarter pixel's footprint at the object's distance; both ways / floor: the error as seen both ways over the larger of the oracle's both ways and a \
         quarter pixel's footprint at the object's distance, {:.3} mm; means, largest in brackets):\n\n\
         | category | instance | rotation (deg) | tilt (deg) | z (mm) | scale | size | as seen / opt. | both ways / floor |\n|---|---|---|---|---|---|---|---|---|\n",
        1e3 * footprint
    );
    for r in rows {
        let n = r.trials.len().max(1) as f64;
        let mean = |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).sum::<f64>() / n;
        let most = |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).fold(0.0, f64::max);
        let least =
            |f: &dyn Fn(&Trial) -> f64| r.trials.iter().map(f).fold(f64::INFINITY, f64::min);
        let floor = r.oracle_both_ways.max(footprint);
        md.push_str(&format!(
            "| {} | {} | {:.1} ({:.1}) | {:.1} ({:.1}) | {:.1} ({:.1}) | {:.3} ({:.3}-{:.3}) | {:.3} ({:.3}-{:.3}) | {:.2} ({:.2}) | {:.2} ({:.2}) |\n",
            r.category,
            r.instance,
            mean(&|t| t.rotation_error_symmetric.to_degrees()),
            most(&|t| t.rotation_error_symmetric.to_degrees()),
            mean(&|t| t.tilt.to_degrees()),
            most(&|t| t.tilt.to_degrees()),
            mean(&|t| 1e3 * t.z_error.abs()),
            most(&|t| 1e3 * t.z_error.abs()),
            mean(&|t| t.scale),
            least(&|t| t.scale),
            most(&|t| t.scale),
            mean(&|t| t.size),
            least(&|t| t.size),
            most(&|t| t.size),
            mean(&|t| t.pose_noise_seen) / r.space_optimum.max(footprint),
            most(&|t| t.pose_noise_seen) / r.space_optimum.max(footprint),
            mean(&|t| t.pose_noise_seen_both_ways) / floor,
            most(&|t| t.pose_noise_seen_both_ways) / floor,
        ));
    }
    md
}

/// Whether the pose-noise fit of `trial` ended with a lower loss than the fit at the true
/// pose: the images prefer what it found to the truth's best code.
fn images_prefer_noise_fit(trial: &Trial) -> bool {
    trial.pose_noise_loss < trial.known_pose_loss
}

/// Pose-noise errors split by what the images prefer: trials whose fit explains the images
/// better than the best code at the true pose (its error is what the observation leaves
/// open: no optimiser would bring it nearer the truth) against trials that ended above it
/// (a local minimum: more starts or iterations can help).
fn preference_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "\nPose noise by what the images prefer (lower loss: the pose-noise fit's final loss is below that of the fit at the true pose, \
         so the images prefer it to the best code at the truth and an error there is what the observation leaves open; \
         higher: it stopped in a local minimum; ratio = mean over the trials of error / the instance's oracle error, \
         as seen in brackets):\n\n\
         | category | lower-loss trials | ratio (as seen) | higher-loss trials | ratio (as seen) |\n|---|---|---|---|---|\n",
    );
    for category in categories(rows) {
        let trials = category_trials(rows, category);
        let summary = |lower: bool| {
            let of: Vec<_> = trials
                .iter()
                .filter(|(_, t)| images_prefer_noise_fit(t) == lower)
                .collect();
            if of.is_empty() {
                return "0 | -".to_string();
            }
            let n = of.len() as f64;
            let ratio = of.iter().map(|(r, t)| t.pose_noise / r.oracle).sum::<f64>() / n;
            let seen = of
                .iter()
                .map(|(r, t)| t.pose_noise_seen / r.oracle)
                .sum::<f64>()
                / n;
            format!("{} | {ratio:.2} ({seen:.2})", of.len())
        };
        md.push_str(&format!(
            "| {category} | {} | {} |\n",
            summary(true),
            summary(false)
        ));
    }
    md
}

/// Every trial of `category`'s rows, with its row.
fn category_trials<'a>(rows: &'a [Row], category: &str) -> Vec<(&'a Row, &'a Trial)> {
    rows.iter()
        .filter(|r| r.category == category)
        .flat_map(|r| r.trials.iter().map(move |t| (r, t)))
        .collect()
}

/// Views whose line of sight lies within this angle of the plane of a test instance's two
/// longest axes count as edge-on.
const EDGE_ON: f64 = 30.0;

/// Pose-noise errors split by view: edge-on views (rotations about the object's shortest
/// axis move it mostly along the line of sight) against the rest.
fn view_table(rows: &[Row]) -> String {
    let mut md = format!(
        "\nPose noise by view (edge-on: the line of sight within {EDGE_ON:.0} deg of the plane of the test instance's two longest \
         bounding-box axes, where rotations about its shortest axis are seen only foreshortened; \
         ratio = mean over the trials of error / the instance's oracle error; rotation: mean final rotation error, \
         up to turns about the up axis for rotationally symmetric instances, raw in brackets):\n\n\
         | category | edge-on trials | ratio | rotation (deg) | other trials | ratio | rotation (deg) |\n|---|---|---|---|---|---|---|\n"
    );
    for category in categories(rows) {
        let trials = category_trials(rows, category);
        let summary = |edge_on: bool| {
            let of: Vec<_> = trials
                .iter()
                .filter(|(_, t)| (t.short_axis_angle.to_degrees() > 90.0 - EDGE_ON) == edge_on)
                .collect();
            if of.is_empty() {
                return "0 | - | -".to_string();
            }
            let n = of.len() as f64;
            let ratio = of.iter().map(|(r, t)| t.pose_noise / r.oracle).sum::<f64>() / n;
            let mean = |f: &dyn Fn(&Trial) -> f64| of.iter().map(|(_, t)| f(t)).sum::<f64>() / n;
            let symmetric = mean(&|t| t.rotation_error_symmetric.to_degrees());
            let raw = mean(&|t| t.rotation_error.to_degrees());
            format!("{} | {ratio:.2} | {symmetric:.1} ({raw:.1})", of.len())
        };
        md.push_str(&format!(
            "| {category} | {} | {} |\n",
            summary(true),
            summary(false)
        ));
    }
    md
}

/// One line per trial: the view, the errors, and the pose error with pose noise.
pub fn trials_csv(rows: &[Row]) -> String {
    let mut csv = String::from(
        "category,instance,trial,azimuth_deg,elevation_deg,long_axis_angle_deg,short_axis_angle_deg,known_pose,pose_noise,pose_noise_placed,pose_noise_seen,rotation_error_deg,rotation_error_symmetric_deg,translation_error,known_pose_on_bound,pose_noise_on_bound,known_pose_loss,pose_noise_loss,pose_noise_seen_both_ways,tilt_deg,z_error,scale,gravity_error_deg,z_error_origin,size,gravity_fallback,add_s,centroid_error,rotation_error_nocs_deg,iou,z_error_known,known_pose_code_sd,pose_noise_code_sd\n",
    );
    for r in rows {
        for (i, t) in r.trials.iter().enumerate() {
            csv.push_str(&format!(
                "{},{},{i},{:.2},{:.2},{:.2},{:.2},{:e},{:e},{:e},{:e},{:.3},{:.3},{:e},{},{},{:e},{:e},{:e},{:.3},{:e},{:.5},{:.3},{:e},{:.5},{},{:e},{:e},{:.3},{:.4},{:e},{:.3},{:.3}\n",
                r.category,
                r.instance,
                t.azimuth.to_degrees(),
                t.elevation.to_degrees(),
                t.long_axis_angle.to_degrees(),
                t.short_axis_angle.to_degrees(),
                t.known_pose,
                t.pose_noise,
                t.pose_noise_placed,
                t.pose_noise_seen,
                t.rotation_error.to_degrees(),
                t.rotation_error_symmetric.to_degrees(),
                t.translation_error,
                t.known_pose_on_bound,
                t.pose_noise_on_bound,
                t.known_pose_loss,
                t.pose_noise_loss,
                t.pose_noise_seen_both_ways,
                t.tilt.to_degrees(),
                t.z_error,
                t.scale,
                t.gravity_error.to_degrees(),
                t.z_error_origin,
                t.size,
                t.gravity_fallback,
                t.add_s,
                t.centroid_error,
                t.rotation_error_nocs.to_degrees(),
                t.iou,
                t.z_error_known,
                t.known_pose_code_sd,
                t.pose_noise_code_sd,
            ));
        }
    }
    csv
}

pub fn write_reports(
    out: &Path,
    rows: &[Row],
    settings: &EvalSettings,
    device: &str,
) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let c = &settings.camera;
    let (known, noisy) = (&settings.known_pose, &settings.pose_noise);
    let held = noisy.holds_unseen(settings.views);
    let mask_first = settings
        .known_pose_params()
        .masks_first()
        .map(|first| first.iterations);
    let mut md = format!(
        "# Registration error (Table 1)\n\nObserved: {}.\n\nDevice: {device}. Camera: fx {} fy {} cx {} cy {}, {}x{} px; object at {} m; views from the hemisphere of each category's up axis (info.json) \
         (elevation {:.0}-{:.0} deg) at random azimuth; {} trials per instance (seed {}); shape spaces of up to {} dimensions (fewer where the training instances span fewer). Pose noise: uniform +-{} cm in x and y, +-{:.0} deg about each axis. \
         Error: mean distance (mm) from {} points sampled uniformly on the test surface to the deformed canonical's surface; \
         oracle: least-squares latent fit to CPD of the canonical onto the true instance (the paper's); \
         space optimum: the code with the least error itself for the true instance (a direct 3D fit: the best the shape space can do); \
         ratio = error / oracle error; / opt. = error / space optimum; chamfer = symmetric chamfer distance of the vertex sets (mm); \
         placed: the pose-noise error after moving each registered shape so that its vertex centroid is the oracle fit's \
         (one view cannot tell a shape shifted in its frame from a shifted pose); \
         as seen: the pose-noise error of each registered shape at its registered pose against the test surface at the true pose \
         (the distance in the camera frame, what a robot acting on the registration meets; the oracle's is the same in either frame); \
         as seen, both ways: the mean of that error and the one from points sampled on the registered surface to the test surface \
         (which also sees parts the registration has and the test instance has not), its ratio to the oracle's error both ways. \
         Registration: known pose, {}{} for {} iterations ({} loss); pose noise, the pose aligned alone for {} iterations ({} loss), \
         {}then pose and shape by {} for {} ({}).{}{}\n\n\
         | category | instance | oracle | space optimum | known pose | ratio | / opt. | pose noise | ratio | / opt. | worst noise trial | noise, placed | noise, as seen | chamfer oracle / known / noise | iterations known / noise | ms known / noise |{}\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|{}\n",
        settings.observation(),
        c.fx, c.fy, c.cx, c.cy, c.width, c.height, settings.distance,
        settings.elevation.0.to_degrees(), settings.elevation.1.to_degrees(), settings.trials, settings.seed, settings.dims,
        100.0 * settings.translation_noise, settings.rotation_noise.to_degrees(), eval::SAMPLE_POINTS,
        mask_first.map_or(String::new(), |first| {
            format!("the mask alone for {first} iterations, then ")
        }),
        known.optimizer.name(), known.iterations, known.loss.name(), noisy.align, noisy.align_loss.name(),
        settings.pose_noise_params().reach().map_or(String::new(), |reach| {
            format!(
                "then {} for {} with the mask and the depth at {} times the depth scale, ",
                if noisy.optimize_scale { "with the shape" } else { "alone" },
                reach.iterations,
                vkdr::register::REACH
            )
        }),
        noisy.optimizer.name(), noisy.iterations,
        if noisy.code_prior > 0.0 {
            format!(
                "{} loss, plus a code prior of weight {:.3e} in training SD, both conditions{}",
                noisy.loss.name(),
                noisy.code_prior,
                if held {
                    format!(
                        "; after the fit the directions of the code the images hardly constrain (curvature below {} times the prior's) \
                         are held by a prior {} times as strong and the fit goes on",
                        vkdr::register::HELD_BELOW,
                        vkdr::register::HOLD
                    )
                } else {
                    String::new()
                }
            )
        } else {
            format!("{} loss", noisy.loss.name())
        },
        settings.shading.map_or(String::new(), |s| format!(
            " Observed: the mask and grey Lambert shading (light towards {:?} in the camera frame, ambient {}); \
             the registrations compare the shading (mse) after the alignment.",
            s.light, s.ambient
        )),
        if settings.starts > 1 {
            format!(" Pose noise: {} starts per trial (the noisy start, and it turned about the up axis by {}): the noisy start registered, the others' turns tried on its fit, the joint fit again from a turn that scores 5% lower; its iterations and ms count it all.",
                settings.starts,
                vkdr::register::start_turns(settings.starts, settings.rotation_noise)[1..].iter().map(|t| format!("{:+.0} deg", t.to_degrees())).collect::<Vec<_>>().join(", "))
        } else {
            String::new()
        } + if settings.from_truth { " From true pose: pose and shape as with pose noise, but starting at the true pose (no alignment)." } else { "" },
        if settings.from_truth { " from true pose | ratio |" } else { "" },
        if settings.from_truth { "---|---|" } else { "" },
    );
    let mut csv = String::from("category,instance,oracle,known_pose_mean,known_pose_std,pose_noise_mean,pose_noise_std,iterations,ms,oracle_chamfer,known_pose_chamfer,pose_noise_chamfer,noise_iterations,noise_ms,from_truth_mean,from_truth_std,pose_noise_placed_mean,pose_noise_placed_std,space_optimum,pose_noise_seen_mean,pose_noise_seen_std,oracle_both_ways,pose_noise_seen_both_ways_mean,pose_noise_seen_both_ways_std\n");
    let shading_json = settings
        .shading
        .map(|s| serde_json::json!({ "light": s.light, "ambient": s.ambient }));
    let depth_json = settings.depth.map(|d| {
        serde_json::json!({ "scale": d.scale, "weight": d.weight, "noise": settings.depth_noise })
    });
    let stat = |s: &eval::Stat| serde_json::json!({ "mean": s.mean, "std": s.std });
    let mut json = Vec::new();
    for r in rows {
        md.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.2} +- {:.2} | {:.2} | {:.2} | {:.2} +- {:.2} | {:.2} | {:.2} | {:.2} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} / {:.2} / {:.2} | {:.1} / {:.1} | {:.0} / {:.0} |{}\n",
            r.category, r.instance, 1e3 * r.oracle, 1e3 * r.space_optimum, 1e3 * r.known_pose.mean, 1e3 * r.known_pose.std, r.known_pose.mean / r.oracle,
            r.known_pose.mean / r.space_optimum,
            1e3 * r.pose_noise.mean, 1e3 * r.pose_noise.std, r.pose_noise.mean / r.oracle, r.pose_noise.mean / r.space_optimum, 1e3 * r.pose_noise_worst,
            1e3 * r.pose_noise_placed.mean, r.pose_noise_placed.mean / r.oracle,
            1e3 * r.pose_noise_seen.mean, r.pose_noise_seen.mean / r.oracle,
            1e3 * r.oracle_chamfer, 1e3 * r.known_pose_chamfer.mean, 1e3 * r.pose_noise_chamfer.mean, r.iterations, r.noise_iterations, r.ms, r.noise_ms,
            r.from_truth.map_or(String::new(), |f| format!(" {:.2} +- {:.2} | {:.2} |", 1e3 * f.mean, 1e3 * f.std, f.mean / r.oracle))
        ));
        csv.push_str(&format!(
            "{},{},{:e},{:e},{:e},{:e},{:e},{},{:.3},{:e},{:e},{:e},{},{:.3},{},{},{:e},{:e},{:e},{:e},{:e},{:e},{:e},{:e}\n",
            r.category,
            r.instance,
            r.oracle,
            r.known_pose.mean,
            r.known_pose.std,
            r.pose_noise.mean,
            r.pose_noise.std,
            r.iterations,
            r.ms,
            r.oracle_chamfer,
            r.known_pose_chamfer.mean,
            r.pose_noise_chamfer.mean,
            r.noise_iterations,
            r.noise_ms,
            r.from_truth
                .map_or(String::new(), |f| format!("{:e}", f.mean)),
            r.from_truth
                .map_or(String::new(), |f| format!("{:e}", f.std)),
            r.pose_noise_placed.mean,
            r.pose_noise_placed.std,
            r.space_optimum,
            r.pose_noise_seen.mean,
            r.pose_noise_seen.std,
            r.oracle_both_ways,
            r.pose_noise_seen_both_ways.mean,
            r.pose_noise_seen_both_ways.std,
        ));
        json.push(serde_json::json!({
            "category": r.category,
            "instance": r.instance,
            "observation": settings.observation(),
            "views": settings.views,
            "oracle": r.oracle,
            "space_optimum": r.space_optimum,
            "known_pose": stat(&r.known_pose),
            "pose_noise": stat(&r.pose_noise),
            "iterations": r.iterations,
            "ms": r.ms,
            "chamfer": {
                "oracle": r.oracle_chamfer,
                "known_pose": r.known_pose_chamfer.mean,
                "pose_noise": r.pose_noise_chamfer.mean,
            },
            "noise_iterations": r.noise_iterations,
            "noise_ms": r.noise_ms,
            "from_truth": r.from_truth.as_ref().map(stat),
            "pose_noise_placed": stat(&r.pose_noise_placed),
            "pose_noise_seen": stat(&r.pose_noise_seen),
            "oracle_both_ways": r.oracle_both_ways,
            "pose_noise_seen_both_ways": stat(&r.pose_noise_seen_both_ways),
            // Trials whose pose-noise fit ended with a lower loss than the known-pose fit.
            "pose_noise_lower_loss": r.trials.iter().filter(|t| images_prefer_noise_fit(t)).count(),
            "shading": shading_json,
            "depth": depth_json,
            "code_prior": noisy.code_prior,
            "hold_unseen": held,
            "mask_first": mask_first.unwrap_or(0),
            "pose_noise_pose": {
                "rotation_symmetric_deg": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.rotation_error_symmetric.to_degrees()).collect::<Vec<_>>())),
                "tilt_deg": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.tilt.to_degrees()).collect::<Vec<_>>())),
                "z_error_abs": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.z_error.abs()).collect::<Vec<_>>())),
                "scale": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.scale).collect::<Vec<_>>())),
                "size": stat(&eval::Stat::of(&r.trials.iter().map(|t| t.size).collect::<Vec<_>>())),
            },
        }));
    }
    md.push_str(&category_table(rows));
    md.push_str(&pose_table(rows, settings));
    write_atomically(&out.join("table.md"), md.as_bytes())?;
    write_atomically(&out.join("table.csv"), csv.as_bytes())?;
    write_atomically(&out.join("trials.csv"), trials_csv(rows).as_bytes())?;
    write_json(&out.join("table.json"), &serde_json::Value::Array(json))?;

    // Speed against error: mean error relative to the oracle after each iteration, at each
    // condition's own mean time per iteration (the pose-noise runs include the alignment).
    let curve = |pick: &dyn Fn(&Row) -> &Vec<f64>, ms: &dyn Fn(&Row) -> f64| -> Vec<(f64, f64)> {
        let n = rows.iter().map(|r| pick(r).len()).min().unwrap_or(0);
        let ms = rows.iter().map(ms).sum::<f64>() / rows.len().max(1) as f64;
        (0..n)
            .map(|t| {
                (
                    (t + 1) as f64 * ms,
                    rows.iter().map(|r| pick(r)[t] / r.oracle).sum::<f64>() / rows.len() as f64,
                )
            })
            .collect()
    };
    let plot = Plot::new(
        "speed against error (all test instances)",
        "cumulative time (ms)",
        "error / oracle error",
    )
    .series(
        "known pose",
        PALETTE[0],
        curve(&|r| &r.curve_known, &|r| r.ms / r.iterations.max(1.0)),
    )
    .series(
        "pose noise",
        PALETTE[1],
        curve(&|r| &r.curve_noise, &|r| {
            r.noise_ms / r.noise_iterations.max(1.0)
        }),
    );
    write_png(
        &out.join("speed_vs_error.png"),
        &image::DynamicImage::ImageRgb8(plot.render()),
    )?;
    Ok(())
}
