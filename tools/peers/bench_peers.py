#!/usr/bin/env python3
"""Times peer differentiable rasterizers on the meshes, camera and image size of
`vkdr bench`, and writes the same CSV columns, so the two files sit side by side:

    vertices,faces,width,height,forward_ms,backward_ms,plain_ms,device

Peers:
  * pytorch3d  - PyTorch3D's MeshRasterizer (hard, faces_per_pixel=1) and a loss on the
                 interpolated depth (its differentiable output), when `import pytorch3d`
                 works;
  * softras    - a SoftRas-style soft silhouette rasterizer written here in plain PyTorch
                 (sigmoid of the signed distance to every triangle, combined as
                 1 - prod(1 - D)), computed in image tiles so it fits in memory.
`plain_ms` is empty for peers (they have no separate plain render).

Not part of CI. Install torch (and optionally pytorch3d) yourself, then:

    python3 tools/peers/bench_peers.py --out peers/ [--size 1024] [--device cuda]

Timing: CUDA events on GPUs, wall clock on CPU; median of --repeats after one warm-up.
"""
import argparse
import math
import statistics
import sys
import time


def sphere(vertices):
    """The UV sphere `vkdr bench` uses (radius 0.1 m, poles on y, welded)."""
    rings = max(2, round(math.sqrt(vertices / 1.6)))
    segments = max(3, vertices // rings)
    pos = [(0.0, -0.1, 0.0)]
    for r in range(1, rings):
        theta = math.pi * r / rings
        y, rr = -0.1 * math.cos(theta), 0.1 * math.sin(theta)
        for s in range(segments):
            phi = 2 * math.pi * s / segments
            pos.append((rr * math.cos(phi), y, rr * math.sin(phi)))
    pos.append((0.0, 0.1, 0.0))
    top = len(pos) - 1

    def ring(r, s):
        return 1 + (r - 1) * segments + s % segments

    faces = []
    for s in range(segments):
        faces.append((0, ring(1, s), ring(1, s + 1)))
        faces.append((top, ring(rings - 1, s + 1), ring(rings - 1, s)))
    for r in range(1, rings - 1):
        for s in range(segments):
            a, b, c, d = ring(r, s), ring(r, s + 1), ring(r + 1, s), ring(r + 1, s + 1)
            faces.append((a, c, d))
            faces.append((a, d, b))
    return pos, faces


def rodrigues(torch, w):
    w = torch.tensor(w, dtype=torch.float64)
    angle = torch.linalg.norm(w)
    k = w / angle
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + torch.sin(angle) * kx + (1 - torch.cos(angle)) * kx @ kx


def camera_points(torch, positions, device):
    """Object to camera with vkdr bench's pose (t = (0.005, -0.004, 0.6), r = (0.3, 0.2, 0))."""
    r = rodrigues(torch, [0.3, 0.2, 0.0]).to(device=device, dtype=torch.float32)
    t = torch.tensor([0.005, -0.004, 0.6], device=device)
    return positions @ r.T + t


def project(torch, cam, size):
    f = 2.0 * size
    c = size / 2.0
    return torch.stack([f * cam[:, 0] / cam[:, 2] + c, f * cam[:, 1] / cam[:, 2] + c], dim=1)


def mask(torch, size, device):
    ys, xs = torch.meshgrid(torch.arange(size, device=device), torch.arange(size, device=device), indexing="ij")
    x, y = xs + 0.5, ys + 0.5
    return (((x - 0.53 * size) ** 2 + (y - 0.48 * size) ** 2).sqrt() < 0.38 * size).float()


def softras_silhouette(torch, uv, faces, size, sigma=1.0, tile=64):
    """SoftRas-style silhouette: D_j(p) = sigmoid(sign * d^2 / sigma) per triangle,
    image = 1 - prod_j (1 - D_j), evaluated per tile over the triangles near it."""
    tri = uv[faces]  # F x 3 x 2
    lo, hi = tri.min(dim=1).values, tri.max(dim=1).values
    rows = []
    margin = 3.0 * math.sqrt(sigma)
    for ty in range(0, size, tile):
        row = []
        for tx in range(0, size, tile):
            near = (hi[:, 0] > tx - margin) & (lo[:, 0] < tx + tile + margin) & \
                   (hi[:, 1] > ty - margin) & (lo[:, 1] < ty + tile + margin)
            t = tri[near]
            ys, xs = torch.meshgrid(torch.arange(ty, ty + tile, device=uv.device),
                                    torch.arange(tx, tx + tile, device=uv.device), indexing="ij")
            p = torch.stack([xs + 0.5, ys + 0.5], dim=-1).reshape(-1, 1, 2).float()
            if t.shape[0] == 0:
                row.append(torch.zeros(tile, tile, device=uv.device))
                continue
            a, b, c = t[None, :, 0], t[None, :, 1], t[None, :, 2]

            def edge(u, v):
                return (v[..., 0] - u[..., 0]) * (p[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (p[..., 0] - u[..., 0])

            area = (b - a)[..., 0] * (c - a)[..., 1] - (b - a)[..., 1] * (c - a)[..., 0]
            inside = (edge(a, b) * area >= 0) & (edge(b, c) * area >= 0) & (edge(c, a) * area >= 0)

            def seg_d2(u, v):
                uv_ = v - u
                s = ((p - u) * uv_).sum(-1) / (uv_ * uv_).sum(-1).clamp_min(1e-12)
                q = u + s.clamp(0, 1)[..., None] * uv_
                return ((p - q) ** 2).sum(-1)

            d2 = torch.minimum(torch.minimum(seg_d2(a, b), seg_d2(b, c)), seg_d2(c, a))
            d = torch.sigmoid(torch.where(inside, d2, -d2) / sigma)
            row.append((1 - torch.prod(1 - d, dim=1)).reshape(tile, tile))
        rows.append(torch.cat(row, dim=1))
    return torch.cat(rows, dim=0)[:size, :size]


def timed(torch, device, fn):
    if device.startswith("cuda"):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        out = fn()
        end.record()
        torch.cuda.synchronize()
        return out, start.elapsed_time(end)
    started = time.perf_counter()
    out = fn()
    return out, (time.perf_counter() - started) * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--max-vertices", type=int, default=1_000_000)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--peers", default="pytorch3d,softras")
    args = parser.parse_args()
    try:
        import torch
    except ImportError:
        sys.exit("bench_peers.py needs torch (pip install torch), and pytorch3d for that peer")
    import os
    os.makedirs(args.out, exist_ok=True)
    device = args.device if (args.device == "cpu" or torch.cuda.is_available()) else "cpu"
    name = torch.cuda.get_device_name() if device.startswith("cuda") else "cpu"
    target = mask(torch, args.size, device)
    for peer in args.peers.split(","):
        rows = []
        for vertices in [1_000, 10_000, 100_000, 1_000_000]:
            if vertices > args.max_vertices:
                continue
            pos, faces = sphere(vertices)
            positions = torch.tensor(pos, device=device, dtype=torch.float32, requires_grad=True)
            faces_t = torch.tensor(faces, device=device, dtype=torch.int64)
            if peer == "pytorch3d":
                try:
                    from pytorch3d.renderer import MeshRasterizer, RasterizationSettings, PerspectiveCameras
                    from pytorch3d.structures import Meshes
                except ImportError:
                    print("pytorch3d is not installed: skipping that peer", file=sys.stderr)
                    break
                f = 2.0 * args.size
                cameras = PerspectiveCameras(focal_length=((f, f),), principal_point=((args.size / 2, args.size / 2),),
                                             image_size=((args.size, args.size),), in_ndc=False, device=device)
                rasterizer = MeshRasterizer(cameras=cameras, raster_settings=RasterizationSettings(
                    image_size=args.size, faces_per_pixel=1, blur_radius=0.0))

                def forward():
                    cam = camera_points(torch, positions, device)
                    # PyTorch3D's camera looks along +z with x left, y up: flip x and y.
                    cam = cam * torch.tensor([-1.0, -1.0, 1.0], device=device)
                    frags = rasterizer(Meshes(verts=[cam], faces=[faces_t]))
                    # Hard rasterization has no silhouette gradient; the timed backward
                    # goes through the interpolated depth (zbuf), as PyTorch3D offers.
                    silhouette = (frags.pix_to_face[0, ..., 0] >= 0).float()
                    depth = frags.zbuf[0, ..., 0] * silhouette
                    return ((depth - 0.6 * target) ** 2).mean()
            else:
                def forward():
                    cam = camera_points(torch, positions, device)
                    image = softras_silhouette(torch, project(torch, cam, args.size), faces_t, args.size)
                    return ((image - target) ** 2).mean()
            forwards, backwards = [], []
            for repeat in range(args.repeats + 1):
                positions.grad = None
                loss, ms_f = timed(torch, device, forward)
                _, ms_b = timed(torch, device, loss.backward)
                if repeat:
                    forwards.append(ms_f)
                    backwards.append(ms_b)
            row = (len(pos), len(faces), args.size, args.size, statistics.median(forwards),
                   statistics.median(backwards), "", f"{peer} on {name}")
            print(",".join(str(v) for v in row), flush=True)
            rows.append(row)
        if rows:
            path = os.path.join(args.out, f"{peer}.csv")
            with open(path, "w") as out:
                out.write("vertices,faces,width,height,forward_ms,backward_ms,plain_ms,device\n")
                for row in rows:
                    out.write(",".join(f"{v:.4f}" if isinstance(v, float) else str(v) for v in row) + "\n")
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
