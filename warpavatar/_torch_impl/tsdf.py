"""Plain-torch reference of the TSDF fusion (:func:`warpavatar.ops.integrate_tsdf`): every voxel against every view
at once, no early exit."""

from __future__ import annotations

import torch

__all__ = ["integrate_tsdf"]


def integrate_tsdf(depth, alpha, color, K, world_to_camera, origin, voxel_size, grid_shape, *, truncation,
                   alpha_threshold=0.5):
    """Reference of :func:`warpavatar.ops.integrate_tsdf` (same arithmetic order, so pixel choices agree)."""
    device = depth.device
    grid_shape = tuple(int(extent) for extent in grid_shape)
    origin = torch.as_tensor(origin, dtype=torch.float32, device=device).reshape(3)
    voxel_size = torch.tensor(float(voxel_size), dtype=torch.float32, device=device)
    truncation = float(truncation)
    axes = [torch.arange(extent, device=device, dtype=torch.float32) for extent in grid_shape]
    i, j, k = torch.meshgrid(*axes, indexing="ij")
    points = [origin[0] + voxel_size * i.reshape(-1), origin[1] + voxel_size * j.reshape(-1),
              origin[2] + voxel_size * k.reshape(-1)]
    voxel_count = points[0].shape[0]
    view_count, height, width = depth.shape
    total = torch.zeros(voxel_count, device=device)
    count = torch.zeros(voxel_count, device=device)
    rgb = torch.zeros(voxel_count, 3, device=device)
    seen = torch.zeros(voxel_count, dtype=torch.bool, device=device)
    carved = torch.zeros(voxel_count, dtype=torch.bool, device=device)
    for view in range(view_count):
        m, intrinsics = world_to_camera[view], K[view]
        x, y, z = (m[r, 0] * points[0] + m[r, 1] * points[1] + m[r, 2] * points[2] + m[r, 3] for r in range(3))
        in_front = z > 0.0
        safe_z = torch.where(in_front, z, torch.ones_like(z))
        xn, yn = x / safe_z, y / safe_z
        u = intrinsics[0, 0] * xn + intrinsics[0, 1] * yn + intrinsics[0, 2]
        v = intrinsics[1, 1] * yn + intrinsics[1, 2]
        inside = in_front & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
        column = torch.floor(u + 0.5).clamp(0, width - 1).long()
        row = torch.floor(v + 0.5).clamp(0, height - 1).long()
        a, d = alpha[view, row, column], depth[view, row, column]
        background = (a < alpha_threshold) | ~torch.isfinite(d)
        counted = inside & ~background & ~carved & (d - z >= -truncation)
        total += torch.where(counted, torch.clamp(d - z, max=truncation), torch.zeros_like(z))
        count += counted.float()
        unpremultiplied = color[view, row, column] / a.clamp(min=1e-6)[:, None]
        rgb += torch.where(counted[:, None], unpremultiplied, torch.zeros_like(rgb))
        carved |= inside & background
        seen |= inside
    empty = carved | ~seen
    averaged = ~empty & (count > 0)
    tsdf = torch.where(empty, torch.full_like(total, truncation),
                       torch.where(averaged, total / count.clamp(min=1.0), torch.full_like(total, -truncation)))
    weight = torch.where(averaged, count, torch.zeros_like(count))
    voxel_color = torch.where(averaged[:, None], rgb / count.clamp(min=1.0)[:, None], torch.zeros_like(rgb))
    return tsdf.reshape(grid_shape), weight.reshape(grid_shape), voxel_color.reshape(*grid_shape, 3)
