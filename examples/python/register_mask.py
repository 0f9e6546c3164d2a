"""A shape space from a few training shapes, then an unseen shape registered from its mask.

    pip install ./bindings/python && python examples/python/register_mask.py

Five lumpy spheres train a 3-dimensional space; a sixth (between them, not among them) is
rendered at a known pose, and `Device.register` fits the space's code and the pose from
its mask, starting 1 cm and 6 degrees away. Prints the fitted code, the pose error and the
surface error; exit status 1 if the pose ends more than 2 mm away. Typed: `mypy --strict`
checks it against the module's stubs (CI does).
"""

import sys

import numpy as np
import numpy.typing as npt

import vkdr

F64 = npt.NDArray[np.float64]


def sphere(radius: float = 0.05, rings: int = 12, segments: int = 20) -> tuple[F64, npt.NDArray[np.int64]]:
    """A UV sphere: vertices (V, 3) and outward faces (F, 3)."""
    vertices: list[list[float]] = [[0.0, radius, 0.0]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            vertices.append([radius * np.sin(theta) * np.cos(phi), radius * np.cos(theta),
                             radius * np.sin(theta) * np.sin(phi)])
    vertices.append([0.0, -radius, 0.0])

    def ring(i: int, j: int) -> int:
        return 1 + (i - 1) * segments + j % segments

    faces = [[0, ring(1, j + 1), ring(1, j)] for j in range(segments)]
    for i in range(1, rings - 1):
        for j in range(segments):
            faces += [[ring(i, j), ring(i, j + 1), ring(i + 1, j + 1)], [ring(i, j), ring(i + 1, j + 1), ring(i + 1, j)]]
    last = len(vertices) - 1
    faces += [[last, ring(rings - 1, j), ring(rings - 1, j + 1)] for j in range(segments)]
    return np.array(vertices), np.array(faces)


def lumpy(vertices: F64, a: float, b: float) -> F64:
    """The sphere stretched along y by `a` and bulged along x by `b`."""
    out = vertices.copy()
    out[:, 1] *= 1.0 + a
    out[:, 0] *= 1.0 + b * (1.0 + out[:, 1] / 0.05)
    return out


def main() -> int:
    device = vkdr.Device()
    vertices, faces = sphere()
    training = [lumpy(vertices, a, b) for a, b in [(0.0, 0.0), (0.4, 0.0), (-0.3, 0.1), (0.2, 0.3), (0.0, -0.2)]]
    space = vkdr.ShapeSpace.build(vertices, faces, training, dims=3, category="lumps", device=device)
    test = lumpy(vertices, 0.25, 0.12)

    K = np.array([[160.0, 0.0, 64.0], [0.0, 160.0, 48.0], [0.0, 0.0, 1.0]])
    size = (128, 96)
    truth = np.array([0.0, 0.0, 0.35, 0.2, 0.3, 0.0])
    ids, _, _ = device.rasterize(test, faces, K, size, truth)
    mask = ids > 0
    start = truth + np.array([0.01, -0.005, 0.0, 0.0, 0.1, 0.0])
    result = device.register(space, mask, K, size, start, optimize_pose=True)

    pose_error = float(np.linalg.norm(result.pose[:3] - truth[:3]))
    surface_error = float(np.abs(result.vertices - test).mean())
    print(f"{device.name}: code in SD {np.round(result.code_sd, 2)}, {result.iterations} iterations, "
          f"{result.milliseconds:.0f} ms; translation error {1e3 * pose_error:.2f} mm, "
          f"mean vertex error {1e3 * surface_error:.2f} mm")
    return 0 if pose_error < 0.002 else 1


if __name__ == "__main__":
    sys.exit(main())
