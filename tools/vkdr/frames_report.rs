//! `vkdr eval-frames`' tables: what the frames were (cameras, sizes, the sensor's depth),
//! how they were registered, vkdr's errors and the field's metrics per unit and per
//! category, the units that failed and why, and speed against error per category.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context as _, Result};

use vkdr::io::{write_atomically, write_json, write_png};
use vkdr_app::eval::{EvalSettings, GravitySource, Row, Trial};
use vkdr_app::metrics;
use vkdr_app::plot::{Plot, PALETTE};

/// Writes OUT/table.md, table.json, trials.csv and speed_vs_error.png for `rows` and
/// `failures`; `frames` describes what was observed (cameras, sizes, depth).
pub fn write(
    out: &Path,
    rows: &[Row],
    failures: &[String],
    settings: &EvalSettings,
    frames: &str,
    device: &str,
) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let noisy = settings.pose_noise_params();
    let gravity = match settings.gravity {
        None => "no gravity".to_string(),
        Some(GravitySource::Known) => "gravity: the true up axis".to_string(),
        Some(GravitySource::FromDepth) => format!(
            "gravity: the support plane fitted in each frame's depth around the mask ({}), the up axis kept within {:.1} deg of its normal",
            if settings.gravity_fallback {
                "where none is found, that frame without gravity (`gravity fallback` in trials.csv)"
            } else {
                "where none is found, the unit fails"
            },
            settings.tilt_tolerance.to_degrees()
        ),
    };
    let mut md = format!(
        "# Registration on observed frames\n\n\
         Frames: {frames}. Device: {device}.\n\n\
         Registration: from each frame's visible mask (pixels hidden by objects in front unknown) and its depth; \
         {} trials per unit (seed {}), each from the true pose disturbed by +-{:.0} cm in x and y and +-{:.0} deg about each axis, \
         {} starts turned about the category's up axis; the shape's scale {}; {gravity}; {}; \
         the pose known: one registration per unit. Shape spaces of up to {} dimensions from each category's training instances.\n\n\
         Errors (mm): known pose: the mean distance from {} points on the test model's surface to the registered surface, with the pose known; \
         as seen: the same for the registration from pose noise, each surface at its pose (camera frame); \
         / opt.: over the space optimum (the least error the category's shape space reaches for this model). \
         rotation: the rotation error as NOCS counts it (up to turns about the up axis where the model is symmetric or the frame does not show what breaks its symmetry, a mug's handle); \
         tilt: the angle between the registered and the true up axis; z: the error in depth of the surface's centroid; z known: the same with the pose known (the shape's part of z: what the frame leaves unseen, a base out of the image or behind an object in front, the shape space fills in); size: the registered surface's size over the model's. \
         ADD-S: the mean over the model's points (up to {}) at the true pose of the distance to the registered surface at its pose \
         (instance-level methods report it with the exact model; here it holds the shape's error too); \
         AUC: its area under the accuracy curve up to {:.0} cm (PoseCNN's YCB-Video protocol), per cent; \
         5 deg 2 cm, ...: the share of trials with the rotation (as above) and the distance between the surfaces' centroids within both; \
         IoU: the 3D intersection over union of the registered and the true oriented bounding boxes (for symmetric views the best turn of the registered box about the up axis).\n\n",
        settings.trials,
        settings.seed,
        100.0 * settings.translation_noise,
        settings.rotation_noise.to_degrees(),
        settings.starts,
        if noisy.optimize_scale {
            "fitted (one uniform scale, from the depth)"
        } else {
            "fixed at the training set's"
        },
        match noisy.detail {
            0 => "rendered and compared at the frame's pixels".to_string(),
            d => format!(
                "an object over {} pixels across rendered and compared at a coarser step (at least {d} pixels across it, each pixel the mean of the frame's)",
                2 * d
            ),
        },
        settings.dims,
        vkdr_app::eval::SAMPLE_POINTS,
        metrics::ADD_S_POINTS,
        100.0 * metrics::AUC_LIMIT,
    );
    md.push_str(&unit_table(rows));
    md.push_str(&category_table(rows));
    if !failures.is_empty() {
        md.push_str(&format!(
            "\n## Failed units ({})\n\nEvery unit was tried; these ended with an error:\n\n",
            failures.len()
        ));
        for f in failures {
            md.push_str(&format!("- {f}\n"));
        }
    }
    write_atomically(&out.join("table.md"), md.as_bytes())?;
    write_json(
        &out.join("table.json"),
        &serde_json::json!({ "rows": rows, "failures": failures, "frames": frames, "device": device }),
    )?;
    write_atomically(
        &out.join("trials.csv"),
        crate::eval_report::trials_csv(rows).as_bytes(),
    )?;
    write_png(
        &out.join("speed_vs_error.png"),
        &image::DynamicImage::ImageRgb8(speed_plot(rows).render()),
    )?;
    Ok(())
}

