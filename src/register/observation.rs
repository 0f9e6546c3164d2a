//! What a registration is given, owned and checked: the images of one object seen by one
//! or more cameras ([`Observation`]), the up direction its depth shows
//! ([`Gravity::from_depth`]), the schedule it calls for ([`RegisterParams::for_observation`])
//! and where to start ([`Plan`]). A front end (the command line, the Python module, the
//! evaluations) reads its input into these and calls [`Registrar::register_observation`].

use glam::DVec3;

use crate::diff::{DepthLoss, Shading};
use crate::error::{Error, Result};
use crate::gpu::Context;
use crate::loss::{hidden_pixels, mark_unknown};
use crate::raster::View;
use crate::shape::ShapeSpace;
use crate::support::{fit_support_plane, SupportPlane};
use crate::{Camera, Pose};

use super::{
    check_starts, turned_starts, Gravity, Job, OnChunk, OtherView, RegisterParams, Registrar,
    Registration, Starts, DEFAULT_STARTS, START_TURN,
};

/// One view's images as a front end reads them, each `[row][column]` of its camera's size.
#[derive(Clone, Debug, Default)]
pub struct ViewImages {
    /// The mask: nonzero = object ([`crate::loss::UNKNOWN`] where unknown).
    pub mask: Vec<f32>,
    /// Depth in metres, 0 = not measured.
    pub depth: Option<Vec<f32>>,
    /// Grey shading; set to background (0) wherever the mask shows background.
    pub shading: Option<Vec<f32>>,
    /// Nonzero where the image cannot be trusted (an occluder, a region to leave out): of
    /// these, the pixels the mask does not show as object become unknown, so that BOP's
    /// whole `mask` works as it is (the hidden part is it less `mask_visib`).
    pub ignore: Option<Vec<f32>>,
}

/// What a registration is given: one object seen by a camera, and optionally by further
/// cameras at poses known relative to it. Each image holds every view's,
/// `[view][row][column]`, the first view first; every view has the first's size.
#[derive(Clone, Debug)]
pub struct Observation {
    /// The first camera.
    pub camera: Camera,
    /// Further cameras of a multi-view observation (empty: one view).
    pub others: Vec<OtherView>,
    /// The masks: nonzero = object, [`crate::loss::UNKNOWN`] where unknown.
    pub mask: Vec<f32>,
    /// The depths, metres, 0 = not measured (a view without depth has none anywhere).
    pub depth: Option<Vec<f32>>,
    /// The grey shadings, background 0.
    pub shaded: Option<Vec<f32>>,
}

impl Observation {
    /// The observation of one view through `camera`: an error where an image has another
    /// size than the camera's. The ignore mask marks pixels unknown ([`ViewImages::ignore`]).
    pub fn new(camera: Camera, first: ViewImages) -> Result<Self> {
        let (mask, depth, shaded) = view_images(&camera, first, "the first view")?;
        Ok(Self {
            camera,
            others: Vec::new(),
            mask,
            depth,
            shaded,
        })
    }

    /// The same seen by a further camera. Its depth is kept where the first view has depth
    /// (a view without one measures nothing); it needs a shading where the first view has
    /// one. An error where its size differs from the first view's.
    pub fn with_view(mut self, other: OtherView, images: ViewImages) -> Result<Self> {
        let which = format!("view {}", self.views());
        let first = (self.camera.width, self.camera.height);
        if (other.camera.width, other.camera.height) != first {
            return Err(Error::InvalidInput(format!(
                "{which} is {}x{}, but every view must have the first's size ({}x{})",
                other.camera.width, other.camera.height, first.0, first.1
            )));
        }
        if self.shaded.is_some() && images.shading.is_none() {
            return Err(Error::InvalidInput(format!(
                "{which} has no shading image, but the first view has one"
            )));
        }
        let (mask, depth, shaded) = view_images(&other.camera, images, &which)?;
        if let Some(all) = self.depth.as_mut() {
            all.extend(depth.unwrap_or_else(|| vec![0.0; mask.len()]));
        }
        if let (Some(all), Some(shaded)) = (self.shaded.as_mut(), shaded) {
            all.extend(shaded);
        }
        self.mask.extend(mask);
        self.others.push(other);
        Ok(self)
    }

