#!/usr/bin/env python3
"""A scan-like copy of a generated category: every mesh midpoint-subdivided to about 1e4
vertices, and the training meshes made the way real scans come: some with a hole (faces
removed, so not watertight), some with every vertex of a band duplicated (unwelded
seams), some with a second component (a loose fragment beside the object). The
canonical stays clean (the shape space deforms it). For `vkdr shape-space` at scan size:

    vkdr gen-dataset --out DS
    python3 tools/messy_category.py DS/bottle OUT/bottle --subdivide 3
    vkdr shape-space OUT/bottle --dims 5 --out space.npz

Plain Python, no packages needed.
"""
import argparse
import math
import os
import shutil


def load_obj(path):
    vertices, faces = [], []
    with open(path) as f:
        for line in f:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                vertices.append(tuple(float(x) for x in parts[1:4]))
            elif parts[0] == "f":
                faces.append(tuple(int(p.split("/")[0]) - 1 for p in parts[1:4]))
    return vertices, faces


def save_obj(path, vertices, faces):
    with open(path, "w") as f:
        for v in vertices:
            f.write("v %.7f %.7f %.7f\n" % v)
        for a, b, c in faces:
            f.write("f %d %d %d\n" % (a + 1, b + 1, c + 1))


def subdivide(vertices, faces):
    """One midpoint subdivision: each triangle into four, shared edge midpoints welded."""
    vertices = list(vertices)
    midpoints = {}

    def midpoint(a, b):
        key = (min(a, b), max(a, b))
        if key not in midpoints:
            va, vb = vertices[a], vertices[b]
            vertices.append(tuple(0.5 * (x + y) for x, y in zip(va, vb)))
            midpoints[key] = len(vertices) - 1
        return midpoints[key]

    out = []
    for a, b, c in faces:
        ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
        out += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
    return vertices, out


def extent(vertices):
    lo = [min(v[k] for v in vertices) for k in range(3)]
    hi = [max(v[k] for v in vertices) for k in range(3)]
    return lo, hi


def punch_hole(vertices, faces):
    """Removes the faces within a radius of a point on the +x side at mid height (and their
    vertices): an open, non-watertight scan."""
    lo, hi = extent(vertices)
    centre = [0.5 * (a + b) for a, b in zip(lo, hi)]
    radius = 0.2 * max(b - a for a, b in zip(lo, hi))
    # The hole sits on the side facing +x, at mid height.
    target = (hi[0], centre[1], centre[2])

    def near(face):
        c = [sum(vertices[i][k] for i in face) / 3 for k in range(3)]
        return math.dist(c, target) < radius

    kept = [f for f in faces if not near(f)]
    # The hole's vertices go too, as in a scan that never saw them.
    used = sorted({i for f in kept for i in f})
    index = {old: new for new, old in enumerate(used)}
    return [vertices[i] for i in used], [tuple(index[i] for i in f) for f in kept]


def unweld_band(vertices, faces):
    """Every face in a horizontal band gets its own copies of its vertices (duplicates at
    the same positions, as scans exported per texture chart have)."""
    lo, hi = extent(vertices)
    y0 = lo[1] + 0.4 * (hi[1] - lo[1])
    y1 = lo[1] + 0.6 * (hi[1] - lo[1])
    vertices = list(vertices)
    out = []
    for face in faces:
        cy = sum(vertices[i][1] for i in face) / 3
        if y0 <= cy <= y1:
            copies = []
            for i in face:
                vertices.append(vertices[i])
                copies.append(len(vertices) - 1)
            out.append(tuple(copies))
        else:
            out.append(face)
    return vertices, out


def add_fragment(vertices, faces):
    """A small loose box beside the object: a second connected component."""
    lo, hi = extent(vertices)
    size = 0.08 * max(b - a for a, b in zip(lo, hi))
    origin = (hi[0] + size, lo[1], lo[2])
    base = len(vertices)
    corners = [
        tuple(origin[k] + size * ((i >> k) & 1) for k in range(3)) for i in range(8)
    ]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    box = []
    for a, b, c, d in quads:
        box += [(base + a, base + b, base + c), (base + a, base + c, base + d)]
    return vertices + corners, faces + box


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("category", help="a generated category folder (canonical.obj, train/, test/)")
    parser.add_argument("out", help="where to write the messy copy (must not exist)")
    parser.add_argument("--subdivide", type=int, default=3, help="midpoint subdivisions (each ~4x the vertices)")
    args = parser.parse_args()
    if os.path.exists(args.out):
        raise SystemExit(f"{args.out} exists; give a new folder")
    os.makedirs(os.path.join(args.out, "train"))
    os.makedirs(os.path.join(args.out, "test"))
    if os.path.exists(os.path.join(args.category, "info.json")):
        shutil.copy(os.path.join(args.category, "info.json"), args.out)

    def convert(src, dst, damage=None):
        v, f = load_obj(src)
        for _ in range(args.subdivide):
            v, f = subdivide(v, f)
        if damage:
            v, f = damage(v, f)
        save_obj(dst, v, f)
        return len(v), len(f)

    n = convert(os.path.join(args.category, "canonical.obj"), os.path.join(args.out, "canonical.obj"))
    print(f"canonical.obj: {n[0]} vertices, {n[1]} faces")
    damages = [None, punch_hole, unweld_band, add_fragment]
    names = sorted(os.listdir(os.path.join(args.category, "train")))
    for i, name in enumerate(names):
        damage = damages[i % len(damages)]
        n = convert(os.path.join(args.category, "train", name), os.path.join(args.out, "train", name), damage)
        what = damage.__name__.replace("_", " ") if damage else "clean"
        print(f"train/{name}: {n[0]} vertices, {n[1]} faces ({what})")
    for name in sorted(os.listdir(os.path.join(args.category, "test"))):
        n = convert(os.path.join(args.category, "test", name), os.path.join(args.out, "test", name))
        print(f"test/{name}: {n[0]} vertices, {n[1]} faces")


if __name__ == "__main__":
    main()
