//! Image losses on the device and the observed images they compare against: mean squared
//! error (of antialiased coverage, or of interpolated colour), soft IoU, and a
//! signed-distance loss whose gradient reaches beyond the silhouette. The signed distance
//! field of an observed mask is computed on the device by jump flooding.
//! [`reference`](mod@reference) holds the float64 versions used by tests.

#[doc(hidden)] // the float64 model the tests check the device against
pub mod reference;

use std::path::Path;

use bytemuck::{Pod, Zeroable};

use crate::error::{Error, Result};
use crate::gpu::{Binding, Buffer, BufferKind, ComputePipeline, Context, Groups, Recorder};
use crate::shaders;

/// Which loss compares the rendered image A with the observed image O (N pixels per view;
/// the total is the sum over views).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Loss {
    /// sum (A - O)^2 / (N channels): of antialiased coverage against a mask, or of
    /// antialiased interpolated colour against a colour image.
    Mse,
    /// 1 - sum A O / sum (A + O - A O) (coverage against a mask).
    Iou,
    /// sum A S / N, with S the signed distance in pixels to the observed mask's boundary
    /// (negative inside): rendered coverage outside the mask costs its distance, inside
    /// the mask it gains, so the silhouette is pulled towards the mask from afar.
    Distance,
}

impl Loss {
    /// The loss's code in the shaders (`glsl/include/loss_codes.glsl`, checked by a test).
    pub(crate) fn code(self) -> u32 {
        match self {
            Loss::Mse => 0,
            Loss::Iou => 1,
            Loss::Distance => 2,
        }
    }

    /// The lower-case name that `from_str` parses (`mse`, `iou`, `distance`).
    pub fn name(self) -> &'static str {
        match self {
            Loss::Mse => "mse",
            Loss::Iou => "iou",
            Loss::Distance => "distance",
        }
    }
}

impl std::str::FromStr for Loss {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "mse" => Ok(Loss::Mse),
            "iou" => Ok(Loss::Iou),
            "distance" => Ok(Loss::Distance),
            other => Err(Error::InvalidInput(format!(
                "unknown loss '{other}' (mse, iou, distance)"
            ))),
        }
    }
}

/// The observed value of a pixel whose content is unknown (channel 0 of an observed image
/// below 0): hidden by something in front of the object, as the pixels outside BOP's
/// `mask_visib` but inside its `mask`, or ignored by the user. Such a pixel counts for
/// nothing, neither mask (or shading) nor depth, and the gradients of the others stay
/// exact (`glsl/include/loss.glsl`, `unknown`).
pub const UNKNOWN: f32 = -1.0;

/// Marks the pixels where `ignore` is nonzero as [`UNKNOWN`] in `image`, an observed image
/// of `channels` values per pixel in the same layout (`[view][row][column][channel]`).
/// An error if the sizes disagree.
pub fn mark_unknown(image: &mut [f32], channels: usize, ignore: &[f32]) -> Result<()> {
    if channels == 0 || image.len() != ignore.len() * channels {
        return Err(Error::InvalidInput(format!(
            "an ignore mask of {} pixels for an image of {} values ({channels} per pixel)",
            ignore.len(),
            image.len()
        )));
    }
    for (pixel, &i) in image.chunks_mut(channels).zip(ignore) {
        if i != 0.0 {
            pixel.fill(UNKNOWN);
        }
    }
    Ok(())
}

/// The hidden pixels of an object: those `whole` (nonzero where the object is, seen or
/// hidden, as BOP's `mask`) covers and the mask `visible` does not show as object; 1 where
/// hidden. Marked [`UNKNOWN`] ([`mark_unknown`]) they count for nothing. An error if the
/// sizes disagree.
pub fn hidden_pixels(visible: &[f32], whole: &[f32]) -> Result<Vec<f32>> {
    if visible.len() != whole.len() {
        return Err(Error::InvalidInput(format!(
            "a whole-object mask of {} pixels for a mask of {}",
            whole.len(),
            visible.len()
        )));
    }
    Ok(visible
        .iter()
        .zip(whole)
        .map(|(&v, &w)| (w != 0.0 && v <= 0.0) as u32 as f32)
        .collect())
}

/// The pixels of one view that its depth shows in front of the object: outside the mask
/// (`observed` channel 0 is 0), measured nearer than the nearest twentieth of the mask's
/// measured depth by more than `tolerance` (metres). What hides part of the object, found
/// before anything is rendered (the registration's pose alignment compares masks alone;
/// `DepthLoss::occlusion` finds the rest against the rendered surface). 1 where found.
pub fn in_front_of_mask(
    observed: &[f32],
    channels: usize,
    depth: &[f32],
    tolerance: f64,
) -> Vec<f32> {
    let mut object: Vec<f32> = depth
        .iter()
        .enumerate()
        .filter(|&(i, &z)| z > 0.0 && observed[i * channels] > 0.0)
        .map(|(_, &z)| z)
        .collect();
    if object.is_empty() || tolerance <= 0.0 {
        return vec![0.0; depth.len()];
    }
    object.sort_by(f32::total_cmp);
    let near = object[object.len() / 20] as f64 - tolerance;
    depth
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            (z > 0.0 && (z as f64) < near && observed[i * channels] == 0.0) as u32 as f32
        })
        .collect()
}

