//! Frames in the BOP format (the field's benchmark layout, bop.felk.cvut.cz), read and
//! written. A scene folder holds `scene_camera.json` (per image `cam_K`, 9 numbers
//! row-major, and `depth_scale`: a depth PNG value times it is millimetres),
//! `scene_gt.json` (per image a list of objects: `obj_id`, `cam_R_m2c` 9 numbers
//! row-major, `cam_t_m2c` in millimetres; model to camera), `depth/IMAGE.png` (16-bit),
//! `mask_visib/IMAGE_GT.png` (the visible part of ground-truth object GT), optionally
//! `mask/IMAGE_GT.png` (the whole object, hidden parts included) and `rgb/`. Image ids are
//! written with six digits. Models are in millimetres.
//!
//! `cam_K` is in BOP's (OpenCV's) convention, pixel centres on integer coordinates; vkdr's
//! [`Camera`] puts pixel (i, j)'s centre at (j + 0.5, i + 0.5), so reading adds half a
//! pixel to the principal point and writing takes it off.
//!
//! Everything a frame needs is checked when it is read, and each problem names the file
//! and the key.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use glam::{DMat3, DVec3};
use serde_json::Value;

use vkdr::{Camera, Pose};

/// One ground-truth object of a frame.
#[derive(Clone, Debug)]
pub struct FrameObject {
    /// Its index in the image's `scene_gt.json` list (the masks' second number).
    pub gt_index: usize,
    pub obj_id: u64,
    /// Model (metres) to camera: BOP's `cam_R_m2c`, `cam_t_m2c` / 1000.
    pub model_to_camera: Pose,
    /// `mask_visib`: 1 where the object is seen.
    pub visible: Vec<f32>,
    /// `mask` where present: 1 where the object is, seen or hidden.
    pub whole: Option<Vec<f32>>,
}

/// One image of a scene: its camera, depth (metres, 0 = none) and objects, and where its
/// colour image is (`rgb/IMAGE.png` or `.jpg`, where the scene has one: for pictures only).
#[derive(Clone, Debug)]
pub struct Frame {
    pub scene: String,
    pub image: u64,
    pub camera: Camera,
    pub depth: Vec<f32>,
    pub objects: Vec<FrameObject>,
    pub rgb: Option<PathBuf>,
}

/// The scene folders under `dir`: `dir` itself where it holds `scene_gt.json`, else each
/// folder in it that does (sorted).
pub fn scene_dirs(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.join("scene_gt.json").is_file() {
        return Ok(vec![dir.to_path_buf()]);
    }
    let mut scenes: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("scene_gt.json").is_file())
        .collect();
    scenes.sort();
    if scenes.is_empty() {
        bail!(
            "{}: no BOP scene (a folder with scene_gt.json, scene_camera.json, depth/ and mask_visib/) \
             in it or under it",
            dir.display()
        );
    }
    Ok(scenes)
}

fn read_json(path: &Path) -> Result<serde_json::Map<String, Value>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    match serde_json::from_str(&text) {
        Ok(Value::Object(map)) => Ok(map),
        Ok(_) => bail!("{}: not a JSON object of images", path.display()),
        Err(e) => bail!("{}: not JSON: {e}", path.display()),
    }
}

/// `N` numbers at `key` of `entry` (`what` names the file and image for errors).
fn numbers<const N: usize>(entry: &Value, key: &str, what: &str) -> Result<[f64; N]> {
    let Some(value) = entry.get(key) else {
        bail!("{what}: no \"{key}\"");
    };
    let list = value
        .as_array()
        .filter(|a| a.len() == N)
        .with_context(|| format!("{what}: \"{key}\" must be a list of {N} numbers, not {value}"))?;
    let mut out = [0.0; N];
    for (o, v) in out.iter_mut().zip(list) {
        *o = v
            .as_f64()
            .filter(|x| x.is_finite())
            .with_context(|| format!("{what}: \"{key}\" holds {v}, not a finite number"))?;
    }
    Ok(out)
}

