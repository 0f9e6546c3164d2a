"""Fixtures of the module's tests: the device, small meshes and shape spaces, the `vkdr`
command line (for agreement with the module) and writers of its input files."""

import json
import os
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

import vkdr

ROOT = Path(__file__).resolve().parents[3]

# One camera for the small scenes: 96 x 80 pixels.
SIZE = (96, 80)
K = np.array([[110.0, 0.0, 48.0], [0.0, 110.0, 40.0], [0.0, 0.0, 1.0]])
POSE = np.array([0.004, -0.003, 0.32, 0.3, -0.4, 0.1])


@pytest.fixture(scope="session")
def device():
    return vkdr.Device()


def sphere(radius=0.05, rings=10, segments=16):
    """A UV sphere: vertices (V x 3, float32) and outward faces (F x 3)."""
    vertices = [[0.0, radius, 0.0]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            vertices.append([radius * np.sin(theta) * np.cos(phi), radius * np.cos(theta), radius * np.sin(theta) * np.sin(phi)])
    vertices.append([0.0, -radius, 0.0])
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments
    faces = [[0, ring(1, j + 1), ring(1, j)] for j in range(segments)]
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, b, d], [a, d, c]]
    last = len(vertices) - 1
    faces += [[last, ring(rings - 1, j), ring(rings - 1, j + 1)] for j in range(segments)]
    return np.array(vertices, dtype=np.float32), np.array(faces, dtype=np.int64)


def lumpy(vertices, k):
    """Training instance k of a small category: the sphere stretched and given a bump."""
    v = vertices.astype(np.float64)
    stretch = np.array([1.0 + 0.12 * np.sin(k), 1.0 + 0.1 * np.cos(1.7 * k), 1.0 - 0.08 * np.sin(2.3 * k)])
    bump = 0.01 * (0.5 + 0.5 * np.sin(k)) * np.exp(-((v[:, 0] - 0.05) ** 2) / 0.0004)[:, None] * np.array([1.0, 0.0, 0.0])
    return v * stretch + bump


@pytest.fixture(scope="session")
def mesh():
    return sphere()


@pytest.fixture(scope="session")
def space(device, mesh):
    """A shape space of 5 lumpy spheres, 3 dimensions."""
    vertices, faces = mesh
    instances = [lumpy(vertices, k) for k in range(5)]
    return vkdr.ShapeSpace.build(vertices, faces, instances, dims=3, category="lumps", device=device)


@pytest.fixture(scope="session")
def cli():
    """Runs the `vkdr` command line (VKDR_BIN, or target/release/vkdr that `cargo test
    --release` builds); a missing binary fails the test, it is not skipped."""
    binary = Path(os.environ.get("VKDR_BIN", ROOT / "target" / "release" / "vkdr"))
    if not binary.exists():
        pytest.fail(f"no vkdr binary at {binary}: run `cargo build --release` or set VKDR_BIN")

    def run(*args):
        done = subprocess.run([str(binary), *map(str, args)], capture_output=True, text=True)
        assert done.returncode == 0, f"vkdr {' '.join(map(str, args))} failed:\n{done.stderr}"
        return done.stdout

    return run


def camera_flags(K=K, size=SIZE, pose=POSE):
    """The command line's camera and pose flags, the numbers written exactly."""
    numbers = lambda values: ",".join(repr(float(v)) for v in values)
    return [
        "--intrinsics", numbers([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
        "--size", f"{size[0]}x{size[1]}",
        f"--pose={numbers(pose)}",
    ]


def write_obj(path, vertices, faces):
    """An OBJ whose vertices read back as the same float32 values."""
    lines = ["v " + " ".join(repr(float(c)) for c in v) for v in np.asarray(vertices, dtype=np.float32)]
    lines += ["f " + " ".join(str(int(i) + 1) for i in f) for f in faces]
    Path(path).write_text("\n".join(lines) + "\n")


def write_png(path, image):
    """An 8-bit grey PNG of a (H, W) array (nonzero: 255)."""
    pixels = np.where(np.asarray(image) != 0, 255, 0).astype(np.uint8)
    h, w = pixels.shape
    raw = b"".join(b"\x00" + pixels[r].tobytes() for r in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def read_json(path):
    return json.loads(Path(path).read_text())