/// Reads a mask PNG of `width` x `height`, row-major. Where the image has an alpha channel
/// that is used (some pixel not fully opaque), alpha is the mask: 1 where it is nonzero (a
/// cut-out, whatever its colour). Otherwise (no alpha, or opaque everywhere, as many tools
/// save masks) 1 where any colour channel is nonzero, at any bit depth (a 16-bit mask
/// whose object value is 1 reads as object). A size other than `width` x `height` is an
/// error (never a silent resize).
pub fn load_mask(path: &Path, width: u32, height: u32) -> Result<Vec<f32>> {
    let image = open_image(path, "mask", width, height)?;
    let object = |on: bool| if on { 1.0 } else { 0.0 };
    if image.color().has_alpha() {
        let rgba = image.to_rgba16();
        if rgba.pixels().any(|p| p.0[3] != u16::MAX) {
            return Ok(rgba.pixels().map(|p| object(p.0[3] != 0)).collect());
        }
    }
    Ok(image
        .to_rgb16()
        .pixels()
        .map(|p| object(p.0.iter().any(|&c| c != 0)))
        .collect())
}

/// Opens the image `path` (a `what`, for errors), which must be `width` x `height`.
fn open_image(path: &Path, what: &str, width: u32, height: u32) -> Result<image::DynamicImage> {
    let image = image::open(path).map_err(|e| Error::format(path, e.to_string()))?;
    if (image.width(), image.height()) != (width, height) {
        return Err(Error::format(
            path,
            format!(
                "{what} is {}x{} but --size is {width}x{height}",
                image.width(),
                image.height()
            ),
        ));
    }
    Ok(image)
}

/// Reads an observed depth image of `width` x `height` as metres, row-major: a `.npy` of
/// float32 or float64 metres (H x W), or a 16-bit grey PNG whose value times
/// `png_millimetres` is millimetres (BOP's `depth_scale`: 1 for millimetres, 0.1 for
/// tenths). 0 is no measurement; a negative or non-finite value is an error (never
/// silently a hole).
pub fn load_depth(path: &Path, width: u32, height: u32, png_millimetres: f64) -> Result<Vec<f32>> {
    if !(png_millimetres.is_finite() && png_millimetres > 0.0) {
        return Err(Error::InvalidInput(format!(
            "the depth scale must be positive millimetres per PNG unit, not {png_millimetres}"
        )));
    }
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    let depth: Vec<f32> = if is_npy {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        // Never allocate for a header that claims more than the file holds.
        crate::io::check_npy_size(&path.display().to_string(), &bytes)?;
        use ndarray_npy::ReadNpyExt;
        let array = match ndarray::Array2::<f32>::read_npy(&bytes[..]) {
            Ok(a) => a,
            Err(_) => ndarray::Array2::<f64>::read_npy(&bytes[..])
                .map_err(|e| {
                    Error::format(
                        path,
                        format!("not an H x W array of float32 or float64: {e}"),
                    )
                })?
                .mapv(|z| z as f32),
        };
        if array.dim() != (height as usize, width as usize) {
            return Err(Error::format(
                path,
                format!(
                    "depth is {:?} (rows, columns) but --size is {width}x{height}",
                    array.dim()
                ),
            ));
        }
        array.iter().copied().collect()
    } else {
        match open_image(path, "depth image", width, height)? {
            image::DynamicImage::ImageLuma16(grey) => {
                let metres = png_millimetres * 1e-3;
                grey.pixels()
                    .map(|p| (p.0[0] as f64 * metres) as f32)
                    .collect()
            }
            other => {
                return Err(Error::format(
                    path,
                    format!(
                        "a depth PNG must be 16-bit grey (millimetres), not {:?}",
                        other.color()
                    ),
                ))
            }
        }
    };
    if let Some(i) = depth.iter().position(|z| !(z.is_finite() && *z >= 0.0)) {
        return Err(Error::format(
            path,
            format!(
                "depth at row {} column {} is {} (metres >= 0 expected; 0 = no measurement)",
                i / width as usize,
                i % width as usize,
                depth[i]
            ),
        ));
    }
    Ok(depth)
}

