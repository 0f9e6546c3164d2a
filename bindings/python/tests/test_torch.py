"""vkdr.torch: the autograd function's gradients are vkdr's, scaled by the incoming
gradient, and agree with central differences; the example fits a pose; the G-buffer's
fragments agree with vkdr's rasterizer and their gradients with finite differences.
Skipped where torch is not installed (it is large; .ci/run installs it)."""

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


def test_example_fits_a_mesh_to_four_silhouettes():
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "python" / "fit_mesh.py")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "in views the fit never saw" in done.stdout.splitlines()[-1]


def test_example_fits_texture_and_pose_to_rgbd():
    done = subprocess.run([sys.executable, str(ROOT / "examples" / "python" / "fit_texture_and_depth.py")], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "(within 1 mm, 1 degree and 0.05)" in done.stdout.splitlines()[-1]


def test_rasterize_agrees_with_vkdr_and_the_rays(device, scene):
    """The torch fragments' barycentrics and depth are vkdr's (float32 rounding) for one
    pose and a batch, and interpolating the camera-space corners gives each pixel's ray
    point at that depth (perspective-correct)."""
    import vkdr.torch as vt

    vertices, faces, _ = scene
    poses = np.stack([POSE, POSE + np.array([0.01, 0.0, 0.02, 0.2, -0.1, 0.3])])
    for pose in (POSE, poses):
        frags = vt.rasterize(torch.tensor(vertices), faces, K, SIZE, torch.tensor(pose), device=device)
        ids, bary, depth = device.rasterize(vertices.astype(np.float32), faces, K, SIZE, pose)
        covered = ids > 0
        assert covered.sum() > 1000
        assert np.array_equal(frags.triangle.numpy(), ids.astype(np.int64) - 1)
        got = frags.bary.numpy()
        # The rasterizer snaps corners to 1/256 pixel (lavapipe; others 1/16 to 1/256) and
        # interpolates in float32: up to about 1e-3 on a triangle 10 pixels across.
        difference = np.abs(got[covered][:, :2] - bary[covered])
        assert difference.max() < 1e-3 and difference.mean() < 1e-4, (difference.max(), difference.mean())
        assert np.allclose(got[covered].sum(-1), 1.0)
        assert np.abs(frags.depth.numpy()[covered] - depth[covered]).max() < 1e-5
        assert not got[~covered].any() and not frags.depth.numpy()[~covered].any()
    # Interpolated camera-space positions lie on the pixels' rays at their depth.
    pose = torch.tensor(POSE)
    frags = vt.rasterize(torch.tensor(vertices), faces, K, SIZE, pose, device=device)
    camera = torch.tensor(vertices) @ vt.rotation_matrix(pose[3:]).T + pose[:3]
    points = vt.interpolate(camera, frags, faces).numpy()
    rows, columns = np.nonzero(frags.triangle.numpy() >= 0)
    z = frags.depth.numpy()[rows, columns]
    ray = np.stack([(columns + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones_like(z)], -1)
    assert np.abs(points[rows, columns] - ray * z[:, None]).max() < 1e-9


def test_fragments_gradients_match_central_differences(device, scene):
    """gradcheck (float64) of the barycentrics and depth in the vertices and the pose, the
    visibility held (it is piecewise constant), on a small image."""
    import vkdr.torch as vt

    vertices, faces, _ = scene
    small_k = K / 4.0
    small_k[2, 2] = 1.0
    size = (64, 64)
    frags = vt.rasterize(torch.tensor(vertices), faces, small_k, size, torch.tensor(POSE), device=device)
    triangle = frags.triangle
    weights = torch.rand(64, 64, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def f(v, p):
        out = vt.barycentrics(triangle, v, faces, small_k, p)
        return (out.bary * weights[..., :3]).sum() + (out.depth * weights[..., 3]).sum()

    v = torch.tensor(vertices, requires_grad=True)
    p = torch.tensor(POSE, requires_grad=True)
    assert torch.autograd.gradcheck(f, (v, p), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_interpolate_fits_vertex_colours(device, scene):
    """Per-vertex colours fitted through interpolate to an image made from known colours
    come back where the image shows them, from two poses at once."""
    import vkdr.torch as vt

    vertices, faces, _ = scene
    poses = torch.tensor(np.stack([POSE, POSE + np.array([0, 0, 0, 0, np.pi, 0])]))
    frags = vt.rasterize(torch.tensor(vertices), faces, K, SIZE, poses, device=device)
    rng = np.random.default_rng(3)
    truth = torch.tensor(rng.uniform(0, 1, (len(vertices), 3)))
    target = vt.interpolate(truth, frags, faces)
    colours = torch.full_like(truth, 0.5, requires_grad=True)
    optimiser = torch.optim.Adam([colours], lr=0.05)
    for _ in range(300):
        optimiser.zero_grad()
        loss = ((vt.interpolate(colours, frags, faces) - target) ** 2).mean()
        loss.backward()
        optimiser.step()
    seen = np.unique(faces[frags.triangle[frags.triangle >= 0].numpy()])
    error = (colours.detach() - truth)[seen].abs().mean().item()
    assert error < 0.03, error


def test_silhouette_loss_takes_numpy_and_refuses_a_second_derivative(device, scene):
    vertices, faces, mask = scene
    plain = silhouette_loss(vertices, POSE, faces, K, SIZE, mask, device=device)
    assert np.isfinite(plain.item())
    v = torch.tensor(vertices, requires_grad=True)
    loss = silhouette_loss(v, torch.tensor(POSE), faces, K, SIZE, mask, device=device)
    (grad,) = torch.autograd.grad(loss, v, create_graph=True)
    with pytest.raises(RuntimeError, match="first derivatives only"):
        grad.sum().backward()


def test_silhouette_loss_under_torch_func_grad(device, scene):
    vertices, faces, mask = scene
    v = torch.tensor(vertices)
    grad = torch.func.grad(lambda x: silhouette_loss(x, torch.tensor(POSE), faces, K, SIZE, mask, device=device))(v)
    _, grad_vertices, _ = device.loss_and_grad(vertices, faces, K, SIZE, POSE, mask)
    assert np.array_equal(grad.numpy(), grad_vertices.astype(np.float64))


def test_silhouette_loss_under_torch_func_vmap(device, scene):
    """vmap over poses, over vertices, and of grad, gives each element's loss and
    gradients as one call does."""
    vertices, faces, mask = scene
    poses = np.stack([POSE, POSE + np.array([0.003, 0.0, 0.01, 0.05, -0.04, 0.1]), POSE - 0.002])
    shapes = np.stack([vertices, vertices * 1.05])
    f = lambda v, p: silhouette_loss(v, p, faces, K, SIZE, mask, device=device)
    each = [device.loss_and_grad(vertices, faces, K, SIZE, p, mask) for p in poses]
    losses = torch.func.vmap(f, in_dims=(None, 0))(torch.tensor(vertices), torch.tensor(poses))
    assert losses.shape == (3,)
    assert np.array_equal(losses.numpy(), [loss for loss, _, _ in each])
    grads = torch.func.vmap(torch.func.grad(f, argnums=1), in_dims=(None, 0))(torch.tensor(vertices), torch.tensor(poses))
    assert np.array_equal(grads.numpy(), np.stack([g for _, _, g in each]))
    by_shape = torch.func.vmap(torch.func.grad(f), in_dims=(0, None))(torch.tensor(shapes), torch.tensor(POSE))
    for got, v in zip(by_shape.numpy(), shapes):
        _, grad_vertices, _ = device.loss_and_grad(v, faces, K, SIZE, POSE, mask)
        assert np.array_equal(got, grad_vertices.astype(np.float64))
    # Both mapped, the batch along another dimension of the vertices: pairs (shape i, pose i).
    pairs = torch.func.vmap(f, in_dims=(2, 0))(torch.tensor(shapes).permute(1, 2, 0), torch.tensor(poses[:2]))
    expected = [device.loss_and_grad(v, faces, K, SIZE, p, mask)[0] for v, p in zip(shapes, poses[:2])]
    assert np.array_equal(pairs.numpy(), expected)
    # The mask is not mapped: a clear error, not torch's missing data pointer.
    masks = torch.tensor(np.stack([mask, mask]), dtype=torch.float32)
    with pytest.raises(ValueError, match="mask cannot be mapped by torch.func.vmap"):
        torch.func.vmap(lambda m: silhouette_loss(torch.tensor(vertices), torch.tensor(POSE), faces, K, SIZE, m, device=device))(masks)
    # grad of a sum over a vmapped batch: each pose's gradient.
    p = torch.tensor(poses, requires_grad=True)
    torch.func.vmap(f, in_dims=(None, 0))(torch.tensor(vertices), p).sum().backward()
    assert np.array_equal(p.grad.numpy(), np.stack([g for _, _, g in each]))


def test_silhouette_composes_to_vkdr_loss(device, scene):
    """rasterize -> silhouette -> a mean squared error in torch is vkdr's own mse loss, its
    value and its exact edge gradients (float32 rounding), for the vertices and the pose;
    a batch of poses gives each pose's image."""
    import vkdr.torch as vt

    vertices, faces, mask = scene
    loss, grad_vertices, grad_pose = device.loss_and_grad(vertices, faces, K, SIZE, POSE, mask)
    v = torch.tensor(vertices, requires_grad=True)
    p = torch.tensor(POSE, requires_grad=True)
    image = vt.silhouette(vt.rasterize(v, faces, K, SIZE, p, device=device), v, faces, K, p)
    assert ((image > 0) & (image < 1)).sum() > 100  # edges were antialiased
    composed = ((image - torch.tensor(mask, dtype=torch.float64)) ** 2).mean()
    composed.backward()
    assert abs(composed.item() - loss) < 1e-5 * loss
    assert np.linalg.norm(v.grad.numpy() - grad_vertices) < 1e-4 * np.linalg.norm(grad_vertices)
    assert np.linalg.norm(p.grad.numpy() - grad_pose) < 1e-4 * np.linalg.norm(grad_pose)
    poses = torch.tensor(np.stack([POSE, POSE + np.array([0.01, 0.0, 0.02, 0.2, -0.1, 0.3])]))
    both = vt.silhouette(vt.rasterize(v, faces, K, SIZE, poses, device=device), v, faces, K, poses)
    # (The same terms, added in another order where a pixel has several pairs.)
    assert torch.allclose(both[0], image, rtol=0, atol=1e-12)
    second = vt.rasterize(v, faces, K, SIZE, poses[1], device=device)
    assert torch.allclose(both[1], vt.silhouette(second, v, faces, K, poses[1]), rtol=0, atol=1e-12)


def test_antialias_gradients_match_central_differences(device):
    """gradcheck (float64) of rasterize's fragments -> interpolate -> antialias in the
    vertices, the pose and the colours, the visibility held, on two spheres, one partly
    behind the other (the front one's edges antialiased over the back one)."""
    import vkdr.torch as vt

    front, faces = sphere(radius=0.045, rings=6, segments=8)
    back = front * 1.2 + np.float32([0.045, 0.02, 0.06])
    vertices = np.concatenate([front, back]).astype(np.float64)
    faces = np.concatenate([faces, faces + len(front)])
    k = np.array([[70.0, 0, 32], [0, 70.0, 32], [0, 0, 1]])
    pose = np.array([-0.01, 0.0, 0.35, 0.1, -0.1, 0.05])
    frags = vt.rasterize(torch.tensor(vertices), faces, k, (64, 64), torch.tensor(pose), device=device)
    triangle = frags.triangle
    front_faces, back_faces = (triangle >= 0) & (triangle < len(faces) // 2), triangle >= len(faces) // 2
    assert front_faces.sum() > 200 and back_faces.sum() > 100
    colours = torch.rand(len(vertices), 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    weights = torch.rand(64, 64, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def f(v, p, c):
        fragments = vt.barycentrics(triangle, v, faces, k, p)
        image = vt.antialias(vt.interpolate(c, fragments, faces), fragments, v, faces, k, p)
        return (image * weights).sum()

    inputs = (torch.tensor(vertices, requires_grad=True), torch.tensor(pose, requires_grad=True), colours.requires_grad_())
    with torch.no_grad():
        fragments = vt.barycentrics(triangle, inputs[0], faces, k, inputs[1])
        plain = vt.interpolate(colours, fragments, faces)
        changed = (vt.antialias(plain, fragments, inputs[0], faces, k, inputs[1]) != plain).any(-1)
    # Along the outer silhouette and where the front sphere covers the back one.
    assert changed.sum() > 50 and (changed & back_faces).sum() > 5
    assert torch.autograd.gradcheck(f, inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


def test_antialias_refuses_an_image_of_another_size(device, scene):
    import vkdr.torch as vt

    vertices, faces, _ = scene
    v = torch.tensor(vertices)
    frags = vt.rasterize(v, faces, K, SIZE, torch.tensor(POSE), device=device)
    with pytest.raises(ValueError, match="matching the fragments"):
        vt.antialias(torch.zeros(10, 10, 3), frags, v, faces, K, torch.tensor(POSE))


def test_resolution_is_height_width_as_nvdiffrast_takes_it(device, scene):
    import vkdr.torch as vt

    vertices, faces, _ = scene
    v, p = torch.tensor(vertices), torch.tensor(POSE)
    by_size = vt.rasterize(v, faces, K, [256, 200], p, device=device)
    by_resolution = vt.rasterize(v, faces, K, pose=p, device=device, resolution=(200, 256))
    assert by_size.triangle.shape == (200, 256) and torch.equal(by_size.triangle, by_resolution.triangle)
    with pytest.raises(ValueError, match="one of them"):
        vt.rasterize(v, faces, K, (256, 200), p, device=device, resolution=(200, 256))


def test_torch_compile_runs_the_ops(device, scene):
    """torch.compile (AOTAutograd without code generation, so that CI need not compile
    C++; inductor ran the same here in 161 s) traces around vkdr's calls (graph breaks)
    and gives the eager value and gradients."""
    import vkdr.torch as vt

    vertices, faces, mask = scene
    target = torch.tensor(mask, dtype=torch.float64)

    def loss(v, p):
        fragments = vt.rasterize(v, faces, K, SIZE, p, device=device)
        composed = ((vt.silhouette(fragments, v, faces, K, p) - target) ** 2).mean()
        return composed + silhouette_loss(v, p, faces, K, SIZE, mask, device=device)

    results = []
    for run in (loss, torch.compile(loss, backend="aot_eager")):
        v = torch.tensor(vertices, requires_grad=True)
        p = torch.tensor(POSE, requires_grad=True)
        value = run(v, p)
        value.backward()
        results.append((value.item(), v.grad, p.grad))
    (eager, gv, gp), (compiled, cv, cp) = results
    assert compiled == eager
    assert torch.allclose(cv, gv, rtol=1e-12, atol=0) and torch.allclose(cp, gp, rtol=1e-12, atol=0)
