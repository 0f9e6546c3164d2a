//! The region of interest a registration renders and compares. An object covers a few per
//! cent of a camera's frame, and every pixel outside its mask and outside where its
//! rendering can go adds nothing to the loss (background against background) or is
//! unknown. A registration therefore cuts the box of the observed mask and of the starts'
//! silhouettes, with a margin, out of the image: the camera's principal point moves by the
//! box's corner (the same rays through the same pixel centres) and the loss stays averaged
//! over the whole image's pixels ([`Job::loss_pixels`]), so that the loss and its
//! gradients are the whole image's as long as the rendering stays inside the box.
//! A fit that ends at the box's border runs again on the whole image
//! (`Registrar::register_jobs`).

use glam::DVec3;

use super::{Job, Registration};
use crate::error::Result;
use crate::raster::View;
use crate::Camera;

/// The margin around the box of the mask and the starts: this share of its larger side...
const MARGIN_SHARE: f64 = 0.2;
/// ... and this many pixels.
const MARGIN_PIXELS: f64 = 8.0;
/// Regions larger than this share of the image are not cut (little to gain).
const LARGEST_SHARE: f64 = 0.5;
/// A fit whose silhouette comes this near (pixels) to a cut side of the region may have
/// been clipped there: it runs again on the whole image.
const BORDER: f64 = 2.0;

/// A rectangle of a view's pixels: columns `x..x + width`, rows `y..y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Region {
    /// The first column.
    pub x: u32,
    /// The first row.
    pub y: u32,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

/// A box of image coordinates.
#[derive(Clone, Copy)]
struct Bounds {
    lo: (f64, f64),
    hi: (f64, f64),
}

impl Bounds {
    fn empty() -> Self {
        Self {
            lo: (f64::INFINITY, f64::INFINITY),
            hi: (f64::NEG_INFINITY, f64::NEG_INFINITY),
        }
    }

    fn add(&mut self, (u, v): (f64, f64)) {
        self.lo = (self.lo.0.min(u), self.lo.1.min(v));
        self.hi = (self.hi.0.max(u), self.hi.1.max(v));
    }

    fn is_empty(&self) -> bool {
        !(self.lo.0 <= self.hi.0 && self.lo.1 <= self.hi.1)
    }
}

/// The image box of `vertices` (object frame) at `pose` through `camera`; None where one
/// lies at or behind the camera's plane.
fn silhouette_bounds(vertices: &[DVec3], view: &View) -> Option<Bounds> {
    let mut bounds = Bounds::empty();
    for p in vertices {
        let c = view.pose.apply(*p);
        if c.z <= view.camera.near {
            return None;
        }
        bounds.add(view.camera.project(c));
    }
    Some(bounds)
}

impl Region {
    /// The region the registrations of `jobs` (one batch: one image size) need: the box of
    /// every job's observed object pixels and of its space's mean shape at its start, with
    /// a margin of a fifth of its larger side and 8 pixels (`MARGIN_SHARE`, `MARGIN_PIXELS`),
    /// within the image. None where it would hold more than half the image
    /// (`LARGEST_SHARE`), where a job has further views, or where a start lies behind the
    /// camera.
    pub fn of_interest(jobs: &[Job]) -> Result<Option<Region>> {
        let Some(first) = jobs.first() else {
            return Ok(None);
        };
        let camera = first.view.camera;
        if jobs
            .iter()
            .any(|j| !j.others.is_empty() || j.view.camera != camera)
        {
            return Ok(None);
        }
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut bounds = Bounds::empty();
        for job in jobs {
            for (i, &m) in job.observed[..w * h].iter().enumerate() {
                if m > 0.0 {
                    bounds.add(((i % w) as f64, (i / w) as f64));
                    bounds.add(((i % w) as f64 + 1.0, (i / w) as f64 + 1.0));
                }
            }
            let mean = job.space.vertices(&vec![0.0; job.space.dims()])?;
            match silhouette_bounds(&mean, &job.view) {
                Some(start) if !start.is_empty() => {
                    bounds.add(start.lo);
                    bounds.add(start.hi);
                }
                _ => return Ok(None),
            }
        }
        if bounds.is_empty() {
            return Ok(None);
        }
        let side = (bounds.hi.0 - bounds.lo.0).max(bounds.hi.1 - bounds.lo.1);
        let margin = MARGIN_SHARE * side + MARGIN_PIXELS;
        let clamp = |v: f64, limit: usize| v.clamp(0.0, limit as f64) as u32;
        let (x0, x1) = (
            clamp((bounds.lo.0 - margin).floor(), w),
            clamp((bounds.hi.0 + margin).ceil(), w),
        );
        let (y0, y1) = (
            clamp((bounds.lo.1 - margin).floor(), h),
            clamp((bounds.hi.1 + margin).ceil(), h),
        );
        let (width, height) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        if width == 0 || height == 0 || (width * height) as f64 > LARGEST_SHARE * (w * h) as f64 {
            return Ok(None);
        }
        Ok(Some(Region {
            x: x0,
            y: y0,
            width,
            height,
        }))
    }

