"""Plain-torch reference of :func:`warpavatar.ops.rasterize_gaussians`.

Dense: every pixel evaluates every Gaussian (sorted by depth), which is only fit for tiny images, but it follows
the Warp rasterizer's rules exactly: the same projection and culling, the same tile rule (a Gaussian reaches
only the pixels of the 16x16 tiles where its ellipse of alpha >= 1/255 meets a pixel centre, see
:func:`reached_tiles`), the same alpha thresholds and early termination,
and autograd through torch. It runs in the dtype of its inputs (float64 for finite-difference checks).
Conventions: ``docs/conventions.md``.
"""

from __future__ import annotations

import math

import torch

from warpavatar.geometry import quat_to_matrix, sh_basis

__all__ = ["rasterize_gaussians", "project_gaussians", "reached_tiles", "depth_sort_keys", "emit_tile_keys",
           "sorted_pairs", "tile_ranges"]

TILE_SIZE = 16
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
BLUR_EPS2D = 0.3
ALPHA_THRESHOLD = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
SIGMA_MARGIN = 0.05  # why this margin suffices: kernels/splat.py, reach_sigma


def reach_sigma(opacities: torch.Tensor) -> torch.Tensor:
    """Largest exponent ``d^T conic d / 2`` at which a Gaussian can reach alpha 1/255, plus the margin."""
    return torch.log(opacities / ALPHA_THRESHOLD) + SIGMA_MARGIN


