"""Triangle-bound Gaussians: Gaussians that live on a triangle mesh's surface, posed from its vertices.

A Gaussian bound to triangle ``f = (a, b, c)`` (vertex positions) holds barycentric coordinates ``(u, v, w)``, an
offset ``d`` along the triangle's normal [world units], a rotation ``q_local`` (w, x, y, z) in the triangle's
frame and log-scales ``s_local`` [log world units], as in "GaussianAvatars: Photorealistic Head Avatars with Rigged
3D Gaussians" and "SplattingAvatar: Realistic Real-Time Human Avatars with Mesh-Embedded Gaussian Splatting". Posed:

* centre ``x = u a + v b + w c + d n``, the barycentric coordinates used as given (the model keeps them on the
  simplex);
* frame ``R = [e | n | e x n]`` (columns): ``e`` the unit edge ``b - a``, ``n`` the unit normal of
  ``(b - a) x (c - a)`` and ``e x n`` the in-plane axis that makes ``R`` a proper rotation (``n x e`` would give a
  reflection); a Gaussian flat on the surface has its thin axis along local y;
* rotation ``q = q(R) q_local``, ``q(R)`` the unit quaternion of ``R`` with ``w >= 0``; ``q_local`` keeps its norm
  (quaternions are normalized where they are used);
* log-scales ``s = s_local + log(k)`` with ``k = sqrt(A / A_rest)``, ``A`` the posed triangle's area and ``A_rest``
  its rest area (the area is floored at 1e-20): a triangle stretched uniformly by ``k`` stretches its Gaussians by
  ``k`` in every direction, a rigid motion leaves them as they are. The offset ``d`` is not scaled.

A degenerate triangle (coincident vertices, zero area) has no frame; the posed values are then undefined. A
triangle id outside ``[0, F)``, or a triangle with a vertex id outside ``[0, V)``, gives NaN outputs (and no
gradient from them): a bad binding shows at once, without a host check on every call.

``pose_triangle_gaussians`` is straight-line code (a thread per Gaussian, no loop), so its backward is Warp's
adjoint of it (``adjoint=True`` launch): gradients of the vertex positions (atomically accumulated over the
Gaussians of each vertex's triangles), the barycentric coordinates, the offsets, the local rotations and the
local log-scales. ``closest_triangles`` (no gradients) finds each point's closest point on a mesh through Warp's
BVH query, for binding existing Gaussians to a mesh. Everything is float32. Launchers take ``warp.array`` objects
and check their sizes; the torch bridge is :mod:`warpavatar._src.triangle_binding`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch
from .quaternion import quat_from_rotation_matrix, quat_multiply

__all__ = ["AREA_FLOOR", "triangle_frame", "launch_pose_triangle_gaussians",
           "launch_pose_triangle_gaussians_adjoint", "launch_closest_triangles"]

AREA_FLOOR = wp.constant(1.0e-20)
"""Smallest triangle area [world units^2] the scale factor's logarithm sees."""


