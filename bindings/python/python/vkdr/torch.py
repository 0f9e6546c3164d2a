"""vkdr as PyTorch operations: a G-buffer to compose into any loss, and exact silhouette
gradients.

    import vkdr.torch as vt
    frags = vt.rasterize(vertices, faces, K, (width, height), pose)   # pose (6,) or (N, 6)
    colour = vt.interpolate(vertex_colours, frags, faces)              # (H, W, C), differentiable
    loss = ((colour - target) ** 2).mean() + ((frags.depth - depth) ** 2).mean()
    loss.backward()                                                     # vertices, pose, colours

    loss = vt.silhouette_loss(vertices, pose, faces, K, (width, height), mask)
    loss.backward()        # vertices.grad (V x 3) and pose.grad (6,) from vkdr

`rasterize` finds what each pixel sees on vkdr's device (which triangle, as
`vkdr.Device.rasterize`) and recomputes, in torch, where the pixel's ray meets that
triangle: perspective-correct barycentrics and depth, differentiable in the vertices and
the pose (as nvdiffrast's `rasterize`). Which triangle a pixel sees does not move with
them, so a rendering's gradients are those of the triangles' interiors; where the
silhouette's edges matter (a mask), `silhouette_loss` has vkdr's exact edge gradients.

`vertices` (V x 3) and `pose` (6: translation in metres, axis-angle in radians; x_camera =
R x + t) are tensors, either of which may require grad; `K` is vkdr's (pixel (i, j)'s
centre at (j + 0.5, i + 0.5)). Tensors on a CUDA device are copied to the host for vkdr's
part and the results are on the vertices' device. Only this module imports torch.
"""

from typing import NamedTuple

import numpy as np
import torch

from . import default_device


def _numpy(value):
    """A tensor as a NumPy array (other values as they are)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return value


class Fragments(NamedTuple):
    """What each pixel sees, `(H, W, ...)` for one pose or `(N, H, W, ...)` for N.

    triangle: int64, the face index a pixel's centre sees, -1 on background.
    bary: the barycentric weights of the face's three corners (0 on background).
    depth: the camera-space z in metres (0 on background).
    """

    triangle: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor


def rotation_matrix(axis_angle):
    """Rodrigues: (..., 3) axis-angle to (..., 3, 3) rotations, differentiable everywhere
    (a series near the identity)."""
    w = axis_angle
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    small = theta2 < 1e-12
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2_safe)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = torch.zeros_like(x)
    k = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(w.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def _intrinsics(K):
    """(fx, fy, cx, cy) from (3, 3) or (4,) numbers."""
    k = np.asarray(_numpy(K), dtype=np.float64)
    if k.shape == (4,):
        return tuple(float(x) for x in k)
    if k.shape == (3, 3):
        return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    raise ValueError(f"K: expected shape (3, 3) or (4,), got {k.shape}")


def barycentrics(triangle, vertices, faces, K, pose):
    """The `Fragments` of a known visibility: where each pixel's ray (through its centre)
    meets the triangle `triangle` says it sees (-1: none), as perspective-correct
    barycentrics and camera-space depth, differentiable in `vertices` and `pose` (`pose`
    (6,) with `triangle` (H, W), or (N, 6) with (N, H, W)). `rasterize` calls it with
    vkdr's visibility; a loss that keeps the visibility fixed (finite differences, say)
    calls it directly."""
    triangle = torch.as_tensor(triangle, dtype=torch.int64, device=vertices.device)
    faces = torch.as_tensor(_numpy(faces), dtype=torch.int64, device=vertices.device)
    pose = torch.as_tensor(pose, device=vertices.device)
    batched = pose.dim() == 2
    if not batched:
        pose, triangle = pose[None], triangle[None]
    if triangle.dim() != 3 or triangle.shape[0] != pose.shape[0]:
        raise ValueError(f"triangle: expected (N, H, W) for {pose.shape[0]} poses, got {tuple(triangle.shape)}")
    dtype = torch.promote_types(vertices.dtype, pose.dtype)
    vertices, pose = vertices.to(dtype), pose.to(dtype)
    fx, fy, cx, cy = _intrinsics(K)
    n, h, w = triangle.shape
    camera = vertices[None] @ rotation_matrix(pose[:, 3:]).transpose(-1, -2) + pose[:, None, :3]
    view, row, column = (triangle >= 0).nonzero(as_tuple=True)
    corners = faces[triangle[view, row, column]]
    a, b, c = (camera[view, corners[:, k]] for k in range(3))
    x, y = column.to(dtype) + 0.5, row.to(dtype) + 0.5
    ray = torch.stack([(x - cx) / fx, (y - cy) / fy, torch.ones_like(x)], -1)
    # Moller-Trumbore from the camera's centre: ray s = a + u (b - a) + v (c - a).
    e1, e2, to_a = b - a, c - a, -a
    p = torch.linalg.cross(ray, e2)
    det = (e1 * p).sum(-1)
    q = torch.linalg.cross(to_a, e1)
    u = (to_a * p).sum(-1) / det
    v = (ray * q).sum(-1) / det
    s = (e2 * q).sum(-1) / det
    bary = torch.zeros(n, h, w, 3, dtype=dtype, device=vertices.device)
    depth = torch.zeros(n, h, w, dtype=dtype, device=vertices.device)
    bary = bary.index_put((view, row, column), torch.stack([1.0 - u - v, u, v], -1))
    depth = depth.index_put((view, row, column), s)
    if not batched:
        return Fragments(triangle[0], bary[0], depth[0])
    return Fragments(triangle, bary, depth)


def rasterize(vertices, faces, K, size, pose, device=None):
    """The mesh (`vertices` V x 3, `faces` F x 3) through the camera `K` at `size` =
    (width, height) from `pose` (6,) or poses (N, 6): `Fragments` whose `bary` and `depth`
    are differentiable in `vertices` and `pose` (see `barycentrics`); the visibility is
    vkdr's (`vkdr.Device.rasterize`, on `device` or the default one)."""
    vertices = torch.as_tensor(vertices)
    pose = torch.as_tensor(pose, device=vertices.device)
    device = device if device is not None else default_device()
    ids, _, _ = device.rasterize(
        vertices.detach().cpu().to(torch.float32).numpy(),
        _numpy(faces),
        _numpy(K),
        tuple(size),
        pose.detach().cpu().to(torch.float64).numpy(),
    )
    triangle = torch.from_numpy(ids.astype(np.int64) - 1)
    return barycentrics(triangle, vertices, faces, K, pose)


