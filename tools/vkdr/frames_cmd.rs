//! `vkdr eval-frames`: the evaluation on observed frames in the BOP format (real camera
//! frames: the visible mask, the sensor's depth, the ground-truth pose), and `vkdr
//! gen-frames`, which renders such frames from a generated dataset (with a table, an
//! occluder, depth noise and holes) so that the whole path can be tried without one.

use std::collections::btree_map::{BTreeMap, Entry};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _, Result};
use glam::DVec3;

use vkdr::gpu::Context;
use vkdr::raster::View;
use vkdr::register::Registrar;
use vkdr::shape::ShapeSpace;
use vkdr::{Mesh, Pose};
use vkdr_app::bop::{self, Frame, FrameObject, ObjectCategory};
use vkdr_app::eval::{self, EvalSettings, GravitySource, Images, TrialScene, TrialSource};

use crate::args::{DepthLossArgs, RenamedArgs, ShardArgs};
use crate::shard;
use crate::spaces::{dir_name, obj_files};

#[derive(clap::Args)]
pub struct Args {
    /// A BOP scene folder (scene_camera.json, scene_gt.json, depth/, mask_visib/, optionally
    /// mask/ and rgb/), or a folder of them.
    #[arg(required_unless_present = "merge", conflicts_with = "merge")]
    dir: Option<PathBuf>,
    /// The map from BOP obj_id to category: {"OBJ_ID": {"category": DIR, "model": PLY or
    /// OBJ in millimetres, "model_to_category": {"translation": [m], "rotation": [axis-angle]}}}.
    /// Default: DIR/map.json.
    #[arg(long, conflicts_with = "merge")]
    categories: Option<PathBuf>,
    /// Only these images: SCENE/IMAGE, comma-separated (e.g. 000000/1,000001/19); an
    /// error where one is not in DIR.
    #[arg(long, value_delimiter = ',')]
    images: Vec<String>,
    /// Pose-noise registrations per object (each from its own seeded noisy start).
    #[arg(long, default_value_t = 3)]
    trials: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// With pose noise, keep the object's up axis within --tilt-tolerance of up: known (the
    /// ground truth's up), from-depth (the support plane fitted around the mask) or none.
    #[arg(long, value_parser = ["known", "from-depth", "none"], default_value = "from-depth")]
    gravity: String,
    #[command(flatten)]
    tilt: crate::args::TiltArgs,
    /// Where --gravity from-depth finds no support plane: register that frame without
    /// gravity (none; its rows say so) or count it as failed (error).
    #[arg(long, value_parser = ["none", "error"], default_value = "none")]
    gravity_fallback: String,
    /// Keep the shape's scale at the training set's. By default one uniform scale (0.25
    /// to 1.75) is fitted too, which the depth observes: a robot does not know the instance's
    /// size.
    #[arg(long)]
    no_scale: bool,
    /// Dimensions of each category's shape space.
    #[arg(long, default_value_t = EvalSettings::default().dims)]
    dims: usize,
    /// Render an object over twice this many pixels across at a coarser step (each pixel
    /// the mean of the image's step x step); 0: at the image's own pixels.
    #[arg(long, default_value_t = vkdr::register::DETAIL)]
    detail: u32,
    /// Register an object only where its visible mask shows at least this share of its
    /// silhouette in the image (BOP's visib_fract; BOP's targets need 0.1): the silhouette
    /// from the scene's mask/ where present, else the model rendered at the annotated
    /// pose. An object under it is a failed unit saying so; 0: every object.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.1)]
    min_visible: f64,
    /// Write a picture of each unit into OUT/pictures (SCENE_IMAGE_K.png): the frame's
    /// colour image (its measured depth where it has none), and its observed mask (blue)
    /// against the silhouette registered with the pose known and from its first trial's
    /// pose noise (red; both magenta; unknown pixels green), cropped around the object.
    #[arg(long, conflicts_with = "merge")]
    pictures: bool,
    #[command(flatten)]
    depth_loss: DepthLossArgs,
    #[command(flatten)]
    renamed: RenamedArgs,
    #[command(flatten)]
    pub shards: ShardArgs,
}

