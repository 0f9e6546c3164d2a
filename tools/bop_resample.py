#!/usr/bin/env python3
"""A copy of BOP scenes at 1/F of their resolution: objects as a camera F times farther
away would see them (in pixels), for `vkdr eval-frames` on frames it was not tuned to.

    pip install numpy pillow
    python3 tools/bop_resample.py ../shared/real/ycbv-dev/bop 4 /tmp/real4
    vkdr eval-frames /tmp/real4 --out /tmp/real4-eval

Every F-th pixel of each image is kept (depth, masks and RGB alike: no pixel is blended,
so a depth value stays a measured one and a mask stays a mask; RGB stored as JPEG is
encoded again, lossily: vkdr reads RGB for pictures only). BOP's `cam_K` has its
pixel centres on integers (OpenCV's convention), so pixel (i, j) of the copy is pixel
(F i, F j) of the original and `fx, fy, cx, cy` are divided by F exactly. The map's
category and model paths are written absolute, so the copy can live anywhere.
`scene_gt_info.json` (boxes and pixel counts at the original resolution) is not copied.
The copy is written into a temporary folder beside OUT and renamed to OUT when whole: a
failure leaves no OUT behind.
"""

import argparse
import functools
import json
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

IMAGE_FOLDERS = ("depth", "mask", "mask_visib", "rgb")


def resample_scene(source: Path, target: Path, factor: int) -> int:
    """Copies one scene folder at 1/factor of its resolution; the images written."""
    target.mkdir(parents=True)
    cameras = json.loads((source / "scene_camera.json").read_text())
    for image, camera in cameras.items():
        k = camera.get("cam_K")
        if not isinstance(k, list) or len(k) != 9:
            raise ValueError(f"{source / 'scene_camera.json'}: image {image} has no 3x3 cam_K")
        for index in (0, 2, 4, 5):
            k[index] /= factor
    (target / "scene_camera.json").write_text(json.dumps(cameras, indent=1))
    shutil.copy(source / "scene_gt.json", target / "scene_gt.json")
    written = 0
    for folder in IMAGE_FOLDERS:
        if not (source / folder).is_dir():
            continue
        (target / folder).mkdir()
        for path in sorted((source / folder).iterdir()):
            try:
                pixels = np.array(Image.open(path))
            except OSError as error:
                raise ValueError(f"{path}: not an image ({error})") from error
            kept = np.ascontiguousarray(pixels[::factor, ::factor])
            Image.fromarray(kept).save(target / folder / path.name)
            written += 1
    return written


def scene_folders(source: Path) -> list[Path]:
    """The BOP scenes at `source` as `vkdr eval-frames` finds them: the folder itself where
    it holds scene_gt.json, else its subfolders that do."""
    if (source / "scene_gt.json").is_file():
        return [source]
    return sorted(p for p in source.iterdir() if (p / "scene_gt.json").is_file())


def write_copy(
    parser: argparse.ArgumentParser,
    source: Path,
    out: Path,
    copy_scene: Callable[[Path, Path], int],
    what: str,
) -> int:
    """Copies the BOP scenes at `source` (a BOP folder or one scene, as the command line
    gave it; a bad one is `parser`'s error) into `out`, each through `copy_scene(scene,
    target)` (the images it wrote), with the map's category and model paths written
    absolute; into a temporary folder beside `out`, renamed to `out` when whole. Says what
    it wrote (`what` ends the line) and returns the exit code."""
    if out.exists():
        parser.error(f"{out} exists: give a new folder")
    source = source.resolve()
    if not source.is_dir():
        parser.error(f"{source} is not a folder")
    scenes = scene_folders(source)
    if not scenes:
        parser.error(f"{source} holds no BOP scene (a folder with scene_gt.json)")
    out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        if scenes == [source]:
            written = copy_scene(source, staging / "scene")
            root = staging / "scene"
        else:
            root = staging
            written = sum(copy_scene(s, staging / s.name) for s in scenes)
        mapping = source / "map.json"
        if mapping.exists():
            objects = json.loads(mapping.read_text())
            for entry in objects.values():
                for key in ("category", "model"):
                    if key in entry:
                        entry[key] = str((source / entry[key]).resolve())
            (root / "map.json").write_text(json.dumps(objects, indent=1))
        root.rename(out)
    except (OSError, ValueError, KeyError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"wrote {len(scenes)} scenes ({written} images) {what} into {out}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="a BOP folder (scene folders and map.json) or one scene")
    parser.add_argument("factor", type=int, help="keep every FACTOR-th pixel (2 or more)")
    parser.add_argument("out", type=Path, help="the copy's folder (must not exist)")
    args = parser.parse_args()
    if args.factor < 2:
        parser.error(f"factor must be 2 or more, not {args.factor}")
    resample = functools.partial(resample_scene, factor=args.factor)
    return write_copy(parser, args.source, args.out, resample, f"at 1/{args.factor}")


if __name__ == "__main__":
    sys.exit(main())
