"""Adam recovers an object's pose from its mask through vkdr's exact gradients.

    pip install ./bindings/python torch && python examples/python/fit_pose.py

An asymmetric object (a block with a handle and a spout) is rendered at a true pose; the
fit starts 2 cm and 12 degrees away and follows `vkdr.torch.silhouette_loss` (the mask's
antialiased mse) with Adam, printing the error each 20 steps. It ends within 1 mm and
1 degree of the true pose (exit status 1 if not).
"""

import sys

import numpy as np
import torch

import vkdr
from vkdr.torch import silhouette_loss


def box(lo, hi):
    """A box's 8 corners and 12 outward triangles."""
    corners = np.array([[(lo, hi)[i & 1][0], (lo, hi)[i >> 1 & 1][1], (lo, hi)[i >> 2][2]] for i in range(8)])
    faces = np.array([
        [0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6],  # z- z+
        [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3],  # y- y+
        [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5],  # x- x+
    ])
    return corners, faces


def object_mesh():
    """A body 6 x 10 x 4 cm, a handle on its right and a spout on its upper left."""
    parts = [
        box((-0.03, -0.05, -0.02), (0.03, 0.05, 0.02)),
        box((0.03, -0.02, -0.008), (0.055, 0.03, 0.008)),
        box((-0.05, -0.05, -0.01), (-0.03, -0.035, 0.01)),
    ]
    vertices, faces = [], []
    for v, f in parts:
        faces.append(f + sum(len(p) for p in vertices))
        vertices.append(v)
    return np.concatenate(vertices).astype(np.float32), np.concatenate(faces).astype(np.int64)


def rotation(r):
    """The rotation matrix of an axis-angle vector (Rodrigues)."""
    angle = np.linalg.norm(r)
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def errors(pose, truth):
    """Translation error (mm) and rotation error (degrees) of `pose` against `truth`."""
    translation = 1e3 * np.linalg.norm(pose[:3] - truth[:3])
    relative = rotation(pose[3:]) @ rotation(truth[3:]).T
    cos = np.clip((np.trace(relative) - 1) / 2, -1, 1)
    return translation, np.degrees(np.arccos(cos))


def main():
    device = vkdr.Device()
    print(f"device: {device.name}")
    vertices, faces = object_mesh()
    size = (192, 192)
    K = np.array([[300.0, 0, 96], [0, 300.0, 96], [0, 0, 1]])
    truth = np.array([0.01, -0.005, 0.45, 0.35, -0.5, 0.2])
    ids, _, _ = device.rasterize(vertices, faces, K, size, truth)
    mask = (ids > 0).astype(np.float32)

    start = truth + np.array([0.015, -0.012, 0.0, 0.12, -0.1, 0.14])
    print("start: %.1f mm, %.1f degrees off" % errors(start, truth))
    vertices_t = torch.from_numpy(vertices)
    translation = torch.tensor(start[:3], requires_grad=True)
    axis_angle = torch.tensor(start[3:], requires_grad=True)
    steps = 300
    # Adam's steps are about lr per coordinate: metres and radians take their own.
    optimizer = torch.optim.Adam([
        {"params": [translation], "lr": 1e-3},
        {"params": [axis_angle], "lr": 1e-2},
    ])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 0.5 * (1 + np.cos(np.pi * k / steps)))
    for step in range(steps + 1):
        pose = torch.cat([translation, axis_angle])
        loss = silhouette_loss(vertices_t, pose, faces, K, size, mask, device=device)
        if step % 20 == 0 or step == steps:
            t, r = errors(pose.detach().numpy(), truth)
            print(f"step {step:3d}  loss {loss.item():.3e}  translation {t:6.2f} mm  rotation {r:6.2f} deg")
        if step == steps:
            break
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    t, r = errors(pose.detach().numpy(), truth)
    ok = t < 1.0 and r < 1.0
    print(f"final: {t:.2f} mm, {r:.2f} degrees from the true pose ({'within' if ok else 'NOT within'} 1 mm and 1 degree)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
