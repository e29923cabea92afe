"""Maths every layer of warpavatar shares, written once: quaternions, spherical harmonics, cameras, pose
matching, skeleton order, positional encodings and the MLP builder.

Quaternions are (w, x, y, z) (``docs/conventions.md``). The quaternion functions take torch tensors or numpy
arrays and answer in kind (numpy arrays go through torch in their own dtype, so both give the same numbers).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

__all__ = ["SH_C0", "quat_multiply", "quat_conjugate", "quat_rotate", "quat_to_matrix", "quat_from_matrix",
           "quat_from_vector", "sh_basis", "camera_centre", "match_pose", "skeleton_levels", "fourier_features",
           "Linear", "linear_rows", "mlp"]

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonics constant: colour = SH_C0 * dc + 0.5."""


def _numpy_in_numpy_out(function):
    """Let a torch function of tensors take numpy arrays too (computed in their dtype, returned as numpy)."""

    def wrapper(*arrays, **options):
        if any(isinstance(a, np.ndarray) for a in arrays):
            result = function(*(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays), **options)
            return result.numpy()
        return function(*arrays, **options)

    wrapper.__name__, wrapper.__qualname__, wrapper.__doc__ = function.__name__, function.__qualname__, function.__doc__
    return wrapper


# ----------------------------------------------------------------------------------------------- quaternions
@_numpy_in_numpy_out
def quat_multiply(a, b):
    """Hamilton product ``a b`` of quaternions [...,4] (w, x, y, z)."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    return torch.cat([aw * bw - (av * bv).sum(-1, keepdim=True),
                      aw * bv + bw * av + torch.cross(av, bv, dim=-1)], dim=-1)


@_numpy_in_numpy_out
def quat_conjugate(q):
    """Conjugate [...,4] of quaternions (the inverse rotation for unit ones)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_rotate(quats: torch.Tensor, vectors: torch.Tensor, *, inverse: bool = False) -> torch.Tensor:
    """Rotate vectors [N,3] by unit quaternions [N,4], or by their inverses."""
    w, axis = quats[..., :1], quats[..., 1:]
    if inverse:
        axis = -axis
    t = 2.0 * torch.cross(axis, vectors, dim=-1)
    return vectors + w * t + torch.cross(axis, t, dim=-1)


@_numpy_in_numpy_out
def quat_to_matrix(quats):
    """Rotation matrices [...,3,3] of unit quaternions [...,4] (normalize first where they may not be)."""
    w, x, y, z = quats.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(*quats.shape[:-1], 3, 3)


@_numpy_in_numpy_out
def quat_from_matrix(rotations):
    """Unit quaternions [...,4] with w >= 0 of rotation matrices [...,3,3].

    Each of the four classic candidates is proportional to the quaternion; the one built on the largest of
    (trace, r00, r11, r22) is normalized, which avoids dividing by small numbers (Shepperd's method).
    """
    r = rotations
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    candidates = torch.stack([
        torch.stack([1.0 + trace, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                     r[..., 1, 0] - r[..., 0, 1]], -1),
        torch.stack([r[..., 2, 1] - r[..., 1, 2], 1.0 + 2.0 * r[..., 0, 0] - trace, r[..., 0, 1] + r[..., 1, 0],
                     r[..., 0, 2] + r[..., 2, 0]], -1),
        torch.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 1.0 + 2.0 * r[..., 1, 1] - trace,
                     r[..., 1, 2] + r[..., 2, 1]], -1),
        torch.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1],
                     1.0 + 2.0 * r[..., 2, 2] - trace], -1),
    ], dim=-2)  # [..., 4 candidates, 4]
    pivot = torch.stack([trace, r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]], -1).argmax(-1)
    chosen = torch.take_along_dim(candidates, pivot[..., None, None], dim=-2)[..., 0, :]
    q = chosen / chosen.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_from_vector(vector: torch.Tensor) -> torch.Tensor:
    """Unit quaternion [...,4] ``(1, v) / |(1, v)|`` of a free 3-vector v [...,3]: the identity at v = 0, smooth
    everywhere, any rotation below 180 degrees (how networks output rotations here)."""
    quats = torch.cat([torch.ones_like(vector[..., :1]), vector], dim=-1)
    return quats / quats.norm(dim=-1, keepdim=True)


# ----------------------------------------------------------------------------------------- colours, cameras
def sh_basis(degree: int, directions: torch.Tensor) -> torch.Tensor:
    """Real spherical-harmonics basis [N,(degree+1)^2] up to ``degree`` (0..3) of directions [N,3] (normalized
    here), ordered as the 3DGS coefficients."""
    x, y, z = torch.nn.functional.normalize(directions, dim=-1).unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        c1 = 0.4886025119029199
        basis += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        zz = z * z
        basis += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * z * y,
            0.9461746957575601 * zz - 0.31539156525252005,
            -1.0925484305920792 * z * x,
            0.5462742152960396 * (x * x - y * y),
        ]
    if degree >= 3:
        c1_, s1 = x * x - y * y, 2 * x * y
        c2, s2 = x * c1_ - y * s1, x * s1 + y * c1_
        band = -2.285228997322329 * zz + 0.4570457994644658
        basis += [
            -0.5900435899266435 * s2,
            1.445305721320277 * z * s1,
            band * y,
            z * (1.865881662950577 * zz - 1.119528997770346),
            band * x,
            1.445305721320277 * z * c1_,
            -0.5900435899266435 * c2,
        ]
    return torch.stack(basis, dim=-1)


