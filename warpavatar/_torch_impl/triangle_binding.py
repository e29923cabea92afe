"""Plain-torch references of the triangle-binding ops (:mod:`warpavatar._src.triangle_binding`), same signatures.

They run in the inputs' dtype (float64 included) and are differentiated by autograd. The frame's quaternion comes
from :func:`warpavatar.geometry.quat_from_matrix` (``w >= 0``, as the kernel's); the closest triangle is found by
brute force over every triangle (Ericson's closest point on a triangle, in chunks of points).
"""

from __future__ import annotations

import torch

from warpavatar._src.triangle_binding import check_binding_inputs, triangle_frames
from warpavatar._src.warp_utils import check_tensor
from warpavatar.geometry import quat_from_matrix, quat_multiply

__all__ = ["pose_triangle_gaussians", "closest_triangles"]

AREA_FLOOR = 1.0e-20


def pose_triangle_gaussians(vertices: torch.Tensor, faces, rest_area: torch.Tensor, triangle_ids,
                            barycentrics: torch.Tensor, offsets: torch.Tensor, local_quats: torch.Tensor,
                            local_log_scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of :func:`warpavatar.ops.pose_triangle_gaussians` (out-of-range ids raise instead of giving
    NaN)."""
    faces, triangle_ids = check_binding_inputs(vertices, faces, rest_area, triangle_ids, barycentrics, offsets,
                                               local_quats, local_log_scales)
    triangle_ids = triangle_ids.long()
    corners = vertices[faces.long()[triangle_ids]]  # [N, 3 corners, 3]
    frame, normal, area = triangle_frames(corners)
    means = (barycentrics[:, :, None] * corners).sum(1) + offsets[:, None] * normal
    quats = quat_multiply(quat_from_matrix(frame), local_quats)
    floor = torch.as_tensor(AREA_FLOOR, dtype=area.dtype, device=area.device)
    log_factor = 0.5 * (torch.maximum(area, floor).log() - torch.maximum(rest_area[triangle_ids], floor).log())
    return means, quats, local_log_scales + log_factor[:, None]


def _closest_on_triangles(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Barycentric weights ``[P, F, 3]`` of the closest point of each triangle ``(a, b, c)`` ``[F, 3]`` to each
    point ``[P, 3]`` (Ericson, "Real-Time Collision Detection", 5.1.5), in the points' dtype."""
    p = points[:, None]
    ab, ac = (b - a)[None], (c - a)[None]
    ap, bp, cp = p - a[None], p - b[None], p - c[None]
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = torch.finfo(points.dtype).tiny
    # interior (the default), then the edges' and corners' regions, the later cases taking precedence
    total = (va + vb + vc)
    total = torch.where(total.abs() > tiny, total, torch.full_like(total, tiny))
    weights = torch.stack([va / total, vb / total, vc / total], dim=-1)

    def put(region, u, v, w):
        nonlocal weights
        weights = torch.where(region[..., None], torch.stack([u, v, w], dim=-1), weights)

    def ratio(n, d):
        return n / torch.where(d.abs() > tiny, d, torch.full_like(d, tiny))

    zero, one = torch.zeros_like(d1), torch.ones_like(d1)
    t_bc = ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    put((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), zero, 1 - t_bc, t_bc)
    t_ac = ratio(d2, d2 - d6)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t_ac, zero, t_ac)
    t_ab = ratio(d1, d1 - d3)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t_ab, t_ab, zero)
    put((d6 >= 0) & (d5 <= d6), zero, zero, one)
    put((d3 >= 0) & (d4 <= d3), zero, one, zero)
    put((d1 <= 0) & (d2 <= 0), one, zero, zero)
    return weights


_CHUNK = 256  # points a brute-force block compares with every triangle


def closest_triangles(points: torch.Tensor, vertices: torch.Tensor, faces, *, max_distance: float = 1.0e6
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Reference of :func:`warpavatar.ops.closest_triangles` (brute force, a block of points at a time)."""
    check_tensor("points", points, (None, 3))
    check_tensor("vertices", vertices, (None, 3), device=points.device)
    faces = torch.as_tensor(faces, device=points.device).long()
    check_tensor("faces", faces, (None, 3), dtype_kind="int")
    if faces.shape[0] == 0:
        raise ValueError("closest_triangles needs a mesh with at least one face")
    a, b, c = (vertices[faces[:, k]].to(points.dtype) for k in range(3))
    ids, weights = [], []
    for start in range(0, points.shape[0], _CHUNK):
        block = points[start:start + _CHUNK]
        bary = _closest_on_triangles(block, a, b, c)  # [P, F, 3]
        closest = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
        distance = (closest - block[:, None]).norm(dim=-1)
        best = distance.argmin(dim=1)
        found = distance.gather(1, best[:, None])[:, 0] <= max_distance
        ids.append(torch.where(found, best, torch.full_like(best, -1)))
        chosen = bary[torch.arange(block.shape[0], device=points.device), best]
        weights.append(torch.where(found[:, None], chosen, torch.zeros_like(chosen)))
    if not ids:
        return (torch.zeros(0, dtype=torch.int64, device=points.device),
                torch.zeros(0, 3, dtype=points.dtype, device=points.device))
    return torch.cat(ids), torch.cat(weights)
