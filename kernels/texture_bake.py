"""Texture-baking kernels: triangles rasterized into a UV atlas, and surface points coloured from camera views.

Four kernels, none differentiated:

* :func:`claim_texels_kernel` then :func:`texel_surface_kernel`: triangles rasterized into a UV atlas. One thread
  per triangle walks the texels of its box, grown by a margin, and claims each texel whose centre lies within the
  margin of it with an atomic minimum of a 64-bit key (its distance to the centre, then its index), so the
  nearest triangle wins, the lowest index on a tie, whatever order threads run in. Then one thread per texel
  writes its triangle, the distance and the barycentric coordinates of the triangle's closest point to the
  centre, with the 3D point and unit normal they interpolate. Texel ``(row r, column c)`` of an ``S x S`` atlas
  has its centre at UV ``((c + 0.5) / S, (r + 0.5) / S)`` (glTF's convention: u right, v down from the top
  row). A margin of a texel and a half covers every texel a bilinear lookup on a triangle reads, so those take
  the colour of their own chart's surface (charts lie further apart than twice that).
* :func:`average_view_colors_kernel`: one thread per surface point loops over the views and averages the
  colour of those that see it, weighted by the cosine between its normal and its direction to the camera. A
  view sees the point when the point faces the camera (cosine above ``min_cosine``), projects into the image
  in front of the camera, the pixel nearest to its projection is covered (alpha >= 0.5) and that pixel's depth
  is within ``depth_tolerance`` of the point's camera z. The colour is the view's image bilinearly sampled at
  the projection, premultiplied colour divided by alpha (views are rendered on black).
* :func:`nearest_point_kernel`: one thread per query finds the nearest of a set of known points within a radius
  on a ``warp.HashGrid`` (ties go to the lower index); the bridge repeats it with growing radii for the queries
  left without one. Points no view sees take the colours of their nearest seen points.

Cameras follow OpenCV (x right, y down, z forward; pixel centres at integer coordinates). Launchers take
Warp arrays, check their sizes and skip empty work; the torch bridge is :mod:`warpavatar._src.texture_bake`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = [
    "COVERAGE_ALPHA",
    "NO_TRIANGLE",
    "closest_on_triangle",
    "claim_texels_kernel",
    "texel_surface_kernel",
    "average_view_colors_kernel",
    "nearest_point_kernel",
    "rasterize_uv",
    "average_view_colors",
    "nearest_point",
]

COVERAGE_ALPHA = 0.5
"""Least alpha of a pixel that sees a surface (the views' depth is defined from this alpha up)."""


# ---------------------------------------------------------------------------------------------------------
# UV rasterization
# ---------------------------------------------------------------------------------------------------------

NO_TRIANGLE = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
"""A texel's key before any triangle claims it."""

DISTANCE_STEPS = wp.constant(wp.float32(1048576.0))
"""Steps per texel of the distance stored in a texel's key (2^20)."""


@wp.func
def _edge_function(a: wp.vec2, b: wp.vec2, p: wp.vec2):
    """Twice the signed area of the triangle (a, b, p)."""
    return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])


@wp.func
def _closest_on_segment(a: wp.vec2, b: wp.vec2, p: wp.vec2):
    """(distance from p to the segment a-b, the closest point's fraction from a to b)."""
    ab = b - a
    length_sq = wp.dot(ab, ab)
    s = float(0.0)
    if length_sq > 0.0:
        s = wp.clamp(wp.dot(p - a, ab) / length_sq, 0.0, 1.0)
    return wp.length(p - (a + s * ab)), s


