"""The module against the command line (the same arrays, byte for byte where the command
line writes them), the pose gradient against central differences, and the registration's
results."""

import signal

import numpy as np
import pytest

import vkdr
from conftest import K, POSE, SIZE, camera_flags, lumpy, read_json, sphere, write_obj, write_png


def test_device_names_itself(device):
    assert device.name and device.name in repr(device)
    assert device.limits["max_image_dimension_2d"] >= 4096
    assert device.kind in ("discrete GPU", "integrated GPU", "virtual GPU", "CPU", "other")


def test_rasterize_agrees_with_the_command_line(device, mesh, cli, tmp_path):
    vertices, faces = mesh
    write_obj(tmp_path / "m.obj", vertices, faces)
    cli("render", tmp_path / "m.obj", *camera_flags(), "--raw", "--out", tmp_path / "out")
    ids, bary, depth = device.rasterize(vertices, faces, K, SIZE, POSE)
    for name, array in [("ids", ids), ("bary", bary), ("depth", depth)]:
        expected = np.load(tmp_path / "out" / f"{name}.npy")
        assert array.dtype == expected.dtype and array.shape == expected.shape, name
        assert array.tobytes() == expected.tobytes(), name
    assert (ids > 0).sum() > 500  # the sphere covers a disc of about 17 px radius

    # Several poses at once: each view as alone.
    moved = POSE + np.array([0.01, 0, 0.05, 0, 0.2, 0])
    all_ids, all_bary, all_depth = device.rasterize(vertices, faces, K, SIZE, np.stack([POSE, moved]))
    assert all_ids.shape == (2, SIZE[1], SIZE[0]) and all_bary.shape == (2, SIZE[1], SIZE[0], 2)
    assert np.array_equal(all_ids[0], ids) and np.array_equal(all_depth[0], depth)
    assert np.array_equal(all_ids[1], device.rasterize(vertices, faces, K, SIZE, moved)[0])
    # The ids alone: the same bytes, one pose or several.
    assert device.visibility(vertices, faces, K, SIZE, POSE).tobytes() == ids.tobytes()
    assert device.visibility(vertices, faces, K, SIZE, np.stack([POSE, moved])).tobytes() == all_ids.tobytes()


def left_jacobian(r):
    """d(rotation increment on the left)/d(axis-angle), as the module's docs give it."""
    a = np.linalg.norm(r)
    k = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    return np.eye(3) + (1 - np.cos(a)) / a**2 * k + (a - np.sin(a)) / a**3 * k @ k


def test_loss_and_grad_agree_with_the_command_line(device, mesh, cli, tmp_path):
    vertices, faces = mesh
    ids, _, _ = device.rasterize(vertices, faces, K, SIZE, POSE + np.array([0.006, 0.004, 0.01, 0.1, 0, 0]))
    write_png(tmp_path / "mask.png", ids > 0)
    write_obj(tmp_path / "m.obj", vertices, faces)
    cli("grad", tmp_path / "m.obj", "--observed", tmp_path / "mask.png", *camera_flags(), "--out", tmp_path / "out")
    loss, grad_vertices, grad_pose = device.loss_and_grad(vertices, faces, K, SIZE, POSE, (ids > 0).astype(np.float32))
    assert np.float32(loss) == np.float32(read_json(tmp_path / "out" / "loss.json")["loss"])
    expected = np.load(tmp_path / "out" / "vertex_grad.npy")
    assert grad_vertices.dtype == np.float32 and grad_vertices.tobytes() == expected.tobytes()
    # The command line writes the engine's dL/dt and dL/d(rotation increment); the module
    # gives dL/d(its pose numbers).
    engine = np.load(tmp_path / "out" / "pose_grad.npy").astype(np.float64)
    assert np.array_equal(grad_pose[:3], engine[:3])
    np.testing.assert_allclose(grad_pose[3:], left_jacobian(POSE[3:]).T @ engine[3:], rtol=1e-6, atol=1e-9)
    assert np.abs(grad_vertices).max() > 0 and np.abs(grad_pose).max() > 0


