"""vkdr as PyTorch operations: a G-buffer to compose into any loss, and exact silhouette
gradients.

    import vkdr.torch as vt
    frags = vt.rasterize(vertices, faces, K, (width, height), pose)   # pose (6,) or (N, 6)
    colour = vt.interpolate(vertex_colours, frags, faces)              # (H, W, C), differentiable
    loss = ((colour - target) ** 2).mean() + ((frags.depth - depth) ** 2).mean()
    loss.backward()                                                     # vertices, pose, colours

    colour = vt.antialias(colour, frags, vertices, faces, K, pose)     # the edges' gradients too
    loss = ((vt.silhouette(frags, vertices, faces, K, pose) - mask) ** 2).mean()

    loss = vt.silhouette_loss(vertices, pose, faces, K, (width, height), mask)
    loss.backward()        # vertices.grad (V x 3) and pose.grad (6,) from vkdr

`rasterize` finds what each pixel sees on vkdr's device (which triangle, as
`vkdr.Device.rasterize`) and recomputes, in torch, where the pixel's ray meets that
triangle: perspective-correct barycentrics and depth, differentiable in the vertices and
the pose (as nvdiffrast's `rasterize`). Which triangle a pixel sees does not move with
them, so a rendering's gradients are those of the triangles' interiors. `antialias`
adds the silhouette edges' (vkdr's own antialiasing, exact at any tessellation) to any
image; `silhouette_loss` is the engine's built-in mask and depth loss, the fast path.

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


def rasterize(vertices, faces, K, size=None, pose=None, device=None, *, resolution=None):
    """The mesh (`vertices` V x 3, `faces` F x 3) through the camera `K` at `size` =
    (width, height), or `resolution` = (height, width) as nvdiffrast takes it, from `pose`
    (6,) or poses (N, 6): `Fragments` whose `bary` and `depth` are differentiable in
    `vertices` and `pose` (see `barycentrics`), (H, W, ...) or (N, H, W, ...); the
    visibility is vkdr's (`vkdr.Device.visibility`, on `device` or the default one)."""
    if (size is None) == (resolution is None):
        raise ValueError("rasterize: give size=(width, height) or resolution=(height, width), one of them")
    if resolution is not None:
        height, width = resolution
        size = (width, height)
    if pose is None:
        raise ValueError("rasterize: pose is required, (6,) or (N, 6)")
    vertices = torch.as_tensor(vertices)
    pose = torch.as_tensor(pose, device=vertices.device)
    device = device if device is not None else default_device()
    ids = device.visibility(
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
    under `torch.func.grad` and `torch.func.vmap` over the vertices and the pose (one
    vkdr call per batch element: the batch is a loop, not one dispatch)."""

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
    def vmap(info, in_dims, vertices, pose, device, faces, K, size, mask, options):
        """`torch.func.vmap`'s rule: the function of each element of the batch (the vertices',
        the pose's or both, along their mapped dimension), stacked along dimension 0. (The
        other arguments are NumPy arrays and options by then, `silhouette_loss`'s doing.)"""
        vertices_dim, pose_dim = in_dims[:2]
        element = lambda x, dim, i: x if dim is None else x.select(dim, i)
        outputs = [
            SilhouetteLoss.apply(
                element(vertices, vertices_dim, i), element(pose, pose_dim, i), device, faces, K, size, mask, options
            )
            for i in range(info.batch_size)
        ]
        return tuple(torch.stack(column) for column in zip(*outputs)), (0, 0, 0)

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

    generate_vmap_rule = True  # forward is torch's own clone

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
    options = {key: _fixed(key, value) for key, value in options.items()}
    options["loss"] = loss
    options["depth"] = _fixed("depth", depth)
    device = device if device is not None else default_device()
    vertices = torch.as_tensor(vertices)
    pose = torch.as_tensor(pose, device=vertices.device)
    value, _, _ = SilhouetteLoss.apply(
        vertices, pose, device, _fixed("faces", faces), _fixed("K", K), tuple(size), _fixed("mask", mask), options
    )
    return value


def _fixed(name, value):
    """`silhouette_loss`'s argument `name` (not differentiated) as NumPy: a ValueError where
    `torch.func.vmap` maps over it, which torch reports as a missing data pointer."""
    try:
        return _numpy(value)
    except RuntimeError as e:
        raise ValueError(
            f"silhouette_loss: {name} cannot be mapped by torch.func.vmap (only the vertices and "
            f"the pose can); give one {name} per call"
        ) from e


# --- Antialiasing: vkdr's silhouette edges for any image --------------------------------
#
# The same rule as vkdr's own pass (glsl/include/diff.glsl; its float64 reference is
# src/diff/reference.rs): for two adjacent pixels seeing different triangles, the front
# one's surface is walked along the segment between their centres to the silhouette edge
# it leaves by (an edge without a neighbour, or whose neighbour faces the other way); the
# edge crosses the segment at alpha (0 at the front centre). Past the middle, the front
# colour reaches into the other pixel by alpha - 1/2; before it, the other colour into the
# front pixel by 1/2 - alpha. Each edge is taken along x or along y, whichever its
# function changes faster along. The walk (which edge) is found without gradients; alpha
# is recomputed from that edge's corners in torch, so the image's gradients reach the
# vertices and the pose through where the edge crosses.

NO_NEIGHBOUR = -1
MAX_WALK = 65536


def _neighbours(faces):
    """For each face t and corner k, the face across the edge opposite k (index 3 t + k),
    or -1 for an edge without exactly one other face (vkdr::diff::neighbours)."""
    f = np.asarray(faces, dtype=np.int64)
    count = len(f)
    proper = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    a, b = f[:, [1, 2, 0]], f[:, [2, 0, 1]]
    key = (np.minimum(a, b) * (int(f.max(initial=0)) + 1) + np.maximum(a, b))[proper].ravel()
    slot = (3 * np.arange(count)[:, None] + np.arange(3)).reshape(count, 3)[proper].ravel()
    order = np.argsort(key, kind="stable")
    key, slot = key[order], slot[order]
    _, first, shared = np.unique(key, return_index=True, return_counts=True)
    s0, s1 = slot[first[shared == 2]], slot[first[shared == 2] + 1]
    out = np.full(3 * count, NO_NEIGHBOUR, dtype=np.int64)
    out[s0], out[s1] = s1 // 3, s0 // 3
    return out


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _edge_function(ci, cj, p):
    """The homogeneous edge function of corners ci, cj (x, y, w) at the pixel p."""
    return _cross2(ci[..., :2] - p * ci[..., 2:], cj[..., :2] - p * cj[..., 2:])


def _corner(c, index):
    """c[n, index[n]] for corners c (P, 3, 3) and index (P,)."""
    return c[np.arange(len(index)), index]


def _walk_edge_function(c, v, k, p):
    """The function of the edge opposite corner k, from its vertices in index order (so
    both faces sharing it agree exactly), as glsl's walk_edge_function."""
    i, j = (k + 1) % 3, (k + 2) % 3
    ci, cj = _corner(c, i), _corner(c, j)
    swap = _corner(v, i) > _corner(v, j)
    first = np.where(swap[:, None], cj, ci)
    second = np.where(swap[:, None], ci, cj)
    e = _edge_function(first, second, p)
    return np.where(swap, -e, e)


def _facing(c):
    return np.sign(np.linalg.det(c))


def _left_of_line(c, pf, d):
    """Which side of the line through pf along d each corner (P, 3, 3) lies on."""
    return _cross2(d[:, None], c[..., :2] - pf[:, None] * c[..., 2:]) >= 0.0


def _crossings(h, faces, neighbours, view, start, pf, pb):
    """The silhouette edge each segment pf -> pb leaves the surface of face `start` by (in
    view `view`, homogeneous pixel corners h (N, V, 3)): (face, edge opposite corner), -1
    where the segment ends on that surface or its line misses the first face."""
    count = len(start)
    d = pb - pf
    found_face = np.full(count, -1, dtype=np.int64)
    found_edge = np.zeros(count, dtype=np.int64)
    corners = lambda rows, t: h[view[rows, None], faces[t]]
    rows = np.arange(count)
    c = corners(rows, start)
    v = faces[start]
    inside = _facing(c)
    # The first face's exit: of the edges the line crosses, the one it leaves by.
    left = _left_of_line(c, pf, d)
    score = np.full((count, 3), -np.inf)
    for k in range(3):
        kk = np.full(count, k)
        crosses = left[:, (k + 1) % 3] != left[:, (k + 2) % 3]
        outward = (_walk_edge_function(c, v, kk, pf) - _walk_edge_function(c, v, kk, pb)) * inside
        score[:, k] = np.where(crosses, outward, -np.inf)
    edge = score.argmax(1)
    active = np.isfinite(score.max(1))
    current = start.copy()
    for _ in range(MAX_WALK):
        rows = np.flatnonzero(active)
        if len(rows) == 0:
            return found_face, found_edge
        t, k = current[rows], edge[rows]
        c, v = corners(rows, t), faces[t]
        eb = _walk_edge_function(c, v, k, pb[rows])
        ends = eb * inside[rows] >= 0.0  # pb lies on this surface: no silhouette between
        following = neighbours[3 * t + k]
        silhouette = following == NO_NEIGHBOUR
        beyond = np.flatnonzero(~silhouette)
        silhouette[beyond] = _facing(corners(rows[beyond], following[beyond])) != inside[rows[beyond]]
        hit = ~ends & silhouette
        found_face[rows[hit]], found_edge[rows[hit]] = t[hit], k[hit]
        walk = ~ends & ~silhouette
        active[rows[~walk]] = False
        rows, t, k, v = rows[walk], following[walk], k[walk], v[walk]
        # The next exit: by the side of the line the corner opposite the entry edge lies on.
        entry = np.stack([_corner(v, (k + 1) % 3), _corner(v, (k + 2) % 3)], 1)
        w = faces[t]
        on_entry = (w[:, :, None] == entry[:, None, :]).any(-1)
        if not (on_entry.sum(1) == 2).all():
            raise RuntimeError("vkdr.torch.antialias: the faces' neighbour table does not match them")
        apex = (~on_entry).argmax(1)
        left = _left_of_line(corners(rows, t), pf[rows], d[rows])
        i, j = (apex + 1) % 3, (apex + 2) % 3
        edge[rows] = np.where(_corner(left, i) != _corner(left, apex), j, i)
        current[rows] = t
    raise RuntimeError(f"vkdr.torch.antialias: a silhouette search crossed {MAX_WALK} faces without an end")


def _homogeneous(vertices, pose, K):
    """Camera-space corners as homogeneous pixel coordinates (fx x + cx z, fy y + cy z, z),
    (N, V, 3), differentiable in `vertices` (V, 3) and `pose` (N, 6)."""
    fx, fy, cx, cy = _intrinsics(K)
    camera = vertices[None] @ rotation_matrix(pose[:, 3:]).transpose(-1, -2) + pose[:, None, :3]
    x, y, z = camera.unbind(-1)
    return torch.stack([fx * x + cx * z, fy * y + cy * z, z], -1)


def antialias(image, fragments, vertices, faces, K, pose):
    """`image` (H, W, C) with its silhouette edges antialiased as vkdr antialiases its
    own renderings (nvdiffrast's `antialias`, with vkdr's walk to the edge: exact at any
    tessellation and behind occluders): differentiable in `image` and, through where each
    silhouette edge crosses between pixel centres, in `vertices` and `pose`. `fragments`
    are `rasterize`'s for the same mesh, camera and pose (6,); for poses (N, 6), `image` is
    (N, H, W, C). The image may hold anything per pixel: coverage, interpolated
    attributes, shading, depth."""
    vertices = torch.as_tensor(vertices)
    pose = torch.as_tensor(pose, device=vertices.device)
    image = torch.as_tensor(image, device=vertices.device)
    batched = pose.dim() == 2
    triangle, depth = fragments.triangle, fragments.depth
    if not batched:
        pose, triangle, depth, image = pose[None], triangle[None], depth[None], image[None]
    if image.dim() != 4 or image.shape[:3] != triangle.shape:
        raise ValueError(
            f"image: expected (H, W, C) or (N, H, W, C) matching the fragments' {tuple(triangle.shape)}, "
            f"got {tuple(image.shape)}"
        )
    dtype = torch.promote_types(torch.promote_types(vertices.dtype, pose.dtype), image.dtype)
    faces_np = np.asarray(_numpy(faces), dtype=np.int64)
    h = _homogeneous(vertices.to(dtype), pose.to(dtype), K)
    n, height, width = triangle.shape
    tri = triangle.detach().cpu().numpy()
    z = np.where(tri >= 0, depth.detach().cpu().to(torch.float64).numpy(), np.inf)
    views, rows_f, cols_f, rows_g, cols_g, faces_f, edges = [], [], [], [], [], [], []
    neighbours = _neighbours(faces_np)
    h_np = h.detach().cpu().to(torch.float64).numpy()
    for along_x in (True, False):
        a = tri[:, :, :-1] if along_x else tri[:, :-1, :]
        b = tri[:, :, 1:] if along_x else tri[:, 1:, :]
        view, i, j = np.nonzero(a != b)
        qi, qj = (i, j + 1) if along_x else (i + 1, j)
        p_front = z[view, i, j] <= z[view, qi, qj]
        fi, fj = np.where(p_front, i, qi), np.where(p_front, j, qj)
        gi, gj = np.where(p_front, qi, i), np.where(p_front, qj, j)
        centre = lambda r, c: np.stack([c + 0.5, r + 0.5], -1).astype(np.float64)
        face, edge = _crossings(h_np, faces_np, neighbours, view, tri[view, fi, fj], centre(fi, fj), centre(gi, gj))
        found = np.flatnonzero(face >= 0)
        c = h_np[view[found, None], faces_np[face[found]]]
        e = edge[found]
        ci, cj = _corner(c, (e + 1) % 3), _corner(c, (e + 2) % 3)
        lx = ci[:, 1] * cj[:, 2] - ci[:, 2] * cj[:, 1]
        ly = ci[:, 2] * cj[:, 0] - ci[:, 0] * cj[:, 2]
        keep = found[(np.abs(lx) >= np.abs(ly)) == along_x]
        for out, value in zip(
            (views, rows_f, cols_f, rows_g, cols_g, faces_f, edges), (view, fi, fj, gi, gj, face, edge)
        ):
            out.append(value[keep])
    view, fi, fj, gi, gj, face, edge = (torch.from_numpy(np.concatenate(x)).to(image.device) for x in (views, rows_f, cols_f, rows_g, cols_g, faces_f, edges))
    faces_t = torch.from_numpy(faces_np).to(image.device)
    corners = faces_t[face]
    ci = h[view, corners.gather(1, ((edge + 1) % 3)[:, None])[:, 0]]
    cj = h[view, corners.gather(1, ((edge + 2) % 3)[:, None])[:, 0]]
    pixel = lambda r, c: torch.stack([c, r], -1).to(dtype) + 0.5
    ef = _edge_function(ci, cj, pixel(fi, fj))
    eb = _edge_function(ci, cj, pixel(gi, gj))
    alpha = ef / (ef - eb)
    weight = (alpha.clamp(0.0, 1.0) - 0.5).abs()
    reaches = alpha.detach() > 0.5  # the front surface reaches into the other pixel
    flat = image.to(dtype).reshape(n * height * width, -1)
    index_f = (view * height + fi) * width + fj
    index_g = (view * height + gi) * width + gj
    changed = torch.where(reaches, index_g, index_f)
    source = torch.where(reaches, index_f, index_g)
    out = flat.index_add(0, changed, weight[:, None] * (flat[source] - flat[changed]))
    out = out.reshape(n, height, width, -1)
    return out if batched else out[0]


def silhouette(fragments, vertices, faces, K, pose):
    """The antialiased coverage (H, W), or (N, H, W): 1 inside the mesh, 0 outside, and
    between them where a silhouette edge crosses; differentiable in `vertices` and `pose`
    (vkdr's exact edge gradients, as `silhouette_loss` uses them)."""
    covered = (fragments.triangle >= 0).to(torch.as_tensor(vertices).dtype)
    return antialias(covered[..., None], fragments, vertices, faces, K, pose)[..., 0]


__all__ = [
    "Fragments",
    "SilhouetteLoss",
    "antialias",
    "barycentrics",
    "interpolate",
    "rasterize",
    "rotation_matrix",
    "silhouette",
    "silhouette_loss",
]