def project_gaussians(means, quats, scales, K, world_to_camera, width: int, height: int, *, opacities):
    """EWA projection as gsplat computes it, with the opacity-aware extent.

    The radius per axis is ``ceil(sqrt(2 reach_sigma(opacity) Sigma_xx))`` (Sigma blurred): the box of the ellipse
    where alpha can reach 1/255. Gaussians with opacity below 1/255, outside the depth range, with a singular
    covariance or a box off the image are culled.

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
    valid = in_depth_range & (det > 0) & (opacities >= ALPHA_THRESHOLD)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)
    means2d = torch.stack(
        [fx * means_camera[:, 0] / safe_z + cx, fy * means_camera[:, 1] / safe_z + cy], dim=-1
    )

    with torch.no_grad():
        max_sigma = reach_sigma(opacities.detach().to(dtype)).clamp(min=0)
        radii = torch.stack(
            [torch.ceil(torch.sqrt(2 * max_sigma * a.clamp(min=0))), torch.ceil(torch.sqrt(2 * max_sigma * c.clamp(min=0)))],
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


def reached_tiles(means2d, conics, opacities, radii, width: int, height: int) -> torch.Tensor:
    """[N, tiles_y * tiles_x] bool: the (Gaussian, tile) pairs the rasterizer lists (row-major tile ids).

    A tile is listed when it lies in the Gaussian's radius box and the ellipse ``sigma <= reach_sigma(opacity)``
    (``sigma = d^T conic d / 2``) contains a pixel centre's position of the tile's rows and columns inside the
    image: per tile row, the x extent of the ellipse within the row's band of pixel-centre rows (its ends at the
    ellipse's leftmost / rightmost points clamped to the band), as pixel columns, as tiles (the rule and the
    derivation of ``kernels/splat.py``'s ``row_tile_span``).
    """
    tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    dtype = conics.dtype
    boxes = _tile_boxes(means2d, radii, tiles_x, tiles_y)
    kept = (radii > 0).any(dim=1)
    max_sigma = reach_sigma(opacities.detach().to(dtype)).clamp(min=0)[:, None]  # [N, 1]
    mx, my = means2d.detach()[:, 0:1], means2d.detach()[:, 1:2]
    a, b, c = (conics.detach()[:, k: k + 1] for k in range(3))
    a, c = torch.where(kept[:, None], a, torch.ones_like(a)), torch.where(kept[:, None], c, torch.ones_like(c))
    b = torch.where(kept[:, None], b, torch.zeros_like(b))
    det = a * c - b * b
    tile_rows = torch.arange(tiles_y, device=conics.device)
    row_lo = (tile_rows * TILE_SIZE).to(dtype)[None]
    row_hi = ((tile_rows + 1) * TILE_SIZE).clamp(max=height).to(dtype)[None] - 1
    reach_y = torch.sqrt(2 * max_sigma * a / det)
    dy_lo = torch.maximum(row_lo + 0.5 - my, -reach_y)
    dy_hi = torch.minimum(row_hi + 0.5 - my, reach_y)  # [N, tiles_y]
    dy_right = -b * torch.sqrt(2 * max_sigma / (c * det))

    def half_width(dy):
        return torch.sqrt(torch.clamp_min(2 * max_sigma - det / a * dy * dy, 0) / a)

    dy = torch.minimum(torch.maximum(dy_right.expand_as(dy_lo), dy_lo), dy_hi)
    x_max = mx - b / a * dy + half_width(dy)
    dy = torch.minimum(torch.maximum((-dy_right).expand_as(dy_lo), dy_lo), dy_hi)
    x_min = mx - b / a * dy - half_width(dy)
    column_first = torch.ceil(x_min - 0.5).clamp_min(0)
    column_last = torch.floor(x_max - 0.5).clamp_max(width - 1)
    span_ok = (dy_lo <= dy_hi) & (column_first <= column_last)
    tile_first = torch.div(column_first, TILE_SIZE, rounding_mode="floor").long()
    tile_last = torch.div(column_last, TILE_SIZE, rounding_mode="floor").long()  # [N, tiles_y]

    tile_y, tile_x = torch.meshgrid(tile_rows, torch.arange(tiles_x, device=conics.device), indexing="ij")
    tile_x, tile_y = tile_x.reshape(-1), tile_y.reshape(-1)
    in_box = ((tile_x[None] >= boxes[:, 0:1]) & (tile_x[None] < boxes[:, 1:2])
              & (tile_y[None] >= boxes[:, 2:3]) & (tile_y[None] < boxes[:, 3:4]))  # fmt: skip
    in_span = (span_ok[:, tile_y] & (tile_x[None] >= tile_first[:, tile_y]) & (tile_x[None] <= tile_last[:, tile_y]))
    return kept[:, None] & in_box & in_span


def depth_sort_keys(depths: torch.Tensor, tile_counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth sort's inputs the projection kernel writes: float32 keys [N] (the depth of a Gaussian that
    reaches a tile, else ``FAR_PLANE``) and int32 records [N, 2] (Gaussian index, tile count)."""
    keys = torch.where(tile_counts > 0, depths.float(), torch.full_like(depths, FAR_PLANE, dtype=torch.float32))
    index = torch.arange(depths.shape[0], device=depths.device)
    return keys, torch.stack([index, tile_counts.long()], dim=-1).to(torch.int32)


def emit_tile_keys(reached: torch.Tensor, order: torch.Tensor, *, capacity: int | None = None):
    """The key emission's slots: the Gaussians in ``order`` (depth order), each its reached tiles in increasing
    id, as (tile ids, Gaussian ids), int32 [S]: S is the pair count, or ``capacity``, which drops the pairs past
    it and pads the slots past the pairs with tile ``tiles`` and Gaussian -1.

    Args:
        reached: [N, tiles] bool, the (Gaussian, tile) pairs (:func:`reached_tiles`).
        order: [N] the Gaussians in depth order (a permutation of ``arange(N)``).
        capacity: None, or the fixed number of slots.
    """
    tile_count = reached.shape[1]
    gaussian_ids, tile_ids = torch.nonzero(reached[order], as_tuple=True)  # row-major: rank, then tile
    gaussian_ids = order[gaussian_ids]
    if capacity is not None:
        gaussian_ids, tile_ids = gaussian_ids[:capacity], tile_ids[:capacity]
        padding = capacity - tile_ids.shape[0]
        tile_ids = torch.cat([tile_ids, tile_ids.new_full((padding,), tile_count)])
        gaussian_ids = torch.cat([gaussian_ids, gaussian_ids.new_full((padding,), -1)])
    return tile_ids.to(torch.int32), gaussian_ids.to(torch.int32)


