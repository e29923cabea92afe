"""UVs for the avatar's surface and its colours baked from the canonical renders: a texture atlas and vertex
colours.

:func:`unwrap` cuts the surface into charts and packs them into one square atlas with xatlas, splitting vertices
along the seams. :func:`bake_texture` rasterizes every triangle into the atlas (each texel on a chart, or within
:data:`MARGIN_TEXELS` of one, learns the 3D point and normal of the chart's closest point) and colours each texel
by the views that see its point: the view-averaged diffuse colour (the renders are at SH degree 0), each view
weighted by the cosine between the normal and the direction to its camera. A view sees a point when the point
faces the camera, projects onto a pixel with alpha >= 0.5 and its camera z lies within a tolerance of that
pixel's depth (:mod:`warpavatar.kernels.texture_bake`). Points no view sees (creases, the soles of the feet) take
the colours of the nearest seen ones, and the rest of the gutter between charts the colour of the nearest chart
texel, so bilinear filtering and mip-maps never blend in black. :func:`vertex_colors` colours points by the same
rule.

Texture coordinates follow glTF (u right, v down from the image's top row): texel (row r, column c) of an
``S x S`` atlas has its centre at UV ((c + 0.5) / S, (r + 0.5) / S). Colours are the renders' own values (sRGB
encoded, as images and glTF's base-colour textures are), 8 bits per channel.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import trimesh

from warpavatar._src.texture_bake import average_view_colors, nearest_points, rasterize_uv_atlas
from warpavatar._src.warp_utils import available_devices
from warpavatar.mesh.mesh_data import CanonicalView

__all__ = ["GUTTER_TEXELS", "CHART_COUNT", "CHART_SMOOTHING", "MARGIN_TEXELS", "DEPTH_TOLERANCE_PIXELS", "unwrap",
           "bake_texture", "vertex_colors"]

GUTTER_TEXELS = 4
"""About the least number of texels between two charts of the atlas (enough for bilinear filtering and the first
two mip-map levels; the baked gutter holds the nearest chart's colours, so coarser levels blend neighbouring
charts' colours, not black)."""

CHART_COUNT = 300
"""The surface's area over this is the largest area of one chart: xatlas's time grows fast with a chart's size,
so a surface cut into a few hundred charts unwraps in a second or two where a handful of large ones take tens."""

CHART_SMOOTHING = 10
"""Laplacian smoothing iterations of the copy of the surface xatlas cuts into charts and flattens: a fused
surface's small bumps otherwise split it into thousands of charts of a few triangles (slow to make, and each costs
a gutter). The UVs are valid for the surface itself: they are a planar layout of its triangles, whatever their
positions."""

_CHART_FILL = 0.38
"""Share of xatlas's atlas its charts fill, gutters not counted (about what it reaches with a gutter of four
texels and a few hundred to two thousand charts)."""

MARGIN_TEXELS = 1.5
"""Texels whose centre lies at most this far outside a chart in UV are baked from the chart's own surface (its
closest point): every texel a bilinear lookup on the chart reads (at most sqrt(2) texels away) is one of them.
Charts lie :data:`GUTTER_TEXELS` apart, so a texel within the margin of one is further from any other."""

DEPTH_TOLERANCE_PIXELS = 3.0
"""Default depth tolerance of the visibility test, in widths of a view's pixel at the surface: wide enough for a
fused surface's offset from the renders' expected depth, narrow enough that a limb a few pixels in front of the
body hides it."""

_NO_VIEW_COLOR = 0.5
"""Grey for points when no view sees any point at all."""


def _as_array(name: str, value, columns: int, dtype) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim != 2 or array.shape[1] != columns:
        raise ValueError(f"{name} must have shape [N,{columns}], got {list(array.shape)}")
    if np.issubdtype(np.dtype(dtype), np.floating) and not np.all(np.isfinite(array)):
        raise ValueError(f"{name} holds non-finite values")
    return np.ascontiguousarray(array, dtype=dtype)


def _faces_array(faces, vertex_count: int) -> np.ndarray:
    array = np.asarray(faces)
    if array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape [F,3], got {array.dtype} {list(array.shape)}")
    if array.size and (array.min() < 0 or array.max() >= vertex_count):
        raise ValueError(f"faces index vertices outside 0..{vertex_count - 1}")
    return np.ascontiguousarray(array, dtype=np.int32)


def _torch_device(device) -> torch.device:
    if device is not None:
        return torch.device(device)
    devices = available_devices()
    return torch.device(devices[1] if len(devices) > 1 else devices[0])


# ---------------------------------------------------------------------------------------------------------
# UVs
# ---------------------------------------------------------------------------------------------------------


def unwrap(vertices, faces, *, size: int = 1024, gutter: int = GUTTER_TEXELS, chart_count: int = CHART_COUNT,
           chart_smoothing: int = CHART_SMOOTHING) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut the surface into charts and pack them into one ``size x size`` atlas (xatlas).

    Args:
        vertices: [V,3] positions [m].
        faces: [F,3] vertex indices.
        size: the atlas's width and height [texels] the packing is made for.
        gutter: about the least number of texels between two charts at ``size`` (even; half of it also
            separates the charts from the atlas's border).
        chart_count: the largest chart's area is the surface's area over this (see :data:`CHART_COUNT`).
        chart_smoothing: Laplacian smoothing iterations of the copy of the surface that xatlas charts (see
            :data:`CHART_SMOOTHING`); 0 charts the surface itself.

    Returns:
        ``(vertices [V',3] float32, faces [F,3] int32, uvs [V',2] float32, source_vertex [V'] int32)``: the mesh
        with its vertices split along the seams (``vertices == input vertices[source_vertex]`` and
        ``source_vertex[faces] == input faces``, face for face), and each vertex's texture coordinates in 0..1
        (u right, v down from the top row). Charts do not overlap.

    Raises:
        ValueError: the arrays are malformed, or an option is out of range.
    """
    import xatlas

    positions = _as_array("vertices", vertices, 3, np.float32)
    indices = _faces_array(faces, positions.shape[0])
    if isinstance(size, bool) or not isinstance(size, int) or size < 16:
        raise ValueError(f"size must be an integer >= 16, got {size!r}")
    if isinstance(gutter, bool) or not isinstance(gutter, int) or not 2 <= gutter <= size // 16:
        raise ValueError(f"gutter must be an integer in 2..{size // 16}, got {gutter!r}")
    if isinstance(chart_count, bool) or not isinstance(chart_count, int) or chart_count < 1:
        raise ValueError(f"chart_count must be a positive integer, got {chart_count!r}")
    if isinstance(chart_smoothing, bool) or not isinstance(chart_smoothing, int) or chart_smoothing < 0:
        raise ValueError(f"chart_smoothing must be a non-negative integer, got {chart_smoothing!r}")
    if indices.shape[0] == 0:
        return positions, indices, np.zeros((positions.shape[0], 2), np.float32), \
            np.arange(positions.shape[0], dtype=np.int32)
    charted = positions
    if chart_smoothing:
        smooth = trimesh.Trimesh(positions, indices, process=False)
        trimesh.smoothing.filter_laplacian(smooth, lamb=0.5, iterations=chart_smoothing)
        charted = np.ascontiguousarray(smooth.vertices, dtype=np.float32)
        if not np.all(np.isfinite(charted)):
            charted = positions
    corners = charted[indices].astype(np.float64)
    area = 0.5 * float(np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                                      axis=1).sum())
    if not area > 0.0:
        raise ValueError("the surface has no area to unwrap")
    atlas = xatlas.Atlas()
    atlas.add_mesh(charted, indices.astype(np.uint32))
    chart_options = xatlas.ChartOptions()
    chart_options.max_chart_area = area / chart_count
    pack_options = xatlas.PackOptions()
    # xatlas dilates each chart by ``padding`` texels plus one for bilinear filtering: charts end up about
    # 2 * (padding + 1) texels apart
    pack_options.padding = max(gutter // 2 - 1, 0)
    pack_options.bilinear = True
    # texels per metre making xatlas's atlas about ``size`` wide (see _CHART_FILL); its scale is corrected below
    pack_options.texels_per_unit = size * math.sqrt(_CHART_FILL / area)
    atlas.generate(chart_options, pack_options)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas packed the charts into {atlas.atlas_count} atlases, expected one")
    source_vertex, new_faces, atlas_uvs = atlas[0]
    # xatlas's UVs are over its atlas's width and height (texel x spans x..x+1, row 0 first); one scale maps
    # its longer side onto ``size`` texels less a border of half the gutter on either side
    texels = atlas_uvs.astype(np.float64) * np.array([atlas.width, atlas.height], dtype=np.float64)
    border = gutter // 2
    uvs = (texels * ((size - 2 * border) / max(atlas.width, atlas.height)) + border) / size
    return (positions[source_vertex], np.ascontiguousarray(new_faces, dtype=np.int32),
            np.clip(uvs, 0.0, 1.0).astype(np.float32), source_vertex.astype(np.int32))


# ---------------------------------------------------------------------------------------------------------
# Colours from the views
# ---------------------------------------------------------------------------------------------------------


def _stack_views(views: list[CanonicalView], device: torch.device) -> dict[str, torch.Tensor]:
    """The views as the kernel's arrays: [C,H,W,4] premultiplied RGBA and [C,H,W] depth padded to the largest
    view, extrinsics, intrinsics and each view's (width, height)."""
    if not isinstance(views, (list, tuple)):
        raise TypeError(f"views must be a list of CanonicalView, got {type(views).__name__}")
    height = max((int(view.height) for view in views), default=1)
    width = max((int(view.width) for view in views), default=1)
    images = np.zeros((len(views), height, width, 4), np.float32)
    depths = np.full((len(views), height, width), np.inf, np.float32)
    for index, view in enumerate(views):
        h, w = int(view.height), int(view.width)
        color, alpha, depth = np.asarray(view.color), np.asarray(view.alpha), np.asarray(view.depth)
        if color.shape != (h, w, 3) or alpha.shape != (h, w) or depth.shape != (h, w):
            raise ValueError(f"view {index}: color, alpha and depth must be [{h},{w},3], [{h},{w}] and [{h},{w}], "
                             f"got {list(color.shape)}, {list(alpha.shape)} and {list(depth.shape)}")
        if np.asarray(view.K).shape != (3, 3) or np.asarray(view.world_to_camera).shape != (4, 4):
            raise ValueError(f"view {index}: K must be [3,3] and world_to_camera [4,4]")
        images[index, :h, :w, :3] = color
        images[index, :h, :w, 3] = alpha
        depths[index, :h, :w] = np.where(np.isfinite(depth), depth, np.inf)
    as_tensor = lambda array, dtype=torch.float32: torch.as_tensor(np.asarray(array), dtype=dtype, device=device)
    return {
        "world_to_camera": as_tensor(np.stack([v.world_to_camera for v in views]) if views else np.zeros((0, 4, 4))),
        "intrinsics": as_tensor(np.stack([v.K for v in views]) if views else np.zeros((0, 3, 3))),
        "images": as_tensor(images),
        "depths": as_tensor(depths),
        "image_sizes": as_tensor([[int(v.width), int(v.height)] for v in views] if views else np.zeros((0, 2)),
                                 torch.int32),
    }


def _default_depth_tolerance(points: np.ndarray, views: list[CanonicalView]) -> float:
    """:data:`DEPTH_TOLERANCE_PIXELS` times the median over the views of the width one pixel covers at the
    points' median [m]."""
    if points.shape[0] == 0 or not views:
        return 0.0
    centre = np.median(points, axis=0).astype(np.float64)
    widths = []
    for view in views:
        matrix = np.asarray(view.world_to_camera, dtype=np.float64)
        depth = float(matrix[2, :3] @ centre + matrix[2, 3])
        widths.append(abs(depth) / float(np.asarray(view.K)[0, 0]))
    return DEPTH_TOLERANCE_PIXELS * float(np.median(widths))


def _point_colors(points: torch.Tensor, normals: torch.Tensor, stacked: dict, depth_tolerance: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """([N,3] float colours in 0..1, [N] bool seen): points no view sees take the colour of the nearest seen one
    (grey when none is seen)."""
    colors, weights = average_view_colors(points, normals, stacked["world_to_camera"], stacked["intrinsics"],
                                          stacked["images"], stacked["depths"], depth_tolerance=depth_tolerance,
                                          image_sizes=stacked["image_sizes"])
    seen = weights > 0
    if bool(seen.all()):
        return colors, seen
    if not bool(seen.any()):
        return torch.full_like(colors, _NO_VIEW_COLOR), seen
    unseen = (~seen).nonzero()[:, 0]
    seen_index = seen.nonzero()[:, 0]
    nearest, _ = nearest_points(points[seen_index].contiguous(), points[unseen].contiguous())
    colors[unseen] = colors[seen_index[nearest]]
    return colors, seen


def _to_uint8(colors: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(colors * 255.0), 0, 255).astype(np.uint8)


def vertex_colors(vertices, normals, views: list[CanonicalView], *, depth_tolerance: float | None = None,
                  device=None) -> np.ndarray:
    """Each vertex's colour, averaged over the views that see it (the rule in the module's doc); a vertex no view
    sees takes the colour of the nearest vertex one does.

    Args:
        vertices: [V,3] positions [m].
        normals: [V,3] unit outward normals.
        views: the canonical renders (:func:`warpavatar.mesh.views.render_canonical_views`).
        depth_tolerance: largest |camera z - rendered depth| of a visible point [m]; by default
            :data:`DEPTH_TOLERANCE_PIXELS` widths of a view's pixel at the surface.
        device: where the kernels run (default: CUDA when present, else the CPU).

    Returns:
        [V,3] uint8 RGB (sRGB encoded, as the renders).
    """
    positions = _as_array("vertices", vertices, 3, np.float32)
    directions = _as_array("normals", normals, 3, np.float32)
    if directions.shape[0] != positions.shape[0]:
        raise ValueError(f"normals has {directions.shape[0]} rows, vertices {positions.shape[0]}")
    device = _torch_device(device)
    with torch.no_grad():
        stacked = _stack_views(views, device)
        tolerance = _default_depth_tolerance(positions, views) if depth_tolerance is None else float(depth_tolerance)
        colors, _ = _point_colors(torch.as_tensor(positions, device=device), torch.as_tensor(directions, device=device),
                                  stacked, tolerance)
    return _to_uint8(colors.cpu().numpy())


def bake_texture(vertices, faces, normals, uvs, views: list[CanonicalView], *, size: int = 1024,
                 depth_tolerance: float | None = None, device=None) -> np.ndarray:
    """Bake the views' colours into a texture atlas over the mesh's UVs.

    Every texel whose centre lies on a triangle in UV, or at most :data:`MARGIN_TEXELS` outside one, gets the
    colour of the triangle's closest 3D point averaged over the views that see it; texels no view sees get the
    colours of their triangle's corners, interpolated (each corner coloured like :func:`vertex_colors`); the rest
    of the gutter between charts gets the colour of the nearest of those texels.

    Args:
        vertices: [V,3] positions [m], split along the UV seams (:func:`unwrap`).
        faces: [F,3] vertex indices.
        normals: [V,3] unit outward vertex normals.
        uvs: [V,2] texture coordinates in 0..1 (u right, v down from the top row), charts not overlapping.
        views: the canonical renders (:func:`warpavatar.mesh.views.render_canonical_views`).
        size: the atlas's width and height [texels].
        depth_tolerance: largest |camera z - rendered depth| of a visible point [m]; by default
            :data:`DEPTH_TOLERANCE_PIXELS` widths of a view's pixel at the surface.
        device: where the kernels run (default: CUDA when present, else the CPU).

    Returns:
        [S,S,3] uint8 RGB atlas, row 0 at the top (sRGB encoded, as the renders).
    """
    positions = _as_array("vertices", vertices, 3, np.float32)
    indices = _faces_array(faces, positions.shape[0])
    directions = _as_array("normals", normals, 3, np.float32)
    coordinates = _as_array("uvs", uvs, 2, np.float32)
    for name, array in (("normals", directions), ("uvs", coordinates)):
        if array.shape[0] != positions.shape[0]:
            raise ValueError(f"{name} has {array.shape[0]} rows, vertices {positions.shape[0]}")
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}")
    device = _torch_device(device)
    with torch.no_grad():
        stacked = _stack_views(views, device)
        tolerance = _default_depth_tolerance(positions, views) if depth_tolerance is None else float(depth_tolerance)
        vertex_tensor = torch.as_tensor(positions, device=device)
        normal_tensor = torch.as_tensor(directions, device=device)
        texel_face, texel_barycentric, texel_point, texel_normal, _ = rasterize_uv_atlas(
            vertex_tensor, torch.as_tensor(indices, device=device), normal_tensor,
            torch.as_tensor(coordinates, device=device), size=size, margin=MARGIN_TEXELS)
        covered = texel_face >= 0
        atlas = torch.zeros(size, size, 3, device=device)
        if bool(covered.any()):
            colors, weights = average_view_colors(
                texel_point[covered], texel_normal[covered], stacked["world_to_camera"], stacked["intrinsics"],
                stacked["images"], stacked["depths"], depth_tolerance=tolerance, image_sizes=stacked["image_sizes"])
            unseen = weights <= 0
            if bool(unseen.any()):
                corner_colors, _ = _point_colors(vertex_tensor, normal_tensor, stacked, tolerance)
                corners = torch.as_tensor(indices, device=device).long()[texel_face[covered][unseen].long()]
                colors[unseen] = (texel_barycentric[covered][unseen][:, :, None] * corner_colors[corners]).sum(dim=1)
            atlas[covered] = colors
        atlas = _to_uint8(atlas.cpu().numpy())
        covered = covered.cpu().numpy()
    return _fill_gutter(atlas, covered)


def _fill_gutter(atlas: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Every texel outside the charts takes the colour of the nearest covered texel (Euclidean, in texels)."""
    if covered.all() or not covered.any():
        return atlas
    # each texel's label is that of its nearest zero (covered) texel, each covered texel having one of its own
    _, labels = cv2.distanceTransformWithLabels((~covered).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    rows, columns = np.nonzero(covered)
    lookup = np.zeros(labels.max() + 1, dtype=np.int64)
    lookup[labels[rows, columns]] = rows * atlas.shape[1] + columns
    nearest = lookup[labels]
    return atlas.reshape(-1, 3)[nearest.reshape(-1)].reshape(atlas.shape)