def interpolate(attributes, fragments, faces):
    """Per-vertex `attributes` (V, C), or (N, V, C) for N poses, at every pixel:
    `(..., H, W, C)`, the corners' values weighted by the fragments' barycentrics
    (perspective-correct), 0 on background; differentiable in both."""
    faces = torch.as_tensor(_numpy(faces), dtype=torch.int64, device=fragments.bary.device)
    attributes = torch.as_tensor(attributes, device=fragments.bary.device)
    triangle, bary = fragments.triangle, fragments.bary
    covered = triangle >= 0
    corners = faces[triangle.clamp(min=0)]  # (..., H, W, 3)
    if attributes.dim() == 2:
        values = attributes[corners]  # (..., H, W, 3, C)
    else:
        if triangle.dim() != 3 or attributes.shape[0] != triangle.shape[0]:
            raise ValueError(
                f"attributes: (N, V, C) needs fragments of N poses, got {tuple(attributes.shape)} "
                f"for {tuple(triangle.shape)}"
            )
        view = torch.arange(triangle.shape[0], device=triangle.device)[:, None, None, None]
        values = attributes[view, corners]
    dtype = torch.promote_types(attributes.dtype, bary.dtype)
    out = (bary.to(dtype)[..., None] * values.to(dtype)).sum(-2)
    return out * covered[..., None].to(dtype)


class SilhouetteLoss(torch.autograd.Function):
    """loss(vertices, pose) of `vkdr.Device.loss_and_grad`, differentiable in both, once
    (vkdr's gradients have no graph: a second derivative is refused, not wrong). Works
    under `torch.func.grad`, not `vmap`."""

    @staticmethod
    def forward(vertices, pose, device, faces, K, size, mask, options):
        v = vertices.detach().cpu().numpy()
        p = pose.detach().to("cpu", torch.float64).numpy()
        loss, grad_vertices, grad_pose = device.loss_and_grad(v, faces, K, size, p, mask, **options)
        return (
            torch.tensor(loss, dtype=vertices.dtype, device=vertices.device),
            torch.from_numpy(grad_vertices).to(vertices),
            torch.from_numpy(grad_pose).to(pose),
        )

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, grad_vertices, grad_pose = output
        ctx.mark_non_differentiable(grad_vertices, grad_pose)
        ctx.save_for_backward(grad_vertices, grad_pose, inputs[0], inputs[1])

    @staticmethod
    def backward(ctx, grad, _grad_vertices, _grad_pose):
        grad_vertices, grad_pose, vertices, pose = ctx.saved_tensors
        grads = grad * grad_vertices, grad * grad_pose
        if torch.is_grad_enabled():  # create_graph=True: the gradients refuse to be differentiated
            grads = tuple(_FirstOrderOnly.apply(g, vertices, pose) for g in grads)
        return (*grads, None, None, None, None, None, None)


class _FirstOrderOnly(torch.autograd.Function):
    """The identity on a gradient, made to depend on what it is the gradient in (the
    vertices and the pose), whose derivative is refused: vkdr's gradients have no graph,
    so a second derivative through them would be silently wrong."""

    @staticmethod
    def forward(x, *depends_on):
        return x.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        pass

    @staticmethod
    def backward(ctx, grad):
        raise RuntimeError(
            "vkdr.torch.silhouette_loss has first derivatives only: its gradient cannot be "
            "differentiated again (create_graph=True, torch.func.hessian, grad of grad)"
        )


def silhouette_loss(vertices, pose, faces, K, size, mask, loss="mse", depth=None, device=None, **options):
    """The loss of the mesh's rendering at `pose` against `mask` (and `depth`, where given),
    with vkdr's exact gradients for `vertices` and `pose`. `options` are the further keyword
    arguments of `vkdr.Device.loss_and_grad` (shading, ignore, depth_sigma, occlusion, ...).
    """
    options = {key: _numpy(value) for key, value in options.items()}
    options["loss"] = loss
    options["depth"] = _numpy(depth)
    device = device if device is not None else default_device()
    vertices = torch.as_tensor(vertices)
    pose = torch.as_tensor(pose, device=vertices.device)
    value, _, _ = SilhouetteLoss.apply(
        vertices, pose, device, _numpy(faces), _numpy(K), tuple(size), _numpy(mask), options
    )
    return value


__all__ = ["Fragments", "SilhouetteLoss", "barycentrics", "interpolate", "rasterize", "rotation_matrix", "silhouette_loss"]
