"""Torch-facing skinning ops: voxel skinning-field sampling and (inverse) linear blend skinning.

TAGA (Sec. 3.1 and 3.4) stores the skinning field on a low-resolution voxel
grid, reads each Gaussian's weights by trilinear interpolation (:func:`sample_grid`), poses Gaussians with
the blended bone transforms (:func:`lbs`) and maps corrected observation-space Gaussians back to the
canonical space with the inverted blend (:func:`inverse_lbs`). Each op runs hand-written Warp kernels from
:mod:`warpavatar.kernels.skinning` on the inputs' device (torch's current stream on CUDA) and has a
hand-written backward pass. Plain-torch references with the same signatures are in
:mod:`warpavatar._torch_impl.skinning`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import skinning as kernels

__all__ = ["sample_grid", "lbs", "inverse_lbs"]

# Thread layout of the grid sampler per device type (see kernels.skinning): on CPU a thread per point
# computes each point's cell and weights once; on CUDA a thread per (point, channel) coalesces the reads of
# the grid's channel rows, the writes of the output and the gradient atomics.
_SAMPLE_GRID_LAYOUT = {"cpu": "point", "cuda": "channel"}


def _require_float32(name: str, tensor: torch.Tensor) -> None:
    if tensor.dtype != torch.float32:
        raise TypeError(f"{name} must be float32 (the Warp kernels are single precision), got {tensor.dtype}")


# ---------------------------------------------------------------------------------------------------------
# sample_grid
# ---------------------------------------------------------------------------------------------------------


def _host_corner(name: str, corner) -> tuple[float, float, float]:
    values = corner.detach().reshape(-1).tolist() if isinstance(corner, torch.Tensor) else list(corner)
    if len(values) != 3:
        raise ValueError(f"{name} must hold 3 coordinates (x, y, z), got {len(values)}")
    values = tuple(float(v) for v in values)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be finite, got {values}")
    return values


def _resolve_box(bbox_min, bbox_max, device: torch.device):
    """The box as launch arguments (host values) or, for CUDA tensors, as a [2, 3] tensor on ``device``.

    Host values are validated here; CUDA tensors are not read back (that would synchronize the host), so
    their values are the caller's responsibility.
    """
    on_device = [isinstance(c, torch.Tensor) and c.device.type == "cuda" for c in (bbox_min, bbox_max)]
    for name, corner in (("bbox_min", bbox_min), ("bbox_max", bbox_max)):
        if isinstance(corner, torch.Tensor):
            if corner.numel() != 3 or corner.dim() > 1:
                raise ValueError(f"{name} must have shape [3], got {list(corner.shape)}")
            if not corner.is_floating_point():
                raise TypeError(f"{name} must be a floating-point tensor, got {corner.dtype}")
        elif not isinstance(corner, Sequence):
            raise TypeError(f"{name} must be a tensor of shape [3] or a sequence of 3 floats, got {type(corner)}")
    if any(on_device):
        for name, corner, here in (("bbox_min", bbox_min, on_device[0]), ("bbox_max", bbox_max, on_device[1])):
            if here and corner.device != device:
                raise ValueError(f"{name} is on {corner.device} but the other inputs are on {device}")
        box = torch.stack([
            torch.as_tensor(bbox_min, dtype=torch.float32, device=device).reshape(3),
            torch.as_tensor(bbox_max, dtype=torch.float32, device=device).reshape(3),
        ]).contiguous()
        return box, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    low = _host_corner("bbox_min", bbox_min)
    high = _host_corner("bbox_max", bbox_max)
    if not all(h > l for l, h in zip(low, high)):
        raise ValueError(f"bbox_max must exceed bbox_min along every axis, got bbox_min={low}, bbox_max={high}")
    return None, low, high


class _SampleGridFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, grid, points, box, box_low, box_high):
        point_count, channel_count = points.shape[0], grid.shape[3]
        layout = _SAMPLE_GRID_LAYOUT[grid.device.type]
        values = torch.empty((point_count, channel_count), dtype=torch.float32, device=grid.device)
        ctx.save_for_backward(grid, points, box)
        ctx.box_corners = (box_low, box_high)
        ctx.layout = layout
        if values.numel() == 0:  # empty tensors may carry strides that Warp refuses; nothing to launch
            return values
        with torch_stream_scope(grid.device):
            kernels.sample_grid_forward(
                to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(values),
                box=None if box is None else to_warp(box, dtype=wp.vec3),
                box_low=box_low, box_high=box_high, layout=layout,
            )
        return values

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_values):
        grid, points, box = ctx.saved_tensors
        need_grid, need_points = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_grid = torch.zeros_like(grid) if need_grid else None
        grad_points = torch.empty_like(points) if need_points else None
        if grad_values.numel() == 0:
            return grad_grid, None if grad_points is None else grad_points.zero_(), None, None, None
        if need_grid or need_points:
            box_low, box_high = ctx.box_corners
            with torch_stream_scope(grid.device):
                kernels.sample_grid_backward(
                    to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(grad_values.contiguous()),
                    grad_grid=None if grad_grid is None else to_warp(grad_grid),
                    grad_points=None if grad_points is None else to_warp(grad_points, dtype=wp.vec3),
                    box=None if box is None else to_warp(box, dtype=wp.vec3),
                    box_low=box_low, box_high=box_high, layout=ctx.layout,
                )
        return grad_grid, grad_points, None, None, None


def sample_grid(grid: torch.Tensor, points: torch.Tensor, bbox_min, bbox_max) -> torch.Tensor:
    """Trilinearly interpolate a channel-last voxel grid spanning an axis-aligned box at ``points``.

    The grid's corner samples lie on the box's corners (``align_corners=True``): sample ``(d, h, w)`` sits at
    ``bbox_min + (w / (W - 1), h / (H - 1), d / (D - 1)) * (bbox_max - bbox_min)``, so a point's ``x`` runs
    along ``W``, ``y`` along ``H`` and ``z`` along ``D``, as in ``torch.nn.functional.grid_sample``. Points
    outside the box are clamped onto it (``padding_mode="border"``). The result equals
    ``grid_sample(grid.permute(3, 0, 1, 2)[None], normalized_points, mode="bilinear", align_corners=True,
    padding_mode="border")`` with points normalized to [-1, 1].

    TAGA's skinning field has 64x64x16 samples. In warpavatar's z-up world (the rest pose stands on z = 0,
    docs/FORMAT.md) a body facing along +-y is tall along z, wide along x (arms) and thin along y, so the field is
    ``grid[D, H, W, J]`` with ``[D, H, W] = [64, 16, 64]``: 64 samples along z, 16 along y, 64 along x.

    Gradients flow to ``grid`` (atomically accumulated) and to ``points``. Following torch's grid_sampler,
    the derivative of a clamped coordinate is zero, and a coordinate exactly on the box's border counts as
    clamped: ``d values / d points`` along an axis is 0 wherever the point is on or outside the box's faces
    on that axis. The box itself is a constant (no gradient).

    Args:
        grid: float32 ``[D, H, W, C]`` voxel samples (C arbitrary, e.g. J skinning weights), any device.
        points: float32 ``[N, 3]`` query positions (world units), on the grid's device. Non-finite points
            are not checked (that would synchronize the host): NaN gives NaN, +-inf is clamped.
        bbox_min: the box's low corner (x, y, z), world units: a tensor of shape [3] or 3 floats.
        bbox_max: the box's high corner, same form; must exceed ``bbox_min`` on every axis (checked for host
            values; CUDA tensors are used as they are, without reading them back).

    Returns:
        float32 ``[N, C]`` interpolated values.
    """
    check_tensor("grid", grid, (None, None, None, None))
    device = grid.device
    check_tensor("points", points, (None, 3), device=device)
    _require_float32("grid", grid)
    _require_float32("points", points)
    if min(grid.shape[:3]) < 1:
        raise ValueError(f"grid needs at least one sample along D, H and W, got shape {list(grid.shape)}")
    box, box_low, box_high = _resolve_box(bbox_min, bbox_max, device)
    return _SampleGridFunction.apply(grid.contiguous(), points.contiguous(), box, box_low, box_high)


# ---------------------------------------------------------------------------------------------------------
# lbs and inverse_lbs
# ---------------------------------------------------------------------------------------------------------


class _LbsFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, weights, bone_transforms, quats, inverse):
        device = points.device
        points_out = torch.empty_like(points)
        quats_out = None if quats is None else torch.empty_like(quats)
        ctx.save_for_backward(points, weights, bone_transforms, quats)
        ctx.inverse = inverse
        if points.shape[0] > 0:  # empty tensors may carry strides that Warp refuses; nothing to launch
            with torch_stream_scope(device):
                kernels.lbs_forward(
                    to_warp(points, dtype=wp.vec3), to_warp(weights), to_warp(bone_transforms, dtype=wp.mat44),
                    to_warp(points_out, dtype=wp.vec3),
                    quats=None if quats is None else to_warp(quats, dtype=wp.vec4),
                    quats_out=None if quats_out is None else to_warp(quats_out, dtype=wp.vec4),
                    inverse=inverse,
                )
        if quats_out is None:
            return points_out
        return points_out, quats_out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_points_out, grad_quats_out=None):
        points, weights, bone_transforms, quats = ctx.saved_tensors
        need_points, need_weights, need_bones, need_quats = ctx.needs_input_grad[:4]
        point_count = points.shape[0]
        grad_points = torch.empty_like(points) if need_points else None
        grad_weights = torch.empty_like(weights) if need_weights else None
        grad_quats = torch.empty_like(quats) if need_quats else None
        grad_blend = (
            torch.empty((point_count, 3, 4), dtype=torch.float32, device=points.device) if need_bones else None
        )
        if point_count == 0:
            return (
                grad_points, grad_weights, torch.zeros_like(bone_transforms) if need_bones else None, grad_quats, None
            )
        if need_points or need_weights or need_bones or need_quats:
            with torch_stream_scope(points.device):
                kernels.lbs_backward(
                    to_warp(points, dtype=wp.vec3), to_warp(weights), to_warp(bone_transforms, dtype=wp.mat44),
                    to_warp(grad_points_out.contiguous(), dtype=wp.vec3),
                    quats=None if quats is None else to_warp(quats, dtype=wp.vec4),
                    grad_quats_out=None if quats is None else to_warp(grad_quats_out.contiguous(), dtype=wp.vec4),
                    inverse=ctx.inverse,
                    grad_points=None if grad_points is None else to_warp(grad_points, dtype=wp.vec3),
                    grad_quats=None if grad_quats is None else to_warp(grad_quats, dtype=wp.vec4),
                    grad_weights=None if grad_weights is None else to_warp(grad_weights),
                    grad_blend=None if grad_blend is None else to_warp(grad_blend, dtype=kernels.mat34),
                )
        grad_bones = None
        if need_bones:
            # Reduce the per-point cotangents of the blended transforms over points: one GEMM, W^T @ G.
            grad_bones = torch.zeros_like(bone_transforms)
            grad_bones[:, :3, :] = (weights.t() @ grad_blend.view(point_count, 12)).view(-1, 3, 4)
        return grad_points, grad_weights, grad_bones, grad_quats, None


def _check_lbs_inputs(points, weights, bone_transforms, quats, points_name: str) -> None:
    check_tensor(points_name, points, (None, 3))
    device = points.device
    check_tensor("weights", weights, (None, None), device=device)
    check_tensor("bone_transforms", bone_transforms, (None, 4, 4), device=device)
    for name, tensor in ((points_name, points), ("weights", weights), ("bone_transforms", bone_transforms)):
        _require_float32(name, tensor)
    if weights.shape[0] != points.shape[0]:
        raise ValueError(
            f"weights has {weights.shape[0]} rows but {points_name} has {points.shape[0]} points"
        )
    if weights.shape[1] != bone_transforms.shape[0]:
        raise ValueError(
            f"weights has {weights.shape[1]} columns but bone_transforms has {bone_transforms.shape[0]} bones"
        )
    if bone_transforms.shape[0] == 0:
        raise ValueError("bone_transforms must hold at least one bone, got 0")
    if quats is not None:
        check_tensor("quats", quats, (points.shape[0], 4), device=device)
        _require_float32("quats", quats)


def _run_lbs(points, weights, bone_transforms, quats, inverse):
    out = _LbsFunction.apply(
        points.contiguous(), weights.contiguous(), bone_transforms.contiguous(),
        None if quats is None else quats.contiguous(), inverse,
    )
    if quats is None:
        return out, None
    return out


def lbs(
    points: torch.Tensor,
    weights: torch.Tensor,
    bone_transforms: torch.Tensor,
    *,
    quats: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Linear blend skinning of positions and, optionally, orientations (TAGA Eq. 2-3).

    Each point's blended transform is ``T_i = sum_k weights[i, k] * bone_transforms[k]`` (a 3x4 affine
    ``[A_i | t_i]``; the weights are used as given, not renormalized, and the bones' bottom rows are ignored).
    Positions map as ``x' = A_i x + t_i``. Orientations map as ``q' = q(R_i) * q`` (Hamilton product, (w, x,
    y, z) order), where ``R_i`` is the proper rotation closest to ``A_i`` in the Frobenius norm: the polar
    factor of ``A_i`` when ``det A_i > 0`` (the usual case), and always a rotation. ``q(R_i)`` is taken with
    a non-negative w; ``|q'| = |q|``, so unit inputs give unit outputs. ``R_i`` is computed by an SVD
    estimate refined by Newton steps; its derivative uses implicit differentiation of the polar
    decomposition, which stays finite when singular values repeat (e.g. blends of rotations about one axis).
    It is undefined where two singular values of ``A_i`` (signed by ``det A_i``) sum to zero.

    Args:
        points: float32 ``[N, 3]`` rest-pose (canonical) positions, world units.
        weights: float32 ``[N, J]`` dense skinning weights (expected to sum to 1 per point).
        bone_transforms: float32 ``[J, 4, 4]`` bone transforms, rest pose to posed world.
        quats: optional float32 ``[N, 4]`` (w, x, y, z) orientations of the Gaussians.

    Returns:
        ``(points_posed, quats_posed)``: float32 ``[N, 3]`` and float32 ``[N, 4]`` (None without ``quats``).
        Differentiable with respect to every input.
    """
    _check_lbs_inputs(points, weights, bone_transforms, quats, "points")
    return _run_lbs(points, weights, bone_transforms, quats, False)


