"""vkdr: differentiable rasterization and category-level deformable registration on Vulkan.

The engine's calls with NumPy arrays in and out (the work runs on the device with the GIL
released):

    import vkdr
    dev = vkdr.Device()                      # the best Vulkan device
    ids, bary, depth = dev.rasterize(vertices, faces, K, (width, height), pose)
    loss, grad_vertices, grad_pose = dev.loss_and_grad(vertices, faces, K, (width, height), pose, mask)
    space = vkdr.ShapeSpace.load("bottle.npz")
    result = dev.register(space, mask, K, (width, height), pose, optimize_pose=True)

A pose is 6 numbers, object to camera: the translation in metres, then an axis-angle
rotation in radians (camera x right, y down, z forward). K is a 3 x 3 pinhole matrix (or
fx, fy, cx, cy) in pixels, the size (width, height), images (height, width) arrays.
`vkdr.torch` (with PyTorch installed) makes loss_and_grad an autograd function.
Bad input raises ValueError naming the argument; the device's errors and limits raise
RuntimeError. See docs/python.md.
"""

from ._vkdr import (
    UNKNOWN,
    Device,
    Registration,
    ShapeSpace,
    __version__,
    cpd,
    default_device,
    load_mesh,
)

__all__ = [
    "UNKNOWN",
    "Device",
    "Registration",
    "ShapeSpace",
    "__version__",
    "cpd",
    "default_device",
    "load_mesh",
]