def test_pose_gradient_matches_central_differences(device):
    # An ellipsoid off the object's origin, at 256 x 256, so that turning it moves its
    # silhouette; steps of a quarter pixel (visibility changes make the loss piecewise
    # smooth: smaller steps see single pixels switch).
    vertices, faces = sphere(rings=24, segments=48)
    vertices = vertices * np.float32([1.6, 1.0, 0.6]) + np.float32([0.03, 0.0, 0.0])
    size, K = (256, 256), np.array([[300.0, 0, 128], [0, 300.0, 128], [0, 0, 1]])
    pose = np.array([0.004, -0.003, 0.4, 0.5, -0.6, 0.3])
    ids, _, _ = device.rasterize(vertices, faces, K, size, pose + np.array([0.005, -0.004, 0.01, 0.1, 0.08, -0.05]))
    mask = ids > 0
    _, _, grad = device.loss_and_grad(vertices, faces, K, size, pose, mask)
    h = np.array([3e-4, 3e-4, 1e-3, 1.2e-3, 1.2e-3, 1.2e-3])
    numeric = np.zeros(6)
    for k in range(6):
        step = np.zeros(6)
        step[k] = h[k]
        plus = device.loss_and_grad(vertices, faces, K, size, pose + step, mask)[0]
        minus = device.loss_and_grad(vertices, faces, K, size, pose - step, mask)[0]
        numeric[k] = (plus - minus) / (2 * h[k])
    relative = lambda got, want: np.linalg.norm(got - want) / np.linalg.norm(want)
    assert relative(grad[:3], numeric[:3]) < 0.06
    assert relative(grad[3:], numeric[3:]) < 0.02
    # The check tells the pose's numbers from the engine's rotation increment.
    increment = np.linalg.solve(left_jacobian(pose[3:]).T, grad[3:])
    assert relative(increment, numeric[3:]) > 0.05


def test_cpd_agrees_with_the_command_line(device, mesh, cli, tmp_path):
    source = mesh[0].astype(np.float64)
    target = lumpy(source, 2)[::2]  # every other point
    np.save(tmp_path / "source.npy", source)
    np.save(tmp_path / "target.npy", target)
    cli("cpd", tmp_path / "source.npy", tmp_path / "target.npy", "--out", tmp_path / "out")
    deformed, w, log = vkdr.cpd(source, target, device=device)
    assert deformed.tobytes() == np.load(tmp_path / "out" / "deformed.npy").tobytes()
    assert w.tobytes() == np.load(tmp_path / "out" / "W.npy").tobytes()
    assert log["iterations"] == read_json(tmp_path / "out" / "log.json")["iterations"]
    # The deformed source lies on the instance that the target samples (every other
    # point of it), far nearer than the undeformed source does.
    surface = lumpy(source, 2)
    nearest = lambda points: np.sqrt(((points[:, None, :] - surface[None]) ** 2).sum(-1)).min(1).mean()
    assert nearest(deformed) < 1e-3 < 0.2 * nearest(source)


def test_shape_space_agrees_with_the_command_line(device, mesh, cli, tmp_path):
    vertices, faces = mesh
    category = tmp_path / "lumps"
    (category / "train").mkdir(parents=True)
    (category / "test").mkdir()
    write_obj(category / "canonical.obj", vertices, faces)
    instances = [lumpy(vertices, k).astype(np.float32) for k in range(4)]
    for k, points in enumerate(instances):
        write_obj(category / "train" / f"instance{k}.obj", points, faces)
    write_obj(category / "test" / "test0.obj", lumpy(vertices, 7), faces)
    cli("shape-space", category, "--dims", "3", "--out", tmp_path / "cli.npz")
    # The command line's category has no info.json: y up, as the module is told.
    space = vkdr.ShapeSpace.build(vertices, faces, instances, dims=3, category="lumps",
                                  names=[f"instance{k}" for k in range(4)], device=device, up=[0, 1, 0])
    space.save(tmp_path / "module.npz")
    assert (tmp_path / "module.npz").read_bytes() == (tmp_path / "cli.npz").read_bytes()
    # A bad up axis is refused before the build starts (no instance registered).
    built = []
    for up in ([0, 0, 0], [np.nan, 1, 0]):
        with pytest.raises(ValueError, match="up"):
            vkdr.ShapeSpace.build(vertices, faces, instances, dims=3, device=device, up=up,
                                  progress=lambda done, total: built.append(done))
    assert built == []


