"""vkdr's exact silhouette gradients as a PyTorch autograd function.

    from vkdr.torch import silhouette_loss
    loss = silhouette_loss(vertices, pose, faces, K, (width, height), mask)
    loss.backward()        # vertices.grad (V x 3) and pose.grad (6,) from vkdr

`vertices` (V x 3) and `pose` (6: translation in metres, axis-angle in radians) are
tensors, either of which may require grad; the rest are what `vkdr.Device.loss_and_grad`
takes (NumPy arrays or tensors). The forward pass renders on vkdr's device and computes the
loss and its exact gradients at once; the backward pass scales them by the incoming
gradient. Tensors on a CUDA device are copied to the host and back. Only this module
imports torch.
"""

import torch

from . import default_device


def _numpy(value):
    """A tensor as a NumPy array (other values as they are)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return value


class SilhouetteLoss(torch.autograd.Function):
    """loss(vertices, pose) of `vkdr.Device.loss_and_grad`, differentiable in both."""

    @staticmethod
    def forward(ctx, vertices, pose, device, faces, K, size, mask, options):
        v = vertices.detach().cpu().numpy()
        p = pose.detach().to("cpu", torch.float64).numpy()
        loss, grad_vertices, grad_pose = device.loss_and_grad(v, faces, K, size, p, mask, **options)
        ctx.save_for_backward(
            torch.from_numpy(grad_vertices).to(vertices),
            torch.from_numpy(grad_pose).to(pose),
        )
        return torch.tensor(loss, dtype=vertices.dtype, device=vertices.device)

    @staticmethod
    def backward(ctx, grad):
        grad_vertices, grad_pose = ctx.saved_tensors
        return grad * grad_vertices, grad * grad_pose, None, None, None, None, None, None


def silhouette_loss(vertices, pose, faces, K, size, mask, loss="mse", depth=None, device=None, **options):
    """The loss of the mesh's rendering at `pose` against `mask` (and `depth`, where given),
    with vkdr's exact gradients for `vertices` and `pose`. `options` are the further keyword
    arguments of `vkdr.Device.loss_and_grad` (shading, ignore, depth_sigma, occlusion, ...).
    """
    options = {key: _numpy(value) for key, value in options.items()}
    options["loss"] = loss
    options["depth"] = _numpy(depth)
    device = device if device is not None else default_device()
    return SilhouetteLoss.apply(
        vertices, pose, device, _numpy(faces), _numpy(K), tuple(size), _numpy(mask), options
    )


__all__ = ["SilhouetteLoss", "silhouette_loss"]
