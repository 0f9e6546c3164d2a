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

/// A start whose projected mean shape has fewer than this share of its vertices on the
/// mask is moved onto the mask ([`onto_mask`]).
pub(super) const ONTO_MASK_BELOW: f64 = 0.1;

/// `job` with its start moved onto the observed mask where the mean shape, projected at
/// the start, lands on the mask's pixels with fewer than [`ONTO_MASK_BELOW`] of its
/// vertices: across the line of sight (x and y at the start's distance), so that the centre
/// of its projected vertices lies on the centre of the mask's pixels (first view). Where
/// what surrounds the mask is unknown (an occluder found in the depth, or an ignore mask),
/// a silhouette wholly inside the unknown pixels costs nothing and has no gradient: the
/// registration would stay where it started. And a start that barely touches a mask cut
/// by the image's border, most of it outside the image, can be pulled out of the image
/// altogether. A start with [`ONTO_MASK_BELOW`] of its vertices on the mask or more is
/// kept as it is.
pub(super) fn onto_mask<'a>(job: &Job<'a>) -> Result<Job<'a>> {
    let camera = &job.view.camera;
    let (width, height) = (camera.width as usize, camera.height as usize);
    let Some(mask) = job.observed.get(..width * height) else {
        return Ok(*job); // Scene::new names the mismatch.
    };
    let pose = job.view.pose;
    let rotation = pose.rotation_matrix();
    let mut centre = (0.0, 0.0, 0usize);
    let mut landing = 0usize;
    for vertex in job.space.vertices(&vec![0.0; job.space.dims()])? {
        let p = rotation * vertex + pose.translation;
        if p.z <= camera.near {
            continue;
        }
        let (u, v) = camera.project(p);
        centre = (centre.0 + u, centre.1 + v, centre.2 + 1);
        let (column, row) = (u.floor(), v.floor());
        landing += (column >= 0.0
            && row >= 0.0
            && (column as usize) < width
            && (row as usize) < height
            && mask[row as usize * width + column as usize] > 0.0) as usize;
    }
    let lands = landing as f64 >= ONTO_MASK_BELOW * centre.2 as f64;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::shape::random_space;
    use crate::Camera;

    /// A start with under a tenth of its vertices on the mask (some, not none) is moved
    /// across the line of sight onto it; one with more is kept.
    #[test]
    fn a_start_barely_on_the_mask_is_moved_onto_it() {
        let space = random_space(&mut Rng::new(1), 4, 2);
        let camera = Camera::new(100.0, 100.0, 32.0, 32.0, 64, 64).unwrap();
        let mean = space.vertices(&[0.0, 0.0]).unwrap();
        let pixel = |pose: Pose, v: DVec3| {
            let (u, v) = camera.project(pose.rotation_matrix() * v + pose.translation);
            (u.floor() as i64, v.floor() as i64)
        };
        // The mask: the box of the mean shape's projection at the true pose.
        let truth = Pose::new([0.0, 0.0, 0.5], [0.3, 0.2, 0.1]).unwrap();
        let corners = mean.iter().map(|&v| pixel(truth, v));
        let (lo, hi) = corners.fold(((64, 64), (0, 0)), |(lo, hi), (u, v)| {
            ((lo.0.min(u), lo.1.min(v)), (hi.0.max(u), hi.1.max(v)))
        });
        let on = |(u, v): (i64, i64)| (lo.0..=hi.0).contains(&u) && (lo.1..=hi.1).contains(&v);
        let mask: Vec<f32> = (0..64 * 64)
            .map(|i| on((i % 64, i / 64)) as u32 as f32)
            .collect();
        let share = |pose: Pose| {
            let landing = mean.iter().filter(|&&v| on(pixel(pose, v))).count();
            landing as f64 / mean.len() as f64
        };
        let start = |dx: f64| Pose {
            translation: truth.translation + DVec3::new(dx, 0.0, 0.0),
            ..truth
        };
        let job = |pose: Pose| Job::new(&space, &mask, View { camera, pose });
        let barely = (1..1000)
            .map(|i| start(i as f64 * 1e-4))
            .find(|&p| share(p) > 0.0 && share(p) < ONTO_MASK_BELOW)
            .expect("a start with a few vertices on the mask");
        let moved = onto_mask(&job(barely)).unwrap().view.pose;
        assert_eq!(moved.rotation, barely.rotation);
        assert_eq!(moved.translation.z, barely.translation.z);
        assert!(share(moved) > 0.5, "{}", share(moved));
        let kept = (1..1000)
            .map(|i| start(i as f64 * 1e-4))
            .find(|&p| share(p) < 0.5)
            .unwrap();
        assert!(share(kept) >= ONTO_MASK_BELOW);
        assert_eq!(onto_mask(&job(kept)).unwrap().view.pose, kept);
    }
}
