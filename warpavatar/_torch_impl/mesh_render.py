"""Plain-torch reference of the mesh renderer (:mod:`warpavatar._src.mesh_render`), same signature.

Brute force, in float64: every pixel's camera ray is intersected with every triangle (Moller-Trumbore, either
side of a face), the closest hit in front of the camera is kept, and the texture is sampled with
``torch.nn.functional.grid_sample`` (bilinear, ``align_corners=False``, border padding: texel centres at
``(c + 0.5) / S``, clamped to the edge). Memory grows as pixels x triangles (processed in chunks of pixels), so
it is for small meshes and images.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["render_mesh"]

_PAIRS_PER_CHUNK = 1 << 21
"""Pixel-triangle pairs intersected at once."""


def _colors(value, device: torch.device) -> torch.Tensor:
    tensor = torch.as_tensor(value)
    scale = 1.0 / 255.0 if tensor.dtype == torch.uint8 else 1.0
    return tensor.to(device=device, dtype=torch.float64) * scale


def _closest_hits(origin: torch.Tensor, directions: torch.Tensor, triangles: torch.Tensor):
    """(face [P] int64, -1 for none; b1, b2 [P]; t [P]) of rays ``origin + t directions`` [P,3] on ``triangles``
    [F,3,3], the closest hit with t > 0."""
    p0, p1, p2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    edge1, edge2 = p1 - p0, p2 - p0
    faces, weights1, weights2, depths = [], [], [], []
    chunk = max(1, _PAIRS_PER_CHUNK // max(1, triangles.shape[0]))
    for start in range(0, directions.shape[0], chunk):
        d = directions[start:start + chunk, None, :]  # [P,1,3]
        h = torch.cross(d.expand(-1, edge2.shape[0], -1), edge2[None].expand(d.shape[0], -1, -1), dim=-1)
        a = (edge1[None] * h).sum(-1)  # [P,F]
        parallel = a.abs() < 1e-14
        inverse = 1.0 / torch.where(parallel, torch.ones_like(a), a)
        s = origin - p0  # [F,3]
        u = inverse * (s[None] * h).sum(-1)
        q = torch.cross(s, edge1, dim=-1)  # [F,3]
        v = inverse * (d * q[None]).sum(-1)
        t = inverse * (edge2 * q).sum(-1)[None]
        hit = ~parallel & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = torch.where(hit, t, torch.full_like(t, torch.inf))
        best, face = t.min(dim=1)
        found = torch.isfinite(best)
        rows = torch.arange(face.shape[0], device=face.device)
        faces.append(torch.where(found, face, torch.full_like(face, -1)))
        weights1.append(torch.where(found, u[rows, face], torch.zeros_like(best)))
        weights2.append(torch.where(found, v[rows, face], torch.zeros_like(best)))
        depths.append(torch.where(found, best, torch.zeros_like(best)))
    return torch.cat(faces), torch.cat(weights1), torch.cat(weights2), torch.cat(depths)


def render_mesh(vertices: torch.Tensor, faces, K, world_to_camera, width: int, height: int, *, uvs=None,
                texture=None, vertex_colors=None, background=None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference of :func:`warpavatar.ops.render_mesh`: ``(image [H,W,3], alpha [H,W], depth [H,W])`` float32
    of a triangle mesh ray cast through an OpenCV pinhole camera (pixel centres at integer coordinates)."""
    device = vertices.device
    points = vertices.detach().to(torch.float64)
    faces = torch.as_tensor(faces, device=device).long()
    K = torch.as_tensor(K).to(device=device, dtype=torch.float64)
    world_to_camera = torch.as_tensor(world_to_camera).to(device=device, dtype=torch.float64)
    background = (torch.zeros(3, dtype=torch.float64, device=device) if background is None
                  else torch.as_tensor(background).to(device=device, dtype=torch.float64))
    rows, columns = torch.meshgrid(torch.arange(height, dtype=torch.float64, device=device),
                                   torch.arange(width, dtype=torch.float64, device=device), indexing="ij")
    camera_directions = torch.stack([(columns - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1],
                                     torch.ones_like(rows)], dim=-1).reshape(-1, 3)
    rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    origin = -rotation.T @ translation
    directions = camera_directions @ rotation  # rows of R^T d
    pixel_count = height * width
    if faces.shape[0] == 0:
        face = torch.full((pixel_count,), -1, dtype=torch.long, device=device)
        b1 = b2 = depth = torch.zeros(pixel_count, dtype=torch.float64, device=device)
    else:
        face, b1, b2, depth = _closest_hits(origin, directions, points[faces])
    found = face >= 0
    corners = faces[face.clamp_min(0)]  # [P,3]
    weights = torch.stack([1.0 - b1 - b2, b1, b2], dim=-1)[..., None]  # [P,3,1]
    if uvs is not None:
        uv = (torch.as_tensor(uvs).to(device=device, dtype=torch.float64)[corners] * weights).sum(1)  # [P,2]
        texels = _colors(texture, device).permute(2, 0, 1)[None]  # [1,3,S_h,S_w]
        grid = (uv * 2.0 - 1.0).reshape(1, 1, -1, 2)
        color = F.grid_sample(texels, grid, mode="bilinear", padding_mode="border", align_corners=False)
        color = color[0, :, 0].T  # [P,3]
    elif vertex_colors is not None:
        color = (_colors(vertex_colors, device)[corners] * weights).sum(1)
    else:
        color = torch.ones(pixel_count, 3, dtype=torch.float64, device=device)
    image = torch.where(found[:, None], color, background)
    return (image.reshape(height, width, 3).float(), found.reshape(height, width).float(),
            depth.reshape(height, width).float())