    /// How many cameras see the object.
    pub fn views(&self) -> usize {
        1 + self.others.len()
    }

    /// The pixels of one view.
    pub fn pixels(&self) -> usize {
        (self.camera.width * self.camera.height) as usize
    }

    /// The first view's mask.
    pub fn first_mask(&self) -> &[f32] {
        &self.mask[..self.pixels().min(self.mask.len())]
    }

    /// The first view's depth, where measured.
    pub fn first_depth(&self) -> Option<&[f32]> {
        let n = self.pixels();
        self.depth.as_deref().map(|d| &d[..n.min(d.len())])
    }

    /// Whether the distance along the line of sight is observed: by depth or by a further
    /// view.
    pub fn observes_z(&self) -> bool {
        self.depth.is_some() || !self.others.is_empty()
    }

    /// An error where no view's mask shows a pixel of the object (an object wholly hidden
    /// or out of the image): there is nothing to register to.
    pub fn check_visible(&self) -> Result<()> {
        if self.mask.iter().any(|&m| m > 0.0) {
            return Ok(());
        }
        Err(Error::InvalidInput(
            "the mask shows nothing of the object (no pixel of it in any view): there is \
             nothing to register to"
                .into(),
        ))
    }

    /// The support plane in the first view's depth: fitted to the measured pixels around
    /// the mask ([`fit_support_plane`]). An error without depth or without such a plane.
    pub fn support_plane(&self) -> Result<SupportPlane> {
        let depth = self.first_depth().ok_or_else(|| {
            Error::InvalidInput("gravity from the depth needs the observed depth".into())
        })?;
        let seen: Vec<f32> = self.first_mask().iter().map(|&m| m.max(0.0)).collect();
        fit_support_plane(&self.camera, depth, &seen, 0.5)
    }

    /// The registration of `space` to this observation from `pose` (the first view's).
    pub fn job<'a>(&'a self, space: &'a ShapeSpace, pose: Pose) -> Job<'a> {
        Job {
            shaded: self.shaded.as_deref(),
            depth: self.depth.as_deref(),
            others: &self.others,
            ..Job::new(
                space,
                &self.mask,
                View {
                    camera: self.camera,
                    pose,
                },
            )
        }
    }
}

/// One view's mask, depth and shading.
type Images = (Vec<f32>, Option<Vec<f32>>, Option<Vec<f32>>);

/// A view's images checked against `camera`'s size (`which` names the view in errors), the
/// shading background off the mask, the ignored pixels unknown.
fn view_images(camera: &Camera, images: ViewImages, which: &str) -> Result<Images> {
    let n = (camera.width * camera.height) as usize;
    let ViewImages {
        mut mask,
        depth,
        shading,
        ignore,
    } = images;
    for (what, len) in [
        ("mask", Some(mask.len())),
        ("depth", depth.as_ref().map(Vec::len)),
        ("shading", shading.as_ref().map(Vec::len)),
        ("ignore mask", ignore.as_ref().map(Vec::len)),
    ] {
        if let Some(len) = len.filter(|&len| len != n) {
            return Err(Error::InvalidInput(format!(
                "{which}: the {what} has {len} pixels, but the camera's {}x{} image has {n}",
                camera.width, camera.height
            )));
        }
    }
    if let Some(bad) = depth
        .iter()
        .flatten()
        .find(|z| !(z.is_finite() && **z >= 0.0))
    {
        return Err(Error::InvalidInput(format!(
            "{which}: depth must be finite metres >= 0 (0 = not measured), not {bad}"
        )));
    }
    let mut shaded = shading.map(|shading| {
        shading
            .iter()
            .zip(&mask)
            .map(|(&s, &m)| if m == 0.0 { 0.0 } else { s })
            .collect::<Vec<f32>>()
    });
    if let Some(ignore) = ignore {
        let hidden = hidden_pixels(&mask, &ignore)?;
        mark_unknown(&mut mask, 1, &hidden)?;
        if let Some(shaded) = shaded.as_mut() {
            mark_unknown(shaded, 1, &hidden)?;
        }
    }
    Ok((mask, depth, shaded))
}

