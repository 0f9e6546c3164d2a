"""vkdr.torch's composed silhouette (rasterize -> silhouette -> mse -> backward) against the
engine's built-in `silhouette_loss` (with its backward) and `rasterize` alone, at 320 x 240.

    python bindings/python/benches/antialias.py [--vertices 4800] [--runs 7]
"""

import argparse
import statistics
import sys
import time

import numpy as np
import torch

import vkdr
import vkdr.torch as vt
from overhead import sphere


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vertices", type=int, default=4800)
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    device = vkdr.Device()
    size = (320, 240)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    pose = np.array([0.004, -0.003, 0.4, 0.5, -0.6, 0.3])
    vertices, faces = sphere(args.vertices)
    vertices = vertices * np.float32([1.6, 1.0, 0.6])
    ids, _, _ = device.rasterize(vertices, faces, K, size, pose + np.array([0.005, -0.004, 0.01, 0.1, 0.08, -0.05]))
    mask = ids > 0
    v = torch.tensor(vertices.astype(np.float64), requires_grad=True)
    p = torch.tensor(pose, requires_grad=True)
    target = torch.tensor(mask, dtype=torch.float64)

    def composed():
        fragments = vt.rasterize(v, faces, K, size, p, device=device)
        ((vt.silhouette(fragments, v, faces, K, p) - target) ** 2).mean().backward()

    cases = [
        ("silhouette_loss + backward", lambda: vt.silhouette_loss(v, p, faces, K, size, mask, device=device).backward()),
        ("rasterize", lambda: vt.rasterize(v, faces, K, size, p, device=device)),
        ("rasterize -> silhouette -> mse + backward", composed),
    ]
    print(f"{device.name}: {len(vertices)} vertices, {len(faces)} faces, {size[0]} x {size[1]}", file=sys.stderr)
    for name, call in cases:
        call()
        times = []
        for _ in range(args.runs):
            start = time.perf_counter()
            call()
            times.append((time.perf_counter() - start) * 1e3)
        print(f"{name}: {statistics.median(times):.1f} ms (median of {args.runs})")


if __name__ == "__main__":
    main()