def inverse_lbs(
    points_posed: torch.Tensor,
    weights: torch.Tensor,
    bone_transforms: torch.Tensor,
    *,
    quats: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Inverse linear blend skinning (TAGA Eq. 7): map posed points back with the inverted blend.

    With ``[A_i | t_i] = sum_k weights[i, k] * bone_transforms[k]`` as in :func:`lbs`, positions map as
    ``x = A_i^-1 (x' - t_i)`` and orientations as ``q = conj(q(R_i)) * q'``, so that
    ``inverse_lbs(*lbs(x, W, B, quats=q), ...)`` returns ``(x, q)`` for the same weights. ``A_i`` must be
    invertible (it is not checked, to avoid a host synchronization: a singular blend gives inf/NaN).

    Args:
        points_posed: float32 ``[N, 3]`` posed (observation-space) positions, world units.
        weights: float32 ``[N, J]`` skinning weights, used as given.
        bone_transforms: float32 ``[J, 4, 4]`` bone transforms, rest pose to posed world.
        quats: optional float32 ``[N, 4]`` (w, x, y, z) posed orientations.

    Returns:
        ``(points_canonical, quats_canonical)``: float32 ``[N, 3]`` and ``[N, 4]`` (None without ``quats``).
        Differentiable with respect to every input.
    """
    _check_lbs_inputs(points_posed, weights, bone_transforms, quats, "points_posed")
    return _run_lbs(points_posed, weights, bone_transforms, quats, True)