/// The evaluation's settings from the flags (the camera and distance are each frame's).
fn settings(args: &Args) -> Result<EvalSettings> {
    args.renamed.check()?;
    if !(0.0..=1.0).contains(&args.min_visible) {
        bail!("--min-visible must be 0 to 1, not {}", args.min_visible);
    }
    if !(2..=1000).contains(&args.trials) {
        bail!(
            "--trials must be 2 to 1000 (a spread needs two), not {}",
            args.trials
        );
    }
    let mut base = EvalSettings {
        trials: args.trials,
        seed: args.seed,
        dims: args.dims,
        depth: Some(args.depth_loss.loss()?),
        tilt_tolerance: args.tilt.radians(args.gravity != "none")?,
        gravity_fallback: args.gravity_fallback == "none",
        gravity: match args.gravity.as_str() {
            "known" => Some(GravitySource::Known),
            "from-depth" => Some(GravitySource::FromDepth),
            _ => None,
        },
        ..Default::default()
    };
    base.known_pose.optimize_scale = !args.no_scale;
    base.pose_noise.optimize_scale = !args.no_scale;
    base.known_pose.detail = args.detail;
    base.pose_noise.detail = args.detail;
    base.known_pose.depth_detail = args.depth_loss.depth_detail;
    base.pose_noise.depth_detail = args.depth_loss.depth_detail;
    // Before any work: a parameter out of range would fail every unit after its reference.
    base.known_pose_params().validate()?;
    base.pose_noise_params().validate()?;
    Ok(base)
}

/// A frame's object with what it needs: its category's index and its model in the
/// category's frame.
struct Target<'a> {
    frame: &'a Frame,
    object: &'a FrameObject,
    category: usize,
}