/// Loads an observed shading image (grey, or colour taken as its luminance) of the given
/// size as values in [0, 1], `[row][column]`, set to 0 (the background's shade) wherever
/// `mask` is 0.
pub fn load_shading(path: &Path, mask: &[f32], width: u32, height: u32) -> Result<Vec<f32>> {
    Ok(open_image(path, "shading image", width, height)?
        .to_luma16()
        .pixels()
        .zip(mask)
        .map(|(p, &m)| {
            if m > 0.0 {
                p.0[0] as f32 / 65535.0
            } else {
                0.0
            }
        })
        .collect())
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct DistanceConstants {
    width: u32,
    height: u32,
    step: i32,
}
const _: () = assert!(shaders::DISTANCE_SEED_COMP.takes::<DistanceConstants>());
const _: () = assert!(shaders::DISTANCE_JUMP_COMP.takes::<DistanceConstants>());
const _: () = assert!(shaders::DISTANCE_FINAL_COMP.takes::<DistanceConstants>());

/// Jump-flooding pipelines for signed distance fields of masks.
pub struct DistanceField {
    seed: ComputePipeline,
    jump: ComputePipeline,
    finish: ComputePipeline,
}

impl DistanceField {
    /// Builds the jump-flooding pipelines.
    pub fn new(ctx: &Context) -> Result<Self> {
        Ok(Self {
            seed: ComputePipeline::new(ctx, &shaders::DISTANCE_SEED_COMP)?,
            jump: ComputePipeline::new(ctx, &shaders::DISTANCE_JUMP_COMP)?,
            finish: ComputePipeline::new(ctx, &shaders::DISTANCE_FINAL_COMP)?,
        })
    }

    /// Records the signed distance field of `views` masks of `width` x `height` (float,
    /// `[view][y][x]`, nonzero = object) into `distance`, using two scratch buffers of
    /// `scratch_bytes` each.
    pub fn record(
        &self,
        rec: &mut Recorder,
        masks: &Buffer,
        scratch: [&Buffer; 2],
        distance: &Buffer,
        (width, height, views): (u32, u32, u32),
    ) -> Result<()> {
        let needed = Self::scratch_bytes(width, height, views);
        if scratch.iter().any(|b| b.size() < needed) || distance.size() < needed / 2 {
            return Err(Error::InvalidInput(
                "distance field buffers are too small".into(),
            ));
        }
        let groups = (width.div_ceil(8), height.div_ceil(8));
        let mut constants = DistanceConstants {
            width,
            height,
            step: 0,
        };
        rec.run_compute(
            &self.seed,
            &[Binding::buffer(masks), Binding::buffer(scratch[0])],
            &constants,
            Groups::Count(groups.0, groups.1, 2 * views),
        );
        rec.memory_barrier();

        let mut steps = Vec::new();
        let mut step = width.max(height).next_power_of_two() / 2;
        while step >= 1 {
            steps.push(step);
            step /= 2;
        }
        // Two more passes at steps 2 and 1 mend most of jump flooding's errors (JFA+2).
        steps.extend([2, 1]);
        let mut current = 0;
        for step in steps {
            constants.step = step as i32;
            rec.run_compute(
                &self.jump,
                &[
                    Binding::buffer(scratch[current]),
                    Binding::buffer(scratch[1 - current]),
                ],
                &constants,
                Groups::Count(groups.0, groups.1, 2 * views),
            );
            rec.memory_barrier();
            current = 1 - current;
        }
        rec.run_compute(
            &self.finish,
            &[
                Binding::buffer(masks),
                Binding::buffer(scratch[current]),
                Binding::buffer(distance),
            ],
            &constants,
            Groups::Count(groups.0, groups.1, views),
        );
        rec.memory_barrier();
        Ok(())
    }

    /// Bytes of each scratch buffer for `views` masks of `width` x `height`.
    pub fn scratch_bytes(width: u32, height: u32, views: u32) -> u64 {
        2 * width as u64 * height as u64 * views as u64 * 4
    }

    /// One-shot convenience: the signed distance field of one mask (row-major).
    pub fn compute(
        &self,
        ctx: &Context,
        mask: &[f32],
        width: u32,
        height: u32,
    ) -> Result<Vec<f32>> {
        if mask.len() != (width * height) as usize {
            return Err(Error::InvalidInput(format!(
                "mask of {} values is not {width}x{height}",
                mask.len()
            )));
        }
        let masks = Buffer::from_slice(ctx, "masks", mask)?;
        let bytes = Self::scratch_bytes(width, height, 1);
        let a = Buffer::new(ctx, "jump flooding a", bytes, BufferKind::Device)?;
        let b = Buffer::new(ctx, "jump flooding b", bytes, BufferKind::Device)?;
        let distance = Buffer::new(ctx, "distance field", bytes / 2, BufferKind::Device)?;
        let mut rec = Recorder::new(ctx)?;
        self.record(&mut rec, &masks, [&a, &b], &distance, (width, height, 1))?;
        ctx.submit_and_wait(rec)?;
        distance.read_range(0, mask.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shaders' loss codes (glsl/include/loss_codes.glsl) are `Loss::code`'s.
    #[test]
    fn loss_codes_match_the_shaders() {
        let glsl = include_str!("../../glsl/include/loss_codes.glsl");
        for loss in [Loss::Mse, Loss::Iou, Loss::Distance] {
            let line = format!(
                "const uint LOSS_{} = {}u;",
                loss.name().to_uppercase(),
                loss.code()
            );
            assert!(glsl.contains(&line), "loss_codes.glsl lacks `{line}`");
        }
    }
}