@wp.func
def triangle_frame(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The frame ``R = [e | n | e x n]`` (columns) of triangle ``(a, b, c)``, its unit normal and its area."""
    edge = b - a
    cross = wp.cross(edge, c - a)
    normal = wp.normalize(cross)
    along = wp.normalize(edge)
    across = wp.cross(along, normal)
    frame = wp.mat33(along[0], normal[0], across[0],
                     along[1], normal[1], across[1],
                     along[2], normal[2], across[2])
    return frame, normal, 0.5 * wp.length(cross)


@wp.kernel
def pose_triangle_gaussians(vertices: wp.array(dtype=wp.vec3), faces: wp.array2d(dtype=wp.int32),
                            rest_area: wp.array(dtype=float), triangle_ids: wp.array(dtype=wp.int32),
                            barycentrics: wp.array(dtype=wp.vec3), offsets: wp.array(dtype=float),
                            local_quats: wp.array(dtype=wp.vec4), local_log_scales: wp.array(dtype=wp.vec3),
                            means: wp.array(dtype=wp.vec3), quats: wp.array(dtype=wp.vec4),
                            log_scales: wp.array(dtype=wp.vec3)):
    """Posed centre, rotation and log-scales of each Gaussian (module docstring); differentiated by Warp."""
    i = wp.tid()
    # ids out of range read a valid triangle and write NaN, so a bad binding shows instead of reading stray memory
    face_count = faces.shape[0]
    vertex_count = vertices.shape[0]
    f = wp.clamp(triangle_ids[i], 0, face_count - 1)
    ia = wp.clamp(faces[f, 0], 0, vertex_count - 1)
    ib = wp.clamp(faces[f, 1], 0, vertex_count - 1)
    ic = wp.clamp(faces[f, 2], 0, vertex_count - 1)
    valid = (triangle_ids[i] == f and faces[f, 0] == ia and faces[f, 1] == ib and faces[f, 2] == ic)
    a = vertices[ia]
    b = vertices[ib]
    c = vertices[ic]
    frame, normal, area = triangle_frame(a, b, c)
    weights = barycentrics[i]
    nan3 = wp.vec3(wp.nan, wp.nan, wp.nan)
    means[i] = wp.where(valid, weights[0] * a + weights[1] * b + weights[2] * c + offsets[i] * normal, nan3)
    frame_quat = quat_from_rotation_matrix(frame)
    frame_quat = frame_quat * wp.where(frame_quat[0] < 0.0, -1.0, 1.0)
    quats[i] = wp.where(valid, quat_multiply(frame_quat, local_quats[i]), wp.vec4(wp.nan, wp.nan, wp.nan, wp.nan))
    log_factor = 0.5 * (wp.log(wp.max(area, AREA_FLOOR)) - wp.log(wp.max(rest_area[f], AREA_FLOOR)))
    log_scales[i] = wp.where(valid, local_log_scales[i] + wp.vec3(log_factor, log_factor, log_factor), nan3)


@wp.kernel(enable_backward=False)
def closest_triangles(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_distance: float,
                      triangle_ids: wp.array(dtype=wp.int32), barycentrics: wp.array(dtype=wp.vec3)):
    """Each point's closest triangle and the barycentric coordinates of its closest point there (-1 and zeros
    when no triangle lies within ``max_distance``)."""
    i = wp.tid()
    query = wp.mesh_query_point_no_sign(mesh, points[i], max_distance)
    if query.result:
        triangle_ids[i] = query.face
        # Warp's (u, v) weigh the triangle's first and second vertex: p = u a + v b + (1 - u - v) c
        barycentrics[i] = wp.vec3(query.u, query.v, 1.0 - query.u - query.v)
    else:
        triangle_ids[i] = -1
        barycentrics[i] = wp.vec3(0.0, 0.0, 0.0)


# -------------------------------------------------------------------------------------------------- launchers
def _check_rows(expected: tuple[int, ...], **arrays) -> None:
    for name, array in arrays.items():
        if tuple(array.shape[: len(expected)]) != expected:
            raise ValueError(f"{name} has shape {tuple(array.shape)}, expected {expected} leading")


def _check_pose_arrays(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                       local_log_scales, **outputs) -> int:
    count = triangle_ids.shape[0]
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces has shape {tuple(faces.shape)}, expected (F, 3)")
    _check_rows((faces.shape[0],), rest_area=rest_area)
    _check_rows((count,), barycentrics=barycentrics, offsets=offsets, local_quats=local_quats,
                local_log_scales=local_log_scales, **outputs)
    return count


def launch_pose_triangle_gaussians(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                                   local_log_scales, means, quats, log_scales) -> None:
    """Write the posed ``means`` vec3 [N], ``quats`` vec4 [N] and ``log_scales`` vec3 [N].

    Args:
        vertices: vec3 [V] posed vertex positions [world units]; faces: int32 [F, 3] vertex ids; rest_area:
            float32 [F] rest areas [world units^2]; triangle_ids: int32 [N] each Gaussian's triangle, in
            ``[0, F)``; barycentrics: vec3 [N]; offsets: float32 [N] along the normal [world units];
            local_quats: vec4 [N] (w, x, y, z) in the triangle's frame; local_log_scales: vec3 [N].
    """
    count = _check_pose_arrays(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                               local_log_scales, means=means, quats=quats, log_scales=log_scales)
    launch(pose_triangle_gaussians, dim=count,
           inputs=[vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats, local_log_scales],
           outputs=[means, quats, log_scales], device=vertices.device)


def launch_pose_triangle_gaussians_adjoint(vertices, faces, rest_area, triangle_ids, barycentrics, offsets,
                                           local_quats, local_log_scales, scratch_means, scratch_quats,
                                           scratch_log_scales, adj_means, adj_quats, adj_log_scales, adj_vertices,
                                           adj_barycentrics, adj_offsets, adj_local_quats,
                                           adj_local_log_scales) -> None:
    """Adjoint launch of :data:`pose_triangle_gaussians`: adds to ``adj_vertices`` [V], ``adj_barycentrics``,
    ``adj_offsets``, ``adj_local_quats`` and ``adj_local_log_scales`` [N] (zero on entry) the gradients from the
    outputs' adjoints [N]; the three ``scratch_*`` [N] arrays are written, never read."""
    count = _check_pose_arrays(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                               local_log_scales, scratch_means=scratch_means, scratch_quats=scratch_quats,
                               scratch_log_scales=scratch_log_scales, adj_means=adj_means, adj_quats=adj_quats,
                               adj_log_scales=adj_log_scales, adj_barycentrics=adj_barycentrics,
                               adj_offsets=adj_offsets, adj_local_quats=adj_local_quats,
                               adj_local_log_scales=adj_local_log_scales)
    _check_rows((vertices.shape[0],), adj_vertices=adj_vertices)
    launch(pose_triangle_gaussians, dim=count,
           inputs=[vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats, local_log_scales],
           outputs=[scratch_means, scratch_quats, scratch_log_scales],
           adj_inputs=[adj_vertices, None, None, None, adj_barycentrics, adj_offsets, adj_local_quats,
                       adj_local_log_scales],
           adj_outputs=[adj_means, adj_quats, adj_log_scales], adjoint=True, device=vertices.device)


def launch_closest_triangles(mesh: wp.Mesh, points, triangle_ids, barycentrics, *, max_distance: float) -> None:
    """Write each point's closest triangle ``triangle_ids`` int32 [N] (-1 beyond ``max_distance``) and the
    barycentric coordinates ``barycentrics`` vec3 [N] of its closest point on it.

    Args:
        mesh: a ``wp.Mesh`` over the triangles (its BVH answers the queries).
        points: vec3 [N] query points [world units].
        max_distance: farthest distance searched [world units].
    """
    count = points.shape[0]
    _check_rows((count,), triangle_ids=triangle_ids, barycentrics=barycentrics)
    launch(closest_triangles, dim=count, inputs=[mesh.id, points, float(max_distance)],
           outputs=[triangle_ids, barycentrics], device=points.device)
