"""Plain-torch reference of :func:`warpavatar.ops.push_out_of_capsules` (dtype-generic: float64 for finite
differences), with the conventions of :mod:`warpavatar.kernels.collision`."""

from __future__ import annotations

import torch

__all__ = ["push_out_of_capsules"]

_AXIS_EPSILON = 1e-9
_SEGMENT_EPSILON_SQ = 1e-12


def _fallback_normal(d: torch.Tensor) -> torch.Tensor:
    """Unit perpendicular [C,3] of each segment direction (+z for degenerate ones), without gradient."""
    d = d.detach()
    magnitude = d.abs()
    ax, ay, az = magnitude.unbind(-1)
    axis = torch.zeros_like(d)
    pick_y = (ay <= ax) & (ay <= az)
    pick_z = ~pick_y & (az < ax) & (az < ay)
    axis[:, 0] = (~pick_y & ~pick_z).to(d.dtype)
    axis[:, 1] = pick_y.to(d.dtype)
    axis[:, 2] = pick_z.to(d.dtype)
    perpendicular = torch.cross(d, axis, dim=-1)
    perpendicular = perpendicular / perpendicular.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    up = torch.zeros_like(d)
    up[:, 2] = 1.0
    degenerate = (d * d).sum(-1, keepdim=True) <= _SEGMENT_EPSILON_SQ
    return torch.where(degenerate, up, perpendicular)


def push_out_of_capsules(x, segment_start, segment_end, radius) -> torch.Tensor:
    """``x [N,3]`` plus the sum over capsules holding it of ``p + radius n - x`` (see the Warp op)."""
    d = segment_end - segment_start  # [C, 3]
    length_sq = (d * d).sum(-1)  # [C]
    degenerate = length_sq <= _SEGMENT_EPSILON_SQ
    w = x[:, None, :] - segment_start[None]  # [N, C, 3]
    s = (w * d[None]).sum(-1) / torch.where(degenerate, torch.ones_like(length_sq), length_sq)[None]
    t = torch.where(degenerate[None], torch.zeros_like(s), s.clamp(0.0, 1.0))
    closest = segment_start[None] + t[..., None] * d[None]
    r = x[:, None, :] - closest
    distance = r.norm(dim=-1)
    on_axis = distance <= _AXIS_EPSILON
    normal = torch.where(on_axis[..., None], _fallback_normal(d)[None].expand_as(r),
                         r / torch.where(on_axis, torch.ones_like(distance), distance)[..., None])
    push = closest + radius[None, :, None] * normal - x[:, None, :]
    inside = distance < radius[None]
    return x + torch.where(inside[..., None], push, torch.zeros_like(push)).sum(dim=1)