/// A 3 x 3 row-major list as a rotation; an error where it is not one (1e-3).
fn rotation(m: [f64; 9], what: &str) -> Result<DMat3> {
    let r = DMat3::from_cols_array(&m).transpose();
    let off = (r * r.transpose() - DMat3::IDENTITY).to_cols_array();
    if off.iter().any(|v| v.abs() > 1e-3) || (r.determinant() - 1.0).abs() > 1e-3 {
        bail!("{what}: \"cam_R_m2c\" is not a rotation (orthonormal, determinant 1)");
    }
    Ok(r)
}

/// A PNG mask (nonzero = 1) that must be `width` x `height`.
fn read_mask(path: &Path, width: u32, height: u32) -> Result<Vec<f32>> {
    let image = image::open(path).with_context(|| format!("reading {}", path.display()))?;
    if (image.width(), image.height()) != (width, height) {
        bail!(
            "{}: the mask is {}x{} but the frame's depth is {width}x{height}",
            path.display(),
            image.width(),
            image.height()
        );
    }
    Ok(image
        .to_luma16()
        .pixels()
        .map(|p| (p.0[0] != 0) as u32 as f32)
        .collect())
}

/// Every frame of one scene folder, checked.
pub fn read_scene(dir: &Path) -> Result<Vec<Frame>> {
    let scene = dir
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let cameras_path = dir.join("scene_camera.json");
    let gt_path = dir.join("scene_gt.json");
    let cameras = read_json(&cameras_path)?;
    let gt = read_json(&gt_path)?;
    let mut images: Vec<(u64, &Value)> = Vec::new();
    for (key, objects) in &gt {
        let image: u64 = key.parse().with_context(|| {
            format!("{}: image key \"{key}\" is not a number", gt_path.display())
        })?;
        images.push((image, objects));
    }
    images.sort_by_key(|(i, _)| *i);
    let mut frames = Vec::new();
    for (image, objects) in images {
        let key = image.to_string();
        let at = format!("{} image {key}", cameras_path.display());
        let Some(entry) = cameras.get(&key) else {
            bail!(
                "{}: no image \"{key}\" (scene_gt.json has it)",
                cameras_path.display()
            );
        };
        let k = numbers::<9>(entry, "cam_K", &at)?;
        let depth_scale = entry.get("depth_scale").with_context(|| {
            format!("{at}: no \"depth_scale\" (millimetres per depth PNG unit)")
        })?;
        let depth_scale = depth_scale
            .as_f64()
            .filter(|d| d.is_finite())
            .with_context(|| {
                format!("{at}: \"depth_scale\" must be a number, not {depth_scale}")
            })?;
        if depth_scale <= 0.0 {
            bail!("{at}: \"depth_scale\" must be positive millimetres per unit, not {depth_scale}");
        }
        if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
            bail!("{at}: \"cam_K\" must be [fx, 0, cx, 0, fy, cy, 0, 0, 1], not {k:?}");
        }
        let depth_path = dir.join("depth").join(format!("{image:06}.png"));
        let depth_image = image::open(&depth_path)
            .with_context(|| format!("reading {}", depth_path.display()))?;
        let (width, height) = (depth_image.width(), depth_image.height());
        let image::DynamicImage::ImageLuma16(grey) = depth_image else {
            bail!(
                "{}: a depth PNG must be 16-bit grey (BOP), not {:?}",
                depth_path.display(),
                depth_image.color()
            );
        };
        let metres = depth_scale * 1e-3;
        let depth: Vec<f32> = grey
            .pixels()
            .map(|p| (p.0[0] as f64 * metres) as f32)
            .collect();
        check_depth_units(&depth, depth_scale, &depth_path)?;
        // BOP's cam_K puts pixel centres on integers (OpenCV); vkdr's camera puts pixel
        // (i, j)'s centre at (j + 0.5, i + 0.5): the principal point moves by half a pixel.
        let camera = Camera::new(k[0], k[4], k[2] + 0.5, k[5] + 0.5, width, height)
            .and_then(|c| c.validated())
            .with_context(|| format!("{at}: \"cam_K\""))?;
        let list = objects.as_array().with_context(|| {
            format!(
                "{}: image \"{key}\" must hold a list of objects",
                gt_path.display()
            )
        })?;
        let mut frame_objects = Vec::new();
        for (gt_index, object) in list.iter().enumerate() {
            let what = format!("{} image {key} object {gt_index}", gt_path.display());
            let obj_id = object
                .get("obj_id")
                .and_then(Value::as_u64)
                .with_context(|| format!("{what}: no \"obj_id\" (a whole number)"))?;
            let r = rotation(numbers::<9>(object, "cam_R_m2c", &what)?, &what)?;
            let t = DVec3::from_array(numbers::<3>(object, "cam_t_m2c", &what)?) * 1e-3;
            let mask_path = |folder: &str| {
                dir.join(folder)
                    .join(format!("{image:06}_{gt_index:06}.png"))
            };
            let visible = read_mask(&mask_path("mask_visib"), width, height)?;
            let whole_path = mask_path("mask");
            let whole = if whole_path.is_file() {
                Some(read_mask(&whole_path, width, height)?)
            } else {
                None
            };
            frame_objects.push(FrameObject {
                gt_index,
                obj_id,
                model_to_camera: Pose {
                    translation: t,
                    rotation: glam::DQuat::from_mat3(&r).to_scaled_axis(),
                },
                visible,
                whole,
            });
        }
        let rgb = ["png", "jpg"]
            .iter()
            .map(|ext| dir.join("rgb").join(format!("{image:06}.{ext}")))
            .find(|path| path.is_file());
        frames.push(Frame {
            scene: scene.clone(),
            image,
            camera,
            depth,
            objects: frame_objects,
            rgb,
        });
    }
    Ok(frames)
}

