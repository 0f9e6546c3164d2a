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
use crate::loss::UNKNOWN;
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

/// A rectangle of a view's pixels: columns `x..x + width`, rows `y..y + height`, rendered
/// with one pixel per `step` x `step` of the image's (`width` and `height` multiples of it).
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
    /// The image's pixels per region pixel along each axis (1: the image's own).
    pub step: u32,
    /// The depth is compared at every `depth_step`-th region pixel along each axis (its
    /// first row and column included), each of them counting for `depth_step` squared
    /// pixels (1: at every pixel). The depth is smooth over the object where the mask is
    /// not, and against a mask a pixel without a depth to compare costs no interpolation.
    pub depth_step: u32,
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

    /// The larger side.
    fn side(&self) -> f64 {
        (self.hi.0 - self.lo.0).max(self.hi.1 - self.lo.1)
    }
}

/// The bounding box of a mask's object pixels (those > 0) in an image `width` pixels
/// wide: the first and last column and row, inclusive; None where no pixel is object.
pub(super) fn mask_box(mask: &[f32], width: usize) -> Option<(usize, usize, usize, usize)> {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m > 0.0) {
        let (x, y) = (i % width, i / width);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
    }
    (x0 <= x1).then_some((x0, y0, x1, y1))
}

/// The span `lo..hi` of an axis of `limit` pixels widened to whole steps (on the high
/// side, or the low one at the image's edge): its start and length; None where empty or
/// where the image is too short.
fn whole_steps(lo: u32, hi: u32, step: u32, limit: u32) -> Option<(u32, u32)> {
    if hi <= lo {
        return None;
    }
    let length = (hi - lo).div_ceil(step) * step;
    if length > limit {
        return None;
    }
    Some((lo.min(limit - length), length))
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
    /// within the image. Where the object (the larger of the mask's box and a start's
    /// silhouette box) spans more than `detail` pixels (and `detail` is not 0), the region
    /// is rendered at the coarsest whole step that keeps at least `detail` across it, and
    /// its depth compared at the coarsest whole step of the region's pixels that keeps at
    /// least `depth_detail` across it (with either 0: at every pixel). None
    /// where it would be the image's own pixels and hold more than half of them
    /// (`LARGEST_SHARE`), where a job has further views, or where a start lies behind the
    /// camera.
    pub fn of_interest(jobs: &[Job], detail: u32, depth_detail: u32) -> Result<Option<Region>> {
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
        let mut object: f64 = 0.0;
        for job in jobs {
            let mut mask = Bounds::empty();
            if let Some((x0, y0, x1, y1)) = mask_box(&job.observed[..w * h], w) {
                mask.add((x0 as f64, y0 as f64));
                mask.add((x1 as f64 + 1.0, y1 as f64 + 1.0));
            }
            let mean = job.space.vertices(&vec![0.0; job.space.dims()])?;
            let start = match silhouette_bounds(&mean, &job.view) {
                Some(start) if !start.is_empty() => start,
                _ => return Ok(None),
            };
            for b in [mask, start].iter().filter(|b| !b.is_empty()) {
                object = object.max(b.side());
                bounds.add(b.lo);
                bounds.add(b.hi);
            }
        }
        if bounds.is_empty() {
            return Ok(None);
        }
        let step = if detail == 0 {
            1
        } else {
            ((object / detail as f64).floor() as u32).max(1)
        };
        let depth_step = if detail == 0 || depth_detail == 0 {
            1
        } else {
            ((object / step as f64 / depth_detail as f64).floor() as u32).max(1)
        };
        let margin = MARGIN_SHARE * bounds.side() + MARGIN_PIXELS;
        let clamp = |v: f64, limit: usize| v.clamp(0.0, limit as f64) as u32;
        let (x0, x1) = (
            clamp((bounds.lo.0 - margin).floor(), w),
            clamp((bounds.hi.0 + margin).ceil(), w),
        );
        let (y0, y1) = (
            clamp((bounds.lo.1 - margin).floor(), h),
            clamp((bounds.hi.1 + margin).ceil(), h),
        );
        let (Some((x, width)), Some((y, height))) = (
            whole_steps(x0, x1, step, camera.width),
            whole_steps(y0, y1, step, camera.height),
        ) else {
            return Ok(None);
        };
        if step == 1 && (width * height) as f64 > LARGEST_SHARE * (w * h) as f64 {
            return Ok(None);
        }
        Ok(Some(Region {
            x,
            y,
            width,
            height,
            step,
            depth_step,
        }))
    }

    /// The whole image of `camera` at this region's steps, the step above 1 (its last
    /// columns and rows dropped where its size is not a multiple of the step); None at a
    /// step of 1.
    pub fn whole(&self, camera: &Camera) -> Option<Region> {
        let step = self.step;
        let (width, height) = (camera.width / step * step, camera.height / step * step);
        (step > 1 && width > 0 && height > 0).then_some(Region {
            x: 0,
            y: 0,
            width,
            height,
            step,
            depth_step: self.depth_step,
        })
    }

    /// The camera of the region of `camera`'s image: the principal point moved by its
    /// corner and the focal lengths divided by the step, so that its pixel (i, j) covers
    /// the image's (y + step i .. y + step (i + 1), x + step j .. x + step (j + 1)).
    pub fn camera(&self, camera: &Camera) -> Camera {
        let step = self.step as f64;
        Camera {
            fx: camera.fx / step,
            fy: camera.fy / step,
            cx: (camera.cx - self.x as f64) / step,
            cy: (camera.cy - self.y as f64) / step,
            width: self.width / self.step,
            height: self.height / self.step,
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

    /// The region's pixels of an observation `[row][column]` of `width` columns, each the
    /// mean of its step x step image pixels: a mask's unknown where most of them are
    /// ([`UNKNOWN`]), else the share of the known ones that show the object; shading the
    /// mean of the known ones; depth the mean measurement of the object's pixels (of all
    /// measured ones where none shows the object; 0 where none is measured).
    fn coarse(&self, job: &Job) -> Cut {
        let width = job.view.camera.width as usize;
        let s = self.step as usize;
        let (cw, ch) = (
            (self.width / self.step) as usize,
            (self.height / self.step) as usize,
        );
        let mut observed = Vec::with_capacity(cw * ch);
        let mut shaded = job.shaded.map(|_| Vec::with_capacity(cw * ch));
        let mut depth = job.depth.map(|_| Vec::with_capacity(cw * ch));
        for i in 0..ch {
            for j in 0..cw {
                let (y, x) = (self.y as usize + i * s, self.x as usize + j * s);
                let block = Block::of(
                    job,
                    (y..y + s).flat_map(|r| (x..x + s).map(move |c| r * width + c)),
                );
                observed.push(if 2 * block.known < s * s {
                    UNKNOWN
                } else {
                    block.observed as f32
                });
                if let Some(out) = shaded.as_mut() {
                    out.push(block.shaded as f32);
                }
                if let Some(out) = depth.as_mut() {
                    out.push(block.depth as f32);
                }
            }
        }
        Cut {
            observed,
            shaded,
            depth,
            camera: self.camera(&job.view.camera),
            loss_pixels: 0,
            depth_step: 1,
        }
    }

    /// `job`'s images cut to the region (and averaged over its steps), the depth kept at
    /// every `depth_step`-th pixel along each axis only.
    pub(super) fn cut(&self, job: &Job) -> Cut {
        let width = job.view.camera.width;
        let whole = job
            .loss_pixels
            .unwrap_or(job.view.camera.width as u64 * job.view.camera.height as u64);
        let mut cut = if self.step > 1 {
            Cut {
                loss_pixels: (whole / (self.step as u64 * self.step as u64)).max(1),
                ..self.coarse(job)
            }
        } else {
            Cut {
                observed: self.crop(job.observed, width),
                shaded: job.shaded.map(|s| self.crop(s, width)),
                depth: job.depth.map(|d| self.crop(d, width)),
                camera: self.camera(&job.view.camera),
                loss_pixels: whole,
                depth_step: 1,
            }
        };
        let ds = self.depth_step as usize;
        if let Some(depth) = cut.depth.as_mut().filter(|_| ds > 1) {
            let columns = cut.camera.width as usize;
            for (i, d) in depth.iter_mut().enumerate() {
                if !(i / columns).is_multiple_of(ds) || !(i % columns).is_multiple_of(ds) {
                    *d = 0.0;
                }
            }
            cut.depth_step = self.depth_step;
        }
        cut
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

/// The means over a block of image pixels (indices into a job's images): the observed
/// mask's and the shading's over its known pixels, the depth's over the object's measured
/// pixels (over all measured ones where none shows the object); each 0 where it has none.
struct Block {
    /// Known pixels (the mask not [`UNKNOWN`]).
    known: usize,
    observed: f64,
    shaded: f64,
    depth: f64,
}

impl Block {
    fn of(job: &Job, pixels: impl Iterator<Item = usize>) -> Self {
        let (mut known, mut observed, mut shaded) = (0, 0.0, 0.0);
        // Measured pixels, and those of them that show the object: count and sum.
        let (mut measured, mut on_object) = ((0, 0.0), (0, 0.0));
        for p in pixels {
            let mask = job.observed[p];
            if mask >= 0.0 {
                known += 1;
                observed += mask as f64;
                shaded += job.shaded.map_or(0.0, |s| s[p] as f64);
            }
            let Some(d) = job.depth.map(|d| d[p]).filter(|&d| d > 0.0) else {
                continue;
            };
            measured = (measured.0 + 1, measured.1 + d as f64);
            if mask > 0.0 {
                on_object = (on_object.0 + 1, on_object.1 + d as f64);
            }
        }
        let mean = |(n, sum): (usize, f64)| sum / n.max(1) as f64;
        Self {
            known,
            observed: mean((known, observed)),
            shaded: mean((known, shaded)),
            depth: mean(if on_object.0 > 0 { on_object } else { measured }),
        }
    }
}

/// A job's images cut to a region, and the region's camera.
pub(super) struct Cut {
    observed: Vec<f32>,
    shaded: Option<Vec<f32>>,
    depth: Option<Vec<f32>>,
    camera: Camera,
    loss_pixels: u64,
    depth_step: u32,
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
            depth_every: self.depth_step,
            ..*job
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Pose;

    /// A 12 x 8 view, a mask of 0s and 1s with an unknown 2 x 2 block and a partly unknown
    /// one, and depth on the object's pixels and the background's.
    #[test]
    fn a_coarse_region_averages_its_steps() {
        let space = crate::shape::random_space(&mut crate::rng::Rng::new(1), 3, 2);
        let camera = Camera::new(100.0, 90.0, 6.0, 4.0, 12, 8).unwrap();
        let (w, h) = (12usize, 8usize);
        let mut observed = vec![0.0f32; w * h];
        let mut depth = vec![0.0f32; w * h];
        for i in 0..h {
            for j in 0..w {
                let object = (2..7).contains(&j) && (1..6).contains(&i);
                observed[i * w + j] = object as u8 as f32;
                depth[i * w + j] = if object { 1.0 + 0.01 * j as f32 } else { 2.0 };
            }
        }
        for p in [8, 9, w + 8, w + 9] {
            observed[p] = UNKNOWN;
        }
        observed[4 * w + 10] = UNKNOWN;
        depth[2 * w + 2] = 0.0;
        let pose = Pose::new([0.0, 0.0, 1.0], [0.0; 3]).unwrap();
        let job = Job::new(&space, &observed, View { camera, pose }).with_depth(&depth);
        let region = Region {
            x: 2,
            y: 0,
            width: 10,
            height: 8,
            step: 2,
            depth_step: 1,
        };
        let cut = region.cut(&job);
        let coarse = cut.job(&job);
        assert_eq!(
            (coarse.view.camera.width, coarse.view.camera.height),
            (5, 4)
        );
        assert_eq!(coarse.loss_pixels, Some((w * h / 4) as u64));
        // A point through the centre of the image's block of rows 2-3 and columns 6-7
        // projects to the centre of the region's pixel (1, 2).
        let p = DVec3::new((7.0 - 6.0) / 100.0, (3.0 - 4.0) / 90.0, 1.0);
        let (u, v) = coarse.view.camera.project(p);
        assert!(
            (u - 2.5).abs() < 1e-12 && (v - 1.5).abs() < 1e-12,
            "{u} {v}"
        );
        let at = |i: usize, j: usize| coarse.observed[i * 5 + j];
        // Rows 0-1, columns 2-3: two object pixels of four.
        assert_eq!(at(0, 0), 0.5);
        // Rows 0-1, columns 8-9: all unknown; rows 4-5, columns 10-11: one of four.
        assert_eq!(at(0, 3), UNKNOWN);
        assert_eq!(at(2, 4), 0.0);
        // Rows 2-3, columns 2-3: all object, one without depth: the others' mean.
        assert_eq!(at(1, 0), 1.0);
        let d = coarse.depth.unwrap();
        assert!((d[5] - (1.02 + 1.03 + 1.03) / 3.0).abs() < 1e-6, "{}", d[5]);
        // Rows 2-3, columns 6-7: object in column 6 only: its depth, not the background's.
        assert!((d[5 + 2] - 1.06).abs() < 1e-6, "{}", d[7]);
        // Rows 6-7: background only.
        assert_eq!(d[15], 2.0);
    }

    /// A mask 200 pixels across (the mean shape's silhouette smaller): at detail 64 a step
    /// of 3 (66 pixels across), and the depth at every second of them at depth detail 32,
    /// every fourth at 16, every one at 0 or with detail 0.
    #[test]
    fn the_depth_step_keeps_the_depth_detail() {
        let space = crate::shape::random_space(&mut crate::rng::Rng::new(1), 3, 2);
        let camera = Camera::new(1000.0, 1000.0, 320.0, 240.0, 640, 480).unwrap();
        let observed: Vec<f32> = (0..640 * 480)
            .map(|i| {
                ((100..300).contains(&(i % 640)) && (100..300).contains(&(i / 640))) as u8 as f32
            })
            .collect();
        let pose = Pose::new([0.0, 0.0, 3.0], [0.0; 3]).unwrap();
        let job = Job::new(&space, &observed, View { camera, pose });
        let steps = |detail, depth_detail| {
            let region = Region::of_interest(&[job], detail, depth_detail)
                .unwrap()
                .unwrap();
            (region.step, region.depth_step)
        };
        assert_eq!(steps(64, 32), (3, 2));
        assert_eq!(steps(64, 16), (3, 4));
        assert_eq!(steps(64, 0), (3, 1));
        assert_eq!(steps(0, 32), (1, 1));
    }

    /// With a depth step, the cut keeps the depth at every depth step's row and column
    /// from the region's corner (the region pixel's own, the mean of its block), 0
    /// elsewhere, and its job weighs each kept sample by the step squared.
    #[test]
    fn the_depth_is_kept_at_every_depth_step() {
        let space = crate::shape::random_space(&mut crate::rng::Rng::new(1), 3, 2);
        let camera = Camera::new(100.0, 90.0, 6.0, 4.0, 12, 8).unwrap();
        let observed = vec![1.0f32; 96];
        let depth: Vec<f32> = (0..96).map(|i| 1.0 + i as f32 / 100.0).collect();
        let pose = Pose::new([0.0, 0.0, 1.0], [0.0; 3]).unwrap();
        let job = Job::new(&space, &observed, View { camera, pose }).with_depth(&depth);
        for step in [1, 2] {
            let region = Region {
                x: 1,
                y: 2,
                width: 10,
                height: 6,
                step,
                depth_step: 2,
            };
            let cut = region.cut(&job);
            let coarse = cut.job(&job);
            assert_eq!(coarse.depth_every, 2);
            let columns = (10 / step) as usize;
            let d = coarse.depth.unwrap();
            assert_eq!(d.len(), columns * (6 / step) as usize);
            for (i, &z) in d.iter().enumerate() {
                let (row, column) = (i / columns, i % columns);
                if row % 2 == 0 && column % 2 == 0 {
                    let (y, x, s) = (
                        2 + step as usize * row,
                        1 + step as usize * column,
                        step as usize,
                    );
                    let image = &depth;
                    let mean = (y..y + s)
                        .flat_map(|r| (x..x + s).map(move |c| image[r * 12 + c] as f64))
                        .sum::<f64>()
                        / (s * s) as f64;
                    assert!((z as f64 - mean).abs() < 1e-6, "{step} {i}: {z} {mean}");
                } else {
                    assert_eq!(z, 0.0, "{step} {i}");
                }
            }
        }
    }

    #[test]
    fn the_whole_image_at_a_step_drops_the_remainder() {
        let camera = Camera::new(100.0, 100.0, 6.5, 4.5, 13, 9).unwrap();
        let at = |step| Region {
            x: 0,
            y: 0,
            width: 2,
            height: 2,
            step,
            depth_step: 3,
        };
        let whole = at(2).whole(&camera).unwrap();
        assert_eq!(
            (whole.width, whole.height, whole.step, whole.depth_step),
            (12, 8, 2, 3)
        );
        assert_eq!(at(1).whole(&camera), None);
        assert_eq!(whole_steps(3, 8, 2, 13), Some((3, 6)));
        assert_eq!(whole_steps(8, 13, 2, 13), Some((7, 6)));
        assert_eq!(whole_steps(0, 13, 2, 13), None);
    }
}