@wp.func
def closest_on_triangle(t0: wp.vec2, t1: wp.vec2, t2: wp.vec2, area: float, p: wp.vec2):
    """(distance from p to the triangle (t0, t1, t2) of signed doubled area ``area`` != 0, 0 inside; the
    barycentric coordinates of the triangle's closest point)."""
    w0 = _edge_function(t1, t2, p) / area
    w1 = _edge_function(t2, t0, p) / area
    w2 = _edge_function(t0, t1, p) / area
    if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0:
        total = w0 + w1 + w2
        return float(0.0), wp.vec3(w0 / total, w1 / total, w2 / total)
    d01, s01 = _closest_on_segment(t0, t1, p)
    d12, s12 = _closest_on_segment(t1, t2, p)
    d20, s20 = _closest_on_segment(t2, t0, p)
    distance = d01
    barycentric = wp.vec3(1.0 - s01, s01, 0.0)
    if d12 < distance:
        distance = d12
        barycentric = wp.vec3(0.0, 1.0 - s12, s12)
    if d20 < distance:
        distance = d20
        barycentric = wp.vec3(s20, 0.0, 1.0 - s20)
    return distance, barycentric


@wp.func
def _texel_triangle(uvs: wp.array(dtype=wp.vec2), faces: wp.array2d(dtype=wp.int32), f: int, scale: float):
    t0 = uvs[faces[f, 0]] * scale
    t1 = uvs[faces[f, 1]] * scale
    t2 = uvs[faces[f, 2]] * scale
    return t0, t1, t2, _edge_function(t0, t1, t2)


@wp.kernel(enable_backward=False)
def claim_texels_kernel(
    uvs: wp.array(dtype=wp.vec2),
    faces: wp.array2d(dtype=wp.int32),
    size: int,
    margin: float,
    texel_key: wp.array2d(dtype=wp.int64),
):
    """One thread per triangle ``f``: every texel ``[r, c]`` whose centre lies within ``margin`` texels of it gets
    ``texel_key = min(texel_key, distance in 2^-20 texels << 32 | f)``: the nearest triangle, the lowest index
    among equally near ones (those sharing an edge a centre lies on). Triangles of no UV area claim nothing."""
    f = wp.tid()
    t0, t1, t2, area = _texel_triangle(uvs, faces, f, float(size))
    if area == 0.0 or not wp.isfinite(area):
        return
    column_first = wp.max(int(wp.ceil(wp.min(wp.min(t0[0], t1[0]), t2[0]) - 0.5 - margin)), 0)
    column_last = wp.min(int(wp.floor(wp.max(wp.max(t0[0], t1[0]), t2[0]) - 0.5 + margin)), size - 1)
    row_first = wp.max(int(wp.ceil(wp.min(wp.min(t0[1], t1[1]), t2[1]) - 0.5 - margin)), 0)
    row_last = wp.min(int(wp.floor(wp.max(wp.max(t0[1], t1[1]), t2[1]) - 0.5 + margin)), size - 1)
    for row in range(row_first, row_last + 1):
        for column in range(column_first, column_last + 1):
            p = wp.vec2(float(column) + 0.5, float(row) + 0.5)
            distance, barycentric = closest_on_triangle(t0, t1, t2, area, p)
            if distance <= margin:
                steps = wp.int64(wp.round(distance * DISTANCE_STEPS))
                wp.atomic_min(texel_key, row, column, (steps << wp.int64(32)) | wp.int64(f))


@wp.kernel(enable_backward=False)
def texel_surface_kernel(
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    uvs: wp.array(dtype=wp.vec2),
    faces: wp.array2d(dtype=wp.int32),
    texel_key: wp.array2d(dtype=wp.int64),
    texel_face: wp.array2d(dtype=wp.int32),
    texel_distance: wp.array2d(dtype=float),
    texel_barycentric: wp.array2d(dtype=wp.vec3),
    texel_point: wp.array2d(dtype=wp.vec3),
    texel_normal: wp.array2d(dtype=wp.vec3),
):
    """One thread per texel ``[r, c]``: the triangle that claimed it (-1: none), the distance [texels] from the
    centre to it (0 inside, inf for none), and the barycentric coordinates, 3D point and unit normal of the
    triangle's closest point to the centre (0 for none)."""
    row, column = wp.tid()
    key = texel_key[row, column]
    if key == NO_TRIANGLE:
        texel_face[row, column] = -1
        texel_distance[row, column] = wp.inf
        texel_barycentric[row, column] = wp.vec3(0.0, 0.0, 0.0)
        texel_point[row, column] = wp.vec3(0.0, 0.0, 0.0)
        texel_normal[row, column] = wp.vec3(0.0, 0.0, 0.0)
        return
    f = int(key & wp.int64(0xFFFFFFFF))
    t0, t1, t2, area = _texel_triangle(uvs, faces, f, float(texel_key.shape[0]))
    distance, b = closest_on_triangle(t0, t1, t2, area, wp.vec2(float(column) + 0.5, float(row) + 0.5))
    i0 = faces[f, 0]
    i1 = faces[f, 1]
    i2 = faces[f, 2]
    normal = b[0] * normals[i0] + b[1] * normals[i1] + b[2] * normals[i2]
    length = wp.length(normal)
    if length > 0.0:
        normal = normal / length
    texel_face[row, column] = f
    texel_distance[row, column] = distance
    texel_barycentric[row, column] = b
    texel_point[row, column] = b[0] * positions[i0] + b[1] * positions[i1] + b[2] * positions[i2]
    texel_normal[row, column] = normal