/// A depth whose measured pixels lie mostly nearer than 5 cm is in other units than
/// declared (metres stored where `depth_scale` says millimetres): an error naming it.
fn check_depth_units(depth: &[f32], depth_scale: f64, path: &Path) -> Result<()> {
    let mut measured: Vec<f32> = depth.iter().copied().filter(|&z| z > 0.0).collect();
    if measured.is_empty() {
        return Ok(());
    }
    measured.sort_by(f32::total_cmp);
    let median = measured[measured.len() / 2] as f64;
    if median < 0.05 {
        bail!(
            "{}: the median measured depth is {:.1} mm with depth_scale {depth_scale} \
             (a PNG value times depth_scale is millimetres): is it stored in metres or in \
             other units than declared?",
            path.display(),
            median * 1e3
        );
    }
    Ok(())
}

/// What `eval-frames` needs of one BOP object: the category it is an instance of (a
/// category folder: canonical.obj, train/), its model (a PLY or OBJ in millimetres, in the
/// model's frame) and the rigid transform from the model's frame to the category's.
#[derive(Clone, Debug)]
pub struct ObjectCategory {
    pub category: PathBuf,
    pub model: PathBuf,
    /// Model frame (metres) to category frame.
    pub model_to_category: Pose,
}

/// Reads the map file: `{"OBJ_ID": {"category": DIR, "model": OBJ (millimetres),
/// "model_to_category": {"translation": [x, y, z] metres, "rotation": [rx, ry, rz]
/// axis-angle radians}}}`; paths relative to the file's folder. `model_to_category` may be
/// left out (the identity).
pub fn read_map(path: &Path) -> Result<BTreeMap<u64, ObjectCategory>> {
    let map = read_json(path)?;
    let folder = path.parent().unwrap_or(Path::new("."));
    let mut out = BTreeMap::new();
    for (key, entry) in &map {
        let what = format!("{} object \"{key}\"", path.display());
        let obj_id: u64 = key
            .parse()
            .with_context(|| format!("{what}: the key must be a BOP obj_id (a whole number)"))?;
        let file = |name: &str| -> Result<PathBuf> {
            let p = entry
                .get(name)
                .and_then(Value::as_str)
                .with_context(|| format!("{what}: no \"{name}\" (a path)"))?;
            Ok(folder.join(p))
        };
        let category = file("category")?;
        if !category.join("canonical.obj").is_file() {
            bail!(
                "{what}: \"category\" {} is not a category folder (canonical.obj, train/)",
                category.display()
            );
        }
        let model = file("model")?;
        let model_to_category = match entry.get("model_to_category") {
            None => Pose::at([0.0; 3]),
            Some(t) => {
                let at = format!("{what} \"model_to_category\"");
                Pose::new(
                    numbers::<3>(t, "translation", &at)?,
                    numbers::<3>(t, "rotation", &at)?,
                )?
            }
        };
        out.insert(
            obj_id,
            ObjectCategory {
                category,
                model,
                model_to_category,
            },
        );
    }
    if out.is_empty() {
        bail!("{}: maps no obj_id to a category", path.display());
    }
    Ok(out)
}

