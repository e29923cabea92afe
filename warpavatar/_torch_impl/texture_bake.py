"""Plain-torch references of the texture-baking ops (:mod:`warpavatar._src.texture_bake`): triangles rasterized
into a UV atlas by brute force (every texel's distance to every triangle), and points coloured from the views that
see them (every point against every view at once)."""

from __future__ import annotations

import torch

__all__ = ["rasterize_uv_atlas", "average_view_colors", "nearest_points"]


def _edge_function(a, b, p):
    return (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])


def _closest_on_segment(a, b, p):
    ab = b - a
    length_sq = (ab * ab).sum(-1)
    s = torch.where(length_sq > 0, ((p - a) * ab).sum(-1) / length_sq.clamp_min(1e-30), torch.zeros_like(length_sq))
    s = s.clamp(0.0, 1.0)
    return (p - (a + s[..., None] * ab)).norm(dim=-1), s


def _closest_on_triangles(t0, t1, t2, area, p):
    """(distance [P,F], barycentric [P,F,3]) from points [P,1,2] to triangles [F,2] of doubled area [F]."""
    w = torch.stack([_edge_function(t1, t2, p), _edge_function(t2, t0, p), _edge_function(t0, t1, p)], -1)
    w = w / area[:, None]
    inside = (w >= 0).all(dim=-1)
    inside_barycentric = w / w.sum(-1, keepdim=True)
    d01, s01 = _closest_on_segment(t0, t1, p)
    d12, s12 = _closest_on_segment(t1, t2, p)
    d20, s20 = _closest_on_segment(t2, t0, p)
    zero = torch.zeros_like(s01)
    distance, barycentric = d01, torch.stack([1 - s01, s01, zero], -1)
    nearer = d12 < distance
    distance = torch.where(nearer, d12, distance)
    barycentric = torch.where(nearer[..., None], torch.stack([zero, 1 - s12, s12], -1), barycentric)
    nearer = d20 < distance
    distance = torch.where(nearer, d20, distance)
    barycentric = torch.where(nearer[..., None], torch.stack([s20, zero, 1 - s20], -1), barycentric)
    distance = torch.where(inside, torch.zeros_like(distance), distance)
    barycentric = torch.where(inside[..., None], inside_barycentric, barycentric)
    return distance, barycentric


def rasterize_uv_atlas(vertices, faces, normals, uvs, *, size, margin=0.0):
    """Reference of :func:`warpavatar.ops.rasterize_uv_atlas` (memory grows with texels times triangles)."""
    device = vertices.device
    texel_face = torch.full((size * size,), -1, dtype=torch.int32, device=device)
    texel_distance = torch.full((size * size,), float("inf"), device=device)
    texel_barycentric = torch.zeros(size * size, 3, device=device)
    texel_point = torch.zeros(size * size, 3, device=device)
    texel_normal = torch.zeros(size * size, 3, device=device)
    faces = faces.long()
    t = uvs * float(size)
    t0, t1, t2 = t[faces[:, 0]], t[faces[:, 1]], t[faces[:, 2]]
    area = _edge_function(t0, t1, t2)
    usable = (area != 0) & torch.isfinite(area)
    if bool(usable.any()):
        index = usable.nonzero()[:, 0]
        centre = torch.arange(size, device=device, dtype=torch.float32) + 0.5
        p = torch.stack(torch.meshgrid(centre, centre, indexing="xy"), dim=-1).reshape(-1, 1, 2)
        distance, barycentric = _closest_on_triangles(t0[index], t1[index], t2[index], area[index], p)
        steps = torch.round(distance.double() * 2.0**20).long()
        key = torch.where(distance <= margin, steps * 2**32 + index[None], torch.iinfo(torch.int64).max)
        best = key.min(dim=1)
        claimed = best.values != torch.iinfo(torch.int64).max
        column = best.indices[claimed]
        texel = claimed.nonzero()[:, 0]
        face = index[column]
        b = barycentric[texel, column]
        normal = (b[:, :, None] * normals[faces[face]]).sum(dim=1)
        length = normal.norm(dim=1, keepdim=True)
        texel_face[texel] = face.to(torch.int32)
        texel_distance[texel] = distance[texel, column]
        texel_barycentric[texel] = b
        texel_point[texel] = (b[:, :, None] * vertices[faces[face]]).sum(dim=1)
        texel_normal[texel] = torch.where(length > 0, normal / length.clamp_min(1e-30), normal)
    return (texel_face.reshape(size, size), texel_barycentric.reshape(size, size, 3),
            texel_point.reshape(size, size, 3), texel_normal.reshape(size, size, 3),
            texel_distance.reshape(size, size))