impl Gravity {
    /// Up from the observation's depth: the normal of the support plane around the mask
    /// ([`Observation::support_plane`], returned too), the object's `up` axis kept within
    /// `tolerance` radians of it. An error without depth or without such a plane.
    pub fn from_depth(
        observation: &Observation,
        up: DVec3,
        tolerance: f64,
    ) -> Result<(Gravity, SupportPlane)> {
        let plane = observation.support_plane()?;
        let gravity = Gravity {
            up,
            direction: plane.normal,
            tolerance,
        };
        gravity.validate()?;
        Ok((gravity, plane))
    }
}

/// Whether a registration knows the object's pose or must find it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseMode {
    /// The pose is known: only the shape is fitted.
    Known,
    /// The pose is found from a start near it, with the shape.
    Free,
}

impl RegisterParams {
    /// The schedule for `observation`: [`RegisterParams::known_pose`] or
    /// [`RegisterParams::free_pose`] for its image size, its depth compared where it has
    /// depth ([`DepthLoss::default`]), its shading where it has shading
    /// ([`Shading::default`]), and with the pose free the z translation free where the
    /// observation tells it ([`Observation::observes_z`]).
    pub fn for_observation(mode: PoseMode, observation: &Observation) -> Self {
        let pixels = observation.pixels();
        let base = match mode {
            PoseMode::Known => Self::known_pose(pixels),
            PoseMode::Free => Self::free_pose(pixels),
        };
        Self {
            depth: observation.depth.is_some().then(DepthLoss::default),
            shading: observation.shaded.is_some().then(Shading::default),
            optimize_z: base.optimize_z || (mode == PoseMode::Free && observation.observes_z()),
            ..base
        }
    }
}

/// Where a registration of an observation starts and how: the start (the first view's
/// pose), the starts turned about the object's `up` axis ([`turned_starts`] by `turn`),
/// which way is up where known, and the parameters.
#[derive(Clone, Copy, Debug)]
pub struct Plan {
    /// The object's pose in the first camera at the start.
    pub start: Pose,
    /// The object's up axis in its own frame (the category's).
    pub up: DVec3,
    /// Starts turned about `up`: 1 to [`super::MAX_STARTS`].
    pub starts: usize,
    /// Radians between the starts.
    pub turn: f64,
    /// Which way is up, where known.
    pub gravity: Option<Gravity>,
    /// How to register.
    pub params: RegisterParams,
}

impl Plan {
    /// From `start` with `params`: [`DEFAULT_STARTS`] starts [`START_TURN`] apart where
    /// `params` free the pose, one where they keep it; no gravity.
    pub fn new(start: Pose, up: DVec3, params: RegisterParams) -> Self {
        Self {
            start,
            up,
            starts: if params.pose_every > 0 {
                DEFAULT_STARTS
            } else {
                1
            },
            turn: START_TURN,
            gravity: None,
            params,
        }
    }
}

