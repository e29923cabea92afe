"""Autograd bridge of the triangle-binding kernels (:mod:`warpavatar.kernels.triangle_binding`).

Two ops: :func:`pose_triangle_gaussians`, Gaussians bound to a triangle mesh posed from its vertices (one launch
forward, Warp's adjoint of it backward, no host synchronization), and :func:`closest_triangles`, each point's
closest point on a mesh (no gradients), which binds existing Gaussians to a mesh. The plain-torch references with
the same signatures are in :mod:`warpavatar._torch_impl.triangle_binding`.
"""

from __future__ import annotations

import torch
import warp as wp
from torch.autograd.function import once_differentiable

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import triangle_binding as kernels

__all__ = ["pose_triangle_gaussians", "closest_triangles", "check_binding_inputs", "triangle_frames"]


def triangle_frames(corners: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Frames ``R = [e | n | e x n]`` ``[..., 3, 3]`` (columns), unit normals ``[..., 3]`` and areas ``[...]`` of
    triangles given by their corners ``[..., 3, 3]`` (corner, xyz), in their dtype: the kernel's
    frame in torch (binding, density control and the reference use it)."""
    a, b, c = corners.unbind(-2)
    edge = b - a
    cross = torch.linalg.cross(edge, c - a, dim=-1)
    length = cross.norm(dim=-1, keepdim=True)
    normal = cross / length
    along = edge / edge.norm(dim=-1, keepdim=True)
    across = torch.linalg.cross(along, normal, dim=-1)
    return torch.stack([along, normal, across], dim=-1), normal, 0.5 * length[..., 0]


def _index_tensor(name: str, value, shape: tuple, device: torch.device, bound: int, bound_name: str) -> torch.Tensor:
    tensor = torch.as_tensor(value)
    check_tensor(name, tensor, shape, dtype_kind="int")
    if tensor.device.type == "cpu" and tensor.numel() and (int(tensor.min()) < 0 or int(tensor.max()) >= bound):
        raise ValueError(f"{name} must hold ids in [0, {bound}) ({bound_name}), got {int(tensor.min())}.."
                         f"{int(tensor.max())}")
    return tensor.to(device=device, dtype=torch.int32).contiguous()


def check_binding_inputs(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                         local_log_scales):
    """The inputs of :func:`pose_triangle_gaussians` checked (shapes, devices, integer ids; ids given on the host
    are range-checked there) and the ids converted to int32 on the vertices' device; shared with the reference."""
    check_tensor("vertices", vertices, (None, 3))
    device = vertices.device
    faces = _index_tensor("faces", faces, (None, 3), device, vertices.shape[0], "vertices")
    face_count = faces.shape[0]
    check_tensor("rest_area", rest_area, (face_count,), device=device)
    triangle_ids = _index_tensor("triangle_ids", triangle_ids, (None,), device, face_count, "triangles")
    count = triangle_ids.shape[0]
    check_tensor("barycentrics", barycentrics, (count, 3), device=device)
    check_tensor("offsets", offsets, (count,), device=device)
    check_tensor("local_quats", local_quats, (count, 4), device=device)
    check_tensor("local_log_scales", local_log_scales, (count, 3), device=device)
    return faces, triangle_ids


class _PoseTriangleGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, vertices, barycentrics, offsets, local_quats, local_log_scales, faces, rest_area,
                triangle_ids):
        count = triangle_ids.shape[0]
        device = vertices.device
        means = torch.empty(count, 3, dtype=torch.float32, device=device)
        quats = torch.empty(count, 4, dtype=torch.float32, device=device)
        log_scales = torch.empty(count, 3, dtype=torch.float32, device=device)
        if count and faces.shape[0]:
            with torch_stream_scope(device):
                kernels.launch_pose_triangle_gaussians(*_input_arrays(vertices, faces, rest_area, triangle_ids,
                                                                      barycentrics, offsets, local_quats,
                                                                      local_log_scales),
                                                       to_warp(means, wp.vec3), to_warp(quats, wp.vec4),
                                                       to_warp(log_scales, wp.vec3))
        ctx.save_for_backward(vertices, barycentrics, offsets, local_quats, local_log_scales, faces, rest_area,
                              triangle_ids)
        return means, quats, log_scales

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_means, grad_quats, grad_log_scales):
        vertices, barycentrics, offsets, local_quats, local_log_scales, faces, rest_area, triangle_ids = \
            ctx.saved_tensors
        grads = [torch.zeros_like(t) for t in (vertices, barycentrics, offsets, local_quats, local_log_scales)]
        count = triangle_ids.shape[0]
        if count and faces.shape[0]:
            scratch = [torch.empty(count, width, dtype=torch.float32, device=vertices.device) for width in (3, 4, 3)]
            cotangents = [torch.zeros_like(s) if g is None else g.to(torch.float32).contiguous()
                          for g, s in zip((grad_means, grad_quats, grad_log_scales), scratch)]
            with torch_stream_scope(vertices.device):
                kernels.launch_pose_triangle_gaussians_adjoint(
                    *_input_arrays(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats,
                                   local_log_scales),
                    to_warp(scratch[0], wp.vec3), to_warp(scratch[1], wp.vec4), to_warp(scratch[2], wp.vec3),
                    to_warp(cotangents[0], wp.vec3), to_warp(cotangents[1], wp.vec4), to_warp(cotangents[2], wp.vec3),
                    to_warp(grads[0], wp.vec3), to_warp(grads[1], wp.vec3), to_warp(grads[2]),
                    to_warp(grads[3], wp.vec4), to_warp(grads[4], wp.vec3))
        needs = ctx.needs_input_grad
        return (*(grad if need else None for grad, need in zip(grads, needs[:5])), None, None, None)