def average_view_colors(points, normals, world_to_camera, intrinsics, images, depths, *, depth_tolerance,
                        min_cosine=0.0, image_sizes=None):
    """Reference of :func:`warpavatar.ops.average_view_colors` (memory grows with points times views)."""
    device = points.device
    view_count, height, width = images.shape[:3]
    if image_sizes is None:
        image_sizes = torch.tensor([[width, height]], device=device).expand(view_count, 2)
    sizes = image_sizes.long()
    rotation, translation = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    centres = -(rotation.transpose(1, 2) @ translation[:, :, None])[..., 0]  # [C,3]
    to_camera = centres[None] - points[:, None]  # [N,C,3]
    distance = to_camera.norm(dim=2)
    cosine = (normals[:, None] * to_camera).sum(dim=2) / distance.clamp_min(1e-30)
    camera = torch.einsum("cij,nj->nci", rotation, points) + translation[None]  # [N,C,3]
    z = camera[..., 2]
    safe_z = torch.where(z > 0, z, torch.ones_like(z))
    x = intrinsics[None, :, 0, 0] * camera[..., 0] / safe_z + intrinsics[None, :, 0, 2]
    y = intrinsics[None, :, 1, 1] * camera[..., 1] / safe_z + intrinsics[None, :, 1, 2]
    w_view, h_view = sizes[None, :, 0], sizes[None, :, 1]
    inside = (x > -0.5) & (x < w_view - 0.5) & (y > -0.5) & (y < h_view - 0.5)
    sees = (distance > 0) & (cosine > min_cosine) & (z > 0) & inside
    view = torch.arange(view_count, device=device)[None].expand_as(z)
    column = torch.floor(x + 0.5).long().clamp(0, width - 1)
    row = torch.floor(y + 0.5).long().clamp(0, height - 1)
    sees &= images[view, row, column, 3] >= 0.5
    sees &= (z - depths[view, row, column]).abs() <= depth_tolerance
    x_floor, y_floor = torch.floor(x), torch.floor(y)
    fx, fy = (x - x_floor)[..., None], (y - y_floor)[..., None]
    c0 = torch.minimum(x_floor.long().clamp_min(0), w_view - 1).clamp(0, width - 1)
    c1 = torch.minimum((x_floor.long() + 1).clamp_min(0), w_view - 1).clamp(0, width - 1)
    r0 = torch.minimum(y_floor.long().clamp_min(0), h_view - 1).clamp(0, height - 1)
    r1 = torch.minimum((y_floor.long() + 1).clamp_min(0), h_view - 1).clamp(0, height - 1)
    top = images[view, r0, c0] + fx * (images[view, r0, c1] - images[view, r0, c0])
    bottom = images[view, r1, c0] + fx * (images[view, r1, c1] - images[view, r1, c0])
    rgba = top + fy * (bottom - top)
    colour = (rgba[..., :3] / rgba[..., 3:].clamp_min(1e-6)).clamp(0.0, 1.0)
    weight = torch.where(sees, cosine, torch.zeros_like(cosine))
    weights = weight.sum(dim=1)
    total = (weight[..., None] * torch.where(sees[..., None], colour, torch.zeros_like(colour))).sum(dim=1)
    colors = torch.where(weights[:, None] > 0, total / weights.clamp_min(1e-30)[:, None], torch.zeros_like(total))
    return colors, weights


def nearest_points(known, queries):
    """Reference of :func:`warpavatar.ops.nearest_points` (every query against every known point)."""
    distances = (queries[:, None] - known[None]).norm(dim=2)
    distance, nearest = distances.min(dim=1)
    return nearest, distance