def rasterize_uv(positions: wp.array, normals: wp.array, uvs: wp.array, faces: wp.array2d, *, size: int,
                 margin: float, texel_key: wp.array2d, texel_face: wp.array2d, texel_distance: wp.array2d,
                 texel_barycentric: wp.array2d, texel_point: wp.array2d, texel_normal: wp.array2d) -> None:
    """Rasterize triangles into an ``size x size`` UV atlas, ``margin`` texels beyond their edges (launcher of
    :func:`claim_texels_kernel` then :func:`texel_surface_kernel`).

    Args:
        positions: [V] vec3 vertex positions [m].
        normals: [V] vec3 vertex normals (interpolated, then normalized per texel).
        uvs: [V] vec2 texture coordinates in 0..1 (u right, v down from the top row).
        faces: [F,3] int32 vertex indices.
        size: the atlas's width and height [texels].
        margin: texels whose centre lies at most this far [texels] outside a triangle are claimed by it too.
        texel_key: [S,S] int64 scratch, filled with ``NO_TRIANGLE`` by the caller.
        texel_face: [S,S] int32 output, the claiming triangle or -1.
        texel_distance: [S,S] float32 output [texels], 0 inside a triangle, inf where none claims.
        texel_barycentric, texel_point, texel_normal: [S,S] vec3 outputs.
    """
    vertex_count = positions.shape[0]
    for name, array in (("normals", normals), ("uvs", uvs)):
        if array.shape[0] != vertex_count:
            raise ValueError(f"{name} has {array.shape[0]} rows, positions {vertex_count}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F,3], got {faces.shape}")
    for name, array in (("texel_key", texel_key), ("texel_face", texel_face), ("texel_distance", texel_distance),
                        ("texel_barycentric", texel_barycentric), ("texel_point", texel_point),
                        ("texel_normal", texel_normal)):
        if array.shape != (size, size):
            raise ValueError(f"{name} must be [{size},{size}], got {array.shape}")
    if size == 0:
        return
    launch(claim_texels_kernel, dim=faces.shape[0], device=positions.device,
           inputs=[uvs, faces, int(size), float(margin)], outputs=[texel_key])
    launch(texel_surface_kernel, dim=(size, size), device=positions.device,
           inputs=[positions, normals, uvs, faces, texel_key],
           outputs=[texel_face, texel_distance, texel_barycentric, texel_point, texel_normal])


# ---------------------------------------------------------------------------------------------------------
# Colour from the views
# ---------------------------------------------------------------------------------------------------------


