"""A batch of poses in one `Device.rasterize` call against a Python loop of single calls.

    python bindings/python/benches/batch.py [--poses 32] [--vertices 20000] [--runs 7]

At 320 x 240 and 640 x 480, the medians of both (each run's results kept, as a caller
keeps them), their ratio, the batch of ids alone (`Device.visibility`), and the check that
the batch's ids, barycentrics and depth are the loop's, byte for byte.
"""

import argparse
import statistics
import sys
import time

import numpy as np

import vkdr
from overhead import sphere


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=32)
    parser.add_argument("--vertices", type=int, default=20_000)
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    device = vkdr.Device()
    vertices, faces = sphere(args.vertices)
    poses = np.array([[0.001 * i, 0.0, 0.3, 0.1 * i, 0.2, 0.0] for i in range(args.poses)])
    print(f"{device.name}: {len(vertices)} vertices, {args.poses} poses", file=sys.stderr)
    for width, height in [(320, 240), (640, 480)]:
        K = np.array([[300.0, 0, width / 2], [0, 300.0, height / 2], [0, 0, 1]])
        size = (width, height)
        loop = lambda: [device.rasterize(vertices, faces, K, size, p) for p in poses]  # noqa: E731
        batch = lambda: device.rasterize(vertices, faces, K, size, poses)  # noqa: E731
        times = {"loop": [], "batch": []}
        for _ in range(args.runs):
            for name, call in [("loop", loop), ("batch", batch)]:
                start = time.perf_counter()
                kept = call()
                times[name].append(1e3 * (time.perf_counter() - start))
                del kept
        singles, together = loop(), batch()
        same = all(np.array_equal(np.stack([s[k] for s in singles]), together[k]) for k in range(3))
        # The ids alone (Device.visibility, what vkdr.torch.rasterize reads): the batch of
        # them against the full batch.
        ids = lambda: device.visibility(vertices, faces, K, size, poses)  # noqa: E731
        for _ in range(args.runs):
            start = time.perf_counter()
            kept = ids()
            times.setdefault("ids", []).append(1e3 * (time.perf_counter() - start))
            del kept
        same = same and np.array_equal(ids(), together[0])
        median = {name: statistics.median(t) for name, t in times.items()}
        print(f"{width} x {height}: loop {median['loop']:.1f} ms, batch {median['batch']:.1f} ms, "
              f"loop / batch {median['loop'] / median['batch']:.2f}; the batch's ids alone "
              f"{median['ids']:.1f} ms (loop / ids {median['loop'] / median['ids']:.2f}); the same bytes: {same}")
        if not same:
            sys.exit(1)


if __name__ == "__main__":
    main()
