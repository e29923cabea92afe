"""Mesh rendering kernels: camera rays cast against a triangle mesh's BVH, and the hits shaded.

A triangle mesh is rendered in two passes, one thread per pixel each, without gradients:

* :data:`cast_camera_rays_kernel`: the ray of pixel (column i, row j) leaves the camera centre through the
  pixel's centre at integer coordinates (``docs/conventions.md``): camera-space direction
  ``((i - cx) / fx, (j - cy) / fy, 1)``, rotated to world space by ``R^T`` of ``world_to_camera``. The closest
  hit on either side of a triangle (``wp.mesh_query_ray`` on Warp's BVH, :class:`warp.Mesh`) gives the face
  index (-1 where nothing is hit), the barycentric weights ``(b1, b2)`` of the face's second and third vertices
  (the first one's is ``1 - b1 - b2``) and the camera-space depth: the direction's camera z is 1, so the ray
  parameter of the hit is its depth ``z``.
* :data:`shade_mesh_hits_kernel`: the colour of each hit pixel from the face's per-vertex texture coordinates
  (interpolated, then the texture sampled bilinearly), from its per-vertex colours (interpolated), or a constant;
  the background where nothing is hit, and a 0/1 alpha.

Texture convention (glTF's): ``u`` runs right and ``v`` down from the image's top row (row 0); texel
``(column c, row r)`` of an ``S_w x S_h`` texture is centred at ``((c + 0.5) / S_w, (r + 0.5) / S_h)``.
Coordinates past the outer texel centres are clamped to the edge texels (clamp-to-edge), never wrapped.
Launchers take Warp arrays, check their sizes and skip empty work; the torch bridge is
:mod:`warpavatar._src.mesh_render`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = [
    "SHADE_CONSTANT",
    "SHADE_VERTEX_COLORS",
    "SHADE_TEXTURE",
    "MISS_FACE",
    "MAX_RAY_DEPTH",
    "build_mesh",
    "cast_camera_rays",
    "shade_mesh_hits",
]

SHADE_CONSTANT = 0
"""Shading mode: every hit pixel takes one colour."""

SHADE_VERTEX_COLORS = 1
"""Shading mode: the face's per-vertex colours interpolated with the hit's barycentric weights."""

SHADE_TEXTURE = 2
"""Shading mode: the face's per-vertex texture coordinates interpolated, then the texture sampled bilinearly."""

MISS_FACE = -1
"""Face index of a pixel whose ray hits nothing."""

MAX_RAY_DEPTH = 1.0e10
"""Largest camera-space depth [world units] a hit may have (the rasterizer's far plane)."""


@wp.func
def _texel(texture: wp.array2d(dtype=wp.vec3), row: int, column: int):
    """Texel at (row, column), both clamped into the texture (clamp-to-edge)."""
    r = wp.clamp(row, 0, texture.shape[0] - 1)
    c = wp.clamp(column, 0, texture.shape[1] - 1)
    return texture[r, c]


@wp.func
def _sample_bilinear(texture: wp.array2d(dtype=wp.vec3), uv: wp.vec2):
    """Bilinear sample of ``texture`` [rows, columns] at glTF texture coordinates ``uv`` (texel centres at
    ``(c + 0.5) / S``), clamped to the edge texels."""
    rows = texture.shape[0]
    columns = texture.shape[1]
    x = wp.clamp(uv[0] * float(columns) - 0.5, 0.0, float(columns - 1))
    y = wp.clamp(uv[1] * float(rows) - 0.5, 0.0, float(rows - 1))
    x0 = wp.min(int(wp.floor(x)), columns - 1)
    y0 = wp.min(int(wp.floor(y)), rows - 1)
    fx = x - float(x0)
    fy = y - float(y0)
    top = _texel(texture, y0, x0) * (1.0 - fx) + _texel(texture, y0, x0 + 1) * fx
    bottom = _texel(texture, y0 + 1, x0) * (1.0 - fx) + _texel(texture, y0 + 1, x0 + 1) * fx
    return top * (1.0 - fy) + bottom * fy