def test_shape_space_round_trip(space, tmp_path):
    path = tmp_path / "lumps.npz"
    space.save(path)
    again = vkdr.ShapeSpace.load(path)
    assert (again.dims, again.category) == (3, "lumps")
    code = np.array([0.01, -0.02, 0.005])
    assert np.array_equal(again.vertices(code), space.vertices(code))
    again.save(tmp_path / "again.npz")
    assert (tmp_path / "again.npz").read_bytes() == path.read_bytes()
    # The training instances' codes reproduce them: their spread is 1 SD per dimension.
    deviations = np.array([again.code_in_deviations(c) for c in again.training_codes])
    np.testing.assert_allclose(deviations.std(0, ddof=1), 1.0, rtol=1e-6)


def observe(device, space, k, pose):
    """Mask and depth of training instance k (through the space's own faces)."""
    vertices = lumpy(space.canonical, k)
    ids, _, depth = device.rasterize(vertices, space.faces, K, SIZE, pose)
    return (ids > 0).astype(np.float32), depth


@pytest.mark.parametrize("optimize_pose", [False, True])
def test_register_agrees_with_the_command_line(device, space, cli, tmp_path, optimize_pose):
    space.save(tmp_path / "space.npz")
    mask, depth = observe(device, space, 3, POSE)
    write_png(tmp_path / "mask.png", mask)
    np.save(tmp_path / "depth.npy", depth)
    start = POSE + (np.array([0.004, -0.003, 0.0, 0.05, 0.04, -0.03]) if optimize_pose else 0)
    flags = ["--optimize-pose"] if optimize_pose else []
    cli("register", "--space", tmp_path / "space.npz", "--observed", tmp_path / "mask.png",
        "--observed-depth", tmp_path / "depth.npy", *camera_flags(pose=start), *flags, "--out", tmp_path / "out")
    result = device.register(space, mask, K, SIZE, start, depth=depth, optimize_pose=optimize_pose)
    assert result.code.tobytes() == np.load(tmp_path / "out" / "code.npy").tobytes()
    pose = read_json(tmp_path / "out" / "pose.json")
    assert list(result.pose) == pose["translation"] + pose["rotation"]
    assert result.loss == pose["loss"] and result.scale == pose["scale"] == 1.0
    assert list(result.code_sd) == pose["code_sd"]
    # The fit explains the observation better than the mean shape at its start (after the
    # stages before it, whose losses are other objectives': with the pose free the pose
    # alignment's, with it known the mask alone first).
    names = [name for name, _ in result.stages]
    assert names[0] == ("pose alignment" if optimize_pose else "mask first")
    fit_at = sum(count for name, count in result.stages[:names.index("fit")]) if "fit" in names else 15
    assert result.loss < result.losses[fit_at]
    if not optimize_pose:
        # The stage asked away (as --mask-first 0 does): the fit alone.
        plain = device.register(space, mask, K, SIZE, start, depth=depth, mask_first=0, hold_unseen=False)
        assert plain.stages == [("fit", len(plain.losses))]
    # The kept iterations are the stages' and the losses'; with the pose free the five
    # starts' turn checks are evaluations besides.
    assert result.iterations == len(result.losses) == sum(count for _, count in result.stages)
    assert result.evaluations > result.iterations if optimize_pose else result.evaluations == result.iterations
    np.testing.assert_allclose(result.vertices, space.vertices(result.code), rtol=0, atol=1e-12)
    assert result.faces.shape == space.faces.shape


def test_register_batch_is_each_registration(device, space):
    poses = np.stack([POSE, POSE + np.array([0.01, 0.0, 0.02, 0.0, 0.3, 0.0])])
    looks = [observe(device, space, k, p) for k, p in zip((1, 4), poses)]
    masks = np.stack([m for m, _ in looks])
    batch = device.register_batch(space, masks, K, SIZE, poses)
    assert len(batch) == 2
    for (mask, _), pose, together in zip(looks, poses, batch):
        alone = device.register(space, mask, K, SIZE, pose)
        np.testing.assert_allclose(together.code, alone.code, rtol=1e-6, atol=1e-9)
        assert together.loss < together.losses[0]