/// Writes one frame of a scene folder in the BOP layout (the fixtures of the tests and of
/// `vkdr gen-frames`): the camera with `depth_scale`, the depth (metres, rounded to the
/// scale's unit), each object's `mask_visib` and `mask`, appended to the scene's JSON
/// files.
pub fn write_frame(dir: &Path, frame: &Frame, depth_scale: f64) -> Result<()> {
    for folder in ["depth", "mask_visib", "mask"] {
        std::fs::create_dir_all(dir.join(folder))
            .with_context(|| format!("creating {}", dir.join(folder).display()))?;
    }
    let key = frame.image.to_string();
    let c = &frame.camera;
    let mut cameras = read_json(&dir.join("scene_camera.json")).unwrap_or_default();
    cameras.insert(
        key.clone(),
        serde_json::json!({
            // BOP's convention: pixel centres on integers (see `read_scene`).
            "cam_K": [c.fx, 0.0, c.cx - 0.5, 0.0, c.fy, c.cy - 0.5, 0.0, 0.0, 1.0],
            "depth_scale": depth_scale,
        }),
    );
    let mut gt = read_json(&dir.join("scene_gt.json")).unwrap_or_default();
    let objects: Vec<Value> = frame
        .objects
        .iter()
        .map(|o| {
            let r = o
                .model_to_camera
                .rotation_matrix()
                .transpose()
                .to_cols_array();
            serde_json::json!({
                "obj_id": o.obj_id,
                "cam_R_m2c": r,
                "cam_t_m2c": (o.model_to_camera.translation * 1e3).to_array(),
            })
        })
        .collect();
    gt.insert(key, Value::Array(objects));
    vkdr::io::write_json(&dir.join("scene_camera.json"), &Value::Object(cameras))?;
    vkdr::io::write_json(&dir.join("scene_gt.json"), &Value::Object(gt))?;
    let units = |z: f32| ((z as f64 * 1e3 / depth_scale).round()).clamp(0.0, 65535.0) as u16;
    let depth = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(c.width, c.height, |x, y| {
        image::Luma([units(frame.depth[(y * c.width + x) as usize])])
    });
    vkdr::io::write_png(
        &dir.join("depth").join(format!("{:06}.png", frame.image)),
        &image::DynamicImage::ImageLuma16(depth),
    )?;
    let mask_png = |mask: &[f32]| {
        image::DynamicImage::ImageLuma8(image::GrayImage::from_fn(c.width, c.height, |x, y| {
            image::Luma([if mask[(y * c.width + x) as usize] > 0.0 {
                255
            } else {
                0
            }])
        }))
    };
    for o in &frame.objects {
        let name = format!("{:06}_{:06}.png", frame.image, o.gt_index);
        vkdr::io::write_png(&dir.join("mask_visib").join(&name), &mask_png(&o.visible))?;
        if let Some(whole) = &o.whole {
            vkdr::io::write_png(&dir.join("mask").join(&name), &mask_png(whole))?;
        }
    }
    Ok(())
}

/// Writes `mesh` as a binary little-endian PLY (float x, y, z; faces as uchar-counted int
/// lists), as BOP ships its models.
pub fn write_ply(path: &Path, mesh: &vkdr::Mesh) -> Result<()> {
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by vkdr gen-frames\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertex_count(),
        mesh.triangle_count()
    )
    .into_bytes();
    for p in mesh.positions() {
        for c in p {
            bytes.extend(c.to_le_bytes());
        }
    }
    for t in mesh.triangles() {
        bytes.push(3);
        for v in t {
            bytes.extend((*v as i32).to_le_bytes());
        }
    }
    Ok(vkdr::io::write_atomically(path, &bytes)?)
}
