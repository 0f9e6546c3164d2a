"""The same silhouette fit with vkdr.torch and with Mitsuba 3: a pose from a mask.

    pip install ./bindings/python torch mitsuba
    python tools/peers/fit_pose_peers.py [--steps 300] [--spp 8] [--out DIR]

Dr.Jit's CPU backend compiles with the system's libLLVM; Debian 12's LLVM 15 (lavapipe's)
fails on its kernels ("Cannot select: fmaximum"), so give it a newer one:
`apt-get install libllvm19` and `DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1`.

The problem is `examples/python/fit_pose.py`'s: an asymmetric block with a handle and a
spout, 192 x 192 pixels, fx = fy = 300, its mask at a true pose, and a start 19 mm and 12
degrees away. Both renderers follow the mean squared error of their antialiased coverage
against the binary mask *they* render at the true pose (so neither pays for the other's
pixel conventions; the script checks that the two masks agree), with the same torch Adam (1e-3
for metres, 1e-2 for radians, a cosine schedule) for the same steps:

- vkdr: `vkdr.torch.silhouette_loss` (exact edge gradients, one sample per pixel);
- Mitsuba 3 (`llvm_ad_rgb`, its CPU backend): the mesh as an area emitter on black, the
  `direct_projective` integrator (projective sampling of the silhouette edges, Mitsuba
  3's differentiable visibility), `--spp` samples per pixel, a box filter, the mask
  where more than half a pixel is covered (256 samples).

Prints and writes (`--out`: fit_pose_peers.json and .md) each one's median time per
step, its first step (Mitsuba compiles its kernels then), and the final translation and
rotation errors. Not part of CI (Mitsuba is large).
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "examples" / "python"))
from fit_pose import errors, object_mesh  # noqa: E402

SIZE = (192, 192)
K = np.array([[300.0, 0, 96], [0, 300.0, 96], [0, 0, 1]])
TRUTH = np.array([0.01, -0.005, 0.45, 0.35, -0.5, 0.2])
START = TRUTH + np.array([0.015, -0.012, 0.0, 0.12, -0.1, 0.14])


def adam(steps):
    translation = torch.tensor(START[:3], requires_grad=True)
    axis_angle = torch.tensor(START[3:], requires_grad=True)
    optimizer = torch.optim.Adam([{"params": [translation], "lr": 1e-3}, {"params": [axis_angle], "lr": 1e-2}])
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 0.5 * (1 + np.cos(np.pi * k / steps)))
    return translation, axis_angle, optimizer, schedule


def fit(name, loss_and_grad, steps):
    """Adam over `steps` steps; loss_and_grad(pose) -> (loss, d loss / d pose (6,))."""
    translation, axis_angle, optimizer, schedule = adam(steps)
    times = []
    for step in range(steps):
        pose = torch.cat([translation, axis_angle]).detach().numpy()
        began = time.perf_counter()
        loss, grad = loss_and_grad(pose, step)
        times.append(1e3 * (time.perf_counter() - began))
        optimizer.zero_grad()
        translation.grad = torch.tensor(grad[:3], dtype=torch.float64)
        axis_angle.grad = torch.tensor(grad[3:], dtype=torch.float64)
        optimizer.step()
        schedule.step()
        if step % 50 == 0:
            t, r = errors(pose, TRUTH)
            print(f"  {name} step {step:3d}: loss {loss:.3e}, {t:.2f} mm, {r:.2f} deg", file=sys.stderr)
    pose = torch.cat([translation, axis_angle]).detach().numpy()
    t, r = errors(pose, TRUTH)
    return {
        "renderer": name,
        "first_step_ms": times[0],
        "median_step_ms": statistics.median(times[1:]),
        "translation_error_mm": t,
        "rotation_error_deg": r,
    }


def vkdr_fit(vertices, faces, steps):
    import vkdr
    from vkdr.torch import silhouette_loss

    device = vkdr.Device()
    ids, _, _ = device.rasterize(vertices, faces, K, SIZE, TRUTH)
    mask = ids > 0
    v = torch.from_numpy(vertices)

    def loss_and_grad(pose, _step):
        p = torch.tensor(pose, requires_grad=True)
        loss = silhouette_loss(v, p, faces, K, SIZE, mask, device=device)
        loss.backward()
        return loss.item(), p.grad.numpy()

    result = fit("vkdr", loss_and_grad, steps)
    result["device"] = device.name
    return result, mask


def mitsuba_fit(vertices, faces, steps, spp, out):
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    mi.set_log_level(mi.LogLevel.Error)
    ply = out / "object.ply"
    with open(ply, "w") as f:
        f.write(f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n")
        f.write(f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
        f.writelines(f"{x} {y} {z}\n" for x, y, z in vertices)
        f.writelines(f"3 {a} {b} {c}\n" for a, b, c in faces)
    fov = float(np.degrees(2 * np.arctan(SIZE[0] / 2 / K[0, 0])))
    scene = mi.load_dict({
        "type": "scene",
        # No indirect light, so no indirect silhouettes to sample (sppi 0).
        "integrator": {"type": "direct_projective", "sppi": 0},
        "sensor": {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "x",
            # Looking along +z with y down the image (vkdr's and OpenCV's camera frame).
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, -1, 0]),
            "film": {"type": "hdrfilm", "width": SIZE[0], "height": SIZE[1], "rfilter": {"type": "box"}, "pixel_format": "luminance", "sample_border": True},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "object": {
            "type": "ply",
            "filename": str(ply),
            "face_normals": True,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}},
        },
    })
    params = mi.traverse(scene)
    rest = dr.unravel(mi.Point3f, params["object.vertex_positions"])

    def place(pose):
        t = mi.Vector3f(*[float(x) for x in pose[:3]])
        w = mi.Vector3f(*[float(x) for x in pose[3:]])
        return t, w

    def transform(t, w):
        angle = dr.norm(w)
        axis = w / angle
        trafo = mi.Transform4f().translate(t) @ mi.Transform4f().rotate(axis, angle * 180.0 / dr.pi)
        params["object.vertex_positions"] = dr.ravel(trafo @ rest)
        params.update()

    transform(*place(TRUTH))
    coverage = mi.render(scene, params, spp=256, seed=12345)
    # A mask, as vkdr's: a pixel is object where more than half of it is covered.
    target = mi.TensorXf(dr.select(coverage > 0.5, 1.0, 0.0))

    def loss_and_grad(pose, step):
        t, w = place(pose)
        dr.enable_grad(t, w)
        transform(t, w)
        image = mi.render(scene, params, spp=spp, seed=step)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.backward(loss)
        grad = np.concatenate([np.array(dr.grad(t)).ravel(), np.array(dr.grad(w)).ravel()])
        return float(np.array(loss).ravel()[0]), grad

    result = fit("Mitsuba 3", loss_and_grad, steps)
    result["device"] = f"llvm_ad_rgb (CPU), {spp} spp"
    return result, np.array(target)[..., 0] > 0.5


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--out", type=Path, default=Path("fit_pose_peers"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    vertices, faces = object_mesh()
    start_t, start_r = errors(START, TRUTH)
    print(f"start: {start_t:.1f} mm, {start_r:.1f} deg from the true pose", file=sys.stderr)
    ours, our_mask = vkdr_fit(vertices, faces, args.steps)
    theirs, their_mask = mitsuba_fit(vertices, faces, args.steps, args.spp, args.out)
    agreement = float((our_mask & their_mask).sum() / (our_mask | their_mask).sum())
    rows = [ours, theirs]
    lines = [
        f"Pose from a mask, 192 x 192, {args.steps} Adam steps, start {start_t:.1f} mm and {start_r:.1f} deg off; "
        f"the two renderers' masks at the true pose agree at IoU {agreement:.4f}.",
        "",
        "| renderer | device | first step (ms) | median step (ms) | translation error (mm) | rotation error (deg) |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['renderer']} | {r['device']} | {r['first_step_ms']:.1f} | {r['median_step_ms']:.1f} | "
        f"{r['translation_error_mm']:.2f} | {r['rotation_error_deg']:.2f} |"
        for r in rows
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    (args.out / "fit_pose_peers.md").write_text(text)
    (args.out / "fit_pose_peers.json").write_text(json.dumps({"mask_iou": agreement, "steps": args.steps, "rows": rows}, indent=2) + "\n")
    if agreement < 0.98:
        print(f"the two masks at the true pose differ (IoU {agreement:.4f}): not the same scene", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
