"""Bad input raises ValueError naming the argument (never a crash), any layout of a valid
array works, two threads may call at once, and calls do not leak memory."""

import threading

import numpy as np
import pytest

import vkdr
from conftest import K, POSE, SIZE


@pytest.fixture(scope="module")
def scene(device, mesh):
    vertices, faces = mesh
    ids, _, _ = device.rasterize(vertices, faces, K, SIZE, POSE + np.array([0.004, 0, 0.01, 0, 0, 0]))
    return vertices, faces, (ids > 0).astype(np.float32)


def call(device, scene, **change):
    vertices, faces, mask = scene
    args = dict(vertices=vertices, faces=faces, K=K, size=SIZE, pose=POSE, mask=mask)
    args.update(change)
    return device.loss_and_grad(**args)


@pytest.mark.parametrize(
    "argument, value, message",
    [
        ("vertices", lambda v, f, m: v[:, :2], r"vertices: expected shape \(V, 3\)"),
        ("vertices", lambda v, f, m: v.astype(np.complex64), "vertices: dtype complex64"),
        ("vertices", lambda v, f, m: v > 0, "vertices: dtype bool is not a number"),
        ("vertices", lambda v, f, m: np.where(np.arange(len(v))[:, None] == 3, np.nan, v), "vertices: value NaN at flat index 9"),
        ("vertices", lambda v, f, m: "not numbers", "vertices"),
        ("faces", lambda v, f, m: f + len(v), "faces: face 0 has index"),
        ("faces", lambda v, f, m: f - 1, "faces: face 0 has index -1"),
        ("faces", lambda v, f, m: f.astype(np.float64), "faces: dtype float64 is not an integer"),
        ("faces", lambda v, f, m: f[:, :2], r"faces: expected shape \(F, 3\)"),
        ("faces", lambda v, f, m: f[:0], "faces: no triangles"),
        ("mask", lambda v, f, m: m.T, r"mask: expected shape \(80, 96\)"),
        ("mask", lambda v, f, m: np.full_like(m, np.inf), "mask: value inf at flat index 0"),
        ("pose", lambda v, f, m: POSE[:5], r"pose: expected shape \(6,\)"),
        ("pose", lambda v, f, m: np.array([0, 0, np.nan, 0, 0, 0.0]), "pose: value NaN at flat index 2"),
        ("K", lambda v, f, m: np.array([[110.0, 1.0, 48.0], [0, 110.0, 40.0], [0, 0, 1]]), "K: expected"),
        ("K", lambda v, f, m: np.eye(2), r"K: expected shape \(3, 3\)"),
        ("K", lambda v, f, m: np.array([110.0, -5.0, 48.0, 40.0]), "K and size"),
        ("size", lambda v, f, m: (-96, 80), "size: expected"),
        ("size", lambda v, f, m: (96, 80, 3), r"size: expected \(width, height\)"),
        ("size", lambda v, f, m: (96.0, 80.5), "size: dtype float64 is not an integer"),
        ("loss", lambda v, f, m: "l2", "loss: .*unknown loss 'l2'"),
        ("depth", lambda v, f, m: np.zeros((3, 3), np.float32), r"depth: expected shape \(80, 96\)"),
        ("depth_sigma", lambda v, f, m: -1.0, "depth_sigma, depth_weight or occlusion"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(device, scene, argument, value, message):
    v, f, m = scene
    change = {argument: value(v, f, m)}
    if argument == "depth_sigma":
        change["depth"] = np.zeros_like(m)
    with pytest.raises(ValueError, match=message):
        call(device, scene, **change)


def test_any_layout_gives_the_same_result(device, scene):
    vertices, faces, mask = scene
    expected = call(device, scene)
    wide = np.zeros((len(vertices), 6), np.float64)
    wide[:, ::2] = vertices
    fortran = np.asfortranarray(vertices)
    readonly = vertices.copy()
    readonly.flags.writeable = False
    readonly_mask = mask.copy()
    readonly_mask.flags.writeable = False
    for v, m, f in [
        (wide[:, ::2], mask, faces),  # strided, float64
        (fortran, mask, faces.astype(np.uint32)),
        (readonly, readonly_mask, faces.astype(np.int32)),
        (vertices.tolist(), mask.astype(bool), faces.tolist()),  # lists, bool mask
        (vertices, np.asfortranarray(mask.astype(np.uint8)), faces[::1]),
    ]:
        loss, grad_vertices, grad_pose = call(device, scene, vertices=v, mask=m, faces=f)
        assert loss == expected[0]
        assert np.array_equal(grad_vertices, expected[1]) and np.array_equal(grad_pose, expected[2])


def test_everyday_values_are_taken_as_meant(device, scene):
    """Integers and lists where numbers and matrices are meant, a size as a list, and a
    mask as 0/255 or 0/1 integers: the same result as float arrays and a 0/1 float mask
    (a mask is object where above 0, as the command line reads a PNG)."""
    vertices, faces, mask = scene
    expected = call(device, scene)
    integer_K = np.array([[110, 0, 48], [0, 110, 40], [0, 0, 1]])
    for change in [
        dict(K=integer_K),
        dict(K=integer_K.tolist()),
        dict(pose=POSE.tolist()),
        dict(size=list(SIZE)),
        dict(size=np.array(SIZE)),
        dict(mask=(mask * 255).astype(np.uint8)),
        dict(mask=(mask * 255).astype(np.float32)),
        dict(mask=mask.astype(np.int64)),
    ]:
        loss, grad_vertices, grad_pose = call(device, scene, **change)
        assert loss == expected[0], change
        assert np.array_equal(grad_vertices, expected[1]) and np.array_equal(grad_pose, expected[2])
    loss, _, _ = call(device, scene, pose=np.array([0, 0, 1, 0, 0, 0]))
    assert np.isfinite(loss)


def test_a_forked_child_is_refused_and_makes_its_own(device, scene):
    """A Device used in a child forked after it was made raises RuntimeError at once (no
    hang); the default device is made anew in the child and works."""
    import os
    import time

    call(device, scene)  # the parent's device in use before the fork
    pid = os.fork()
    if pid == 0:
        code = 3
        try:
            try:
                call(device, scene)
                code = 1
            except RuntimeError as e:
                code = 0 if "forked child" in str(e) else 2
            if code == 0:
                vertices, faces, mask = scene
                loss = vkdr.default_device().loss_and_grad(vertices, faces, K, SIZE, POSE, mask)[0]
                code = 0 if np.isfinite(loss) else 4
        finally:
            os._exit(code)
    deadline = time.monotonic() + 60
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            pytest.fail("the forked child hung")
        time.sleep(0.1)
    assert os.waitstatus_to_exitcode(status) == 0


def test_device_errors_are_runtime_errors(device, scene):
    vertices, faces, _ = scene
    width = device.limits["max_image_dimension_2d"] + 1
    with pytest.raises(RuntimeError, match="device limit exceeded"):
        device.rasterize(vertices, faces, K, (width, 2), POSE)
    with pytest.raises(RuntimeError, match="no suitable Vulkan device"):
        vkdr.Device("no such device name")


def test_register_refuses_bad_options(device, space, scene):
    _, _, mask = scene
    with pytest.raises(TypeError, match="unexpected keyword argument 'iteration'"):
        device.register(space, mask, K, SIZE, POSE, iteration=5)
    with pytest.raises(ValueError, match="starts: turns the starting pose"):
        device.register(space, mask, K, SIZE, POSE, starts=3)
    with pytest.raises(ValueError, match="starts must be 1 to 8"):
        device.register(space, mask, K, SIZE, POSE, optimize_pose=True, starts=9)
    with pytest.raises(ValueError, match="code_prior"):
        device.register(space, mask, K, SIZE, POSE, code_prior=2.0)
    with pytest.raises(ValueError, match="needs the observed depth"):
        device.register(space, mask, K, SIZE, POSE, optimize_pose=True, gravity="from-depth")
    with pytest.raises(ValueError, match=r"code: expected shape \(3,\)"):
        space.vertices(np.zeros(4))
    with pytest.raises(ValueError, match="the mask shows nothing of the object"):
        device.register(space, np.zeros_like(mask), K, SIZE, POSE, optimize_pose=True)
    with pytest.raises(ValueError, match=r"views\[0\]: has no \"mask\""):
        device.register(space, mask, K, SIZE, POSE, views=[{"K": K, "size": SIZE, "from_first": np.zeros(6)}])


def test_two_threads_calling_at_once(device, scene):
    expected = call(device, scene)
    results, errors = [], []

    def work():
        try:
            for _ in range(20):
                results.append(call(device, scene))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(results) == 40
    for loss, grad_vertices, grad_pose in results:
        assert loss == expected[0] and np.array_equal(grad_vertices, expected[1])


def resident_bytes():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


def test_a_thousand_calls_keep_their_memory(device, scene):
    for _ in range(50):  # the allocator's pools and Python's arenas settle first
        call(device, scene)
    before = resident_bytes()
    for _ in range(1000):
        call(device, scene)
    grown = resident_bytes() - before
    assert grown < 10 * 2**20, f"1000 calls grew the process by {grown / 2**20:.1f} MiB"