pub fn run(args: &Args) -> Result<()> {
    if let Some(merge) = &args.shards.merge {
        return shard::write_merged(
            "eval-frames",
            &merge[0],
            &merge[1..],
            |line| {
                let run = shard::parse_flags::<Args>("eval-frames", line)?;
                let frames = read_frames(&run)?;
                let (map_file, map) = read_map(&run)?;
                let mapped = Mapped::new(&frames, &map, &map_file)?;
                let settings = settings(&run)?;
                let resolved = shard::resolved(&settings);
                Ok(((settings, describe(&frames, &mapped)), resolved))
            },
            |out, rows, failures, (settings, frames), device| {
                crate::frames_report::write(out, rows, failures, settings, frames, device)
            },
        );
    }
    let base = settings(args)?;
    let shard = args.shards.shard()?;
    let out = args.shards.out();
    let (map_file, map) = read_map(args)?;
    // Every frame is read and checked before any work.
    let frames = read_frames(args)?;
    let mapped = Mapped::new(&frames, &map, &map_file)?;
    if let Some(skipped) = mapped.skipped() {
        eprintln!("note: {skipped}");
    }
    let Mapped {
        categories,
        targets,
        ..
    } = &mapped;
    let models: BTreeMap<u64, Mesh> = map
        .iter()
        .map(|(id, entry)| Ok((*id, model_in_category(entry)?)))
        .collect::<Result<_>>()?;
    let described = describe(&frames, &mapped);
    let ctx = Context::new()?;
    let device = format!("{} ({})", ctx.info().name, ctx.info().driver_info);
    let registrar = Registrar::new(&ctx)?;
    // The units of work, each frame's object, and their expected cost (the category's
    // canonical vertices); a shard keeps its own.
    let mut units = Vec::new();
    let mut costs = Vec::new();
    // Each category's up axis and the expected cost of its units.
    let mut checked = Vec::new();
    for dir in categories {
        let category = crate::spaces::check_first(dir, false, false)?;
        checked.push((category.info.up, shard::unit_cost(&category)?));
    }
    for (t, target) in targets.iter().enumerate() {
        units.push(shard::Unit {
            category: t,
            instance: 0,
            category_name: dir_name(&categories[target.category]),
            instance_name: target_name(target),
        });
        costs.push(checked[target.category].1);
    }
    shard::keep_own(&mut units, &costs, shard);
    let mut file = shard.map(|shard| {
        shard::ShardFile::new(
            "eval-frames",
            shard::run_flags("eval-frames"),
            shard::resolved(&base),
            shard,
            device.clone(),
            units.clone(),
        )
    });
    if let Some(file) = &file {
        file.write(out)?;
    }
    let mut spaces: BTreeMap<usize, ShapeSpace> = BTreeMap::new();
    // Each model's reference (sample, oracle, space optimum), once for all its frames.
    let mut references: BTreeMap<u64, eval::Reference> = BTreeMap::new();
    let mut placed = Vec::new();
    let mut failures: Vec<String> = Vec::new();
    let pictures = args.pictures.then(|| out.join("pictures"));
    if let Some(dir) = &pictures {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    for unit in &units {
        let target = &targets[unit.category];
        let c = target.category;
        // Each category's space when its first unit needs it.
        let space = match spaces.entry(c) {
            Entry::Occupied(built) => built.into_mut(),
            Entry::Vacant(slot) => {
                let dir = &categories[c];
                slot.insert(crate::spaces::shared_space(
                    &ctx,
                    dir,
                    &dir_name(dir),
                    &base,
                    args.shards.spaces.as_deref(),
                )?)
            }
        };
        let (category, up) = (&unit.category_name, checked[c].0);
        let name = &unit.instance_name;
        let obj_id = target.object.obj_id;
        // A unit that fails is a row of the failures with its reason; the others go on.
        let evaluated = (|| -> Result<eval::Row> {
            let frame = target.frame;
            let pose = map[&obj_id]
                .model_to_category
                .inverse()
                .followed_by(&target.object.model_to_camera);
            let model = &models[&obj_id];
            check_visible_share(
                &ctx,
                &registrar,
                frame,
                target.object,
                model,
                pose,
                args.min_visible,
            )?;
            if let Entry::Vacant(slot) = references.entry(obj_id) {
                let model = vkdr_app::reference::Model {
                    space,
                    test: model,
                    seed: obj_id,
                    cpd: &base.cpd,
                    scale: 1.0,
                    free_scale: base.pose_noise.optimize_scale,
                    up,
                };
                let reference = eval::Reference::cached(
                    args.shards.spaces.as_deref(),
                    || eprint!("\r  obj_id {obj_id}: the model's oracle and space optimum "),
                    &ctx,
                    &model,
                )
                .context("the model's reference")?;
                slot.insert(reference);
            }
            let settings = EvalSettings {
                camera: frame.camera,
                distance: pose.translation.length(),
                up,
                ..base.clone()
            };
            let scene = frame_scene(frame, target.object, pose)?;
            Ok(eval::evaluate_instance(
                &ctx,
                &registrar,
                space,
                category,
                name,
                model,
                &settings,
                TrialSource::Frame {
                    scene: &scene,
                    reference: &references[&obj_id],
                },
                |done, total| eprint!("\r  {name:<22} trial {done}/{total}  "),
                |trial, registered| match &pictures {
                    Some(dir) if trial == 0 => {
                        let file = dir.join(format!("{}.png", name.replace('/', "_")));
                        let occlusion = base.depth.map(|d| d.occlusion);
                        let rgb = frame.rgb.as_deref();
                        let picture =
                            unit_picture(&ctx, &registrar, space, registered, occlusion, rgb)?;
                        vkdr::io::write_png(&file, &image::DynamicImage::ImageRgb8(picture))
                    }
                    _ => Ok(()),
                },
            )?)
        })();
        match evaluated {
            Ok(row) => {
                eprintln!(
                    "\r  {name:<22} known pose {:.2} mm ({:.2}x the space optimum), pose noise as seen {:.2} mm",
                    1e3 * row.known_pose.mean,
                    row.known_pose.mean / row.space_optimum,
                    1e3 * row.pose_noise_seen.mean
                );
                placed.push(shard::Placed {
                    unit: unit.clone(),
                    row,
                });
            }
            Err(e) => {
                eprintln!("\r  {name:<22} failed: {e:#}");
                failures.push(format!("{name} ({category}): {e:#}"));
            }
        }
        write_progress(
            out, &mut file, &placed, &failures, &base, &described, &device,
        )?;
    }
    match shard {
        Some(shard) => println!(
            "shard {}/{}: {} objects; wrote {}/{}",
            shard.index,
            shard.count,
            placed.len(),
            out.display(),
            shard::FILE
        ),
        None => {
            print!("{}", std::fs::read_to_string(out.join("table.md"))?);
            println!(
                "wrote {0}/table.md, table.csv, table.json, trials.csv, speed_vs_error.png",
                out.display()
            );
        }
    }
    if !failures.is_empty() {
        bail!(
            "{} of {} units failed (every unit was tried; the rows and the failures are in {}):\n  {}",
            failures.len(),
            units.len(),
            out.display(),
            failures.join("\n  ")
        );
    }
    Ok(())
}

/// Writes what is done so far: the shard's file, or the tables with the failures.
fn write_progress(
    out: &Path,
    file: &mut Option<shard::ShardFile>,
    placed: &[shard::Placed],
    failures: &[String],
    base: &EvalSettings,
    frames: &str,
    device: &str,
) -> Result<()> {
    match file {
        Some(file) => {
            file.rows = placed.to_vec();
            file.failures = failures.to_vec();
            file.write(out)
        }
        None => {
            let rows: Vec<eval::Row> = placed.iter().map(|p| p.row.clone()).collect();
            crate::frames_report::write(out, &rows, failures, base, frames, device)
        }
    }
}

/// The frames of the run's DIR (every scene, checked), only `--images` where given.
fn read_frames(args: &Args) -> Result<Vec<Frame>> {
    let dir = args.dir.as_deref().expect("clap requires DIR");
    let mut frames = Vec::new();
    for scene in bop::scene_dirs(dir)? {
        frames.extend(bop::read_scene(&scene)?);
    }
    if !args.images.is_empty() {
        let name = |f: &Frame| format!("{}/{}", f.scene, f.image);
        for wanted in &args.images {
            let (scene, image) = wanted.split_once('/').unwrap_or(("", wanted));
            let found = frames
                .iter()
                .any(|f| f.scene == scene && image.parse::<u64>().ok() == Some(f.image));
            if !found {
                bail!(
                    "--images: {wanted} is not an image of {} (SCENE/IMAGE, as 000000/1)",
                    dir.display()
                );
            }
        }
        frames.retain(|f| {
            args.images.iter().any(|w| {
                w.split_once('/')
                    .is_some_and(|(s, i)| s == f.scene && i.parse::<u64>().ok() == Some(f.image))
            }) || args.images.contains(&name(f))
        });
    }
    Ok(frames)
}

/// What the frames are, in words: how many, of which scenes, their cameras (BOP's `cam_K`,
/// pixel centres on integers) and sizes, and the depth.
/// The map from BOP obj_id to category (--categories, else DIR/map.json) and its file.
fn read_map(args: &Args) -> Result<(PathBuf, BTreeMap<u64, ObjectCategory>)> {
    let dir = args.dir.as_deref().expect("clap requires DIR");
    let map_file = args
        .categories
        .clone()
        .unwrap_or_else(|| dir.join("map.json"));
    if !map_file.is_file() {
        bail!(
            "{}: no map from BOP obj_id to category; give --categories MAP",
            map_file.display()
        );
    }
    let map = bop::read_map(&map_file)?;
    Ok((map_file, map))
}

/// The frames' objects a map covers, the units of the evaluation. A BOP scene annotates
/// every object in view and a category map covers some: the others are skipped and
/// counted.
struct Mapped<'a> {
    /// The map's category folders, sorted, each once.
    categories: Vec<PathBuf>,
    targets: Vec<Target<'a>>,
    /// The obj_ids the map does not cover, with how many objects of the frames each is.
    unmapped: BTreeMap<u64, usize>,
    /// The obj_ids the map covers, for the note.
    known: String,
}