def test_progress_is_reported_and_its_exceptions_raised(device, space, mesh):
    mask, _ = observe(device, space, 2, POSE)
    seen = []
    result = device.register(space, mask, K, SIZE, POSE, progress=lambda done, total: seen.append((done, total)))
    # The total is the most it can take: the fit's 30 iterations, and as many again where
    # it holds the directions of the code the mask hardly constrains.
    assert seen and all(0 < done <= total == 60 for done, total in seen)
    assert [d for d, _ in seen] == sorted(d for d, _ in seen) and seen[-1][0] == result.iterations

    # A callback that raises stops the registration at that chunk (it is called once,
    # where the run above reported len(seen) chunks), and its exception is raised.
    calls = []

    def stop(done, total):
        calls.append(done)
        raise KeyError("stop here")

    with pytest.raises(KeyError, match="stop here"):
        device.register(space, mask, K, SIZE, POSE, progress=stop)
    assert len(seen) > 1 and calls == [seen[0][0]]
    # Ctrl-C (SIGINT) while the callback runs stops it the same way, as KeyboardInterrupt.
    interrupts = []

    def interrupt(done, total):
        interrupts.append(done)
        signal.raise_signal(signal.SIGINT)

    # Python turns SIGINT into KeyboardInterrupt only where SIGINT was not ignored at its
    # start (a shell without job control starts background commands so): install it here.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            device.register(space, mask, K, SIZE, POSE, progress=interrupt)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert interrupts == [seen[0][0]]
    instances = []
    vertices, faces = mesh
    vkdr.ShapeSpace.build(vertices, faces, [lumpy(vertices, k) for k in range(3)], dims=2, device=device,
                          progress=lambda done, total: instances.append((done, total)))
    assert instances[-1] == (3, 3)
    iterations = []
    vkdr.cpd(vertices, lumpy(vertices, 1), device=device, progress=lambda i, total: iterations.append(i))
    assert iterations and iterations == sorted(iterations)


def test_calls_without_a_device_share_the_default_one(mesh):
    vertices, _ = mesh
    vkdr.cpd(vertices, lumpy(vertices, 1))  # on the default device
    shared = vkdr.default_device()
    assert shared.engine_ms > 0, "the default device ran the cpd"
    assert vkdr.Device().engine_ms == 0.0, "a new device has run nothing"
    assert shared.name == vkdr.default_device().name


def test_spaces_and_registrations_pickle(device, space, tmp_path):
    """A ShapeSpace pickles as its .npz file's bytes (the description inside, so the .npz
    alone loads), a Registration as its space and numbers: both come back exactly."""
    import pickle

    again = pickle.loads(pickle.dumps(space))
    code = np.array([0.5, -0.2, 0.1])
    assert np.array_equal(again.vertices(code), space.vertices(code))
    assert (again.dims, again.category, again.training_names) == (space.dims, space.category, space.training_names)
    space.save(tmp_path / "lumps.npz")
    (tmp_path / "lumps.npz.json").unlink()
    alone = vkdr.ShapeSpace.load(tmp_path / "lumps.npz")
    assert np.array_equal(alone.vertices(code), space.vertices(code))
    mask, depth = observe(device, space, 2, POSE)
    result = device.register(space, mask, K, SIZE, POSE)
    copy = pickle.loads(pickle.dumps(result))
    for name in ("code", "code_sd", "pose", "vertices", "faces", "losses"):
        assert np.array_equal(getattr(copy, name), getattr(result, name)), name
    assert copy.stages == result.stages == [("fit", len(result.losses))]
    assert (copy.loss, copy.iterations, copy.evaluations, copy.scale) == (result.loss, result.iterations, result.evaluations, result.scale)
    # Every stage's name comes back: with depth the known pose compares the mask first.
    with_depth = device.register(space, mask, K, SIZE, POSE, depth=depth)
    assert with_depth.stages[0][0] == "mask first", with_depth.stages
    assert pickle.loads(pickle.dumps(with_depth)).stages == with_depth.stages