def _input_arrays(vertices, faces, rest_area, triangle_ids, barycentrics, offsets, local_quats, local_log_scales):
    return (to_warp(vertices, wp.vec3), to_warp(faces), to_warp(rest_area), to_warp(triangle_ids),
            to_warp(barycentrics, wp.vec3), to_warp(offsets), to_warp(local_quats, wp.vec4),
            to_warp(local_log_scales, wp.vec3))


def pose_triangle_gaussians(vertices: torch.Tensor, faces, rest_area: torch.Tensor, triangle_ids,
                            barycentrics: torch.Tensor, offsets: torch.Tensor, local_quats: torch.Tensor,
                            local_log_scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pose Gaussians bound to the triangles of a mesh from its vertex positions.

    Gaussian ``i`` on triangle ``f = triangle_ids[i]`` with corners ``a, b, c``: centre ``u a + v b + w c + d n``;
    rotation ``q(R) q_local`` with ``R = [e | n | e x n]`` (unit edge ``b - a``, unit normal, their cross product);
    log-scales ``s_local + 0.5 log(A / A_rest)`` (``kernels/triangle_binding.py`` gives the details). One kernel
    launch forward, its Warp adjoint backward; no host synchronization.

    Args:
        vertices: float32 ``[V, 3]`` posed vertex positions [world units]; differentiable.
        faces: integer ``[F, 3]`` vertex ids of each triangle.
        rest_area: float32 ``[F]`` each triangle's rest area [world units^2] (the scale factor's reference).
        triangle_ids: integer ``[N]`` each Gaussian's triangle.
        barycentrics: float32 ``[N, 3]`` weights of the triangle's corners (used as given); differentiable.
        offsets: float32 ``[N]`` distance along the unit normal [world units]; differentiable.
        local_quats: float32 ``[N, 4]`` (w, x, y, z) rotations in the triangle's frame; differentiable.
        local_log_scales: float32 ``[N, 3]`` log-scales in the triangle's frame at rest; differentiable.

    Returns:
        ``(means [N, 3], quats [N, 4], log_scales [N, 3])`` float32 on the vertices' device: world centres
        [world units], world (w, x, y, z) rotations (the norm of ``local_quats``), world log-scales. A Gaussian
        whose triangle id or corner ids are out of range (possible only for ids on CUDA, which are not checked on
        the host) gets NaN.

    Raises:
        TypeError: a float input is not float32, or ids are not integers.
        ValueError: inconsistent shapes or devices, ids given on the host out of range.
    """
    faces, triangle_ids = check_binding_inputs(vertices, faces, rest_area, triangle_ids, barycentrics, offsets,
                                               local_quats, local_log_scales)
    for name, tensor in (("vertices", vertices), ("rest_area", rest_area), ("barycentrics", barycentrics),
                         ("offsets", offsets), ("local_quats", local_quats),
                         ("local_log_scales", local_log_scales)):
        check_tensor(name, tensor, tuple(tensor.shape), dtype_kind="float32")
    return _PoseTriangleGaussians.apply(vertices.contiguous(), barycentrics.contiguous(), offsets.contiguous(),
                                        local_quats.contiguous(), local_log_scales.contiguous(), faces,
                                        rest_area.contiguous(), triangle_ids)


def closest_triangles(points: torch.Tensor, vertices: torch.Tensor, faces, *, max_distance: float = 1.0e6
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each point's closest point on a triangle mesh: its triangle and barycentric coordinates (no gradients).

    One BVH build over the mesh (Warp's :class:`warp.Mesh`) and one query launch. Where two triangles are equally
    close (a point closest to a shared edge or vertex) either may be returned.

    Args:
        points: float ``[N, 3]`` query points [world units].
        vertices: float ``[V, 3]`` the mesh's vertex positions [world units], on the points' device.
        faces: integer ``[F, 3]`` vertex ids of each triangle (at least one).
        max_distance: farthest distance searched [world units]; a point farther from every triangle gets -1.

    Returns:
        ``(triangle_ids int64 [N], barycentrics float32 [N, 3])``: the closest point is ``sum_k
        barycentrics[i, k] vertices[faces[triangle_ids[i], k]]`` (weights in [0, 1], summing to 1).

    Raises:
        ValueError: bad shapes, devices, no faces, ids given on the host out of range, a non-positive distance.
    """
    check_tensor("points", points, (None, 3))
    device = points.device
    check_tensor("vertices", vertices, (None, 3), device=device)
    faces = _index_tensor("faces", faces, (None, 3), device, vertices.shape[0], "vertices")
    if faces.shape[0] == 0:
        raise ValueError("closest_triangles needs a mesh with at least one face")
    if not max_distance > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    count = points.shape[0]
    triangle_ids = torch.full((count,), -1, dtype=torch.int32, device=device)
    barycentrics = torch.zeros(count, 3, dtype=torch.float32, device=device)
    if count:
        query_points = points.detach().to(torch.float32).contiguous()
        mesh_points = vertices.detach().to(torch.float32).contiguous()
        with torch_stream_scope(device):
            mesh = wp.Mesh(points=to_warp(mesh_points, wp.vec3), indices=to_warp(faces.reshape(-1)))
            kernels.launch_closest_triangles(mesh, to_warp(query_points, wp.vec3), to_warp(triangle_ids),
                                             to_warp(barycentrics, wp.vec3), max_distance=float(max_distance))
            del mesh  # freed on the stream the query was queued on
    return triangle_ids.long(), barycentrics
