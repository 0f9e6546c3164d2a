#!/usr/bin/env python3
"""A copy of BOP scenes with a box standing in front of each object: frames where more
of each object is hidden than in the originals, for `vkdr eval-frames` on frames it was
not tuned to.

    pip install numpy pillow
    python3 tools/bop_occlude.py ../shared/real/ycbv-dev/bop 0.3 /tmp/occluded
    vkdr eval-frames /tmp/occluded --out /tmp/occluded-eval

For each annotated object of each image, a box covers SHARE of its visible mask's
bounding box from one side (`--side`, left or right), and 20 pixels past that side and
10 above and below, NEARER millimetres (60) in front of the median measured depth of the
object's visible pixels: in the copy, where the scene lies behind the box (or was not
measured), the depth is the box's (a flat face the sensor measured) and every object's
visible mask loses those pixels; what stands in front of the box stays. The RGB
images are copied as they are (vkdr reads them for pictures only) and so are `mask/`'s
whole silhouettes, which the box does not change. The map's category and model paths are
written absolute, so the copy can live anywhere. `scene_gt_info.json` (the originals'
visible fractions) is not copied. The copy is written into a temporary folder beside OUT
and renamed to OUT when whole: a failure leaves no OUT behind.
"""

import argparse
import functools
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from bop_resample import write_copy

COPIED_FOLDERS = ("mask", "rgb")


def read_image(path: Path) -> np.ndarray:
    try:
        return np.array(Image.open(path))
    except OSError as error:
        raise ValueError(f"{path}: not an image ({error})") from error


def box_of(mask: np.ndarray, depth: np.ndarray, share: float, side: str):
    """The rows and columns of the box in front of `mask` (covering `share` of its bounding
    box from `side`); None where the mask has no pixel or none with a measured depth."""
    rows, columns = np.nonzero(mask)
    if rows.size == 0 or not (depth[mask] > 0).any():
        return None
    x0, x1 = columns.min(), columns.max()
    width = x1 - x0 + 1
    if side == "left":
        c0, c1 = max(0, x0 - 20), x0 + int(share * width)
    else:
        c0, c1 = x1 + 1 - int(share * width), x1 + 21
    return slice(max(0, rows.min() - 10), rows.max() + 11), slice(c0, c1)


def occlude_scene(source: Path, target: Path, share: float, side: str, nearer: float) -> int:
    """Copies one scene with the boxes in front; the depth and mask images written."""
    target.mkdir(parents=True)
    cameras = json.loads((source / "scene_camera.json").read_text())
    annotations = json.loads((source / "scene_gt.json").read_text())
    for name in ("scene_camera.json", "scene_gt.json"):
        shutil.copy(source / name, target / name)
    for folder in COPIED_FOLDERS:
        if (source / folder).is_dir():
            shutil.copytree(source / folder, target / folder)
    (target / "depth").mkdir()
    (target / "mask_visib").mkdir()
    written = 0
    for image, objects in annotations.items():
        depth_path = source / "depth" / f"{int(image):06d}.png"
        depth = read_image(depth_path)
        if depth.dtype != np.uint16:
            raise ValueError(f"{depth_path}: a depth image of {depth.dtype}, not 16-bit")
        scale = cameras.get(image, {}).get("depth_scale")
        if not isinstance(scale, (int, float)) or not scale > 0:
            raise ValueError(
                f"{source / 'scene_camera.json'}: image {image} has no positive depth_scale"
            )
        masks = [
            source / "mask_visib" / f"{int(image):06d}_{k:06d}.png" for k in range(len(objects))
        ]
        hidden = np.zeros(depth.shape, bool)
        boxed = depth.astype(np.int64)
        for path in masks:
            visible = read_image(path) > 0
            if visible.shape != depth.shape:
                raise ValueError(f"{path}: {visible.shape} pixels, its depth image {depth.shape}")
            box = box_of(visible, depth, share, side)
            if box is None:
                continue
            front = np.median(depth[visible & (depth > 0)]) * scale - nearer
            if front <= 0:
                raise ValueError(f"{path}: the object is nearer than {nearer} mm")
            # The box hides what lies behind it, not what stands in front (another object,
            # or a nearer box): there the scene is as it was.
            at = int(round(front / scale))
            behind = np.zeros(depth.shape, bool)
            behind[box] = True
            behind &= (boxed == 0) | (boxed > at)
            boxed[behind] = at
            hidden |= behind
        Image.fromarray(boxed.astype(np.uint16)).save(target / "depth" / depth_path.name)
        written += 1
        for path in masks:
            mask = read_image(path)
            mask[hidden] = 0
            Image.fromarray(mask).save(target / "mask_visib" / path.name)
            written += 1
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a BOP folder (scene folders and map.json) or one scene")
    parser.add_argument("share", type=float, help="the share of each object's box hidden (0 to 1)")
    parser.add_argument("out", type=Path, help="the copy's folder (must not exist)")
    parser.add_argument("--side", choices=("left", "right"), default="left")
    parser.add_argument("--nearer", type=float, default=60.0, help="mm in front of the object")
    args = parser.parse_args()
    if not 0.0 < args.share < 1.0:
        parser.error(f"share must be between 0 and 1, not {args.share}")
    if not args.nearer > 0.0:
        parser.error(f"--nearer must be positive, not {args.nearer}")
    occlude = functools.partial(
        occlude_scene, share=args.share, side=args.side, nearer=args.nearer
    )
    what = f"with {args.share:g} of each object hidden from the {args.side}"
    return write_copy(parser, args.source, args.out, occlude, what)


if __name__ == "__main__":
    sys.exit(main())
