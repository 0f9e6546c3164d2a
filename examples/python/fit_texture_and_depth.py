"""A pose and per-vertex colours recovered together from an RGB-D image, with a loss of
one's own: vkdr.torch's G-buffer (rasterize -> interpolate -> antialias) composed in torch.

    pip install ./bindings/python torch && python examples/python/fit_texture_and_depth.py

A squashed sphere painted with a smooth colour pattern is rendered at a true pose into a
colour image (interpolated vertex colours, antialiased as vkdr antialiases) and a depth
image. The fit starts 15 mm and 10 degrees away with every vertex grey, and Adam follows
an L1 colour loss plus a Huber loss on the depth where both images see the object: the
colours reach the loss through the barycentrics, the pose through the barycentrics, the
depth and the silhouette's edges. It prints the errors every 50 steps and exits 1 unless
the pose ends within 1 mm and 1 degree and the seen vertices' colours within 0.05.
"""

import sys
import time

import numpy as np
import torch

import vkdr
import vkdr.torch as vt

SIZE = (128, 128)
K = np.array([[200.0, 0.0, 64.0], [0.0, 200.0, 64.0], [0.0, 0.0, 1.0]])


def sphere(radius=0.05, rings=16, segments=24):
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
    return np.array(vertices) * np.array([1.4, 0.9, 0.7]), np.array(faces, dtype=np.int64)


def pattern(vertices):
    """Smooth colours over the surface: three waves of different directions."""
    u = vertices / np.abs(vertices).max(0)
    return 0.5 + 0.4 * np.stack([np.sin(3.0 * u[:, 0] + 1.0), np.sin(2.5 * u[:, 1] - 2.0 * u[:, 2]), np.cos(3.5 * u[:, 2] + u[:, 0])], 1)


def render(device, vertices, faces, colours, pose):
    """The antialiased colour image (H, W, 3) and the fragments."""
    fragments = vt.rasterize(vertices, faces, K, SIZE, pose, device=device)
    colour = vt.antialias(vt.interpolate(colours, fragments, faces), fragments, vertices, faces, K, pose)
    return colour, fragments


def pose_errors(pose, truth):
    """Translation (mm) and rotation (degrees) errors."""
    relative = vt.rotation_matrix(pose[3:]) @ vt.rotation_matrix(truth[3:]).T
    cos = ((torch.trace(relative) - 1) / 2).clamp(-1, 1)
    return 1e3 * (pose[:3] - truth[:3]).norm().item(), np.degrees(torch.arccos(cos).item())


def main():
    device = vkdr.Device()
    points, faces = sphere()
    vertices = torch.tensor(points)
    truth = torch.tensor([0.01, -0.005, 0.4, 0.4, -0.3, 0.2], dtype=torch.float64)
    true_colours = torch.tensor(pattern(points))
    with torch.no_grad():
        target, target_fragments = render(device, vertices, faces, true_colours, truth)
        target_depth = target_fragments.depth
    seen = np.unique(faces[target_fragments.triangle[target_fragments.triangle >= 0].numpy()])

    start = truth + torch.tensor([0.012, -0.009, 0.0, 0.1, -0.08, 0.12], dtype=torch.float64)
    translation = start[:3].clone().requires_grad_()
    axis_angle = start[3:].clone().requires_grad_()
    colours = torch.full_like(true_colours, 0.5).requires_grad_()
    steps = 200
    optimizer = torch.optim.Adam([
        {"params": [translation], "lr": 1e-3},
        {"params": [axis_angle], "lr": 1e-2},
        {"params": [colours], "lr": 2e-2},
    ])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 0.5 * (1 + np.cos(np.pi * k / steps)))
    t, r = pose_errors(start, truth)
    print(f"start: {t:.1f} mm, {r:.1f} degrees off; colours all grey")
    began = time.perf_counter()
    for step in range(steps + 1):
        pose = torch.cat([translation, axis_angle])
        colour, fragments = render(device, vertices, faces, colours, pose)
        both = (fragments.triangle >= 0) & (target_fragments.triangle >= 0)
        depth_mm = 1e3 * (fragments.depth - target_depth)[both]
        loss = (colour - target).abs().mean() + 0.01 * torch.nn.functional.huber_loss(depth_mm, torch.zeros_like(depth_mm), delta=2.0)
        if step % 50 == 0 or step == steps:
            t, r = pose_errors(pose.detach(), truth)
            error = (colours.detach() - true_colours)[seen].abs().mean().item()
            print(f"step {step:3d}: loss {loss.item():.4f}, pose {t:.2f} mm {r:.2f} deg, colours {error:.3f} off")
        if step == steps:
            break
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    per_step = 1e3 * (time.perf_counter() - began) / (steps + 1)
    print(f"{per_step:.1f} ms per step ({len(points)} vertices, {SIZE[0]} x {SIZE[1]}, {device.name})")
    ok = t < 1.0 and r < 1.0 and error < 0.05
    print(
        f"final: pose {t:.2f} mm and {r:.2f} degrees off, the seen vertices' colours {error:.3f} off "
        f"({'within' if ok else 'NOT within'} 1 mm, 1 degree and 0.05)"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
