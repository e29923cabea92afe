"""Plain-torch reference of :func:`warpavatar.ops.rasterize_gaussians`.

Dense: every pixel evaluates every Gaussian (sorted by depth), which is only fit for tiny images, but it follows
the Warp rasterizer's rules exactly: the same projection and culling, the same tile rule (a Gaussian reaches
only the pixels of the 16x16 tiles its radius box overlaps), the same alpha thresholds and early termination,
and autograd through torch. It runs in the dtype of its inputs (float64 for finite-difference checks).
Conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import math

import torch

from warpavatar.geometry import quat_to_matrix, sh_basis

__all__ = ["rasterize_gaussians", "project_gaussians"]

TILE_SIZE = 16
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
BLUR_EPS2D = 0.3
RADIUS_SIGMAS = 3.33
ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4


def project_gaussians(means, quats, scales, K, world_to_camera, width: int, height: int):
    """EWA projection as gsplat computes it.

    Returns ``(means2d [N, 2] with pixel centres at half-integers, conics [N, 3], depths [N], radii [N, 2] int32)``;
    culled Gaussians have radii (0, 0) and finite (meaningless) other values.
    """
    dtype = means.dtype
    K = K.to(dtype)
    world_to_camera = world_to_camera.to(dtype)
    rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    means_camera = means @ rotation.T + translation
    depths = means_camera[:, 2]
    in_depth_range = (depths > NEAR_PLANE) & (depths < FAR_PLANE)
    # Divide by a safe depth for culled Gaussians so that no inf/NaN reaches the gradients.
    safe_z = torch.where(in_depth_range, depths, torch.ones_like(depths))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5  # gsplat's principal point
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = safe_z * torch.clamp(means_camera[:, 0] / safe_z, min=-(cx / fx + 0.3 * tan_x), max=(width - cx) / fx + 0.3 * tan_x)
    ty = safe_z * torch.clamp(means_camera[:, 1] / safe_z, min=-(cy / fy + 0.3 * tan_y), max=(height - cy) / fy + 0.3 * tan_y)
    zeros = torch.zeros_like(safe_z)
    jacobian = torch.stack(
        [fx / safe_z, zeros, -fx * tx / safe_z**2, zeros, fy / safe_z, -fy * ty / safe_z**2], dim=-1
    ).reshape(-1, 2, 3)

    transform = rotation @ quat_to_matrix(torch.nn.functional.normalize(quats, dim=-1)) * scales[:, None, :]
    covariance_camera = transform @ transform.transpose(-1, -2)
    covariance_2d = jacobian @ covariance_camera @ jacobian.transpose(-1, -2)
    a = covariance_2d[:, 0, 0] + BLUR_EPS2D
    b = covariance_2d[:, 0, 1]
    c = covariance_2d[:, 1, 1] + BLUR_EPS2D
    det = a * c - b * b
    valid = in_depth_range & (det > 0)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    means2d = torch.stack(
        [fx * means_camera[:, 0] / safe_z + cx, fy * means_camera[:, 1] / safe_z + cy], dim=-1
    )

    with torch.no_grad():
        radii = torch.stack(
            [torch.ceil(RADIUS_SIGMAS * torch.sqrt(a.clamp(min=0))), torch.ceil(RADIUS_SIGMAS * torch.sqrt(c.clamp(min=0)))],
            dim=-1,
        )
        on_screen = (
            (means2d[:, 0] + radii[:, 0] > 0)
            & (means2d[:, 0] - radii[:, 0] < width)
            & (means2d[:, 1] + radii[:, 1] > 0)
            & (means2d[:, 1] - radii[:, 1] < height)
        )
        radii = torch.where((valid & on_screen)[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return means2d, conics, depths, radii


def _tile_boxes(means2d: torch.Tensor, radii: torch.Tensor, tiles_x: int, tiles_y: int) -> torch.Tensor:
    """[N, 4] int64 (x0, x1, y0, y1) tile ranges [x0, x1) x [y0, y1) of each Gaussian's radius box."""
    center = means2d.detach().float() / TILE_SIZE
    radius = radii.float() / TILE_SIZE
    x0 = torch.floor(center[:, 0] - radius[:, 0]).clamp(0, tiles_x)
    x1 = torch.ceil(center[:, 0] + radius[:, 0]).clamp(0, tiles_x)
    y0 = torch.floor(center[:, 1] - radius[:, 1]).clamp(0, tiles_y)
    y1 = torch.ceil(center[:, 1] + radius[:, 1]).clamp(0, tiles_y)
    return torch.stack([x0, x1, y0, y1], dim=-1).long()