@wp.func
def _bilinear_rgba(images: wp.array4d(dtype=float), view: int, x: float, y: float, width: int, height: int):
    """The view's RGBA bilinearly interpolated at pixel coordinates (x, y), neighbours clamped to the image."""
    column = wp.floor(x)
    row = wp.floor(y)
    fx = x - column
    fy = y - row
    c0 = wp.clamp(int(column), 0, width - 1)
    c1 = wp.clamp(int(column) + 1, 0, width - 1)
    r0 = wp.clamp(int(row), 0, height - 1)
    r1 = wp.clamp(int(row) + 1, 0, height - 1)
    result = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for k in range(4):
        top = images[view, r0, c0, k] + fx * (images[view, r0, c1, k] - images[view, r0, c0, k])
        bottom = images[view, r1, c0, k] + fx * (images[view, r1, c1, k] - images[view, r1, c0, k])
        result[k] = top + fy * (bottom - top)
    return result


@wp.kernel(enable_backward=False)
def average_view_colors_kernel(
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    world_to_camera: wp.array(dtype=wp.mat44),
    intrinsics: wp.array(dtype=wp.vec4),
    camera_centres: wp.array(dtype=wp.vec3),
    image_sizes: wp.array2d(dtype=wp.int32),
    images: wp.array4d(dtype=float),
    depths: wp.array3d(dtype=float),
    depth_tolerance: float,
    min_cosine: float,
    colors: wp.array(dtype=wp.vec3),
    weights: wp.array(dtype=float),
):
    """One thread per point ``i``: ``colors[i]`` = the cosine-weighted mean colour of the views that see it (0 when
    none does) and ``weights[i]`` = the sum of their cosines."""
    i = wp.tid()
    p = points[i]
    n = normals[i]
    total = wp.vec3(0.0, 0.0, 0.0)
    weight = float(0.0)
    for view in range(world_to_camera.shape[0]):
        to_camera = camera_centres[view] - p
        distance = wp.length(to_camera)
        if distance <= 0.0:
            continue
        cosine = wp.dot(n, to_camera) / distance
        if not (cosine > min_cosine):
            continue
        m = world_to_camera[view]
        z = m[2, 0] * p[0] + m[2, 1] * p[1] + m[2, 2] * p[2] + m[2, 3]
        if not (z > 0.0):
            continue
        k = intrinsics[view]
        x = k[0] * (m[0, 0] * p[0] + m[0, 1] * p[1] + m[0, 2] * p[2] + m[0, 3]) / z + k[2]
        y = k[1] * (m[1, 0] * p[0] + m[1, 1] * p[1] + m[1, 2] * p[2] + m[1, 3]) / z + k[3]
        width = image_sizes[view, 0]
        height = image_sizes[view, 1]
        # the nearest pixel (centres at integers) decides visibility
        if not (x > -0.5 and x < float(width) - 0.5 and y > -0.5 and y < float(height) - 0.5):
            continue
        column = int(wp.floor(x + 0.5))
        row = int(wp.floor(y + 0.5))
        if not (images[view, row, column, 3] >= COVERAGE_ALPHA):
            continue
        if not (wp.abs(z - depths[view, row, column]) <= depth_tolerance):
            continue
        rgba = _bilinear_rgba(images, view, x, y, width, height)
        alpha = wp.max(rgba[3], 1.0e-6)
        colour = wp.vec3(wp.clamp(rgba[0] / alpha, 0.0, 1.0), wp.clamp(rgba[1] / alpha, 0.0, 1.0),
                         wp.clamp(rgba[2] / alpha, 0.0, 1.0))
        total += cosine * colour
        weight += cosine
    if weight > 0.0:
        colors[i] = total / weight
    else:
        colors[i] = wp.vec3(0.0, 0.0, 0.0)
    weights[i] = weight


