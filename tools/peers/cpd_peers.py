#!/usr/bin/env python3
"""CPD side by side: `vkdr cpd` against pycpd (the NumPy reference implementation) and,
where it installs from PyPI, probreg, on the same point sets, with the same beta, lambda
(pycpd's alpha) and w. Writes one CSV:

    method,points,seconds,iterations,mean_distance,device

`points` is M; `mean_distance` is the mean distance from each moved source point to its
true counterpart (the sets are a known smooth deformation of each other; the target is
shuffled, and with --missing / --outliers loses that fraction of its points and gains
uniform outliers), in units of the source's RMS radius.

The sets are normalised so the source has zero mean and unit RMS radius: then vkdr's
beta (relative to that radius) and the peers' beta (in data units) are the same number.

    pip install pycpd numpy [probreg]
    cargo build --release
    python3 tools/peers/cpd_peers.py --out cpd-peers/ [--sizes 1000,2000,5000] [--repeats 3]

Each method runs --repeats times per size; the CSV has every run, and the summary printed
at the end the median seconds.

Not part of CI.
"""
import argparse
import csv
import json
import os
import subprocess
import sys
import time

import numpy as np


def point_sets(n, seed, missing=0.0, outliers=0.0):
    rng = np.random.default_rng(seed)
    # Points on a bumpy closed surface (a deformed sphere), then a smooth deformation.
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    source = d * (1.0 + 0.2 * np.sin(3 * d[:, :1]) * np.cos(2 * d[:, 1:2])) * np.array([1.0, 1.6, 1.0])
    source = (source - source.mean(0)) / np.sqrt((np.linalg.norm(source - source.mean(0), axis=1) ** 2).mean())
    target = source + 0.15 * np.stack([np.sin(2 * source[:, 1]), np.cos(1.5 * source[:, 2]) - 1, 0.5 * source[:, 0] * source[:, 1]], 1)
    # The observed target: shuffled, a fraction missing, uniform outliers in its box added.
    observed = target[rng.permutation(n)[: n - int(missing * n)]]
    lo, hi = target.min(0), target.max(0)
    observed = np.concatenate([observed, rng.uniform(lo, hi, size=(int(outliers * n), 3))])
    return source, observed[rng.permutation(len(observed))], target


def mean_error(moved, truth):
    return float(np.linalg.norm(moved - truth, axis=1).mean())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--sizes", default="1000,5000,20000")
    parser.add_argument("--beta", type=float, default=2.0)
    parser.add_argument("--lamb", type=float, default=2.0)
    parser.add_argument("--w", type=float, default=0.1)
    parser.add_argument("--max-iterations", type=int, default=150)
    parser.add_argument("--vkdr", default="target/release/vkdr")
    parser.add_argument("--skip-pycpd-above", type=int, default=5000, help="peers only up to this size")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--missing", type=float, default=0.0, help="fraction of target points removed")
    parser.add_argument("--outliers", type=float, default=0.0, help="uniform outliers, as a fraction of n")
    parser.add_argument("--plain", action="store_true", help="also run vkdr without SQUAREM (vkdr-plain rows)")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for n in [int(s) for s in args.sizes.split(",")]:
        source, target, truth = point_sets(n, seed=n, missing=args.missing, outliers=args.outliers)
        src, tgt = os.path.join(args.out, f"source_{n}.npy"), os.path.join(args.out, f"target_{n}.npy")
        np.save(src, source)
        np.save(tgt, target)

        variants = [("vkdr", [])] + ([("vkdr-plain", ["--no-accelerate"])] if args.plain else [])
        for _ in range(args.repeats):
            for method, extra in variants:
                out = os.path.join(args.out, f"{method}_{n}")
                started = time.perf_counter()
                run = subprocess.run([args.vkdr, "cpd", src, tgt, "--beta", str(args.beta), "--lambda", str(args.lamb),
                                      "--w", str(args.w), "--max-iterations", str(args.max_iterations), "--out", out, "--force"] + extra,
                                     capture_output=True, text=True)
                wall = time.perf_counter() - started
                if run.returncode != 0:
                    sys.exit(f"vkdr cpd failed: {run.stderr}")
                log = json.load(open(os.path.join(out, "log.json")))
                device = run.stderr.split(" on ", 1)[-1].splitlines()[0].strip() if " on " in run.stderr else "vkdr device"
                moved = np.load(os.path.join(out, "deformed.npy"))
                rows.append((method, n, round(wall, 3), log["iterations"], mean_error(moved, truth), device))
                print(*rows[-1], sep=",", flush=True)
        if n > args.skip_pycpd_above:
            continue
        for _ in range(args.repeats):
            from pycpd import DeformableRegistration
            reg = DeformableRegistration(X=target, Y=source, alpha=args.lamb, beta=args.beta, w=args.w,
                                         max_iterations=args.max_iterations, tolerance=1e-5 * np.var(target) * 3)
            started = time.perf_counter()
            moved, _ = reg.register()
            rows.append(("pycpd", n, round(time.perf_counter() - started, 3), reg.iteration, mean_error(moved, truth), "numpy cpu"))
            print(*rows[-1], sep=",", flush=True)
        for _ in range(args.repeats):
            try:
                from probreg import cpd as probreg_cpd
            except ImportError:
                break
            started = time.perf_counter()
            # registration_cpd returns (transformation, sigma2, q); the iterations are
            # counted by a callback. Its own stopping rule: |change of q| < tol (1e-3).
            iterations = []
            result = probreg_cpd.registration_cpd(source, target, tf_type_name="nonrigid", w=args.w,
                                                  beta=args.beta, lmd=args.lamb, maxiter=args.max_iterations,
                                                  callbacks=[lambda tf: iterations.append(1)])
            moved = result.transformation.transform(source)
            rows.append(("probreg", n, round(time.perf_counter() - started, 3), len(iterations), mean_error(moved, truth), "numpy cpu"))
            print(*rows[-1], sep=",", flush=True)
    with open(os.path.join(args.out, "cpd_peers.csv"), "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["method", "points", "seconds", "iterations", "mean_distance", "device"])
        writer.writerows(rows)
    print("method,points,median_seconds,median_error,runs")
    for key in sorted({(r[0], r[1]) for r in rows}, key=lambda k: (k[1], k[0])):
        runs = [r for r in rows if (r[0], r[1]) == key]
        print(key[0], key[1], float(np.median([r[2] for r in runs])), float(np.median([r[4] for r in runs])), len(runs), sep=",")
    print(f"wrote {os.path.join(args.out, 'cpd_peers.csv')}")


if __name__ == "__main__":
    main()