def camera_centre(world_to_camera: torch.Tensor) -> torch.Tensor:
    """World position [3] of a camera's centre from its [4,4] ``world_to_camera`` (``-R^T t``)."""
    return -world_to_camera[:3, :3].T @ world_to_camera[:3, 3]


# --------------------------------------------------------------------------------------------------- poses
def match_pose(frame_poses: torch.Tensor, bone_transforms: torch.Tensor, *, tolerance: float = 1e-4
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Which of a sequence's poses a pose is, without a host synchronization.

    Args:
        frame_poses: [T,J,4,4] the sequence's bone transforms (T >= 1).
        bone_transforms: [J',4,4] the pose (J' >= J: only its first J transforms are compared).
        tolerance: largest entry difference of a match.

    Returns:
        (index of the closest row, 1.0 if every entry is within ``tolerance`` else 0.0), both device tensors.
    """
    difference = (frame_poses - bone_transforms[: frame_poses.shape[1]]).abs().amax(dim=(1, 2, 3))
    closest, best = difference.min(dim=0)  # (no indexing by a device scalar: that would read it on the host)
    return best, (closest <= tolerance).to(frame_poses.dtype)


def skeleton_levels(parents) -> list[list[int]]:
    """The joints by depth below their root: roots first, every joint after its parent.

    Raises:
        ValueError: parents that do not form a forest.
    """
    parents = [int(p) for p in parents]
    depth = [-1] * len(parents)
    for start in range(len(parents)):
        chain, joint = [], start
        while joint >= 0 and depth[joint] < 0:
            if joint in chain:
                raise ValueError("the skeleton's parents form a cycle")
            chain.append(joint)
            joint = parents[joint]
        base = -1 if joint < 0 else depth[joint]
        for offset, member in enumerate(reversed(chain)):
            depth[member] = base + 1 + offset
    return [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]


# ------------------------------------------------------------------------------------------------ networks
def fourier_features(values: torch.Tensor, frequencies: int) -> torch.Tensor:
    """NeRF positional encoding [..., C * (1 + 2 * frequencies)] of values [..., C] (about unit range): the
    values, then sin and cos of ``pi 2^k values`` for k = 0 .. frequencies - 1."""
    bands = [values]
    for octave in range(frequencies):
        scaled = values * (math.pi * 2.0**octave)
        bands += [torch.sin(scaled), torch.cos(scaled)]
    return torch.cat(bands, dim=-1)


class _RowsLinear(torch.autograd.Function):
    """``x @ weight.T + bias`` over rows [N,C]; the bias gradient is one matrix-vector product with a vector of
    ones (on an H100 four times faster than the column sum autograd runs for it: 0.024 against 0.096 ms at
    90,000 rows of 128)."""

    @staticmethod
    def forward(ctx, x, weight, bias):
        ctx.save_for_backward(x, weight)
        return torch.addmm(bias, x, weight.t())

    @staticmethod
    def backward(ctx, grad):
        x, weight = ctx.saved_tensors
        grad_x = grad @ weight if ctx.needs_input_grad[0] else None
        grad_weight = grad.t() @ x if ctx.needs_input_grad[1] else None
        grad_bias = torch.mv(grad.t(), grad.new_ones(grad.shape[0])) if ctx.needs_input_grad[2] else None
        return grad_x, grad_weight, grad_bias


class Linear(torch.nn.Linear):
    """:class:`torch.nn.Linear` (same parameters and state dict) whose backward over rows [N,C] takes the bias
    gradient as a matrix-vector product: the per-Gaussian and per-grid-point MLPs run it on 10^4-10^5 rows at
    every training step."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear_rows(x, self.weight, self.bias)


def linear_rows(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``torch.nn.functional.linear`` whose backward over rows ``x`` [N,C] takes the bias gradient as one
    matrix-vector product (see :class:`Linear`); other shapes, no bias or no gradients: the plain function."""
    if x.dim() != 2 or bias is None or not torch.is_grad_enabled():
        return torch.nn.functional.linear(x, weight, bias)
    return _RowsLinear.apply(x, weight, bias)


def mlp(width_in: int, hidden: int, layers: int, width_out: int | None = None, *,
        activation: Callable[[], torch.nn.Module] = torch.nn.ReLU, layer_norm: bool = False) -> torch.nn.Sequential:
    """``layers`` hidden layers (Linear to ``hidden``, LayerNorm when asked, ``activation()``), then a Linear to
    ``width_out`` (none when it is None)."""
    modules: list[torch.nn.Module] = []
    for _ in range(layers):
        modules.append(Linear(width_in, hidden))
        if layer_norm:
            modules.append(torch.nn.LayerNorm(hidden))
        modules.append(activation())
        width_in = hidden
    if width_out is not None:
        modules.append(Linear(width_in, width_out))
    return torch.nn.Sequential(*modules)