impl Registrar {
    /// Registers `space` to `observation` as `plan` says: the parameters checked, the
    /// starts turned about the up axis and used as the schedules use them
    /// ([`Starts::for_params`]). The one path from an observation to a registration:
    /// `vkdr register`, `demo`, the Python module and the evaluations take it.
    pub fn register_observation(
        &self,
        ctx: &Context,
        space: &ShapeSpace,
        observation: &Observation,
        plan: &Plan,
        on_chunk: impl OnChunk,
    ) -> Result<Registration> {
        check_starts(plan.starts)?;
        plan.params.validate()?;
        observation.check_visible()?;
        if let Some(gravity) = &plan.gravity {
            gravity.validate()?;
        }
        let job = Job {
            gravity: plan.gravity,
            ..observation.job(space, plan.start)
        };
        let starts = turned_starts(plan.start, plan.up, plan.starts, plan.turn);
        self.register_starts(
            ctx,
            job,
            Starts::for_params(&starts, &plan.params),
            &plan.params,
            on_chunk,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        Camera::new(40.0, 40.0, 4.0, 3.0, 8, 6).unwrap()
    }

    fn square_mask() -> Vec<f32> {
        (0..48)
            .map(|i| ((2..6).contains(&(i % 8)) && (2..5).contains(&(i / 8))) as u32 as f32)
            .collect()
    }

    /// The ignore mask makes unknown only what the mask does not show as object, in the
    /// shading too; the shading is background off the mask.
    #[test]
    fn ignored_pixels_off_the_object_become_unknown() {
        let mask = square_mask();
        let ignore: Vec<f32> = (0..48).map(|i| (i % 8 >= 4) as u32 as f32).collect();
        let observation = Observation::new(
            camera(),
            ViewImages {
                mask: mask.clone(),
                shading: Some(vec![0.5; 48]),
                ignore: Some(ignore.clone()),
                ..Default::default()
            },
        )
        .unwrap();
        let shaded = observation.shaded.as_ref().unwrap();
        for i in 0..48 {
            let unknown = ignore[i] > 0.0 && mask[i] == 0.0;
            let expected = if unknown {
                crate::loss::UNKNOWN
            } else {
                mask[i]
            };
            assert_eq!(observation.mask[i], expected, "pixel {i}");
            let shade = if unknown {
                crate::loss::UNKNOWN
            } else {
                0.5 * mask[i]
            };
            assert_eq!(shaded[i], shade, "pixel {i}");
        }
    }

    /// An observation whose mask shows no pixel of the object (background, or unknown
    /// everywhere) is refused; one object pixel in a further view is enough.
    #[test]
    fn an_observation_without_the_object_is_refused() {
        let only = |mask: Vec<f32>| {
            Observation::new(
                camera(),
                ViewImages {
                    mask,
                    ..Default::default()
                },
            )
            .unwrap()
        };
        assert!(only(square_mask()).check_visible().is_ok());
        for nothing in [vec![0.0; 48], vec![crate::loss::UNKNOWN; 48]] {
            let error = only(nothing).check_visible().unwrap_err().to_string();
            assert!(error.contains("shows nothing of the object"), "{error}");
        }
        let other = OtherView {
            camera: camera(),
            from_first: Pose::new([0.1, 0.0, 0.0], [0.0; 3]).unwrap(),
        };
        let seen_by_the_other = only(vec![0.0; 48])
            .with_view(
                other,
                ViewImages {
                    mask: square_mask(),
                    ..Default::default()
                },
            )
            .unwrap();
        assert!(seen_by_the_other.check_visible().is_ok());
    }

    /// Sizes are checked against the camera, a further view's against the first's; a view
    /// without depth measures nothing where the first has depth; a shading is needed where
    /// the first view has one.
    #[test]
    fn views_are_checked_and_laid_out_view_after_view() {
        let wrong = Observation::new(
            camera(),
            ViewImages {
                mask: vec![0.0; 47],
                ..Default::default()
            },
        );
        assert!(wrong.unwrap_err().to_string().contains("47 pixels"));
        let first = ViewImages {
            mask: square_mask(),
            depth: Some(vec![0.7; 48]),
            ..Default::default()
        };
        let other = OtherView {
            camera: camera(),
            from_first: Pose::new([0.1, 0.0, 0.0], [0.0, 0.2, 0.0]).unwrap(),
        };
        let two = Observation::new(camera(), first.clone())
            .unwrap()
            .with_view(
                other,
                ViewImages {
                    mask: square_mask(),
                    ..Default::default()
                },
            )
            .unwrap();
        assert_eq!(two.views(), 2);
        assert_eq!(two.mask.len(), 96);
        let depth = two.depth.as_ref().unwrap();
        assert!(depth[..48].iter().all(|&z| z == 0.7) && depth[48..].iter().all(|&z| z == 0.0));
        assert!(two.observes_z());
        let small = OtherView {
            camera: Camera::new(40.0, 40.0, 4.0, 3.0, 8, 5).unwrap(),
            ..other
        };
        let err = Observation::new(camera(), first.clone())
            .unwrap()
            .with_view(small, ViewImages::default())
            .unwrap_err();
        assert!(err.to_string().contains("first's size"), "{err}");
        let shaded = ViewImages {
            shading: Some(vec![0.5; 48]),
            ..first
        };
        let err = Observation::new(camera(), shaded)
            .unwrap()
            .with_view(
                other,
                ViewImages {
                    mask: square_mask(),
                    ..Default::default()
                },
            )
            .unwrap_err();
        assert!(err.to_string().contains("no shading"), "{err}");
    }

    /// The schedule follows what is observed: depth compared where measured, z free with
    /// the pose free where depth or a further view tells it.
    #[test]
    fn the_schedule_follows_the_observation() {
        let mask_only = Observation::new(
            camera(),
            ViewImages {
                mask: square_mask(),
                ..Default::default()
            },
        )
        .unwrap();
        let known = RegisterParams::for_observation(PoseMode::Known, &mask_only);
        let free = RegisterParams::for_observation(PoseMode::Free, &mask_only);
        assert!(known.depth.is_none() && !known.optimize_z && known.pose_every == 0);
        assert!(free.pose_every > 0 && !free.optimize_z);
        let with_depth = Observation {
            depth: Some(vec![0.7; 48]),
            ..mask_only
        };
        let free = RegisterParams::for_observation(PoseMode::Free, &with_depth);
        assert!(free.depth.is_some() && free.optimize_z);
        let known = RegisterParams::for_observation(PoseMode::Known, &with_depth);
        assert!(known.depth.is_some() && !known.optimize_z);
        assert_eq!(
            Plan::new(Pose::at([0.0, 0.0, 0.7]), DVec3::Y, free).starts,
            DEFAULT_STARTS
        );
        assert_eq!(
            Plan::new(Pose::at([0.0, 0.0, 0.7]), DVec3::Y, known).starts,
            1
        );
    }

    /// Gravity from the depth of an object on a table: the table's normal, towards the
    /// camera's side; none without depth.
    #[test]
    fn gravity_from_the_depth_is_the_table_s_normal() {
        let camera = Camera::new(100.0, 100.0, 32.0, 24.0, 64, 48).unwrap();
        // A table seen from above, the object standing on it 5 cm in front of it along
        // each ray in the middle of the image.
        let normal = DVec3::new(0.0, -1.0, -0.6).normalize();
        let point = DVec3::new(0.0, 0.1, 0.8);
        let mut depth = vec![0.0f32; 64 * 48];
        let mut mask = vec![0.0f32; 64 * 48];
        for row in 0..48 {
            for column in 0..64 {
                let ray = DVec3::new(
                    (column as f64 + 0.5 - 32.0) / 100.0,
                    (row as f64 + 0.5 - 24.0) / 100.0,
                    1.0,
                );
                let i = row * 64 + column;
                let table = normal.dot(point) / normal.dot(ray);
                let object = (24..40).contains(&column) && (16..32).contains(&row);
                mask[i] = object as u32 as f32;
                depth[i] = if object { table - 0.05 } else { table } as f32;
            }
        }
        let observation = Observation::new(
            camera,
            ViewImages {
                mask: mask.clone(),
                depth: Some(depth),
                ..Default::default()
            },
        )
        .unwrap();
        let (gravity, plane) = Gravity::from_depth(&observation, DVec3::Y, 0.01).unwrap();
        assert!(plane.normal.dot(normal).abs() > 0.999, "{:?}", plane.normal);
        assert_eq!(gravity.direction, plane.normal);
        assert_eq!(gravity.up, DVec3::Y);
        let no_depth = Observation::new(
            camera,
            ViewImages {
                mask,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(Gravity::from_depth(&no_depth, DVec3::Y, 0.01).is_err());
    }
}