@wp.kernel(enable_backward=False)
def cast_camera_rays_kernel(
    mesh: wp.uint64,
    intrinsics: wp.array(dtype=wp.mat33),
    world_to_camera: wp.array(dtype=wp.mat44),
    face_index: wp.array2d(dtype=wp.int32),
    barycentrics: wp.array2d(dtype=wp.vec2),
    depth: wp.array2d(dtype=wp.float32),
):
    """One thread per pixel (row j, column i): the closest hit of the pixel's camera ray on ``mesh``.

    Outputs per pixel: ``face_index`` (-1 for none), ``barycentrics`` (b1, b2) of the face's second and third
    vertices (0 for none) and ``depth``, the hit's camera-space z [world units] (0 for none).
    """
    j, i = wp.tid()
    k = intrinsics[0]
    m = world_to_camera[0]
    direction_camera = wp.vec3((float(i) - k[0, 2]) / k[0, 0], (float(j) - k[1, 2]) / k[1, 1], 1.0)
    rotation = wp.mat33(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])
    translation = wp.vec3(m[0, 3], m[1, 3], m[2, 3])
    origin = -(wp.transpose(rotation) @ translation)
    direction = wp.transpose(rotation) @ direction_camera
    hit = wp.mesh_query_ray(mesh, origin, direction, MAX_RAY_DEPTH)
    if hit.result:
        # Warp's weights (u, v) belong to the face's first and second vertices
        face_index[j, i] = hit.face
        barycentrics[j, i] = wp.vec2(hit.v, 1.0 - hit.u - hit.v)
        depth[j, i] = hit.t
    else:
        face_index[j, i] = MISS_FACE
        barycentrics[j, i] = wp.vec2(0.0, 0.0)
        depth[j, i] = 0.0


@wp.kernel(enable_backward=False)
def shade_mesh_hits_kernel(
    face_index: wp.array2d(dtype=wp.int32),
    barycentrics: wp.array2d(dtype=wp.vec2),
    faces: wp.array2d(dtype=wp.int32),
    mode: int,
    vertex_uvs: wp.array(dtype=wp.vec2),
    texture: wp.array2d(dtype=wp.vec3),
    vertex_colors: wp.array(dtype=wp.vec3),
    constant_color: wp.vec3,
    background: wp.array(dtype=wp.vec3),
    image: wp.array2d(dtype=wp.vec3),
    alpha: wp.array2d(dtype=wp.float32),
):
    """One thread per pixel: the hit's colour (``mode``: :data:`SHADE_CONSTANT`, :data:`SHADE_VERTEX_COLORS`
    or :data:`SHADE_TEXTURE`; the arrays a mode does not read may be null) and alpha 1, or the background and
    alpha 0 where nothing was hit."""
    j, i = wp.tid()
    face = face_index[j, i]
    if face < 0:
        image[j, i] = background[0]
        alpha[j, i] = 0.0
        return
    b = barycentrics[j, i]
    w0 = 1.0 - b[0] - b[1]
    a = faces[face, 0]
    c1 = faces[face, 1]
    c2 = faces[face, 2]
    color = constant_color
    if mode == SHADE_TEXTURE:
        uv = vertex_uvs[a] * w0 + vertex_uvs[c1] * b[0] + vertex_uvs[c2] * b[1]
        color = _sample_bilinear(texture, uv)
    elif mode == SHADE_VERTEX_COLORS:
        color = vertex_colors[a] * w0 + vertex_colors[c1] * b[0] + vertex_colors[c2] * b[1]
    image[j, i] = color
    alpha[j, i] = 1.0


def build_mesh(points: wp.array, face_indices: wp.array) -> wp.Mesh:
    """Warp's BVH-backed mesh of ``points`` ``vec3[V]`` (world units) and ``face_indices`` ``int32[3 F]`` (the
    faces' vertex indices, flattened), on ``points``' device. The caller keeps both arrays alive while the mesh
    is used."""
    if face_indices.shape[0] % 3:
        raise ValueError(f"face_indices must hold 3 indices a face, got {face_indices.shape[0]}")
    if face_indices.shape[0] == 0:
        raise ValueError("a mesh needs at least one face")
    return wp.Mesh(points=points, indices=face_indices)