impl<'a> Mapped<'a> {
    /// An error where the map covers no object of the frames, or they have none.
    fn new(
        frames: &'a [Frame],
        map: &BTreeMap<u64, ObjectCategory>,
        map_file: &Path,
    ) -> Result<Self> {
        let mut categories: Vec<PathBuf> = map.values().map(|c| c.category.clone()).collect();
        categories.sort();
        categories.dedup();
        let known = format!(
            "{} (it maps {})",
            map_file.display(),
            map.keys()
                .map(|k| k.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
        let mut targets = Vec::new();
        let mut unmapped = BTreeMap::new();
        let mut first_unmapped = None;
        for frame in frames {
            for object in &frame.objects {
                let Some(entry) = map.get(&object.obj_id) else {
                    *unmapped.entry(object.obj_id).or_insert(0) += 1;
                    first_unmapped.get_or_insert((frame, object));
                    continue;
                };
                let category = categories
                    .iter()
                    .position(|c| *c == entry.category)
                    .expect("every mapped category is listed");
                targets.push(Target {
                    frame,
                    object,
                    category,
                });
            }
        }
        if targets.is_empty() {
            let Some((frame, object)) = first_unmapped else {
                bail!("the frames annotate no object: each image's list in scene_gt.json is empty");
            };
            bail!(
                "no object of the frames is in the map: {}/scene_gt.json image {} object {}: \
                 obj_id {} is not in {known}",
                frame.scene,
                frame.image,
                object.gt_index,
                object.obj_id,
            );
        }
        Ok(Self {
            categories,
            targets,
            unmapped,
            known,
        })
    }

    /// What was skipped, in words (None: nothing).
    fn skipped(&self) -> Option<String> {
        if self.unmapped.is_empty() {
            return None;
        }
        let count: usize = self.unmapped.values().sum();
        let ids: Vec<String> = self
            .unmapped
            .iter()
            .map(|(id, n)| format!("{id} ({n})"))
            .collect();
        Some(format!(
            "{count} object{} skipped, their obj_id not in {}: {}",
            if count == 1 { "" } else { "s" },
            self.known,
            ids.join(", ")
        ))
    }
}

fn describe(frames: &[Frame], mapped: &Mapped) -> String {
    let mut scenes: Vec<&str> = frames.iter().map(|f| f.scene.as_str()).collect();
    scenes.dedup();
    let mut cameras: Vec<String> = frames
        .iter()
        .map(|f| {
            let c = &f.camera;
            format!(
                "fx {:.1} fy {:.1} cx {:.1} cy {:.1}, {}x{} px",
                c.fx,
                c.fy,
                c.cx - 0.5,
                c.cy - 0.5,
                c.width,
                c.height
            )
        })
        .collect();
    cameras.sort();
    cameras.dedup();
    format!(
        "{} images of BOP scene{} {} ({} objects, each a unit{}); camera{} {} (cam_K as BOP gives it); \
         the depth measured by the sensor (BOP depth images), its holes unknown",
        frames.len(),
        if scenes.len() > 1 { "s" } else { "" },
        scenes.join(", "),
        mapped.targets.len(),
        mapped
            .skipped()
            .map(|skipped| format!("; {skipped}"))
            .unwrap_or_default(),
        if cameras.len() > 1 { "s" } else { "" },
        cameras.join("; ")
    )
}

/// A frame's object's row name: SCENE/IMAGE/GT.
fn target_name(target: &Target) -> String {
    format!(
        "{}/{:06}/{}",
        target.frame.scene, target.frame.image, target.object.gt_index
    )
}

/// The object's model (a PLY or OBJ in millimetres) in its category's frame (metres).
fn model_in_category(entry: &ObjectCategory) -> Result<Mesh> {
    let model = Mesh::load(&entry.model)
        .with_context(|| format!("the model of {}", entry.category.display()))?;
    let (lo, hi) = model.bounds();
    let extent = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    if extent < 1.0 {
        bail!(
            "{}: the model spans {extent:.3} units, under a millimetre: BOP models are in \
             millimetres (is it in metres?)",
            entry.model.display()
        );
    }
    let points: Vec<DVec3> = model
        .points()
        .iter()
        .map(|p| entry.model_to_category.apply(*p * 1e-3))
        .collect();
    Ok(model.with_points(&points)?)
}

/// An error where the object's visible mask shows less than `min_visible` of its
/// silhouette in the image (`mask/` where the scene has it, else `model` rendered at
/// `pose`); an object not seen at all is left to the registration's own refusal.
fn check_visible_share(
    ctx: &Context,
    registrar: &Registrar,
    frame: &Frame,
    object: &FrameObject,
    model: &Mesh,
    pose: Pose,
    min_visible: f64,
) -> Result<()> {
    let count = |mask: &[f32]| mask.iter().filter(|&&m| m > 0.5).count();
    let visible = count(&object.visible);
    if min_visible <= 0.0 || visible == 0 {
        return Ok(());
    }
    let whole = match &object.whole {
        Some(whole) => count(whole),
        None => {
            let view = View {
                camera: frame.camera,
                pose,
            };
            count(&eval::render_mask(ctx, registrar, model, view)?)
        }
    };
    let share = visible as f64 / whole.max(visible) as f64;
    if share < min_visible {
        bail!(
            "{:.1}% of the object's silhouette is visible ({visible} of {whole} pixels), \
             under --min-visible {} (BOP's targets need 0.1): not registered",
            100.0 * share,
            min_visible
        );
    }
    Ok(())
}

/// A unit's picture, cropped to the observed mask and the registered silhouettes with half
/// their box's size around: the frame's colour image `rgb` where it has one of its size,
/// else the measured depth (grey, near bright; black where none), then the observed mask
/// (blue) against the silhouette registered with the pose known and then from the first
/// trial's pose noise (red; both: magenta; unknown pixels green: hidden by the scene's
/// whole mask, or by the depth's `occlusion` rule, a measured depth that many metres
/// nearer than the registered surface outside the mask), each panel enlarged to at least
/// 240 pixels high.
fn unit_picture(
    ctx: &Context,
    registrar: &Registrar,
    space: &ShapeSpace,
    registered: &eval::Registered,
    occlusion: Option<f64>,
    rgb: Option<&Path>,
) -> vkdr::Result<image::RgbImage> {
    let camera = registered.view.camera;
    let (w, h) = (camera.width, camera.height);
    // A colour image that cannot be read, or of another size, leaves the depth's panel
    // (the registration never reads it), with a warning.
    let colour = rgb.and_then(|path| match image::open(path) {
        Ok(image) if image.width() == w && image.height() == h => Some(image.to_rgb8()),
        Ok(image) => {
            eprintln!(
                "\nwarning: {}: {}x{} pixels, the camera's are {w}x{h}; the picture shows the depth",
                path.display(),
                image.width(),
                image.height()
            );
            None
        }
        Err(e) => {
            eprintln!(
                "\nwarning: {}: not an image ({e}); the picture shows the depth",
                path.display()
            );
            None
        }
    });
    let depth = registered.observation.depth.as_deref();
    let measured = |k: usize| depth.map_or(0.0, |d| d[k]);
    let mut silhouettes = Vec::new();
    let mut observed = Vec::new();
    for result in [&registered.known, &registered.noisy] {
        let mesh = space.canonical.with_points(&result.vertices)?;
        let view = View {
            camera,
            pose: result.pose,
        };
        let rendered = registrar.renderer().rasterizer().render(
            ctx,
            &mesh,
            &[view],
            vkdr::raster::Outputs::IdsBaryDepth,
        )?;
        let surface = rendered.depth.expect("IdsBaryDepth renders depth");
        let surface = surface.as_slice().expect("a standard-layout image");
        let mut mask = registered.observation.mask.clone();
        if let Some(nearer) = occlusion.filter(|&o| o > 0.0) {
            for (k, m) in mask.iter_mut().enumerate() {
                let z = measured(k);
                if *m == 0.0 && surface[k] > 0.0 && z > 0.0 && z < surface[k] - nearer as f32 {
                    *m = vkdr::loss::UNKNOWN;
                }
            }
        }
        silhouettes.push(
            surface
                .iter()
                .map(|&z| (z > 0.0) as u8 as f32)
                .collect::<Vec<_>>(),
        );
        observed.push(mask);
    }
    let observed_any = &registered.observation.mask;
    // The box of every pixel the mask or a silhouette covers, with a margin.
    let covered = |k: usize| observed_any[k] > 0.0 || silhouettes.iter().any(|s| s[k] > 0.0);
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for y in 0..h {
        for x in 0..w {
            if covered((y * w + x) as usize) {
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
            }
        }
    }
    if x0 >= x1 {
        (x0, y0, x1, y1) = (0, 0, w, h);
    }
    let margin = (x1 - x0).max(y1 - y0) / 2;
    let (x0, y0) = (x0.saturating_sub(margin), y0.saturating_sub(margin));
    let (x1, y1) = ((x1 + margin).min(w), (y1 + margin).min(h));
    let (cw, ch) = (x1 - x0, y1 - y0);
    let zoom = 240u32.div_ceil(ch).max(1);
    // The first panel, in the crop's pixels: the colour image, else the measured depth.
    let first = match colour {
        Some(colour) => image::imageops::crop_imm(&colour, x0, y0, cw, ch).to_image(),
        None => {
            let crop: Vec<f32> = (y0..y1)
                .flat_map(|y| (x0..x1).map(move |x| (y * w + x) as usize))
                .map(measured)
                .collect();
            let crop = ndarray::ArrayView2::from_shape((ch as usize, cw as usize), &crop)
                .expect("the crop's pixels");
            crate::pictures::depth(crop).to_rgb8()
        }
    };
    let panels: Vec<image::RgbImage> = silhouettes
        .iter()
        .zip(&observed)
        .map(|(s, o)| crate::registration::overlay(o, s, w, h))
        .collect();
    Ok(image::RgbImage::from_fn(
        3 * cw * zoom,
        ch * zoom,
        |px, py| {
            let (panel, x, y) = (px / (cw * zoom), (px % (cw * zoom)) / zoom, py / zoom);
            match panel {
                0 => *first.get_pixel(x, y),
                p => *panels[p as usize - 1].get_pixel(x0 + x, y0 + y),
            }
        },
    ))
}

/// One object of a frame as a trial's scene: the visible mask, with the pixels the whole
/// mask adds (hidden by something in front) unknown, and the frame's depth.
fn frame_scene(frame: &Frame, object: &FrameObject, pose: Pose) -> Result<TrialScene> {
    let mut mask = object.visible.clone();
    if let Some(whole) = &object.whole {
        let hidden = vkdr::loss::hidden_pixels(&object.visible, whole)?;
        vkdr::loss::mark_unknown(&mut mask, 1, &hidden)?;
    }
    Ok(TrialScene {
        azimuth: 0.0,
        elevation: 0.0,
        pose,
        view: View {
            camera: frame.camera,
            pose,
        },
        others: Vec::new(),
        observed: Images {
            mask,
            depth: Some(frame.depth.clone()),
            shaded: None,
        },
    })
}

#[derive(clap::Args)]
pub struct GenArgs {
    /// A category dataset (`vkdr gen-dataset`): the frames show its test instances.
    #[arg(long)]
    dataset: PathBuf,
    /// Only these categories (comma-separated).
    #[arg(long)]
    categories: Option<String>,
    /// Frames per test instance, each from its own random view.
    #[arg(long, default_value_t = 1)]
    frames: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A box in front of the left half of each object.
    #[arg(long)]
    occluder: bool,
    /// Standard deviation of the depth's noise, metres.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.002)]
    depth_noise: f64,
    /// Fraction of the depth missing, in clusters.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.1)]
    depth_holes: f64,
    /// Scale every test instance by this (its model is the scaled instance).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    test_scale: f64,
    #[arg(long)]
    pub out: PathBuf,
}

/// The model frame of the written models: z up (as many scanned models), the category's y
/// up turned onto it, and shifted, so that the map's transform is exercised.
fn category_to_model() -> Pose {
    Pose {
        translation: DVec3::new(0.003, -0.002, 0.01),
        rotation: DVec3::new(std::f64::consts::FRAC_PI_2, 0.0, 0.0),
    }
}

/// `vkdr gen-frames`: one BOP scene (OUT/000000) of rendered frames, the models
/// (OUT/models, binary PLY in millimetres, as BOP's) and the map (OUT/map.json) for `vkdr
/// eval-frames`.
pub fn generate(args: &GenArgs) -> Result<()> {
    if !(1..=100).contains(&args.frames) {
        bail!("--frames must be 1 to 100, not {}", args.frames);
    }
    if !(args.depth_noise.is_finite() && (0.0..=0.1).contains(&args.depth_noise)) {
        bail!("--depth-noise must be 0 to 0.1 m, not {}", args.depth_noise);
    }
    if !(args.depth_holes.is_finite() && (0.0..=0.9).contains(&args.depth_holes)) {
        bail!("--depth-holes must be 0 to 0.9, not {}", args.depth_holes);
    }
    if !(args.test_scale.is_finite() && (0.1..=10.0).contains(&args.test_scale)) {
        bail!("--test-scale must be 0.1 to 10, not {}", args.test_scale);
    }
    let only: Option<Vec<String>> = args
        .categories
        .as_deref()
        .map(|c| c.split(',').map(|s| s.trim().to_string()).collect());
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&args.dataset)
        .with_context(|| format!("reading {}", args.dataset.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("canonical.obj").is_file() && p.join("test").is_dir())
        .filter(|p| {
            only.as_ref().is_none_or(|o| {
                o.iter()
                    .any(|c| p.file_name().is_some_and(|n| n.to_string_lossy() == *c))
            })
        })
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        bail!(
            "{} has no category folders{}",
            args.dataset.display(),
            if only.is_some() {
                " of --categories"
            } else {
                ""
            }
        );
    }
    let ctx = Context::new()?;
    let registrar = Registrar::new(&ctx)?;
    let scene_dir = args.out.join("000000");
    let models_dir = args.out.join("models");
    std::fs::create_dir_all(&models_dir)
        .with_context(|| format!("creating {}", models_dir.display()))?;
    let mut rng = vkdr_app::dataset::Rng::new(args.seed);
    let mut map = serde_json::Map::new();
    let (mut obj_id, mut image) = (0u64, 0u64);
    for dir in &dirs {
        let up = vkdr_app::check::Info::read(dir)?.up;
        let settings = EvalSettings {
            up,
            depth: Some(vkdr::diff::DepthLoss::default()),
            depth_noise: args.depth_noise,
            depth_holes: args.depth_holes,
            occluder: args.occluder,
            table: true,
            ..Default::default()
        };
        for test_path in obj_files(&dir.join("test"))? {
            obj_id += 1;
            let test = Mesh::load_obj(&test_path)?;
            let test = test.with_points(
                &test
                    .points()
                    .iter()
                    .map(|p| *p * args.test_scale)
                    .collect::<Vec<_>>(),
            )?;
            let to_model = category_to_model();
            let model = test.with_points(
                &test
                    .points()
                    .iter()
                    .map(|p| to_model.apply(*p) * 1e3)
                    .collect::<Vec<_>>(),
            )?;
            let model_name = format!("obj_{obj_id:06}.ply");
            bop::write_ply(&models_dir.join(&model_name), &model)?;
            let to_category = to_model.inverse();
            map.insert(
                obj_id.to_string(),
                serde_json::json!({
                    // Absolute, so that the frames can be moved without their dataset.
                    "category": std::fs::canonicalize(dir)
                        .with_context(|| format!("resolving {}", dir.display()))?
                        .display()
                        .to_string(),
                    "model": format!("models/{model_name}"),
                    "model_to_category": {
                        "translation": to_category.translation.to_array(),
                        "rotation": to_category.rotation.to_array(),
                    },
                }),
            );
            let table = eval::table_under(&test, up)?;
            for _ in 0..args.frames {
                let scene =
                    eval::render_trial(&ctx, &registrar, &test, Some(&table), &settings, &mut rng)?;
                let whole = eval::render_mask(&ctx, &registrar, &test, scene.view)?;
                let depth = scene.observed.depth.clone().expect("rendered with depth");
                let frame = Frame {
                    scene: "000000".into(),
                    image,
                    camera: scene.view.camera,
                    depth,
                    rgb: None,
                    objects: vec![FrameObject {
                        gt_index: 0,
                        obj_id,
                        model_to_camera: to_category.followed_by(&scene.pose),
                        visible: scene.observed.mask.iter().map(|&m| m.max(0.0)).collect(),
                        whole: Some(whole),
                    }],
                };
                bop::write_frame(&scene_dir, &frame, 0.1)?;
                image += 1;
            }
        }
    }
    vkdr::io::write_json(&args.out.join("map.json"), &serde_json::Value::Object(map))?;
    println!(
        "wrote {image} frames of {obj_id} objects to {} (BOP: depth in tenths of a millimetre), \
         their models to {} and the map to {}",
        scene_dir.display(),
        models_dir.display(),
        args.out.join("map.json").display()
    );
    Ok(())
}