def average_view_colors(points: wp.array, normals: wp.array, world_to_camera: wp.array, intrinsics: wp.array,
                        camera_centres: wp.array, image_sizes: wp.array2d, images: wp.array4d, depths: wp.array3d,
                        *, depth_tolerance: float, min_cosine: float, colors: wp.array, weights: wp.array) -> None:
    """Colour points from the views that see them (launcher of :func:`average_view_colors_kernel`).

    Args:
        points: [N] vec3 surface points [m].
        normals: [N] vec3 unit outward normals.
        world_to_camera: [C] mat44 OpenCV extrinsics.
        intrinsics: [C] vec4 (fx, fy, cx, cy) [px].
        camera_centres: [C] vec3 camera positions [m] (``-R^T t`` of each extrinsic).
        image_sizes: [C,2] int32 (width, height) of each view [px], at most the arrays' W and H.
        images: [C,H,W,4] float32 premultiplied RGB and alpha, 0..1.
        depths: [C,H,W] float32 camera z of the surface each pixel sees [m] (``inf`` where none).
        depth_tolerance: largest |point z - pixel depth| of a visible point [m].
        min_cosine: a view sees only points whose normal's cosine to it exceeds this.
        colors: [N] vec3 output (0..1; 0 where no view sees the point).
        weights: [N] float32 output, the sum of the seeing views' cosines.
    """
    count = points.shape[0]
    view_count = world_to_camera.shape[0]
    for name, array in (("normals", normals), ("colors", colors), ("weights", weights)):
        if array.shape[0] != count:
            raise ValueError(f"{name} has {array.shape[0]} rows, points {count}")
    for name, array in (("intrinsics", intrinsics), ("camera_centres", camera_centres), ("image_sizes", image_sizes),
                        ("images", images), ("depths", depths)):
        if array.shape[0] != view_count:
            raise ValueError(f"{name} has {array.shape[0]} views, world_to_camera {view_count}")
    if images.ndim != 4 or images.shape[3] != 4 or depths.shape != images.shape[:3]:
        raise ValueError(f"images must be [C,H,W,4] and depths [C,H,W], got {images.shape} and {depths.shape}")
    if count == 0:
        return
    launch(average_view_colors_kernel, dim=count, device=points.device,
           inputs=[points, normals, world_to_camera, intrinsics, camera_centres, image_sizes, images, depths,
                   float(depth_tolerance), float(min_cosine)],
           outputs=[colors, weights])


# ---------------------------------------------------------------------------------------------------------
# Nearest known point
# ---------------------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def nearest_point_kernel(
    grid: wp.uint64,
    known: wp.array(dtype=wp.vec3),
    queries: wp.array(dtype=wp.vec3),
    query_index: wp.array(dtype=wp.int32),
    radius: float,
    nearest: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=float),
):
    """One thread per listed query ``j`` (``i = query_index[j]``): ``nearest[i]`` = the index of the nearest known
    point at most ``radius`` away (the lowest index among equally near ones) and ``distance[i]`` its distance;
    both left as they were when none is that near."""
    j = wp.tid()
    i = query_index[j]
    q = queries[i]
    best = int(-1)
    best_distance = radius
    neighbours = wp.hash_grid_query(grid, q, radius)
    candidate = int(0)
    while wp.hash_grid_query_next(neighbours, candidate):
        d = wp.length(known[candidate] - q)
        if d < best_distance or (d == best_distance and (best < 0 or candidate < best)):
            best = candidate
            best_distance = d
    if best >= 0:
        nearest[i] = best
        distance[i] = best_distance


def nearest_point(grid: wp.HashGrid, known: wp.array, queries: wp.array, query_index: wp.array, *, radius: float,
                  nearest: wp.array, distance: wp.array) -> None:
    """Search the listed queries' nearest known points within ``radius`` (launcher of
    :func:`nearest_point_kernel`).

    Args:
        grid: a hash grid built over ``known`` with cells at least ``radius`` wide.
        known: [K] vec3 points searched.
        queries: [Q] vec3 query points.
        query_index: [M] int32 the queries to search (indices into ``queries``).
        radius: largest distance searched [m].
        nearest: [Q] int32 output, written where a known point lies within ``radius``.
        distance: [Q] float32 output, likewise.
    """
    for name, array in (("nearest", nearest), ("distance", distance)):
        if array.shape[0] != queries.shape[0]:
            raise ValueError(f"{name} has {array.shape[0]} rows, queries {queries.shape[0]}")
    if query_index.shape[0] == 0 or known.shape[0] == 0:
        return
    launch(nearest_point_kernel, dim=query_index.shape[0], device=queries.device,
           inputs=[grid.id, known, queries, query_index, float(radius)], outputs=[nearest, distance])