    /// The camera of the region of `camera`'s image: the principal point moved by its
    /// corner, so that its pixel (i, j) is the image's (i + y, j + x).
    pub fn camera(&self, camera: &Camera) -> Camera {
        Camera {
            cx: camera.cx - self.x as f64,
            cy: camera.cy - self.y as f64,
            width: self.width,
            height: self.height,
            ..*camera
        }
    }

    /// The region's pixels of an image `[row][column]` of `width` columns.
    pub fn crop(&self, image: &[f32], width: u32) -> Vec<f32> {
        let mut out = Vec::with_capacity((self.width * self.height) as usize);
        for row in self.y..self.y + self.height {
            let start = (row * width + self.x) as usize;
            out.extend_from_slice(&image[start..start + self.width as usize]);
        }
        out
    }

    /// `job`'s images cut to the region.
    pub(super) fn cut(&self, job: &Job) -> Cut {
        let width = job.view.camera.width;
        Cut {
            observed: self.crop(job.observed, width),
            shaded: job.shaded.map(|s| self.crop(s, width)),
            depth: job.depth.map(|d| self.crop(d, width)),
            camera: self.camera(&job.view.camera),
            loss_pixels: job
                .loss_pixels
                .unwrap_or(job.view.camera.width as u64 * job.view.camera.height as u64),
        }
    }

    /// Whether `fit`'s silhouette (at its pose, through `job`'s camera) stays clear of the
    /// region's cut sides: then the whole image would have compared nothing more.
    pub(super) fn holds(&self, job: &Job, fit: &Registration) -> bool {
        let view = View {
            pose: fit.pose,
            ..job.view
        };
        let Some(bounds) = silhouette_bounds(&fit.vertices, &view) else {
            return false;
        };
        let camera = &job.view.camera;
        let (x1, y1) = (self.x + self.width, self.y + self.height);
        let left = self.x == 0 || bounds.lo.0 >= self.x as f64 + BORDER;
        let top = self.y == 0 || bounds.lo.1 >= self.y as f64 + BORDER;
        let right = x1 == camera.width || bounds.hi.0 <= x1 as f64 - BORDER;
        let bottom = y1 == camera.height || bounds.hi.1 <= y1 as f64 - BORDER;
        left && top && right && bottom
    }
}

/// A job's images cut to a region, and the region's camera.
pub(super) struct Cut {
    observed: Vec<f32>,
    shaded: Option<Vec<f32>>,
    depth: Option<Vec<f32>>,
    camera: Camera,
    loss_pixels: u64,
}

impl Cut {
    /// `job` seen through the region.
    pub(super) fn job<'a>(&'a self, job: &Job<'a>) -> Job<'a> {
        Job {
            observed: &self.observed,
            shaded: self.shaded.as_deref(),
            depth: self.depth.as_deref(),
            view: View {
                camera: self.camera,
                ..job.view
            },
            loss_pixels: Some(self.loss_pixels),
            ..*job
        }
    }
}
