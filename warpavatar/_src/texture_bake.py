"""Torch bridge of the texture-baking kernels (``kernels/texture_bake.py``): triangles rasterized into a UV atlas
(:func:`rasterize_uv_atlas`) and surface points coloured from the views that see them
(:func:`average_view_colors`), and each query point's nearest known point (:func:`nearest_points`). None has
gradients (a bake is an export step). Plain-torch references with
the same signatures are in :mod:`warpavatar._torch_impl.texture_bake`; :mod:`warpavatar.mesh.texture` uses both
ops to bake an avatar mesh's texture and vertex colours.
"""

from __future__ import annotations

import torch
import warp as wp

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import texture_bake as kernels

__all__ = ["rasterize_uv_atlas", "average_view_colors", "nearest_points"]

_GRID_CELLS = 128
"""Hash-grid cells along each axis (cells further out alias onto these)."""

_FIRST_RADIUS_SPACINGS = 4.0
"""First search radius, in typical spacings of the known points (as if they covered their box's surface)."""

_RADIUS_GROWTH = 4.0
"""Search radius ratio between consecutive rounds of :func:`nearest_points`."""


def _no_gradients(name: str, *tensors: torch.Tensor) -> None:
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        raise ValueError(f"{name} has no gradients (an export step): call it under torch.no_grad()")