def sorted_pairs(reached: torch.Tensor, depths: torch.Tensor, *, capacity: int | None = None):
    """The binning's result, by definition: the (Gaussian, tile) pairs in lexicographic order of (tile, depth,
    Gaussian index), as (tile ids, Gaussian ids), int32 [S].

    With a ``capacity`` the pairs the emission keeps are the first ``capacity`` in (depth, index, tile) order,
    and the list is padded to ``capacity`` with tile ``tiles`` and Gaussian -1 (:func:`emit_tile_keys`).

    Args:
        reached: [N, tiles] bool, the (Gaussian, tile) pairs.
        depths: [N] the Gaussians' depths (their order only matters; equal ones are ordered by index).
        capacity: None, or the fixed number of slots.
    """
    tile_count = reached.shape[1]
    gaussian_ids, tile_ids = torch.nonzero(reached, as_tuple=True)  # by index, then tile
    pair_depths = depths[gaussian_ids]

    def lexsort(*keys):  # the first key is the most significant; stable sorts from the least significant
        order = torch.arange(gaussian_ids.shape[0], device=reached.device)
        for key in reversed(keys):
            order = order[torch.argsort(key[order], stable=True)]
        return order

    if capacity is not None:
        kept = lexsort(pair_depths, gaussian_ids, tile_ids)[:capacity]
        gaussian_ids, tile_ids, pair_depths = gaussian_ids[kept], tile_ids[kept], pair_depths[kept]
    order = lexsort(tile_ids, pair_depths, gaussian_ids)
    tile_ids, gaussian_ids = tile_ids[order], gaussian_ids[order]
    if capacity is not None:
        padding = capacity - tile_ids.shape[0]
        tile_ids = torch.cat([tile_ids, tile_ids.new_full((padding,), tile_count)])
        gaussian_ids = torch.cat([gaussian_ids, gaussian_ids.new_full((padding,), -1)])
    return tile_ids.to(torch.int32), gaussian_ids.to(torch.int32)


def tile_ranges(sorted_tiles: torch.Tensor, tile_count: int) -> torch.Tensor:
    """[tile_count, 2] int32 ``[start, end)`` of each tile in a sorted list of tile ids (ids of ``tile_count``
    and more are padding and belong to no tile; an absent tile gets [0, 0])."""
    tiles = sorted_tiles.long()
    real = tiles < tile_count
    counts = torch.bincount(tiles[real], minlength=tile_count)
    ends = torch.cumsum(counts, dim=0)
    ranges = torch.stack([ends - counts, ends], dim=-1)
    return torch.where((counts > 0)[:, None], ranges, torch.zeros_like(ranges)).to(torch.int32)


def rasterize_gaussians(means, quats, scales, opacities, colors, K, world_to_camera, width: int, height: int, *,
                        background=None, sh_degree: int | None = None, densify_grad_out=None, return_info=False,
                        intersection_capacity: int | None = None):
    """Reference of :func:`warpavatar.ops.rasterize_gaussians` (same arguments, types and outputs; it has no
    sort buffers, so ``intersection_capacity`` changes nothing and ``info["status"]`` only counts the pairs)."""
    device, dtype = means.device, means.dtype
    means2d, conics, depths, radii = project_gaussians(means, quats, scales, K, world_to_camera, width, height,
                                                       opacities=opacities)

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
    reached = reached_tiles(means2d, conics, opacities, radii, width, height)[order]  # [M, tiles]
    in_box = reached[:, (pixel_y // TILE_SIZE) * tiles_x + pixel_x // TILE_SIZE]  # [M, P]

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
        pair_count = reached.sum()  # the (Gaussian, tile) pairs the rasterizer lists
        status = torch.stack([pair_count, torch.zeros_like(pair_count)])
        info = {"radii": radii, "means2d": (means2d.detach() - 0.5).float(), "depths": depths.detach(),
                "status": status.to(torch.int32)}
        return outputs + (info,)
    return outputs