def rasterize_gaussians(means, quats, scales, opacities, colors, K, world_to_camera, width: int, height: int, *,
                        background=None, sh_degree: int | None = None, densify_grad_out=None, return_info=False,
                        intersection_capacity: int | None = None):
    """Reference of :func:`warpavatar.ops.rasterize_gaussians` (same arguments, types and outputs; it has no
    sort buffers, so ``intersection_capacity`` changes nothing and ``info["status"]`` only counts the pairs)."""
    device, dtype = means.device, means.dtype
    means2d, conics, depths, radii = project_gaussians(means, quats, scales, K, world_to_camera, width, height)

    if sh_degree is None:
        rgb = colors
    else:
        rotation, translation = world_to_camera[:3, :3].to(dtype), world_to_camera[:3, 3].to(dtype)
        camera_center = -rotation.T @ translation
        basis = sh_basis(sh_degree, means - camera_center)
        coefficient_count = (sh_degree + 1) ** 2
        rgb = torch.clamp_min((basis[:, :, None] * colors[:, :coefficient_count, :]).sum(dim=1) + 0.5, 0.0)

    tiles_x = math.ceil(width / TILE_SIZE)
    tiles_y = math.ceil(height / TILE_SIZE)
    pixel_y, pixel_x = torch.meshgrid(
        torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij"
    )
    pixel_x, pixel_y = pixel_x.reshape(-1), pixel_y.reshape(-1)
    centers = torch.stack([pixel_x, pixel_y], dim=-1).to(dtype) + 0.5  # [P, 2]

    kept = (radii[:, 0] > 0) | (radii[:, 1] > 0)
    order = torch.argsort(torch.where(kept, depths.detach(), torch.full_like(depths, math.inf)), stable=True)
    order = order[: int(kept.sum())]
    boxes = _tile_boxes(means2d, radii, tiles_x, tiles_y)[order]  # [M, 4]
    pixel_tile_x, pixel_tile_y = pixel_x // TILE_SIZE, pixel_y // TILE_SIZE
    in_box = (
        (pixel_tile_x[None] >= boxes[:, 0:1]) & (pixel_tile_x[None] < boxes[:, 1:2])
        & (pixel_tile_y[None] >= boxes[:, 2:3]) & (pixel_tile_y[None] < boxes[:, 3:4])
    )  # [M, P]  fmt: skip

    sorted_means2d = means2d[order]
    per_pixel_means2d = sorted_means2d[:, None, :].expand(-1, centers.shape[0], -1)  # [M, P, 2]
    if densify_grad_out is not None and per_pixel_means2d.requires_grad:
        # The hook sees d loss / d mean2d of every (Gaussian, pixel) pair: sum their absolute values per axis.
        def _accumulate_abs(grad, order=order, out=densify_grad_out):
            out.index_add_(0, order, grad.abs().sum(dim=1).to(out.dtype))

        per_pixel_means2d.register_hook(_accumulate_abs)
    delta = per_pixel_means2d - centers[None]
    conic = conics[order]
    sigma = 0.5 * (conic[:, None, 0] * delta[..., 0] ** 2 + conic[:, None, 2] * delta[..., 1] ** 2) + conic[
        :, None, 1
    ] * delta[..., 0] * delta[..., 1]
    alpha = torch.clamp_max(opacities[order][:, None] * torch.exp(-sigma), ALPHA_MAX)  # [M, P]
    valid = in_box & (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)

    # Transmittance after each Gaussian if every valid one were composited; it only decreases, so the pixel
    # composites exactly the valid Gaussians before the first one that takes it to TRANSMITTANCE_MIN or below.
    factors = torch.where(valid, 1 - alpha, torch.ones_like(alpha))
    after = torch.cumprod(factors, dim=0)
    composited = valid & (after > TRANSMITTANCE_MIN)
    factors = torch.where(composited, 1 - alpha, torch.ones_like(alpha))
    after = torch.cumprod(factors, dim=0)
    before = torch.cat([torch.ones_like(after[:1]), after[:-1]], dim=0)
    weights = torch.where(composited, alpha * before, torch.zeros_like(alpha))  # [M, P]
    final_transmittance = after[-1] if after.shape[0] else torch.ones(centers.shape[0], device=device, dtype=dtype)

    image = weights.T @ rgb[order]  # [P, 3]
    if background is not None:
        image = image + final_transmittance[:, None] * background.to(dtype)
    depth = weights.T @ depths[order]
    outputs = (
        image.reshape(height, width, 3),
        (1 - final_transmittance).reshape(height, width),
        depth.reshape(height, width),
    )
    if return_info:
        box_tiles = (boxes[:, 1] - boxes[:, 0]).clamp_min(0) * (boxes[:, 3] - boxes[:, 2]).clamp_min(0)
        status = torch.stack([box_tiles.sum(), torch.zeros((), dtype=box_tiles.dtype, device=device)])
        info = {"radii": radii, "means2d": (means2d.detach() - 0.5).float(), "depths": depths.detach(),
                "status": status.to(torch.int32)}
        return outputs + (info,)
    return outputs
