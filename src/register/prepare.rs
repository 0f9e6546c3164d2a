//! A job made ready for the device: what its depth shows in front of the object marked
//! unknown, and a start moved onto the mask.

use glam::DVec3;

use crate::error::Result;
use crate::raster::View;
use crate::Pose;

use super::{Job, RegisterParams};

/// With depth and an occlusion tolerance: the job's mask (and shading) with the pixels
/// that its depth shows in front of the object marked unknown
/// ([`crate::loss::in_front_of_mask`], per view); None where nothing is.
pub(super) fn unknown_in_front(job: &Job, params: &RegisterParams) -> Result<Option<Marked>> {
    let (Some(loss), Some(depth)) = (params.depth, job.depth) else {
        return Ok(None);
    };
    let pixels = (job.view.camera.width * job.view.camera.height) as usize;
    if depth.len() != job.observed.len() || depth.len() % pixels.max(1) != 0 {
        return Ok(None); // Scene::new names the mismatch.
    }
    let hidden: Vec<f32> = job
        .observed
        .chunks(pixels)
        .zip(depth.chunks(pixels))
        .flat_map(|(mask, depth)| crate::loss::in_front_of_mask(mask, 1, depth, loss.occlusion))
        .collect();
    if hidden.iter().all(|&h| h == 0.0) {
        return Ok(None);
    }
    let mut observed = job.observed.to_vec();
    crate::loss::mark_unknown(&mut observed, 1, &hidden)?;
    let shaded = match job.shaded {
        Some(shaded) if shaded.len() == hidden.len() => {
            let mut shaded = shaded.to_vec();
            crate::loss::mark_unknown(&mut shaded, 1, &hidden)?;
            Some(shaded)
        }
        other => other.map(<[f32]>::to_vec),
    };
    Ok(Some(Marked { observed, shaded }))
}

/// `job` with its start moved onto the observed mask where the mean shape, projected at
/// the start, lands on none of the mask's pixels: across the line of sight (x and y at the
/// start's distance), so that the centre of its projected vertices lies on the centre of
/// the mask's pixels (first view). Where what surrounds the mask is unknown (an occluder
/// found in the depth, or an ignore mask), a silhouette wholly inside the unknown pixels
/// costs nothing and has no gradient: the registration would stay where it started. A
/// start that lands on the mask is kept as it is.
pub(super) fn onto_mask<'a>(job: &Job<'a>) -> Result<Job<'a>> {
    let camera = &job.view.camera;
    let (width, height) = (camera.width as usize, camera.height as usize);
    let Some(mask) = job.observed.get(..width * height) else {
        return Ok(*job); // Scene::new names the mismatch.
    };
    let pose = job.view.pose;
    let rotation = pose.rotation_matrix();
    let mut centre = (0.0, 0.0, 0usize);
    let mut lands = false;
    for vertex in job.space.vertices(&vec![0.0; job.space.dims()])? {
        let p = rotation * vertex + pose.translation;
        if p.z <= camera.near {
            continue;
        }
        let (u, v) = camera.project(p);
        centre = (centre.0 + u, centre.1 + v, centre.2 + 1);
        let (column, row) = (u.floor(), v.floor());
        lands |= column >= 0.0
            && row >= 0.0
            && (column as usize) < width
            && (row as usize) < height
            && mask[row as usize * width + column as usize] > 0.0;
    }
    let mut seen = (0.0, 0.0, 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m > 0.0) {
        let (column, row) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
        seen = (seen.0 + column, seen.1 + row, seen.2 + 1);
    }
    if lands || centre.2 == 0 || seen.2 == 0 {
        return Ok(*job);
    }
    let (du, dv) = (
        seen.0 / seen.2 as f64 - centre.0 / centre.2 as f64,
        seen.1 / seen.2 as f64 - centre.1 / centre.2 as f64,
    );
    let z = pose.translation.z;
    let translation = pose.translation + DVec3::new(du * z / camera.fx, dv * z / camera.fy, 0.0);
    Ok(Job {
        view: View {
            pose: Pose {
                translation,
                ..pose
            },
            ..job.view
        },
        ..*job
    })
}

/// A job's observed images with what stands in front of the object marked unknown.
pub(super) struct Marked {
    pub(super) observed: Vec<f32>,
    pub(super) shaded: Option<Vec<f32>>,
}
