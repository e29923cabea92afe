"""Torch bridge of the TSDF kernel (``kernels/tsdf.py``): views of an object fused into a truncated signed distance
on a voxel grid, with space carving, for the mesh export (no gradients). Plain-torch reference:
:mod:`warpavatar._torch_impl.tsdf`."""

from __future__ import annotations

import math

import torch
import warp as wp

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import tsdf as kernels

__all__ = ["integrate_tsdf"]


def _grid_arguments(origin, voxel_size, grid_shape, truncation) -> tuple[tuple, float, tuple, float]:
    origin = tuple(float(value) for value in (origin.tolist() if isinstance(origin, torch.Tensor) else origin))
    if len(origin) != 3 or not all(math.isfinite(value) for value in origin):
        raise ValueError(f"origin must be 3 finite coordinates, got {origin}")
    grid_shape = tuple(int(extent) for extent in grid_shape)
    if len(grid_shape) != 3 or min(grid_shape) < 0:
        raise ValueError(f"grid_shape must be 3 sizes >= 0, got {grid_shape}")
    voxel_size, truncation = float(voxel_size), float(truncation)
    if not (voxel_size > 0.0 and math.isfinite(voxel_size)):
        raise ValueError(f"voxel_size must be positive and finite, got {voxel_size}")
    if not (truncation > 0.0 and math.isfinite(truncation)):
        raise ValueError(f"truncation must be positive and finite, got {truncation}")
    return origin, voxel_size, grid_shape, truncation


def integrate_tsdf(depth: torch.Tensor, alpha: torch.Tensor, color: torch.Tensor, K: torch.Tensor,
                   world_to_camera: torch.Tensor, origin, voxel_size: float, grid_shape, *, truncation: float,
                   alpha_threshold: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fuse views into a truncated signed distance on a voxel grid, carving what any view sees as background.

    For each voxel centre ``origin + voxel_size * (i, j, k)`` and each view it projects into (nearest pixel, OpenCV
    camera, in front of it): a pixel with ``alpha < alpha_threshold`` or a non-finite depth carves the voxel as
    empty; otherwise the signed distance ``depth - z`` [m] counts unless it is below ``-truncation`` (occluded),
    clamped to ``+truncation``. The voxel's value is the mean of the counted distances; a voxel inside every
    silhouette it falls into with no counted view is inside (``-truncation``); carved voxels and voxels in no
    image are empty (``+truncation``). Colours are the counted views' mean of ``color / alpha``. No gradients.

    Args:
        depth: float32 [V,H,W] camera-space z [m] (``inf`` where a view sees nothing).
        alpha: float32 [V,H,W] coverage in 0..1.
        color: float32 [V,H,W,3] RGB premultiplied by alpha (the rasterizer's image on black).
        K: float32 [V,3,3] intrinsics [px], pixel centres at integers.
        world_to_camera: float32 [V,4,4] rigid extrinsics.
        origin: centre of voxel (0, 0, 0) [m], 3 floats (or a tensor of 3).
        voxel_size: spacing of the voxel centres [m].
        grid_shape: ``(X, Y, Z)`` voxels along x, y, z.
        truncation: largest magnitude of the signed distance [m].
        alpha_threshold: a pixel with less alpha is background.

    Returns:
        ``(tsdf [X,Y,Z], weight [X,Y,Z], color [X,Y,Z,3])`` float32 on the inputs' device: the signed distance [m]
        (positive outside), the number of views averaged (0 where none counted) and the mean colour (0 there).
    """
    origin, voxel_size, grid_shape, truncation = _grid_arguments(origin, voxel_size, grid_shape, truncation)
    check_tensor("depth", depth, (None, None, None), dtype_kind="float32")
    device = depth.device
    view_count, height, width = depth.shape
    check_tensor("alpha", alpha, (view_count, height, width), dtype_kind="float32", device=device)
    check_tensor("color", color, (view_count, height, width, 3), dtype_kind="float32", device=device)
    check_tensor("K", K, (view_count, 3, 3), dtype_kind="float32", device=device)
    check_tensor("world_to_camera", world_to_camera, (view_count, 4, 4), dtype_kind="float32", device=device)
    tsdf = torch.empty(grid_shape, dtype=torch.float32, device=device)
    weight = torch.empty(grid_shape, dtype=torch.float32, device=device)
    voxel_color = torch.empty((*grid_shape, 3), dtype=torch.float32, device=device)
    if tsdf.numel() == 0:
        return tsdf, weight, voxel_color
    if depth.numel() == 0:  # no pixel: every voxel is unknown, written as empty (and Warp refuses empty views)
        return tsdf.fill_(truncation), weight.zero_(), voxel_color.zero_()
    with torch_stream_scope(device):
        kernels.integrate_tsdf(
            to_warp(depth), to_warp(alpha), to_warp(color, dtype=wp.vec3), to_warp(K, dtype=wp.mat33),
            to_warp(world_to_camera, dtype=wp.mat44), origin, voxel_size, grid_shape, truncation,
            float(alpha_threshold), to_warp(tsdf.view(-1)), to_warp(weight.view(-1)),
            to_warp(voxel_color.view(-1, 3), dtype=wp.vec3))
    return tsdf, weight, voxel_color
