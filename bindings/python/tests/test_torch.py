"""vkdr.torch: the autograd function's gradients are vkdr's, scaled by the incoming
gradient, and agree with central differences; the example fits a pose. Skipped where
torch is not installed (it is large; CI installs it only when asked)."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, sphere

torch = pytest.importorskip("torch")
from vkdr.torch import silhouette_loss  # noqa: E402 - needs torch

SIZE = (256, 256)
K = np.array([[300.0, 0, 128], [0, 300.0, 128], [0, 0, 1]])
POSE = np.array([0.004, -0.003, 0.4, 0.5, -0.6, 0.3])


@pytest.fixture(scope="module")
def scene(device):
    vertices, faces = sphere(rings=24, segments=48)
    vertices = vertices * np.float32([1.6, 1.0, 0.6]) + np.float32([0.03, 0.0, 0.0])
    ids, _, _ = device.rasterize(vertices, faces, K, SIZE, POSE + np.array([0.005, -0.004, 0.01, 0.1, 0.08, -0.05]))
    return vertices.astype(np.float64), faces, ids > 0


def loss_of(device, scene, vertices, pose):
    _, faces, mask = scene
    return silhouette_loss(vertices, pose, faces, K, SIZE, mask, device=device)


def test_backward_gives_vkdr_gradients_scaled(device, scene):
    vertices, faces, mask = scene
    v = torch.tensor(vertices, requires_grad=True)
    p = torch.tensor(POSE, requires_grad=True)
    (2.5 * loss_of(device, scene, v, p)).backward()
    loss, grad_vertices, grad_pose = device.loss_and_grad(vertices, faces, K, SIZE, POSE, mask)
    assert np.array_equal(v.grad.numpy(), 2.5 * grad_vertices.astype(np.float64))
    assert np.array_equal(p.grad.numpy(), 2.5 * grad_pose)


def test_gradients_match_central_differences(device, scene):
    vertices, _, _ = scene
    v = torch.tensor(vertices, requires_grad=True)
    p = torch.tensor(POSE, requires_grad=True)
    loss_of(device, scene, v, p).backward()
    with torch.no_grad():
        at = lambda dv, dp: loss_of(device, scene, torch.tensor(vertices + dv), torch.tensor(POSE + dp)).item()
        # The pose, a quarter-pixel step per coordinate.
        h = np.array([3e-4, 3e-4, 1e-3, 1.2e-3, 1.2e-3, 1.2e-3])
        numeric = np.array([(at(0, h * e) - at(0, -h * e)) / (2 * h[k]) for k, e in enumerate(np.eye(6))])
        got = p.grad.numpy()
        assert np.linalg.norm(got - numeric) < 0.06 * np.linalg.norm(numeric)
        # The vertices: along the gradient, a step of 3e-5 m (the loss curves along it:
        # 1e-4 and 3e-4 m steps see 1.6% and 4% less).
        g = v.grad.numpy()
        direction = g / np.linalg.norm(g)
        step = 3e-5
        numeric = (at(step * direction, 0) - at(-step * direction, 0)) / (2 * step)
        assert numeric > 0
        assert abs((direction * g).sum() - numeric) < 0.02 * numeric


def test_example_fits_the_pose():
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "python" / "fit_pose.py")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "within 1 mm and 1 degree" in done.stdout.splitlines()[-1]