def rasterize_uv_atlas(vertices: torch.Tensor, faces: torch.Tensor, normals: torch.Tensor, uvs: torch.Tensor, *,
                       size: int, margin: float = 0.0
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which triangle covers each texel of a ``size x size`` UV atlas, and where.

    Texel ``(row r, column c)`` has its centre at UV ``((c + 0.5) / size, (r + 0.5) / size)`` (u right, v down
    from the top row). A texel belongs to the triangle nearest to its centre in UV (0 inside it) if that is at
    most ``margin`` texels away, the lowest index among equally near ones (triangles sharing the edge a centre
    lies on); it gets the barycentric coordinates of that triangle's closest point to the centre, and the 3D
    point and unit normal they interpolate. Triangles of no UV area cover nothing.

    Args:
        vertices: float32 [V,3] positions [m].
        faces: int32 [F,3] vertex indices.
        normals: float32 [V,3] vertex normals.
        uvs: float32 [V,2] texture coordinates in 0..1.
        size: the atlas's width and height [texels].
        margin: how far [texels] outside its triangles a texel centre may lie and still be covered (0: centres
            inside a triangle or on its edges only).

    Returns:
        ``(texel_face [S,S] int32 (-1 where no triangle covers), texel_barycentric [S,S,3], texel_point [S,S,3]
        [m], texel_normal [S,S,3] unit, texel_distance [S,S] [texels] (inf where no triangle covers))``; the
        vectors are 0 where no triangle covers.
    """
    _no_gradients("rasterize_uv_atlas", vertices, normals, uvs)
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}")
    if not 0.0 <= margin <= 64.0:
        raise ValueError(f"margin must lie in 0..64 texels, got {margin}")
    check_tensor("vertices", vertices, (None, 3), dtype_kind="float32")
    device = vertices.device
    vertex_count = vertices.shape[0]
    check_tensor("faces", faces, (None, 3), dtype_kind="int", device=device)
    if faces.dtype != torch.int32:
        raise TypeError(f"faces must be int32, got {faces.dtype}")
    check_tensor("normals", normals, (vertex_count, 3), dtype_kind="float32", device=device)
    check_tensor("uvs", uvs, (vertex_count, 2), dtype_kind="float32", device=device)
    texel_key = torch.full((size, size), torch.iinfo(torch.int64).max, dtype=torch.int64, device=device)
    texel_face = torch.empty(size, size, dtype=torch.int32, device=device)
    texel_distance = torch.empty(size, size, device=device)
    texel_barycentric = torch.empty(size, size, 3, device=device)
    texel_point = torch.empty(size, size, 3, device=device)
    texel_normal = torch.empty(size, size, 3, device=device)
    with torch_stream_scope(device):
        kernels.rasterize_uv(to_warp(vertices, dtype=wp.vec3), to_warp(normals, dtype=wp.vec3),
                             to_warp(uvs, dtype=wp.vec2), to_warp(faces), size=size, margin=float(margin),
                             texel_key=to_warp(texel_key), texel_face=to_warp(texel_face),
                             texel_distance=to_warp(texel_distance),
                             texel_barycentric=to_warp(texel_barycentric, dtype=wp.vec3),
                             texel_point=to_warp(texel_point, dtype=wp.vec3),
                             texel_normal=to_warp(texel_normal, dtype=wp.vec3))
    return texel_face, texel_barycentric, texel_point, texel_normal, texel_distance


def average_view_colors(points: torch.Tensor, normals: torch.Tensor, world_to_camera: torch.Tensor,
                        intrinsics: torch.Tensor, images: torch.Tensor, depths: torch.Tensor, *,
                        depth_tolerance: float, min_cosine: float = 0.0,
                        image_sizes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each point's colour averaged over the views that see it, weighted by the cosine between its normal and its
    direction to the camera.

    A view sees a point when the cosine exceeds ``min_cosine``, the point projects into the image in front of
    the camera, the nearest pixel to its projection has alpha >= 0.5 and a depth within ``depth_tolerance`` of
    the point's camera z. Its colour there is the bilinearly sampled premultiplied colour over the bilinearly
    sampled alpha (views are rendered on black), clamped to 0..1.

    Args:
        points: float32 [N,3] surface points [m].
        normals: float32 [N,3] unit outward normals.
        world_to_camera: float32 [C,4,4] OpenCV extrinsics.
        intrinsics: float32 [C,3,3] pinhole intrinsics ``K`` [px] (pixel centres at integers).
        images: float32 [C,H,W,4] premultiplied RGB and alpha in 0..1.
        depths: float32 [C,H,W] camera z of what each pixel sees [m], ``inf`` where nothing.
        depth_tolerance: largest |point z - pixel depth| of a visible point [m].
        min_cosine: least cosine (exclusive) between a normal and the direction to a camera that sees it.
        image_sizes: int32 [C,2] (width, height) of each view when views of several sizes share the arrays
            (each in the top-left corner); by default every view fills H x W.

    Returns:
        ``(colors [N,3] in 0..1, 0 where no view sees the point; weights [N], the sums of the cosines)``.
    """
    _no_gradients("average_view_colors", points, normals, images)
    check_tensor("points", points, (None, 3), dtype_kind="float32")
    device = points.device
    count = points.shape[0]
    check_tensor("normals", normals, (count, 3), dtype_kind="float32", device=device)
    check_tensor("world_to_camera", world_to_camera, (None, 4, 4), dtype_kind="float32", device=device)
    view_count = world_to_camera.shape[0]
    check_tensor("intrinsics", intrinsics, (view_count, 3, 3), dtype_kind="float32", device=device)
    check_tensor("images", images, (view_count, None, None, 4), dtype_kind="float32", device=device)
    height, width = images.shape[1], images.shape[2]
    check_tensor("depths", depths, (view_count, height, width), dtype_kind="float32", device=device)
    if image_sizes is None:
        image_sizes = torch.tensor([[width, height]], dtype=torch.int32, device=device).expand(view_count, 2)
    check_tensor("image_sizes", image_sizes, (view_count, 2), dtype_kind="int", device=device)
    image_sizes = image_sizes.to(torch.int32).contiguous()
    if view_count and (bool((image_sizes < 1).any()) or bool((image_sizes[:, 0] > width).any())
                       or bool((image_sizes[:, 1] > height).any())):
        raise ValueError(f"image_sizes must lie in 1..{width} x 1..{height} (the arrays' W x H)")
    if not (depth_tolerance >= 0.0):
        raise ValueError(f"depth_tolerance must be >= 0, got {depth_tolerance}")
    rotation = world_to_camera[:, :3, :3]
    camera_centres = -(rotation.transpose(1, 2) @ world_to_camera[:, :3, 3:4])[..., 0].contiguous()
    focal = torch.stack([intrinsics[:, 0, 0], intrinsics[:, 1, 1], intrinsics[:, 0, 2], intrinsics[:, 1, 2]], dim=1)
    colors = torch.empty(count, 3, device=device)
    weights = torch.empty(count, device=device)
    with torch_stream_scope(device):
        kernels.average_view_colors(
            to_warp(points, dtype=wp.vec3), to_warp(normals, dtype=wp.vec3), to_warp(world_to_camera, dtype=wp.mat44),
            to_warp(focal.contiguous(), dtype=wp.vec4), to_warp(camera_centres, dtype=wp.vec3), to_warp(image_sizes),
            to_warp(images), to_warp(depths), depth_tolerance=float(depth_tolerance), min_cosine=float(min_cosine),
            colors=to_warp(colors, dtype=wp.vec3), weights=to_warp(weights))
    return colors, weights


def nearest_points(known: torch.Tensor, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each query's nearest known point (exact; the lowest index among equally near ones), on a hash grid.

    Rounds of growing radius: the first searches a few typical spacings of the known points, each next one a
    radius four times larger for the queries still without a point, the last one a radius spanning every point.

    Args:
        known: float32 [K,3] points searched (K >= 1).
        queries: float32 [Q,3] query points.

    Returns:
        ``(nearest [Q] int64 indices into known, distance [Q] float32 [m])``.
    """
    _no_gradients("nearest_points", known, queries)
    check_tensor("known", known, (None, 3), dtype_kind="float32")
    device = known.device
    check_tensor("queries", queries, (None, 3), dtype_kind="float32", device=device)
    if known.shape[0] == 0:
        raise ValueError("nearest_points needs at least one known point")
    nearest = torch.full((queries.shape[0],), -1, dtype=torch.int32, device=device)
    distance = torch.full((queries.shape[0],), float("inf"), device=device)
    if queries.shape[0] == 0:
        return nearest.long(), distance
    both = torch.cat([known, queries])
    low, high = both.min(dim=0).values, both.max(dim=0).values
    span = float((high - low).norm()) * 1.01 + 1e-6  # every known point lies within this of every query
    extent = (high - low).clamp_min(1e-6)
    box_surface = 2.0 * float(extent[0] * extent[1] + extent[1] * extent[2] + extent[2] * extent[0])
    radius = min(_FIRST_RADIUS_SPACINGS * (box_surface / known.shape[0]) ** 0.5, span)
    pending = torch.arange(queries.shape[0], dtype=torch.int32, device=device)
    warp_known, warp_queries = to_warp(known, dtype=wp.vec3), to_warp(queries, dtype=wp.vec3)
    warp_nearest, warp_distance = to_warp(nearest), to_warp(distance)
    with torch_stream_scope(device):
        grid = wp.HashGrid(_GRID_CELLS, _GRID_CELLS, _GRID_CELLS, device=warp_known.device)
        while pending.numel():
            grid.build(warp_known, radius)
            kernels.nearest_point(grid, warp_known, warp_queries, to_warp(pending), radius=radius,
                                  nearest=warp_nearest, distance=warp_distance)
            if radius >= span:
                break
            pending = pending[nearest[pending.long()] < 0]
            radius = min(radius * _RADIUS_GROWTH, span)
    return nearest.long(), distance
