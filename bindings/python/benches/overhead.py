"""The binding's overhead over the engine's own time, for loss_and_grad.

    python bindings/python/benches/overhead.py [--vertices 100000] [--size 1024] [--runs 15] [--json F]

Each call's wall time in Python against the time the same call spent in the engine
(`Device.engine_ms`: the scene's buffers, the forward and backward passes and the read-back,
as a Rust caller of `Scene::new` and `evaluate` spends it). The rest is the binding's:
reading the NumPy arrays in, making the arrays out. Prints the medians and the gradient's
check against the first run (the same bytes every run).
"""

import argparse
import json
import statistics
import sys
import time

import numpy as np

import vkdr


def sphere(vertices):
    """A UV sphere of radius 5 cm with about `vertices` vertices."""
    rings = int(np.sqrt(vertices / 2))
    segments = max(3, vertices // rings)
    theta = np.pi * (np.arange(rings) + 0.5) / rings
    phi = 2 * np.pi * np.arange(segments) / segments
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = 0.05 * np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a, b = i * segments + j, i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return v.astype(np.float32), faces.astype(np.int64)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vertices", type=int, default=100_000)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--json", help="also write the medians to this JSON file")
    args = parser.parse_args()
    device = vkdr.Device()
    vertices, faces = sphere(args.vertices)
    size = (args.size, args.size)
    f = 1.2 * args.size
    K = np.array([[f, 0, args.size / 2], [0, f, args.size / 2], [0, 0, 1]])
    pose = np.array([0.003, -0.002, 0.3, 0.2, 0.1, 0.0])
    ids, _, _ = device.rasterize(vertices, faces, K, size, pose + np.array([0.004, 0, 0.01, 0, 0, 0]))
    mask = (ids > 0).astype(np.float32)
    print(f"{device.name}: {len(vertices)} vertices, {len(faces)} triangles, {args.size} x {args.size}, "
          f"{int(mask.sum())} object pixels", file=sys.stderr)
    walls, engines, first = [], [], None
    for run in range(args.runs + 1):
        start = time.perf_counter()
        loss, grad_vertices, grad_pose = device.loss_and_grad(vertices, faces, K, size, pose, mask)
        wall = 1e3 * (time.perf_counter() - start)
        if first is None:
            first = grad_vertices.tobytes()
            continue  # the first call builds the pipelines
        assert grad_vertices.tobytes() == first, "the gradient changed between runs"
        walls.append(wall)
        engines.append(device.engine_ms)
        print(f"\r  run {run}/{args.runs}: {wall:.1f} ms", end="", file=sys.stderr)
    print(file=sys.stderr)
    wall, engine = statistics.median(walls), statistics.median(engines)
    overhead = statistics.median(w - e for w, e in zip(walls, engines))
    print(f"device: {device.name}")
    print(f"loss_and_grad, {len(vertices)} vertices, {args.size}x{args.size}, median of {args.runs}: "
          f"{wall:.1f} ms in Python, {engine:.1f} ms in the engine, overhead {overhead:.2f} ms "
          f"({100 * overhead / engine:.2f}% of the engine's time); loss {loss:.6e}, "
          f"|dL/dv| {np.linalg.norm(grad_vertices):.4e}, identical gradients every run")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device.name, "vertices": len(vertices), "size": args.size,
                       "runs": args.runs, "wall_ms": wall, "engine_ms": engine, "overhead_ms": overhead,
                       "overhead_percent": 100 * overhead / engine, "loss": float(loss)}, f, indent=1)


if __name__ == "__main__":
    main()