def cast_camera_rays(mesh: wp.Mesh, intrinsics: wp.array, world_to_camera: wp.array, face_index: wp.array,
                     barycentrics: wp.array, depth: wp.array) -> None:
    """Launch :data:`cast_camera_rays_kernel` over the image ``face_index`` spans.

    Args:
        mesh: the posed mesh (:func:`build_mesh`).
        intrinsics: ``mat33[1]`` pinhole K [px] (pixel centres at integer coordinates).
        world_to_camera: ``mat44[1]`` rigid OpenCV-convention extrinsic.
        face_index: ``int32[H, W]`` output, -1 where nothing is hit.
        barycentrics: ``vec2[H, W]`` output, weights of each face's second and third vertices.
        depth: ``float32[H, W]`` output, camera-space z [world units], 0 where nothing is hit.
    """
    height, width = face_index.shape
    for name, array in (("barycentrics", barycentrics), ("depth", depth)):
        if tuple(array.shape) != (height, width):
            raise ValueError(f"{name} has shape {tuple(array.shape)}, face_index {(height, width)}")
    if intrinsics.shape[0] != 1 or world_to_camera.shape[0] != 1:
        raise ValueError("intrinsics and world_to_camera must hold one matrix each")
    launch(cast_camera_rays_kernel, dim=(height, width), inputs=[mesh.id, intrinsics, world_to_camera],
           outputs=[face_index, barycentrics, depth], device=face_index.device)


def shade_mesh_hits(face_index: wp.array, barycentrics: wp.array, faces: wp.array, background: wp.array,
                    image: wp.array, alpha: wp.array, *, vertex_uvs: wp.array | None = None,
                    texture: wp.array | None = None, vertex_colors: wp.array | None = None,
                    constant_color: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
    """Launch :data:`shade_mesh_hits_kernel`: textured when ``vertex_uvs`` and ``texture`` are given, else
    vertex-coloured when ``vertex_colors`` is, else ``constant_color``.

    Args:
        face_index, barycentrics: ``int32[H, W]`` and ``vec2[H, W]``, what :func:`cast_camera_rays` wrote.
        faces: ``int32[F, 3]`` vertex indices of the faces.
        background: ``vec3[1]`` RGB where nothing is hit.
        image: ``vec3[H, W]`` output RGB.
        alpha: ``float32[H, W]`` output, 1 where a face is hit, else 0.
        vertex_uvs: ``vec2[V]`` glTF texture coordinates (u right, v down from the top row).
        texture: ``vec3[S_h, S_w]`` RGB, row 0 at the top.
        vertex_colors: ``vec3[V]`` RGB.
        constant_color: RGB of every hit pixel without uvs or vertex colours.
    """
    height, width = face_index.shape
    for name, array in (("barycentrics", barycentrics), ("image", image), ("alpha", alpha)):
        if tuple(array.shape) != (height, width):
            raise ValueError(f"{name} has shape {tuple(array.shape)}, face_index {(height, width)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be [F, 3], got {tuple(faces.shape)}")
    if (vertex_uvs is None) != (texture is None):
        raise ValueError("texture shading needs both vertex_uvs and texture")
    if texture is not None:
        if texture.shape[0] == 0 or texture.shape[1] == 0:
            raise ValueError(f"texture must hold at least one texel, got shape {tuple(texture.shape)}")
        mode = SHADE_TEXTURE
    elif vertex_colors is not None:
        mode = SHADE_VERTEX_COLORS
    else:
        mode = SHADE_CONSTANT
    launch(shade_mesh_hits_kernel, dim=(height, width),
           inputs=[face_index, barycentrics, faces, mode, vertex_uvs, texture, vertex_colors,
                   wp.vec3(*constant_color), background],
           outputs=[image, alpha], device=face_index.device)
