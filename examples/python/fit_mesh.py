"""A sphere deformed into an object seen in four silhouettes, as PyTorch3D's mesh-fitting
tutorial does, with vkdr's exact edge gradients composed into a torch loss.

    pip install ./bindings/python torch && python examples/python/fit_mesh.py

The target (a lumpy, squashed blob) is rendered from four cameras around it; its masks are
all the fit sees. A sphere of the same topology is deformed by per-vertex offsets, with
Adam on: the four views' antialiased silhouettes (`vkdr.torch.rasterize` of the four poses
in one call, then `vkdr.torch.silhouette`) against the masks, plus a Laplacian smoothness
term and an edge-length term written in torch. Every 25 steps it prints the silhouettes'
IoU in the four views and in four others the fit never sees, and the surface's chamfer
distance to the target; it exits 1 unless the unseen views end above 0.95 IoU and the
surface within half its starting distance.
"""

import sys
import time

import numpy as np
import torch

import vkdr
import vkdr.torch as vt

SIZE = (96, 96)
K = np.array([[150.0, 0.0, 48.0], [0.0, 150.0, 48.0], [0.0, 0.0, 1.0]])
DISTANCE = 0.3


def sphere(radius=0.05, rings=12, segments=20):
    """A closed UV sphere: vertices (V, 3) and outward faces (F, 3)."""
    vertices = [[0.0, radius, 0.0]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            vertices.append([radius * np.sin(theta) * np.cos(phi), radius * np.cos(theta), radius * np.sin(theta) * np.sin(phi)])
    vertices.append([0.0, -radius, 0.0])
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments  # noqa: E731
    faces = [[0, ring(1, j + 1), ring(1, j)] for j in range(segments)]
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, b, d], [a, d, c]]
    last = len(vertices) - 1
    faces += [[last, ring(rings - 1, j), ring(rings - 1, j + 1)] for j in range(segments)]
    return np.array(vertices), np.array(faces, dtype=np.int64)


def target_shape(vertices):
    """The sphere squashed, stretched and given two lumps."""
    v = vertices * np.array([1.3, 0.8, 1.0])
    for centre, height in [((0.7, 0.5, 0.5), 0.012), ((-0.6, -0.2, -0.77), 0.010)]:
        direction = np.array(centre) / np.linalg.norm(centre)
        along = vertices @ direction / 0.05
        v = v + height * np.exp(-8.0 * (1.0 - along))[:, None] * vertices / 0.05
    return v


def camera_poses(count=4):
    """Cameras around the object, each looking at its centre from DISTANCE, alternately
    above and below it (pose: x_camera = R x + t; translation, then axis-angle)."""
    poses = []
    for k in range(count):
        turn = np.array([0.0, 2 * np.pi * k / count, 0.0])
        tilt = np.array([0.35 * (-1) ** k, 0.0, 0.0])
        r = vt.rotation_matrix(torch.tensor(tilt)) @ vt.rotation_matrix(torch.tensor(turn))
        poses.append(np.concatenate([[0.0, 0.0, DISTANCE], axis_angle(r.numpy())]))
    return np.array(poses)


def axis_angle(r):
    """The axis-angle vector of a rotation matrix (angles below pi)."""
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
    if angle < 1e-9:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * np.sin(angle))
    return angle * axis


def neighbours_of(faces, count):
    """Each vertex's neighbours as a row-normalised adjacency (V, V), and the edges (E, 2)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    adjacency = np.zeros((count, count))
    adjacency[edges[:, 0], edges[:, 1]] = adjacency[edges[:, 1], edges[:, 0]] = 1.0
    return torch.tensor(adjacency / adjacency.sum(1, keepdims=True)), torch.tensor(edges)


def surface_points(vertices, faces, count=4000, seed=0):
    """Points spread uniformly over the mesh's surface."""
    rng = np.random.default_rng(seed)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    chosen = rng.choice(len(faces), count, p=area / area.sum())
    u, v = rng.uniform(size=(2, count, 1))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    return a[chosen] + u * (b - a)[chosen] + v * (c - a)[chosen]


def surface_distance(vertices, truth, faces):
    """The symmetric chamfer distance between the two surfaces (mm, 4000 points each)."""
    d = torch.cdist(torch.tensor(surface_points(vertices, faces)), torch.tensor(surface_points(truth, faces, seed=1)))
    return 500.0 * (d.min(0).values.mean() + d.min(1).values.mean()).item()


def silhouette_iou(device, vertices, truth, faces, poses):
    """The mean IoU of the two meshes' masks from `poses`."""
    seen, want = (device.rasterize(v.astype(np.float32), faces, K, SIZE, poses)[0] > 0 for v in (vertices, truth))
    return float(np.mean([(s & w).sum() / (s | w).sum() for s, w in zip(seen, want)]))


def main():
    device = vkdr.Device()
    start, faces = sphere()
    truth = target_shape(start)
    poses = torch.tensor(camera_poses())
    # Four further cameras the fit never sees, between the others: the shape, not only
    # the four silhouettes.
    unseen = camera_poses(8)[1::2]
    ids, _, _ = device.rasterize(truth.astype(np.float32), faces, K, SIZE, poses.numpy())
    masks = torch.tensor(ids > 0, dtype=torch.float64)
    adjacency, edges = neighbours_of(faces, len(start))
    base = torch.tensor(start)
    offsets = torch.zeros_like(base, requires_grad=True)
    adam = torch.optim.Adam([offsets], lr=5e-4)
    mean_edge = (base[edges[:, 0]] - base[edges[:, 1]]).norm(dim=1).mean()

    def report(step, vertices):
        v = vertices.detach().numpy()
        distance = surface_distance(v, truth, faces)
        iou = silhouette_iou(device, v, truth, faces, poses.numpy())
        held_out = silhouette_iou(device, v, truth, faces, unseen)
        print(f"step {step:3d}: IoU {iou:.3f} in the fitted views, {held_out:.3f} in four others; surface {distance:.2f} mm")
        return distance, held_out

    first, first_held_out = report(0, base)
    began = time.perf_counter()
    steps = 150
    for step in range(1, steps + 1):
        vertices = base + offsets
        fragments = vt.rasterize(vertices, faces, K, SIZE, poses, device=device)
        images = vt.silhouette(fragments, vertices, faces, K, poses)
        silhouettes = ((images - masks) ** 2).mean()
        laplacian = ((adjacency @ vertices - vertices) ** 2).sum(1).mean() / mean_edge**2
        lengths = (vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1)
        edge = ((lengths / mean_edge - 1.0) ** 2).mean()
        loss = silhouettes + 0.01 * laplacian + 0.001 * edge
        adam.zero_grad()
        loss.backward()
        adam.step()
        if step % 25 == 0 and step < steps:
            report(step, base + offsets)
    per_step = 1e3 * (time.perf_counter() - began) / steps
    distance, held_out = report(steps, base + offsets)
    print(f"{per_step:.1f} ms per step ({len(start)} vertices, {len(poses)} views of {SIZE[0]} x {SIZE[1]}, {device.name})")
    if not (held_out > 0.95 and distance < 0.5 * first):
        print(f"FAILED: held-out IoU {held_out:.3f} (needs > 0.95), surface {distance:.2f} mm (needs < {0.5 * first:.2f})")
        sys.exit(1)
    print(
        f"fitted: IoU {first_held_out:.3f} -> {held_out:.3f} in views the fit never saw, "
        f"the surface {first:.2f} -> {distance:.2f} mm from the target's"
    )


if __name__ == "__main__":
    main()
