//! Pictures of G-buffers for people: masks, false-colour ids, barycentrics, depth; and a
//! mesh's views rendered and written as those pictures.

use std::path::Path;

use anyhow::{Context as _, Result};
use image::{DynamicImage, GrayImage, Rgb, RgbImage, RgbaImage};
use ndarray::{s, ArrayView2};

use vkdr::gpu::Context;
use vkdr::io::{write_npy, write_png};
use vkdr::raster::{Outputs, Rasterizer, View};
use vkdr::Mesh;

/// White where a triangle covers the pixel.
pub fn mask(ids: ArrayView2<u32>) -> DynamicImage {
    let (h, w) = ids.dim();
    DynamicImage::ImageLuma8(GrayImage::from_fn(w as u32, h as u32, |x, y| {
        image::Luma([if ids[[y as usize, x as usize]] > 0 {
            255
        } else {
            0
        }])
    }))
}

/// Each triangle id in its own colour (a hash), black background.
pub fn ids(ids: ArrayView2<u32>) -> DynamicImage {
    let (h, w) = ids.dim();
    DynamicImage::ImageRgb8(RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let id = ids[[y as usize, x as usize]];
        if id == 0 {
            return Rgb([0, 0, 0]);
        }
        let hash = id
            .wrapping_mul(0x9E37_79B1)
            .rotate_left(13)
            .wrapping_mul(0x85EB_CA6B);
        let [r, g, b, _] = hash.to_le_bytes();
        Rgb([r | 0x40, g | 0x40, b | 0x40])
    }))
}

/// Barycentrics as colour: red = corner 0, green = corner 1, blue = corner 2.
pub fn barycentrics(ids: ArrayView2<u32>, bary: ndarray::ArrayView3<f32>) -> DynamicImage {
    let (h, w) = ids.dim();
    DynamicImage::ImageRgb8(RgbImage::from_fn(w as u32, h as u32, |x, y| {
        let (i, j) = (y as usize, x as usize);
        if ids[[i, j]] == 0 {
            return Rgb([0, 0, 0]);
        }
        let (u, v) = (bary[[i, j, 0]], bary[[i, j, 1]]);
        let to_byte = |t: f32| (t.clamp(0.0, 1.0) * 255.0).round() as u8;
        Rgb([to_byte(u), to_byte(v), to_byte(1.0 - u - v)])
    }))
}

/// Depth as grey, near = bright, scaled to the covered range; background black.
pub fn depth(depth: ArrayView2<f32>) -> DynamicImage {
    let (h, w) = depth.dim();
    let covered = depth.iter().copied().filter(|&z| z > 0.0);
    let (lo, hi) = covered.fold((f32::INFINITY, 0.0f32), |(lo, hi), z| {
        (lo.min(z), hi.max(z))
    });
    let span = (hi - lo).max(f32::EPSILON);
    DynamicImage::ImageLuma8(GrayImage::from_fn(w as u32, h as u32, |x, y| {
        let z = depth[[y as usize, x as usize]];
        image::Luma([if z > 0.0 {
            (255.0 - 200.0 * (z - lo) / span).round() as u8
        } else {
            0
        }])
    }))
}

/// An RGBA8 render.
pub fn colour(pixels: ndarray::ArrayView3<u8>) -> DynamicImage {
    let (h, w, _) = pixels.dim();
    let data: Vec<u8> = pixels.iter().copied().collect();
    DynamicImage::ImageRgba8(RgbaImage::from_raw(w as u32, h as u32, data).expect("RGBA8 image"))
}

/// Renders the views and writes pictures (and the raw G-buffer) into `out`; with several
/// views, file names get a `view<k>_` prefix. Returns the written paths.
pub fn write_views(
    ctx: &Context,
    rasterizer: &Rasterizer,
    mesh: &Mesh,
    views: &[View],
    out: &Path,
    raw: bool,
) -> Result<Vec<String>> {
    let gbuffer = rasterizer.render(ctx, mesh, views, Outputs::IdsBaryDepth)?;
    let colour = rasterizer.render_shaded(ctx, mesh, views)?;
    let depth = gbuffer
        .depth
        .as_ref()
        .context("G-buffer rendered without depth")?;
    let bary_all = gbuffer
        .bary
        .as_ref()
        .context("G-buffer rendered without barycentrics")?;
    let mut written = Vec::new();
    for k in 0..views.len() {
        let prefix = if views.len() > 1 {
            format!("view{k}_")
        } else {
            String::new()
        };
        let ids = gbuffer.ids.slice(s![k, .., ..]);
        let bary = bary_all.slice(s![k, .., .., ..]);
        let z = depth.slice(s![k, .., ..]);
        let mut save = |name: &str, picture: image::DynamicImage| -> Result<()> {
            let path = out.join(format!("{prefix}{name}"));
            write_png(&path, &picture)?;
            written.push(path.display().to_string());
            Ok(())
        };
        save("colour.png", self::colour(colour.slice(s![k, .., .., ..])))?;
        save("mask.png", mask(ids))?;
        save("ids.png", self::ids(ids))?;
        save("bary.png", barycentrics(ids, bary))?;
        save("depth.png", self::depth(z))?;
        if raw {
            for (name, result) in [
                (
                    "ids.npy",
                    write_npy(&out.join(format!("{prefix}ids.npy")), &ids),
                ),
                (
                    "bary.npy",
                    write_npy(&out.join(format!("{prefix}bary.npy")), &bary),
                ),
                (
                    "depth.npy",
                    write_npy(&out.join(format!("{prefix}depth.npy")), &z),
                ),
            ] {
                result?;
                written.push(out.join(format!("{prefix}{name}")).display().to_string());
            }
        }
    }
    Ok(written)
}