/// The mean of `of` over the trials.
fn mean(trials: &[&Trial], of: impl Fn(&Trial) -> f64) -> f64 {
    trials.iter().map(|t| of(t)).sum::<f64>() / trials.len().max(1) as f64
}

fn unit_table(rows: &[Row]) -> String {
    let mut md = String::from(
        "| category | unit | known pose | / opt. | as seen | / opt. | rotation (deg) | tilt (deg) | abs z | abs z known | size | ADD-S | IoU | ms | gravity |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let trials: Vec<&Trial> = r.trials.iter().collect();
        let fallbacks = trials.iter().filter(|t| t.gravity_fallback).count();
        md.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} | {:.1} | {:.1} | {:.1} | {:.3} | {:.1} | {:.2} | {:.0} | {} |\n",
            r.category,
            r.instance,
            1e3 * r.known_pose.mean,
            r.known_pose.mean / r.space_optimum,
            1e3 * r.pose_noise_seen.mean,
            r.pose_noise_seen.mean / r.space_optimum,
            mean(&trials, |t| t.rotation_error_nocs.to_degrees()),
            mean(&trials, |t| t.tilt.to_degrees()),
            1e3 * mean(&trials, |t| t.z_error.abs()),
            1e3 * mean(&trials, |t| t.z_error_known.abs()),
            mean(&trials, |t| t.size),
            1e3 * mean(&trials, |t| t.add_s),
            mean(&trials, |t| t.iou),
            r.noise_ms,
            if fallbacks > 0 {
                "none found: without".to_string()
            } else {
                "used".to_string()
            },
        ));
    }
    md
}

fn category_table(rows: &[Row]) -> String {
    let mut by_category: BTreeMap<&str, Vec<&Row>> = BTreeMap::new();
    for r in rows {
        by_category.entry(&r.category).or_default().push(r);
    }
    let mut md = String::from(
        "\nPer category (over every trial of its units):\n\n\
         | category | units | trials | known pose | as seen | / opt. | ADD-S | AUC (10 cm) | 5 deg 2 cm | 5 deg 5 cm | 10 deg 5 cm | IoU > 25% | IoU > 50% | ms per registration |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (category, rows) in by_category {
        let trials: Vec<&Trial> = rows.iter().flat_map(|r| &r.trials).collect();
        let n = trials.len().max(1) as f64;
        let share = |ok: &dyn Fn(&Trial) -> bool| {
            100.0 * trials.iter().filter(|t| ok(t)).count() as f64 / n
        };
        let within = |degrees: f64, metres: f64| {
            share(&|t: &Trial| {
                t.rotation_error_nocs.to_degrees() <= degrees && t.centroid_error <= metres
            })
        };
        let add_s: Vec<f64> = trials.iter().map(|t| t.add_s).collect();
        let units = rows.len() as f64;
        let optimum = rows.iter().map(|r| r.space_optimum).sum::<f64>() / units;
        let seen = rows.iter().map(|r| r.pose_noise_seen.mean).sum::<f64>() / units;
        md.push_str(&format!(
            "| {category} | {} | {} | {:.2} | {:.2} | {:.2} | {:.1} | {:.1} | {:.0}% | {:.0}% | {:.0}% | {:.0}% | {:.0}% | {:.0} |\n",
            rows.len(),
            trials.len(),
            1e3 * rows.iter().map(|r| r.known_pose.mean).sum::<f64>() / units,
            1e3 * seen,
            seen / optimum,
            1e3 * add_s.iter().sum::<f64>() / n,
            metrics::add_s_auc(&add_s),
            within(5.0, 0.02),
            within(5.0, 0.05),
            within(10.0, 0.05),
            share(&|t: &Trial| t.iou > 0.25),
            share(&|t: &Trial| t.iou > 0.5),
            rows.iter().map(|r| r.noise_ms).sum::<f64>() / units,
        ));
    }
    md
}

/// Per category, the mean error (over the space optimum) after each iteration of the
/// registrations from pose noise against their mean cumulative time.
fn speed_plot(rows: &[Row]) -> Plot {
    let mut by_category: BTreeMap<&str, Vec<&Row>> = BTreeMap::new();
    for r in rows {
        by_category.entry(&r.category).or_default().push(r);
    }
    let mut plot = Plot::new(
        "speed against error (pose noise, per category)",
        "cumulative time (ms)",
        "error / space optimum",
    );
    for (k, (category, rows)) in by_category.into_iter().enumerate() {
        let n = rows.iter().map(|r| r.curve_noise.len()).min().unwrap_or(0);
        let units = rows.len() as f64;
        let ms = rows
            .iter()
            .map(|r| r.noise_ms / r.noise_iterations.max(1.0))
            .sum::<f64>()
            / units;
        let points = (0..n)
            .map(|t| {
                (
                    (t + 1) as f64 * ms,
                    rows.iter()
                        .map(|r| r.curve_noise[t] / r.space_optimum)
                        .sum::<f64>()
                        / units,
                )
            })
            .collect();
        plot = plot.series(category, PALETTE[k % PALETTE.len()], points);
    }
    plot
}
